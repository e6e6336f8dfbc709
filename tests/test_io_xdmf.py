"""The `xdmf` export format (latticedft.io.xdmf): read back with meshio, pyvista and (when present) ParaView."""

from __future__ import annotations

import shutil
from pathlib import Path

import meshio
import numpy as np
import pytest
import pyvista as pv
import xarray as xr

from latticedft import InputError
from latticedft.io.exporters import ExportTask, get_exporter
from latticedft.io.xdmf import read_xdmf, write_xdmf


def _lattice(
    shape: tuple[int, ...], dims: tuple[str, ...], comps: list[str] | None = None, name: str = "psi"
) -> xr.DataArray:
    rng = np.random.default_rng(3)
    coords: dict[str, object] = {d: np.arange(n) * 0.25 + 0.1 * i for i, (d, n) in enumerate(zip(dims, shape))}
    if comps:
        coords["component"] = comps
    return xr.DataArray(
        rng.standard_normal(shape + ((len(comps),) if comps else ())),
        coords=coords,
        name=name,
        dims=dims + (("component",) if comps else ()),
    )


def _meshio_series(path: Path) -> tuple[np.ndarray, np.ndarray, list, list[dict[str, np.ndarray]]]:
    with meshio.xdmf.TimeSeriesReader(path) as reader:
        points, cells = reader.read_points_cells()
        steps = [reader.read_data(k) for k in range(reader.num_steps)]
    return np.array([t for t, _, _ in steps]), points, cells, [pd for _, pd, _ in steps]


