"""Slice-Newton: all equations of one slice solved together with the slice's sparse Jacobian."""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np
import torch

from .._action import CellDerivatives
from .._contract import AbstractLagrangian
from ._slices import (
    _known_sizes,
    _scale,
    _SliceSystem,
    abs_max,
    finite_step,
    is_singular,
    singular_message,
    values_abs_max,
)
from ._solvers import SolverRefused, factor_step

#: A chord step (the factorisation or preconditioner of an earlier Jacobian reused) is followed by another
#: while each cuts the residual by at least this factor; otherwise the next step assembles a fresh Jacobian.
CHORD_DROP = 1e-2

#: A slice whose chord steps from the last Jacobian took at least this many evaluations (each cut the residual
#: less than the tolerance needs) has the next slices start from a fresh Jacobian at their predictor (Newton's
#: own steps from the first); every :data:`FRESH_FIRST_RETRY`-th of them tries the chord again, whose count
#: decides as before.
FRESH_FIRST_ON = 4
FRESH_FIRST_RETRY = 8

#: The chord is kept only while its rate predicts the target in one more step (:func:`_chord_pays`); a slice
#: that assembled a fresh Jacobian after its first iteration (its chord did not pay), and the field's first
#: slice where its own Jacobian did not serve it in one step, count as slow chords for :data:`FRESH_FIRST_ON`.
CHORD_PREDICT = True

#: ``allmax(*values)``: each value's largest over the processes serving one slice together (identity in one).
AllMax = Callable[..., tuple[float, ...]]


def _local(*values: float) -> tuple[float, ...]:
    """The values themselves: one process holds the whole slice."""
    return values


def predict(flat: torch.Tensor, unk: torch.Tensor, i: int, older: torch.Tensor | None) -> None:
    """Slice-Newton's predictor on the unknown sites ``unk`` of slice ``i + 1`` of ``flat`` (``(slices, sites,
    m)``): ``2 psi_i - psi_{i-1}``, plus, with ``older`` (slice ``i - 2``, ``(sites, m)``), the previous slice's
    correction to its own such predictor (``3 psi_i - 3 psi_{i-1} + psi_{i-2}``: the next term of the
    extrapolation), in this order. One process's run (``_stepper.solve_and_tally``) and a slab of a split one
    (``_decomp``) predict by it; the compiled, folded and device kernels repeat it to the bit."""
    flat[i + 1, unk] = 2 * flat[i, unk] - flat[i - 1, unk]
    if older is not None:
        flat[i + 1, unk] += flat[i, unk] - 2 * flat[i - 1, unk] + older[unk]


def _chord_pays(res: float, prev: float, target: float) -> bool:
    """Whether the next step reuses the last Jacobian (a chord step): the last step cut the residual by at least
    :data:`CHORD_DROP` and, cutting it again by as much, one more step is predicted to reach ``target``;
    otherwise a fresh Jacobian (one Newton step from a residual this small converges) costs less than the
    chord steps it would take."""
    return res <= CHORD_DROP * prev and (not CHORD_PREDICT or res * (res / prev) <= target)


def _fresh_blocks(ev: CellDerivatives, sys: _SliceSystem, cache: dict[str, Any], allmax: AllMax = _local) -> dict:
    """Hessian blocks of the slice at the current state; records their diagonal size (the residual scale).

    Also checks the mixed Hessian's conditioning at every unknown site: ``cache["singular"]`` is
    ``(message, row)`` when its smallest singular value is singular relative to the largest met on this
    field so far (``cache["mscale"]``), else None. The sizes are the whole slice's (``allmax``). (A stacked
    ensemble's members are judged one by one, by ``._members``.)
    """
    blocks = ev.blocks(sys.pairs)
    dmax = max((abs_max(blocks[p]) for p in sys.diag_pairs), default=1.0)
    smin, smax, row = sys.site_singular_values(blocks)
    cache["dmax"], low, smax = allmax(dmax, -smin, smax)
    smin = -low
    cache["mscale"] = scale = max(cache.get("mscale", 0.0), smax)
    cache["singular"] = (singular_message(smin, scale), row) if is_singular(smin, scale) else None
    return blocks


def _factorise(sys: _SliceSystem, blocks: Any, vol: float, cache: dict[str, Any], tol: float) -> None:
    """Factorise the slice Jacobian of ``blocks`` into ``cache["solve"]``, by ``cache["factor"]`` (a split
    slice's: the processes' own) or ``_solvers.factor_step``, with the solver ``cache["solver"]``; the name of
    the solver chosen joins ``cache["used"]``, and the blocks are kept where a checkpoint rebuilds from them."""
    factor = cache.get("factor", factor_step)
    cache["solve"], name = factor(sys, blocks, vol, cache.get("solver", "auto"), tol)
    if cache.get("keep_factored"):
        cache["factored"] = (blocks, tol)
    used = cache.setdefault("used", [])
    if name not in used:
        used.append(name)


