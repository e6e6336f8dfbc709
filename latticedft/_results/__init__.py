"""Results of a run: the staging folder, model files, task files, exports, summary.

Everything is first written into a temporary folder beside the destination
(``CASE/results.tmp-XXXXXXXXXX``) that replaces ``CASE/results/`` in one atomic
step only when the stage succeeded, so a failed, interrupted or killed run
never leaves a half-written ``results/`` and never loses the previous one.
:func:`staged_results` is the one place that stages and publishes; every
command uses it, inside :func:`hold_results`.

Guarantees (docs/guarantees.md):

- A run writes only its results folder ``DEST`` and staging folders beside it
  named ``DEST.tmp-<10 hex digits>`` (and, where the atomic swap is not
  available, ``DEST.tmp-old-<10 hex digits>`` for a moment).
- Publishing swaps the staging folder and ``DEST`` with one
  ``renameat2(RENAME_EXCHANGE)`` (Linux); elsewhere ``DEST`` is renamed aside
  and the staging folder renamed in its place. A crash at any point leaves
  the old results or the new ones at ``DEST`` (with the two-rename fallback:
  or the old ones parked beside it, which the next run puts back).
- One run per results folder's parent at a time: :func:`hold_results` takes a
  non-blocking ``flock`` on the parent folder itself (no lock file), and,
  once it holds it, removes the staging folders of killed runs and restores
  parked results (one warning line).
- SIGINT and SIGTERM during the publishing step are deferred until it is done.

Test hook: the environment variable ``LATTICEDFT_FAULT`` (read only here, for
the fault-injection tests; never set it otherwise) lists comma-separated
``ACTION:POINT`` items: ACTION is ``kill`` (SIGKILL), ``term`` (SIGTERM),
``int`` (SIGINT), ``stop`` (SIGSTOP), ``enospc`` or ``eacces`` (raise that
OSError), POINT one of :data:`FAULT_POINTS`; the item ``no-exchange`` forces
the two-rename fallback of the publishing step.
"""

from __future__ import annotations

from ._files import align_reference as align_reference
from ._files import config_attrs as config_attrs
from ._files import export_task as export_task
from ._files import json_safe as json_safe
from ._files import load_verified_model as load_verified_model
from ._files import read_summary as read_summary
from ._files import read_task as read_task
from ._files import read_task_series as read_task_series
from ._files import sha256 as sha256
from ._files import versions as versions
from ._files import write_field as write_field
from ._files import write_model as write_model
from ._files import write_summary as write_summary
from ._files import write_task as write_task
from ._safety import FAULT_ENV as FAULT_ENV
from ._safety import FAULT_POINTS as FAULT_POINTS
from ._safety import ResultsError as ResultsError
from ._staging import MARKER as MARKER
from ._staging import RUN_LOG as RUN_LOG
from ._staging import Staging as Staging
from ._staging import check_destination as check_destination
from ._staging import held_by_another as held_by_another
from ._staging import hold_results as hold_results
from ._staging import leftovers as leftovers
from ._staging import published as published
from ._staging import staged_results as staged_results

__all__ = [
    "FAULT_ENV",
    "FAULT_POINTS",
    "MARKER",
    "held_by_another",
    "RUN_LOG",
    "ResultsError",
    "Staging",
    "align_reference",
    "check_destination",
    "config_attrs",
    "export_task",
    "hold_results",
    "json_safe",
    "leftovers",
    "load_verified_model",
    "published",
    "read_summary",
    "read_task",
    "read_task_series",
    "sha256",
    "staged_results",
    "versions",
    "write_field",
    "write_model",
    "write_summary",
    "write_task",
]
