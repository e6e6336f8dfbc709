"""Serving with an output cadence: a rolling window of slices, every ``every``-th slice kept.

``serve(..., every=k)`` keeps in memory only the slices the stencil needs (a
window of a few slices, refilled chunk by chunk) and the kept slices ``t = 0,
k, 2k, ...`` and the last one. Each slice is solved by the same arithmetic as
the whole-field driver (``_field``): the affine recurrence chunk by chunk with
the same residual test, then slice-Newton (or the sweep) from the first slice
that fails it, so the kept slices equal the whole field's. The Dirichlet
strips are copied into the window slice by slice from the input field (read
block by block from its file when it was opened lazily: :func:`lazy_field`). The
extrapolation record (``ServeResult.extrapolation``) covers every slice served.

A callback ``on_slice(index, values)`` sees each kept slice as it is served; an
object that also has a method ``on_block(start, block)`` sees every slice, as
DataArrays of consecutive slices starting at slice ``start`` (the pipeline's
error and invariant meters).
"""

from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import math
import sys
import time
from collections.abc import Callable
from typing import Any

import numpy as np
import torch
import xarray as xr

from .._lattice import LatticeField, as_lattice_field
from .._layout import validate_field
from .._models import AbstractLagrangian
from .._options import option
from ._affine import _AffineSlices, _slice_residuals, affine_recurrence, passing_slices
from ._checkpoint import keep_factored, restore_stream, stream_state
from ._edges import known_slices, require_edges
from ._options import Cadence, ServeOptions, kept_slices
from ._range import EXTRAPOLATION_TOL, _excess, extrapolation_warning, feature_labels
from ._result import ServeResult
from ._slices import _SliceSystem
from ._stepper import SteppedRun, served_where, step_slices

__all__ = ["kept_slices", "thin_result", "SliceSource", "lazy_field"]

_MIN_CHUNK = 4
#: Memory handed back to the system (``malloc_trim``) after this many bytes of slices served.
_TRIM_BYTES = 128 * 2**20

SliceCallback = Callable[[int, np.ndarray], Any]


def _trim() -> None:
    """Hand freed heap memory back to the system (glibc ``malloc_trim``), so that the RSS stays flat."""
    if not sys.platform.startswith("linux"):
        return
    with contextlib.suppress(OSError, AttributeError):  # not glibc: nothing to trim
        ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6").malloc_trim(0)


def _with_slice_coord(da: xr.DataArray, idx: np.ndarray, every: int) -> xr.DataArray:
    """``da`` (its slices are slices ``idx`` of the served field) with the coordinate ``slice(t)``."""
    tdim = da.dims[0]
    da = da.assign_coords(slice=(tdim, np.asarray(idx, dtype=np.int64), {"long_name": "time slice index"}))
    da.attrs["latticedft_every"] = int(every)
    return da


def thin_result(result: ServeResult, cadence: Cadence, on_slice: SliceCallback | None) -> ServeResult:
    """A whole-field result thinned to its kept slices (1D serving, where the whole field is small)."""
    da = result.field
    tdim = da.dims[0]
    n = da.sizes[tdim]
    block = getattr(on_slice, "on_block", None)
    if block is not None:
        block(0, da)
    idx = cadence.kept(n)
    if on_slice is not None:
        for k in idx:
            on_slice(int(k), np.asarray(da.values[k]))
    result.field = _with_slice_coord(da.isel({tdim: idx}), idx, cadence.every)
    return result


class SliceSource:
    """The slices of an input field left in its file (a DataArray opened lazily), read block by block.

    ``source(a, b)`` is slices ``a .. b - 1`` as ``f.values[a:b]`` would hold them (float64, the component
    axis last); ``nt`` the slices the file holds.
    """

    def __init__(self, da: xr.DataArray, has_comp: bool):
        self.da, self.tdim, self.has_comp = da, da.dims[0], has_comp
        self.nt = int(da.sizes[self.tdim])

    def __call__(self, a: int, b: int) -> torch.Tensor:
        v = np.asarray(self.da.isel({self.tdim: slice(a, b)}).values, dtype=np.float64)
        return torch.from_numpy(np.ascontiguousarray(v if self.has_comp else v[..., None]))


def lazy_field(da: xr.DataArray, source: str, boundary: Any) -> tuple[LatticeField, SliceSource]:
    """A lazily opened ``da`` as the field of its first two slices and the source of the others.

    ``da`` is validated as :func:`as_lattice_field` does (its NaN/inf scan reads blocks of slices); only the
    first two slices are loaded.
    """
    validate_field(da, source)
    tdim = da.dims[0]
    head = as_lattice_field(da.isel({tdim: slice(0, 2)}).compute(), source=source, boundary=boundary, min_slices=2)
    return head, SliceSource(da, head.components is not None)


