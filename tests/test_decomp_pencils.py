"""Serving split into pencils (``latticedft._serve._grid``): the grid's choice, its refusals, and the field
of 4 gloo processes on the loopback in a 2 x 2 grid against the one-process field, for the affine
recurrence, site-wise slice-Newton and the Krylov step (whose cell stencil reaches the corner blocks), the
split checkpoints, a non-convergence, and the command line's driver (errors reduced over the blocks)."""

from __future__ import annotations

from pathlib import Path

import pytest
from test_decomp_krylov import _MODEL

from latticedft._errors import InputError
from latticedft._serve._grid import grid_text, plan_grid, plan_slabs

from helpers import RANK_RESULTS_END, run_ranks

_WORKER = (
    _MODEL
    + """
import os, sys, json
torch.set_num_threads(1)
import torch.distributed as dist
import latticedft as ldft
from latticedft._learn import _dist
from latticedft._serve._decomp import serve_slabs
from latticedft._errors import InputError
_dist.init_from_env()
rank, out = dist.get_rank(), {}
def sg(cells, h):  # sine-Gordon on the first-order stencil: site-wise slice-Newton
    u0 = cells[..., 0, 0]
    kin = 0.5 * ((cells[..., 1, 0] - u0) / h[0]) ** 2
    grad = sum(0.5 * ((cells[..., a + 1, 0] - u0) / h[a]) ** 2 for a in range(1, len(h)))
    return kin - grad - (1 - torch.cos(u0))
def grid(shape, nt=2):
    axes = [np.arange(n) / n for n in shape]
    b = np.sin(2 * np.pi * axes[0])[:, None] * np.cos(2 * np.pi * axes[1])[None, :] + 0.2 * axes[1][None, :]
    if len(shape) == 3:
        b = b[..., None] * (1 + 0.3 * np.sin(2 * np.pi * axes[2]))
    v = np.stack([b * np.cos(2 * np.pi * k * 0.01) for k in range(nt)])
    dims = ("t", "x", "y", "z")[: len(shape) + 1]
    return xr.DataArray(v, dims=dims, coords={"t": np.arange(nt) * 0.01, **dict(zip(dims[1:], axes))}, name="psi")
sG = ldft.AnalyticLagrangian(sg, name="sG")
cases = {  # name: model, start, slices, boundary, every, grid, rtol
    "affine 2+1D periodic": (ldft.lagrangians.wave(), grid((6, 8)), 24, "periodic", 5, (2, 2), 1e-10),
    "affine 2+1D dirichlet": (ldft.lagrangians.wave(), grid((6, 8), 20), 20, "dirichlet", 3, (2, 2), 1e-10),
    "affine 3+1D periodic": (ldft.lagrangians.wave(), grid((4, 4, 3)), 10, "periodic", 3, (2, 2), 1e-10),
    "sitewise 2+1D periodic": (sG, grid((6, 8)), 16, "periodic", 3, (2, 2), 1e-10),
    "krylov 2+1D periodic": (MODEL, field(2), 10, "periodic", 3, (2, 2), 1e-13),
    "krylov 2+1D dirichlet": (MODEL, field(10), 10, "dirichlet", 3, (2, 2), 1e-13),
    "auto: 4 processes, 3 planes": (ldft.lagrangians.wave(), grid((3, 8)), 12, "periodic", 4, None, 1e-10),
}
for name, (model, init, slices, bnd, every, shape, rtol) in cases.items():
    rep, seen = {}, {}  # seen: every slice whole, gathered to rank 0 (a task with an output cadence)
    got = serve_slabs(model, init, slices, boundary=bnd, every=every, rtol=rtol, report=rep, grid=shape,
                      on_slice=lambda i, v: seen.update({i: v}))
    if rank == 0:
        kept = np.stack([seen[int(i)][..., 0] for i in got["slice"].values])
        assert len(seen) == slices and np.array_equal(kept, got.values), name
        one = ldft.serve(model, init, slices=slices, boundary=bnd, every=every, rtol=rtol).field
        assert got["slice"].values.tolist() == one["slice"].values.tolist()
        rel = float(np.abs(got.values - one.values).max() / np.abs(one.values).max())
        out[name] = [rel, bool(np.array_equal(got.values, one.values)), rep["grid"], rep.get("slice_solver")]
        if shape is None:  # what summary.json records of the task
            from latticedft._run._split import _decomposition
            out["summary"] = _decomposition(rep, "test")
from types import SimpleNamespace
from latticedft._run._split import serve_split
from latticedft._serve._options import Cadence, ServeOptions
ref = grid((6, 8), 20)  # the command line's driver: the errors against the reference and the baseline, reduced
task = SimpleNamespace(options=ServeOptions(), start="auto", cadence=Cadence(1), boundary="dirichlet", name="t")
td = SimpleNamespace(task=task, slices=20, init=ref, reference=ref, baseline=ref * 1.001, invariant=None)
split = serve_split(ldft.lagrangians.wave(), td, ref)
if rank == 0:
    one = ldft.serve(ldft.lagrangians.wave(), ref, slices=20, boundary="dirichlet").field.values
    d, b = np.abs(one - ref.values), np.abs(td.baseline.values - ref.values)
    err, base = split.errors[0], split.baseline[0]
    out["driver"] = [
        split.decomposition, bool(np.array_equal(split.result.field.values, one)),
        bool(err["max_error"] == d.max()), float(err["rms_error"] / np.sqrt(np.mean(d**2))),
        bool(base["max_error"] == b.max()), float(base["rms_error"] / np.sqrt(np.mean(b**2))),
    ]
from latticedft._serve._flag import SlabError
from latticedft._errors import ServeError
try:  # slice-Newton not converging: one process's message, its site in the whole lattice; the slices before
    serve_slabs(sG, grid((6, 8)), 12, boundary="periodic", max_newton=1, grid=(2, 2))
except SlabError as err:
    try:
        ldft.serve(sG, grid((6, 8)), slices=12, boundary="periodic", max_newton=1)
    except ServeError as one:
        same = None if err.result is None else bool(np.array_equal(err.result.values, one.result.field.values))
        out["newton"] = [str(err), str(one), err.site, same]
from latticedft._stencil import Stencil
reach = Stencil([(0, 0, 0), (1, 0, 0), (0, 1, 0), (0, 2, 0), (0, 0, 1), (0, 0, 2)])  # two planes each way
def wide(c, h):
    u = c[..., 0]
    return 0.5 * ((u[..., 1] - u[..., 0]) / h[0]) ** 2 - sum(
        0.5 * ((u[..., 2 * a + 3] - u[..., 0]) / (2 * h[a + 1])) ** 2 for a in range(2))
try:
    serve_slabs(ldft.AnalyticLagrangian(wide, name="wide", stencil=reach), grid((3, 3)), 6, boundary="periodic")
except InputError as exc:
    out["thin"] = str(exc)
from latticedft._serve._slabstate import SlabCheckpoint
for name, model in (("resume affine", ldft.lagrangians.wave()), ("resume newton", sG)):
    init, saved, put = grid((8, 6)), [], []
    first = SlabCheckpoint(4, lambda: rank, put.append, save=saved.append if rank == 0 else None)
    whole = serve_slabs(model, init, 18, boundary="periodic", checkpoint=first, grid=(2, 2))
    state = None
    if rank == 0:
        state = saved[1]  # the second checkpoint
        state["kept_values"] = whole.values[: state["nkept"], ..., None]
    got = {"saved": len(saved)}
    for again in ((2, 2), (4, 1)):  # the same grid, and slabs going on from the pencils' state
        ckpt = SlabCheckpoint(4, lambda: rank, put.append, state=None if state is None else dict(state))
        resumed = serve_slabs(model, init, 18, boundary="periodic", checkpoint=ckpt, grid=again)
        if rank == 0:
            got[str(again)] = float(np.abs(resumed.values - whole.values).max() / np.abs(whole.values).max())
            got["same"] = got.get("same", bool(np.array_equal(whole.values, resumed.values)))
    got["put"] = put
    out[name] = got
"""
    + RANK_RESULTS_END
)


