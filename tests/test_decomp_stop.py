"""A split serve that fails in one process, or in all, stops every process with the same one-line error;
rank 0 keeps what was served before it (``latticedft._serve._flag``). Two gloo processes on the loopback."""

from __future__ import annotations

from pathlib import Path

import pytest

from helpers import RANK_RESULTS_END, two_ranks

_WORKER = (
    """
import os, sys, json, numpy as np, torch, xarray as xr
torch.set_num_threads(1)
import torch.distributed as dist
import latticedft as ldft
from latticedft._errors import ServeError
from latticedft._learn import _dist
from latticedft._models import AnalyticLagrangian
from latticedft._serve._decomp import serve_slabs
from latticedft._serve._flag import SlabError
_dist.init_from_env()
rank = dist.get_rank()
calls = [0]
def sg(cells, h, fail_at=None):  # sine-Gordon on the first-order stencil: split slice-Newton
    calls[0] += 1
    if fail_at is not None and rank == 1 and calls[0] == fail_at:
        raise RuntimeError("injected failure\\nof the model")
    u0 = cells[..., 0, 0]
    kin = 0.5 * ((cells[..., 1, 0] - u0) / h[0]) ** 2
    grad = sum(0.5 * ((cells[..., a + 1, 0] - u0) / h[a]) ** 2 for a in range(1, len(h)))
    return kin - grad - (1 - torch.cos(u0))
x, y, t = np.arange(8) / 8, np.arange(6) / 6, np.arange(2) * 0.05
b = np.sin(2 * np.pi * x)[:, None] * (1 + 0.5 * np.cos(2 * np.pi * y))[None, :]
init = xr.DataArray(np.stack([b, b]), dims=("t", "x", "y"), coords={"t": t, "x": x, "y": y}, name="psi")
def failing_read(i, slab, values):
    if rank == 1 and i == 6:
        raise OSError("injected: cannot read the reference")
runs = {
    "read": (ldft.lagrangians.wave(), dict(on_slab=failing_read, every=2)),
    "model": (AnalyticLagrangian(lambda c, h: sg(c, h, fail_at=12), name="sG"), {}),
    "newton": (AnalyticLagrangian(sg, name="sG"), dict(max_newton=1)),
}
out = {}
for name, (model, kw) in runs.items():
    calls[0] = 0
    try:
        serve_slabs(model, init, 12, boundary="periodic", **kw)
        out[name] = None
        continue
    except SlabError as err:
        got = {"error": str(err), "slice": err.slice, "site": err.site}
        field = err.result
    if rank == 0:
        got["slices"] = field["slice"].values.tolist()
        kw.pop("on_slab", None)
        try:
            one = ldft.serve(AnalyticLagrangian(sg, name="sG") if name != "read" else model, init, slices=12,
                             boundary="periodic", every=1, max_newton=kw.get("max_newton", 30)).field
        except ServeError as e:
            one, got["one"] = e.result.field, str(e)
        ref = one.isel(t=got["slices"]).values
        got["diff"] = float(np.abs(field.values - ref).max() / np.abs(ref).max())
    else:
        got["result"] = field is None
    out[name] = got
"""
    + RANK_RESULTS_END
)


@pytest.mark.slow
def test_a_failure_in_one_process_stops_both_with_one_error(tmp_path: Path) -> None:
    zero, one = two_ranks(tmp_path, _WORKER)
    for name in ("read", "model", "newton"):
        assert zero[name]["error"] == one[name]["error"] and "\n" not in zero[name]["error"]
        assert one[name]["result"] and zero[name]["diff"] <= 1e-12
    assert zero["read"]["error"] == "slice 6: process 1 of 2 failed: OSError: injected: cannot read the reference"
    assert zero["read"]["slices"] == [0, 2, 4, 5] and zero["read"]["slice"] == 6
    assert zero["model"]["error"].endswith("process 1 of 2 failed: RuntimeError: injected failure")
    # a slice-Newton that does not converge: the message of one process, its site in the whole lattice
    assert zero["newton"]["error"] == zero["newton"]["one"] and zero["newton"]["slices"] == [0, 1]
