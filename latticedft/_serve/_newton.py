"""Slice-Newton: all equations of one slice solved together with the slice's sparse Jacobian."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch

from .._action import CellDerivatives
from .._contract import AbstractLagrangian
from ._slices import _scale, _SliceSystem, is_singular, singular_message
from ._solvers import SolverRefused, factor_step

#: A chord step (the factorisation or preconditioner of an earlier Jacobian reused) is followed by another
#: while each cuts the residual by at least this factor; otherwise the next step assembles a fresh Jacobian.
CHORD_DROP = 1e-2


def _fresh_blocks(ev: CellDerivatives, sys: _SliceSystem, cache: dict[str, Any]) -> dict:
    """Hessian blocks of the slice at the current state; records their diagonal size (the residual scale).

    Also checks the mixed Hessian's conditioning at every unknown site: ``cache["singular"]`` is
    ``(message, row)`` when its smallest singular value is singular relative to the largest met on this
    field so far (``cache["mscale"]``), else None.
    """
    blocks = ev.blocks(sys.pairs)
    cache["dmax"] = max((float(blocks[p].abs().max()) for p in sys.diag_pairs), default=1.0)
    smin, smax, row = sys.site_singular_values(blocks)
    cache["mscale"] = scale = max(cache.get("mscale", 0.0), smax)
    cache["singular"] = (singular_message(smin, scale), row) if is_singular(smin, scale) else None
    return blocks


def _newton_slice(
    model: AbstractLagrangian, sys: _SliceSystem, psi, flat, unk, i, g_prev, vol, rtol, max_newton, cells_at, cache
):
    """Newton on one slice. Steps reuse the cached factorised Jacobian (chord steps, exact for quadratic
    ``L_d``) while each cuts the residual a hundredfold; fresh Hessian blocks are assembled only when one did not.
    The linear solver is ``cache["solver"]`` (``_solvers.SOLVERS``; ``cache["used"]`` collects those chosen)."""
    m = sys.m
    res = math.inf
    prev = math.inf
    r = np.zeros(0)
    rscale = None
    small = False
    for it in range(1, max_newton + 1):
        ev = CellDerivatives(model, cells_at(i))
        r = sys.residual(g_prev, ev.grad, vol)
        res = float(np.abs(r).max()) if r.size else 0.0
        if not math.isfinite(res):
            return it, res, ev.grad, ("residual is not finite", None, res)
        stale = "solve" in cache and (it == 1 or res <= CHORD_DROP * prev)
        prev = res
        blocks = _fresh_blocks(ev, sys, cache) if "dmax" not in cache else None
        if blocks is not None and cache["singular"]:
            return it, res, ev.grad, (*cache["singular"], res)
        if rscale is None:
            rscale = vol * cache["dmax"] * _scale(flat, i, unk)
        if res <= rtol * rscale or small:
            # converged (or the last step was below rtol times the values: the residual stalls at round-off);
            # the cells anchored at slice i are evaluated at the solution: reuse them for slice i + 1
            return it, res, ev.grad, None
        try:
            if not stale:
                if blocks is None:
                    blocks = _fresh_blocks(ev, sys, cache)
                    if cache["singular"]:
                        return it, res, ev.grad, (*cache["singular"], res)
                cache["solve"], name = factor_step(sys, blocks, vol, cache.get("solver", "auto"), rtol * rscale)
                if cache.get("keep_factored"):  # a checkpoint rebuilds the factorisation from them
                    cache["factored"] = (blocks, rtol * rscale)
                used = cache.setdefault("used", [])
                if name not in used:
                    used.append(name)
            delta = cache["solve"](-r)
        except SolverRefused as exc:
            return it, res, ev.grad, (str(exc), None, res)
        except (np.linalg.LinAlgError, ValueError) as exc:
            cache.pop("solve", None)
            row = int(np.argmax(np.abs(r)))
            return it, res, ev.grad, (f"singular Jacobian (mixed Hessian) of the slice: {exc}", row, res)
        if not np.all(np.isfinite(delta)):
            cache.pop("solve", None)
            if stale:
                continue
            return (
                it,
                res,
                ev.grad,
                ("Newton step is not finite (singular mixed Hessian?)", int(np.argmax(np.abs(r))), res),
            )
        flat[i + 1, unk] += torch.from_numpy(delta.reshape(-1, m))
        small = not stale and float(np.abs(delta).max()) <= rtol * _scale(flat, i, unk)
    worst: int | None = int(np.argmax(np.abs(r))) if r.size else None
    return max_newton, res, ev.grad, (f"Newton did not converge in {max_newton} iterations", worst, res)
