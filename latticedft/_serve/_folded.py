"""Slice-Newton of a polynomial ``L_d`` on compiled kernels: the stencil gathered, the derivatives of its folded
coefficients evaluated and the residual scattered in one compiled pass per Newton iteration.

The polynomial's numpy forms fold its coefficients onto the monomials of its scaled variables
(``latticedft._models._polynumpy``). The kernels of ``latticedft._kernel_folded.folded_kernels`` take those folded
coefficients as data, so one build serves every polynomial (any orders, stencil, dimension, components). Here
they replace, inside slice-Newton (``._newton._newton_slice``: the same iterations, tests and linear solves),
the gathering of the cells, the numpy evaluation of their gradients, the residual's scatter and the
predictor; the Hessian blocks of a fresh Jacobian come from the same kernel with the blocks' columns. The
values differ from the numpy forms' by round-off only (the sums run in another order). The path is the
default (it serves a dense polynomial in about half the numpy forms' time: docs/performance.md); it is left
where ``set_options(compiled_kernels=False)`` asks, and where numba cannot build the kernels.
"""

from __future__ import annotations

import logging
import weakref
from collections.abc import Callable
from typing import Any

import numpy as np
import torch

from .._kernel_folded import folded_cells_kernel, folded_kernels, horner_cells_kernel
from .._kernel_zchain import zchain_kernel
from .._models import PolynomialLagrangian
from .._models._polynumpy import _numpy_forms
from .._options import option
from ._slices import Blocks, _SliceSystem

__all__ = ["FoldedSlices", "folded_slices", "folds", "not_affine_by_forms"]

log = logging.getLogger("latticedft")


def _data(model: PolynomialLagrangian, pairs: list[tuple[int, int]]) -> tuple[np.ndarray, ...] | None:
    """``(w, shift, expo, gc)`` of the folded forms for ``pairs``: the scaled variables ``z = x.flat @ w -
    shift``, the exponents ``(monomials, V)`` of the monomials some derivative needs and the matrix
    ``(monomials, K m + pairs m m)`` from them to ``[dL/dx | blocks]``; ``None`` where the model does not fold."""
    folded = _numpy_forms(model, pairs)[1]
    if folded is None:
        return None
    keep = np.nonzero(np.any(folded.g_chain != 0, axis=1))[0]
    expo = np.stack(np.unravel_index(keep, folded.widths)).T if folded.widths else np.zeros((keep.size, 0))
    return (
        np.ascontiguousarray(folded.w, dtype=np.float64),
        np.ascontiguousarray(folded.shift, dtype=np.float64),
        np.ascontiguousarray(expo, dtype=np.int64),
        np.ascontiguousarray(folded.g_chain[keep], dtype=np.float64),
    )


def _horner(data: tuple[np.ndarray, ...]) -> tuple[Any, ...]:
    """``(w, shift, head, texp, coef, top)``: the folded forms ``(w, shift, expo, gc)`` as polynomials in one
    variable (``head``, the one of highest degree) per tail (the monomial of the others, ``texp`` ``(tails, V)``
    with the head's exponent 0): ``coef[tail, column, e]`` the coefficient of ``z_head^e``, ``top[tail, column]``
    its degree (``-1``: none)."""
    w, shift, expo, gc = data
    head = int(np.argmax(expo.max(axis=0))) if expo.size else 0
    rest = expo.copy()
    if rest.size:
        rest[:, head] = 0
    texp, which = np.unique(rest, axis=0, return_inverse=True)
    deg = int(expo[:, head].max()) if expo.size else 0
    coef = np.zeros((texp.shape[0], gc.shape[1], deg + 1))
    coef[which.reshape(-1), :, expo[:, head] if expo.size else 0] = gc
    nonzero = coef != 0
    top = np.where(nonzero.any(axis=2), deg - np.argmax(nonzero[:, :, ::-1], axis=2), -1)
    return (
        w,
        shift,
        head,
        np.ascontiguousarray(texp, dtype=np.int64),
        np.ascontiguousarray(coef),
        np.ascontiguousarray(top, dtype=np.int64),
    )


