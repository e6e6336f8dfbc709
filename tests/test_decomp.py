"""Serving split into slabs over processes (``latticedft._serve._decomp``): the plan, its refusals, and the
field of 2 processes (gloo on the loopback, and a two-node ``torchrun``) against the one-process field."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
import xarray as xr

import latticedft as ldft
from latticedft._errors import InputError
from latticedft._models import AnalyticLagrangian
from latticedft._serve._decomp import plan_slabs, serve_slabs

from helpers import GROUP_END, free_port, group_env, run_group

REPO = Path(__file__).resolve().parents[1]

_WORKER = (
    """
import os, sys, json, numpy as np, torch, xarray as xr
torch.set_num_threads(1)
import torch.distributed as dist
import latticedft as ldft
from latticedft._learn import _dist
from latticedft._serve._decomp import serve_slabs
from latticedft._models import AnalyticLagrangian
_dist.init_from_env()
def sg(cells, h):  # sine-Gordon on the first-order stencil: a nonlinear DEL, block-diagonal slice Jacobian
    u0 = cells[..., 0, 0]
    kin = 0.5 * ((cells[..., 1, 0] - u0) / h[0]) ** 2
    grad = sum(0.5 * ((cells[..., a + 1, 0] - u0) / h[a]) ** 2 for a in range(1, len(h)))
    return kin - grad - (1 - torch.cos(u0))
rank = dist.get_rank() if dist.is_initialized() else 0
def field(nx, ny=None, nt=2):
    x, t = np.arange(nx) / nx, np.arange(nt) * 0.01
    if ny is None:
        b = np.sin(2 * np.pi * x) + 0.3 * np.cos(6 * np.pi * x)
        v = np.stack([b * np.cos(2 * np.pi * k * 0.01) for k in range(nt)])
        return xr.DataArray(v, dims=("t", "x"), coords={"t": t, "x": x}, name="psi")
    y = np.arange(ny) / ny
    b = np.sin(2 * np.pi * x)[:, None] * np.cos(4 * np.pi * y)[None, :]
    v = np.stack([b * np.cos(2 * np.pi * k * 0.01) for k in range(nt)])
    return xr.DataArray(v, dims=("t", "x", "y"), coords={"t": t, "x": x, "y": y}, name="psi")
cases = {
    "1+1D periodic": (ldft.lagrangians.klein_gordon(1.0), field(40), 120, "periodic", 7),
    "2+1D periodic": (ldft.lagrangians.wave(), field(16, 12), 90, "periodic", 10),
    "2+1D dirichlet": (ldft.lagrangians.wave(), field(16, 12, nt=60), 60, "dirichlet", 5),
    "1+1D sine-Gordon": (AnalyticLagrangian(sg, name="sG"), field(24), 60, "periodic", 4),
    "2+1D sine-Gordon": (AnalyticLagrangian(sg, name="sG"), field(10, 8), 30, "periodic", 3),
}
out = {}
for name, (model, init, slices, bnd, every) in cases.items():
    got = serve_slabs(model, init, slices, boundary=bnd, every=every)
    if rank == 0:
        one = ldft.serve(model, init, slices=slices, boundary=bnd, every=every).field
        assert got["slice"].values.tolist() == one["slice"].values.tolist()
        out[name] = float(np.abs(got.values - one.values).max() / np.abs(one.values).max())
    else:
        assert got is None
if rank == 0:
    with open(sys.argv[1], "w") as f:
        json.dump(out, f)
