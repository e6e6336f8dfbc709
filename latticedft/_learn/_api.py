"""The public :func:`learn`: check the arguments, bind the model, run the exact solve or training, report."""

from __future__ import annotations

import copy
import math
import os
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from typing import Any

import torch
import xarray as xr

from .._contract import GaugeName
from .._device import device_label, on_device, resolve_device
from .._errors import InputError
from .._lattice import BoundaryKinds, LatticeField
from .._models import AbstractLagrangian, EnsembleLagrangian, LinearLagrangian, SparseLagrangian
from ._ensemble import learn_ensemble
from ._exact import learn_exact
from ._gauge import AUTO, Gauge, gauge_named
from ._neural import Training, learn_neural
from ._noise import NOISE_MODES, learn_noisy
from ._report import LearnReport, fit_warnings
from ._sparse import learn_sparse
from ._stream import TrainingData, training_data

__all__ = ["learn"]

#: Optimizers: ``exact`` (linear models), ``lbfgs`` and ``adam`` (neural models).
OPTIMIZERS = ("exact", "lbfgs", "adam")


#: ``gauge="auto"``: unit-mass is kept when its training ``rel_res`` is at most this (exact to round-off).
AUTO_EXACT = 1e-8
#: ... otherwise trace is chosen when its ``rel_res`` is below this factor times unit-mass's ...
AUTO_FACTOR = 0.1
#: ... and the smallest singular value of ``h_0^2 M`` over its training cells is at least this.
AUTO_MIN_SV = 1e-8

#: The rule of ``gauge="auto"`` in words (docs/api.md repeats it).
AUTO_RULE = (
    "fit unit-mass; keep it when the field has one component (the two gauges are then the same condition), "
    "when the model has a unit mass by construction, or when its rel_res <= 1e-8; otherwise fit trace from "
    "the same start and choose it when its rel_res is below a tenth of unit-mass's and its mixed Hessian stays "
    "invertible (min sv of h0^2 M >= 1e-8); else keep unit-mass. Under noise (the fields corrected), a model of "
    "several components that kept unit-mass is learned again, correction included, in trace, and the same rule "
    "compares the two corrected fits"
)


def _checked(
    model: AbstractLagrangian, gauge: str, ridge: float | str, optimizer: str | None, max_iter: int
) -> tuple[Gauge | None, str]:
    """The gauge (``None`` for ``auto``) and the optimizer (its default filled in, from the kind of the model,
    or of an ensemble's members), or an InputError naming the bad argument."""
    fix = None if gauge == AUTO else gauge_named(gauge)
    if not isinstance(model, AbstractLagrangian):
        raise InputError(f"model: expected a latticedft model, got {type(model).__name__}")
    model = model.member(0)
    optimizer = optimizer or ("exact" if model.linear else "lbfgs")
    if optimizer not in OPTIMIZERS:
        raise InputError.at("optimizer", f"expected 'exact', 'lbfgs' or 'adam', got {optimizer!r}")
    if optimizer == "exact" and not model.linear:
        raise InputError.at("optimizer", f"'exact' needs a model linear in its parameters; {model.kind!r} is not")
    if not (ridge == "auto" or (isinstance(ridge, (int, float)) and not isinstance(ridge, bool) and ridge >= 0)):
        raise InputError.at("ridge", f"expected a number >= 0 or 'auto', got {ridge!r}")
    if not isinstance(max_iter, int) or isinstance(max_iter, bool) or max_iter < 1:
        raise InputError.at("max_iter", f"expected a positive integer, got {max_iter!r}")
    return fix, optimizer


def _check_number(name: str, value: object, *, strict: bool, optional: bool = False) -> None:
    """Refuse ``value`` unless it is a finite real number ``> 0`` (``strict``) or ``>= 0`` (or None if ``optional``)."""
    if optional and value is None:
        return
    ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
    if not ok or value < 0 or (strict and value == 0):  # type: ignore[operator]
        what = "a number > 0" if strict else "a number >= 0"
        raise InputError.at(name, f"expected {what}{' or None' if optional else ''}, got {value!r}")


