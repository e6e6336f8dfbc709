"""The compiled block-tridiagonal solve of a 1+1D slice Jacobian: equal to a dense solve, refused where it would
need pivoting between blocks, and serving the fields the sparse LU serves."""

from __future__ import annotations

import sys

import numpy as np
import pytest
import torch
from test_kernel import _polynomial
from test_solvers import _full_cell

import latticedft as ldft
from latticedft import systems
from latticedft._kernel_band import band_kernels
from latticedft._lattice import as_lattice_field
from latticedft._serve import _band
from latticedft._serve._band import band_factor, band_places
from latticedft._serve._slices import _SliceSystem

from helpers import smooth_start

# the module itself (the package `latticedft._serve` has a function of that name)
_slices_module = sys.modules["latticedft._serve._slices"]


def _dense(band: np.ndarray, wrap: bool) -> np.ndarray:
    """The matrix of ``band`` ``(3, n, m, m)``: row block ``x`` holds blocks at unknowns ``x - 1, x, x + 1``."""
    n, m = band.shape[1], band.shape[2]
    a = np.zeros((n * m, n * m))
    for x in range(n):
        for k, y in ((0, x - 1), (1, x), (2, x + 1)):
            if 0 <= y < n or wrap:
                a[x * m : (x + 1) * m, (y % n) * m : (y % n + 1) * m] += band[k, x]
    return a


def _random_band(n: int, m: int, seed: int, wrap: bool, couple: float = 0.3) -> np.ndarray:
    """A random, well-conditioned, block diagonally dominant system (off-diagonal blocks ``couple`` of the
    diagonal's size); without the wrap the corner blocks are zero, as a Jacobian's."""
    rng = np.random.default_rng(seed)
    band = couple * rng.uniform(-1, 1, (3, n, m, m)) / m
    band[1] = rng.uniform(-0.2, 0.2, (n, m, m)) / m + np.eye(m) * rng.choice([-1.0, 1.0], (n, 1, 1))
    if not wrap:
        band[0, 0] = band[2, n - 1] = 0.0
    return 1e3 * band  # a scale far from one


def _factor_solve(band: np.ndarray, wrap: bool, rhs: np.ndarray) -> tuple[int, np.ndarray | None]:
    mod = band_kernels()
    assert mod is not None
    status, *factors = mod.band_factor(band, wrap, 1e-8)
    return status, (mod.band_solve(band, wrap, *factors, rhs) if status == 0 else None)


@pytest.mark.parametrize("m", [1, 2, 3])
@pytest.mark.parametrize(("wrap", "n"), [(False, 1), (False, 2), (False, 9), (True, 3), (True, 4), (True, 17)])
def test_the_block_tridiagonal_solve_equals_a_dense_solve(m: int, wrap: bool, n: int) -> None:
    for seed in range(5):
        band = _random_band(n, m, seed, wrap)
        rhs = np.random.default_rng(100 + seed).standard_normal(n * m)
        status, x = _factor_solve(band, wrap, rhs)
        assert status == 0 and x is not None
        want = np.linalg.solve(_dense(band, wrap), rhs)
        assert np.abs(x - want).max() <= 1e-12 * np.abs(want).max(), (m, wrap, n, seed)
        if m == 1:  # the scalar kernels: the same elimination
            mod = band_kernels()
            flat = np.ascontiguousarray(band.reshape(3, n))
            status1, *factors = mod.band_factor1(flat, wrap, 1e-8)
            assert status1 == 0
            assert np.abs(mod.band_solve1(flat, wrap, *factors, rhs) - want).max() <= 1e-12 * np.abs(want).max()


