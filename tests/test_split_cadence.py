"""A task with an output cadence (``every > 1``) served split over two processes (``serve --workers 2``):
the task file of one process, to 1e-12 (its kept slices, errors, invariant on every slice and training
range), and its summary figures."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
from test_split_cli import _latticedft, _same_task, tiny_klein_gordon


@pytest.mark.slow
def test_serve_with_two_workers_and_every_gives_the_one_process_task_file(tmp_path: Path) -> None:
    case = tiny_klein_gordon(tmp_path)
    text = (case / "case.toml").read_text().replace('name = "test"', 'name = "test"\nevery = 7')
    text = text.replace('charges = ["momentum-x", "energy"]', "")  # measured on the whole field: every = 1
    (case / "case.toml").write_text(text)
    one = _latticedft("run", case, "--out", tmp_path / "one")
    assert one.returncode == 0, one.stderr
    shutil.copytree(tmp_path / "one", tmp_path / "two")
    two = _latticedft("serve", case, "--workers", 2, "--out", tmp_path / "two")
    assert two.returncode == 0, two.stderr
    assert "task test: split over 2 processes along 'x', slabs [0, 10) [10, 20)" in two.stderr
    _same_task(tmp_path / "one", tmp_path / "two")
    ref, split = (json.loads((tmp_path / d / "summary.json").read_text())["tasks"]["test"] for d in ("one", "two"))
    assert split["decomposition"]["processes"] == 2 and split["kept_slices"] == ref["kept_slices"] == 7
    for key in ("max_error", "rms_error", "relative_error", "invariant_drift"):
        assert split[key] == pytest.approx(ref[key], rel=1e-6, abs=1e-13), key
    assert split["extrapolation"]["first_slice"] == ref["extrapolation"]["first_slice"]
    assert split["extrapolation"]["max"] == pytest.approx(ref["extrapolation"]["max"], rel=1e-12)