def _check_training(training: Training) -> None:
    """Refuse bad iterative-training settings with an InputError naming the argument."""
    _check_number("max_time", training.max_time, strict=True, optional=True)
    _check_number("tol", training.tol, strict=False)
    _check_number("rel_tol", training.rel_tol, strict=True, optional=True)
    _check_number("lr", training.lr, strict=True)
    _check_number("penalty", training.penalty, strict=False)
    if training.progress is not None and not isinstance(training.progress, bool):
        raise InputError.at("progress", f"expected True, False or None, got {training.progress!r}")


def _bound_to(model: AbstractLagrangian, fields: TrainingData) -> int:
    """Bind and prepare ``model`` on the training data and record the training range of each stencil feature
    (chunk by chunk when streamed); returns the number of DEL equations (sites)."""
    return fields.bind(model)


def learn(
    model: AbstractLagrangian,
    data: xr.DataArray | str | os.PathLike[str] | Sequence[xr.DataArray | str | os.PathLike[str]],
    *,
    gauge: str = "auto",
    ridge: float | str = 0.0,
    optimizer: str | None = None,
    max_iter: int = 500,
    max_time: float | None = None,
    tol: float = 0.0,
    rel_tol: float | None = None,
    lr: float = 1e-3,
    penalty: float = 1.0,
    boundary: BoundaryKinds | None = None,
    progress: bool | None = None,
    symmetries: bool = False,
    chunk_sites: int | None = None,
    noise: str = "none",
    noise_sigma: float | None = None,
    device: str | None = None,
    ensemble: int | None = None,
    ensemble_seed: int = 0,
) -> LearnReport:
    """Learn ``L_d`` from one or more observed fields; the model is fitted in place.

    Parameters
    ----------
    model : AbstractLagrangian
        The model to fit (e.g. ``PolynomialLagrangian((4, 8))``).
    data : DataArray, path, or a list of them
        Observed fields (time first, then the spatial axes, then an optional
        ``component`` axis), each on its own lattice of the same spacing. Lazy
        DataArrays (``xr.open_dataset(...)["psi"]`` unloaded, or dask-backed)
        and paths of field files are read one chunk at a time.
    gauge : "unit-mass", "trace", "none" or "auto"
        How the gauge is fixed (see :data:`GAUGES`). ``trace`` fixes only the
        trace of the mean mixed Hessian (components of unequal mass, terms
        linear in the velocity such as a magnetic field); ``none`` shows the
        collapse the loss alone leads to; ``auto`` fits unit-mass and, for a
        vector field whose unit-mass fit is not exact, trace too, and keeps
        the better by the training residual (:data:`AUTO_RULE`; the choice is
        in ``report.gauge`` and ``report.gauge_choice``).
    ridge : float or "auto"
        Linear models: Tikhonov weight (relative to the mean squared column
        norm); ``"auto"`` picks it from a grid by the held-out relative
        residual (leave-one-field-out, or the last 30 % of a single field).
    optimizer : "exact", "lbfgs" or "adam"
        Default: ``exact`` for linear models (:class:`LinearLagrangian`),
        ``lbfgs`` otherwise.
    max_iter, max_time, tol, rel_tol, lr, penalty
        Iterative training: stop after ``max_iter`` iterations or
        ``max_time`` seconds, or when the objective is ``<= tol`` or has
        fallen by the factor ``rel_tol`` (the paper stops at ``1e-5``);
        Adam's learning rate; weight of the gauge penalty.
    boundary : str or dict, optional
        Boundary kinds per spatial axis (``periodic`` axes wrap, so every
        site carries an equation); default from the coordinates' ``periodic``
        attribute.
    progress : bool, optional
        Progress bar; ``None`` shows it only on a terminal.
    symmetries : bool
        Also test the learned ``L_d`` for every built-in symmetry of the data's lattice over the training
        data (:func:`latticedft.symmetries`); the results are ``report.symmetries`` (docs/symmetries.md).
    chunk_sites : int, optional
        Training streams the data in chunks of about this many lattice sites,
        so memory does not grow with the data (default: from the model's
        size); ``0`` holds and processes all data at once (in memory). Under
        an initialised ``torch.distributed`` process group every process
        reads its share of the chunks and all end with the same model.
    noise : "none", "auto" or "correct"
        Noisy data (docs/noise.md): ``correct`` alternates the fit with a
        correction of the training fields toward the learned DEL (errors in
        variables: exact refits of a linear model; an iterative model is
        refitted from its previous weights, about five trainings in all);
        ``auto`` does so only when the noise estimated from the data
        (:func:`estimate_noise`) is significant. The estimate and what was
        done are in ``report.noise``. With ``ensemble``, member 0 is learned
        so and the other members on resamples of the corrected fields.
    noise_sigma : float, optional
        The noise's standard deviation when known (field units); skips the
        estimate.
    device : "cpu", "cuda", "cuda:N" or "auto", optional
        Where iterative training evaluates the model (its parameters, and
        ``L_d`` with its derivatives on the cells of each chunk): default the
        CPU; ``"auto"`` is CUDA when available. CUDA where none is available
        falls back to the CPU with one :class:`DeviceWarning`. The exact solve
        of linear models runs on the CPU. The fitted model is left on the CPU;
        ``report.device`` names the device used.
    ensemble : int, optional
        Also learn an ensemble of this many members (at least 2) for an error bar on served fields:
        ``model`` is member 0, fitted on all the data as without ``ensemble``, and the ensemble
        (:class:`EnsembleLagrangian`, the other members fitted on bootstrap resamples of the data's time
        windows) is ``model.ensemble_``; serve it for ``mean`` and ``std``. Passing an
        ``EnsembleLagrangian`` as ``model`` does the same.
    ensemble_seed : int
        Seed of the ensemble's resampling.

    Returns
    -------
    LearnReport
        Also stored as ``model.report_``.

    Examples
    --------
    >>> import numpy as np, xarray as xr, latticedft as ldft
    >>> t = np.arange(60) * 0.1
    >>> data = [xr.DataArray(a * np.cos(t), dims="t", coords={"t": t}, name="psi") for a in (0.5, 1.0)]
    >>> model = ldft.PolynomialLagrangian(orders=(2, 2))
    >>> report = ldft.learn(model, data)
    >>> report.gauge_residual < 1e-10 and report.rel_res < 1e-3
    True
    """
    fix, optimizer = _checked(model, gauge, ridge, optimizer, max_iter)
    where = resolve_device(device)
    settings = Training(
        optimizer=optimizer,
        max_iter=max_iter,
        max_time=max_time,
        tol=tol,
        rel_tol=rel_tol,
        lr=lr,
        penalty=penalty,
        progress=progress,
        device=where,
    )
    _check_training(settings)
    if not isinstance(symmetries, bool):
        raise InputError.at("symmetries", f"expected true or false, got {symmetries!r}")
    if noise not in NOISE_MODES:
        raise InputError.at("noise", f"expected 'auto', 'none' or 'correct', got {noise!r}")
    _check_number("noise_sigma", noise_sigma, strict=False, optional=True)
    ens = _ensemble_of(model, ensemble, ensemble_seed)
    fields = training_data(data, boundary, chunk_sites)
    learner = _Learner(
        fix=fix,
        ridge=ridge,
        settings=settings,
        symmetries=symmetries,
        noise=noise,
        noise_sigma=noise_sigma,
        make=lambda f: training_data(f, boundary, chunk_sites),
        trained_on=device_label(where) if optimizer != "exact" else "cpu",
    )
    if ens is None:
        return learner.fit_noisy(model, fields)[0]
    report = learn_ensemble(ens, lambda one: learner.fit_noisy(one, fields), learner.fit)
    if ens is not model:
        object.__setattr__(model, "ensemble_", ens)  # not a submodule: the ensemble holds the model
        model.report_ = report
    return report


