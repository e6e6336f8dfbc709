"""Slice-Newton on the model's device: every unknown site of a slice solved at once, on a GPU where the model
runs on one (``serve(device="cuda")``).

It serves a scalar ``L_d`` whose slice Jacobian is diagonal (each unknown's equation involves that unknown
alone: the site-wise solver). Before the first Newton slice a probe at the predictor measures the
Jacobian's off-diagonal blocks and the conditioning of its diagonal as slice-Newton's first iteration would
(``_stepper._choose_device``); where slice-Newton solved the first slice instead, the device takes over once
it has chosen the site-wise solver. The derivatives are sympy's of the model's closed form, generated once
as one torch function of the cells' columns (:func:`closed_terms`), or autograd's where it has none. The
last slices stay on the device between slices (a window keyed by the slice's index in the whole field), so
a slice costs one copy back to the host, of the slice solved, and none the other way on a periodic lattice.

Per slice: the predictor of slice-Newton; the gradients of the cells anchored on the slice before, once
(those of the last evaluation of the previous slice where it was solved here); then Newton's iterations,
each evaluating every cell anchored on the slice with its gradient and, per site, the second derivatives of
the pairs of points that sit on it (the Jacobian's diagonal). A site stops where its residual is below the
slice's tolerance, or one evaluation after a step below ``rtol`` times the values, as in the compiled CPU
kernel (:mod:`._fused`); a slice with a site that cannot finish (a Jacobian below the singular scale, a
residual that is not a number, no convergence) is handed back to slice-Newton, which reports it as usual.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import torch

from ._slices import SINGULAR_RTOL, _SliceSystem

__all__ = ["DeviceSlices", "device_slices", "ON_CPU"]

#: The generated derivatives of the closed forms met in this process, by expression and pairs (sympy
#: differentiates each once, not once per served field).
_CLOSED: dict[tuple[str, tuple[tuple[int, int], ...]], _Closed] = {}

#: Take this path on the CPU too (the tests compare it there with slice-Newton); serving uses it on CUDA only.
ON_CPU = False

#: The slices kept on the device: the three a slice's equations read (with the predictor's older one).
_WINDOW = 3


class DeviceSlices:
    """The device slice Newton of one served field: its index maps on the device and the slices kept there."""

    def __init__(self, model: Any, sys: _SliceSystem, where: torch.device):
        self.model, self.where = model, where
        self.site_of = [torch.from_numpy(s).to(where) for s in sys.site_of]  # per stencil point: its site, per cell
        self.upper = [o[0] == 1 for o in sys.st.offsets]  # the point sits on the next slice
        self.rows = torch.from_numpy(np.nonzero(sys.interior)[0]).to(where)
        self.interior = torch.from_numpy(sys.interior).to(where)
        self.pairs = sys.pairs  # (a point on this slice, a point on the next) of each Jacobian block
        self.same_site: list[
            tuple[int, int, torch.Tensor | None]
        ] = []  # (a, b, cells): the pairs' entries on the Jacobian's diagonal (cells None: all)
        for a, b in sys.pairs:
            same = self.site_of[a] == self.site_of[b]
            if bool(same.all()):
                self.same_site.append((a, b, None))
            elif bool(same.any()):
                self.same_site.append((a, b, same))
        self.every_site = int(self.rows.numel()) == sys.nsite  # no known site: the next slice is not copied over
        self.nsite = sys.nsite
        self.window: dict[int, torch.Tensor] = {}  # slice index in the whole field -> its values on the device
        self.lower: tuple[int, torch.Tensor] | None = None  # (anchor, gradients) of cells evaluated last

    def _slice(self, flat: torch.Tensor, j: int, at: int) -> torch.Tensor:
        """Slice ``j`` of ``flat`` (index ``at`` in the whole field) on the device, from the window or copied."""
        got = self.window.get(at)
        if got is None:
            got = flat[j].reshape(-1).to(self.where, copy=True)  # never a view of the host window
            self.window[at] = got
        return got

    def _cells(self, lo: torch.Tensor, hi: torch.Tensor) -> torch.Tensor:
        """``(cells, points, 1)``: the cells with their points on ``lo`` (this slice) and ``hi`` (the next)."""
        return torch.stack([(hi if up else lo)[s] for up, s in zip(self.upper, self.site_of)], dim=1)[..., None]

    def _scatter(self, grads: torch.Tensor, upper: bool) -> torch.Tensor:
        """Per site: the gradients at the stencil points on the cells' ``upper`` (or lower) slice that sit there."""
        out = torch.zeros(self.nsite, dtype=grads.dtype, device=grads.device)
        for a, (up, s) in enumerate(zip(self.upper, self.site_of)):
            if up == upper:
                out = out.index_add(0, s, grads[:, a, 0])
        return out

    @functools.cached_property
    def closed(self) -> _Closed | None:
        """The generated derivatives of the model's closed form (:func:`closed_terms`), made on the first
        Newton iteration (not for a probe alone); ``None``: autograd."""
        return closed_terms(self.model, [(a, b) for a, b, _ in self.same_site])

    def _at(self, values: torch.Tensor) -> torch.Tensor:
        """``values`` (one per site) at the unknown sites."""
        return values if self.every_site else values[self.rows]

    def _second(self, g: torch.Tensor, cells: torch.Tensor) -> dict[int, torch.Tensor]:
        """Per stencil point ``b`` on the next slice: the second derivatives of ``L_d`` by ``b`` and every point,
        ``(cells, points)``, from the gradients ``g`` of ``cells`` taken with a graph."""
        upper = [b for b, up in enumerate(self.upper) if up]
        return {
            b: torch.autograd.grad(g[:, b, 0].sum(), cells, retain_graph=k < len(upper) - 1)[0][..., 0].detach()
            for k, b in enumerate(upper)
        }

    def _gradients(self, lo: torch.Tensor, hi: torch.Tensor) -> torch.Tensor:
        """The gradients of ``L_d`` on the cells of ``lo`` and ``hi``: ``(cells, points, 1)``."""
        with torch.enable_grad():
            cells = self._cells(lo, hi).requires_grad_(True)
            (g,) = torch.autograd.grad(self.model(cells).sum(), cells)
        return g.detach()

    def _newton_terms(self, lo: torch.Tensor, hi: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """``(gradients, part of the residual per site, its derivative by the site's unknown)`` on the cells of
        ``lo`` and ``hi`` (the unknowns): the derivative sums, per site, the second derivatives of the pairs of
        points that sit on it (the Jacobian being diagonal, nothing else moves the site's equation). From the
        model's closed form where it has one (:func:`closed_terms`), else by autograd."""
        closed = self.closed
        if closed is not None:
            columns = [(hi if up else lo)[s] for up, s in zip(self.upper, self.site_of)]
            grads, seconds = closed(columns)
            g = torch.stack(grads, dim=1)[..., None]
        else:
            with torch.enable_grad():
                cells = self._cells(lo, hi).requires_grad_(True)
                (g,) = torch.autograd.grad(self.model(cells).sum(), cells, create_graph=True)
                second = self._second(g, cells)
            g = g.detach()
            seconds = [second[b][:, a] for a, b, _ in self.same_site]
        jac = torch.zeros_like(lo)
        for (a, _, same), h in zip(self.same_site, seconds):
            jac = (
                jac.index_add(0, self.site_of[a], h)
                if same is None
                else jac.index_add(0, self.site_of[a][same], h[same])
            )
        return g, self._scatter(g, upper=False), jac

    def _predicted(
        self, flat: torch.Tensor, i: int, at: int, older: torch.Tensor | None
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """``(prev, cur, nxt, pred)``: slices ``i - 1`` and ``i`` on the device, slice ``i + 1`` with slice-Newton's
        predictor on its unknown sites (``_stepper.solve_and_tally``'s, in its order), and those values alone."""
        prev, cur = self._slice(flat, i - 1, at - 1), self._slice(flat, i, at)
        pred = 2 * self._at(cur) - self._at(prev)
        if older is not None:
            pred = pred + (self._at(cur) - 2 * self._at(prev) + self._at(self._slice(older[None], 0, at - 2)))
        if self.every_site:
            return prev, cur, pred, pred
        nxt = flat[i + 1].reshape(-1).to(self.where, copy=True)
        nxt[self.rows] = pred
        return prev, cur, nxt, pred

    def probe(self, flat: torch.Tensor, i: int, at: int, older: torch.Tensor | None) -> dict[str, float]:
        """The sizes of slice ``i``'s Jacobian at the predictor, as slice-Newton's first iteration finds them
        (``_newton._fresh_blocks``, ``_solvers._diag_and_offdiag``): ``dmax`` (the largest Hessian block of a
        pair with a diagonal entry), ``smin`` and ``smax`` (the smallest and largest diagonal entry at an
        unknown site, in size) and ``off`` (the largest off-diagonal entry), each without the cell volume."""
        _, cur, nxt, _ = self._predicted(flat, i, at, older)
        with torch.enable_grad():
            cells = self._cells(cur, nxt).requires_grad_(True)
            (g,) = torch.autograd.grad(self.model(cells).sum(), cells, create_graph=True)
            second = self._second(g, cells)
        zero = cur.new_zeros(())
        diag, dmax, off, diagonal = torch.zeros_like(cur), zero, zero, False
        for a, b in self.pairs:
            block = second[b][:, a]
            rows, cols = self.site_of[a], self.site_of[b]
            inside = self.interior[rows] & self.interior[cols]
            same = inside & (rows == cols)
            diag = diag.index_add(0, rows[same], block[same])
            if bool(same.any()):
                dmax, diagonal = torch.maximum(dmax, block.abs().max()), True
            other = block[inside & (rows != cols)]
            off = torch.maximum(off, other.abs().max()) if other.numel() else off
        sv = torch.nan_to_num(self._at(diag).abs(), nan=0.0)
        low, high = (sv.min(), sv.max()) if sv.numel() else (zero + float("inf"), zero)
        found = dict(zip(("dmax", "smin", "smax", "off"), torch.stack([dmax, low, high, off]).tolist()))
        if not diagonal:
            found["dmax"] = 1.0  # as ``_fresh_blocks`` without a diagonal pair
        return found

    def solve(
        self,
        flat: torch.Tensor,
        i: int,
        at: int,
        older: torch.Tensor | None,
        vol: float,
        rtol: float,
        max_newton: int,
        cache: dict,
    ) -> tuple[int, float] | None:
        """Solve slice ``i``'s equations for slice ``i + 1`` of ``flat`` (``(slices, sites, 1)``; slice ``i``
        is slice ``at`` of the whole field): ``(evaluations, residual)`` (the most of any site), or ``None``
        where a site failed (slice-Newton then solves the slice afresh)."""
        prev, cur, nxt, pred = self._predicted(flat, i, at, older)
        top = torch.stack([prev.abs().max(), cur.abs().max(), pred.abs().max() if pred.numel() else prev.new_zeros(())])
        scale = max(float(top.max()), 1e-300)  # slice-Newton's step scale (``_slices._scale``), one read back
        tol, step_tol = rtol * vol * cache["dmax"] * scale, rtol * scale
        smin = SINGULAR_RTOL * cache["mscale"] * vol
        if self.lower is not None and self.lower[0] == at - 1:
            fixed = self._scatter(self.lower[1], upper=True)
        else:
            fixed = self._scatter(self._gradients(prev, cur), upper=True)
        found = self._iterate(cur, nxt, fixed, vol, (tol, step_tol, smin), max_newton)
        if found is None:
            self.window.clear()
            self.lower = None
            return None
        its, res, grads = found
        self.lower = (at, grads)
        flat[i + 1].reshape(-1).copy_(nxt)  # the one copy to the host
        self.window[at + 1] = nxt
        for key in [k for k in self.window if k <= at + 1 - _WINDOW]:
            del self.window[key]
        return its, res

    def _iterate(
        self,
        cur: torch.Tensor,
        nxt: torch.Tensor,
        fixed: torch.Tensor,
        vol: float,
        tols: tuple[float, float, float],
        max_newton: int,
    ) -> tuple[int, float, torch.Tensor] | None:
        """Newton's iterations on every unknown site of ``nxt`` in place: ``(evaluations, residual, gradients
        of the last evaluation)``, or ``None`` where a site fails."""
        tol, step_tol, smin = tols
        r = self.rows
        active = torch.ones(r.numel(), dtype=torch.bool, device=self.where)
        small = torch.zeros_like(active)
        res = torch.zeros(r.numel(), dtype=torch.float64, device=self.where)
        for it in range(1, max_newton + 1):
            grads, part, jac = self._newton_terms(cur, nxt)
            resid = vol * self._at(fixed + part)
            size = resid.abs()
            not_a_number = (active & ~torch.isfinite(resid)).any()
            stop = active & ((size <= tol) | small)
            res = torch.where(stop, size, res)
            active &= ~stop
            diag = vol * self._at(jac)
            singular = (active & ~(diag.abs() > smin)).any()
            bad, left, flat_jac = torch.stack([not_a_number, active.any(), singular]).tolist()  # one read back
            if bad:
                return None
            if not left:  # the last sites stopped at this evaluation
                return it, float(res.max()) if res.numel() else 0.0, grads
            if it >= max_newton or flat_jac:
                return None
            step = torch.where(active, -resid / diag, torch.zeros_like(resid))
            if self.every_site:
                nxt += step
            else:
                nxt[r] = nxt[r] + step
            small = active & (step.abs() <= step_tol)
        return None


class _Closed:
    """The gradients of ``L_d`` at every stencil point and the second derivatives of some pairs of points, as
    one generated torch function of the cells' columns (sympy's derivatives of the closed form, common
    subexpressions shared): elementwise passes only, no autograd graph."""

    def __init__(self, fn: Callable[..., list[Any]], k: int):
        self.fn, self.k = fn, k

    def __call__(self, columns: Sequence[torch.Tensor]) -> tuple[list[torch.Tensor], list[torch.Tensor]]:
        out = self.fn(*columns)
        full = [v if isinstance(v, torch.Tensor) else torch.full_like(columns[0], float(v)) for v in out]
        return full[: self.k], full[self.k :]


def closed_terms(model: Any, pairs: list[tuple[int, int]]) -> _Closed | None:
    """The generated gradients and second derivatives of ``pairs`` of ``model``'s closed form (scalar), or
    ``None`` without one (autograd then serves)."""
    try:
        form = model.symbolic()
    except Exception:  # noqa: BLE001 - a model whose trace fails has no closed form here
        return None
    if form is None or form.m != 1:
        return None
    key = (sympy_key(form.expr), tuple(pairs))
    if key in _CLOSED:
        return _CLOSED[key]
    import sympy

    symbols = form.flat_symbols()
    grads = [sympy.diff(form.expr, x) for x in symbols]
    seconds = [sympy.diff(grads[a], symbols[b]) for a, b in pairs]
    fn = sympy.lambdify(symbols, grads + seconds, modules="torch", cse=True)
    _CLOSED[key] = _Closed(fn, len(symbols))
    return _CLOSED[key]


def sympy_key(expr: Any) -> str:
    """A key of a sympy expression that tells apart what prints alike (``srepr``)."""
    import sympy

    return str(sympy.srepr(expr))


def device_slices(model: Any, sys: _SliceSystem, flat: torch.Tensor, where: torch.device) -> DeviceSlices | None:
    """The device slice Newton for ``model`` on ``sys``, or ``None``: for a scalar field in double precision,
    served on CUDA (or anywhere with :data:`ON_CPU`)."""
    if sys.m != 1 or flat.dtype != torch.float64 or not (where.type == "cuda" or ON_CPU):
        return None
    return DeviceSlices(model, sys, where)
