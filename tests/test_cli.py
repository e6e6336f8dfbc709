"""The command line, in-process (``main(argv)``) and once as a subprocess."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
import xarray as xr

import latticedft
from latticedft import systems
from latticedft.io import read_field, write_field

from case_helpers import (
    FAST,
    copy_wave,
    leftovers,
    nan_field,
    oscillator_case,
    run_cli,
    snapshot,
    tiny_wave,
    write_toml,
)


@pytest.fixture(scope="module")
def wave_run(tmp_path_factory) -> Path:
    """One in-process run of (a quick variant of) cases/wave, shared read-only by several tests."""
    case = copy_wave(tmp_path_factory.mktemp("cli"))
    assert latticedft.cli.main(["run", str(case), "-q", *FAST]) == 0
    return case


def _one_line_error(err: str, *needles: str) -> str:
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1, err
    assert "Traceback" not in err
    assert lines[0].startswith("latticedft: error: ")
    for n in needles:
        assert n in lines[0], (n, lines[0])
    return lines[0]


# -- the happy path ------------------------------------------------------------------------------------------
def test_run_writes_every_result(wave_run: Path) -> None:
    res = wave_run / "results"
    names = {p.name for p in res.iterdir()}
    assert {
        "model.pt",
        "model.json",
        "test.nc",
        "test.pvd",
        "test_spacetime.vtr",
        "test.png",
        "summary.json",
        "run.log",
    } <= names
    assert len([n for n in names if n.startswith("test_0")]) == 6  # export.max_frames=6
    assert leftovers(wave_run) == []
    summary = json.loads((res / "summary.json").read_text())
    assert summary["exit_status"] == 0 and summary["stage"] == "run"
    assert set(summary["versions"]) >= {"latticedft", "torch", "numpy", "python"}
    assert summary["overrides"] == ["serve.test.slices=60", "export.max_frames=6", "run.threads=1"]
    assert "--set serve.test.slices=60" in summary["command"]
    train = summary["train"]
    for key in ("loss", "rel_res", "iterations", "wall_time", "gauge_residual", "hessian_min_sv", "hessian_cond"):
        assert isinstance(train[key], (int, float)), key
    assert train["rel_res"] < 1e-2 and train["gauge_residual"] < 1e-4
    task = summary["tasks"]["test"]
    assert task["complete"] and task["slices"] == 60
    for key in ("max_error", "rms_error", "newton_iterations", "wall_time", "sites_per_second"):
        assert task[key] is not None, key
    # the learned theory beats the leapfrog of the true equation at the same dt, dx
    assert task["max_error"] < task["baseline"]["max_error_same_slices"]
    model = json.loads((res / "model.json").read_text())
    assert model["kind"] == "polynomial" and model["options"]["orders"] == [2, 2]
    import hashlib

    assert model["sha256"] == hashlib.sha256((res / "model.pt").read_bytes()).hexdigest()
    assert model["overrides"] == summary["overrides"] and "loss" in model["training"]
    with xr.open_dataset(res / "test.nc") as ds:
        assert "--set serve.test.slices=60" in ds.attrs["history"]
        assert "serve.test.slices=60" in ds.attrs["latticedft_overrides"]
        assert ds.attrs["Conventions"].startswith("CF")
    log = (res / "run.log").read_text()
    assert "DEBUG" in log and "task test: complete" in log


def test_info_prints_case_model_and_summary(wave_run: Path, capsys) -> None:
    code, out, err = run_cli(capsys, "info", wave_run)
    assert code == 0
    assert "L_d =" in out and "training: loss" in out and "task test: complete" in out
    assert "verdict: good: the data obey the learned equations" in out


def test_check_prints_a_summary_and_writes_nothing(tmp_path: Path, capsys) -> None:
    case = tiny_wave(tmp_path)
    before = snapshot(case)
    code, out, _ = run_cli(capsys, "check", case)
    assert code == 0 and "serve test" in out and "does not exist yet" in out
    assert snapshot(case) == before


def test_train_then_serve_then_export(tmp_path: Path, capsys) -> None:
    case = tiny_wave(tmp_path)
    assert run_cli(capsys, "train", case, "-q")[0] == 0
    assert {p.name for p in (case / "results").iterdir()} == {
        "model.pt",
        "model.json",
        "summary.json",
        "run.log",
        ".latticedft-results",
    }
    code, _, err = run_cli(capsys, "serve", case)
    assert code == 0 and "task test: complete" in err
    res = case / "results"
    assert (res / "test.nc").is_file() and (res / "test.png").is_file()
    summary = json.loads((res / "summary.json").read_text())
    assert summary["stage"] == "serve" and summary["train"]["loss"] is not None
    for p in res.glob("test*.vt*"):
        p.unlink()
    (res / "test.pvd").unlink()
    code, _, _ = run_cli(capsys, "export", case, "--set", "export.max_frames=3", "-q")
    assert code == 0
    assert len(list(res.glob("test_0*.vtr"))) == 3 and (res / "test.pvd").is_file()
    assert "export" in (res / "run.log").read_text()


def test_out_and_overwrite(tmp_path: Path, capsys) -> None:
    case = tiny_wave(tmp_path)
    out = tmp_path / "elsewhere" / "res"
    fast = ("--set", "export.figures=false", "--set", "export.paraview=false")
    assert run_cli(capsys, "run", case, "--out", out, "-q", *fast)[0] == 0
    assert (out / "model.pt").is_file() and not (case / "results").exists()
    (out / "stale.txt").write_text("old")
    assert run_cli(capsys, "run", case, "--out", out, "--overwrite", "-q", *fast)[0] == 0
    assert not (out / "stale.txt").exists() and (out / "summary.json").is_file()


def test_version_and_verbosity(tmp_path: Path, capsys) -> None:
    code = latticedft.cli.main(["--version"])
    out, _ = capsys.readouterr()
    assert code == 0 and out.strip() == f"latticedft {latticedft.__version__}"
    case = tiny_wave(tmp_path)
    _, _, err_v = run_cli(capsys, "train", case, "-v")
    assert "torch and BLAS/OpenMP threads: 1" in err_v  # DEBUG reaches stderr with -v
    _, _, err_q = run_cli(capsys, "train", case, "-q", "--overwrite")
    assert err_q == ""


def test_threads_from_case(tmp_path: Path, capsys) -> None:
    case = tiny_wave(tmp_path)
    old = torch.get_num_threads()
    try:
        assert run_cli(capsys, "check", case)[0] == 0
        assert run_cli(capsys, "train", case, "-q", "--set", "run.threads=2")[0] == 0
        assert torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(old)


def test_subprocess_python_m(tmp_path: Path) -> None:
    case = tiny_wave(tmp_path)
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    proc = subprocess.run(
        [sys.executable, "-m", "latticedft", "run", str(case), "--set", "export.figures=false"],
        capture_output=True,
        text=True,
        env=env,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr
    assert "task test: complete" in proc.stderr and proc.stdout == ""
    assert (case / "results" / "test.nc").is_file()


# -- a serving task that stops part-way ----------------------------------------------------------------------
def test_incomplete_task_exit_3(tmp_path: Path, capsys) -> None:
    case = oscillator_case(tmp_path)
    code, _, err = run_cli(capsys, "run", case)
    assert code == 3
    warning = [ln for ln in err.splitlines() if "task outside stopped" in ln]
    assert warning and "slice" in warning[0] and "residual" in warning[0]
    summary = json.loads((case / "results" / "summary.json").read_text())
    out, ins = summary["tasks"]["outside"], summary["tasks"]["inside"]
    assert not out["complete"] and 2 < out["slices"] < 100 and "did not converge" in out["reason"]
    assert ins["complete"] and ins["max_error"] < 1e-3
    assert summary["exit_status"] == 3 and summary["incomplete_tasks"] == ["outside"]
    part = read_field(case / "results" / "outside.nc")  # the solved part, NaN-free
    assert part.sizes["t"] == out["slices"]
    assert (case / "results" / "outside.pvd").is_file() and (case / "results" / "inside.png").is_file()


# -- bad input: exit 1, one line, nothing written, earlier results untouched -----------------------------------
@pytest.fixture(scope="module")
def _earlier_template(tmp_path_factory) -> Path:
    case = tiny_wave(tmp_path_factory.mktemp("earlier"))
    assert latticedft.cli.main(["run", str(case), "-q"]) == 0
    return case


@pytest.fixture()
def earlier(tmp_path: Path, _earlier_template: Path) -> Path:
    """A tiny case with earlier results (a copy per test)."""
    case = tmp_path / "tiny"
    shutil.copytree(_earlier_template, case)
    return case


def _refused(capsys, case: Path, *argv: str, needles: tuple[str, ...], stage: str = "run") -> None:
    before = snapshot(case / "results")
    extra = ("--overwrite",) if stage in ("run", "train") else ()
    code, out, err = run_cli(capsys, stage, case, "-q", *extra, *argv)
    assert code == 1
    _one_line_error(err, *needles)
    assert snapshot(case / "results") == before
    assert leftovers(case) == []


def test_unknown_key_suggests(earlier: Path, capsys) -> None:
    text = (earlier / "case.toml").read_text().replace("max_frames = 4", "max_frame = 4")
    (earlier / "case.toml").write_text(text)
    _refused(capsys, earlier, needles=("export.max_frame", "did you mean 'max_frames'"))


def test_unknown_override_key(earlier: Path, capsys) -> None:
    _refused(capsys, earlier, "--set", "train.max_tme=3", needles=("--set", "train.max_tme", "'max_time'"))


def test_wrong_type(earlier: Path, capsys) -> None:
    _refused(
        capsys,
        earlier,
        "--set",
        "serve.test.slices='ten'",
        needles=("serve[0].slices", "expected a positive integer, got 'ten'"),
    )
    text = (earlier / "case.toml").read_text().replace('name = "test"', 'name = "test"\nslices = "ten"')
    (earlier / "case.toml").write_text(text)
    _refused(capsys, earlier, needles=("case.toml: serve[0].slices", "got 'ten'"))


def test_missing_data_file(earlier: Path, capsys) -> None:
    (earlier / "data" / "test.nc").unlink()
    _refused(capsys, earlier, needles=("serve[0].from", "file not found: data/test.nc"))


def test_nan_in_data(earlier: Path, capsys) -> None:
    nan_field(earlier / "data" / "train.nc")
    _refused(capsys, earlier, needles=("train.nc", "NaN"))


def test_non_uniform_coordinate(earlier: Path, capsys) -> None:
    psi = systems.wave_string([(1, 1.0)], nx=13, nt=20)
    x = psi.x.values.copy()
    x[6] += 0.3 * (x[1] - x[0])
    write_field(earlier / "data" / "train.nc", {"psi": psi.assign_coords(x=x)})
    _refused(capsys, earlier, needles=("train.nc", "'x' is not uniformly spaced"))


def test_mismatched_component_labels(tmp_path: Path, capsys) -> None:
    case = tmp_path / "orbit"
    (case / "data").mkdir(parents=True)
    t = np.arange(30) * 0.1
    for name, labels in (("a", ["x", "y"]), ("b", ["x", "z"])):
        values = np.stack([np.cos(t), np.sin(t)], axis=-1)
        write_field(
            case / "data" / f"{name}.nc", {"psi": systems.make_field(values, ("t",), spacing=0.1, components=labels)}
        )
    write_toml(
        case,
        """
        [train]
        data = ["data/a.nc", "data/b.nc"]
        """,
    )
    (case / "results").mkdir()
    (case / "results" / "keep.txt").write_text("earlier")
    _refused(capsys, case, needles=("b.nc", "component labels do not match"))


def test_results_present_without_overwrite(earlier: Path, capsys) -> None:
    before = snapshot(earlier / "results")
    code, _, err = run_cli(capsys, "run", earlier)
    assert code == 1
    _one_line_error(err, "results/ exists; use --overwrite")
    assert snapshot(earlier / "results") == before


@pytest.mark.parametrize("stage", ["serve", "info"])
def test_corrupt_model_file(earlier: Path, capsys, stage: str) -> None:
    (earlier / "results" / "model.pt").write_bytes(b"PK\x03\x04 this is not a zip archive at all")
    _refused(capsys, earlier, needles=("model.pt", "not a readable model file"), stage=stage)


class _Payload:
    """Any pickled object: weights_only=True refuses it."""

    def __reduce__(self):
        return (print, ("this must never run",))


@pytest.mark.parametrize("stage", ["serve", "info"])
def test_pickled_model_file_refused(earlier: Path, capsys, stage: str) -> None:
    torch.save({"format": "latticedft-model", "payload": _Payload()}, earlier / "results" / "model.pt")
    _refused(capsys, earlier, needles=("model.pt", "refused to load", "weights_only=True"), stage=stage)


def test_serve_without_model(tmp_path: Path, capsys) -> None:
    case = tiny_wave(tmp_path)
    code, _, err = run_cli(capsys, "serve", case, "-q")
    assert code == 1
    _one_line_error(err, "model.pt: not found")
    assert not (case / "results").exists()


def test_bad_input_found_late_leaves_nothing(earlier: Path, capsys) -> None:
    """A serving task on another lattice spacing is refused at check time, before training."""
    write_field(earlier / "data" / "test.nc", {"psi": systems.wave_string([(1, 0.5)], nx=25, nt=30)})
    _refused(capsys, earlier, needles=("test.nc", "spacing"))


def test_unknown_model_kind_suggests(tmp_path: Path, capsys) -> None:
    case = tiny_wave(tmp_path)
    text = (case / "case.toml").read_text().replace('kind = "polynomial"', 'kind = "polinomial"')
    (case / "case.toml").write_text(text)
    code, _, err = run_cli(capsys, "check", case)
    assert code == 1
    _one_line_error(err, "model.kind", "did you mean 'polynomial'")
    shutil.rmtree(case)


def test_strict_turns_warnings_into_status_4(tmp_path: Path, capsys) -> None:
    """cases/wave warns (its test wave leaves the training range): 0 as usual, 4 with --strict or
    [run] strict = true, the results published either way and marked."""
    import shutil

    case = tmp_path / "wave"
    shutil.copytree(
        Path(__file__).resolve().parents[1] / "cases" / "wave", case, ignore=shutil.ignore_patterns("results*")
    )
    text = (case / "case.toml").read_text().replace("[export]\n", "[export]\nformats = []\n", 1)
    (case / "case.toml").write_text(text)
    code, _, err = run_cli(capsys, "run", case, "-q")
    assert code == 0 and "extrapolation" in err
    assert json.loads((case / "results" / "summary.json").read_text())["strict"] is False
    code, _, err = run_cli(capsys, "run", case, "-q", "--overwrite", "--strict")
    summary = json.loads((case / "results" / "summary.json").read_text())
    assert code == 4 and summary["exit_status"] == 4 and summary["strict"] is True and summary["warnings"]
    assert "strict: 1 warning(s)" in err and "exit status 4" in err
    (case / "case.toml").write_text(text + "\n[run]\nstrict = true\n")
    code, _, _ = run_cli(capsys, "serve", case, "-q")
    assert code == 4 and json.loads((case / "results" / "summary.json").read_text())["exit_status"] == 4
