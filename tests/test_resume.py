"""Resumable serving: ``[[serve]] checkpoint = K`` and ``--resume``.

A run killed (SIGKILL) in the middle of a checkpointed task is continued by ``--resume``; its results equal
those of the uninterrupted run bit for bit (the task files' data variables, the summary's task entries but
their timings). Bad input (no checkpoint, a changed case, a bad ``checkpoint``) is refused in one line
naming the key, and writes nothing.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import xarray as xr

from latticedft import systems
from latticedft.io import write_field

from case_helpers import FAST, copy_wave, run_cli, snapshot, write_toml

REPO = Path(__file__).resolve().parents[1]
TIMINGS = {"wall_time", "sites_per_second"}
WAVE_SETS = ["--set", "serve.test.every=7", "--set", "serve.test.checkpoint=10", "--set", "export.formats=[]"]


def _env(fault: str | None) -> dict[str, str]:
    env = dict(os.environ, OMP_NUM_THREADS="1")
    env["PYTHONPATH"] = os.pathsep.join([str(REPO), *filter(None, [os.environ.get("PYTHONPATH")])])
    env.pop("LATTICEDFT_FAULT", None)
    if fault:
        env["LATTICEDFT_FAULT"] = fault
    return env


def _latticedft(*argv: object, fault: str | None = None) -> subprocess.CompletedProcess[str]:
    """``python -m latticedft ARGV`` in a subprocess (with the fault hook ``fault``)."""
    cmd = [sys.executable, "-m", "latticedft", *map(str, argv)]
    return subprocess.run(cmd, env=_env(fault), capture_output=True, text=True, timeout=300, check=False)


def _started(*argv: object, fault: str | None = None) -> subprocess.Popen[str]:
    """``python -m latticedft ARGV`` started in a subprocess (not waited for)."""
    cmd = [sys.executable, "-m", "latticedft", *map(str, argv)]
    return subprocess.Popen(cmd, env=_env(fault), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _same_results(a: Path, b: Path) -> None:
    """The task files' data variables and the summary's task entries (but timings) are equal bit for bit."""
    sa, sb = (json.loads((p / "summary.json").read_text()) for p in (a, b))
    assert sa["tasks"].keys() == sb["tasks"].keys()
    for name, ta in sa["tasks"].items():
        tb = sb["tasks"][name]
        assert {k: v for k, v in ta.items() if k not in TIMINGS} == {k: v for k, v in tb.items() if k not in TIMINGS}
        with xr.open_dataset(a / f"{name}.nc") as da, xr.open_dataset(b / f"{name}.nc") as db:
            assert list(da.data_vars) == list(db.data_vars)
            for v in da.data_vars:
                xr.testing.assert_identical(da[v].drop_attrs(), db[v].drop_attrs())
    assert not [p.name for p in b.iterdir() if p.name.endswith((".ckpt", ".part")) or "resume" in p.name]


def _stage(case: Path, name: str = "results") -> Path:
    (stage,) = case.glob(f"{name}.tmp-*")
    return stage


def test_run_killed_at_a_checkpoint_is_resumed_to_the_same_results(tmp_path):
    """The affine path (the wave case), with an output cadence: killed at its first checkpoint."""
    case = copy_wave(tmp_path)
    whole = _latticedft("run", case, "-q", *FAST, *WAVE_SETS, "--out", tmp_path / "whole")
    assert whole.returncode == 0, whole.stderr
    killed = _latticedft("run", case, "-q", *FAST, *WAVE_SETS, fault="kill:checkpoint")
    assert killed.returncode == -9, killed.stderr
    assert not (case / "results").exists()
    assert (_stage(case) / ".test.ckpt").is_file()
    resumed = _latticedft("run", case, "-q", *FAST, *WAVE_SETS, "--resume")
    assert resumed.returncode == 0, resumed.stderr
    assert not list(case.glob("results.tmp-*"))
    _same_results(tmp_path / "whole", case / "results")


def tiny_sine_gordon(tmp: Path) -> Path:
    """A 1+1D sine-Gordon case served by slice-Newton: one breather learned, another served (Dirichlet)."""
    case = tmp / "sg"
    (case / "data").mkdir(parents=True)
    lattice = {"xlim": (-12.0, 12.0), "nx": 61, "dt": 0.05}
    write_field(case / "data" / "train.nc", {"psi": systems.sine_gordon_breather(0.3, nt=161, **lattice)})
    write_field(case / "data" / "test.nc", {"psi": systems.sine_gordon_breather(0.6, x0=-1.0, nt=241, **lattice)})
    return write_toml(
        case,
        """
        [model]
        kind = "polynomial"
        orders = [2, 8]
        time_symmetric = true
        [train]
        data = ["data/train.nc"]
        [[serve]]
        name = "test"
        from = "data/test.nc"
        boundary = "dirichlet"
        checkpoint = 20
        invariant = "latticedft.systems:sine_gordon_energy"
        [run]
        threads = 1
        [export]
        formats = []
        """,
    )


def _stopped(proc: subprocess.Popen[str], path: Path, timeout: float = 300.0) -> None:
    """Wait (polling) until ``path`` exists and the process ``proc`` is stopped (it stops itself there)."""
    t_end = time.monotonic() + timeout
    while time.monotonic() < t_end:
        assert proc.poll() is None, proc.communicate()[1]
        state = Path(f"/proc/{proc.pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
        if path.is_file() and state == "T":
            return
        time.sleep(0.02)
    raise AssertionError(f"{path} did not appear in {timeout} s")


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="reads the process state from /proc")
def test_serve_killed_in_the_middle_is_resumed_to_the_same_field(tmp_path):
    """Slice-Newton (LU chord steps reused across slices), every slice kept: ``serve`` stops itself after its
    first checkpoint, is killed there with SIGKILL, and ``--resume`` gives the uninterrupted run's results."""
    case = tiny_sine_gordon(tmp_path)
    trained = _latticedft("train", case, "-q")
    assert trained.returncode == 0, trained.stderr
    shutil.copytree(case / "results", tmp_path / "whole")
    whole = _latticedft("serve", case, "-q", "--out", tmp_path / "whole")
    assert whole.returncode == 0, whole.stderr
    before = snapshot(case / "results")
    proc = _started("serve", case, "-q", fault="stop:checkpoint")
    try:
        deadline = time.monotonic() + 300
        while not list(case.glob("results.tmp-*/.test.ckpt")):
            assert proc.poll() is None and time.monotonic() < deadline, proc.communicate()[1]
            time.sleep(0.02)
        _stopped(proc, next(case.glob("results.tmp-*/.test.ckpt")))
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.communicate(timeout=60)
    assert proc.returncode == -9
    assert snapshot(case / "results") == before  # nothing published
    resumed = _latticedft("serve", case, "-q", "--resume")
    assert resumed.returncode == 0, resumed.stderr
    _same_results(tmp_path / "whole", case / "results")
    task = json.loads((case / "results" / "summary.json").read_text())["tasks"]["test"]
    assert (task["solver"], task["slice_solver"], task["complete"]) == ("newton", "lu", True)
    with xr.open_dataset(case / "results" / "test.nc") as ds:
        assert ds["psi"].sizes["t"] == 241 and np.isfinite(ds["psi"].values).all()


