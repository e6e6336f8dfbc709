"""Slice solvers of n-D serving: site-wise and Krylov steps serve what the sparse LU serves; auto's choice."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

import latticedft as ldft
from latticedft import ConfigError, lagrangians, systems
from latticedft._case import load_case
from latticedft.cli import main
from latticedft.io import write_field

from case_helpers import tiny_wave, write_toml
from helpers import membrane_field, wave_field


def _sine_gordon() -> ldft.AnalyticLagrangian:
    """The sine-Gordon ``L_d`` on the first-order stencil (any dimension): a block-diagonal slice Jacobian."""

    def fn(c, h):
        u = c[..., 0, 0]
        out = 0.5 * ((c[..., 1, 0] - u) / h[0]) ** 2 - (1 - torch.cos(u))
        for k in range(1, len(h)):
            out = out - 0.5 * ((c[..., k + 1, 0] - u) / h[k]) ** 2
        return out

    return ldft.AnalyticLagrangian(fn, name="sine-Gordon")


def _full_cell(n: int) -> ldft.AnalyticLagrangian:
    """A non-quadratic ``L_d`` on the full unit cell (every corner): each unknown couples to its neighbours."""
    st = ldft.Stencil.full_cell(n)
    offs = torch.tensor(st.offsets, dtype=torch.float64)  # (K, n)
    corners = 2 ** (n - 1)

    def fn(c, h):
        u = c[..., 0]  # (..., K)
        grads = [((2 * offs[:, k] - 1) * u).sum(-1) / (corners * h[k]) for k in range(n)]
        mean = u.mean(-1)
        out = 0.5 * grads[0] ** 2 - (1 - torch.cos(mean))
        for g in grads[1:]:
            out = out - 0.5 * g**2
        return out

    return ldft.AnalyticLagrangian(fn, stencil=st, name="full-cell sine-Gordon")


def _field_3p1d(n: int = 6, nt: int = 6):
    """A smooth 3+1D field (the first two slices matter; Dirichlet strips from the same formula)."""
    h = 1.0 / (n - 1)
    x = h * np.arange(n)
    t = 0.4 * h * np.arange(nt)
    u = (
        0.5
        * np.cos(t)[:, None, None, None]
        * np.sin(np.pi * x)[None, :, None, None]
        * np.sin(np.pi * x)[None, None, :, None]
        * np.sin(2 * np.pi * x)[None, None, None, :]
    )
    return systems.make_field(u, ("t", "z", "y", "x"), spacing=(0.4 * h, h, h, h))


def _fields():
    return {
        "1+1D": wave_field(nx=17, nt=12),
        "2+1D": membrane_field(n=9, nt=8),
        "3+1D": _field_3p1d(),
    }


@pytest.mark.parametrize("boundary", ["dirichlet", "periodic"])
@pytest.mark.parametrize("dims", ["1+1D", "2+1D", "3+1D"])
def test_sitewise_and_krylov_equal_lu_on_a_block_diagonal_jacobian(dims, boundary):
    field = _fields()[dims]
    lu = ldft.serve(_sine_gordon(), field, boundary=boundary, solver="lu")
    assert lu.slice_solver == "lu" and lu.complete
    for solver in ("sitewise", "krylov", "auto"):
        out = ldft.serve(_sine_gordon(), field, boundary=boundary, solver=solver)
        assert out.complete and out.max_residual <= lu.max_residual * 10 + 1e-300
        np.testing.assert_allclose(out.field.values, lu.field.values, rtol=0, atol=1e-12)
        assert out.slice_solver == ("sitewise" if solver == "auto" else solver)


@pytest.mark.parametrize("boundary", ["dirichlet", "periodic"])
@pytest.mark.parametrize("n", [1, 2])
def test_krylov_equals_lu_on_a_coupled_jacobian(n, boundary):
    field = wave_field(nx=15, nt=10) if n == 1 else membrane_field(n=9, nt=8)
    model = _full_cell(n + 1)
    lu = ldft.serve(model, field, boundary=boundary, solver="lu")
    kr = ldft.serve(model, field, boundary=boundary, solver="krylov")
    auto = ldft.serve(model, field, boundary=boundary)
    assert lu.complete and kr.complete and kr.slice_solver == "krylov"
    assert auto.slice_solver == ("lu" if n == 1 else "krylov")  # off-diagonal blocks: never site-wise
    np.testing.assert_allclose(kr.field.values, lu.field.values, rtol=0, atol=1e-10)
    np.testing.assert_allclose(auto.field.values, lu.field.values, rtol=0, atol=1e-10)


def test_forced_sitewise_on_a_coupled_jacobian_is_refused_at_the_slice():
    field = membrane_field(n=9, nt=6)
    with pytest.raises(ldft.ServeError) as err:
        ldft.serve(_full_cell(3), field, solver="sitewise")
    msg = str(err.value)
    assert msg.startswith("slice 2 ") and "solver 'sitewise' needs a block-diagonal slice Jacobian" in msg
    assert "'krylov'" in msg and "\n" not in msg
    assert err.value.slice == 2 and not err.value.result.complete


def test_quadratic_ld_keeps_its_affine_recurrence():
    out = ldft.serve(lagrangians.wave(1.0), membrane_field(n=8, nt=8))
    assert out.solver == "affine" and out.slice_solver is None
    forced = ldft.serve(lagrangians.wave(1.0), membrane_field(n=8, nt=8), affine=False)
    assert forced.solver == "newton" and forced.slice_solver == "sitewise"
    np.testing.assert_allclose(forced.field.values, out.field.values, rtol=0, atol=1e-12)
    assert forced.to_dict()["slice_solver"] == "sitewise"


@pytest.mark.parametrize("bad", ["gmres", "", None, 3])
def test_invalid_solver_is_refused(bad):
    with pytest.raises(ldft.InputError, match=r"^solver: expected one of \['auto', 'sitewise', 'krylov', 'lu'\]"):
        ldft.serve(_sine_gordon(), membrane_field(n=6, nt=4), solver=bad)


def test_case_toml_solver_key(tmp_path: Path):
    case = tiny_wave(tmp_path)
    assert load_case(case).serve[0].options.solver == "auto"
    c = load_case(case, ["serve.test.solver=krylov"])
    assert c.serve[0].options.solver == "krylov"
    with pytest.raises(ConfigError) as info:
        load_case(case, ["serve.test.solver=gmres"])
    msg = str(info.value)
    assert "solver" in msg and "krylov" in msg and "\n" not in msg


def test_krylov_non_convergence_names_slice_site_and_residual():
    field = membrane_field(n=9, nt=8)
    with pytest.raises(ldft.ServeError) as err:
        ldft.serve(_full_cell(3), field * 40, solver="krylov", max_newton=1)
    msg = str(err.value)
    assert "did not converge" in msg and "site" in msg and "residual" in msg and "\n" not in msg
    part = err.value.result
    assert not part.complete and part.slice_solver == "krylov" and part.field.sizes["t"] == err.value.slice


def _sine_gordon_string(nt: int, amplitude: float):
    """A 1+1D sine-Gordon field on 13 sites with fixed ends (numpy leapfrog, dt = dx / 2)."""
    x = np.linspace(0.0, 1.0, 13)
    u0 = amplitude * np.sin(np.pi * x)
    u = systems.leapfrog(u0, u0.copy(), nt - 1, 0.5 / 12, 1 / 12, force=lambda v: -np.sin(v))
    return systems.make_field(u, ("t", "x"), spacing=(0.5 / 12, 1 / 12))


def test_summary_json_records_the_slice_solver(tmp_path: Path, capsys):
    case = tmp_path / "sg"
    (case / "data").mkdir(parents=True)
    write_field(case / "data" / "train.nc", {"psi": _sine_gordon_string(30, 1.5)})
    write_field(case / "data" / "test.nc", {"psi": _sine_gordon_string(20, 1.2)})
    write_toml(
        case,
        """
        [model]
        kind = "polynomial"
        orders = [2, 6]
        time_symmetric = true
        [train]
        data = ["data/train.nc"]
        [[serve]]
        name = "test"
        from = "data/test.nc"
        solver = "krylov"
        [run]
        threads = 1
        [export]
        formats = []
        """,
    )
    code = main(["run", str(case), "-q"])
    capsys.readouterr()
    assert code == 0
    task = json.loads((case / "results" / "summary.json").read_text())["tasks"]["test"]
    assert task["complete"] and task["solver"] == "newton" and task["slice_solver"] == "krylov"
    assert task["max_error"] < 1e-2


def _system_and_blocks(full: bool, periodic: bool = True):
    """A 2+1D slice system (the sine-Gordon's first-order stencil or the full unit cell, 7^2 sites) and random
    Hessian blocks on it."""
    from latticedft._lattice import as_lattice_field
    from latticedft._serve._slices import _SliceSystem

    model = _full_cell(3) if full else _sine_gordon()
    n = 7
    x = np.arange(n) / n
    u = 0.3 * np.sin(2 * np.pi * x)[None, :, None] * np.cos(2 * np.pi * x)[None, None, :] * np.ones((2, 1, 1))
    attrs = {d: {"periodic": "true", "period": n * 0.1} for d in ("y", "x")} if periodic else None
    init = systems.make_field(u, ("t", "y", "x"), spacing=(0.04, 0.1, 0.1), coord_attrs=attrs)
    f = as_lattice_field(init, source="init", min_slices=2)
    model.bind(f.ndim, f.ncomp, f.spacing, f.components)
    sys_ = _SliceSystem(model, f)
    rng = np.random.default_rng(0)
    blocks = {p: torch.from_numpy(rng.standard_normal((sys_.site_of[0].size, 1, 1))) for p in sys_.pairs}
    return sys_, blocks


@pytest.mark.parametrize(("full", "shared"), [(False, False), (True, True)])
def test_the_jacobian_assembled_on_its_kept_structure_is_scipys(full: bool, shared: bool) -> None:
    """The slice Jacobian in CSR from its structure sorted once per lattice: scipy's matrix from the same entries
    (data, indices, row pointers); where entries share a place (the full unit cell's pairs) scipy sums them."""
    import scipy.sparse

    sys_, blocks = _system_and_blocks(full)
    assert (sys_._csr_pattern is None) == shared
    rows, cols, vals = sys_.matrix_entries(blocks, 0.5)
    want = scipy.sparse.csr_matrix((vals, (rows, cols)), shape=(sys_.n, sys_.n))
    got = sys_.csr(blocks, 0.5)
    np.testing.assert_array_equal(got.indptr, want.indptr)
    np.testing.assert_array_equal(got.indices, want.indices)
    np.testing.assert_array_equal(got.data, want.data)


@pytest.mark.parametrize(("full", "periodic"), [(False, True), (True, True), (False, False)])
def test_the_largest_off_diagonal_entry_is_read_from_the_kept_cells(full: bool, periodic: bool) -> None:
    """The largest off-diagonal entry of the slice Jacobian (``auto``'s choice of solver) from the cells kept per
    pair (a whole pair's blocks where every cell holds one): the largest over the assembled entries."""
    from latticedft._serve._solvers import _diag_and_offdiag

    sys_, blocks = _system_and_blocks(full, periodic)
    rows, cols, vals = sys_.matrix_entries(blocks, 1.0)
    off = rows != cols
    assert off.any()
    assert _diag_and_offdiag(sys_, blocks)[1] == float(np.abs(vals[off]).max())
