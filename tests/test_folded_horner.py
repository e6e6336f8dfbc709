"""The folded polynomial's columns by Horner's rule in one variable (``horner_cells``) equal the monomial kernel's."""

from __future__ import annotations

import itertools

import numpy as np
import pytest


def _forms(nvar: int, cols: int, degree: int, seed: int) -> tuple[np.ndarray, ...]:
    """Random folded forms ``(w, shift, expo, gc)``: every monomial of degree ``<= degree`` in variable 1 (the
    head) times one of degree ``<= 2`` in the others, some columns of it zero."""
    rng = np.random.default_rng(seed)
    tails = [e for e in itertools.product(range(3), repeat=nvar - 1) if sum(e) <= 2]
    expo = np.array([(*t[:1], d, *t[1:]) for t in tails for d in range(degree + 1)], dtype=np.int64)
    gc = rng.normal(size=(expo.shape[0], cols)) / (1.0 + expo.sum(axis=1, keepdims=True))
    gc[rng.random(gc.shape) < 0.2] = 0.0
    k = 4
    w = rng.normal(size=(k, nvar)) * 0.5
    return w, rng.normal(size=nvar) * 0.1, expo, gc


@pytest.mark.parametrize(("nvar", "cols", "degree"), [(4, 4, 12), (3, 7, 6), (1, 2, 5)])
def test_horner_columns_equal_the_monomials(nvar: int, cols: int, degree: int) -> None:
    from latticedft._kernel_folded import folded_kernels
    from latticedft._serve._folded import _horner

    mod = folded_kernels()
    assert mod is not None
    w, shift, expo, gc = _forms(nvar, cols, degree, seed=nvar + cols)
    rng = np.random.default_rng(1)
    lo, hi = rng.uniform(-1, 1, (40, 1)), rng.uniform(-1, 1, (40, 1))
    site_of = rng.integers(0, 40, size=(4, 300)).astype(np.int64)
    upper = np.array([0, 1, 0, 0], dtype=np.int64)
    want, got = np.empty((300, cols)), np.empty((300, cols))
    mod.folded_cells(lo, hi, site_of, upper, w, shift, expo, gc, want)
    mod.horner_cells(lo, hi, site_of, upper, *_horner((w, shift, expo, gc)), got)
    assert np.abs(got - want).max() <= 1e-13 * np.abs(want).max()


def test_horner_is_chosen_only_where_it_takes_fewer_products() -> None:
    from latticedft._serve._folded import _horner

    w, shift, expo, gc = _forms(4, 4, 12, seed=0)
    forms = _horner((w, shift, expo, gc))
    assert int((forms[5] + 1).sum()) <= expo.shape[0] * (4 + 4)  # dense in the head: Horner
    sparse = expo[expo[:, 1] % 6 == 0]  # degrees 0, 6, 12 of the head only: the monomials are fewer
    sparse_forms = _horner((w, shift, sparse, gc[: sparse.shape[0]]))
    assert int((sparse_forms[5] + 1).sum()) > sparse.shape[0] * (4 + 4)