@pytest.mark.parametrize(
    "shape,dims,cell",
    [
        ((7, 9), ("t", "x"), "line"),
        ((5, 4, 6), ("t", "y", "x"), "quad"),
        ((3, 2, 3, 4), ("t", "z", "y", "x"), "hexahedron"),
        ((11,), ("t",), "vertex"),
    ],
)
def test_meshio_reads_back_values_and_times(tmp_path: Path, shape, dims, cell) -> None:
    psi = _lattice(shape, dims)
    ref = psi * 2 + 1
    err = psi - ref
    files = write_xdmf(tmp_path, "task", psi, {"psi_ref": ref, "psi_err": err})
    assert [p.name for p in files] == ["task.xdmf", "task.h5"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["task.h5", "task.xdmf"]  # no temporary files left
    times, points, cells, steps = _meshio_series(files[0])
    np.testing.assert_array_equal(times, psi.t.values)  # exact: times are written with repr precision
    assert [c.type for c in cells] == [cell]
    n_points = int(np.prod(shape[1:]))
    assert points.shape == (n_points, 3)
    # VTK x along the last lattice dim, then y, then z; x runs fastest
    spatial = list(reversed(dims[1:]))
    for axis, d in enumerate(spatial):
        grid = np.meshgrid(*[psi.coords[k].values for k in dims[1:]], indexing="ij")[dims[1:].index(d)]
        np.testing.assert_array_equal(points[:, axis], grid.ravel())
    for i, step in enumerate(steps):
        assert set(step) == {"psi", "psi_ref", "psi_err"}
        for key, da in (("psi", psi), ("psi_ref", ref), ("psi_err", err)):
            assert step[key].dtype == np.float64
            np.testing.assert_array_equal(step[key].reshape(-1), da.values[i].reshape(-1))


def test_max_frames_nan_and_vector_components(tmp_path: Path) -> None:
    psi = _lattice((25, 4, 3), ("t", "y", "x"), ["u", "v"])
    psi[20:] = np.nan  # a task that stopped early
    files = write_xdmf(tmp_path, "flow", psi, max_frames=5)
    times, arrays = read_xdmf(files[0])
    keep = [0, 6, 12, 18, 24]
    np.testing.assert_array_equal(times, psi.t.values[keep])
    assert set(arrays) == {"psi_u", "psi_v"}
    for label in ("u", "v"):
        want = psi.isel(t=keep).sel(component=label).values.reshape(5, -1)
        np.testing.assert_array_equal(arrays[f"psi_{label}"], want)  # NaN where it stopped (equal_nan)
    assert np.isnan(arrays["psi_u"][-1]).all() and np.isfinite(arrays["psi_u"][:-1]).all()


def test_rewrite_replaces_both_files(tmp_path: Path) -> None:
    psi = _lattice((6, 5), ("t", "x"))
    write_xdmf(tmp_path, "w", psi)
    write_xdmf(tmp_path, "w", psi[:3] * 10)
    times, arrays = read_xdmf(tmp_path / "w.xdmf")
    assert times.size == 3
    np.testing.assert_array_equal(arrays["psi"], psi.values[:3] * 10)


def test_the_exporter_writes_reference_and_error(tmp_path: Path) -> None:
    psi = _lattice((6, 5), ("t", "x"), name="phi")
    task = ExportTask(folder=tmp_path, name="t1", field=psi, reference=psi + 1, error=psi * 0 - 1, max_frames=2)
    files = get_exporter("xdmf").write(task)
    assert files == [tmp_path / "t1.xdmf", tmp_path / "t1.h5"]
    times, arrays = read_xdmf(files[0])
    assert set(arrays) == {"phi", "phi_ref", "phi_err"} and times.tolist() == [psi.t.values[0], psi.t.values[-1]]
    only = get_exporter("xdmf").write(ExportTask(folder=tmp_path, name="t2", field=psi, reference=psi))
    assert set(read_xdmf(only[0])[1]) == {"phi"}  # no error array: no reference arrays either


def test_pyvista_reads_the_series(tmp_path: Path) -> None:
    psi = _lattice((4, 5, 7), ("t", "y", "x"))
    path = write_xdmf(tmp_path, "plate", psi, {"psi_ref": psi * 2})[0]
    reader = pv.get_reader(path)
    np.testing.assert_allclose(reader.time_values, psi.t.values, rtol=1e-15)
    for i, t in enumerate(reader.time_values):
        reader.set_active_time_value(t)
        series = reader.read()["TimeSeries_meshio"]
        assert series.n_points == 35 and series.n_cells == 24
        np.testing.assert_array_equal(np.asarray(series.point_data["psi"]), psi.values[i].ravel())
        np.testing.assert_array_equal(np.asarray(series.point_data["psi_ref"]), 2 * psi.values[i].ravel())


def test_bad_input(tmp_path: Path) -> None:
    psi = _lattice((4, 5), ("t", "x"))
    with pytest.raises(InputError, match="plain file name stem"):
        write_xdmf(tmp_path, "a/b", psi)
    with pytest.raises(InputError, match="max_frames"):
        write_xdmf(tmp_path, "a", psi, max_frames=0)
    with pytest.raises(InputError, match="differ"):
        write_xdmf(tmp_path, "a", psi, {"psi_ref": _lattice((4, 6), ("t", "x"))})
    with pytest.raises(InputError, match="at most 3"):
        write_xdmf(tmp_path, "a", _lattice((2, 2, 2, 2, 2), ("t", "w", "z", "y", "x")))
    with pytest.raises(InputError, match="file not found"):
        read_xdmf(tmp_path / "none.xdmf")
    assert list(tmp_path.iterdir()) == []


@pytest.mark.paraview
@pytest.mark.skipif(shutil.which("pvpython") is None, reason="pvpython not found")
def test_paraview_opens_the_series(tmp_path: Path) -> None:
    from test_paraview import _run_pvpython

    fields = {
        "wave": _lattice((6, 9), ("t", "x")),
        "plate": _lattice((4, 5, 7), ("t", "y", "x")),
        "cube": _lattice((3, 2, 3, 4), ("t", "z", "y", "x")),
        "flow": _lattice((3, 4, 5), ("t", "y", "x"), ["u", "v"]),
        "osc": _lattice((15,), ("t",)),
    }
    paths = {stem: write_xdmf(tmp_path / "out", stem, psi, {"psi_ref": psi * 2})[0] for stem, psi in fields.items()}
    report = _run_pvpython(tmp_path, list(paths.values()))
    for stem, psi in fields.items():
        rep = report[str(paths[stem])]
        assert "error" not in rep, (stem, rep)
        assert rep["times"] == pytest.approx(psi.t.values.tolist()), stem
        n_points = int(np.prod([psi.sizes[d] for d in psi.dims[1:] if d != "component"]))
        for i, step in enumerate(rep["steps"]):
            assert step["points"] == n_points, stem
            if "component" not in psi.dims:
                frame = psi.values[i]
                assert step["ranges"]["psi"] == pytest.approx([frame.min(), frame.max()]), stem
                assert step["ranges"]["psi_ref"] == pytest.approx([2 * frame.min(), 2 * frame.max()]), stem
            else:
                assert {"psi_u", "psi_v", "psi_ref_u", "psi_ref_v"} == set(step["ranges"]), stem
