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


@pytest.mark.parametrize(("ndim", "m"), [(1, 1), (2, 1), (3, 1), (1, 2)])
def test_the_columns_in_the_scaled_variables_equal_the_horner_forms(ndim: int, m: int) -> None:
    """The columns evaluated in the scaled variables (``zchain_cells``: each derivative in ``z`` by its tails'
    Horner chains, then the chain rule) equal the Horner forms of the columns themselves to round-off, every
    pass (gradients, gradients with blocks, blocks alone, the later points' gradients) the same columns to the
    bit as the others; a learned polynomial of the sine-Gordon class evaluates them that way."""
    import torch
    import xarray as xr
    from test_kernel import _field, _polynomial

    from latticedft._lattice import as_lattice_field
    from latticedft._serve import _folded
    from latticedft._serve._slices import _SliceSystem

    model = _polynomial(ndim, m)
    init = _field(ndim, {1: 40, 2: 9, 3: 5}[ndim])
    if m > 1:
        init = xr.concat([init + 0.1 * c for c in range(m)], dim="component").transpose(..., "component")
        init = init.assign_coords(component=[f"c{c}" for c in range(m)])
    sys_ = _SliceSystem(model, as_lattice_field(init, source="init", min_slices=2))
    rng = np.random.default_rng(ndim)
    flat = torch.from_numpy(rng.uniform(-0.9, 0.9, (2, sys_.nsite, m)))
    lo, hi = flat[0].numpy(), flat[1].numpy()
    got = {}
    for z in (False, True):
        _folded._DATA.clear()
        _folded.ZFORMS = z
        try:
            folded = _folded.folded_slices(model, sys_, flat)
            assert folded is not None
            grad = folded.columns(lo, hi, folded.grad_data)
            together, held, first = folded.both_columns(lo, hi)
            alone, start = folded.block_columns(lo, hi)
            later = folded.grad(flat, 0)
            got[z] = (grad, together, np.asarray(held[:, first:]), np.asarray(alone[:, start:]), later)
            assert folded.kept["zchain"] is z
        finally:
            _folded.ZFORMS = True
            _folded._DATA.clear()
    grad, together, held, alone, later = got[True]
    up = np.repeat(folded.upper.astype(bool), m)
    assert np.array_equal(grad, together) and np.array_equal(held, alone)
    assert np.array_equal(later[:, up], grad[:, up]) and not later[:, ~up].any()
    for a, b in zip(got[True], got[False]):
        assert a.shape == b.shape and np.abs(a - b).max() <= 1e-13 * np.abs(b).max()


def test_the_scaled_variable_kernel_of_a_pattern() -> None:
    """``zchain_cells`` of a small pattern written by hand: two tails, a derivative of two chains and one of one,
    two columns from them, the second into ``rest``; against the same sums in numpy."""
    from latticedft._kernel_zchain import zchain_kernel

    tails = ((0, 0), (0, 1))  # 1 and z1 (z0 the head)
    chains = ((0, 0, 2), (1, 0, 1), (1, 1, 0))  # d0 = P(z0) + z1 Q(z0), d1 = z1 * c
    kernel = zchain_kernel(0, tails, chains, ((0,), (0, 1)), 2, 1)
    assert kernel is not None
    rng = np.random.default_rng(3)
    lo, hi = rng.uniform(-1, 1, (30, 1)), rng.uniform(-1, 1, (30, 1))
    site_of = rng.integers(0, 30, size=(2, 300)).astype(np.int64)
    upper = np.array([0, 1], dtype=np.int64)
    w, shift = rng.normal(size=(2, 2)), rng.normal(size=2)
    coef = rng.normal(size=(3, 3))
    coef[1, 2] = coef[2, 1:] = 0.0
    cmat = rng.normal(size=(2, 2))
    out, rest = np.empty((300, 1)), np.empty((1, 300))
    kernel(lo, hi, site_of, upper, w, shift, coef, cmat, out, rest)
    x = np.stack([lo[site_of[0], 0], hi[site_of[1], 0]], axis=1)
    z = x @ w - shift
    d0 = np.polyval(coef[0, ::-1], z[:, 0]) + z[:, 1] * np.polyval(coef[1, 1::-1], z[:, 0])
    d1 = z[:, 1] * coef[2, 0]
    np.testing.assert_allclose(out[:, 0], cmat[0, 0] * d0, rtol=1e-13, atol=1e-13)
    np.testing.assert_allclose(rest[0], cmat[0, 1] * d0 + cmat[1, 1] * d1, rtol=1e-13, atol=1e-13)
