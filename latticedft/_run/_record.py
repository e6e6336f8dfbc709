"""What ``summary.json`` records of a served task: :class:`TaskRecord`, and when its accuracy is worth a warning.

A task can be complete (the solver converged on every slice) and still far from its reference: the record
holds its relative error (the largest error over the reference's largest magnitude, on the compared slices),
and :func:`accuracy_warning` words it when it exceeds :data:`RELATIVE_ERROR_LIMIT`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from .._serve._result import RUN_KEYS

__all__ = ["RELATIVE_ERROR_LIMIT", "SERVED_KEYS", "TaskRecord", "accuracy_warning"]

#: A complete task whose relative error exceeds this is warned about: off by more than half the reference's
#: largest magnitude, the served field no longer predicts it. The cases of the repository serve to at most
#: 0.17 of it (Kepler's most eccentric orbit); a field that drifted away (1.8, or 1e46) is far above.
RELATIVE_ERROR_LIMIT = 0.5

#: The keys of :meth:`latticedft.ServeResult.to_dict` a task record starts with, in their order.
SERVED_KEYS = (*RUN_KEYS, "extrapolation", "warnings")


@dataclass
class TaskRecord:
    """One task of ``summary.json`` (``tasks.<name>``): :meth:`to_dict` gives its keys in their documented order.

    The first fields are the served result's numbers (:meth:`latticedft.ServeResult.to_dict`, with the wall
    time of the whole task); then how the task was served, its errors against the reference and the
    baseline's, an ensemble's calibration, the invariant's drift, the charges, and the files written. A field
    left None is a key the task's summary does not hold (but ``reason``, ``stop_reason``, ``reference`` and
    ``invariant_drift``, which are written as null).
    """

    complete: bool
    reason: str
    slices: int
    newton_iterations: int
    max_newton_iterations: int
    wall_time: float
    sites_per_second: float
    max_residual: float
    mode: str
    solver: str
    device: str
    slice_solver: str | None
    extrapolation: dict[str, Any] | None
    warnings: list[str]
    every: int
    kept_slices: int
    stop_reason: str | None
    requested_slices: int
    source: str  # the key ``from``
    start: str
    ensemble_members: int | None = None
    #: an ensemble's members that stopped short: ``{member, slice, reason}`` each (empty when none did)
    members_stopped: list[dict[str, Any]] | None = None
    #: an ensemble's members whose fields leave their own training range: ``{member, slice, feature, excess}``
    #: each (empty when none does)
    members_outside: list[dict[str, Any]] | None = None
    reference: str | None = None
    max_error: float | None = None  # with the next three: present when the task has a reference
    rms_error: float | None = None
    compared_slices: int | None = None
    relative_error: float | None = None
    baseline: dict[str, Any] | None = None
    error_estimate: dict[str, Any] | None = None
    calibration: dict[str, Any] | None = None
    invariant: str | None = None  # with ``invariant_drift`` (None when the invariant is zero or undefined)
    invariant_drift: float | None = None
    charges_auto: list[dict[str, Any]] | None = None
    charges: dict[str, Any] | None = None
    charges_error: str | None = None
    file: str | None = None
    exports: list[str] | None = None
    #: served split over processes: ``processes``, ``axis`` and each process's ``slabs`` ``[lo, hi)``
    decomposition: dict[str, Any] | None = None

    @classmethod
    def served(cls, result: dict[str, Any], **rest: Any) -> TaskRecord:
        """A record from a result's numbers (``ServeResult.to_dict()``) and the task's other fields."""
        own = {k: result[k] for k in SERVED_KEYS}
        return cls(
            **own,
            ensemble_members=result.get("ensemble_members"),
            members_stopped=result.get("members_stopped"),
            members_outside=result.get("members_outside"),
            **rest,
        )

    def to_dict(self) -> dict[str, Any]:
        """The task's entry of ``summary.json``, its keys in order (those of the result first)."""
        out: dict[str, Any] = {k: getattr(self, k) for k in SERVED_KEYS}
        out["warnings"] = list(self.warnings)
        if self.ensemble_members is not None:
            out["ensemble_members"] = self.ensemble_members
            out["members_stopped"] = list(self.members_stopped or [])
            out["members_outside"] = list(self.members_outside or [])
        out.update(
            every=self.every,
            kept_slices=self.kept_slices,
            stop_reason=self.stop_reason,
            requested_slices=self.requested_slices,
        )
        out["from"] = self.source
        out.update(start=self.start, reference=self.reference)
        if self.max_error is not None:
            out.update(
                max_error=self.max_error,
                rms_error=self.rms_error,
                compared_slices=self.compared_slices,
                relative_error=self.relative_error,
            )
        optional: dict[str, Any] = {
            "baseline": self.baseline,
            "error_estimate": self.error_estimate,
            "calibration": self.calibration,
        }
        out.update({k: v for k, v in optional.items() if v is not None})
        if self.invariant is not None:
            out.update(invariant_drift=self.invariant_drift, invariant=self.invariant)
        optional = {
            "decomposition": self.decomposition,
            "charges_auto": self.charges_auto,
            "charges": self.charges,
            "charges_error": self.charges_error,
            "file": self.file,
            "exports": self.exports,
        }
        out.update({k: v for k, v in optional.items() if v is not None})
        return out


def accuracy_warning(rec: TaskRecord) -> str | None:
    """The warning of a task whose relative error exceeds :data:`RELATIVE_ERROR_LIMIT` (None when it does not,
    or when the task has no reference)."""
    rel = rec.relative_error
    if rec.max_error is None or rel is None or rel <= RELATIVE_ERROR_LIMIT:
        return None
    size = f"{rel:.0%} of" if rel < 1 else f"{rel:.2g} times" if math.isfinite(rel) else "a non-finite multiple of"
    return (
        f"inaccurate: the served field is off by {size} the reference's largest magnitude (relative error "
        f"{rel:.3g}, above {RELATIVE_ERROR_LIMIT:g}) over {rec.compared_slices} slices"
        + (", though the task is complete" if rec.complete else "")
        + "; next: check the training verdict, serve fewer slices, or train on data closer to this task's"
    )