def test_resume_without_a_checkpoint_is_refused_and_writes_nothing(tmp_path, capsys):
    case = copy_wave(tmp_path)
    code, _, err = run_cli(capsys, "run", case, "-q", *FAST, *WAVE_SETS, "--resume")
    assert code != 0
    assert (
        err.strip().startswith("latticedft: error: --resume: no checkpointed run")
        and len(err.strip().splitlines()) == 1
    )
    assert not (case / "results").exists() and not list(case.glob("results.tmp-*"))


def test_resume_with_a_changed_case_is_refused_naming_the_key(tmp_path, capsys):
    case = copy_wave(tmp_path)
    killed = _latticedft("run", case, "-q", *FAST, *WAVE_SETS, fault="kill:checkpoint")
    assert killed.returncode == -9, killed.stderr
    stage = snapshot(_stage(case))
    code, _, err = run_cli(capsys, "run", case, "-q", *FAST, *WAVE_SETS, "--set", "serve.test.slices=61", "--resume")
    assert code != 0 and len(err.strip().splitlines()) == 1, err
    assert "serve[0].slices: is 61 now but the checkpointed run had 60" in err
    assert snapshot(_stage(case)) == stage and not (case / "results").exists()  # the checkpoint is kept
    text = (case / "case.toml").read_text().replace('name = "test"', 'name = "test"\nrtol = 1e-9')
    (case / "case.toml").write_text(text)
    code, _, err = run_cli(capsys, "run", case, "-q", *FAST, *WAVE_SETS, "--resume")
    assert code != 0 and "serve[0].rtol: is 1e-09 now but the checkpointed run had unset" in err, err


