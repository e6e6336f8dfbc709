"""Serving a learned theory: fill a lattice slice by slice by solving the DEL.

On slice ``i`` every interior site ``y`` gives one equation ``EL_y = 0`` for
the values on slice ``i + 1``. ``mode="newton"`` solves a whole slice by
Newton's method with the sparse (block lower-triangular for the first-order
stencil) Jacobian assembled from per-cell Hessian blocks; ``mode="sweep"`` is
the paper's site-by-site sweep (Qin 2020, Sec. 2, Steps 1-5), kept as a
reference. In 1D a slice is one site and a batch of trajectories is stepped
together.

One module per concept: ``_options`` (the serving options and the output cadence, as values),
``_result`` (the result record and metrics),
``_slices`` (one slice as a system of equations), ``_affine`` (the affine
recurrence of a quadratic ``L_d``), ``_newton`` (slice-Newton), ``_solvers`` (the linear
solve of a Newton step: site-wise, Krylov or LU), ``_sweep``
(the site-by-site sweep), ``_batch`` (1D trajectories), ``_fast1d`` (the
same 1D loop in numpy, for models with numpy closed forms) and ``_field``
(the n-D driver).
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass
from typing import Any, overload

import torch
import xarray as xr

from .._action import check_model_lattice as _check_model_lattice
from .._boundary import BoundaryKinds
from .._device import device_label, on_device, resolve_device
from .._errors import InputError, ServeError
from .._lattice import LatticeField, as_lattice_fields
from .._layout import is_lazy, lattice_dims
from .._models import AbstractLagrangian, EnsembleLagrangian
from ._ensemble import calibration, serve_ensemble, serves_alone
from ._field import _serve_field
from ._onedim import _serve_batch
from ._options import MODES, Cadence, ServeOptions
from ._result import ServeResult, compare, error_vs_time, invariant_vs_time, served_source
from ._solvers import SOLVERS
from ._stream import SliceCallback, SliceSource, _serve_stream, lazy_field, thin_result

__all__ = [
    "MODES",
    "SOLVERS",
    "Cadence",
    "ServeOptions",
    "ServeResult",
    "calibration",
    "compare",
    "error_vs_time",
    "invariant_vs_time",
    "serve",
]


def _prepare_model(model: AbstractLagrangian, f: LatticeField) -> None:
    """Check that ``model`` can serve on ``f``'s lattice (binding an analytic model to it)."""
    if not isinstance(model, AbstractLagrangian):
        raise InputError(f"model: expected a latticedft model, got {type(model).__name__}")
    if model.rebinds_to_any_lattice:
        model.bind(f.ndim, f.ncomp, f.spacing, f.components)  # a formula in h: valid on any lattice
    if not model.bound:
        raise InputError(f"model: {type(model).__name__} has not been learned yet (latticedft.learn)")
    _check_model_lattice(model, f, "init")


def _in_file(init: Any) -> bool:
    """``init`` is an n-D DataArray whose values are left in its file (opened lazily: ``read_field(lazy=True)``,
    or dask-backed)."""
    return isinstance(init, xr.DataArray) and is_lazy(init) and len(lattice_dims(init)) > 1


def _slices(slices: int | None, f: LatticeField, key: str = "slices") -> int:
    """The number of time slices to serve: ``slices``, or by default as many as ``f`` holds."""
    if slices is None:
        return f.shape[0]
    if not isinstance(slices, int) or isinstance(slices, bool) or slices < 3:
        raise InputError.at(
            key,
            f"expected an integer >= 3 (time slices of the served field, the two initial ones included), "
            f"got {slices!r}",
        )
    return slices


def _served_attrs(results: list[ServeResult], model: AbstractLagrangian) -> None:
    """A served field is not the data it started from: the input's ``source`` attribute (how the initial
    data were made) moves to ``latticedft_initial_from`` and ``source`` says what made the field."""
    for r in results:
        attrs = r.field.attrs
        if "source" in attrs:
            attrs["latticedft_initial_from"] = attrs.pop("source")
        attrs["source"] = served_source(model.kind)


