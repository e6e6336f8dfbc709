"""A case's error bars: the calibration law measured after training (``[train] calibrate``), and a served task's
calibrated estimate (``<var>_err_est``, the calibrated ``<var>_std``) with the warnings of its extrapolation.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import xarray as xr

from .._calibrate import Calibration, calibrate, runner_up, too_short, trial_keywords
from .._case import Case
from .._collective import alone
from .._contract import AbstractLagrangian
from .._errors import LatticeDFTError
from .._models import EnsembleLagrangian
from .._select import _build
from ._data import CaseData

__all__ = ["CaseCalibration", "TaskBand", "case_calibration", "task_band", "wanted"]

log = logging.getLogger("latticedft")


def wanted(case: Case) -> bool:
    """Whether ``[train] calibrate`` asks for a calibration: ``true``, or ``"auto"`` with ``[model] select``,
    ``[train] ensemble`` or a noise-aware fit (``noise`` other than ``"none"``)."""
    flag = case.train.calibrate
    if flag != "auto":
        return bool(flag)
    learn = case.train.learn
    return case.model.select is not None or bool(learn.get("ensemble")) or learn.get("noise", "none") != "none"


@dataclass
class CaseCalibration:
    """A case's calibration after training: the law as a dict (None: none measured), its warnings, the trial
    model and the runner-up candidate's trial (None without one: :attr:`Calibration.candidates`)."""

    law: dict[str, Any] | None
    warnings: list[str]
    trial: AbstractLagrangian | None = None
    runner: AbstractLagrangian | None = None


def case_calibration(case: Case, data: CaseData, model: AbstractLagrangian, report: Any) -> CaseCalibration:
    """Measure the case's calibration law by held-out serving after training. Training data too short for a
    held-out window give one warning and no law."""
    if not wanted(case):
        return CaseCalibration(None, [])
    short = too_short(data.train)
    if short is not None:
        return CaseCalibration(None, [short])
    with alone():  # rank 0's alone under --workers: the other processes take no part in it
        fresh, kwargs, runner_up, learned, served = _candidates(case, data, model, report)
        log.info("calibrating the error bar by held-out serving ...")
        second: list[AbstractLagrangian] = []
        sel = getattr(report, "selection", None)
        try:
            ens = model if isinstance(model, EnsembleLagrangian) else None
            cal, warnings, trial = calibrate(
                fresh,
                data.train,
                boundary=case.train.boundary,
                runner_up=runner_up,
                ensemble_model=ens,
                learned=learned,
                served=served,
                chosen=sel["candidates"][sel["chosen"]]["label"] if sel else None,
                runner_trial=second,
                **kwargs,
            )
        except LatticeDFTError as exc:
            return CaseCalibration(None, [_failed(" ".join(str(exc).split())[:160])])
        if cal.failed is not None:
            return CaseCalibration(None, [*warnings, _failed(cal.failed)])
    log.info(
        "calibration: err(k) = A * %.3g * k^%.2f on %d held-out slices (2 std covers %.0f %% of them; %.1f s)",
        cal.scale,
        cal.exponent,
        cal.held_out_slices,
        100 * cal.coverage,
        cal.wall_time,
    )
    runner = second[0] if second and cal.candidates is not None else None
    return CaseCalibration(cal.to_dict(), warnings, trial, runner)


def _failed(why: str) -> str:
    """The warning of a calibration that could not be measured."""
    return f"calibration: failed ({why}): served without a calibrated error bar"


