"""The public :func:`learn`: check the arguments, bind the model, run the exact solve or training, report."""

from __future__ import annotations

import os
import time
from collections.abc import Sequence

import xarray as xr

from .._errors import InputError
from .._lattice import BoundaryKinds
from .._models import AbstractLagrangian, LinearLagrangian
from ._exact import learn_exact
from ._gauge import Gauge, gauge_named
from ._neural import Training, learn_neural
from ._report import LearnReport
from ._stream import training_data

__all__ = ["learn"]

#: Optimizers: ``exact`` (linear models), ``lbfgs`` and ``adam`` (neural models).
OPTIMIZERS = ("exact", "lbfgs", "adam")


def _checked(
    model: AbstractLagrangian, gauge: str, ridge: float | str, optimizer: str | None, max_iter: int
) -> tuple[Gauge, str]:
    """The gauge and the optimizer (its default filled in), or an InputError naming the bad argument."""
    fix = gauge_named(gauge)
    if not isinstance(model, AbstractLagrangian):
        raise InputError(f"model: expected a latticedft model, got {type(model).__name__}")
    optimizer = optimizer or ("exact" if isinstance(model, LinearLagrangian) else "lbfgs")
    if optimizer not in OPTIMIZERS:
        raise InputError.at("optimizer", f"expected 'exact', 'lbfgs' or 'adam', got {optimizer!r}")
    if optimizer == "exact" and not isinstance(model, LinearLagrangian):
        raise InputError.at("optimizer", f"'exact' needs a model linear in its parameters; {model.kind!r} is not")
    if not (ridge == "auto" or (isinstance(ridge, (int, float)) and not isinstance(ridge, bool) and ridge >= 0)):
        raise InputError.at("ridge", f"expected a number >= 0 or 'auto', got {ridge!r}")
    if not isinstance(max_iter, int) or max_iter < 1:
        raise InputError.at("max_iter", f"expected a positive integer, got {max_iter!r}")
    return fix, optimizer


def learn(
    model: AbstractLagrangian,
    data: xr.DataArray | str | os.PathLike[str] | Sequence[xr.DataArray | str | os.PathLike[str]],
    *,
    gauge: str = "unit-mass",
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
    chunk_sites: int | None = None,
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
    gauge : "unit-mass", "trace" or "none"
        How the gauge is fixed (see :data:`GAUGES`). ``none`` shows the
        collapse the loss alone leads to.
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
    chunk_sites : int, optional
        Training streams the data in chunks of about this many lattice sites,
        so memory does not grow with the data (default: from the model's
        size); ``0`` holds and processes all data at once (in memory). Under
        an initialised ``torch.distributed`` process group every process
        reads its share of the chunks and all end with the same model.

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
    fields = training_data(data, boundary, chunk_sites)
    nsites = fields.bind(model)
    t0 = time.perf_counter()
    history: list[tuple[int, float, float]] = []
    initial = None
    validation: dict[str, float] = {}
    used_ridge = 0.0
    if optimizer == "exact" and isinstance(model, LinearLagrangian):  # _checked refuses 'exact' for others
        used_ridge, validation = learn_exact(model, fields, fix, ridge, nsites)
        iterations, reason = 1, "exact solve"
    else:
        settings = Training(
            optimizer=optimizer,
            max_iter=max_iter,
            max_time=max_time,
            tol=tol,
            rel_tol=rel_tol,
            lr=lr,
            penalty=penalty,
            progress=progress,
        )
        iterations, history, initial, reason = learn_neural(model, fields, fix, nsites, settings)
    wall = time.perf_counter() - t0
    diag = fields.diagnose(model, gauge)
    report = LearnReport(
        method=optimizer,
        loss=diag["loss"],
        rel_res=diag["rel_res"],
        iterations=iterations,
        wall_time=wall,
        gauge=gauge,
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
    )
    model.report_ = report
    return report