def _served_on(results: list[ServeResult], where: torch.device) -> None:
    """Record where the model was evaluated in each result."""
    for r in results:
        r.device = device_label(where)


@overload
def serve(
    model: AbstractLagrangian,
    init: xr.DataArray,
    *,
    slices: int | None = None,
    boundary: BoundaryKinds | None = None,
    options: ServeOptions | None = None,
    on_slice: SliceCallback | None = None,
    steps: int | None = None,
    **keywords: Any,
) -> ServeResult: ...


@overload
def serve(
    model: AbstractLagrangian,
    init: list[xr.DataArray] | tuple[xr.DataArray, ...],
    *,
    slices: int | None = None,
    boundary: BoundaryKinds | None = None,
    options: ServeOptions | None = None,
    on_slice: SliceCallback | None = None,
    steps: int | None = None,
    **keywords: Any,
) -> list[ServeResult]: ...


def serve(
    model: AbstractLagrangian,
    init: xr.DataArray | list[xr.DataArray] | tuple[xr.DataArray, ...],
    *,
    slices: int | None = None,
    boundary: BoundaryKinds | None = None,
    options: ServeOptions | None = None,
    on_slice: SliceCallback | None = None,
    steps: int | None = None,
    **keywords: Any,
) -> ServeResult | list[ServeResult]:
    """Predict a field from its first two time slices (and boundary strips) with the learned ``L_d``.

    Parameters
    ----------
    model : AbstractLagrangian
        A learned (or analytic) model.
    init : DataArray, or a list of 1D DataArrays
        The first two time slices, and for Dirichlet axes the boundary strips
        on every slice to serve (so usually the whole reference field). A
        list of 1D fields is served as one batch. An n-D field opened lazily
        (``io.read_field(path, lazy=True)``) and served with ``every > 1`` (or
        ``on_slice``) stays in its file: its first two slices are loaded and
        the strips read block by block as the window advances.
    slices : int, optional
        Number of time slices of the served field, the two initial ones
        included (default: the length of ``init`` along time): ``N`` time
        steps from ``t_0`` are ``slices = N + 1``.
    boundary : "dirichlet", "periodic" or dict axis -> kind, optional
        Per spatial axis; default from the coordinates' ``periodic`` attribute,
        else Dirichlet.
    options : ServeOptions, optional
        The serving options as one value; keywords given beside it replace its fields.
    mode, rtol, max_newton, box, affine, progress, device, solver, every
        The fields of :class:`ServeOptions`, as keywords (defaults there):

        - ``mode``: ``"newton"`` (whole-slice Newton, fast) or ``"sweep"``
          (the paper's site-by-site sweep, reference).
        - ``rtol`` (``1e-10``): Newton stops when the residual is below
          ``rtol`` times the size of the kinetic terms; ``max_newton``
          (``30``): Newton iterations per slice.
        - ``box``: 1D only, a trajectory stops (completed) once ``|psi| > box``.
        - ``affine`` (``True``): n-D ``mode="newton"`` only. When the DEL is
          affine in the field (a quadratic ``L_d`` such as the wave or
          Klein-Gordon ``L_d``: detected from the model's Hessian and gradient
          at random states), serve the affine recurrence
          ``P psi_{i-1} + C psi_i + N psi_{i+1} + c = 0`` with ``N``
          factorised once: one sparse solve per slice instead of Newton's
          autograd passes. The served field is then checked against the
          model's own DEL (the same residual test as Newton's); from the first
          slice that fails it, Newton takes over. ``False``: always Newton.
        - ``progress``: progress bar; ``None`` shows it only on a terminal.
        - ``device``: ``"cpu"``, ``"cuda"``, ``"cuda:N"`` or ``"auto"``,
          where the model is evaluated (``L_d``, its gradients and Hessian
          blocks on the cells of each slice): default the CPU; ``"auto"`` is
          CUDA when available. The slice's linear algebra stays on the CPU.
          CUDA where none is available falls back to the CPU with one
          :class:`DeviceWarning`. ``result.device`` names the device used.
        - ``solver``: ``"auto"``, ``"sitewise"``, ``"krylov"`` or ``"lu"``,
          n-D ``mode="newton"`` only: the linear solve of each Newton step.
          ``"sitewise"`` inverts the Jacobian's per-site ``m x m`` diagonal
          blocks (exact when each unknown site appears in one equation, as for
          the first-order stencil with an ``L_d`` whose spatial differences do
          not mix with the time difference; off-diagonal blocks up to 1e-6 of
          the diagonal make it a quasi-Newton iteration, larger ones stop the
          slice with a ``ServeError`` saying so); ``"krylov"`` runs GMRES
          preconditioned by those blocks; ``"lu"`` factorises the sparse
          Jacobian. ``"auto"`` measures the off-diagonal blocks of each fresh
          Jacobian: site-wise when they vanish, else LU in 1+1D and Krylov in
          more dimensions. Newton's convergence test is the same for all.
          ``ServeResult.slice_solver`` says which one served.
        - ``every`` (``1``): output cadence, keep only the time slices
          ``0, every, 2 every, ...`` and the last one. For ``every > 1`` an
          n-D field is served through a rolling window of a few slices (memory
          bounded in the number of slices); the result's field holds the kept
          slices with their ``t`` values, a coordinate ``slice(t)`` (the slice
          index) and the attribute ``latticedft_every``; its ``extrapolation``
          covers every slice. The kept slices equal those of ``every=1``.
    on_slice : callable, optional
        ``on_slice(index, values)``, called with each kept slice (its index and
        a NumPy array in the field's layout without time) as it is served.
    steps : int, optional
        Deprecated alias of ``slices`` (the same count; a ``FutureWarning``).

    Returns
    -------
    ServeResult, or a list of them for a list ``init``.

    Raises
    ------
    ServeError
        When Newton fails; the message names the slice, site and residual,
        and ``err.result`` holds what was solved.

    Examples
    --------
    Störmer–Verlet for the harmonic oscillator, served from its Lagrangian:

    >>> import numpy as np, xarray as xr, latticedft as ldft
    >>> osc = ldft.lagrangians.verlet(lambda q: 0.5 * q ** 2)
    >>> t = np.arange(2) * 0.1
    >>> init = xr.DataArray([1.0, np.cos(0.1)], dims="t", coords={"t": t}, name="psi")
    >>> out = ldft.serve(osc, init, slices=64)
    >>> out.complete, out.field.sizes["t"]
    (True, 64)
    """
    slices = _deprecated_steps(slices, steps)
    opts = ServeOptions.from_keywords(options, **keywords)
    where = resolve_device(opts.device)
    if on_slice is not None and not callable(on_slice):
        raise InputError.at("on_slice", f"expected a function on_slice(index, values), got {type(on_slice).__name__}")
    batch = isinstance(init, (list, tuple))
    fs, sources = _fields(init, boundary, opts.cadence.streams(on_slice))
    _prepare_model(model, fs[0])
    for k, f in enumerate(fs):
        _check_model_lattice(model, f, "init" if not batch else f"init[{k}]")
    plan = _Plan(batch=batch, slices=slices, options=opts, where=where, on_slice=on_slice, sources=sources)
    if isinstance(model, EnsembleLagrangian):
        if opts.checkpoint is not None:
            raise InputError.at("checkpoint", "an ensemble is served whole, without checkpoints: remove checkpoint")
        if opts.cadence.streams(on_slice):
            raise InputError.at(
                "every", "an ensemble is served whole (every member on every slice): give every=1 and no on_slice"
            )
        alone = serves_alone(model, fs, opts, where)
        out = serve_ensemble(model, fs, plan.run, batch, opts.box, alone)
    else:
        out = plan.run(model, fs)
    return out if batch else out[0]