#: Per model, the folded data for its pairs with the parameters and buffers they were built from.
_DATA: weakref.WeakKeyDictionary[Any, tuple[list[tuple[torch.Tensor, int]], tuple[Any, ...], tuple[Any, Any]]] = (
    weakref.WeakKeyDictionary()
)


def per_model_state(
    cache: weakref.WeakKeyDictionary[Any, Any], model: Any, key: tuple[Any, ...], build: Callable[[], Any]
) -> tuple[Any, bool]:
    """``(build(), True)`` the first time for ``model`` in its present state (its parameters and buffers, the
    same tensors unchanged in place) and ``key``, kept in ``cache``; ``(that value, False)`` after."""
    state = [(t, t._version) for t in [*model.parameters(), *model.buffers()]]
    known = cache.get(model)
    same = known is not None and known[1] == key and len(known[0]) == len(state)
    if known is not None and same and all(a is b and u == v for (a, u), (b, v) in zip(known[0], state)):
        return known[2], False
    built = build()
    cache[model] = (state, key, built)
    return built, True


def _zsource(model: PolynomialLagrangian, pairs: list[tuple[int, int]]) -> tuple[np.ndarray, ...] | None:
    """``(w, shift, expo, g, chain)``: the folded forms for ``pairs`` in the scaled variables, the exponents
    ``(monomials, V)`` of every monomial, ``g`` from them to ``[dL/dz | d2L/dz_v dz_w]`` and ``chain`` from those
    to ``[dL/dx | blocks]`` (:func:`_zforms`); ``None`` where the model does not fold."""
    folded = _numpy_forms(model, pairs)[1]
    if folded is None or folded.g is None or folded.chain is None:
        return None
    size = int(np.prod(folded.widths)) if folded.widths else 1
    expo = np.stack(np.unravel_index(np.arange(size), folded.widths)).T if folded.widths else np.zeros((1, 0))
    return (
        np.ascontiguousarray(folded.w, dtype=np.float64),
        np.ascontiguousarray(folded.shift, dtype=np.float64),
        np.ascontiguousarray(expo, dtype=np.int64),
        np.asarray(folded.g, dtype=np.float64),
        np.asarray(folded.chain, dtype=np.float64),
    )


def _zforms(source: tuple[np.ndarray, ...], columns: np.ndarray) -> tuple[tuple[Any, ...], tuple[Any, ...], int]:
    """``(forms, pattern, madds)``: the ``columns`` of ``[dL/dx | blocks]`` as ``zchain_cells`` evaluates them
    (``latticedft._kernel_zchain.zchain_kernel``): the derivatives in the scaled variables that those columns read
    (``d``, in the order of ``g``'s columns), each a sum over its tails (the monomials of the variables but the
    head, the variable of highest degree; in ``np.unique``'s order) of the tail times a polynomial in the head
    (a Horner chain of the chain's own degree), then each column ``sum_d cmat[d, column] * d``. ``forms``:
    ``(w, shift, coef, cmat)`` (``coef[chain, e]``: the coefficient of ``z_head^e``); ``pattern``: ``(head,
    tails, chains, outputs, derivatives)``, :func:`zchain_kernel`'s arguments; ``madds``: its multiply-adds per
    cell. A derivative's chains, and a column's sum, are the same whatever else ``columns`` holds: each column
    is the same to the bit in every subset."""
    w, shift, expo, g, chain = source
    nvar = expo.shape[1]
    used = np.any(g != 0, axis=1)
    head = int(np.argmax(expo[used].max(axis=0))) if used.any() and nvar else 0
    sub = chain[:, columns]
    ds = [q for q in range(g.shape[1]) if np.any(sub[q] != 0) and np.any(g[:, q] != 0)]
    keep = np.nonzero(np.any(g[:, ds] != 0, axis=1))[0] if ds else np.zeros(0, dtype=np.int64)
    rest = expo[keep].copy()
    if nvar:
        rest[:, head] = 0
    tails, which = np.unique(rest, axis=0, return_inverse=True)
    deg = int(expo[keep, head].max()) if keep.size and nvar else 0
    per = np.zeros((tails.shape[0], len(ds), deg + 1))
    if keep.size:
        per[which.reshape(-1), :, expo[keep, head] if nvar else 0] = g[keep][:, ds]
    chains, rows = [], []
    for d in range(len(ds)):
        for t in range(tails.shape[0]):
            nonzero = np.nonzero(per[t, d])[0]
            if nonzero.size:
                top = int(nonzero.max())
                chains.append((t, d, top))
                rows.append(per[t, d, : top + 1])
    coef = np.zeros((max(len(chains), 1), deg + 1))
    for i, row in enumerate(rows):
        coef[i, : row.size] = row
    cmat = np.ascontiguousarray(sub[ds] if ds else np.zeros((1, len(columns))))
    outputs = tuple(tuple(d for d in range(len(ds)) if cmat[d, c] != 0) for c in range(len(columns)))
    pattern = (head, tuple(tuple(int(e) for e in t) for t in tails), tuple(chains), outputs, len(ds))
    madds = sum(c[2] + 1 for c in chains) + sum(len(o) for o in outputs)
    return (w, shift, coef, cmat), pattern, madds


