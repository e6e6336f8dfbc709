"""Numpy closed forms of a sparse library's terms, for serving.

The same sympy derivatives as :mod:`latticedft._models._termderiv` (each term's first and second derivatives in
its inputs ``w``), lambdified with numpy instead of torch and built once per list of term names. For a model's
kept terms and coefficients, the chain rule through the input maps ``A`` (``w = A x``, derivative rows over the
spacing) and the sum over terms are folded into two constant matrices, so one evaluation is the lambdified
derivatives on every cell and two matrix products: ``fn(cells (B, K, m)) -> (dL/dx, [blocks per pair])``, the
contract of :meth:`latticedft.AbstractLagrangian.numpy_derivatives` that the 1D numpy Newton loop serves.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from .._contract import NumpyForms
from ._termderiv import _derive
from ._terms import Term

__all__ = ["NumpyTermDerivatives", "numpy_term_derivatives", "numpy_forms"]


@dataclass(frozen=True)
class NumpyTermDerivatives:
    """:class:`latticedft._models._termderiv.TermDerivatives` in numpy, first and second derivatives apart (a
    gradient alone skips the second): ``first_fn(*w)`` returns the values named by ``first``, ``second_fn(*w)``
    those named by ``second`` (a constant as a Python number)."""

    n_vars: int
    first: list[tuple[int, int]]
    second: list[tuple[int, int, int]]
    first_fn: Callable[..., Sequence[Any]]
    second_fn: Callable[..., Sequence[Any]]


#: The numpy functions a lambdified term derivative may call (the torch ones' names: the same printed code).
_NUMPY = {"sin": np.sin, "cos": np.cos, "exp": np.exp, "log": np.log, "sqrt": np.sqrt}

_CACHE: dict[tuple[tuple[str, ...], int, int], NumpyTermDerivatives | None] = {}


def numpy_term_derivatives(terms: Sequence[Term], n: int, m: int) -> NumpyTermDerivatives | None:
    """The derivatives of ``terms`` on a lattice of ``n`` axes and ``m`` components in numpy (None when a term
    has no sympy form); built once per list of term names, as the torch ones are."""
    key = (tuple(t.name for t in terms), n, m)
    if key not in _CACHE:
        _CACHE[key] = _build(terms, n, m)
    return _CACHE[key]


def _build(terms: Sequence[Term], n: int, m: int) -> NumpyTermDerivatives | None:
    import sympy

    got = _derive(terms, n, m)
    if got is None:
        return None
    first_fn = sympy.lambdify(got.w, got.exprs, modules=[_NUMPY, "math"])
    second_fn = sympy.lambdify(got.w, got.hessians, modules=[_NUMPY, "math"])
    return NumpyTermDerivatives(len(got.w), got.first, got.second, first_fn, second_fn)


def numpy_forms(
    rule: NumpyTermDerivatives,
    maps: Sequence[np.ndarray],
    spacing: Sequence[float],
    pairs: Sequence[tuple[int, int]],
    coef: np.ndarray,
) -> NumpyForms:
    """``fn(cells (B, K, m)) -> (dL/dx (B, K, m), [d^2 L / dx_a dx_b (B, m, m) for (a, b) in pairs])`` of
    ``L = sum_c coef_c mean over A in maps of T_c(A x)`` (each map ``(n + 1, K)``, before dividing the derivative
    rows by the spacing; ``coef`` one per term of ``rule``)."""
    k = maps[0].shape[1]
    m = rule.n_vars // (len(spacing) + 1)
    scale, inputs, spaced = _inputs(maps, tuple(spacing), m)
    count = len(maps)
    gmat = np.concatenate([_first_matrix(rule, a, scale, m, coef) for a in maps]) / count
    hmat = np.concatenate([_second_matrix(rule, a, scale, m, coef, pairs) for a in maps]) / count
    nf, ns, mm = len(rule.first), len(rule.second), m * m

    def derivatives(cells: np.ndarray) -> tuple[np.ndarray, list[np.ndarray]]:
        b = cells.shape[0]
        x = cells.reshape(b, k * m)
        first = np.empty((b, count * nf))
        second = np.empty((b, count * ns)) if pairs else None
        for j, p in enumerate(inputs):
            w = ((x @ p) / spaced).T
            _fill(first, j * nf, rule.first_fn(*w))
            if second is not None:
                _fill(second, j * ns, rule.second_fn(*w))
        grad = (first @ gmat).reshape(b, k, m)
        if second is None:
            return grad, []
        out = second @ hmat
        return grad, [out[:, q * mm : (q + 1) * mm].reshape(b, m, m) for q in range(len(pairs))]

    return derivatives


#: :func:`_inputs` of the last input maps met (a sparse fit builds the closed forms of every support it serves on
#: the same maps), at most :data:`INPUTS_KEPT`.
_INPUTS: dict[tuple[Any, ...], tuple[np.ndarray, list[np.ndarray], np.ndarray]] = {}
INPUTS_KEPT = 8


def _inputs(
    maps: Sequence[np.ndarray], spacing: tuple[float, ...], m: int
) -> tuple[np.ndarray, list[np.ndarray], np.ndarray]:
    """``(scale, inputs, spaced)`` of :func:`numpy_forms`: the derivative rows' scale, each map's inputs ``(K m,
    V)`` before dividing by the spacing, and that spacing per input; kept by the maps' numbers (the same maps,
    the same arrays; read only)."""
    key = (tuple((a.shape, a.tobytes()) for a in maps), spacing, m)
    if key not in _INPUTS:
        if len(_INPUTS) >= INPUTS_KEPT:
            del _INPUTS[next(iter(_INPUTS))]
        scale = np.array([1.0] + [1.0 / h for h in spacing])
        inputs = [np.kron(a.T, np.eye(m)) for a in maps]
        spaced = np.repeat(np.array([1.0, *spacing]), m)
        for a in (scale, spaced, *inputs):
            a.setflags(write=False)
        _INPUTS[key] = (scale, inputs, spaced)
    return _INPUTS[key]


def _fill(dst: np.ndarray, start: int, values: Sequence[Any]) -> None:
    """Columns ``start ..`` of ``dst`` set to ``values`` (arrays over the cells, or constants)."""
    for j, value in enumerate(values):
        dst[:, start + j] = value


def _first_matrix(
    rule: NumpyTermDerivatives, a_map: np.ndarray, scale: np.ndarray, m: int, coef: np.ndarray
) -> np.ndarray:
    """``(len(first), K m)``: the first derivatives in ``w`` (one map's) to ``dL/dx`` (flat), ``coef`` summed."""
    k = a_map.shape[1]
    out = np.zeros((len(rule.first), k, m))
    for j, (v, c) in enumerate(rule.first):
        r, i = divmod(v, m)
        out[j, :, i] = coef[c] * scale[r] * a_map[r]
    return out.reshape(len(rule.first), k * m)


def _second_matrix(
    rule: NumpyTermDerivatives,
    a_map: np.ndarray,
    scale: np.ndarray,
    m: int,
    coef: np.ndarray,
    pairs: Sequence[tuple[int, int]],
) -> np.ndarray:
    """``(len(second), len(pairs) m m)``: the second derivatives in ``w`` (``v <= u``, one map's) to the blocks
    ``d^2 L / dx_a dx_b`` (flat, pair after pair), ``coef`` summed."""
    out = np.zeros((len(rule.second), len(pairs), m, m))
    for j, (v, u, c) in enumerate(rule.second):
        (rv, iv), (ru, iu) = divmod(v, m), divmod(u, m)
        h = coef[c] * scale[rv] * scale[ru]
        for q, (a, b) in enumerate(pairs):
            out[j, q, iv, iu] += a_map[rv, a] * a_map[ru, b] * h
            if v != u:
                out[j, q, iu, iv] += a_map[ru, a] * a_map[rv, b] * h
    return out.reshape(len(rule.second), len(pairs) * m * m)