def _deprecated_steps(slices: int | None, steps: int | None) -> int | None:
    """``slices``, or its deprecated alias ``steps`` (with a FutureWarning)."""
    if steps is None:
        return slices
    if slices is not None:
        raise InputError.at("steps", "give slices only (steps is its deprecated alias)")
    warnings.warn(
        "serve(slices=...) is deprecated: use slices=... (the same count: time slices served, "
        "the two initial ones included)",
        FutureWarning,
        stacklevel=3,
    )
    return steps


def _fields(
    init: xr.DataArray | list[xr.DataArray] | tuple[xr.DataArray, ...], boundary: BoundaryKinds | None, streams: bool
) -> tuple[list[LatticeField], list[SliceSource | None]]:
    """The checked fields of ``init`` and, for an n-D field left in its file and served through a rolling
    window (``streams``), the source its later slices are read from."""
    batch = isinstance(init, (list, tuple))
    items = list(init) if isinstance(init, (list, tuple)) else [init]
    if not items:
        raise InputError("init: no initial fields given")
    sources: list[SliceSource | None] = [None] * len(items)
    if not batch and streams and _in_file(items[0]):  # read slice by slice
        head, sources[0] = lazy_field(items[0], "init", boundary)
        return [head], sources
    names = [f"init[{k}]" for k in range(len(items))] if batch else ["init"]
    return as_lattice_fields(items, names, boundary=boundary, min_slices=2), sources  # one pass over a batch