@pytest.mark.parametrize("m", [1, 2])
@pytest.mark.parametrize("wrap", [False, True])
def test_the_elimination_is_refused_where_it_would_need_pivoting(m: int, wrap: bool) -> None:
    """Status 2 where a multiplier block exceeds 1 in norm, 1 where a pivot is below the tolerance (zero, or a
    singular periodic system whose last Schur complement vanishes) or an entry is not finite."""
    mod = band_kernels()
    kernels = [(mod.band_factor, lambda b: b)]
    if m == 1:
        kernels.append((mod.band_factor1, lambda b: np.ascontiguousarray(b.reshape(3, b.shape[1]))))
    for factor, shape in kernels:
        big = _random_band(8, m, 0, wrap)
        big[0, 4] = 3e3 * np.eye(m)  # below a pivot of about 1e3: a multiplier of about 3
        assert factor(shape(big), wrap, 1e-8)[0] == 2
        zero = _random_band(8, m, 1, wrap)
        zero[:, 0] = 0.0  # the first pivot block zero
        zero[0, 1] = 0.0
        assert factor(shape(zero), wrap, 1e-8)[0] == 1
        nan = _random_band(8, m, 2, wrap)
        nan[1, 5, 0, 0] = np.nan
        assert factor(shape(nan), wrap, 1e-8)[0] == 1
    if wrap:  # u_x - u_{x-1} on the periodic axis: every multiplier -1, the matrix singular (constants)
        shift = np.zeros((3, 8, m, m))
        shift[1], shift[0] = np.eye(m), -np.eye(m)
        assert mod.band_factor(shift, True, 1e-8)[0] == 1
        if m == 1:
            assert mod.band_factor1(np.ascontiguousarray(shift.reshape(3, 8)), True, 1e-8)[0] == 1


def _init(n: int, periodic: bool, m: int = 1):
    """Two slices at rest of a smooth 1+1D field on ``n`` sites (periodic or with fixed ends), ``m`` components
    (copies of one, shifted)."""
    init = smooth_start(1, n, periodic)
    if m == 1:
        return init
    values = np.stack([init.values + 0.1 * c for c in range(m)], axis=-1)
    attrs = {"x": {"periodic": "true", "period": n * 0.1}} if periodic else None
    comps = [f"c{c}" for c in range(m)]
    return systems.make_field(values, ("t", "x"), spacing=(0.04, 0.1), components=comps, coord_attrs=attrs)


def _system(model: ldft.AnalyticLagrangian | ldft.PolynomialLagrangian, n: int, periodic: bool, m: int = 1):
    """The 1+1D slice system of ``model`` on ``n`` sites (periodic or with fixed ends), ``m`` components."""
    f = as_lattice_field(_init(n, periodic, m), source="init", min_slices=2)
    model.bind(f.ndim, f.ncomp, f.spacing, f.components)
    return _SliceSystem(model, f)


@pytest.mark.parametrize("m", [1, 2])
@pytest.mark.parametrize("periodic", [True, False])
@pytest.mark.parametrize("full", [False, True])
def test_a_slice_jacobian_solved_in_its_band_equals_the_dense_solve(m: int, periodic: bool, full: bool) -> None:
    """Random Hessian blocks on the slice system of the first-order stencil (bidiagonal: each row couples its own
    unknown and the one before) and of the full unit cell (tridiagonal), the diagonal blocks made dominant:
    the band's solve equals numpy's dense solve of the slice Jacobian that ``matrix_entries`` assembles."""
    model = _full_cell(2) if full else ldft.AnalyticLagrangian(lambda c, h: 0 * c[..., 0, 0])
    sys_ = _system(model, 11, periodic, m)
    assert band_places(sys_) is not None
    rng = np.random.default_rng(3)
    ncell = sys_.site_of[0].size
    blocks = {p: torch.from_numpy(0.2 * rng.uniform(-1, 1, (ncell, m, m)) / m) for p in sys_.pairs}
    for p in sys_.diag_pairs:
        blocks[p] = blocks[p] + torch.from_numpy(np.tile(np.eye(m), (ncell, 1, 1)))
    solve = band_factor(sys_, blocks, 0.3)
    assert solve is not None
    rows, cols, vals = sys_.matrix_entries(blocks, 0.3)
    dense = np.zeros((sys_.n * m, sys_.n * m))
    np.add.at(dense, (rows, cols), vals)
    rhs = rng.standard_normal(sys_.n * m)
    want = np.linalg.solve(dense, rhs)
    assert np.abs(solve(rhs) - want).max() <= 1e-12 * np.abs(want).max()


