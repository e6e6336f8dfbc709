"""1D serving in numpy: the batched Newton loop of ``_batch`` for models with numpy closed forms.

A 1D step solves a handful of ``m x m`` systems, where a torch call per operation costs far more than the
arithmetic. A linear model that offers :meth:`LinearLagrangian.numpy_derivatives` (the polynomial and the sparse
model do), and an ensemble of such models stacked as components, is served here: the same Newton iteration as
:meth:`_Batch.newton` (predictor, backtracking, the same convergence, conditioning and non-convergence tests,
in the same order), on numpy arrays that share memory with the batch's torch tensors, so the results, reports
and partial fields are built exactly as before.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np
import torch
import xarray as xr

from .._action import compiled_closed_forms, serving_pairs
from .._contract import NumpyForms
from .._kernel import CompiledForms
from .._lattice import LatticeField
from .._models import AbstractLagrangian
from .._options import option
from ._batch import _Batch
from ._range import assess_batch
from ._result import ServeResult
from ._slices import SINGULAR_RTOL
from ._stepper import Stepping, step_members

__all__ = ["numpy_derivatives_of", "FastBatch", "serve_fast", "step_fast"]


def numpy_derivatives_of(model: AbstractLagrangian) -> NumpyForms | None:
    """The model's numpy closed forms for the pair ``(anchor, forward)`` of a 1D first-order stencil, or
    ``None`` (then the torch loop serves): also for a model whose parameters are not on the CPU. A model
    without numpy closed forms whose closed form compiles serves by its compiled kernel
    (:func:`latticedft._action.compiled_closed_forms`)."""
    if any(t.device.type != "cpu" for t in model.parameters()):  # a model moved to an accelerator stays there
        return None
    st = model.stencil
    if st.ndim != 1 or st.size != 2:
        return None
    if not model.numpy_ready:
        if serving_pairs(st) != [(st.anchor, st.forward)]:
            return None
        compiled = compiled_closed_forms(model, torch.zeros(0, dtype=torch.float64))
        return None if compiled is None else compiled.both
    return model.numpy_derivatives([(st.anchor, st.forward)])


_FLOAT_MAX = float(np.finfo(np.float64).max)


def _fmax(a: float, b: float) -> float:
    """``numpy.maximum`` of two floats (NaN if either is)."""
    return a if a >= b or a != a else b


def _fmin(a: float, b: float) -> float:
    """``numpy.minimum`` of two floats (NaN if either is)."""
    return a if a <= b or a != a else b


def _first(a: np.ndarray) -> np.ndarray:
    return a[:, 0]


def _rowmax(a: np.ndarray) -> np.ndarray:
    return a.max(-1)


@dataclass
class _Step:
    """What Newton made of one slice of the members ``act`` (numpy arrays, one row per member)."""

    act: np.ndarray
    u: np.ndarray
    g: np.ndarray
    rabs: np.ndarray
    ok: np.ndarray
    sing: np.ndarray
    it: int
    smin: np.ndarray


def _solve(jac: np.ndarray, rhs: np.ndarray) -> tuple[np.ndarray, np.ndarray | bool]:
    """``(step, failed)``: ``jac step = rhs`` per member; ``failed`` where the matrix is exactly singular (for
    ``m = 1`` its step is not finite, which the caller tests anyway)."""
    if jac.shape[-1] == 1:
        return rhs / jac[..., 0], False
    try:
        return np.linalg.solve(jac, rhs[..., None])[..., 0], np.zeros(jac.shape[0], dtype=bool)
    except np.linalg.LinAlgError:  # one member's matrix is singular: the others are solved one by one
        step = np.full_like(rhs, math.nan)
        failed = np.ones(jac.shape[0], dtype=bool)
        for j in range(jac.shape[0]):
            try:
                step[j] = np.linalg.solve(jac[j], rhs[j])
                failed[j] = False
            except np.linalg.LinAlgError:
                pass
        return step, failed


class FastBatch(_Batch):
    """:class:`_Batch` with the Newton loop and the bookkeeping of each slice in numpy; one scalar trajectory
    by the compiled ``trajectory`` where :func:`trajectory_kernel` offers it (``kernel``)."""

    def __init__(
        self,
        model: AbstractLagrangian,
        fs: list[LatticeField],
        steps: list[int],
        derivatives: NumpyForms,
        mode: str,
        progress: bool | None,
        numpy_first: bool = False,
    ):
        """``numpy_first``: each member's first gradient from the numpy closed forms ``derivatives`` (equal to
        the torch one of :class:`_Batch` to round-off; the held-out serving of a fit, which serves many short
        windows, each from its own first gradient)."""
        self.kernel = trajectory_kernel(model) if len(fs) == 1 and fs[0].ncomp == 1 else None
        label = ", 1 trajectory, compiled" if self.kernel is not None else None
        super().__init__(model, fs, steps, mode, progress, label, first=not numpy_first)
        self._views()
        self._begin(derivatives, numpy_first)
        #: A stacked ensemble's largest singular value met per trajectory and member (set on its first step).
        self.nmember_mscale: np.ndarray | None = None
        self._progress = progress

    def _begin(self, derivatives: NumpyForms, numpy_first: bool) -> None:
        """The numpy side of the batch starting on its fields: the closed forms ``derivatives``, each member's first
        gradient from them where ``numpy_first``, each member's length and running flag."""
        self.fn = derivatives
        if numpy_first:
            g, _ = derivatives(self.npsi[:, 0:2])
            self.ngprev[:] = g[:, self.a1]
        self.nlength = np.array(self.length, dtype=np.int64)
        self.running = np.ones(len(self.fs), dtype=bool)

    def _views(self) -> None:
        """Numpy views of the batch's tensors: what is written there is what ``results`` reads."""
        self.npsi, self.ngprev = self.psi.numpy(), self.g_prev.numpy()
        self.nworst, self.niters, self.nmax_iters = self.worst.numpy(), self.iters.numpy(), self.max_iters.numpy()
        self.nmscale = self.mscale.numpy()

    def restart(self, fs: list[LatticeField], derivatives: NumpyForms) -> None:
        """Serve ``fs`` (as many fields as the batch holds members, of the same components, each to its own
        length) with the closed forms ``derivatives`` (the model's coefficients may have changed since), each
        member's first gradient from them: the state a new ``FastBatch(model, fs, lengths, derivatives, mode,
        progress, numpy_first=True)`` starts from, without building one (its tensors are reused, grown where a
        field is longer than the batch's). For many short windows served one after another (the held-out
        serving of a sparse fit)."""
        if len(fs) != len(self.fs) or any(f.ncomp != self.m for f in fs):
            raise ValueError("restart: the fields must match the batch's members and components")
        steps = [f.shape[0] for f in fs]
        b, self.fs, self.nmax = len(fs), fs, max(steps)
        if self.nmax > self.psi.shape[1]:
            self.psi = torch.empty((b, self.nmax, self.m), dtype=torch.float64)
            self.npsi = self.psi.numpy()
        self.kernel = trajectory_kernel(self.model) if b == 1 and self.m == 1 else None
        label = ", 1 trajectory, compiled" if self.kernel is not None else f", {b} trajectories"
        self.length, self.reason, self.failed, self.fail_at = list(steps), ["complete"] * b, [False] * b, {}
        for a in (self.nworst, self.niters, self.nmax_iters, self.nmscale):  # views of the tensors
            a[:] = 0
        self.member_mscale = self.nmember_mscale = None
        if self._progress is False:  # the bar is never shown (a disabled bar holds no count): only the clock
            self.steps, self.affine_slices, self.t0 = self.nmax, 0, time.perf_counter()
        else:
            Stepping.__init__(self, self.mode, self.nmax, self._progress, label)
        self.npsi[:, : self.nmax] = math.nan
        for k, f in enumerate(fs):
            self.npsi[k, :2] = f.values.detach()[:2].numpy()
        self._begin(derivatives, True)

    def retire(self, k: int, slices: int, why: str, bad: bool, res: float = math.nan) -> None:
        super().retire(k, slices, why, bad, res)
        self.nlength[k] = slices
        self.running[k] = False

    def assess(self, fields: list[LatticeField]) -> list[tuple[xr.DataArray | None, list[str]]]:
        """The members' training-range excess in one pass over the batch (:func:`assess_batch`)."""
        return assess_batch(self.model, fields, self.psi)

    def active(self, group: np.ndarray, i: int) -> np.ndarray:
        """The members of ``group`` that still have slice ``i + 1`` to solve."""
        return group[self.running[group] & (self.nlength[group] > i + 1)]

    def singular_values(self, jac: np.ndarray) -> np.ndarray:
        """``(n, m)``: the singular values of each member's Jacobian (the mixed Hessian), NaN read as 0."""
        if jac.shape[-1] == 1:
            sv = np.abs(jac.reshape(-1, 1))
            return sv if np.isfinite(sv[:, 0]).all() else np.nan_to_num(sv, nan=0.0)
        bad = ~np.isfinite(jac).all(axis=(-2, -1))
        sv = np.linalg.svd(np.where(bad[:, None, None], 0.0, jac), compute_uv=False)
        sv[bad] = math.nan
        return sv if np.isfinite(sv).all() else np.nan_to_num(sv, nan=0.0)

    def step(self, act: np.ndarray, i: int, rtol: float, max_newton: int) -> _Step:
        """Newton with backtracking for slice ``i + 1`` of the members ``act``: :meth:`_Batch.newton` and its
        its conditioning test, the same tests in the same order, with shortcuts where every member takes
        its full Newton step (no halving, no member stopped). A stacked ensemble's members are solved as rows
        of their own (:meth:`_step_members`)."""
        if self.model.n_members > 1:
            return self._step_members(act, i, rtol, max_newton)
        q_now, q_old = self.npsi[act, i], self.npsi[act, i - 1]
        u, g, rabs, ok, sing, it, smin, mscale, count = self._newton_np(
            q_now, q_old, self.ngprev[act], self.nmscale[act], self.fn, rtol, max_newton, False
        )
        self.nmscale[act] = mscale
        self.niters[act] += count
        return _Step(act, u, g, rabs, ok, sing, it, smin)

    def _step_members(self, act: np.ndarray, i: int, rtol: float, max_newton: int) -> _Step:
        """:meth:`step` of a stacked ensemble (``n_members`` models side by side, never coupled): every member of
        every trajectory is a row of its own, judged on its own (its residual against its own scale, its mixed
        Hessian's conditioning against the largest singular value it met, its step against its own values) and
        left as it is once converged, as serving that member alone does: a member with smaller values is neither
        converged nor declared singular on another member's scale. A trajectory's slice is solved when every
        member's is; it stops where one member's does (the ensemble then serves each member alone)."""
        n, nm, m = act.size, self.model.n_members, self.m
        w = m // nm

        def rows(a: np.ndarray) -> np.ndarray:  # (n, ..., nm * w) -> (n * nm, ..., w)
            return np.moveaxis(a.reshape(*a.shape[:-1], nm, w), -2, 1).reshape(n * nm, *a.shape[1:-1], w)

        def back(a: np.ndarray) -> np.ndarray:  # (n * nm, ..., w) -> (n, ..., nm * w)
            return np.moveaxis(a.reshape(n, nm, *a.shape[1:]), 1, -2).reshape(n, *a.shape[1:-1], m)

        def fn(cells: np.ndarray) -> tuple[np.ndarray, tuple[np.ndarray]]:
            g, (block,) = self.fn(back(cells))
            b = block.reshape(n, nm, w, nm, w)
            own = np.arange(nm)
            return rows(g), (b[:, own, :, own, :].transpose(1, 0, 2, 3).reshape(n * nm, w, w),)

        if self.nmember_mscale is None:
            self.nmember_mscale = np.zeros((len(self.fs), nm))
        q_now, q_old = self.npsi[act, i], self.npsi[act, i - 1]
        first = np.zeros(n * nm, dtype=np.int64)
        u, g, rabs, ok, sing, it, smin, mscale, count = self._newton_np(
            rows(q_now),
            rows(q_old),
            rows(self.ngprev[act]),
            self.nmember_mscale[act].reshape(-1),
            fn,
            rtol,
            max_newton,
            True,
            first,
        )
        self.nmember_mscale[act] = mscale.reshape(n, nm)
        # member 0's evaluations, iterations and residual: the result's figures, as member 0's alone
        self.niters[act] += count.reshape(n, nm)[:, 0]
        own = first.reshape(n, nm)[:, 0]
        # per trajectory: the first member that did not converge (else member 0) reports its conditioning
        bad = ~ok.reshape(n, nm)
        at = np.argmax(bad, axis=1)
        pick = np.arange(n) * nm + at
        self.nmscale[act] = mscale[pick]
        solved = np.asarray(~bad.any(axis=1))
        res = np.where(solved, rabs.reshape(n, nm)[:, 0], rabs.reshape(n, nm).max(axis=1))
        iters = int(own.max()) if own.all() else it
        return _Step(act, back(u), back(g), res, solved, sing[pick], iters, smin[pick])

    def _newton_np(
        self,
        q_now: np.ndarray,
        q_old: np.ndarray,
        g_prev: np.ndarray,
        mscale: np.ndarray,
        fn,
        rtol: float,
        max_newton: int,
        freeze: bool,
        first: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, int, np.ndarray, np.ndarray, np.ndarray]:
        """The Newton loop of :meth:`step` on rows ``(n, w)`` (``fn`` their derivatives): ``(u, g, rabs, ok, sing,
        iterations, smin, mscale, count)``. ``freeze``: a row that converged is left as it is (as if it had
        stopped iterating there) while the others go on; ``first`` (with ``freeze``) is set to the iteration at
        which each row converged (left at 0 for a row that did not: the loop's own count is its)."""
        vol, a0 = self.vol, self.a0
        n, m = q_now.shape
        u = 2 * q_now - q_old
        rowmax = _first if m == 1 else _rowmax  # the largest entry of each row
        mag = np.maximum(np.maximum(rowmax(np.abs(q_now)), rowmax(np.abs(q_old))), rowmax(np.abs(u)))
        rtol_mag = rtol * mag
        rscale = None
        mscale = mscale.copy()  # the largest singular value met per row (given back at the end)
        done = np.zeros(n, dtype=bool)
        count = np.ones(n, dtype=np.int64)  # Newton iterations counted per member
        sing = np.zeros(n, dtype=bool)
        prev = np.full(n, math.inf)
        last = np.zeros_like(u)
        halved = np.zeros(n, dtype=np.int64)
        any_halved = False
        small = None  # the last step was below rtol times the values (None: no member's was)
        smin = np.full(n, math.inf)
        cells = np.empty((n, 2, m))
        cells[:, 0] = q_now
        for it in range(1, max_newton + 1):
            cells[:, 1] = u
            g, (block,) = fn(cells)
            jac = vol * block
            r = vol * (g[:, a0] + g_prev)
            rabs = rowmax(np.abs(r))
            if rscale is None:  # size of the kinetic terms, per trajectory
                rscale = rtol * (np.maximum(np.abs(jac).sum(-1).max(-1), 1e-300) * np.maximum(mag, 1e-300))
            sv = self.singular_values(jac)
            mscale = np.maximum(mscale, sv[:, 0])
            smin = np.minimum(smin, sv[:, -1])
            sing |= ~(sv[:, -1] > SINGULAR_RTOL * mscale)  # as is_singular: mscale >= sv >= 0 (0 when mscale is)
            ok = rabs <= rscale
            if small is not None:
                ok |= small & np.isfinite(rabs)
            ok &= ~sing
            if freeze:
                ok |= done
                if first is not None:
                    first[ok & ~done] = it
                done = ok
            if it > 1:
                count += ~ok
            if ok.all() or it == max_newton:
                break
            worse = ~(ok | sing | (rabs < prev))
            if any_halved:
                worse &= halved < 12
            step, failed = _solve(jac, -r)
            sing |= ~worse & (failed | ~(np.isfinite(step[:, 0]) if m == 1 else np.isfinite(step).all(-1)))
            take = ~(ok | sing | worse)
            if take.all():  # every member takes its Newton step (none halved, none stopped)
                u = u + step
                prev, last = rabs, step
                if any_halved:
                    halved, any_halved = np.zeros(n, dtype=np.int64), False
                small = rowmax(np.abs(step)) <= rtol_mag
                continue
            last = np.where(worse[:, None], last / 2, last)
            u = np.where(worse[:, None], u - last, np.where(take[:, None], u + step, u))
            prev = np.where(take, rabs, prev)
            last = np.where(take[:, None], step, last)
            halved = np.where(take, 0, halved + worse)
            any_halved = bool(halved.any())
            small = (take | worse) & (rowmax(np.abs(last)) <= rtol_mag)
        return u, g, rabs, ok, sing, it, smin, mscale, count

    def step_one(self, k: int, i: int, rtol: float, max_newton: int) -> _Step | None:
        """:meth:`step` for one scalar member ``k`` in Python floats (the same IEEE operations in the same
        order; NaN propagated as by numpy). Stores the slice itself and returns None when it converged;
        otherwise returns the step for :meth:`store` to report."""
        vol, a0, a1, fn = self.vol, self.a0, self.a1, self.fn
        q_now, q_old = float(self.npsi[k, i, 0]), float(self.npsi[k, i - 1, 0])
        g_prev = float(self.ngprev[k, 0])
        u = 2 * q_now - q_old
        mag = _fmax(_fmax(abs(q_now), abs(q_old)), abs(u))
        rtol_mag = rtol * mag
        rscale = math.nan
        mscale = float(self.nmscale[k])
        count, sing, prev, last, halved = 1, False, math.inf, 0.0, 0
        small: bool | None = None
        smin = math.inf
        cells = np.empty((1, 2, 1))
        cells[0, 0, 0] = q_now
        for it in range(1, max_newton + 1):
            cells[0, 1, 0] = u
            g, (block,) = fn(cells)
            jac = vol * float(block[0, 0, 0])
            r = vol * (float(g[0, a0, 0]) + g_prev)
            rabs = abs(r)
            if it == 1:  # size of the kinetic terms
                rscale = rtol * (_fmax(abs(jac), 1e-300) * _fmax(mag, 1e-300))
            sv = abs(jac)
            if not math.isfinite(sv):  # as numpy.nan_to_num(nan=0)
                sv = 0.0 if sv != sv else _FLOAT_MAX
            mscale = _fmax(mscale, sv)
            smin = _fmin(smin, sv)
            sing = sing or not sv > SINGULAR_RTOL * mscale
            ok = rabs <= rscale
            if small is not None:
                ok = ok or (small and math.isfinite(rabs))
            ok = ok and not sing
            if it > 1:
                count += not ok
            if ok or it == max_newton:
                break
            worse = not (ok or sing or rabs < prev) and halved < 12
            step = -r / jac if jac != 0 else math.nan  # (numpy: inf or nan; only its finiteness is used)
            sing = sing or (not worse and not math.isfinite(step))
            if not (ok or sing or worse):  # the full Newton step
                u = u + step
                prev, last, halved = rabs, step, 0
                small = abs(step) <= rtol_mag
                continue
            if worse:
                last = last / 2
                u = u - last
            halved = halved + worse
            small = worse and abs(last) <= rtol_mag
        self.nmscale[k] = mscale
        self.niters[k] += count
        if ok:
            self.npsi[k, i + 1, 0] = u
            self.ngprev[k, 0] = g[0, a1, 0]
            self.nmax_iters[k] = max(int(self.nmax_iters[k]), it)
            self.nworst[k] = _fmax(float(self.nworst[k]), rabs)
            return None
        one = np.array([k])
        return _Step(one, np.array([[u]]), g, np.array([rabs]), np.array([ok]), np.array([sing]), it, np.array([smin]))

    def advance(self, group: np.ndarray, i: int, rtol: float, max_newton: int, box: float | None) -> None:
        """:meth:`_Batch.advance` in numpy; one scalar member (no box) by Python floats (:meth:`step_one`)."""
        act = self.active(group, i)
        if act.size:
            if act.size == 1 and self.m == 1 and box is None:  # one scalar member: Python floats
                one = self.step_one(int(act[0]), i, rtol, max_newton)
                if one is not None:
                    self.store(i, one, max_newton, box)
            else:
                self.store(i, self.step(act, i, rtol, max_newton), max_newton, box)

    def store(self, i: int, s: _Step, max_newton: int, box: float | None) -> None:
        """:meth:`_Batch.record` in numpy: store slice ``i + 1``; retire the members that failed or left the box."""
        act = s.act
        self.npsi[act, i + 1] = s.u
        self.ngprev[act] = s.g[:, self.a1]
        self.nmax_iters[act] = np.maximum(self.nmax_iters[act], s.it)
        self.nworst[act] = np.maximum(self.nworst[act], np.where(s.ok, s.rabs, self.nworst[act]))
        if not s.ok.all():
            j = np.nonzero(~s.ok)[0]
            self.stop_failed(act[j].tolist(), i, s.rabs[j].tolist(), s.sing[j].tolist(), s.smin[j].tolist(), max_newton)
        if box is not None:  # member 0's own components (a stacked ensemble stops where member 0 alone would)
            own = s.u[..., : self.m // self.model.n_members]
            out = (np.sqrt((own * own).sum(-1)) > box) & s.ok
            self.leave_box(act[out].tolist(), i, box)


def serve_fast(
    model: AbstractLagrangian,
    fs: list[LatticeField],
    steps: list[int],
    mode: str,
    rtol: float,
    max_newton: int,
    box: float | None,
    progress: bool | None,
    derivatives,
) -> list[ServeResult]:
    """``_serve_batch`` with the numpy Newton loop (``derivatives`` from :func:`numpy_derivatives_of`)."""
    batch = FastBatch(model, fs, steps, derivatives, mode, progress)
    step_fast(batch, rtol, max_newton, box)
    return batch.results()


def step_fast(batch: FastBatch, rtol: float, max_newton: int, box: float | None) -> None:
    """Serve every member of ``batch`` to its end: one scalar trajectory by the compiled ``trajectory`` where
    :func:`trajectory_kernel` offers it (``batch.kernel``), else by the numpy loop (:func:`step_members`)."""
    if batch.kernel is not None:  # one scalar trajectory: every slice in one compiled call
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            serve_trajectory(batch, batch.kernel, rtol, max_newton, box)
        batch.bar.close()
        return
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):  # non-finite values are tested for
        step_members(batch, rtol, max_newton, box)