#: Columns are evaluated in the scaled variables (:func:`_zforms`) where that takes fewer multiply-adds than the
#: Horner forms of the columns themselves (``ZFORMS = False``: never; the Horner forms serve).
ZFORMS = True


def _data_of(model: PolynomialLagrangian, pairs: list[tuple[int, int]]) -> tuple[Any, Any, dict[str, Any], Any]:
    """``(_data(model, []), _data(model, pairs), kept, _zsource(model, pairs))``, built once per model state,
    pairs and ``folded_max_powers`` (the option that decides whether the coefficients fold); ``kept``: what
    :class:`FoldedSlices` derives from them (Horner forms, kernels), for later fields of the same state."""
    key = (tuple(pairs), option("folded_max_powers"))
    built, fresh = per_model_state(
        _DATA, model, key, lambda: (_data(model, []), _data(model, pairs), {}, _zsource(model, pairs))
    )
    if fresh and (built[0] is None or built[1] is None):  # once per model state
        log.info(
            "compiled polynomial kernels unavailable for %s (its coefficients do not fold onto few monomials): "
            "serving uses its numpy forms",
            type(model).__name__,
        )
    return built


#: The written-out Horner kernel (``horner_cells_kernel``) serves forms whose chains use at least this share of
#: its multiply-adds (it runs every (tail, column) to the full degree, each about a quarter cheaper than
#: ``horner_cells``'s, which stops at each chain's own degree and skips empty ones).
HORNER_CLASS_FILL = 0.8


def _horner_kernel(forms: tuple[Any, ...], mod: Any) -> Any:
    """The kernel for the Horner ``forms``: the one written out for their columns and degree where their chains
    fill it (:data:`HORNER_CLASS_FILL`) and it builds, else the module's ``horner_cells``."""
    coef, top = forms[4], forms[5]
    full = coef.size
    if full and int((top + 1).sum()) >= HORNER_CLASS_FILL * full:
        kernel = horner_cells_kernel(coef.shape[1], coef.shape[2] - 1)
        if kernel is not None:
            return kernel
    return mod.horner_cells


def _cell_at(site_of: np.ndarray, nsite: int) -> np.ndarray | None:
    """``(K, nsite)``: per stencil point and site, the cell whose point that site is (``-1``: none), for the
    residual read per equation row (``gather_residual``); ``None`` where a point is the same site in two cells
    (a lattice narrower than the stencil), which only the scatter sums."""
    cell_at = np.full((site_of.shape[0], nsite), -1, dtype=np.int64)
    cells = np.arange(site_of.shape[1], dtype=np.int64)
    for a in range(site_of.shape[0]):
        cell_at[a, site_of[a]] = cells
        if not np.array_equal(cell_at[a, site_of[a]], cells):  # a site written twice keeps one cell only
            return None
    return cell_at


