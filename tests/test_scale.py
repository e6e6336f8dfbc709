"""Training whose memory does not grow with the data, and training in several processes.

Streamed training (chunks of sites, fields read a slab at a time) must learn what the in-memory path
learns: to round-off for the exact solve of linear models, to a small tolerance for iterative training
(the same objective, summed in another order). Lazy DataArrays and field-file paths train like in-memory
fields. Two processes on the loopback (torch.distributed, gloo) learn what one process learns.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
import xarray as xr

import latticedft as ldft
import latticedft.io
from latticedft import systems
from latticedft._errors import InputError
from latticedft._lattice import gather_cells, interior_slices
from latticedft._learn._source import as_sources, is_lazy, pieces

from helpers import GROUP_END, alone_and_in_two, group_env

REPO = Path(__file__).resolve().parents[1]


def _strings(n: int = 4, nx: int = 24, nt: int = 40) -> list[xr.DataArray]:
    return [systems.wave_string([(k, 0.5 / k), (k + 1, 0.1, 0.3 * k)], nx=nx, nt=nt) for k in range(1, n + 1)]


def _coef(model: ldft.AbstractLagrangian) -> np.ndarray:
    return torch.cat([p.detach().reshape(-1) for p in model.parameters()]).numpy().copy()


def _rel(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.abs(a - b).max() / np.abs(b).max())


# -- the plan of pieces -----------------------------------------------------------------------------------------
@pytest.mark.parametrize("budget", [0, 1, 50, 130, 10_000])
@pytest.mark.parametrize("boundary", ["dirichlet", "periodic"])
def test_pieces_own_every_site_and_cell_exactly_once(budget: int, boundary: str) -> None:
    fields = _strings(2, nx=9, nt=11)
    sources = as_sources(fields, boundary)
    model = ldft.PolynomialLagrangian((2, 2))
    model.bind(2, 1, sources[0].lattice.spacing)
    st = model.stencil
    sites = [np.zeros(s.shape, dtype=int) for s in sources]
    cells = [np.zeros(s.shape, dtype=int) for s in sources]
    chunks = pieces(sources, st, budget)
    if budget == 0:
        assert len(chunks) == 1
    for chunk in chunks:
        assert budget <= 0 or len(chunk) == 1 or sum((p.t1 - p.t0 + 2) * 9 for p in chunk) <= budget
        for p in chunk:
            f, skip = p.read(sources, st)
            a = max(0, p.t0 - 1)
            # interior sites of the slab: the piece's own
            idx = np.arange(f.values[..., 0].numel()).reshape(f.shape)
            inner = idx[interior_slices(f.shape, st, f.boundary)]
            t, x = np.unravel_index(inner.reshape(-1), f.shape)
            np.add.at(sites[p.source], (t + a, x), 1)
            # cells of the slab from the skip-th time slice on: the piece's own (their anchor site)
            anchor = gather_cells(torch.from_numpy(idx).reshape(*f.shape, 1), st, f.boundary)[skip:, :, 0, 0]
            t, x = np.unravel_index(anchor.reshape(-1).numpy(), f.shape)
            np.add.at(cells[p.source], (t + a, x), 1)
    for s, c, src in zip(sites, cells, sources):
        inner_all = np.zeros(src.shape, dtype=int)
        inner_all[interior_slices(src.shape, st, src.lattice.boundary)] = 1
        assert np.array_equal(s, inner_all)
        ref = gather_cells(torch.arange(s.size).reshape(*s.shape, 1), st, src.lattice.boundary)[..., 0, 0]
        expect = np.zeros(s.size, dtype=int)
        np.add.at(expect, ref.reshape(-1).numpy(), 1)
        assert np.array_equal(c.reshape(-1), expect)


# -- the exact solve ------------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "orders,ridge,gauge,n,tol",
    [
        ((2, 2), 0.0, "unit-mass", 3, 1e-10),
        # a null Lagrangian (the constant term) held only by the ridge: its coefficient, ~1e-9, is round-off
        # whatever the path (the in-memory solve moves it by 4e-11 when the rows of R are permuted)
        ((4, 4), 1e-10, "unit-mass", 3, 3e-9),
        ((2, 4), "auto", "unit-mass", 3, 1e-10),  # leave one field out
        ((2, 4), "auto", "unit-mass", 8, 1e-10),  # six folds and a rest
        ((2, 4), "auto", "trace", 1, 1e-10),  # one field: its first 70 % against the rest
    ],
)
def test_streamed_exact_solve_equals_the_in_memory_solve(orders, ridge, gauge, n, tol) -> None:
    data = _strings(n)
    ref = ldft.PolynomialLagrangian(orders)
    rep_ref = ldft.learn(ref, data, ridge=ridge, gauge=gauge, chunk_sites=0)
    for chunk in (None, 53):  # the default, and tiny chunks: a field in ~10 slabs, many QR folds
        model = ldft.PolynomialLagrangian(orders)
        rep = ldft.learn(model, data, ridge=ridge, gauge=gauge, chunk_sites=chunk)
        assert _rel(_coef(model), _coef(ref)) < tol
        assert rep.ridge == rep_ref.ridge and rep.n_sites == rep_ref.n_sites and rep.n_fields == rep_ref.n_fields
        assert rep.validation.keys() == rep_ref.validation.keys()
        for k, v in rep_ref.validation.items():
            assert rep.validation[k] == pytest.approx(v, rel=1e-8)
        for k in ("loss", "rel_res", "hessian_min_sv", "hessian_cond"):
            assert getattr(rep, k) == pytest.approx(getattr(rep_ref, k), rel=1e-8), k
        assert rep.gauge_residual < 1e-13


def test_streamed_solve_on_a_periodic_2p1d_field_and_without_gauge() -> None:
    membrane = systems.wave_membrane([(1, 1, 1.0), (2, 1, 0.3)], nx=9, ny=8, nt=12)
    ref = ldft.PolynomialLagrangian((2, 2))
    ldft.learn(ref, membrane, boundary="periodic", chunk_sites=0)
    model = ldft.PolynomialLagrangian((2, 2))
    ldft.learn(model, membrane, boundary="periodic", chunk_sites=100)
    assert _rel(_coef(model), _coef(ref)) < 1e-10
    collapsed = ldft.PolynomialLagrangian((2, 2))
    rep = ldft.learn(collapsed, _strings(2), gauge="none", chunk_sites=60)
    assert rep.hessian_min_sv < 1e-8 and rep.loss < 1e-20  # the collapse, streamed too


def test_prepare_reduces_chunk_by_chunk_to_the_same_scaling() -> None:
    f = ldft.as_lattice_field(_strings(1)[0])
    for model in (ldft.PolynomialLagrangian((2, 4)), ldft.MLPLagrangian(hidden=[4], form="free")):
        model.bind(2, 1, f.spacing)
        cells = gather_cells(f.values, model.stencil, f.boundary)
        model.prepare([cells])
        whole = {k: v.clone() for k, v in model.state_dict().items()}
        model.prepare([cells[:7], cells[7:20], cells[20:20], cells[20:]])
        for k, v in model.state_dict().items():
            assert torch.equal(v, whole[k]), k


# -- iterative training ----------------------------------------------------------------------------------------
@pytest.mark.parametrize("form", ["kinetic-potential", "free"])
def test_chunked_objective_trains_like_the_full_batch(form: str) -> None:
    data = systems.klein_gordon_training_set(n=4, steps=10, seed=0)

    def train(chunk: int | None) -> tuple[np.ndarray, ldft.LearnReport]:
        model = ldft.MLPLagrangian(hidden=[6], activation="tanh", form=form, seed=0)
        rep = ldft.learn(model, data, optimizer="lbfgs", max_iter=8, chunk_sites=chunk, boundary="periodic")
        return _coef(model), rep

    ref, rep_ref = train(0)
    same, rep_same = train(None)  # the default chunk holds all four fields: the in-memory path itself
    assert np.array_equal(same, ref) and rep_same.loss == rep_ref.loss
    chunked, rep = train(70)  # fields cut in slabs; the penalty's gradient by the chain rule
    assert _rel(chunked, ref) < 1e-8
    assert rep.loss == pytest.approx(rep_ref.loss, rel=1e-6) and rep.iterations == rep_ref.iterations


# -- lazy data ------------------------------------------------------------------------------------------------
def _files(tmp_path: Path, fields: list[xr.DataArray]) -> list[Path]:
    paths = []
    for i, f in enumerate(fields):
        p = tmp_path / f"field_{i}.nc"
        ldft.io.write_field(p, {"psi": f})
        paths.append(p)
    return paths


def test_paths_and_lazy_dataarrays_train_like_in_memory_fields(tmp_path: Path) -> None:
    data = _strings(3)
    paths = _files(tmp_path, data)
    ref = ldft.PolynomialLagrangian((2, 4))
    ldft.learn(ref, data, chunk_sites=0, ridge="auto")
    by_path = ldft.PolynomialLagrangian((2, 4))
    rep = ldft.learn(by_path, [str(p) for p in paths], chunk_sites=90, ridge="auto")
    assert _rel(_coef(by_path), _coef(ref)) < 1e-10 and rep.n_fields == 3
    lazy = [xr.open_dataset(p)["psi"] for p in paths]
    assert all(is_lazy(d) for d in lazy)
    model = ldft.PolynomialLagrangian((2, 4))
    ldft.learn(model, lazy, chunk_sites=90, ridge="auto")
    assert _rel(_coef(model), _coef(ref)) < 1e-10
    assert all(is_lazy(d) for d in lazy)  # read slab by slab, never loaded whole
    single = ldft.PolynomialLagrangian((2, 2))
    ldft.learn(single, paths[0])
    assert single.bound


def test_lazy_data_errors_name_the_file(tmp_path: Path) -> None:
    bad = _strings(1)[0].copy()
    bad[30, 5] = np.nan
    (path,) = _files(tmp_path, [bad])
    with pytest.raises(InputError, match=r"field_0\.nc: field holds 1 NaN/inf value\(s\).*first at \(t=30, x=5\)"):
        ldft.learn(ldft.PolynomialLagrangian((2, 2)), [path], chunk_sites=100)
    with pytest.raises(InputError, match="file not found"):
        ldft.learn(ldft.PolynomialLagrangian((2, 2)), [tmp_path / "nope.nc"])
    with pytest.raises(InputError, match="chunk_sites: expected an integer >= 0"):
        ldft.learn(ldft.PolynomialLagrangian((2, 2)), _strings(1), chunk_sites=-1)


# -- several processes -----------------------------------------------------------------------------------------
_WORKER = (
    """
