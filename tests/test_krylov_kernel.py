"""The compiled GMRES of Krylov steps: scipy's algorithm, the same steps to round-off, the same served fields."""

from __future__ import annotations

import importlib

import numpy as np
import pytest
import scipy.sparse
import scipy.sparse.linalg
from test_kernel import _field, _polynomial
from test_solvers import _full_cell

import latticedft as ldft
from latticedft._kernel_krylov import krylov_kernels

from helpers import membrane_field


def _system(n: int, m: int, coupling: float, seed: int) -> tuple[scipy.sparse.csr_matrix, np.ndarray]:
    """A sparse system of ``n`` block rows of ``m x m`` blocks: diagonal blocks near the identity, a few coupled
    neighbours (at -1, +3, -7 block rows, around the wrap) of size ``coupling``; and its inverted diagonal."""
    rng = np.random.default_rng(seed)
    size = n * m
    diag = np.eye(m) * 2.0 + 0.3 * rng.normal(size=(n, m, m))
    rows, cols, vals = [], [], []
    for q in range(n):
        for d, scale in ((0, 1.0), (-1, coupling), (3, coupling), (-7, coupling)):
            block = diag[q] if d == 0 else scale * rng.normal(size=(m, m))
            p = (q + d) % n
            for i in range(m):
                for j in range(m):
                    rows.append(q * m + i)
                    cols.append(p * m + j)
                    vals.append(block[i, j])
    mat = scipy.sparse.csr_matrix((vals, (rows, cols)), shape=(size, size))
    return mat, np.linalg.inv(diag)


@pytest.mark.parametrize(("m", "coupling", "restart"), [(1, 1e-6, 40), (1, 0.3, 40), (2, 0.3, 40), (1, 0.45, 3)])
def test_compiled_gmres_takes_scipys_steps(m: int, coupling: float, restart: int) -> None:
    mod = krylov_kernels()
    if mod is None:
        pytest.skip("numba cannot build the kernels here")
    n = 300
    mat, inv = _system(n, m, coupling, seed=m)
    size = n * m
    rhs = np.random.default_rng(7).normal(size=size)
    pre = scipy.sparse.linalg.LinearOperator(
        (size, size), matvec=lambda r: np.einsum("nij,nj->ni", inv, r.reshape(n, m)).reshape(-1)
    )
    x0 = pre.matvec(rhs)
    for atol, rtol in ((1e-3, 1e-8), (0.0, 1e-12)):
        want, info = scipy.sparse.linalg.gmres(
            mat, rhs, x0=x0.copy(), rtol=rtol, atol=atol, restart=restart, maxiter=50, M=pre
        )
        got = x0.copy()
        work = np.empty((min(restart, size) + 1, size)), np.empty(size), np.empty(size)
        status, res = mod.gmres(mat.indptr, mat.indices, mat.data, inv, rhs, got, atol, rtol, restart, 50, *work)
        assert status == info
        assert np.abs(got - want).max() <= 1e-12 * np.abs(want).max()
        assert res == pytest.approx(np.linalg.norm(rhs - mat @ got), rel=1e-10)
        assert res <= max(atol, rtol * np.linalg.norm(rhs))
    # a basis too short for the solve: said (-1), and the solve with the whole basis is the same as at first
    if info == 0:
        short = x0.copy()
        status, _ = mod.gmres(
            mat.indptr, mat.indices, mat.data, inv, rhs, short, 0.0, 1e-12, restart, 50, work[0][:1], *work[1:]
        )
        assert status == -1
    # a zero right-hand side, and a start that solves the system already
    zero = np.ones(size)
    work = np.empty((min(restart, size) + 1, size)), np.empty(size), np.empty(size)
    assert (
        mod.gmres(mat.indptr, mat.indices, mat.data, inv, np.zeros(size), zero, 0.0, 1e-8, restart, 50, *work)[0] == 0
    )
    assert not zero.any()