def test_slabs_are_kept_where_they_hold_no_more_halo() -> None:
    for sizes, n in (((16, 12), 2), ((9, 7), 2), ((8, 8), 4), ((40,), 7)):
        blocks = plan_grid(sizes, n, (1,) * len(sizes), (True,) * len(sizes), ("x", "y")[: len(sizes)])
        assert grid_text(blocks) == f"slabs {n} over x"
        assert [b.parts for b in blocks] == [(s,) for s in plan_slabs(sizes[0], n, 1, True)]


def test_pencils_where_they_hold_less_halo_or_slabs_cannot_split() -> None:
    big = plan_grid((64, 64, 64), 16, (1, 1), (True, True), ("z", "y"))
    assert grid_text(big) == "pencils 4 x 4 over (z, y)"
    assert [b.bounds() for b in big[:2]] == [[[0, 16], [0, 16]], [[0, 16], [16, 32]]]
    assert [b.at for b in big[:5]] == [(0, 0), (0, 1), (0, 2), (0, 3), (1, 0)]
    assert grid_text(plan_grid((6, 12), 4, (1, 1), (True, True), ("x", "y"))) == "pencils 2 x 2 over (x, y)"
    assert grid_text(plan_grid((3, 8), 4, (1, 1), (True, True), ("x", "y"))) == "pencils 1 x 4 over (x, y)"


