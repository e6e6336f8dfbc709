"""Split slice-Newton with the Krylov step (``latticedft._serve._slabkrylov``): a DEL whose new slice couples
neighbouring unknowns, served by two gloo processes on the loopback, gives the one-process field to 1e-12;
``solver = "lu"`` is refused in one line naming the alternative."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import latticedft as ldft
from latticedft._errors import InputError
from latticedft._models import AnalyticLagrangian
from latticedft._serve._decomp import serve_slabs
from latticedft._serve._slabkrylov import gmres

from helpers import RANK_RESULTS_END, two_ranks

_MODEL = """
import numpy as np, torch, xarray as xr
from latticedft._models import AnalyticLagrangian
from latticedft._stencil import Stencil
st = Stencil.full_cell(3)
off = np.array(st.offsets)
NXT, NOW = [k for k, o in enumerate(off) if o[0] == 1], [k for k, o in enumerate(off) if o[0] == 0]
def fn(c, h):  # sine-Gordon on the unit cell: the time difference of the cell's faces couples the new sites
    u = c[..., 0]
    u0, u1 = u[..., 0], u[..., st.index((1, 0, 0))]
    kin = 0.5 * ((u1 - u0) / h[0]) ** 2 + 0.05 * ((u[..., NXT].mean(-1) - u[..., NOW].mean(-1)) / h[0]) ** 2
    grad = sum(0.5 * ((u[..., st.index(e)] - u0) / h[a + 1]) ** 2 for a, e in enumerate([(0, 1, 0), (0, 0, 1)]))
    return kin - grad - (1 - torch.cos(u0))
MODEL = AnalyticLagrangian(fn, name="cell-sG", stencil=st)
def field(nt):
    x, y, t = np.arange(9) / 9, np.arange(7) / 7, np.arange(nt) * 0.02
    b = np.sin(2 * np.pi * x)[:, None] * (1 + 0.5 * np.cos(2 * np.pi * y))[None, :]
    v = np.stack([b * np.cos(0.3 * k * 0.02) for k in range(nt)])
    return xr.DataArray(v, dims=("t", "x", "y"), coords={"t": t, "x": x, "y": y}, name="psi")
"""

_WORKER = (
    _MODEL
    + """
import os, sys, json
torch.set_num_threads(1)
import torch.distributed as dist
import latticedft as ldft
from latticedft._errors import InputError
from latticedft._learn import _dist
from latticedft._serve._decomp import serve_slabs
_dist.init_from_env()
rank, out = dist.get_rank(), {}
for bnd, nt in (("periodic", 2), ("dirichlet", 16)):
    rep = {}
    got = serve_slabs(MODEL, field(nt), 16, boundary=bnd, rtol=1e-13, report=rep)
    if rank == 0:
        one = ldft.serve(MODEL, field(nt), slices=16, boundary=bnd, rtol=1e-13).field
        out[bnd] = [float(np.abs(got.values - one.values).max() / np.abs(one.values).max()), rep["slice_solver"]]
try:
    serve_slabs(MODEL, field(2), 16, boundary="periodic", solver="lu")
except InputError as exc:
    out["lu"] = str(exc)
from latticedft._serve import _slabkrylov
from latticedft._serve._flag import SlabError
inverse, calls = _slabkrylov._block_inverse, [0]
def failing(diag, vol):  # the preconditioner of rank 1 fails at its fifth use: inside a GMRES solve
    prec = inverse(diag, vol)
    def apply(v):
        calls[0] += 1
        if rank == 1 and calls[0] == 5:
            raise RuntimeError("injected failure\\nin the preconditioner")
        return prec(v)
    return apply
_slabkrylov._block_inverse = failing
try:
    serve_slabs(MODEL, field(2), 16, boundary="periodic", rtol=1e-13)
except SlabError as err:
    out["gmres"] = [str(err), None if err.result is None else err.result["slice"].values.tolist(), calls[0]]
