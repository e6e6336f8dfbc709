"""A case's model learned from its training fields: :func:`train_model` (with ``[model] select``, chosen first)."""

from __future__ import annotations

import logging
from typing import Any

from .._case import Case
from .._collective import is_parallel
from .._contract import AbstractLagrangian
from .._errors import ConfigError, InputError
from .._learn import learn
from .._options import set_options
from .._select import select
from ._data import CaseData, as_case_error

__all__ = ["train_model"]

log = logging.getLogger("latticedft")


def train_model(case: Case, data: CaseData) -> tuple[Any, Any]:
    """Build the model of ``[model]`` and learn it from the training fields."""
    model = case.model.build(len(data.dims))
    try:
        with set_options(learn_share="fields"):  # several processes: each reads the training files it holds
            model, report = _learn(case, data, model)
    except InputError as exc:
        if exc.key is not None and exc.key in case.train.learn:
            raise as_case_error(exc, f"train.{exc.key}") from None
        raise
    log.info("%s", report.summary_line())
    log.info("%s", report.verdict())
    if report.noise is not None:  # [train] noise = "auto" | "correct"
        nz = report.noise
        est = f"sigma {nz['sigma']:.2e} ({nz['relative']:.1e} of the amplitude)" if nz["resolved"] else "unresolved"
        done = f"{nz['method']}, rms shift {nz['shift']:.2e}" if nz["method"] != "none" else "none"
        log.info("noise (%s): %s; correction: %s", nz["mode"], est, done)
    log.debug("training device: %s", report.device)
    if model.ensemble_ is not None:  # [train] ensemble: serve every member, member 0 the full-data model
        model = model.ensemble_
        log.info(
            "ensemble: %d members on resamples of %d time windows", len(model), (report.ensemble or {}).get("windows")
        )
    if report.symmetries is not None:
        log.info("symmetries of the learned L_d over the training data (verdicts at tol 1e-9):")
        for line in report.symmetry_lines():
            log.info("  %s", line)
    log.debug("training report: %s", {k: v for k, v in report.to_dict().items() if k != "history"})
    for warning in report.warnings:  # a degenerate M, a poor fit (thresholds in docs/outputs.md)
        log.warning("%s", warning)
    return model, report


def _learn(case: Case, data: CaseData, model: AbstractLagrangian) -> tuple[Any, Any]:
    """The model learned (chosen first with ``[model] select``) and its report."""
    if case.model.select is not None:
        return _select_and_learn(case, data, model)
    log.info("training %s model on %d field(s) ...", case.model.kind, len(data.train))
    report = learn(
        model, data.train, boundary=case.train.boundary, progress=None, device=case.run.device, **case.train.learn
    )
    return model, report


def _select_and_learn(case: Case, data: CaseData, model: AbstractLagrangian) -> tuple[Any, Any]:
    """``[model] select``: score the candidates by serving held-out data (table to the log); the chosen model,
    learned on all the data. With ``[train] ensemble`` the candidates are scored as single models and the chosen
    one is then learned as the ensemble's member 0 (its report keeps the selection table and warnings)."""
    learn_kw = dict(case.train.learn)
    ens = {k: learn_kw.pop(k) for k in ("ensemble", "ensemble_seed") if k in learn_kw}
    candidates = case.model.select if isinstance(case.model.select, str) else list(case.model.select or ())
    log.info("selecting a model by serving held-out data (select = %s) ...", "auto" if candidates == "auto" else "list")
    try:
        sel = select(model, data.train, candidates, boundary=case.train.boundary, device=case.run.device, **learn_kw)
    except InputError as exc:
        if exc.key == "candidates":
            raise ConfigError(f"case.toml: model.select: {exc.problem}", key="model.select") from None
        raise
    for line in sel.table_lines():
        log.info("  %s", line)
    log.info("selection: %s", sel.reason)
    chosen: Any = sel.model
    report = chosen.report_
    if ens.get("ensemble"):
        selection, warnings = report.selection, list(report.warnings)
        learn_kw["ridge"] = report.ridge
        report = learn(
            chosen, data.train, boundary=case.train.boundary, progress=None, device=case.run.device, **learn_kw, **ens
        )
        report.selection = selection
        report.warnings[:0] = [w for w in warnings if w not in report.warnings]
        chosen.report_ = report
    if case.run.device == "cpu" and not is_parallel():  # the calibration's fits would be these, learned alike
        object.__setattr__(chosen, "selection_trials_", sel.trials)  # not submodules: read by the calibration
        object.__setattr__(chosen, "selection_served_", sel.served)  # the fields two of them served when scored
    return chosen, report
