"""``latticedft new NAME --like TEMPLATE``: a case folder that ``latticedft run`` passes at once."""

from __future__ import annotations

import json
import tomllib
from pathlib import Path

import pytest

from latticedft.cli._templates import TEMPLATES
from latticedft.io.figures import task_figure

from case_helpers import leftovers, run_cli, snapshot


@pytest.mark.parametrize("like", list(TEMPLATES))
def test_new_then_run(tmp_path: Path, capsys, like: str) -> None:
    case = tmp_path / f"my-{like}"
    code, out, err = run_cli(capsys, "new", case, "--like", like)
    assert code == 0, err
    assert f"latticedft run {case}" in out
    assert {p.name for p in case.iterdir()} == {"case.toml", "make_data.py", "README.md", "data"}
    assert any((case / "data").glob("*.nc"))
    text = (case / "case.toml").read_text()
    config = tomllib.loads(text)
    # a comment on every key
    for line in text.splitlines():
        if "=" in line and not line.lstrip().startswith("#"):
            assert "#" in line, line
    assert all("steps" not in task for task in config.get("serve", []))
    code, _, err = run_cli(capsys, "run", case, "-q")
    assert code == 0, err
    assert err == ""  # a template runs clean: no warning (e.g. no extrapolation beyond the training range)
    res = case / "results"
    summary = json.loads((res / "summary.json").read_text())
    assert summary["exit_status"] == 0 and summary["incomplete_tasks"] == [] and not summary.get("warnings")
    for task in config["serve"]:
        name = task["name"]
        assert summary["tasks"][name]["complete"]
        assert summary["tasks"][name]["slices"] == task["slices"]
        assert (res / f"{name}.nc").is_file() and (res / f"{name}.png").is_file() and (res / f"{name}.pvd").is_file()
        # every template draws the drift of a conserved quantity (an invariant or the energy)
        fig = task_figure(res / f"{name}.nc")
        assert [ax for ax in fig.axes if "conserved" in ax.get_title()], like
    assert (res / "model.pt").is_file() and leftovers(case) == []


def test_default_template_is_wave(tmp_path: Path, capsys) -> None:
    code, _, err = run_cli(capsys, "new", tmp_path / "c")
    assert code == 0, err
    assert "--like wave" in (tmp_path / "c" / "case.toml").read_text()


def test_an_empty_folder_is_filled(tmp_path: Path, capsys) -> None:
    (tmp_path / "c").mkdir()
    assert run_cli(capsys, "new", tmp_path / "c", "--like", "oscillator")[0] == 0
    assert (tmp_path / "c" / "case.toml").is_file()


def test_a_non_empty_folder_is_refused(tmp_path: Path, capsys) -> None:
    case = tmp_path / "c"
    case.mkdir()
    (case / "notes.txt").write_text("mine")
    before = snapshot(tmp_path)
    code, out, err = run_cli(capsys, "new", case)
    assert code == 1 and out == ""
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("latticedft: error: ") and "not empty" in lines[0]
    assert snapshot(tmp_path) == before  # nothing written, no staging folder left
    (tmp_path / "file").write_text("x")
    assert run_cli(capsys, "new", tmp_path / "file")[0] == 1


def test_unknown_template_is_a_usage_error(tmp_path: Path, capsys) -> None:
    code, _, err = run_cli(capsys, "new", tmp_path / "c", "--like", "waves")
    assert code == 2 and "invalid choice" in err
    assert not (tmp_path / "c").exists()