@dataclass(frozen=True)
class _Learner:
    """The settings of one :func:`learn` call, applied to a model (member 0 of an ensemble, or another member)."""

    fix: Gauge | None  # None: "auto"
    ridge: float | str
    settings: Training
    symmetries: bool
    noise: str
    noise_sigma: float | None
    make: Callable[[list[LatticeField]], TrainingData]  # the training data of corrected fields
    trained_on: str  # the device label of the reports

    def fit(self, one: AbstractLagrangian, data: TrainingData, main: LearnReport | None = None) -> LearnReport:
        """Learn ``one``; an ensemble's resampled members (``main``: member 0's report) skip the symmetry tests
        and take member 0's ridge and gauge where ``"auto"`` chose them."""
        nsites = _bound_to(one, data)
        tests = self.symmetries and main is None
        weight = main.ridge if main is not None and self.ridge == "auto" else self.ridge
        chosen = gauge_named(main.gauge) if main is not None and self.fix is None else self.fix  # member 0's choice
        if chosen is None:  # "auto"
            report = _learn_auto(one, data, weight, nsites, self.settings, tests)
        else:
            report = _fit(one, data, chosen, weight, nsites, self.settings, tests)
        report = replace(report, device=self.trained_on)
        one.report_ = report
        return report

    def fit_noisy(self, one: AbstractLagrangian, fields: TrainingData) -> tuple[LearnReport, TrainingData]:
        """Learn ``one`` with the noise handling asked for; the report and the data of its last fit."""
        if self.noise == "none":
            return self.fit(one, fields), fields
        report, used = learn_noisy(one, fields, lambda fs: self.fit(one, fs), self.noise, self.noise_sigma, self.make)
        if self._gauge_after_correction(one, report):
            report, used = self._trace_after_correction(one, fields, report, used)
        one.report_ = report
        return report, used

    def _gauge_after_correction(self, one: AbstractLagrangian, report: LearnReport) -> bool:
        """Whether ``gauge="auto"`` kept unit-mass for a model of several components whose fit corrected the noise
        of its data, without fitting it to round-off: the rule's comparison of ``rel_res`` then met the noise's
        floor (both gauges near it), and it is made again after the correction (:meth:`_trace_after_correction`)."""
        corrected = (report.noise or {}).get("method", "none") != "none"
        return (
            self.fix is None
            and corrected
            and one.m > 1
            and not one.unit_mass_by_construction
            and report.gauge == GaugeName.UNIT_MASS.value
            and report.rel_res > AUTO_EXACT
        )

    def _trace_after_correction(
        self, one: AbstractLagrangian, fields: TrainingData, report: LearnReport, used: TrainingData
    ) -> tuple[LearnReport, TrainingData]:
        """The noise-aware fit again in the trace gauge, kept by the rule of :data:`AUTO_RULE` applied to the two
        fits on their corrected fields (a magnetic term, or unequal masses, that unit-mass cannot hold: the
        correction then pulls the data toward the wrong equations, and the rule's factor 10 is met only after it).
        """
        kept = copy.deepcopy(one)
        trace = replace(self, fix=gauge_named(GaugeName.TRACE))
        second, used2 = learn_noisy(one, fields, lambda fs: trace.fit(one, fs), self.noise, self.noise_sigma, self.make)
        better, why = _trace_better(report, second)
        scores = {report.gauge: report.rel_res, second.gauge: second.rel_res}
        why = f"{why}, each after the noise correction"
        if better:
            return replace(second, gauge_requested="auto", gauge_scores=scores, gauge_choice=why), used2
        one.load_state_dict(kept.state_dict())
        if isinstance(one, SparseLagrangian) and isinstance(kept, SparseLagrangian):  # an attribute, not state
            one.bag_spread = kept.bag_spread
        return replace(report, gauge_scores=scores, gauge_choice=why), used


