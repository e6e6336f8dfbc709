"""Slice-Newton of a stacked ensemble (``n_members`` models side by side on the components, never coupled):
every member judged on its own, as it is when served alone.

The slice system of a stacked ensemble is block diagonal in its members. What the stacked run must not share
is its judgement: each member's residual is tested against its own scale (its own kinetic terms and values), its
step against its own values, and it is left as it is once converged while the others go on; each member takes a
chord step (the factorisation of its last fresh Jacobian) or a fresh Jacobian by its own residuals, and starts a
slice fresh by its own count of slow chords, as :func:`._newton._newton_slice` decides for a single model. Each
member's Jacobian is factorised on its own (``_solvers.factor_members``: its own solver, band LU pivots and
GMRES stop at its own tolerance), only when it takes a fresh one, and solves its own part of the step. A member
whose affine recurrence passed its own DEL check further than another's keeps its recurrence's slices until its
own first failing one (:func:`affine_held`), as alone.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np
import torch

from .._action import CellDerivatives
from .._contract import AbstractLagrangian
from . import _newton
from ._newton import FRESH_FIRST_RETRY, _chord_pays
from ._slices import _SliceSystem, first_singular, member_abs_max, member_block_sizes, singular_message
from ._solvers import SolverRefused, factor_members, members_solve

__all__ = ["MemberFigures", "affine_held", "counted_figures", "member_figures", "newton_members"]


class MemberFigures:
    """Each stacked member's own figures of a served field, counted as the member counts them served alone: its
    slice-Newton evaluations (``total``, and ``most`` on one slice; the affine recurrence's slices one each),
    the largest residual it converged to (``worst``) and the linear solvers chosen for its own Jacobians
    (``used``, in the order first chosen). A stacked run reports member 0's (``_stepper.SteppedRun.counts``),
    as its ``field`` is member 0's."""

    def __init__(self, nm: int):
        self.total = np.zeros(nm, dtype=np.int64)
        self.most = np.zeros(nm, dtype=np.int64)
        self.worst = np.zeros(nm)
        self.used: list[list[str]] = [[] for _ in range(nm)]

    def affine(self, counts: np.ndarray, worst: np.ndarray) -> None:
        """The slices each member's affine recurrence served (``counts``, after the two given ones) and the
        largest residual among them (``worst``): one evaluation each, as alone (``SteppedRun.count_affine``)."""
        served = counts > 0
        self.total = np.where(served, counts, 0).astype(np.int64)
        self.most = served.astype(np.int64)
        self.worst = np.where(served, worst, 0.0)

    def newton(self, its: np.ndarray, res: np.ndarray) -> None:
        """One slice of slice-Newton: each member's evaluations until it converged (``its``; 0: held, not
        iterated) and the residual it converged to (``res``)."""
        took = its > 0
        self.total += its
        self.most = np.maximum(self.most, its)
        self.worst = np.where(took, np.maximum(self.worst, res), self.worst)

    def solver(self, k: int, name: str) -> None:
        """Member ``k`` took a fresh Jacobian solved by ``name``."""
        if name not in self.used[k]:
            self.used[k].append(name)


def member_figures(cache: dict[str, Any], nm: int) -> MemberFigures:
    """The :class:`MemberFigures` of a stacked run's Newton cache (made on first use)."""
    figures: MemberFigures = cache.setdefault("member_figures", MemberFigures(nm))
    return figures


def counted_figures(cache: dict[str, Any]) -> MemberFigures | None:
    """The :class:`MemberFigures` of a stacked run's Newton cache where its members were counted (``None``
    where no affine slice or Newton step was)."""
    figures: MemberFigures | None = cache.get("member_figures")
    return figures


def _member_scales(flat: torch.Tensor, i: int, unk: torch.Tensor, nm: int, w: int) -> np.ndarray:
    """:func:`._slices._scale` of each member: the size of its own values on slices ``i - 1``, ``i`` and the
    unknowns of ``i + 1``."""
    nxt = flat[i + 1] if unk.numel() == flat.shape[1] else flat[i + 1, unk]
    parts = [member_abs_max(flat[i - 1], nm, w), member_abs_max(flat[i], nm, w), member_abs_max(nxt, nm, w)]
    return np.maximum(np.maximum(np.maximum(parts[0], parts[1]), parts[2]), 1e-300)


def _assess(sys: _SliceSystem, blocks: Any, cache: dict[str, Any], which: np.ndarray) -> tuple[str, int] | None:
    """The members ``which`` (a mask) take fresh Hessian blocks: each one's diagonal size (``member_dmax``) and
    the largest singular value met on its own blocks (``member_mscale``) updated, and its conditioning judged
    against that (``_newton._fresh_blocks`` of a single model); ``(message, row)`` of the first singular one."""
    nm = sys.members
    dmax = np.full(nm, 1.0) if not sys.diag_pairs else np.zeros(nm)
    for p in sys.diag_pairs:
        dmax = np.maximum(dmax, member_block_sizes(blocks, p, nm))
    lows, highs, rows = sys.member_singular_values(blocks)
    mscale = np.array(cache.get("member_mscale", np.zeros(nm)), dtype=np.float64)
    mscale[which] = np.maximum(mscale[which], highs[which])
    cache["member_mscale"] = mscale
    cache["mscale"] = float(mscale.max())
    cache["member_dmax"][which] = dmax[which]
    cache["dmax"] = float(np.nanmax(cache["member_dmax"]))
    k = first_singular(np.where(which, lows, np.inf), np.where(which, mscale, 1.0))
    return None if k is None else (singular_message(lows[k], mscale[k]), int(rows[k]))


def affine_held(cache: dict[str, Any], flat: torch.Tensor, i: int) -> tuple[np.ndarray, torch.Tensor] | None:
    """``(held, values)``: the members whose slice ``i + 1`` of ``flat`` the affine recurrence served (it passed
    their own DEL check: ``cache["member_affine"]``, each member's count of slices served after the two given
    ones) and a copy of that slice, for :func:`newton_members` to leave them as served alone; ``None`` where no
    member is held."""
    counts = cache.get("member_affine")
    held = None if counts is None else i <= counts
    return None if held is None or not held.any() else (held, flat[i + 1].clone())


class _Slice:
    """One slice of a stacked ensemble's slice-Newton: per member, what :func:`._newton._newton_slice` keeps for
    one model (the chord state across slices in ``cache``, the rest for this slice)."""

    def __init__(self, sys: _SliceSystem, cache: dict[str, Any], rtol: float, held: np.ndarray | None = None):
        nm = sys.members
        self.sys, self.cache, self.rtol, self.nm, self.w = sys, cache, rtol, nm, sys.m // nm
        if "member_dmax" not in cache:
            cache["member_dmax"] = np.full(nm, math.nan)
        if "solve" not in cache or "member_solve" not in cache:
            cache["member_solve"] = np.zeros(nm, dtype=bool)
        self.has: np.ndarray = cache["member_solve"]  # a factorised Jacobian of its own (its last fresh one)
        self.fresh = np.array(cache.get("member_fresh", np.zeros(nm, dtype=np.int64)))
        self.first_stale = self.has & (self.fresh % FRESH_FIRST_RETRY == 0)
        self.first = ~self.has
        self.refreshed = np.zeros(nm, dtype=bool)
        self.active = np.ones(nm, dtype=bool) if held is None else ~held  # not yet converged (nor held)
        self.small = np.zeros(nm, dtype=bool)
        self.prev = np.full(nm, math.inf)
        self.done = np.zeros(nm)  # the residual each converged member was left at
        self.its = np.zeros(nm, dtype=np.int64)  # the iteration at which each member converged (0: held)
        self.rscale: np.ndarray | None = None

    def stale(self, it: int, res: np.ndarray) -> np.ndarray:
        """The members that take a chord step at iteration ``it`` (``_newton._chord_pays`` on their own residuals)."""
        out = np.zeros(self.nm, dtype=bool)
        for k in np.nonzero(self.active & self.has)[0]:
            target = self.rtol * float(self.rscale[k]) if self.rscale is not None else 0.0
            out[k] = bool(self.first_stale[k]) if it == 1 else _chord_pays(float(res[k]), float(self.prev[k]), target)
        self.prev = np.where(self.active, res, self.prev)
        return out

    def converge(self, it: int, res: np.ndarray) -> bool:
        """The members converged at iteration ``it`` left as they are, their chord count kept as served alone;
        whether every member has."""
        assert self.rscale is not None
        converged = self.active & ((res <= self.rtol * self.rscale) | self.small)
        fresh, first_stale = self.fresh, self.first_stale
        for k in np.nonzero(converged)[0]:
            # read at call time, as slice-Newton's own loop reads them: the switches reach a stack too
            predict = _newton.CHORD_PREDICT
            if first_stale[k] or fresh[k] or (predict and self.first[k]):
                slow = it >= _newton.FRESH_FIRST_ON or (predict and self.refreshed[k])
                fresh[k] = fresh[k] + 1 if fresh[k] and not first_stale[k] else int(slow)
            self.done[k] = res[k]
        self.its[converged] = it
        self.active &= ~converged
        if self.active.any():
            return False
        self.cache["member_fresh"] = fresh
        member_figures(self.cache, self.nm).newton(self.its, self.done)
        return True

    def factorise(self, ev: Any, blocks: Any, assessed: np.ndarray, need: np.ndarray, vol: float) -> Any:
        """The members ``need`` take a fresh Jacobian (each judged singular on its own scale: ``(message, row)``
        returned), each factorised on its own with its own tolerance (the others keep theirs); ``None`` when
        factorised."""
        cache = self.cache
        if blocks is None:
            blocks = ev.blocks(self.sys.pairs)
        if (need & ~assessed).any():
            singular = _assess(self.sys, blocks, cache, need & ~assessed)
            if singular:
                return singular
        solves = cache.setdefault("member_solves", [None] * self.nm)
        assert self.rscale is not None
        names = factor_members(
            self.sys, blocks, vol, cache.get("solver", "auto"), self.rtol * self.rscale, solves, need
        )
        used = cache.setdefault("used", [])
        used.extend(name for name in dict.fromkeys(names) if name not in used)
        figures = member_figures(cache, self.nm)
        for k, name in zip(np.nonzero(need)[0], names, strict=True):
            figures.solver(int(k), name)
        cache["solve"] = members_solve(solves, self.nm, self.w)
        self.has |= need
        return None

    def step(self, delta: np.ndarray, stale: np.ndarray, flat: torch.Tensor, i: int, unk: torch.Tensor) -> bool:
        """Each member still iterating moves by its own part of ``delta``; a chord step that is not finite leaves
        its member where it is, to take a fresh Jacobian next (as alone). ``False``: a fresh Jacobian's step is
        not finite (the slice fails)."""
        nm, w = self.nm, self.w
        d = delta.reshape(-1, nm, w)  # the solve's own array
        step = member_abs_max(d, nm, w)  # not finite where a member's step is not
        bad = self.active & ~np.isfinite(step)
        if (bad & ~stale).any():
            return False
        self.has &= ~bad
        moved = self.active & ~bad
        if not moved.all():
            d[:, ~moved] = 0.0
            step = np.where(moved, step, 0.0)
        if unk.numel() == flat.shape[1]:
            flat[i + 1] += torch.from_numpy(d.reshape(-1, self.sys.m))
        else:
            flat[i + 1, unk] += torch.from_numpy(d.reshape(-1, self.sys.m))
        now = _member_scales(flat, i, unk, nm, w)
        self.small = np.where(moved, ~stale & (step <= self.rtol * now), self.small)
        return True

    def worst_row(self, r: np.ndarray) -> int | None:
        """The equation row of the largest residual among the members not converged."""
        if not r.size:
            return None
        wrong = np.abs(r.reshape(-1, self.nm, self.w))
        wrong[:, ~self.active] = 0.0
        return int(np.argmax(wrong.reshape(-1)))


def newton_members(
    model: AbstractLagrangian,
    sys: _SliceSystem,
    flat: torch.Tensor,
    unk: torch.Tensor,
    i: int,
    g_prev: Any,
    vol: float,
    rtol: float,
    max_newton: int,
    cells_at: Callable[[int], torch.Tensor],
    cache: dict[str, Any],
    evaluate: Callable[[int, Any, bool], tuple[Any, np.ndarray]] | None = None,
    held: tuple[np.ndarray, torch.Tensor] | None = None,
) -> tuple[int, float, Any, tuple[str, int | None, float] | None]:
    """:func:`._newton._newton_slice` of a stacked ensemble, every member judged on its own: ``(evaluations,
    largest residual, gradients of the cells anchored at i, failure or None)``. A member converges when its own
    residual is below ``rtol`` times its own scale (or its last step below ``rtol`` times its own values) and
    is then left as it is; the slice is solved when every member is. Each member keeps its own chord state in
    ``cache``: whether it has a factorised Jacobian (``member_solve``), its slices started fresh since a slow
    chord (``member_fresh``), its Hessian's size (``member_dmax``) and the factorisation of its last fresh Jacobian
    (``member_solves``). ``held``: the members whose slice ``i + 1`` the affine recurrence served and that slice
    before the predictor (:func:`affine_held`): their values put back and left as they are, their chord state
    untouched, as when each is served alone (Newton from its own first failing slice on)."""
    run = _Slice(sys, cache, rtol, None if held is None else held[0])
    nm, w = run.nm, run.w
    if held is not None:
        keep = torch.from_numpy(np.repeat(held[0], w))
        flat[i + 1][:, keep] = held[1][:, keep]
    r = np.zeros(0)
    ev: Any = None
    for it in range(1, max_newton + 1):
        unset = np.isnan(cache["member_dmax"])
        if evaluate is None:
            ev = CellDerivatives(model, cells_at(i))
            r = sys.residual(g_prev, ev.grad, vol)
        else:
            ev, r = evaluate(i, g_prev, bool(unset.any()) or (it == 1 and not run.first_stale.all()))
        res = member_abs_max(r, nm, w)
        top = float(np.max(res))
        if not np.isfinite(res[run.active]).all():
            return it, top, ev.grad, ("residual is not finite", None, top)
        stale = run.stale(it, res)
        blocks = None
        if unset.any():  # the field's first Jacobian: its size and conditioning at once (a single model's too)
            blocks = ev.blocks(sys.pairs)
            singular = _assess(sys, blocks, cache, unset)
            if singular:
                return it, top, ev.grad, (*singular, top)
        if run.rscale is None:
            run.rscale = vol * cache["member_dmax"] * _member_scales(flat, i, unk, nm, w)
        if run.converge(it, res):
            return it, float(np.max(run.done)), ev.grad, None
        need = run.active & ~stale
        try:
            if need.any():
                run.refreshed |= need & (it > 1)
                singular = run.factorise(ev, blocks, unset, need, vol)
                if singular:
                    return it, top, ev.grad, (*singular, top)
            rhs = -r.reshape(-1, nm, w)
            rhs[:, ~run.active] = 0.0  # a converged member is left as it is
            delta = cache["solve"](rhs.reshape(-1))
        except SolverRefused as exc:
            return it, top, ev.grad, (str(exc), None, top)
        except (np.linalg.LinAlgError, ValueError) as exc:
            cache.pop("solve", None)
            msg = f"singular Jacobian (mixed Hessian) of the slice: {exc}"
            return it, top, ev.grad, (msg, run.worst_row(r), top)
        if not run.step(delta, stale, flat, i, unk):
            cache.pop("solve", None)
            return it, top, ev.grad, ("Newton step is not finite (singular mixed Hessian?)", run.worst_row(r), top)
    last = float(np.max(member_abs_max(r, nm, w)[run.active])) if r.size else 0.0
    return max_newton, last, ev.grad, (f"Newton did not converge in {max_newton} iterations", run.worst_row(r), last)