class _Planted:
    """An object whose unpickling would write a file: what a checkpoint from someone else could hold."""

    def __init__(self, marker: Path):
        self.marker = marker

    def __reduce__(self):
        return (Path.write_text, (self.marker, "unpickled"))


def test_a_checkpoint_holding_a_pickled_object_is_refused_unread(tmp_path, capsys):
    import pickle

    case = copy_wave(tmp_path)
    killed = _latticedft("run", case, "-q", *FAST, *WAVE_SETS, fault="kill:checkpoint")
    assert killed.returncode == -9, killed.stderr
    marker = tmp_path / "marker"
    (_stage(case) / ".test.ckpt").write_bytes(pickle.dumps({"nkept": 3, "x": _Planted(marker)}))
    code, _, err = run_cli(capsys, "run", case, "-q", *FAST, *WAVE_SETS, "--resume")
    assert code != 0 and len(err.strip().splitlines()) == 1 and "checkpoint" in err, err
    assert "cannot be read" in err and not marker.exists()


@pytest.mark.parametrize("value", ["0", "-3", "2.5", '"ten"', "true"])
def test_a_checkpoint_that_is_not_a_positive_integer_is_refused(tmp_path, capsys, value):
    case = copy_wave(tmp_path)
    code, _, err = run_cli(capsys, "check", case, "--set", f"serve.test.checkpoint={value}")
    assert code != 0 and "serve[0].checkpoint" in err and "positive integer" in err, err
    assert len(err.strip().splitlines()) == 1


def test_a_checkpointed_run_interrupted_by_sigterm_keeps_its_stage(tmp_path):
    case = copy_wave(tmp_path)
    termed = _latticedft("run", case, "-q", *FAST, *WAVE_SETS, fault="term:checkpoint")
    assert termed.returncode == 143, termed.stderr
    assert "--resume" in termed.stderr and (_stage(case) / ".test.ckpt").is_file()
    plain = _latticedft("run", case, "-q", *FAST, *WAVE_SETS)  # without --resume: starts afresh
    assert plain.returncode == 0, plain.stderr
    assert not list(case.glob("results.tmp-*"))


class _Keeper:
    """An ``on_slice`` with a ``checkpointer``: keeps the kept slices and the states saved; ``load`` gives
    back ``resume_from`` (a state, with the kept slices up to it) or None."""

    def __init__(self, resume_from: dict | None = None):
        self.kept: list[np.ndarray] = []
        self.saved: list[bytes] = []
        self.resume_from = resume_from
        self.checkpointer = self

    def __call__(self, index: int, values: np.ndarray) -> None:
        self.kept.append(np.array(values))

    def save(self, state: dict) -> None:
        from latticedft._run._resume import state_bytes

        self.saved.append(state_bytes({**state, "kept_values": np.stack(self.kept[: state["nkept"]])}))

    def load(self) -> dict | None:
        return self.resume_from