"""
    + GROUP_END
)


def _check(out: Path) -> None:
    rel = json.loads(out.read_text())
    assert set(rel) == {"1+1D periodic", "2+1D periodic", "2+1D dirichlet", "1+1D sine-Gordon", "2+1D sine-Gordon"}
    assert all(v <= 1e-12 for v in rel.values()), rel


def test_the_slabs_cover_the_axis_once() -> None:
    slabs = plan_slabs(10, 3, 1, True)
    assert [(s.lo, s.hi) for s in slabs] == [(0, 3), (3, 6), (6, 10)]
    assert slabs[0].local.tolist() == [9, 0, 1, 2, 3] and slabs[0].own == slice(1, 4)
    edge = plan_slabs(10, 3, 1, False)[0]
    assert edge.local.tolist() == [0, 1, 2, 3] and edge.own == slice(0, 3)


def test_more_processes_than_planes_is_refused_in_one_line() -> None:
    with pytest.raises(InputError) as err:
        plan_slabs(4, 5, 1, True)
    assert str(err.value) == "--workers: 5 processes for the 4 planes of the outer axis 'x': at most 4 (one plane each)"


def test_a_halo_wider_than_a_slab_is_refused_in_one_line() -> None:
    with pytest.raises(InputError) as err:
        plan_slabs(5, 3, 2, True)
    assert str(err.value).startswith("--workers: the halo of 2 planes is wider than a slab of 1 planes")
    assert "\n" not in str(err.value)


def test_one_process_serves_sine_gordon_by_slice_newton_as_serve() -> None:
    def fn(cells: torch.Tensor, h: tuple[float, ...]) -> torch.Tensor:
        u0, u1, u2 = cells[..., 0, 0], cells[..., 1, 0], cells[..., 2, 0]
        return 0.5 * ((u1 - u0) / h[0]) ** 2 - 0.5 * ((u2 - u0) / h[1]) ** 2 - (1 - torch.cos(u0))

    x = np.arange(8) / 8
    init = xr.DataArray(
        np.stack([np.sin(2 * np.pi * x)] * 2), dims=("t", "x"), coords={"t": [0.0, 0.01], "x": x}, name="psi"
    )
    model = AnalyticLagrangian(fn, name="sG")
    got = serve_slabs(model, init, 10, boundary="periodic")
    one = ldft.serve(model, init, slices=10, boundary="periodic").field
    assert got is not None and np.array_equal(got.values, one.values)


def test_one_process_serves_the_field_of_serve() -> None:
    x = np.arange(20) / 20
    init = xr.DataArray(
        np.stack([np.sin(2 * np.pi * x)] * 2), dims=("t", "x"), coords={"t": [0.0, 0.01], "x": x}, name="psi"
    )
    got = serve_slabs(ldft.lagrangians.wave(), init, 30, boundary="periodic", every=4)
    one = ldft.serve(ldft.lagrangians.wave(), init, slices=30, boundary="periodic", every=4).field
    assert got is not None and np.abs(got.values - one.values).max() <= 1e-12 * np.abs(one.values).max()


@pytest.mark.slow
def test_two_processes_on_gloo_serve_the_one_process_field(tmp_path: Path) -> None:
    script = tmp_path / "worker.py"
    script.write_text(_WORKER)
    run_group(lambda r: [sys.executable, str(script), str(tmp_path / "two.json")], 2, group_env(REPO))
    _check(tmp_path / "two.json")


@pytest.mark.slow
def test_a_two_node_torchrun_serves_the_one_process_field(tmp_path: Path) -> None:
    """Two invocations of ``torchrun --nnodes 2`` (one process each) meeting at 127.0.0.1, bounded in time."""
    script = tmp_path / "worker.py"
    script.write_text(_WORKER)
    port = str(free_port())
    procs = [
        subprocess.Popen(
            [
                *[sys.executable, "-m", "torch.distributed.run", "--nnodes", "2", "--nproc-per-node", "1"],
                *["--node-rank", str(node), "--master-addr", "127.0.0.1", "--master-port", port],
                *[str(script), str(tmp_path / "nodes.json")],
            ],
            env=group_env(REPO),
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
        )
        for node in range(2)
    ]
    try:
        logs = [p.communicate(timeout=300)[0] for p in procs]
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
                p.communicate()
    assert [p.returncode for p in procs] == [0, 0], "\n".join(log[-3000:] for log in logs)
    _check(tmp_path / "nodes.json")