def _candidates(
    case: Case, data: CaseData, model: AbstractLagrangian, report: Any
) -> tuple[
    AbstractLagrangian,
    dict[str, Any],
    tuple[AbstractLagrangian, dict[str, Any], str] | None,
    tuple[AbstractLagrangian, AbstractLagrangian | None] | None,
    tuple[list[np.ndarray] | None, list[np.ndarray] | None] | None,
]:
    """The chosen model unlearned with its learn keywords, the runner-up of model selection (None without
    selection, or without one: :func:`latticedft._calibrate.runner_up`), the two as selection learned them on
    the held-in slices where it kept them (``selection_trials_``; else None), and the fields they served when
    selection scored them (``selection_served_``, :attr:`latticedft.SelectionReport.served`; else None)."""
    kwargs = {k: v for k, v in case.train.learn.items() if k not in ("ensemble", "ensemble_seed")}
    hand = case.model.build(len(data.dims))
    sel = getattr(report, "selection", None)
    if not sel:  # the trial takes the weight the model's fit chose where ridge = "auto"
        return hand, trial_keywords(kwargs, getattr(report, "ridge", None)), None, None, None
    rows, at = sel["candidates"], sel["chosen"]
    chosen = rows[at]
    fresh = _build(hand, chosen["kind"], dict(chosen["options"]))
    own = {**kwargs, "ridge": chosen["ridge"]}
    runner = runner_up(rows, at)
    first = model.member(0) if isinstance(model, EnsembleLagrangian) else model
    trials = getattr(first, "selection_trials_", None)
    learned = (trials[at], None if runner is None else trials[runner]) if trials and trials[at] is not None else None
    kept = getattr(first, "selection_served_", None)
    served = (kept[at], None if runner is None else kept[runner]) if learned is not None and kept else None
    if runner is None:
        return fresh, own, None, learned, served
    r = rows[runner]
    up = (_build(hand, r["kind"], dict(r["options"])), {**kwargs, "ridge": r["ridge"]}, r["label"])
    return fresh, own, up, learned, served


@dataclass
class TaskBand:
    """A served task's calibrated error bar: ``err_est`` (per slice, RMS over the lattice), the calibrated
    standard deviation of an ensemble (None for a single model) and the summary's ``error_estimate``."""

    err_est: xr.DataArray
    std: xr.DataArray | None
    record: dict[str, Any]
    warnings: list[str]


def task_band(
    cal: dict[str, Any],
    field: xr.DataArray,
    std: xr.DataArray | None,
    other: np.ndarray | None = None,
    members: xr.DataArray | None = None,
    between: np.ndarray | None = None,
) -> TaskBand:
    """The calibrated error bar of a served ``field`` (an ensemble's raw ``std`` beside it, or None): the larger
    of the law and ``other``, the trial model's disagreement with the field per slice (None without one); an
    ensemble's calibrated standard deviation by :meth:`Calibration.band`. ``members``: an ensemble's fields
    (``member`` first), each checked against the training fields' range (:meth:`Calibration.members_warning`).
    ``between``: the runner-up's trial's disagreement with the trial per slice (RMS over the lattice; None
    without a runner-up), compared with the training fields' (:meth:`Calibration.candidates_ratio`)."""
    law = Calibration.from_dict(cal)
    tdim = field.dims[0]
    k = np.asarray(field["slice"].values if "slice" in field.coords else np.arange(field.sizes[tdim]))
    values = np.asarray(field.values, dtype=np.float64)
    finite = np.abs(values[np.isfinite(values)])
    amplitude = float(finite.max()) if finite.size else math.nan
    est = law.estimate(k, amplitude)
    if other is not None:
        other = np.where(k >= 2, other, 0.0)
        est = np.fmax(est, other)
    err_est = xr.DataArray(est, dims=(tdim,), coords={tdim: field[tdim].values}, name="err_est")
    err_est.attrs = {
        "long_name": "calibrated error estimate (1 std, RMS over the lattice) from held-out serving",
        "law": law.law,
        "scale": law.scale,
        "exponent": law.exponent,
    }
    if "units" in field.attrs:
        err_est.attrs["units"] = field.attrs["units"]
    calibrated = law.band(std, est, other) if std is not None else None
    served = int(k.max()) + 1 if k.size else 0
    record = {
        "band": "ensemble and held-out error" if std is not None else "held-out error",
        "terms": ["law", "trial disagreement"] if other is not None else ["law"],
        "mean": float(np.mean(est[k >= 2])) if (k >= 2).any() else None,
        "last": float(est[-1]) if est.size else None,
        "amplitude": amplitude,
    }
    warnings = law.warnings(served, values)
    if between is not None:
        ratio = law.candidates_ratio(np.asarray(between) / amplitude, k)
        record["candidates_ratio"] = ratio
        warning = law.candidates_warning(ratio, int(np.sum((k >= 2) & (k < law.slices))))
        warnings += [warning] if warning else []
    if members is not None:
        warning = law.members_warning(np.asarray(members.values, dtype=np.float64))
        warnings += [warning] if warning else []
    return TaskBand(err_est, calibrated, record, warnings)