def _newton_slice(
    model: AbstractLagrangian,
    sys: _SliceSystem,
    psi,
    flat,
    unk,
    i,
    g_prev,
    vol,
    rtol,
    max_newton,
    cells_at,
    cache,
    allmax: AllMax = _local,
    evaluate: Callable[[int, Any, bool], tuple[Any, np.ndarray]] | None = None,
    sizes: tuple[float, float, float] | None = None,
):
    """Newton on one slice. Steps reuse the cached factorised Jacobian (chord steps, exact for quadratic
    ``L_d``) while each cuts the residual a hundredfold; fresh Hessian blocks are assembled only when one did not.
    The linear solver is ``cache["solver"]`` (``_solvers.SOLVERS``; ``cache["used"]`` collects those chosen),
    factorised by ``cache["factor"]`` when given (a split slice's), else ``_solvers.factor_step``.

    ``allmax`` makes every test that reads the whole slice (residual, sizes, singular values, the step) global
    when the slice is split over processes (one part each in ``flat``): they then stop at the same iteration.
    ``evaluate(i, g_prev, blocks) -> (cells, residual)`` replaces the gathering of the cells anchored on slice
    ``i``, their derivatives (``CellDerivatives``: ``grad``, ``blocks(pairs)``; ``blocks``: this iteration reads
    the blocks unless it converges) and the residual (``._folded``). ``sizes``: the three sizes of
    ``_slices._scale(flat, i, unk)`` at the predictor (slices ``i - 1``, ``i`` and the predicted unknowns), where
    the predictor measured them; the first two serve every later step's scale too (as where they are measured
    at the first step: the iterations do not move those slices).

    A slice whose chord steps took :data:`FRESH_FIRST_ON` evaluations or more has the next ones assemble a fresh
    Jacobian at their first iteration (``cache["fresh_first"]``: how many slices since; every
    :data:`FRESH_FIRST_RETRY`-th starts with the chord again, which decides anew)."""
    m = sys.m
    res = math.inf
    prev = math.inf
    r = np.zeros(0)
    rscale = None
    small = False
    fresh = cache.get("fresh_first", 0)  # slices started fresh since a slow chord (0: chord starts)
    first_stale = "solve" in cache and fresh % FRESH_FIRST_RETRY == 0
    refreshed = False  # a fresh Jacobian assembled after the first iteration
    first = "solve" not in cache  # no Jacobian yet: the field's first slice (or the first after a failed step)
    known = None if sizes is None else sizes[:2]  # the sizes of slices i - 1 and i in _scale, once measured
    for it in range(1, max_newton + 1):
        if evaluate is None:
            ev = CellDerivatives(model, cells_at(i))
            r = sys.residual(g_prev, ev.grad, vol)
        else:
            ev, r = evaluate(i, g_prev, "dmax" not in cache or (it == 1 and not first_stale))
        (res,) = allmax(values_abs_max(r) if r.size else 0.0)
        if not math.isfinite(res):
            return it, res, ev.grad, ("residual is not finite", None, res)
        stale = "solve" in cache and (first_stale if it == 1 else _chord_pays(res, prev, rtol * (rscale or 0.0)))
        prev = res
        blocks = _fresh_blocks(ev, sys, cache, allmax) if "dmax" not in cache else None
        if blocks is not None and cache["singular"]:
            return it, res, ev.grad, (*cache["singular"], res)
        if rscale is None:
            if sizes is None:
                known = _known_sizes(flat, i)
                size = _scale(flat, i, unk, known)
            else:
                size = max(*sizes, 1e-300)
            rscale = vol * cache["dmax"] * allmax(size)[0]
        if res <= rtol * rscale or small:
            # converged (or the last step was below rtol times the values: the residual stalls at round-off);
            # the cells anchored at slice i are evaluated at the solution: reuse them for slice i + 1
            if first_stale or fresh or (CHORD_PREDICT and first):
                slow = it >= FRESH_FIRST_ON or (CHORD_PREDICT and refreshed)
                cache["fresh_first"] = fresh + 1 if fresh and not first_stale else int(slow)
            return it, res, ev.grad, None
        try:
            if not stale:
                refreshed = refreshed or it > 1
                if blocks is None:
                    blocks = _fresh_blocks(ev, sys, cache, allmax)
                    if cache["singular"]:
                        return it, res, ev.grad, (*cache["singular"], res)
                _factorise(sys, blocks, vol, cache, rtol * rscale)
            delta = cache["solve"](-r)
        except SolverRefused as exc:
            return it, res, ev.grad, (str(exc), None, res)
        except (np.linalg.LinAlgError, ValueError) as exc:
            cache.pop("solve", None)
            row = int(np.argmax(np.abs(r)))
            return it, res, ev.grad, (f"singular Jacobian (mixed Hessian) of the slice: {exc}", row, res)
        finite, size = finite_step(delta)
        bad, step = allmax(0.0 if finite else 1.0, size)
        if bad:
            cache.pop("solve", None)
            if stale:
                continue
            failure = ("Newton step is not finite (singular mixed Hessian?)", int(np.argmax(np.abs(r))), res)
            return it, res, ev.grad, failure
        if unk.numel() == flat.shape[1]:  # every site an unknown (distinct sites): no gather and scatter
            flat[i + 1] += torch.from_numpy(delta.reshape(-1, m))
        else:
            flat[i + 1, unk] += torch.from_numpy(delta.reshape(-1, m))
        small = not stale and step <= rtol * allmax(_scale(flat, i, unk, known))[0]
    worst: int | None = int(np.argmax(np.abs(r))) if r.size else None
    return max_newton, res, ev.grad, (f"Newton did not converge in {max_newton} iterations", worst, res)
