"""``latticedft serve/run CASE --workers N``: each task that can be split is served in slabs over the processes.

A small periodic 1+1D Klein-Gordon case (the affine recurrence of a learned quadratic ``L_d``): ``run
--workers 2``, ``serve --workers 2`` and ``serve`` under ``torchrun --nproc-per-node 2`` give the task file
one process gives with the same model, to 1e-12 of the field's scale, and ``summary.json`` records the
processes and the slabs. Bad input (more processes than planes of the outer axis, a halo wider than a slab)
is refused in one line naming ``--workers``, and writes nothing.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import xarray as xr

from latticedft import systems
from latticedft.io import write_field

from case_helpers import run_cli, snapshot, write_toml
from helpers import group_env

REPO = Path(__file__).resolve().parents[1]


def tiny_klein_gordon(tmp: Path, stencil: str = "") -> Path:
    """Eight training fields of 20 sites, a test field of 41 slices with a perturbed baseline, periodic."""
    case = tmp / "kg"
    (case / "data").mkdir(parents=True)
    for k, da in enumerate(systems.klein_gordon_training_set(n=8, steps=20, seed=0)):
        write_field(case / "data" / f"train_{k}.nc", {"psi": da})
    test = systems.klein_gordon_test_field(steps=40)
    write_field(case / "data" / "test.nc", {"psi": test})
    write_field(case / "data" / "base.nc", {"psi": test * (1 + 1e-3 * np.cos(np.arange(41)))[:, None]})
    return write_toml(
        case,
        f"""
        [model]
        kind = "polynomial"
        orders = [2, 2]
        {stencil}
        [train]
        data = ["data/train_*.nc"]
        boundary = "periodic"
        [[serve]]
        name = "test"
        from = "data/test.nc"
        boundary = "periodic"
        baseline = "data/base.nc"
        invariant = "latticedft.systems:klein_gordon_energy"
        charges = ["momentum-x", "energy"]
        [run]
        threads = 1
        [export]
        formats = []
        """,
    )


def _python(*argv: object) -> subprocess.CompletedProcess[str]:
    """``python ARGV`` in a subprocess that imports this checkout, outside any process group."""
    env = group_env(REPO)
    env["PYTHONPATH"] = os.pathsep.join([str(REPO), *filter(None, [os.environ.get("PYTHONPATH")])])
    cmd = [sys.executable, *map(str, argv)]
    return subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=600, check=False)


def _latticedft(*argv: object) -> subprocess.CompletedProcess[str]:
    return _python("-m", "latticedft", *argv)


def _same_task(a: Path, b: Path, name: str = "test") -> None:
    """The task files hold the same variables, equal to 1e-12 of the field's largest magnitude."""
    with xr.open_dataset(a / f"{name}.nc") as da, xr.open_dataset(b / f"{name}.nc") as db:
        assert list(da.data_vars) == list(db.data_vars)
        scale = float(np.abs(da["psi"]).max())
        for v in da.data_vars:
            assert da[v].dims == db[v].dims and da[v].shape == db[v].shape, v
            diff = np.nanmax(np.abs(np.asarray(da[v].values, float) - np.asarray(db[v].values, float)))
            assert diff <= 1e-12 * max(scale, float(np.nanmax(np.abs(da[v].values)))), (v, diff)
            for c in da[v].coords:
                np.testing.assert_array_equal(da[v][c].values, db[v][c].values)


def _split_recorded(folder: Path, processes: int = 2) -> dict:
    summary = json.loads((folder / "summary.json").read_text())
    assert summary["processes"] == processes
    task = summary["tasks"]["test"]
    assert task["decomposition"] == {"processes": 2, "axis": "x", "slabs": [[0, 10], [10, 20]]}
    assert task["complete"] and task["solver"] == "affine"
    return task


