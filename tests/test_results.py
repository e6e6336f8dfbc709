"""Results of a run: task files reload to the served field, ParaView files match them, staging is atomic."""

from __future__ import annotations

import json
import logging
import shutil
from pathlib import Path

import numpy as np
import pytest
import pyvista as pv
import xarray as xr

import latticedft as ldft
from latticedft._results import MARKER, RUN_LOG, Staging, json_safe, staged_results
from latticedft.cli import main
from latticedft.io import read_field, read_pvd

from case_helpers import leftovers, tiny_wave


@pytest.fixture(scope="module")
def run(tmp_path_factory) -> Path:
    case = tiny_wave(tmp_path_factory.mktemp("results"))
    assert main(["run", str(case), "-q", "--set", "export.max_frames=30"]) == 0
    return case


def test_task_file_reloads_to_the_served_field(run: Path) -> None:
    res = run / "results"
    psi = read_field(res / "test.nc")
    ref = read_field(res / "test.nc", "psi_ref")
    err = read_field(res / "test.nc", "psi_err")
    model = ldft.load_model(res / "model.pt")
    served = ldft.serve(model, read_field(run / "data" / "test.nc")).field
    assert psi.dims == served.dims == ("t", "x")
    np.testing.assert_array_equal(psi.values, served.values)
    np.testing.assert_array_equal(psi.t.values, served.t.values)
    np.testing.assert_array_equal(ref.values, read_field(run / "data" / "test.nc").values)
    np.testing.assert_allclose(err.values, psi.values - ref.values, rtol=0, atol=1e-15)
    summary = json.loads((res / "summary.json").read_text())
    assert summary["tasks"]["test"]["max_error"] == pytest.approx(float(np.abs(err.values).max()))
    # no CF axis X on x (ParaView's netCDF CF reader would take it for longitude); t keeps axis T
    assert "axis" not in psi.x.attrs and psi.t.attrs.get("axis") == "T"


def test_pvd_matches_the_task_file(run: Path) -> None:
    res = run / "results"
    psi = read_field(res / "test.nc")
    ref = read_field(res / "test.nc", "psi_ref")
    entries = read_pvd(res / "test.pvd")
    assert len(entries) == psi.sizes["t"] == 30  # every slice: 30 <= max_frames
    times = np.array([t for t, _ in entries])
    np.testing.assert_allclose(times, psi.t.values, rtol=1e-12)
    for i, (t, path) in enumerate(entries):
        mesh = pv.read(path)
        np.testing.assert_allclose(np.asarray(mesh.point_data["psi"]).ravel(), psi.values[i], rtol=0, atol=1e-14)
        np.testing.assert_allclose(np.asarray(mesh.point_data["psi_ref"]).ravel(), ref.values[i], atol=1e-14)
        assert float(np.asarray(mesh.field_data["TimeValue"]).ravel()[0]) == pytest.approx(t)
        np.testing.assert_allclose(np.asarray(mesh.points)[:, 0], psi.x.values)
    st = pv.read(res / "test_spacetime.vtr")
    assert st.n_points == psi.size


def test_staging_publishes_or_leaves_everything(tmp_path: Path) -> None:
    dest = tmp_path / "results"
    dest.mkdir()
    (dest / "old.txt").write_text("old")
    s = Staging(dest)
    (s.tmp / "new.txt").write_text("new")
    s.discard()
    assert [p.name for p in tmp_path.iterdir()] == ["results"] and (dest / "old.txt").is_file()
    s = Staging(dest, copy_existing=True)
    (s.tmp / "new.txt").write_text("new")
    s.publish()
    s.discard()  # no-op after publish
    assert sorted(p.name for p in dest.iterdir()) == [MARKER, "new.txt", "old.txt"]
    assert [p.name for p in tmp_path.iterdir()] == ["results"]


def _handlers() -> list:
    return [h for h in logging.getLogger("latticedft").handlers if isinstance(h, logging.FileHandler)]


@pytest.mark.parametrize("exc", [RuntimeError("boom"), KeyboardInterrupt()])
def test_staged_results_discards_on_failure(tmp_path: Path, exc: BaseException) -> None:
    dest = tmp_path / "results"
    dest.mkdir()
    (dest / "old.txt").write_text("old")
    before = _handlers()
    with pytest.raises(type(exc)), staged_results(dest, copy_existing=True) as folder:
        assert folder.parent == tmp_path and folder.name.startswith("results.tmp-")
        assert (folder / "old.txt").read_text() == "old"  # a copy of dest
        (folder / "old.txt").write_text("changed")
        (folder / "new.txt").write_text("new")
        logging.getLogger("latticedft").debug("half-way")
        raise exc
    assert [p.name for p in tmp_path.iterdir()] == ["results"]  # no staging folder left
    assert sorted(p.name for p in dest.iterdir()) == ["old.txt"] and (dest / "old.txt").read_text() == "old"
    assert _handlers() == before  # run.log detached