class FoldedCells:
    """The cells anchored on one slice, their gradients evaluated (``grad``: ``(cells, K m)``), their Hessian
    blocks on demand (what slice-Newton reads of ``CellDerivatives``), or evaluated with the gradients in one
    pass where ``with_blocks`` says they will be read (the gradients are the same columns, to the bit)."""

    def __init__(self, owner: FoldedSlices, lo: np.ndarray, hi: np.ndarray, with_blocks: bool = False):
        self.owner, self.lo, self.hi = owner, lo, hi
        self.both: tuple[np.ndarray, int] | None = None  # the blocks' columns (cells, ...) from the index given on
        if with_blocks:
            self.grad, held, first = owner.both_columns(lo, hi)
            self.both = (held, first)
        else:
            self.grad = owner.columns(lo, hi, owner.grad_data)

    def blocks(self, pairs: list[tuple[int, int]]) -> dict[tuple[int, int], torch.Tensor]:
        """The Hessian blocks ``(cells, m, m)`` of ``pairs`` (the slice system's pairs): from the columns evaluated
        with the gradients, else from a pass of the blocks' columns alone (:meth:`FoldedSlices.block_columns`)."""
        o = self.owner
        mm = o.m * o.m
        if self.both is not None:
            out, first = self.both
        else:
            out, first = o.block_columns(self.lo, self.hi)
        blocks = Blocks(
            (
                p,
                torch.from_numpy(
                    np.ascontiguousarray(out[:, first + q * mm : first + (q + 1) * mm]).reshape(-1, o.m, o.m)
                ),
            )
            for q, p in enumerate(pairs)
        )
        if list(pairs) == list(o.sys.pairs):  # the slice Jacobian's entries read from the columns themselves
            blocks.columns = (out, first)
        return blocks