@pytest.mark.slow
def test_run_and_serve_with_two_workers_give_the_one_process_task_file(tmp_path: Path) -> None:
    case = tiny_klein_gordon(tmp_path)
    two = _latticedft("run", case, "--workers", 2, "--out", tmp_path / "two")
    assert two.returncode == 0, two.stderr
    assert "task test: split over 2 processes along 'x', slabs [0, 10) [10, 20)" in two.stderr
    assert "split over 2 processes" in (tmp_path / "two" / "run.log").read_text()
    split = _split_recorded(tmp_path / "two")
    shutil.copytree(tmp_path / "two", tmp_path / "one")  # the same model, served in one process
    one = _latticedft("serve", case, "--out", tmp_path / "one")
    assert one.returncode == 0, one.stderr
    _same_task(tmp_path / "one", tmp_path / "two")
    whole = json.loads((tmp_path / "one" / "summary.json").read_text())
    assert "processes" not in whole and "decomposition" not in whole["tasks"]["test"]
    ref = whole["tasks"]["test"]
    for key in ("max_error", "rms_error", "relative_error", "invariant_drift"):
        assert split[key] == pytest.approx(ref[key], rel=1e-6, abs=1e-13), key
    for key in ("max_error", "rms_error", "max_error_same_slices", "rms_error_same_slices"):
        assert split["baseline"][key] == pytest.approx(ref["baseline"][key], rel=1e-9), key
    shutil.copytree(tmp_path / "one", tmp_path / "served")
    served = _latticedft("serve", case, "--workers", 2, "--out", tmp_path / "served")
    assert served.returncode == 0, served.stderr
    _split_recorded(tmp_path / "served")
    _same_task(tmp_path / "one", tmp_path / "served")
    shutil.copytree(tmp_path / "one", tmp_path / "torchrun")
    launcher = ["-m", "torch.distributed.run", "--standalone", "--nproc-per-node", "2", "-m", "latticedft"]
    under = _python(*launcher, "serve", case, "--out", tmp_path / "torchrun")
    assert under.returncode == 0, under.stderr[-2000:]
    _split_recorded(tmp_path / "torchrun")
    _same_task(tmp_path / "one", tmp_path / "torchrun")


@pytest.mark.parametrize(
    ("stencil", "size", "problem"),
    [
        ("", 21, "21 processes for the 20 planes of the outer axis 'x': at most 20"),
        ("stencil = [[0, 0], [1, 0], [0, 1], [0, 2], [0, 3]]", 8, "the halo of 3 planes is wider than a slab"),
    ],
)
def test_bad_split_is_refused_naming_workers_and_writes_nothing(tmp_path, capsys, monkeypatch, stencil, size, problem):
    """Rank 0 of ``size`` processes (as ``torchrun`` starts it) refuses before it joins the group."""
    case = tiny_klein_gordon(tmp_path, stencil)
    code, _, err = run_cli(capsys, "run", case, "-q")
    assert code == 0, err
    before = snapshot(case / "results")
    monkeypatch.setenv("WORLD_SIZE", str(size))
    monkeypatch.setenv("RANK", "0")
    for command in ("serve", "run") if size == 21 else ("serve",):
        code, _, err = run_cli(capsys, command, case, "-q", *(["--overwrite"] if command == "run" else []))
        assert code == 1
        lines = err.strip().splitlines()
        assert len(lines) == 1 and "--workers" in lines[0] and problem in lines[0], err
        assert snapshot(case / "results") == before


@pytest.mark.slow
def test_train_with_two_workers_serves_nothing(tmp_path: Path) -> None:
    """``train`` has no serving: its other rank leaves after training, though the case's task could be split.
    Rank 0's calibration (``[train] calibrate``: trial fits and held-out serving of its own after training)
    enters no collective, so it neither waits on the rank that left (it hung there) nor mixes with it."""
    case = tiny_klein_gordon(tmp_path)
    out = tmp_path / "out"
    proc = _latticedft("train", case, "--workers", 2, "--out", out, "--set", "train.calibrate=true")
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "training in 2 processes" in proc.stderr and "split over" not in proc.stderr
    assert not list(out.glob("*.nc"))
    calibration = json.loads((out / "summary.json").read_text())["train"]["calibration"]
    assert calibration["held_out_slices"] > 0 and (out / "calibration.pt").is_file()
