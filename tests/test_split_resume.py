"""Checkpointed serving split over processes: ``[[serve]] checkpoint = K`` with ``--workers 2``.

Rank 0 writes each checkpoint (the state gathered from every process, in one process's layout). A split
serve killed (SIGKILL, of rank 0, right after its first checkpoint; the launcher then stops the other
rank) is continued by ``serve --resume --workers 2`` to the results of the uninterrupted split run, bit for
bit; the same checkpoint taken up by one process gives the field to Newton's tolerance (the factorisation
of the chord steps is not carried across decompositions). ``run --resume --workers 2`` takes up the same
checkpoint split too, to the same results bit for bit. Bad input under ``--workers``: ``--resume``
without a checkpoint, or with a changed case, is refused in one line naming the key, writing nothing.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import xarray as xr
from test_resume import _latticedft, _same_results, _stage, tiny_sine_gordon

from latticedft._run._resume import RESUME_FILE

from case_helpers import copy_wave, run_cli, snapshot
from helpers import RANK_RESULTS_END, two_ranks

SETS = ["--set", "serve.test.slices=41", "--set", "serve.test.checkpoint=10"]


@pytest.mark.slow
def test_a_killed_split_serve_is_resumed_split_to_the_same_results(tmp_path: Path, capsys) -> None:
    """1+1D sine-Gordon by split slice-Newton (the Krylov step, chord steps across slices), with an invariant
    measured by rank 0 on the whole slices and the errors on each slab."""
    case = tiny_sine_gordon(tmp_path)
    trained = _latticedft("train", case, "-q")
    assert trained.returncode == 0, trained.stderr
    shutil.copytree(case / "results", tmp_path / "whole")
    whole = _latticedft("serve", case, "-q", "--workers", "2", *SETS, "--out", tmp_path / "whole")
    assert whole.returncode == 0, whole.stderr
    before = snapshot(case / "results")
    killed = _latticedft("serve", case, "-q", "--workers", "2", *SETS, fault="kill:checkpoint")
    assert killed.returncode != 0 and snapshot(case / "results") == before
    stage = _stage(case)
    assert (stage / ".test.ckpt").is_file()
    shutil.copytree(stage, tmp_path / "stage")
    held = snapshot(stage)
    code, _, err = run_cli(
        capsys, "serve", case, "-q", "--workers", "2", *SETS, "--set", "serve.test.rtol=1e-9", "--resume"
    )
    assert code != 0 and len(err.strip().splitlines()) == 1, err
    assert "serve[0].rtol: is 1e-09 now but the checkpointed run had unset" in err
    assert snapshot(stage) == held and snapshot(case / "results") == before
    resumed = _latticedft("serve", case, "-q", "--workers", "2", *SETS, "--resume")
    assert resumed.returncode == 0, resumed.stderr
    _same_results(tmp_path / "whole", case / "results")
    shutil.copytree(tmp_path / "stage", stage)  # the same checkpoint, taken up by one process
    alone = _latticedft("serve", case, "-q", *SETS, "--resume")
    assert alone.returncode == 0, alone.stderr
    with xr.open_dataset(tmp_path / "whole" / "test.nc") as a, xr.open_dataset(case / "results" / "test.nc") as b:
        diff = float(np.abs(a["psi"].values - b["psi"].values).max() / np.abs(a["psi"].values).max())
        assert 0 < diff < 1e-7 and a["psi"].sizes["t"] == b["psi"].sizes["t"] == 41
    # `run --resume --workers 2` serves on split too: the same stage, its journal made a killed `run`'s
    shutil.copytree(tmp_path / "stage", stage)
    journal = json.loads((stage / RESUME_FILE).read_text())
    (stage / RESUME_FILE).write_text(json.dumps({**journal, "command": "run"}))
    resumed = _latticedft("run", case, "-q", "--workers", "2", *SETS, "--resume")
    assert resumed.returncode == 0, resumed.stderr
    _same_results(tmp_path / "whole", case / "results")


def test_resume_without_a_checkpoint_under_workers_is_refused_before_the_processes_start(tmp_path, capsys):
    case = copy_wave(tmp_path)
    code, _, err = run_cli(capsys, "serve", case, "-q", "--workers", "2", "--resume")
    assert code != 0 and len(err.strip().splitlines()) == 1, err
    assert err.startswith("latticedft: error: --resume: no checkpointed run")
    assert not (case / "results").exists() and not list(case.glob("results.tmp-*"))


_WORKER = (
    """