def test_a_block_thinner_than_the_halo_is_refused_in_one_line_naming_workers() -> None:
    with pytest.raises(InputError) as err:
        plan_grid((3, 3), 4, (2, 2), (True, True), ("x", "y"))
    text = str(err.value)
    assert text.startswith("--workers: 4 processes for the 3 planes of the outer axis 'x'") and "\n" not in text
    assert text.endswith("nor into pencils over ('x', 'y')")
    with pytest.raises(InputError) as err:
        plan_grid((8, 8), 4, (1, 1), (True, True), ("x", "y"), grid=(2, 3))
    assert str(err.value).startswith("--workers: ")
    with pytest.raises(InputError) as err:  # 1+1D: the slabs' refusal alone
        plan_grid((4,), 5, (1,), (True,), ("x",))
    assert str(err.value) == "--workers: 5 processes for the 4 planes of the outer axis 'x': at most 4 (one plane each)"


@pytest.mark.slow
def test_four_processes_in_a_2_by_2_grid_serve_the_one_process_field(tmp_path: Path) -> None:
    """One group of 4 processes runs every check (tens of seconds on a loaded 2-core machine, mostly the
    processes' start): one group rather than one a check."""
    import json

    script = tmp_path / "worker.py"
    script.write_text(_WORKER)
    ranks = run_ranks(script, 4, str(tmp_path / "out"))
    assert [rc for rc, _, _ in ranks] == [0] * 4, "\n".join(err[-3000:] for _, _, err in ranks)
    zero = json.loads((tmp_path / "out.0").read_text())
    thin = zero.pop("thin")
    record, same, worst, rms, base_worst, base_rms = zero.pop("driver")
    assert record["grid"].startswith("pencils") and same and worst and base_worst, zero
    assert abs(rms - 1) <= 1e-12 and abs(base_rms - 1) <= 1e-12
    err, one, site, same = zero.pop("newton")
    assert err == one and "in the DEL equation of site index t=1" in err and site[0] == 1 and same, (err, one)
    blocks = [[[0, 3], [lo, lo + 2]] for lo in (0, 2, 4, 6)]
    grid = "pencils 1 x 4 over (x, y)"
    assert zero.pop("summary") == {"processes": 4, "grid": grid, "axes": ["x", "y"], "blocks": blocks}
    for name in ("resume affine", "resume newton"):  # from the second checkpoint: bit for bit on the same grid
        got = zero.pop(name)
        assert got["saved"] == 3 and got["same"] and got["(2, 2)"] == 0.0, got
        assert got["(4, 1)"] <= (1e-12 if "affine" in name else 1e-8), got
        assert got["put"] == [0, None], got  # its own figures back to each process of the same grid only
    assert len(zero) == 7, zero
    for name, (rel, _same, grid, solver) in zero.items():
        assert rel <= 1e-12, (name, zero[name])
        assert grid == ("pencils 1 x 4 over (x, y)" if name.startswith("auto") else "pencils 2 x 2 over (x, y)")
        assert solver == ("krylov" if name.startswith("krylov") else "sitewise" if "sitewise" in name else None)
    # the local solves are those of one process: Dirichlet and site-wise Newton bit for bit
    assert zero["affine 2+1D dirichlet"][1] and zero["sitewise 2+1D periodic"][1]
    assert thin.startswith("--workers: 4 processes for the 3 planes") and thin.endswith(
        "nor into pencils over ('x', 'y')"
    )
    assert "\n" not in thin


def test_each_block_measures_its_own_part_of_the_reference() -> None:
    """The task's errors (``_run._split._SlabErrors``) over the blocks of a 2 x 2 grid: together, every site
    of the reference once (the sums of one process over the whole lattice)."""
    import numpy as np
    import xarray as xr

    from latticedft._run._split import _SlabErrors

    rng = np.random.default_rng(0)
    ref = xr.DataArray(rng.normal(size=(3, 6, 8)), dims=("t", "x", "y"))
    served = ref.values + 1e-3 * rng.normal(size=ref.shape)
    meters = []
    for block in plan_grid((6, 8), 4, (1, 1), (True, True), ("x", "y"), grid=(2, 2)):
        meter = _SlabErrors(ref)
        for i in range(3):
            meter(i, block, block.take(served[i], 0)[block.own][..., None])
        meters.append(meter.own())
    d = np.abs(served - ref.values)
    assert max(m[0] for m in meters) == d.max() and sum(m[3] for m in meters) == d.size
    assert abs(sum(m[1] for m in meters) - np.sum(d**2)) <= 1e-15 * np.sum(d**2)