class FoldedSlices:
    """The folded kernels of one served field: the model's folded coefficients and the slice's index maps."""

    def __init__(
        self,
        mod: Any,
        sys: _SliceSystem,
        grad_data: tuple[np.ndarray, ...],
        both_data: tuple[np.ndarray, ...],
        kept: dict[str, Any] | None = None,
        zsource: tuple[np.ndarray, ...] | None = None,
    ):
        self.mod = mod
        self.zsource = zsource
        self.k, self.m = len(sys.st.offsets), sys.m
        if "folded_maps" not in sys.kept:  # per lattice
            site_of = np.ascontiguousarray(np.stack(sys.site_of), dtype=np.int64)  # (K, cells)
            upper = np.array([o[0] for o in sys.st.offsets], dtype=np.int64)  # 1: the point is on the next slice
            sys.kept["folded_maps"] = (
                site_of,
                upper,
                np.ascontiguousarray(np.nonzero(sys.interior)[0], dtype=np.int64),
            )
        self.site_of, self.upper, self.rows = sys.kept["folded_maps"]
        self.grad_data, self.both_data = grad_data, both_data
        self.el = np.empty((sys.nsite, sys.m))
        # what is derived from the data, kept per model state (``kept``, from _data_of) for this module's kernels
        self.kept = {} if kept is None else kept
        if self.kept.get("mod") is not mod:
            self.kept.clear()
            self.kept["mod"] = mod
        self.cells: dict[tuple[int, int], Any] = self.kept.setdefault("cells", {})  # folded_cells per (V, columns)
        self.horner: dict[int, tuple[Any, ...] | None] = self.kept.setdefault("horner", {})  # per data (id): forms
        self.horner_kernel: dict[int, Any] = self.kept.setdefault("kernel", {})  # per data (id): their kernel
        self.sys = sys

    @property
    def cell_at(self) -> np.ndarray | None:
        """:func:`_cell_at` of the slice's cells, kept with the slice system (per lattice)."""
        if "cell_at" not in self.sys.kept:
            self.sys.kept["cell_at"] = _cell_at(self.site_of, self.sys.nsite)
        cell_at: np.ndarray | None = self.sys.kept["cell_at"]
        return cell_at

    def columns(self, lo: np.ndarray, hi: np.ndarray, data: tuple[np.ndarray, ...]) -> np.ndarray:
        """The folded forms' columns on every cell anchored on slice ``lo`` (``hi``: the next one): by Horner's
        rule in the head variable (``horner_cells``) where that takes fewer products than the monomials, else
        by the monomial kernel of the polynomial's class where it builds, else the generic one."""
        nvar, cols = data[0].shape[1], data[3].shape[1]
        zpass = self._zpass("grad", list(range(cols)), cols) if data is self.grad_data else None
        if zpass is not None:
            return self._run(zpass, lo, hi)[0]
        out = np.empty((self.site_of.shape[1], cols))
        forms = self._horner_forms(data)
        if forms is not None:
            self.horner_kernel[id(data)](lo, hi, self.site_of, self.upper, *forms, out)
            return out
        if (nvar, cols) not in self.cells:
            self.cells[(nvar, cols)] = folded_cells_kernel(nvar, cols) or self.mod.folded_cells
        self.cells[(nvar, cols)](lo, hi, self.site_of, self.upper, *data, out)
        return out

    def both_columns(self, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
        """``(grad, columns, first)``: the gradients ``(cells, K m)`` of the cells anchored on ``lo`` and their Hessian
        blocks' columns in one pass, the blocks in ``columns`` ``(cells, ...)`` from ``first`` on (in the scaled
        variables: ``first`` 0, a view of one contiguous row per column; else the whole pass's columns, ``first``
        ``K m``)."""
        km, width = self.k * self.m, self.both_data[3].shape[1]
        zpass = self._zpass("both", list(range(width)), km)
        if zpass is not None:
            grad, rest = self._run(zpass, lo, hi)
            return grad, rest.T, 0
        both = self.columns(lo, hi, self.both_data)
        return np.ascontiguousarray(both[:, :km]), both, km

    def _horner_forms(self, data: tuple[np.ndarray, ...]) -> tuple[Any, ...] | None:
        """The Horner forms of ``data`` where they take fewer products than its monomials (their kernel in
        ``horner_kernel``), else ``None``; chosen once per model state."""
        if id(data) not in self.horner:
            nvar, cols = data[0].shape[1], data[3].shape[1]
            built = _horner(data)
            fewer = int((built[5] + 1).sum()) <= data[2].shape[0] * (cols + nvar)
            self.horner[id(data)] = built if fewer else None
            self.horner_kernel[id(data)] = _horner_kernel(built, self.mod) if fewer else None
        return self.horner[id(data)]

    def grad(self, flat: torch.Tensor, i: int) -> np.ndarray:
        """The gradients ``(cells, K m)`` of the cells anchored on slice ``i`` as slice ``i + 1``'s residual reads
        them: the columns of the points on slice ``i + 1`` (``upper``: ``gather_residual`` and ``scatter`` read
        no other column of the earlier cells), the others zero. Where the gradients run by Horner's rule, the
        chains of those columns alone run (each column's chain is the same, so are its values to the bit)."""
        lo, hi = flat[i].numpy(), flat[i + 1].numpy()
        up = [a for a in range(self.k) if self.upper[a]]
        columns = [a * self.m + c for a in up for c in range(self.m)]
        zpass = self._zpass("later", columns, len(columns))
        later = zpass or self._subset_forms("later", self.grad_data, columns)
        if later is None:
            return FoldedCells(self, lo, hi).grad
        cols = later[2]
        if zpass is not None:
            part = self._run(zpass, lo, hi)[0]
        else:
            part = np.empty((self.site_of.shape[1], cols.size))
            later[1](lo, hi, self.site_of, self.upper, *later[0], part)
        out = np.zeros((self.site_of.shape[1], self.k * self.m))
        out[:, cols] = part
        return out

    def block_columns(self, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, int]:
        """``(columns, first)``: the Hessian blocks' columns of the cells anchored on ``lo`` from ``first`` on: where
        the forms run by Horner's rule, by the chains of those columns alone (``first`` 0; the same values to the
        bit as with the gradients' columns), else every column of ``both_data``."""
        km, width = self.k * self.m, self.both_data[3].shape[1]
        columns = list(range(km, width))
        zpass = self._zpass("blocks", columns, 0)
        if zpass is not None:
            return self._run(zpass, lo, hi)[1].T, 0
        blocks = self._subset_forms("blocks", self.both_data, columns)
        if blocks is None:
            return self.columns(lo, hi, self.both_data), km
        forms, kernel, cols = blocks
        out = np.empty((self.site_of.shape[1], cols.size))
        kernel(lo, hi, self.site_of, self.upper, *forms, out)
        return out, 0

    def _run(self, zpass: tuple[Any, ...], lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(out, rest)``: the columns of ``zpass`` (``_zpass``'s) on every cell anchored on ``lo``, the first
        ``split`` as ``(cells, split)``, the others as ``(columns - split, cells)``."""
        forms, kernel, cols, split = zpass
        ncell = self.site_of.shape[1]
        out, rest = np.empty((ncell, split)), np.empty((cols.size - split, ncell))
        kernel(lo, hi, self.site_of, self.upper, *forms, out, rest)
        return out, rest

    def _zpass(self, name: str, columns: list[int], split: int) -> tuple[Any, ...] | None:
        """``(forms, kernel, columns, split)``: the ``columns`` of ``[dL/dx | blocks]`` evaluated in the scaled
        variables (:func:`_zforms`, ``zchain_kernel``; those from ``split`` on written one contiguous row per
        column) where :data:`ZFORMS` is on and, for every column of the blocks' pass,
        that takes fewer multiply-adds than the Horner forms of the columns themselves (decided once per model
        state, so that every pass evaluates its columns the same way: each to the bit as in the others);
        ``None`` otherwise (or where the kernel does not build). Kept per model state under ``name``."""
        if "zchain" not in self.kept:
            every = self.both_data[3].shape[1]
            self.kept["zchain"] = False
            if ZFORMS and self.zsource is not None and self.zsource[4].shape[1] == every:
                _, _, madds = _zforms(self.zsource, np.arange(every))
                full = self._horner_forms(self.both_data)
                horner = int((full[5] + 1).sum()) if full is not None else self.both_data[2].shape[0] * every
                self.kept["zchain"] = madds < horner
        if not self.kept["zchain"]:
            return None
        key = "z " + name
        if key not in self.kept:
            cols = np.array(columns, dtype=np.int64)
            forms, pattern, _ = _zforms(self.zsource, cols)  # type: ignore[arg-type]
            head, tails, chains, outputs, ncomb = pattern
            kernel = zchain_kernel(head, tails, chains, outputs, ncomb, split)
            self.kept[key] = None if kernel is None else (forms, kernel, cols, split)
        got: tuple[Any, ...] | None = self.kept[key]
        return got

    def _subset_forms(
        self, name: str, data: tuple[np.ndarray, ...], columns: list[int]
    ) -> tuple[tuple[Any, ...], Any, np.ndarray] | None:
        """``(forms, kernel, columns)``: the Horner forms of ``data`` restricted to ``columns`` (the same head and
        tails, so each column's chain is the same), and their kernel; ``None`` where ``data`` does not run by
        Horner's rule. Kept per model state under ``name``."""
        if name not in self.kept:
            full = self._horner_forms(data)
            subset = None
            if full is not None:
                cols = np.array(columns, dtype=np.int64)
                forms = (*full[:4], np.ascontiguousarray(full[4][:, cols]), np.ascontiguousarray(full[5][:, cols]))
                subset = (forms, _horner_kernel(forms, self.mod), cols)
            self.kept[name] = subset
        kept: tuple[tuple[Any, ...], Any, np.ndarray] | None = self.kept[name]
        return kept

    def predict(self, flat: torch.Tensor, i: int, older: torch.Tensor | None) -> tuple[float, float, float]:
        """Slice-Newton's predictor on the unknown sites of slice ``i + 1`` (``_stepper.solve_and_tally``'s); returns
        the sizes of slices ``i - 1``, ``i`` and the predicted unknowns that the same pass measured: those of
        ``_slices._scale(flat, i, unknowns)`` at the predictor, in its order (``max(*sizes, 1e-300)``: a NaN first
        stays)."""
        old = older.numpy() if older is not None else np.zeros((0, self.m))
        a, b, c = self.mod.predict(flat[i - 1].numpy(), flat[i].numpy(), flat[i + 1].numpy(), old, self.rows)
        return float(a), float(b), float(c)

    def excess(self, model: Any, values: torch.Tensor) -> np.ndarray | None:
        """``(slices - 1, features)``: ``_range._excess`` of the served ``values`` ``(slices, *sites, m)``: the cells'
        stencil mean and differences in a compiled pass, their extremes per slice against ``model``'s training
        range; ``None`` without a range."""
        rng = model.trained_range()
        if rng is None or values.dtype != torch.float64 or not values.is_contiguous():
            return None
        rng = rng.to(torch.float64)
        lo, hi = rng[0], rng[1]
        span = torch.maximum(hi - lo, 1e-12 * torch.maximum(lo.abs(), hi.abs())).clamp_min(1e-300)  # as _excess
        proj = np.ascontiguousarray(model.proj.detach().to(torch.float64).numpy())
        flat = values.numpy().reshape(values.shape[0], -1, self.m)
        low, high, size = (t.reshape(-1).numpy() for t in (lo, hi, span))
        fmin, fmax = self._feature_range(flat, proj)
        # the largest excess over the cells from the features' extremes: subtraction and division by a positive
        # span are monotone, so this is the per-cell maximum to the bit (+ 0.0: no negative zero)
        out: np.ndarray = np.maximum(np.maximum(low - fmin, fmax - high), 0.0) / size + 0.0
        out[np.isnan(fmin) | np.isnan(fmax)] = np.inf
        return out

    def _feature_range(self, flat: np.ndarray, proj: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Per slice but the last and feature (``(slices - 1, features)``), the least and largest value of the
        feature over the cells anchored on the slice (a not-a-number wherever one is), in one compiled pass
        (``feature_extremes``: no array of the features themselves)."""
        nq = proj.shape[0] * self.m
        fmin, fmax = np.empty((flat.shape[0] - 1, nq)), np.empty((flat.shape[0] - 1, nq))
        self.mod.feature_extremes(flat, self.site_of, self.upper, proj, fmin, fmax)
        return fmin, fmax

    def evaluate(
        self, flat: torch.Tensor, vol: float, i: int, g_prev: Any, blocks: bool = False
    ) -> tuple[FoldedCells, np.ndarray]:
        """The cells anchored on slice ``i`` at the current state and the slice's DEL residual on its equation
        rows (``g_prev``: the gradients of the cells anchored on ``i - 1``, as this or ``CellDerivatives``
        gives them). ``blocks``: slice-Newton reads the Hessian blocks at this state (a fresh Jacobian), so they
        are evaluated with the gradients, in one pass."""
        ev = FoldedCells(self, flat[i].numpy(), flat[i + 1].numpy(), with_blocks=blocks)
        gp = g_prev.reshape(ev.grad.shape).numpy() if isinstance(g_prev, torch.Tensor) else g_prev
        r = np.empty(self.rows.size * self.m)
        gp = np.ascontiguousarray(gp)
        if self.cell_at is not None:
            self.mod.gather_residual(gp, ev.grad, self.cell_at, self.upper, self.rows, vol, r)
        else:
            self.mod.scatter(gp, ev.grad, self.site_of, self.upper, self.rows, vol, self.el, r)
        return ev, r


def _foldable(model: Any) -> bool:
    """Whether ``model`` may be served on the folded kernels: a polynomial ready for its numpy forms, on the
    CPU, where the ``compiled_kernels`` option is on (the default)."""
    if not option("compiled_kernels") or not isinstance(model, PolynomialLagrangian) or not model.numpy_ready:
        return False
    return all(t.device.type == "cpu" for t in [*model.parameters(), *model.buffers()])


def folds(model: Any, sys: _SliceSystem) -> bool:
    """Whether :func:`folded_slices` serves ``model`` on ``sys`` (with its values on the CPU in double precision),
    without building its kernels' maps on the lattice."""
    if not _foldable(model):
        return False
    grad_data, both_data, _, _ = _data_of(model, list(sys.pairs))
    return grad_data is not None and both_data is not None and folded_kernels() is not None


def folded_slices(model: Any, sys: _SliceSystem, flat: torch.Tensor) -> FoldedSlices | None:
    """The folded kernels for ``model`` on ``sys``, or ``None``: for a polynomial whose numpy forms fold its
    coefficients, with the values on the CPU in double precision, where the ``compiled_kernels`` option is on
    (the default) and numba builds the kernels."""
    if not _foldable(model):
        return None
    if flat.dtype != torch.float64 or flat.device.type != "cpu" or not flat.is_contiguous():
        return None
    grad_data, both_data, kept, zsource = _data_of(model, list(sys.pairs))
    if grad_data is None or both_data is None:
        return None
    mod = folded_kernels()
    return None if mod is None else FoldedSlices(mod, sys, grad_data, both_data, kept, zsource)


#: The affine probe (``._affine._AffineSlices.probe``) leaves a polynomial without its autograd pass where the
#: Hessian blocks of its folded forms at the probe's states differ from those at the first state by more than
#: this share of the largest entry there: 1e4 times the probe's own tolerance (1e-10), far beyond the round-off
#: by which the two evaluations of one polynomial differ, so the probe would find the same.
NOT_AFFINE_MARGIN = 1e-6

#: Per model, the folded forms of every pair of stencil points (the probe's Hessian), with the state they are of.
_ALL_PAIRS: weakref.WeakKeyDictionary[Any, Any] = weakref.WeakKeyDictionary()


def not_affine_by_forms(model: Any, states: np.ndarray) -> bool:
    """Whether the DEL of ``model`` is found not affine on its folded kernels: its Hessian blocks of every pair
    of stencil points on the cells ``states`` ``(cells, K, m)`` (the affine probe's, the first one the state
    the others are compared with) vary by more than :data:`NOT_AFFINE_MARGIN` of the largest entry on the
    first. ``False`` where they do not, or where the model is not served on the folded kernels (the probe
    decides then)."""
    if not _foldable(model):
        return False
    k, m = states.shape[1], states.shape[2]
    pairs = [(a, b) for a in range(k) for b in range(k)]
    key = (k, m, option("folded_max_powers"))
    data, _ = per_model_state(_ALL_PAIRS, model, key, lambda: _data(model, pairs))
    mod = folded_kernels() if data is not None else None
    if mod is None:
        return False
    ncell = states.shape[0]
    x = np.ascontiguousarray(states.reshape(ncell * k, m), dtype=np.float64)
    site_of = np.ascontiguousarray(np.arange(ncell * k, dtype=np.int64).reshape(ncell, k).T)  # each cell its own
    out = np.empty((ncell, data[3].shape[1]))
    mod.folded_cells(x, x, site_of, np.zeros(k, dtype=np.int64), *data, out)
    hess = out[:, k * m :]
    if not hess.size or not np.isfinite(hess).all():
        return False
    big = float(np.abs(hess[0]).max())
    return big > 0.0 and float(np.abs(hess - hess[0]).max()) > NOT_AFFINE_MARGIN * big