@dataclass(frozen=True)
class _Plan:
    """What a serving run needs besides the model and the fields: the checked options and where to run."""

    batch: bool
    slices: int | None
    options: ServeOptions
    where: torch.device
    on_slice: SliceCallback | None
    sources: list[SliceSource | None]

    def run(self, model: AbstractLagrangian, fs: list[LatticeField]) -> list[ServeResult]:
        """Serve the checked fields ``fs`` with ``model``; a ServeError (``result`` a list for a ``batch``)
        when one stops, an InputError naming ``slices`` when the served field cannot be allocated."""
        try:
            return self._run(model, fs)
        except (MemoryError, RuntimeError) as exc:
            if isinstance(exc, RuntimeError) and "allocate" not in str(exc):
                raise
            n = max(_slices(self.slices, f) for f in fs)
            values = n * max(math.prod(f.shape[1:]) for f in fs) * len(fs)
            raise InputError.at(
                "slices",
                f"{n} slices of {values // n} values cannot be held in memory (about {8 * values / 2**30:.3g} GiB "
                "for the served field alone); serve fewer slices",
            ) from None

    def _run(self, model: AbstractLagrangian, fs: list[LatticeField]) -> list[ServeResult]:
        if fs[0].ndim == 1:
            return self._run_1d(model, fs)
        if self.options.box is not None:
            raise InputError("box: stopping when leaving a box is for 1D trajectories only")
        out: list[ServeResult] = []
        for f, src in zip(fs, self.sources if len(self.sources) == len(fs) else [None] * len(fs)):
            try:
                n_f = _slices(self.slices, f) if self.slices is not None or src is None else src.nt
                options = self.options.replace(device=str(self.where))  # checked, its fallback said once
                with on_device(model, self.where):
                    if options.cadence.streams(self.on_slice):
                        out.append(_serve_stream(model, f, n_f, options, self.on_slice, src))
                    else:
                        out.append(_serve_field(model, f, n_f, options))
            except ServeError as err:
                if isinstance(err.result, ServeResult):
                    _served_attrs([err.result], model)
                    _served_on([err.result], self.where)
                raise
        _served_attrs(out, model)
        _served_on(out, self.where)
        return out

    def _run_1d(self, model: AbstractLagrangian, fs: list[LatticeField]) -> list[ServeResult]:
        """A batch of 1D trajectories, stepped together (thinned to the kept slices afterwards)."""
        if self.options.checkpoint is not None:
            raise InputError.at("checkpoint", "a 1D field is served whole, without checkpoints: remove checkpoint")
        with on_device(model, self.where):
            results = _serve_batch(model, fs, [_slices(self.slices, f) for f in fs], self.options)
        _served_attrs(results, model)
        _served_on(results, self.where)
        if self.options.cadence.streams(self.on_slice):
            results = [thin_result(r, self.options.cadence, self.on_slice) for r in results]
        failed = [(r, r.fail_at) for r in results if r.fail_at is not None]  # the members not complete
        if failed:
            first, (at_slice, res) = failed[0]
            raise ServeError(first.reason, result=results if self.batch else first, slice=at_slice, residual=res)
        return results
