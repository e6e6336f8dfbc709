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


@pytest.mark.parametrize(("nvar", "cols", "degree"), [(4, 4, 12), (3, 7, 6), (2, 1, 0)])
def test_the_written_out_horner_kernel_equals_horner_cells_to_the_bit(nvar: int, cols: int, degree: int) -> None:
    """Every column's chain written out for the class (columns, degree): the same multiply-adds in the same order
    as ``horner_cells``, chains of lower degree and empty columns (zero coefficients) included."""
    from latticedft._kernel_folded import folded_kernels, horner_cells_kernel
    from latticedft._serve._folded import _horner

    mod = folded_kernels()
    assert mod is not None
    w, shift, expo, gc = _forms(nvar, cols, degree, seed=7 * nvar + cols)
    forms = _horner((w, shift, expo, gc))
    assert int((forms[5] + 1).sum()) < forms[4].size or degree == 0  # some chains shorter than the class's
    kernel = horner_cells_kernel(forms[4].shape[1], forms[4].shape[2] - 1)
    assert kernel is not None
    rng = np.random.default_rng(2)
    lo, hi = rng.uniform(-1, 1, (40, 1)), rng.uniform(-1, 1, (40, 1))
    site_of = rng.integers(0, 40, size=(4, 700)).astype(np.int64)  # two whole chunks of 256 cells and a part
    upper = np.array([0, 1, 0, 0], dtype=np.int64)
    want, got = np.empty((700, cols)), np.empty((700, cols))
    mod.horner_cells(lo, hi, site_of, upper, *forms, want)
    kernel(lo, hi, site_of, upper, *forms, got)
    np.testing.assert_array_equal(got, want)


def test_the_residual_read_per_row_equals_the_scatter_to_the_bit() -> None:
    """``gather_residual`` (each equation row's terms read through the cell of each point) adds the terms in the
    order the scatter adds them; a point that is the same site in two cells is left to the scatter."""
    from latticedft._kernel_folded import folded_kernels
    from latticedft._serve._folded import _cell_at

    mod = folded_kernels()
    assert mod is not None
    rng = np.random.default_rng(5)
    nsite, k, m = 60, 4, 2
    site_of = np.stack([rng.permutation(nsite) for _ in range(k)])[:, :50].astype(np.int64)  # 50 cells
    upper = np.array([0, 1, 0, 0], dtype=np.int64)
    gprev, gcur = rng.standard_normal((50, k * m)), rng.standard_normal((50, k * m))
    rows = np.sort(rng.choice(nsite, 45, replace=False)).astype(np.int64)
    want, got = np.empty(rows.size * m), np.empty(rows.size * m)
    mod.scatter(gprev, gcur, site_of, upper, rows, 0.3, np.empty((nsite, m)), want)
    cell_at = _cell_at(site_of, nsite)
    assert cell_at is not None
    mod.gather_residual(gprev, gcur, cell_at, upper, rows, 0.3, got)
    np.testing.assert_array_equal(got, want)
    twice = site_of.copy()
    twice[2, 1] = twice[2, 0]
    assert _cell_at(twice, nsite) is None
