"""The polynomial model's basis tables, shared by its torch forms (``_polynomial``) and numpy forms
(``_polynumpy``): the exact monomial coefficients of the basis polynomials and the order of variable pairs."""

from __future__ import annotations

import functools
from fractions import Fraction

import numpy as np
import torch

#: Highest degree whose basis tables are built as a Vandermonde matrix times constant coefficients; the
#: monomial coefficients of Legendre polynomials grow like 2^k, so above this the recurrence is kept.
_VANDERMONDE_MAX_DEGREE = 12


@functools.cache
def _coefficient_rows(basis: str, deg: int) -> tuple[tuple[Fraction, ...], ...]:
    """Monomial coefficients of the basis polynomials, exact: row ``k`` holds ``P_k`` (or ``z^k``)."""
    rows = [[Fraction(0)] * (deg + 1) for _ in range(deg + 1)]
    for k in range(deg + 1):
        if basis != "legendre" or k < 2:
            rows[k][k] = Fraction(1)
            continue
        j = k - 1  # (j+1) P_{j+1} = (2j+1) z P_j - j P_{j-1}
        for e in range(deg + 1):
            rows[k][e] = Fraction(2 * j + 1, j + 1) * (rows[j][e - 1] if e else 0) - Fraction(j, j + 1) * rows[j - 1][e]
    return tuple(tuple(r) for r in rows)


@functools.cache
def _coefficient_matrix_f64(basis: str, deg: int) -> torch.Tensor:
    rows = _coefficient_rows(basis, deg)
    w = deg + 1
    mat = np.zeros((w, 3 * w))  # powers (rows) -> [values | first derivatives | second derivatives] (columns)
    for k in range(w):
        for e in range(w):
            a = float(rows[k][e])
            mat[e, k] = a
            if e >= 1:
                mat[e - 1, w + k] = e * a
            if e >= 2:
                mat[e - 2, 2 * w + k] = e * (e - 1) * a
    return torch.from_numpy(mat)


@functools.cache
def _pairs(nvar: int) -> tuple[tuple[int, int], ...]:
    """Unordered variable pairs ``v <= w`` in the order of the second derivatives of ``_term_derivatives``."""
    return tuple((v, w) for v in range(nvar) for w in range(v, nvar))