import os, sys, json, numpy as np, torch, xarray as xr
torch.set_num_threads(1)
import torch.distributed as dist
import latticedft as ldft
from latticedft._learn import _dist
from latticedft._models import AnalyticLagrangian
from latticedft._serve._decomp import serve_slabs
from latticedft._serve._slabstate import SlabCheckpoint
_dist.init_from_env()
rank = dist.get_rank()
def sg(cells, h):  # sine-Gordon on the first-order stencil: split site-wise slice-Newton, chord steps
    u0 = cells[..., 0, 0]
    kin = 0.5 * ((cells[..., 1, 0] - u0) / h[0]) ** 2
    grad = sum(0.5 * ((cells[..., a + 1, 0] - u0) / h[a]) ** 2 for a in range(1, len(h)))
    return kin - grad - (1 - torch.cos(u0))
x, y, t = np.arange(8) / 8, np.arange(6) / 6, np.arange(2) * 0.05
b = np.sin(2 * np.pi * x)[:, None] * (1 + 0.5 * np.cos(2 * np.pi * y))[None, :]
init = xr.DataArray(np.stack([b, 1.01 * b]), dims=("t", "x", "y"), coords={"t": t, "x": x, "y": y}, name="psi")
class Keeper:  # one process's checkpointer, going on from a split state
    def __init__(self, state):
        self.state, self.checkpointer = state, self
    def __call__(self, i, values):
        pass
    def save(self, state):
        pass
    def load(self):
        return self.state
out = {}
for name, model in (("affine", ldft.lagrangians.wave()), ("newton", AnalyticLagrangian(sg, name="sG"))):
    saved, put = [], []
    first = SlabCheckpoint(5, lambda: rank, put.append, save=saved.append if rank == 0 else None)
    whole = serve_slabs(model, init, 24, boundary="periodic", checkpoint=first)
    state = None
    if rank == 0:
        state = saved[1]  # the second checkpoint, after slice 10
        state["kept_values"] = whole.values[: state["nkept"], ..., None]
    again = SlabCheckpoint(5, lambda: rank, put.append, state=state)
    resumed = serve_slabs(model, init, 24, boundary="periodic", checkpoint=again)
    got = {"put": put, "saved": len(saved)}
    if rank == 0:
        got["same"] = bool(np.array_equal(whole.values, resumed.values))
        alone = ldft.serve(model, init, slices=24, boundary="periodic", checkpoint=5, on_slice=Keeper(state))
        one = ldft.serve(model, init, slices=24, boundary="periodic")
        scale = np.abs(one.field.values).max()
        got["alone"] = float(np.abs(alone.field.values - whole.values).max() / scale)
        got["split"] = float(np.abs(one.field.values - whole.values).max() / scale)
    out[name] = got
"""
    + RANK_RESULTS_END
)


@pytest.mark.slow
def test_split_states_resume_bit_for_bit_and_in_one_process(tmp_path: Path) -> None:
    """The library piece, 2+1D periodic, the affine recurrence and site-wise slice-Newton: a split serve
    resumed from its second checkpoint gives the uninterrupted split field bit for bit (each process's own
    figures put back); one process going on from the split state gives it to round-off (affine) or Newton's
    tolerance (the factorisation not carried over)."""
    zero, one = two_ranks(tmp_path, _WORKER)
    for name in ("affine", "newton"):
        assert zero[name]["same"] and zero[name]["saved"] == 4, zero
        assert zero[name]["put"] == [0] and one[name]["put"] == [1]  # each process's own figures, back to it
        assert zero[name]["split"] <= 1e-12
    assert zero["affine"]["alone"] <= 1e-12 and zero["newton"]["alone"] <= 1e-8