@pytest.mark.parametrize(
    ("name", "model", "init"),
    [
        ("learned polynomial 3+1D", lambda: _polynomial(3), lambda: _field(3, 5)),
        ("learned polynomial 2+1D", lambda: _polynomial(2), lambda: _field(2, 8)),
        ("full-cell sine-Gordon 2+1D (coupled)", lambda: _full_cell(3), lambda: membrane_field(n=9, nt=8)),
    ],
)
def test_a_field_served_with_compiled_gmres_equals_scipys(name, model, init, monkeypatch: pytest.MonkeyPatch) -> None:
    from latticedft._serve import _solvers

    if krylov_kernels() is None:
        pytest.skip("numba cannot build the kernels here")
    lagrangian, start = model(), init()
    fast = ldft.serve(lagrangian, start, slices=8, solver="krylov", progress=False)
    monkeypatch.setattr(_solvers, "GMRES_KEPT_ROWS", 2)  # solves that need more of the basis run again with all of it
    short = ldft.serve(lagrangian, start, slices=8, solver="krylov", progress=False)
    monkeypatch.setattr(_solvers, "COMPILED_GMRES", False)
    slow = ldft.serve(lagrangian, start, slices=8, solver="krylov", progress=False)
    b = np.asarray(slow.field.values)
    for got in (fast, short):
        a = np.asarray(got.field.values)
        assert got.slice_solver == slow.slice_solver == "krylov", name
        assert got.newton_iterations == slow.newton_iterations, name
        assert np.abs(a - b).max() <= 1e-12 * np.abs(b).max(), name
    assert np.array_equal(np.asarray(short.field.values), np.asarray(fast.field.values)), name