import os, sys, json, numpy as np, torch
torch.set_num_threads(1)
import torch.distributed as dist
import latticedft as ldft
import latticedft.io
from latticedft import systems
from latticedft._learn import _dist
_dist.init_from_env()
out = {}
fields = [systems.wave_string([(k, 0.5 / k), (k + 1, 0.1, 0.3 * k)], nx=24, nt=40) for k in range(1, 5)]
for ridge in (0.0, "auto"):
    m = ldft.PolynomialLagrangian((2, 4))
    rep = ldft.learn(m, fields, chunk_sites=200, ridge=ridge)
    out[f"poly {ridge}"] = [m.coef.tolist(), rep.rel_res, rep.ridge]
data = systems.klein_gordon_training_set(n=4, steps=10, seed=0)
m = ldft.MLPLagrangian(hidden=[6], activation="tanh", form="free", seed=0)
rep = ldft.learn(m, data, optimizer="lbfgs", max_iter=8, chunk_sites=150, boundary="periodic")
out["mlp"] = [torch.cat([p.detach().reshape(-1) for p in m.parameters()]).tolist(), rep.loss, rep.iterations]
with open(sys.argv[1], "w") as f:
    json.dump(out, f)
"""
    + GROUP_END
)


@pytest.mark.slow
def test_two_processes_on_the_loopback_learn_what_one_learns(tmp_path: Path) -> None:
    ref, ranks = alone_and_in_two(tmp_path, _WORKER)
    assert ranks[0] == ranks[1]  # every process ends with the same model, bit for bit
    for key in ("poly 0.0", "poly auto"):
        coef, rel_res, ridge = ranks[0][key]
        assert _rel(np.array(coef), np.array(ref[key][0])) < 1e-10  # linear models: round-off
        assert rel_res == pytest.approx(ref[key][1], rel=1e-8) and ridge == ref[key][2]
    params, loss, iterations = ranks[0]["mlp"]
    assert _rel(np.array(params), np.array(ref["mlp"][0])) < 1e-8  # an MLP, 8 L-BFGS iterations, seed 0
    assert loss == pytest.approx(ref["mlp"][1], rel=1e-6) and iterations == ref["mlp"][2]


@pytest.mark.slow
def test_cli_workers_train_the_same_model(tmp_path: Path) -> None:
    case = tmp_path / "case"
    (case / "data").mkdir(parents=True)
    for i, f in enumerate(_strings(3)):
        ldft.io.write_field(case / "data" / f"train_{i}.nc", {"psi": f})
    (case / "case.toml").write_text(
        '[model]\nkind = "polynomial"\norders = [2, 4]\n\n[train]\ndata = ["data/train_*.nc"]\nchunk_sites = 300\n'
    )
    env = group_env(REPO)
    runs = {}
    for workers in (1, 2):
        out = tmp_path / f"results_{workers}"
        proc = subprocess.run(
            [sys.executable, "-m", "latticedft", "train", str(case), "--out", str(out), "--workers", str(workers)],
            env=env,
            capture_output=True,
            text=True,
            timeout=600,
        )
        assert proc.returncode == 0, proc.stderr[-2000:]
        runs[workers] = ldft.load_model(out / "model.pt")
    assert "training in 2 processes" in proc.stderr
    assert _rel(_coef(runs[2]), _coef(runs[1])) < 1e-10
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "latticedft",
            "train",
            str(case),
            "--out",
            str(tmp_path / "results_1"),
            "--workers",
            "2",
        ],
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert proc.returncode == 1 and "exists; use --overwrite" in proc.stderr  # rank 0's error, once
    assert proc.stderr.count("latticedft: error") == 1