def trajectory_kernel(model: AbstractLagrangian) -> CompiledForms | None:
    """The compiled kernels of a scalar 0+1D closed-form model whose module holds ``trajectory``
    (:mod:`latticedft._kernel`), or ``None`` (the numpy loop serves); for a model with numpy closed forms (the
    polynomial) only where the ``compiled_numpy_models`` option asks (its first build takes seconds to a minute
    per model, more than most trajectories take by the numpy loop); never for a stacked ensemble."""
    if model.n_members != 1 or any(t.device.type != "cpu" for t in model.parameters()):
        return None
    if model.numpy_ready and not option("compiled_numpy_models"):
        return None
    compiled = compiled_closed_forms(model, torch.zeros(0, dtype=torch.float64), numpy_too=True)
    return compiled if compiled is not None and compiled.has_trajectory else None


def serve_trajectory(batch: FastBatch, kernel: CompiledForms, rtol: float, max_newton: int, box: float | None) -> None:
    """Serve member 0 of ``batch`` (one scalar trajectory) by the compiled ``trajectory``: the slices of
    :meth:`FastBatch.step_one` in one call; a slice that fails is stored and reported by :meth:`FastBatch.store`
    (the step and residual; the slices solved before it kept), one that leaves the box retires the trajectory
    as there."""
    fst = np.array([batch.ngprev[0, 0], batch.nmscale[0], batch.nworst[0]])
    ist = np.array([batch.niters[0], batch.nmax_iters[0]], dtype=np.int64)
    fail = np.zeros(6)
    psi = batch.npsi[0, :, 0]
    stop = int(batch.nlength[0]) - 1
    i, status = kernel.module.trajectory(
        psi, 1, stop, batch.vol, rtol, max_newton, -1.0 if box is None else box, SINGULAR_RTOL, fst, ist, fail
    )
    batch.ngprev[0, 0], batch.nmscale[0], batch.nworst[0] = fst
    batch.niters[0], batch.nmax_iters[0] = ist
    if status == 1:
        g = np.zeros((1, 2, 1))
        g[0, batch.a1, 0] = fail[5]
        one = np.zeros(1, dtype=bool)
        step = _Step(np.array([0]), fail[None, :1], g, fail[1:2], one, fail[2:3] != 0, int(fail[4]), fail[3:4])
        batch.store(int(i), step, max_newton, None)
    elif status == 2:  # the new slice ``i`` left the box
        assert box is not None
        batch.leave_box([0], int(i) - 1, box)
