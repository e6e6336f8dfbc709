"""The task record of summary.json: its keys follow the served result's, in order, and the accuracy warning
trips above its threshold only."""

from __future__ import annotations

import math

import latticedft as ldft
from latticedft._run import RELATIVE_ERROR_LIMIT, TaskRecord
from latticedft._run._record import accuracy_warning

from helpers import oscillator_data


def _record(**rest: object) -> TaskRecord:
    _, data = oscillator_data(amplitudes=(0.6,), steps=30)
    model = ldft.PolynomialLagrangian((2, 4))
    ldft.learn(model, data)
    result = ldft.serve(model, data[0], progress=False)
    fields = dict(every=1, kept_slices=30, stop_reason=None, requested_slices=30, source="a.nc", start="data")
    rec = TaskRecord.served(result.to_dict(), **{**fields, **rest})
    assert list(rec.to_dict())[: len(result.to_dict())] == list(result.to_dict())  # the result's keys first
    return rec


def test_the_record_keys_are_in_the_summary_order() -> None:
    rec = _record(reference="a.nc", max_error=0.1, rms_error=0.05, compared_slices=30, relative_error=0.2)
    rec.invariant, rec.invariant_drift, rec.charges, rec.file, rec.exports = "m:f", None, {}, "a.nc", []
    keys = list(rec.to_dict())
    tail = ["every", "kept_slices", "stop_reason", "requested_slices", "from", "start", "reference", "max_error"]
    assert keys[keys.index("every") : keys.index("every") + len(tail)] == tail
    assert keys[-8:] == [
        "rms_error",
        "compared_slices",
        "relative_error",
        "invariant_drift",
        "invariant",
        "charges",
        "file",
        "exports",
    ]
    bare = list(_record().to_dict())
    assert bare[-1] == "reference" and "max_error" not in bare and "invariant" not in bare


def test_the_accuracy_warning_trips_above_its_threshold_only() -> None:
    def warning(rel: float) -> str | None:
        return accuracy_warning(_fake(rel))

    assert warning(0.17) is None and warning(RELATIVE_ERROR_LIMIT) is None
    assert "off by 73% of the reference's" in str(warning(0.73))
    assert "off by 1.8 times the reference's" in str(warning(1.8))
    assert "off by 7.6e+46 times" in str(warning(7.6e46))
    assert "non-finite" in str(warning(math.inf)) and "non-finite" in str(warning(math.nan))


def _fake(rel: float) -> TaskRecord:
    served = dict(reason="complete", newton_iterations=20, max_newton_iterations=2, wall_time=0.1)
    served.update(sites_per_second=100.0, max_residual=1e-12, mode="newton", solver="newton", device="cpu")
    fields = dict(every=1, kept_slices=10, stop_reason=None, requested_slices=10, source="a.nc", start="data")
    return TaskRecord(
        complete=True,
        slices=10,
        slice_solver=None,
        extrapolation=None,
        warnings=[],
        **served,
        **fields,
        reference="b.nc",
        max_error=1.0,
        rms_error=0.5,
        compared_slices=10,
        relative_error=rel,
    )