def _ensemble_of(model: AbstractLagrangian, ensemble: int | None, seed: int) -> EnsembleLagrangian | None:
    """The ensemble to learn: ``model`` itself, one built around it (``ensemble`` members), or None."""
    if not isinstance(seed, int) or isinstance(seed, bool) or seed < 0:
        raise InputError.at("ensemble_seed", f"expected an integer >= 0, got {seed!r}")
    if ensemble is None:
        return model if isinstance(model, EnsembleLagrangian) else None
    if not isinstance(ensemble, int) or isinstance(ensemble, bool) or ensemble < 2:
        raise InputError.at(
            "ensemble", f"expected an integer >= 2 (members, the full-data model included), got {ensemble!r}"
        )
    if isinstance(model, EnsembleLagrangian):
        raise InputError.at("ensemble", "the model is an EnsembleLagrangian already: give its members there")
    return EnsembleLagrangian(model, members=ensemble, seed=seed)


def _fit(
    model: AbstractLagrangian,
    fields: TrainingData,
    fix: Gauge,
    ridge: float | str,
    nsites: int,
    settings: Training,
    symmetries: bool = False,
    shared: dict[str, Any] | None = None,
) -> LearnReport:
    """One fit of the bound ``model`` with the gauge ``fix``, measured (``shared``: a sparse fit's rows, kept for
    the next fit of the same library on the same fields)."""
    t0 = time.perf_counter()
    history: list[tuple[int, float, float]] = []
    initial = None
    validation: dict[str, float] = {}
    used_ridge = 0.0
    if isinstance(model, SparseLagrangian) and settings.optimizer == "exact":  # few columns: rows held in memory
        used_ridge, validation = learn_sparse(model, fields.fields, fix, ridge, nsites, shared)
        iterations, reason = 1, "sparse exact solve"
        wall = time.perf_counter() - t0
        diag = fields.diagnose(model, fix.name, symmetries)
    elif settings.optimizer == "exact" and isinstance(model, LinearLagrangian):  # _checked refuses 'exact' for others
        used_ridge, validation = learn_exact(model, fields, fix, ridge, nsites)
        iterations, reason = 1, "exact solve"
        wall = time.perf_counter() - t0
        diag = fields.diagnose(model, fix.name, symmetries)
    else:  # iterative training and its diagnostics evaluate the model on the device
        with on_device(model, settings.device or torch.device("cpu")):
            iterations, history, initial, reason = learn_neural(model, fields, fix, nsites, settings)
            wall = time.perf_counter() - t0
            diag = fields.diagnose(model, fix.name, symmetries)
    degenerate, warnings = fit_warnings(diag)
    return LearnReport(
        method=settings.optimizer,
        loss=diag["loss"],
        rel_res=diag["rel_res"],
        iterations=iterations,
        wall_time=wall,
        gauge=fix.name,
        gauge_residual=diag["gauge_residual"],
        hessian_min_sv=diag["hessian_min_sv"],
        hessian_cond=diag["hessian_cond"],
        ridge=used_ridge,
        initial_loss=initial,
        n_fields=len(fields),
        n_sites=nsites,
        n_parameters=model.n_parameters(),
        stop_reason=reason,
        history=history,
        validation=validation,
        symmetries=diag.get("symmetries"),
        hessian_max_sv=diag["hessian_max_sv"],
        degenerate=degenerate,
        warnings=warnings,
        _sparse=model.sparse_summary(equation=False) if isinstance(model, SparseLagrangian) else None,
        _equation=model.equation_later() if isinstance(model, SparseLagrangian) else None,
    )