@pytest.mark.parametrize("ndim", [2, 3])
def test_a_fresh_jacobians_compiled_assembly_equals_torch_and_numpy_to_the_bit(
    ndim: int, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The diagonal sum (``index_add_``'s), the site-wise extremes and the CSR values read from the evaluated
    columns, by the compiled loops and by torch and numpy: the same to the bit, on a periodic lattice and on a
    Dirichlet frame, with a not-a-number on the diagonal too, and with two components (the diagonal alone)."""
    import torch

    from latticedft._lattice import as_lattice_field
    from latticedft._serve._folded import FoldedCells, folded_slices
    from latticedft._serve._slices import _SliceSystem

    _slices = importlib.import_module("latticedft._serve._slices")  # the module (the package's name is a function)
    if krylov_kernels() is None:
        pytest.skip("numba cannot build the kernels here")
    model = _polynomial(ndim)
    init = _field(ndim, {2: 9, 3: 5}[ndim])
    frame = init.copy()
    for d in frame.dims[1:]:
        frame[d].attrs = {}  # a Dirichlet frame: fewer unknowns than cells
    for f0 in (init, frame):
        f = as_lattice_field(f0, source="init", min_slices=2)
        sys_ = _SliceSystem(model, f)
        flat = (f.values * torch.tensor([1.0, 1.02], dtype=torch.float64).reshape(2, *[1] * (ndim + 1))).contiguous()
        folded = folded_slices(model, sys_, flat.reshape(2, -1, 1))
        assert folded is not None
        lo, hi = flat.reshape(2, -1, 1)[0].numpy(), flat.reshape(2, -1, 1)[1].numpy()
        got = {}
        for compiled in (True, False):
            monkeypatch.setattr(_slices, "COMPILED_ASSEMBLY", compiled)
            blocks = FoldedCells(folded, lo, hi, with_blocks=True).blocks(sys_.pairs)
            diag = sys_.diagonal(dict(blocks))
            got[compiled] = (sys_.csr_arrays(blocks, 0.003), diag, sys_.site_singular_values(dict(blocks)))
            key, cells, _ = sys_.diag_entries[0]
            blocks[key].view(-1)[int(cells[1])] = float("nan")  # a not-a-number on the diagonal: taken as 0 by both
            got[compiled] += (sys_.site_singular_values(dict(blocks)),)
        (a, da, sa, na), (b, db, sb, nb) = got[True], got[False]
        assert all(np.array_equal(x, y) for x, y in zip(a, b)) and np.abs(b[0]).max() > 0
        assert torch.equal(da, db) and sa == sb and na == nb and na[0] == 0.0
    # two components: the diagonal blocks summed as index_add_ sums them
    sys2 = _SliceSystem(model, as_lattice_field(init, source="init", min_slices=2))
    sys2.m = 2
    rng = np.random.default_rng(3)
    ncell = sys2.site_of[0].size
    blocks2 = {p: torch.from_numpy(rng.normal(size=(ncell, 2, 2))) for p in sys2.pairs}
    sums = []
    for compiled in (True, False):
        monkeypatch.setattr(_slices, "COMPILED_ASSEMBLY", compiled)
        sums.append(sys2.diagonal(blocks2))
    assert torch.equal(sums[0], sums[1])


def test_the_compiled_largest_sizes_are_torchs_and_numpys() -> None:
    import torch

    from latticedft._serve._slices import abs_max, finite_step, values_abs_max

    rng = np.random.default_rng(5)
    cases = [rng.normal(size=1000), -np.abs(rng.normal(size=7)), np.array([-0.0, 0.0]), np.array([1.0, np.inf, -3.0])]
    cases += [np.array([2.0, np.nan, -5.0]), np.array([np.nan, -np.inf]), rng.normal(size=(40, 3))]
    # a not-a-number or an infinity in the eight-lane body and in the tail, at each lane; sizes whose sum overflows
    for size in (8, 19, 1003):
        for bad in (np.nan, np.inf, -np.inf):
            for at in sorted({0, 3, 7, size // 2 + 5, size - 1} & set(range(size))):
                a = rng.normal(size=size)
                a[at] = bad
                cases.append(a)
    both = rng.normal(size=200)
    both[[17, 150]] = [np.inf, -np.inf]
    cases += [both, np.full(64, 1e308), np.full(64, -1e308), np.concatenate([np.full(64, 1e308), [np.nan]])]
    for a in cases:
        t = torch.from_numpy(a)
        want, got = float(t.abs().max()), abs_max(t)
        assert got == want or (np.isnan(got) and np.isnan(want)), a
        flat = a.reshape(-1)
        want, got = float(np.abs(flat).max()), values_abs_max(flat)
        assert got == want or (np.isnan(got) and np.isnan(want)), a
        finite = bool(np.all(np.isfinite(flat)))
        assert finite_step(flat) == (finite, float(np.abs(flat).max()) if finite else 0.0), a
    assert finite_step(np.zeros(0)) == (True, 0.0)
    strided = torch.from_numpy(rng.normal(size=(6, 4)))[:, 1]  # not contiguous: torch's own reduction
    assert abs_max(strided) == float(strided.abs().max())


@pytest.mark.parametrize("ndim", [2, 3])
def test_newtons_step_scale_from_the_predictors_sizes_serves_the_same_field(
    ndim: int, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Newton's step scale reads the sizes of the two slices before from the folded predictor (one pass a step over
    the unknowns): the same field to the bit, the same iterations, as each step measuring all three slices."""
    from latticedft._serve import _newton, _stepper

    lagrangian, start = _polynomial(ndim), _field(ndim, 5 if ndim == 3 else 8)
    passed = []

    def measuring(*args, **kwargs):
        passed.append(kwargs.get("sizes") is not None)
        return _newton._newton_slice(*args, **kwargs)

    monkeypatch.setattr(_stepper, "_newton_slice", measuring)
    fast = ldft.serve(lagrangian, start, slices=8, solver="krylov", progress=False)
    assert passed and all(passed)  # the folded predictor measured them on every slice
    passed.clear()

    def remeasuring(*args, **kwargs):  # the sizes dropped: every step measures the three slices itself
        kwargs["sizes"] = None
        return _newton._newton_slice(*args, **kwargs)

    monkeypatch.setattr(_stepper, "_newton_slice", remeasuring)
    slow = ldft.serve(lagrangian, start, slices=8, solver="krylov", progress=False)
    assert fast.newton_iterations == slow.newton_iterations
    assert np.array_equal(np.asarray(fast.field.values), np.asarray(slow.field.values))