class _Stream(SteppedRun):
    """One n-D field served through a rolling window; the kept slices collected in one preallocated array."""

    def __init__(
        self,
        model: AbstractLagrangian,
        f: LatticeField,
        steps: int,
        options: ServeOptions,
        on_slice: SliceCallback | None,
        source: SliceSource | None = None,
    ):
        self.source = source  # the input's slices left in its file (then ``f`` holds the first two)
        self.on_slice = on_slice
        self.on_block = getattr(on_slice, "on_block", None)
        self.every = every = options.every
        self.nt = nt = f.shape[0] if source is None else source.nt
        self.boundary_value = options.boundary_value
        require_edges(f, nt, steps, self.boundary_value)
        self.sys = sys_ = _SliceSystem(model, f)
        m = f.ncomp
        slice_bytes = sys_.nsite * m * 8
        self.chunk = max(_MIN_CHUNK, option("serve_window_bytes") // max(slice_bytes, 1))
        self.chunk = max(1, min(self.chunk, steps - 2, options.checkpoint or steps))
        self.buf = torch.full((self.chunk + 2, *f.shape[1:], m), math.nan, dtype=torch.float64)
        self.flat = self.buf.reshape(self.chunk + 2, sys_.nsite, m)
        known = np.ones(sys_.nsite, dtype=bool)
        known[sys_.interior] = False
        self.kidx = torch.from_numpy(np.nonzero(known)[0]) if known.any() else None
        self.unk = torch.from_numpy(np.nonzero(sys_.interior)[0])
        self.kept = options.cadence.kept(steps)
        self.kept_values = np.empty((len(self.kept), *f.shape[1:], m))
        self.nkept = 0
        rng = model.trained_range()
        self.rng = rng.to(torch.float64) if rng is not None and tuple(rng.shape[1:]) == (f.ndim + 1, m) else None
        self.per_anchor = np.zeros((steps - 1, self.rng[0].numel())) if self.rng is not None else None
        self.done = 0  # slices handed out (0 .. done - 1)
        self.trimmed = 0
        self.slice_bytes = slice_bytes
        # ``base``: the slice held at buffer position 0; ``before``: the one before it (Newton's predictor)
        where = served_where(options.device)  # where the slice solves run (``_stepper.on_device``)
        super().__init__(model, f, steps, options.mode, options.solver, where, options.progress, f", every {every}")
        self.buf[:2] = f.values[:2]

    @property
    def values(self) -> torch.Tensor:
        """The window's slices, ``(chunk + 2, *spatial, m)``."""
        return self.buf

    # -- the window ------------------------------------------------------------------------------------------
    def fill(self, n_new: int) -> None:
        """Positions ``2 .. n_new + 1``: NaN, with the known (Dirichlet) sites copied from the input, slice by slice."""
        self.flat[2 : n_new + 2] = math.nan
        if self.kidx is None:
            return
        m = self.f.ncomp
        lo = self.base + 2
        data = self.source if self.source is not None else lambda a, b: self.f.values[a:b]
        known = known_slices(self.f, data, self.nt, self.boundary_value, lo, lo + n_new)
        for p in range(2, n_new + 2):
            self.flat[p, self.kidx] = known[p - 2].reshape(self.sys.nsite, m)[self.kidx]

    def emit(self, upto: int) -> None:
        """Hand out the slices up to buffer position ``upto``: extrapolation, callbacks, the kept ones stored."""
        first = self.done - self.base  # the first position not handed out yet
        if upto < first:
            return
        if self.per_anchor is not None and self.rng is not None and upto >= 1:
            lo = max(first - 1, 0)  # anchors lo .. upto - 1 (those before were measured already)
            self.per_anchor[self.base + lo : self.base + upto] = _excess(
                self.model, self.rng, self.f, self.buf[lo : upto + 1]
            )
        if self.on_block is not None:
            block = self.f.with_values(self.buf[first : upto + 1], t0=self.t_of(self.base + first))
            self.on_block(self.base + first, block.to_dataarray())
        for p in range(first, upto + 1):
            g = self.base + p
            if self.nkept < len(self.kept) and self.kept[self.nkept] == g:
                self.kept_values[self.nkept] = self.buf[p].numpy()
                if self.on_slice is not None:
                    v = self.kept_values[self.nkept]
                    self.on_slice(g, v[..., 0] if self.f.components is None else v)
                self.nkept += 1
        self.done = self.base + upto + 1
        if (self.done * self.slice_bytes) // _TRIM_BYTES > self.trimmed:
            self.trimmed = (self.done * self.slice_bytes) // _TRIM_BYTES
            _trim()

    def t_of(self, g: int) -> float:
        """The time coordinate of slice ``g`` (as the whole-field driver computes it)."""
        t0 = float(self.f.coords[self.f.dims[0]][0])
        return float((t0 + self.f.spacing[0] * np.arange(g + 1, dtype=np.float64))[g])

    # -- solving ---------------------------------------------------------------------------------------------
    def affine_setup(self) -> tuple[_AffineSlices, float] | None:
        """The affine recurrence and the mixed Hessian's scale, when the DEL is affine (:func:`affine_recurrence`,
        as the whole field's). A window serves one model (an ensemble is served whole), so the scale is one number."""
        found = affine_recurrence(self.model, self.f, self.sys)
        return None if found is None else (found[0], float(np.max(found[1])))

    def affine_chunk(self, op: _AffineSlices, n_new: int, rtol: float) -> int:
        """Serve positions ``2 .. n_new + 1`` by the affine recurrence; how many leading ones pass the DEL test
        (:func:`passing_slices`, as the whole field's)."""
        w = n_new + 2
        v = self.flat[:w].reshape(w, -1).numpy()
        op.run(v, 1, n_new + 1)
        res = _slice_residuals(self.model, self.f, self.buf[:w], 1, n_new + 1)
        k, worst = passing_slices(v, res, rtol * self.vol * op.dmax)
        if k:
            self.worst = max(self.worst, worst)
        return k

    # -- the result ------------------------------------------------------------------------------------------
    def result(self, nt: int, complete: bool, reason: str, rate: float, residual: float) -> ServeResult:
        """The result over the ``nt`` slices served: the kept ones (the last slice among them)."""
        n = self.nkept
        idx = self.kept[:n]
        values = self.kept_values[:n]
        if n and idx[-1] != nt - 1:  # stopped early: the last slice served is kept too
            last = self.buf[nt - 1 - self.base].numpy()[None]
            idx, values = np.append(idx, nt - 1), np.concatenate([values, last])
        f = self.f
        da = f.with_values(torch.from_numpy(values)).to_dataarray()
        tdim = f.dims[0]
        t_all = f.coords[tdim][0] + f.spacing[0] * np.arange(nt, dtype=np.float64)
        da = da.assign_coords({tdim: (tdim, t_all[idx], dict(da[tdim].attrs))})
        da = _with_slice_coord(da, idx, self.every)
        ext = None
        if self.per_anchor is not None and nt >= 2:
            per_slice = np.zeros((nt, self.per_anchor.shape[1]))
            per_slice[:-1] = self.per_anchor[: nt - 1]
            per_slice[1:] = np.maximum(per_slice[1:], self.per_anchor[: nt - 1])
            ext = xr.DataArray(
                per_slice,
                dims=(tdim, "feature"),
                coords={tdim: t_all, "feature": feature_labels(self.model, f.dims, f.components)},
                name="extrapolation",
                attrs={
                    "long_name": "excess of the stencil inputs beyond the training range, relative to its span",
                    "tolerance": EXTRAPOLATION_TOL,
                },
            )
        warning = extrapolation_warning(ext)
        return ServeResult(
            field=da,
            complete=complete,
            reason=reason,
            slices=nt,
            wall_time=time.perf_counter() - self.t0,
            sites_per_second=rate,
            max_residual=residual,
            extrapolation=ext,
            warnings=[warning] if warning else [],
            **self.counts(),
        )

    def partial(self, p: int, msg: str, res: float) -> ServeResult:
        """The result of a run stopped by position ``p``'s equations: the kept slices up to there."""
        i = self.base + p
        self.emit(p)
        return self.result(i + 1, False, msg, self.timed(i + 1)[1], res)


def _serve_stream(
    model: AbstractLagrangian,
    f: LatticeField,
    steps: int,
    options: ServeOptions,
    on_slice: SliceCallback | None,
    source: SliceSource | None = None,
) -> ServeResult:
    """Serve one n-D field through a rolling window, keeping the slices of ``options.cadence`` (the input's
    later slices read from ``source`` when ``f`` holds its first two only)."""
    mode, rtol, max_newton = options.mode, options.rtol, options.max_newton
    run = _Stream(model, f, steps, options, on_slice, source)
    setup = run.affine_setup() if mode == "newton" and options.affine and steps > 2 else None
    on_affine = setup is not None
    saver = getattr(on_slice, "checkpointer", None) if options.checkpoint else None
    if saver is not None:
        keep_factored(run.cache)
        state = saver.load()
        on_affine = restore_stream(run, state) if state is not None else on_affine
    saved = run.base
    g_prev: torch.Tensor | None = None  # the first Newton slice evaluates them (the folded kernels where they serve)
    run.emit(1)
    while run.base + 2 < steps:
        n_new = min(run.chunk, steps - run.base - 2)
        run.fill(n_new)
        start = 1  # the first position whose equations Newton (or the sweep) solves
        if setup is not None and on_affine:
            op, mscale = setup
            k = run.affine_chunk(op, n_new, rtol)
            run.affine_slices += k
            run.bar.update(k)
            start = 1 + k
            if k < n_new:  # Newton takes over from the first slice the recurrence fails
                on_affine = False
                if run.affine_slices:
                    run.count_affine()
                    run.cache["dmax"], run.cache["mscale"] = op.dmax, mscale
                g_prev = None
        g_prev = step_slices(run, start, n_new + 1, g_prev, rtol, max_newton)
        run.emit(n_new + 1)
        if run.base + n_new + 2 >= steps:
            break
        run.before = run.flat[n_new - 1].clone()
        run.buf[:2] = run.buf[n_new : n_new + 2].clone()
        run.base += n_new
        if saver is not None and run.base - saved >= (options.checkpoint or 0):
            saver.save(stream_state(run, on_affine))
            saved = run.base
    run.bar.close()
    _, rate = run.timed(steps)
    if on_affine and run.affine_slices:
        run.count_affine()
    return run.result(steps, True, "complete", rate, run.worst)
