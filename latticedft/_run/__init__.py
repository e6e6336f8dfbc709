"""A case run: the stages the command line runs on a case, and the checks made before anything is written.

- ``_task``: read and check a case's fields (:func:`check_case`), learn its model (:func:`train_model`),
  serve one task (:func:`serve_task`) into a :class:`TaskOutcome`;
- ``_guards``: the checks made before anything is written (file-name limits, memory, the case's inputs);
- ``_charges``: the Noether charges of a task, checked against its lattice and measured along it;
- ``_meter``: a task's errors and invariant measured slice by slice as it is served with an output cadence.

Each stage logs INFO lines (to stderr via the command line) and DEBUG details (to ``results/run.log``).
"""

from __future__ import annotations

from ._guards import case_inputs as case_inputs
from ._guards import check_before_writing as check_before_writing
from ._task import CaseData as CaseData
from ._task import TaskData as TaskData
from ._task import TaskOutcome as TaskOutcome
from ._task import check_case as check_case
from ._task import serve_task as serve_task
from ._task import train_model as train_model

__all__ = [
    "CaseData",
    "TaskData",
    "TaskOutcome",
    "case_inputs",
    "check_before_writing",
    "check_case",
    "serve_task",
    "train_model",
]