def _learn_auto(
    model: AbstractLagrangian,
    fields: TrainingData,
    ridge: float | str,
    nsites: int,
    settings: Training,
    symmetries: bool = False,
) -> LearnReport:
    """``gauge="auto"``: the rule of :data:`AUTO_RULE`, every candidate fitted from the same start."""
    if isinstance(model, SparseLagrangian) and model.m > 1 and settings.optimizer == "exact":
        return _learn_auto_sparse(model, fields, ridge, nsites, settings, symmetries)
    start = {k: v.detach().clone() for k, v in model.state_dict().items()}
    unit_mass, trace = gauge_named(GaugeName.UNIT_MASS), gauge_named(GaugeName.TRACE)
    first = _fit(model, fields, unit_mass, ridge, nsites, settings, symmetries)
    scores = {unit_mass.name: first.rel_res}
    if model.m == 1:
        why = "one component: unit-mass and trace are the same condition"
    elif model.unit_mass_by_construction:
        why = "the model has a unit mass by construction"
    elif first.rel_res <= AUTO_EXACT:
        why = f"unit-mass fits to round-off (rel_res {first.rel_res:.1e} <= {AUTO_EXACT:g})"
    else:
        kept = {k: v.detach().clone() for k, v in model.state_dict().items()}
        model.load_state_dict(start)
        second = _fit(model, fields, trace, ridge, nsites, settings, symmetries)
        scores[trace.name] = second.rel_res
        better, why = _trace_better(first, second)
        wall = first.wall_time + second.wall_time
        if better:
            return replace(second, wall_time=wall, gauge_requested="auto", gauge_scores=scores, gauge_choice=why)
        model.load_state_dict(kept)
        return replace(first, wall_time=wall, gauge_requested="auto", gauge_scores=scores, gauge_choice=why)
    return replace(first, gauge_requested="auto", gauge_scores=scores, gauge_choice=why)