"""
    + RANK_RESULTS_END
)


def _model() -> tuple[AnalyticLagrangian, object]:
    space: dict[str, object] = {}
    exec(_MODEL, space)
    return space["MODEL"], space["field"]  # type: ignore[return-value]


def test_one_process_serves_a_coupled_slice_by_krylov_as_serve() -> None:
    model, field = _model()
    rep: dict[str, object] = {}
    got = serve_slabs(model, field(2), 12, boundary="periodic", rtol=1e-13, report=rep)  # type: ignore[operator]
    one = ldft.serve(model, field(2), slices=12, boundary="periodic", rtol=1e-13)  # type: ignore[operator]
    assert rep["slice_solver"] == "krylov" and one.slice_solver == "krylov"
    assert got is not None and np.abs(got.values - one.field.values).max() <= 1e-12 * np.abs(one.field.values).max()


def test_lu_is_refused_in_one_line_naming_krylov() -> None:
    model, field = _model()
    with pytest.raises(InputError) as err:
        serve_slabs(model, field(2), 12, boundary="periodic", solver="lu")  # type: ignore[operator]
    assert str(err.value).startswith(
        "solver: 'lu' is not split across processes (a sparse LU of the whole slice); use solver = \"krylov\""
    )


def test_gmres_solves_a_small_system_in_one_process() -> None:
    rng = np.random.default_rng(0)
    a = np.eye(30) * 4 + rng.normal(size=(30, 30)) * 0.3
    b = rng.normal(size=30)
    x = gmres(lambda v: a @ v, lambda v: v / 4, b, np.zeros(30), atol=0.0, rtol=1e-12, restart=7)
    assert np.abs(a @ x - b).max() <= 1e-10 * np.abs(b).max()


@pytest.mark.slow
def test_two_processes_serve_a_coupled_slice_by_krylov_as_one(tmp_path: Path) -> None:
    zero, one = two_ranks(tmp_path, _WORKER)
    for bnd in ("periodic", "dirichlet"):
        assert zero[bnd][0] <= 1e-12 and zero[bnd][1] == "krylov", zero
    assert zero["lu"] == one["lu"] and "\n" not in zero["lu"]
    # an exception in one process inside a GMRES solve stops both with its one-line error
    assert zero["gmres"][0] == one["gmres"][0] == "slice 2: process 1 of 2 failed: RuntimeError: injected failure"
    assert zero["gmres"][1] == [0, 1] and one["gmres"][1] is None
    assert zero["gmres"][2] >= 5 and one["gmres"][2] == 5  # rank 0 went on into the solve


def test_the_command_refuses_lu_under_workers_naming_the_key_and_writes_nothing(tmp_path, capsys, monkeypatch):
    from test_split_cli import tiny_klein_gordon

    from case_helpers import run_cli, snapshot

    case = tiny_klein_gordon(tmp_path)
    code, _, err = run_cli(capsys, "run", case, "-q")
    assert code == 0, err
    before = snapshot(case / "results")
    monkeypatch.setenv("WORLD_SIZE", "2")
    monkeypatch.setenv("RANK", "0")
    for command in ("serve", "run"):
        extra = ["--overwrite"] if command == "run" else []
        code, _, err = run_cli(capsys, command, case, "-q", "--set", "serve.test.solver=lu", *extra)
        lines = err.strip().splitlines()
        assert code == 1 and len(lines) == 1, err
        assert "serve[0].solver: 'lu' is not split across processes" in lines[0] and 'solver = "krylov"' in lines[0]
        assert snapshot(case / "results") == before


def test_an_ensemble_is_refused_in_one_line() -> None:
    """An ensemble (or its members stacked) is not split: its slice tests are each member's own, which the split
    slice's all-reduced tests are not (the command line serves it whole)."""
    from latticedft import systems
    from latticedft._models._ensemble import stacked

    train = systems.wave_string([(1, 1.0), (2, 0.4)], nx=13, nt=20)
    ens = ldft.EnsembleLagrangian(ldft.PolynomialLagrangian((2, 2)), members=2, seed=0)
    ldft.learn(ens, [train])
    for each in (ens, stacked(ens, ("member0", "member1"))):
        with pytest.raises(InputError) as err:
            serve_slabs(each, train, 12, boundary="dirichlet")
        assert str(err.value).startswith("model: an ensemble is served whole, in one process")
        assert "\n" not in str(err.value)