def test_a_2p1d_newton_stream_resumed_from_a_state_equals_the_whole_run():
    """In-process, 2+1D periodic, a nonlinear ``L_d`` served by slice-Newton (not the affine path): the run
    resumed from its second checkpoint gives the kept slices, counters and extrapolation of the whole run."""
    import torch

    import latticedft as ldft
    from latticedft._models import AnalyticLagrangian
    from latticedft._run._resume import state_from_bytes

    def fn(cells: torch.Tensor, h: tuple[float, ...]) -> torch.Tensor:
        u0, u1 = cells[..., 0, 0], cells[..., 1, 0]
        out = 0.5 * ((u1 - u0) / h[0]) ** 2 - (1 - torch.cos(0.5 * (u0 + u1)))
        for k in range(1, len(h)):
            out = out - 0.5 * ((cells[..., k + 1, 0] - u0) / h[k]) ** 2
        return out

    x = np.arange(12) / 12
    y = np.arange(10) / 10
    base = np.sin(2 * np.pi * x)[:, None] * np.cos(2 * np.pi * y)[None, :]
    t = np.array([0.0, 0.02])
    init = xr.DataArray(
        np.stack([base, 1.01 * base]), dims=("t", "x", "y"), coords={"t": t, "x": x, "y": y}, name="psi"
    )
    opts = {"slices": 70, "boundary": "periodic", "every": 6, "checkpoint": 9, "affine": False}
    model = AnalyticLagrangian(fn, name="sine-Gordon-like")
    first = _Keeper()
    whole = ldft.serve(model, init, on_slice=first, **opts)
    assert whole.solver == "newton" and len(first.saved) >= 3
    state = state_from_bytes(first.saved[1])
    again = _Keeper(state)
    resumed = ldft.serve(model, init, on_slice=again, **opts)
    xr.testing.assert_identical(whole.field, resumed.field)
    for key in ("newton_iterations", "max_newton_iterations", "max_residual", "solver", "slice_solver"):
        assert getattr(whole, key) == getattr(resumed, key), key
    later = [state_from_bytes(b) for b in first.saved[2:]], [state_from_bytes(b) for b in again.saved]
    assert len(later[0]) == len(later[1]) >= 1
    for a, b in zip(*later):  # the later checkpoints too, bit for bit
        assert (a["base"], a["nkept"], a["counters"], a["on_affine"]) == (
            b["base"],
            b["nkept"],
            b["counters"],
            b["on_affine"],
        )
        assert torch.equal(a["head"], b["head"]) and torch.equal(a["before"], b["before"])


def test_a_checkpoint_is_read_once_on_resume(tmp_path, monkeypatch):
    """``open_part`` reads the checkpoint; the task's checkpointer goes on from that state, unread again."""
    from latticedft._part_file import PartFile
    from latticedft._run import _resume
    from latticedft._run._meter import TaskMeter

    t, x = np.arange(5) * 0.1, np.arange(4) * 0.25
    template = xr.DataArray(np.zeros((5, 4)), dims=("t", "x"), coords={"t": t, "x": x}, name="psi")
    part = PartFile(tmp_path, "test", "psi", template, 1)
    for i in range(3):
        part(i, np.full(4, float(i)))
    meter = TaskMeter(None, None, part)
    meter.max_error = 0.5
    _resume.TaskCheckpoint(part, meter, "test", None).save({"nkept": 3, "done": 3})
    part.close()
    reads = []
    monkeypatch.setattr(
        _resume, "read_state", lambda path: reads.append(path) or _resume.state_from_bytes(path.read_bytes())
    )
    again, state = _resume.open_part(tmp_path, "test", "psi", template, 1, True)
    went_on = TaskMeter(None, None, again)
    loaded = _resume.TaskCheckpoint(again, went_on, "test", state).load()
    again.close()
    assert len(reads) == 1 and loaded is not None and loaded["done"] == 3 and went_on.max_error == 0.5
    assert np.array_equal(loaded["kept_values"], np.repeat(np.arange(3.0), 4).reshape(3, 4))
    fresh, none = _resume.open_part(tmp_path, "other", "psi", template, 1, True)
    fresh.close()
    assert none is None and len(reads) == 1
