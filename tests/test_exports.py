"""Export formats of a run: the registry, `[export] formats`, and clean-up by the files each task recorded."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from latticedft import systems
from latticedft.io import write_field
from latticedft.io.exporters import DEFAULT_FORMATS, EXPORTERS, Exporter, get_exporter, remove_exports

from case_helpers import leftovers, run_cli, tiny_wave, write_toml

DOCS = Path(__file__).resolve().parents[1] / "docs"
KEEP = {"model.pt", "model.json", "summary.json", "run.log", ".latticedft-results"}


def _two_tasks(tmp: Path) -> Path:
    """The tiny wave with a second task named like a file of the first (`test` writes `test_spacetime.vtr`)."""
    case = tiny_wave(tmp)
    text = (case / "case.toml").read_text()
    (case / "case.toml").write_text(
        text.replace("[run]", '[[serve]]\nname = "test_spacetime"\nfrom = "data/test.nc"\nslices = 12\n[run]')
    )
    return case


def _check_listed(res: Path, tasks: tuple[str, ...]) -> dict[str, list[str]]:
    """Every file the summary lists exists, and every other file is a task file or the model/summary/log."""
    summary = json.loads((res / "summary.json").read_text())
    exports = {name: summary["tasks"][name]["exports"] for name in tasks}
    listed = [f for files in exports.values() for f in files]
    assert len(listed) == len(set(listed)), exports  # no file belongs to two tasks
    missing = [f for f in listed if not (res / f).is_file()]
    assert missing == [], missing
    on_disk = {p.name for p in res.iterdir()}
    assert on_disk == set(listed) | KEEP | {f"{t}.nc" for t in tasks}, on_disk ^ (set(listed) | KEEP)
    return exports


def test_registry_loads_every_format() -> None:
    assert set(DEFAULT_FORMATS) <= set(EXPORTERS)
    for name in EXPORTERS:
        exporter = get_exporter(name)
        assert isinstance(exporter, Exporter) and exporter.name == name and exporter.summary
        for page in ("outputs.md", "case-toml.md"):
            assert f"`{name}`" in (DOCS / page).read_text() or f'`"{name}"`' in (DOCS / page).read_text(), (name, page)


def test_a_task_never_deletes_another_tasks_files(tmp_path: Path, capsys) -> None:
    """Tasks `test` and `test_spacetime`: run, then export; every file listed in summary.json exists."""
    case = _two_tasks(tmp_path)
    res = case / "results"
    assert run_cli(capsys, "run", case, "-q")[0] == 0
    after_run = _check_listed(res, ("test", "test_spacetime"))
    assert "test_spacetime.vtr" in after_run["test"]  # the first task's space-time image ...
    assert "test_spacetime.pvd" in after_run["test_spacetime"]  # ... beside the second task's files
    assert run_cli(capsys, "export", case, "-q")[0] == 0
    assert _check_listed(res, ("test", "test_spacetime")) == after_run
    assert run_cli(capsys, "serve", case, "-q")[0] == 0
    assert _check_listed(res, ("test", "test_spacetime")) == after_run
    assert leftovers(case) == []


def test_export_in_other_formats_removes_exactly_the_old_files(tmp_path: Path, capsys) -> None:
    case = _two_tasks(tmp_path)
    res = case / "results"
    assert run_cli(capsys, "run", case, "-q", "--set", "export.figures=false")[0] == 0
    (res / "notes.txt").write_text("mine")  # not an export: left alone
    code, _, err = run_cli(capsys, "export", case, "--set", 'export.formats=["xdmf", "figures"]')
    assert code == 0 and "exported test: test.xdmf, test.h5, test.png" in err
    (res / "notes.txt").unlink()
    exports = _check_listed(res, ("test", "test_spacetime"))
    assert exports == {
        "test": ["test.xdmf", "test.h5", "test.png"],
        "test_spacetime": ["test_spacetime.xdmf", "test_spacetime.h5", "test_spacetime.png"],
    }
    summary = json.loads((res / "summary.json").read_text())
    assert summary["exports"][-1]["overrides"] == ['export.formats=["xdmf", "figures"]']
    before = {p.name for p in res.iterdir()}
    code, _, err = run_cli(capsys, "export", case, "-q", "--set", "export.formats=[]")
    assert code == 1 and "nothing to export" in err  # every format off: refused, nothing changed
    assert {p.name for p in res.iterdir()} == before


def test_export_without_a_record_deletes_nothing(tmp_path: Path, capsys) -> None:
    """Results whose summary lists no exports (e.g. written by hand): files are overwritten, none deleted."""
    case = tiny_wave(tmp_path)
    res = case / "results"
    assert run_cli(capsys, "run", case, "-q", "--set", "export.figures=false")[0] == 0
    summary = json.loads((res / "summary.json").read_text())
    del summary["tasks"]["test"]["exports"]
    (res / "summary.json").write_text(json.dumps(summary))
    (res / "test_0099.vtr").write_text("a stale frame, unknown to the summary")
    assert run_cli(capsys, "export", case, "-q")[0] == 0
    assert (res / "test_0099.vtr").is_file() and (res / "test.png").is_file()
    assert json.loads((res / "summary.json").read_text())["tasks"]["test"]["exports"][-1] == "test.png"


def test_two_tasks_writing_one_file_is_refused(tmp_path: Path, capsys) -> None:
    """1D tasks `a` and `a_0000`: frame 0 of `a` and the whole curve of `a_0000` are both `a_0000.vtp`."""
    case = tmp_path / "osc"
    (case / "data").mkdir(parents=True)
    write_field(case / "data" / "train.nc", {"psi": systems.oscillator_sin(1.2, n=41)})
    write_field(case / "data" / "start.nc", {"psi": systems.oscillator_sin(0.6, n=41)})
    write_toml(
        case,
        """
        [model]
        orders = [2, 4]
        [train]
        data = ["data/train.nc"]
        [[serve]]
        name = "a"
        from = "data/start.nc"
        slices = 10
        [[serve]]
        name = "a_0000"
        from = "data/start.nc"
        slices = 10
        [run]
        threads = 1
        [export]
        formats = ["paraview"]
        """,
    )
    code, _, err = run_cli(capsys, "run", case, "-q")
    assert code == 1, err
    assert "export file a_0000.vtp of task 'a_0000' is also a file of task 'a'" in err
    assert not (case / "results").exists() and leftovers(case) == []


def test_remove_exports_deletes_only_plain_export_files(tmp_path: Path) -> None:
    for name in ("a.png", "a.nc", "model.pt", "summary.json", "run.log"):
        (tmp_path / name).write_text("x")
    (tmp_path / "sub").mkdir()
    (tmp_path / "sub" / "b.png").write_text("x")
    removed = remove_exports(
        tmp_path,
        ["a.png", "a.nc", "model.pt", "summary.json", "run.log", "sub/b.png", "../x.png", "sub", "", "gone.vtr"],
    )
    assert removed == ["a.png"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.nc", "model.pt", "run.log", "sub", "summary.json"]


def test_unknown_format_from_the_command_line(tmp_path: Path, capsys) -> None:
    case = tiny_wave(tmp_path)
    code, _, err = run_cli(capsys, "check", case, "--set", 'export.formats=["paraveiw"]')
    assert code == 1
    assert err.strip() == (
        "latticedft: error: --set: export.formats: unknown format 'paraveiw'; did you mean "
        "'paraview'? (formats: paraview, figures, xdmf)"
    )


@pytest.mark.parametrize("fmt", sorted(EXPORTERS))
def test_each_format_alone(tmp_path: Path, capsys, fmt: str) -> None:
    case = tiny_wave(tmp_path)
    assert run_cli(capsys, "run", case, "-q", "--set", f'export.formats=["{fmt}"]')[0] == 0
    files = _check_listed(case / "results", ("test",))["test"]
    suffixes = {"paraview": {".pvd", ".vtr", ".py"}, "figures": {".png"}, "xdmf": {".xdmf", ".h5"}}[fmt]
    assert {Path(f).suffix for f in files} == suffixes