def _trace_better(first: LearnReport, second: LearnReport) -> tuple[bool, str]:
    """Whether the trace fit ``second`` is chosen over the unit-mass fit ``first`` (:data:`AUTO_RULE`), and why."""
    if second.rel_res < AUTO_FACTOR * first.rel_res and second.hessian_min_sv >= AUTO_MIN_SV:
        return True, f"trace: rel_res {second.rel_res:.2e} against unit-mass {first.rel_res:.2e}"
    return False, (
        f"unit-mass: trace is not better by the factor {1 / AUTO_FACTOR:g} with an invertible M "
        f"(rel_res {second.rel_res:.2e} against {first.rel_res:.2e}, min sv {second.hessian_min_sv:.2e})"
    )


def _learn_auto_sparse(
    model: SparseLagrangian,
    fields: TrainingData,
    ridge: float | str,
    nsites: int,
    settings: Training,
    symmetries: bool = False,
) -> LearnReport:
    """``gauge="auto"`` for a sparse model of several components: the rule of :data:`AUTO_RULE` applied to the
    dense fits of its whole library (threshold 0, no bags: one solve each), then one sparse fit in the gauge
    chosen. The choice is made before the support is: a support is then chosen (by held-out serving, for
    ``threshold = "auto"``) only once, in a gauge the library can meet (a magnetic term ``q x Dq`` has an
    antisymmetric mixed Hessian, which unit-mass cannot hold; a double pendulum's mass is not the identity)."""
    unit_mass, trace = gauge_named(GaugeName.UNIT_MASS), gauge_named(GaugeName.TRACE)
    probes: list[LearnReport] = []
    shared: dict[str, Any] = {}  # the rows and the mean mixed Hessian, computed once for the three fits
    for gauge in (unit_mass, trace):
        probe = copy.deepcopy(model)
        probe.threshold, probe.bags = 0.0, 0
        probes.append(_fit(probe, fields, gauge, ridge, nsites, settings, shared=shared))
        if probes[0].rel_res <= AUTO_EXACT or model.unit_mass_by_construction:
            break
    scores = {g.name: p.rel_res for g, p in zip((unit_mass, trace), probes)}
    if model.unit_mass_by_construction:
        better, why = False, "the model has a unit mass by construction"
    elif len(probes) == 1:
        better, why = False, f"unit-mass fits to round-off (rel_res {probes[0].rel_res:.1e} <= {AUTO_EXACT:g})"
    else:
        better, why = _trace_better(*probes)
    report = _fit(model, fields, trace if better else unit_mass, ridge, nsites, settings, symmetries, shared)
    wall = report.wall_time + sum(p.wall_time for p in probes)
    return replace(
        report,
        wall_time=wall,
        gauge_requested="auto",
        gauge_scores=scores,
        gauge_choice=f"{why}, for the dense fits of the library",
    )