def test_the_band_is_left_where_the_jacobian_is_not_block_tridiagonal_on_one_axis() -> None:
    """No places in 2+1D, nor on a periodic axis of two sites (the unknowns before and after a site coincide)."""
    assert band_places(_system(_full_cell(2), 2, True)) is None
    init = smooth_start(2, 5)
    f = as_lattice_field(init, source="init", min_slices=2)
    model = _full_cell(3)
    model.bind(f.ndim, f.ncomp, f.spacing, f.components)
    assert band_places(_SliceSystem(model, f)) is None


def _count_band(monkeypatch: pytest.MonkeyPatch) -> list[bool]:
    """The slice factorisations' band answers from now on: ``True`` where the band factorised, ``False`` where
    it refused."""
    used: list[bool] = []
    real = _band.band_factor

    def counted(*a):
        solve = real(*a)
        used.append(solve is not None)
        return solve

    monkeypatch.setattr(_slices_module, "band_factor", counted)
    return used


def _serve_both(model, init, monkeypatch: pytest.MonkeyPatch, **kw):
    """``model`` served from ``init`` with the compiled band (counting its factorisations) and without it."""
    used = _count_band(monkeypatch)
    fast = ldft.serve(model, init, progress=False, **kw)
    fast_used = list(used)
    monkeypatch.setattr(_band, "BAND_KERNEL", False)
    slow = ldft.serve(model, init, progress=False, **kw)
    assert not any(used[len(fast_used) :])
    return fast, slow, fast_used


@pytest.mark.parametrize(
    ("name", "m", "periodic"),
    [("periodic", 1, True), ("fixed ends", 1, False), ("periodic, two components", 2, True)],
)
def test_a_learned_polynomial_served_in_its_band_equals_the_sparse_lu(
    name: str, m: int, periodic: bool, monkeypatch: pytest.MonkeyPatch
) -> None:
    edge = {} if periodic else {"boundary_value": 0.3}
    fast, slow, used = _serve_both(_polynomial(1, m), _init(40, periodic, m), monkeypatch, slices=14, **edge)
    assert used and all(used), name  # every factorisation in the band
    assert fast.slice_solver == slow.slice_solver == "lu", name
    a, b = np.asarray(fast.field.values), np.asarray(slow.field.values)
    assert np.abs(a - b).max() <= 1e-12 * np.abs(b).max(), name
    assert fast.newton_iterations == slow.newton_iterations, name
    assert fast.complete and slow.complete and fast.warnings == slow.warnings, name


@pytest.mark.parametrize("periodic", [True, False])
def test_a_coupled_analytic_ld_served_in_its_band_equals_the_sparse_lu(
    periodic: bool, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The full unit cell's sine-Gordon: a tridiagonal slice Jacobian whose off-diagonal entries are not small."""
    edge = {} if periodic else {"boundary_value": 0.3}
    fast, slow, used = _serve_both(_full_cell(2), smooth_start(1, 24, periodic), monkeypatch, slices=12, **edge)
    assert used and all(used) and fast.slice_solver == "lu"
    a, b = np.asarray(fast.field.values), np.asarray(slow.field.values)
    assert np.abs(a - b).max() <= 1e-12 * np.abs(b).max()
    assert fast.newton_iterations == slow.newton_iterations and fast.complete


def test_a_singular_periodic_jacobian_is_left_to_the_sparse_lu_and_reported_as_before(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """``L = u1 (u0 - u2) + cos u0``: each mixed-Hessian block is 1 (the sites' singular values pass), but the
    periodic slice Jacobian ``I - shift`` is singular (constants). The band refuses it (its last Schur complement
    vanishes) and the sparse LU reports the slice as it does without the band, to the letter."""

    def fn(c, h):
        return c[..., 1, 0] * (c[..., 0, 0] - c[..., 2, 0]) + torch.cos(c[..., 0, 0])

    model = ldft.AnalyticLagrangian(fn, name="shift")
    init = smooth_start(1, 12, True)
    used = _count_band(monkeypatch)
    messages = []
    for flag in (True, False):
        monkeypatch.setattr(_band, "BAND_KERNEL", flag)
        with pytest.raises(ldft.ServeError) as err:
            ldft.serve(model, init, slices=6, progress=False)
        messages.append(str(err.value))
        if flag:
            assert used and not any(used)  # the band was asked and refused
    assert messages[0] == messages[1] and "singular Jacobian" in messages[0] and "slice 2" in messages[0]