def test_staged_results_publishes_on_success(tmp_path: Path) -> None:
    dest = tmp_path / "sub" / "results"
    before = _handlers()
    with staged_results(dest) as folder:
        assert not dest.exists() and folder.is_dir()
        (folder / "a.txt").write_text("a")
        logging.getLogger("latticedft").debug("written a.txt")
        assert len(_handlers()) == len(before) + 1
    assert _handlers() == before
    assert sorted(p.name for p in dest.iterdir()) == [MARKER, "a.txt", RUN_LOG]
    assert "DEBUG written a.txt" in (dest / RUN_LOG).read_text()
    logging.getLogger("latticedft").debug("after the block")
    assert "after the block" not in (dest / RUN_LOG).read_text()
    (dest / "stale.txt").write_text("stale")
    with staged_results(dest, run_log=False) as folder:  # a fresh folder replaces dest
        (folder / "b.txt").write_text("b")
    assert sorted(p.name for p in dest.iterdir()) == [MARKER, "b.txt"] and leftovers(tmp_path / "sub") == []
    with staged_results(dest, copy_existing=True) as folder:  # a copy of dest, and a run.log
        (folder / "c.txt").write_text("c")
    assert sorted(p.name for p in dest.iterdir()) == [MARKER, "b.txt", "c.txt", RUN_LOG]


def test_json_safe() -> None:
    out = json_safe({"a": np.float64(1.5), "b": float("inf"), "c": [np.int64(2), Path("x")], "d": np.nan})
    assert out == {"a": 1.5, "b": None, "c": [2, "x"], "d": None}


@pytest.mark.paraview
@pytest.mark.skipif(shutil.which("pvpython") is None, reason="pvpython not found")
def test_paraview_opens_every_result(run: Path, tmp_path: Path) -> None:
    from test_paraview import _run_pvpython

    res = run / "results"
    files = sorted(p for p in res.iterdir() if p.suffix in (".pvd", ".vtr", ".vtp"))
    report = _run_pvpython(tmp_path, files)
    assert set(report) == {str(f) for f in files}
    psi = read_field(res / "test.nc")
    pvd = report[str(res / "test.pvd")]
    assert pvd["times"] == pytest.approx(psi.t.values.tolist())
    for i, step in enumerate(pvd["steps"]):
        assert {"psi", "psi_ref", "psi_err"} <= set(step["ranges"])
        assert step["ranges"]["psi"] == pytest.approx([psi.values[i].min(), psi.values[i].max()], abs=1e-14)


def test_task_file_labels_say_what_each_variable_is(tmp_path: Path) -> None:
    """psi_ref is described as the reference (its own source, not "predicted by ..."), psi_err carries nothing of
    either operand, and an invariant that inherited the field's attributes is not called by the field's name."""
    from latticedft import systems
    from latticedft._results import write_task

    ref = systems.wave_string([(1, 1.0)], nx=9, nt=7).assign_attrs(
        long_name="string displacement", units="m", source="an experiment"
    )
    pred = (ref * 1.01).assign_attrs(ref.attrs, source="latticedft.serve: predicted ...")
    invariant = (pred**2).sum("x", keep_attrs=True)  # a user's function handing on psi's attributes
    path = write_task(tmp_path, "task", "psi", pred, ref, invariant, attrs={}, history="test")
    with xr.open_dataset(path) as ds:
        assert ds["psi_ref"].attrs["source"] == "an experiment" and ds["psi_ref"].attrs["comment"] == "reference"
        assert ds["psi_ref"].attrs["long_name"] == "string displacement" and ds["psi_ref"].attrs["units"] == "m"
        assert ds["psi_err"].attrs == {"long_name": "psi - psi_ref", "units": "m"}
        assert ds["invariant"].attrs == {"long_name": "invariant"}
        assert ds["psi"].attrs["source"].startswith("latticedft.serve")
    assert "comment" not in pred.attrs  # the caller's field is not changed
    named = (pred**2).sum("x", keep_attrs=False).assign_attrs(long_name="discrete energy", units="J")
    path = write_task(tmp_path, "named", "psi", pred, ref, named, attrs={}, history="test")
    with xr.open_dataset(path) as ds:
        assert ds["invariant"].attrs == {"long_name": "discrete energy", "units": "J"}
