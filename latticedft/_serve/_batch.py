"""1D serving: a batch of trajectories stepped together. In 1D a slice is one site: each member's slice is a
dense ``m x m`` Newton solve, batched over the members still running."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch
import xarray as xr

from .._action import CellDerivatives, cell_derivatives
from .._lattice import LatticeField, to_dataarrays
from .._models import AbstractLagrangian
from ._range import assess
from ._result import ServeResult, box_reason
from ._slices import SINGULAR_RTOL, is_singular, singular_message, slice_message
from ._stepper import Stepping


@dataclass
class _GroupStep:
    """What Newton made of one slice of a group of members."""

    act: torch.Tensor  # the members solved (indices into the batch)
    u: torch.Tensor  # their values on the new slice
    g: torch.Tensor  # per-cell gradients at those values
    rabs: torch.Tensor  # max |residual| per member
    ok: torch.Tensor  # converged
    sing: torch.Tensor  # stopped at a singular Jacobian (mixed Hessian)
    it: int  # Newton iterations taken
    smin: torch.Tensor  # smallest singular value of the mixed Hessian met, per member


def failure_text(f: LatticeField, i: int, singular: bool, smin: float, scale: float, max_newton: int) -> str:
    """Why a trajectory stopped on slice ``i + 1``: Newton did not converge, or its mixed Hessian is singular."""
    if not singular:
        why = f"Newton did not converge in {max_newton} iterations"
    else:
        why = singular_message(smin, scale) if is_singular(smin, scale) else "singular mixed Hessian"
    return slice_message(f, i, why)


class _Batch(Stepping):
    """The values of a batch of 1D trajectories and each member's bookkeeping (length, reason, iterations);
    its mode, clock, progress bar (``label`` after the mode: the members by default) and solver name are
    those of every stepped run (:class:`._stepper.Stepping`), its slices stepped by
    :func:`._stepper.step_members`."""

    def __init__(
        self,
        model: AbstractLagrangian,
        fs: list[LatticeField],
        steps: list[int],
        mode: str,
        progress: bool | None,
        label: str | None = None,
        first: bool = True,
    ):
        """``first``: take each member's first gradient ``g_prev`` by :func:`cell_derivatives` (else left at
        zero for a subclass to set)."""
        st = model.stencil
        self.model, self.fs = model, fs
        self.a0, self.a1 = st.anchor, st.forward
        b = len(fs)
        self.m = fs[0].ncomp
        self.nmax = max(steps)
        self.psi = torch.full((b, self.nmax, self.m), math.nan, dtype=torch.float64)
        for k, f in enumerate(fs):
            self.psi[k, :2] = f.values[:2]
        self.vol = math.prod(model.spacing)
        self.length = list(steps)
        self.reason = ["complete"] * b
        self.failed = [False] * b
        self.fail_at: dict[int, tuple[int, float]] = {}
        self.worst = torch.zeros(b, dtype=torch.float64)
        self.iters = torch.zeros(b, dtype=torch.long)
        self.max_iters = torch.zeros(b, dtype=torch.long)
        super().__init__(mode, self.nmax, progress, f", {b} trajectories" if label is None else label)
        if first:
            g_prev, _ = cell_derivatives(model, self.psi[:, 0:2], [])
            self.g_prev = g_prev[:, self.a1].clone()  # d L(q_{i-1}, q_i) / d q_i, per member
        else:
            self.g_prev = torch.zeros((b, self.m), dtype=torch.float64)
        # A model whose mixed Hessian is constant by construction (the kinetic-potential MLP) has the same
        # Jacobian d r / d u at every state: it is assembled once, and Newton needs only gradients after that
        # (an exact Newton step, not a chord). Other models get fresh Hessian blocks every iteration: a chord
        # step with a stale Jacobian was seen to land near a spurious root at a stiff turning point.
        self.const_model = bool(model.constant_mixed_hessian)
        self.jac_const: torch.Tensor | None = None
        # per member: the largest singular value of the mixed Hessian met so far (the scale a singular one is
        # measured against)
        self.mscale = torch.zeros(b, dtype=torch.float64)
        #: A stacked ensemble's largest singular value met per trajectory and member (set on its first step).
        self.member_mscale: torch.Tensor | None = None

    def retire(self, k: int, slices: int, why: str, bad: bool, res: float = math.nan) -> None:
        """Member ``k`` stops after ``slices`` slices; ``bad``: it failed (with residual ``res``)."""
        self.length[k] = slices
        self.reason[k] = why
        self.failed[k] = bad
        if bad:
            self.fail_at[k] = (slices, res)

    def members(self, group: list[int], i: int) -> list[int]:
        """The members of ``group`` that still have slice ``i + 1`` to solve."""
        return [k for k in group if self.length[k] > i + 1 and self.reason[k] == "complete"]

    def derivatives(self, cells: torch.Tensor, n: int) -> tuple[torch.Tensor, torch.Tensor]:
        """Per-cell gradients and the Jacobian ``d r / d u`` of ``n`` members' cells."""
        if self.jac_const is not None:  # constant mixed Hessian: the gradient is all that changes
            return CellDerivatives(self.model, cells).grad, self.jac_const.expand(n, self.m, self.m)
        g, blocks = cell_derivatives(self.model, cells, [(self.a0, self.a1)])
        jac = self.vol * blocks[(self.a0, self.a1)]  # d r_i / d u_j = vol d^2 L / dx_{a0,i} dx_{a1,j}
        if self.const_model:
            self.jac_const = jac[0].clone()
        return g, jac

    def advance(self, group: np.ndarray, i: int, rtol: float, max_newton: int, box: float | None) -> None:
        """Slice ``i + 1`` of the members of ``group`` still running: one batched Newton, stored (:meth:`record`)."""
        act_list = self.members(group.tolist(), i)
        if act_list:
            self.record(act_list, i, self.newton(act_list, i, rtol, max_newton), max_newton, box)

    def newton(self, act_list: list[int], i: int, rtol: float, max_newton: int) -> _GroupStep:
        """Newton with backtracking for slice ``i + 1`` of the members ``act_list``, from the predictor; a stacked
        ensemble's members as rows of their own (:meth:`_newton_members`)."""
        act = torch.tensor(act_list, dtype=torch.long)
        n = len(act_list)
        if self.model.n_members > 1:
            return self._newton_members(act, i, rtol, max_newton)
        q_now, q_old = self.psi[act, i], self.psi[act, i - 1]
        u, g, rabs, ok, sing, it, smin, mscale, count = self._newton(
            q_now, q_old, self.g_prev[act], self.mscale[act], lambda c: self.derivatives(c, n), rtol, max_newton, False
        )
        self.mscale[act] = mscale
        self.iters[act] += count
        return _GroupStep(act, u, g, rabs, ok, sing, it, smin)

    def _newton_members(self, act: torch.Tensor, i: int, rtol: float, max_newton: int) -> _GroupStep:
        """:meth:`newton` of a stacked ensemble (``n_members`` models side by side, never coupled): every member
        of every trajectory a row of its own, judged on its own (its residual against its own scale, its mixed
        Hessian's conditioning against the largest singular value it met, its step against its own values) and
        left as it is once converged, as serving that member alone does (``_fast1d.FastBatch._step_members``)."""
        n, nm, m = act.numel(), self.model.n_members, self.m
        w = m // nm

        def rows(a: torch.Tensor) -> torch.Tensor:  # (n, ..., nm * w) -> (n * nm, ..., w)
            return a.unflatten(-1, (nm, w)).movedim(-2, 1).reshape(n * nm, *a.shape[1:-1], w)

        def back(a: torch.Tensor) -> torch.Tensor:  # (n * nm, ..., w) -> (n, ..., nm * w)
            return a.reshape(n, nm, *a.shape[1:]).movedim(1, -2).flatten(-2)

        own = torch.arange(nm)

        def derivatives(cells: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
            g, jac = self.derivatives(back(cells), n)
            blocks = jac.reshape(n, nm, w, nm, w)[:, own, :, own, :]  # (members, n, w, w)
            return rows(g), blocks.transpose(0, 1).reshape(n * nm, w, w)

        if self.member_mscale is None:
            self.member_mscale = torch.zeros(len(self.fs), nm, dtype=torch.float64)
        q_now, q_old = self.psi[act, i], self.psi[act, i - 1]
        first = torch.zeros(n * nm, dtype=torch.long)
        u, g, rabs, ok, sing, it, smin, mscale, count = self._newton(
            rows(q_now),
            rows(q_old),
            rows(self.g_prev[act]),
            self.member_mscale[act].reshape(-1),
            derivatives,
            rtol,
            max_newton,
            True,
            first,
        )
        self.member_mscale[act] = mscale.reshape(n, nm)
        # member 0's evaluations, iterations and residual: the result's figures, as member 0's alone
        self.iters[act] += count.reshape(n, nm)[:, 0]
        own = first.reshape(n, nm)[:, 0]
        bad = ~ok.reshape(n, nm)
        pick = torch.arange(n) * nm + torch.argmax(bad.long(), dim=1)  # the first member that did not converge
        self.mscale[act] = mscale[pick]
        solved = ~bad.any(1)
        res = torch.where(solved, rabs.reshape(n, nm)[:, 0], rabs.reshape(n, nm).amax(1))
        iters = int(own.max()) if bool(own.all()) else it
        return _GroupStep(act, back(u), back(g), res, solved, sing[pick], iters, smin[pick])

    def _newton(
        self,
        q_now: torch.Tensor,
        q_old: torch.Tensor,
        g_prev: torch.Tensor,
        mscale: torch.Tensor,
        derivatives: Callable[[torch.Tensor], tuple[torch.Tensor, torch.Tensor]],
        rtol: float,
        max_newton: int,
        freeze: bool,
        first: torch.Tensor | None = None,
    ) -> tuple[
        torch.Tensor,
        torch.Tensor,
        torch.Tensor,
        torch.Tensor,
        torch.Tensor,
        int,
        torch.Tensor,
        torch.Tensor,
        torch.Tensor,
    ]:
        """The Newton loop of :meth:`newton` on rows ``(n, w)`` (``derivatives(cells)``: their gradients and
        Jacobians): ``(u, g, rabs, ok, sing, iterations, smin, mscale, count)``, ``mscale`` the largest singular
        value met per row. ``freeze``: a row that converged is left as it is while the others go on; ``first``
        (with ``freeze``) is set to the iteration at which each row converged (left at 0 for a row that did
        not: the loop's own count is its)."""
        n = q_now.shape[0]
        u = 2 * q_now - q_old
        mag = torch.maximum(torch.maximum(q_now.abs().amax(-1), q_old.abs().amax(-1)), u.abs().amax(-1))
        rscale = None
        ok = torch.zeros(n, dtype=torch.bool)
        done = torch.zeros(n, dtype=torch.bool)
        sing = torch.zeros(n, dtype=torch.bool)
        count = torch.zeros(n, dtype=torch.long)
        # Backtracking: a Newton step that does not lower the residual (a poor predictor at a stiff
        # turning point, say) is halved instead, so Newton finds the root near the predictor rather
        # than a spurious one far away. A step below rtol times the values counts as converged, as
        # in the n-D slice Newton (the residual can stall at round-off just above rtol * rscale).
        prev = torch.full((n,), math.inf, dtype=torch.float64)
        last = torch.zeros_like(u)
        halved = torch.zeros(n, dtype=torch.long)
        small = torch.zeros(n, dtype=torch.bool)
        smin = torch.full((n,), math.inf, dtype=torch.float64)
        for it in range(1, max_newton + 1):
            g, jac = derivatives(torch.stack([q_now, u], dim=1))
            r = self.vol * (g[:, self.a0] + g_prev)
            rabs = r.abs().amax(-1)
            if rscale is None:  # size of the kinetic terms, per trajectory
                rscale = torch.linalg.matrix_norm(jac, ord=math.inf).clamp_min(1e-300) * mag.clamp_min(1e-300)
            sv = jac.abs().reshape(-1, 1) if jac.shape[-1] == 1 else torch.linalg.svdvals(jac)
            sv = torch.nan_to_num(sv, nan=0.0)
            mscale = torch.maximum(mscale, sv[:, 0])
            s_now = sv[:, -1]
            smin = torch.minimum(smin, s_now)
            # a singular mixed Hessian is refused, whatever the residual says (vectorised is_singular)
            sing = sing | ~((mscale > 0) & (s_now > SINGULAR_RTOL * mscale))
            ok = ((rabs <= rtol * rscale) | (small & torch.isfinite(rabs))) & ~sing
            if freeze:
                ok = ok | done
                if first is not None:
                    first[ok & ~done] = it
                done = ok
            count += (~ok).long() if it > 1 else 1
            if bool(ok.all()) or it == max_newton:
                break
            worse = ~ok & ~sing & ~(rabs < prev) & (halved < 12)
            last = torch.where(worse[:, None], last / 2, last)
            step, info = torch.linalg.solve_ex(jac, -r)
            sing = sing | (~worse & ((info != 0) | ~torch.isfinite(step).all(-1)))
            take = ~ok & ~sing & ~worse
            u = torch.where(worse[:, None], u - last, torch.where(take[:, None], u + step, u))
            prev = torch.where(take, rabs, prev)
            last = torch.where(take[:, None], step, last)
            halved = torch.where(take, 0, halved + worse.long())
            small = (take | worse) & (last.abs().amax(-1) <= rtol * mag)
        return u, g, rabs, ok, sing, it, smin, mscale, count

    def record(self, act_list: list[int], i: int, s: _GroupStep, max_newton: int, box: float | None) -> None:
        """Store slice ``i + 1`` of the members solved; retire those that failed or left the box."""
        act = s.act
        self.psi[act, i + 1] = s.u
        self.g_prev[act] = s.g[:, self.a1]
        self.max_iters[act] = torch.maximum(self.max_iters[act], torch.tensor(s.it))
        self.worst[act] = torch.maximum(self.worst[act], torch.where(s.ok, s.rabs, self.worst[act]))
        bad = ~s.ok
        if bool(bad.any()):
            j = torch.nonzero(bad).flatten()
            ks = [act_list[int(k)] for k in j]
            self.stop_failed(ks, i, s.rabs[j].tolist(), s.sing[j].tolist(), s.smin[j].tolist(), max_newton)
        if box is not None:  # member 0's own components (a stacked ensemble stops where member 0 alone would)
            out = (s.u[..., : self.m // self.model.n_members].norm(dim=-1) > box) & s.ok
            self.leave_box([act_list[j] for j in torch.nonzero(out).flatten().tolist()], i, box)

    def stop_failed(
        self, ks: list[int], i: int, rabs: list[float], sing: list[bool], smin: list[float], max_newton: int
    ) -> None:
        """The members ``ks`` failed on slice ``i``'s equations (their residuals ``rabs``, whether their mixed
        Hessian is singular, ``sing``, and its smallest singular value met, ``smin``): each retires with its one
        line and residual (the torch and the numpy loop alike)."""
        for k, res, singular, small in zip(ks, rabs, sing, smin):
            why = failure_text(self.fs[k], i, bool(singular), float(small), float(self.mscale[k]), max_newton)
            self.retire(k, i + 1, f"{why}, residual {res:.3e}", True, res)
            self.worst[k] = max(float(self.worst[k]), res)

    def leave_box(self, ks: list[int], i: int, box: float) -> None:
        """The members ``ks`` left the box on slice ``i + 1``: each retires (complete) after that slice."""
        for k in ks:
            self.retire(k, i + 2, box_reason(box, i + 1), False)

    def assess(self, fields: list[LatticeField]) -> list[tuple[xr.DataArray | None, list[str]]]:
        """``(extrapolation, warnings)`` of each member's served field."""
        return [assess(self.model, lf) for lf in fields]

    def results(self) -> list[ServeResult]:
        """One result per member; a failed member's ``fail_at`` is ``(slice, residual)``."""
        wall, rate = self.rate(sum(max(n - 2, 0) for n in self.length))
        out = []
        fields = [LatticeField.with_values(f, self.psi[k, : self.length[k]].clone()) for k, f in enumerate(self.fs)]
        arrays = to_dataarrays(fields)  # members of one lattice share their coordinates' construction
        for k, (da, (ext, warnings)) in enumerate(zip(arrays, self.assess(fields))):
            n = self.length[k]
            out.append(
                ServeResult(
                    field=da,
                    complete=not self.failed[k],
                    reason=self.reason[k],
                    slices=n,
                    wall_time=wall,
                    sites_per_second=rate,
                    max_residual=float(self.worst[k]),
                    extrapolation=ext,
                    warnings=warnings,
                    fail_at=self.fail_at.get(k),
                    **self.figures(int(self.iters[k]), int(self.max_iters[k])),
                )
            )
        return out
