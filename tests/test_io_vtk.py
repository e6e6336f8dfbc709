"""ParaView export and figures (latticedft.io.vtk, latticedft.io.figures), read back with pyvista."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import pyvista as pv
import xarray as xr

from latticedft import InputError
from latticedft.io import read_pvd, write_paraview
from latticedft.io.figures import plot_prediction


def lattice(shape: tuple[int, ...], dims: tuple[str, ...], comps: list[str] | None = None) -> xr.DataArray:
    rng = np.random.default_rng(0)
    coords = {d: np.arange(n) * (0.1 * (k + 1)) + k for k, (d, n) in enumerate(zip(dims, shape))}
    full = shape + ((len(comps),) if comps else ())
    alldims = dims + (("component",) if comps else ())
    if comps:
        coords["component"] = comps
    return xr.DataArray(rng.standard_normal(full), dims=alldims, coords=coords, name="psi")


def read_time_series(pvd: Path) -> tuple[list[float], list[pv.DataSet]]:
    reader = pv.get_reader(str(pvd))
    assert isinstance(reader, pv.PVDReader)
    meshes = []
    for t in reader.time_values:
        reader.set_active_time_value(t)
        meshes.append(reader.read()[0])
    return list(reader.time_values), meshes


@pytest.mark.parametrize(
    "dims,shape", [(("t", "x"), (5, 7)), (("t", "y", "x"), (4, 3, 6)), (("t", "z", "y", "x"), (3, 2, 3, 4))]
)
def test_grid_frames_match_field(tmp_path: Path, dims, shape) -> None:
    psi = lattice(shape, dims)
    ref = psi * 2.0
    files = write_paraview(tmp_path, "task", psi, {"psi_ref": ref, "psi_err": psi - ref})
    assert files[0] == tmp_path / "task.pvd"
    assert all(f.exists() for f in files)
    entries = read_pvd(files[0])
    t = psi.t.values
    assert [e[0] for e in entries] == pytest.approx(t)
    assert [e[1].name for e in entries] == [f"task_{i:04d}.vtr" for i in range(shape[0])]
    times, meshes = read_time_series(files[0])
    assert times == pytest.approx(t)
    spatial = list(reversed(dims[1:]))  # VTK x, y, z
    for i, mesh in enumerate(meshes):
        assert isinstance(mesh, pv.RectilinearGrid)
        np.testing.assert_allclose(mesh.x, psi[spatial[0]].values)
        if len(spatial) > 1:
            np.testing.assert_allclose(mesh.y, psi[spatial[1]].values)
        np.testing.assert_allclose(mesh.point_data["psi"], psi[i].values.ravel())
        np.testing.assert_allclose(mesh.point_data["psi_ref"], ref[i].values.ravel())
        assert mesh.field_data["TimeValue"][0] == pytest.approx(t[i])
        # point order: VTK point k sits where the C-order flatten of psi(t_i, ...) puts value k
        k = mesh.n_points // 2 + 1
        idx = np.unravel_index(k, shape[1:])
        expect = [psi[d].values[j] for d, j in zip(dims[1:], idx)][::-1]
        np.testing.assert_allclose(mesh.points[k][: len(expect)], expect)
    spacetime = tmp_path / "task_spacetime.vtr"
    assert spacetime.exists() == (len(dims) == 2)


def test_spacetime_grid(tmp_path: Path) -> None:
    psi = lattice((5, 7), ("t", "x"))
    files = write_paraview(tmp_path, "w", psi)
    assert files[-1].name == "w_spacetime.vtr"
    g = pv.read(files[-1])
    assert g.dimensions == (7, 5, 1)
    np.testing.assert_allclose(g.x, psi.x.values)
    np.testing.assert_allclose(g.y, psi.t.values)
    np.testing.assert_allclose(g.point_data["psi"], psi.values.ravel())


def test_vector_field_on_grid(tmp_path: Path) -> None:
    psi = lattice((3, 4, 5), ("t", "y", "x"), ["u", "v"])
    files = write_paraview(tmp_path, "v", psi)
    g = pv.read(files[1])
    assert g.point_data["psi"].shape == (20, 2)
    np.testing.assert_allclose(g.point_data["psi"], psi[0].values.reshape(20, 2))


def test_max_frames(tmp_path: Path) -> None:
    psi = lattice((50, 4), ("t", "x"))
    files = write_paraview(tmp_path, "s", psi, max_frames=5)
    entries = read_pvd(files[0])
    assert len(entries) == 5
    assert entries[0][0] == pytest.approx(psi.t.values[0])
    assert entries[-1][0] == pytest.approx(psi.t.values[-1])
    assert [e[1].name for e in entries][-1] == "s_0049.vtr"
    with pytest.raises(InputError, match="max_frames"):
        write_paraview(tmp_path, "s", psi, max_frames=0)


def test_orbit_polylines(tmp_path: Path) -> None:
    th = np.linspace(0, 2 * np.pi, 40)
    psi = xr.DataArray(
        np.c_[np.cos(th), 0.5 * np.sin(th)],
        dims=["t", "component"],
        coords={"t": th, "component": ["x", "y"]},
        name="psi",
    )
    psi[30:] = np.nan  # the trajectory stopped early
    files = write_paraview(tmp_path, "orbit", psi, {"psi_ref": psi.fillna(0.0)})
    names = [f.name for f in files]
    assert names[0] == "orbit.pvd" and names[-1] == "orbit.vtp" and len(names) == 42
    whole = pv.read(tmp_path / "orbit.vtp")
    assert whole.n_points == 30 and whole.n_lines == 1
    np.testing.assert_allclose(whole.points[:, :2], psi[:30].values)
    np.testing.assert_allclose(whole.points[:, 2], 0.0)
    np.testing.assert_allclose(whole.point_data["time"], th[:30])
    np.testing.assert_allclose(whole.point_data["psi_ref"], psi[:30].values)
    times, meshes = read_time_series(files[0])
    assert times == pytest.approx(th)
    assert [m.n_points for m in meshes] == [min(i + 1, 30) for i in range(40)]
    assert meshes[5].field_data["TimeValue"][0] == pytest.approx(th[5])
    np.testing.assert_allclose(meshes[5].points[:, :2], psi[:6].values)


def test_orbit_3d_and_frame_limit(tmp_path: Path) -> None:
    psi = lattice((20,), ("t",), ["x", "y", "z"])
    files = write_paraview(tmp_path, "o3", psi, max_frames=4)
    assert len(read_pvd(files[0])) == 4
    np.testing.assert_allclose(pv.read(files[-1]).points, psi.values)


def test_scalar_time_series(tmp_path: Path) -> None:
    psi = lattice((12,), ("t",))
    files = write_paraview(tmp_path, "osc", psi)
    whole = pv.read(files[-1])
    np.testing.assert_allclose(whole.points, np.c_[psi.t, psi.values, np.zeros(12)])
    np.testing.assert_allclose(whole.point_data["psi"], psi.values)


def test_bad_exports(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="4 components"):
        write_paraview(tmp_path, "b", lattice((5,), ("t",), list("abcd")))
    with pytest.raises(InputError, match="psi_ref"):
        write_paraview(tmp_path, "b", lattice((5, 4), ("t", "x")), {"psi_ref": lattice((5, 3), ("t", "x"))})
    with pytest.raises(InputError, match="stem"):
        write_paraview(tmp_path, "a/b", lattice((5, 4), ("t", "x")))
    with pytest.raises(InputError, match="not uniformly spaced"):
        write_paraview(tmp_path, "b", lattice((5, 4), ("t", "x")).assign_coords(x=[0, 1, 3, 4]))


def test_read_pvd_errors(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="not found"):
        read_pvd(tmp_path / "none.pvd")
    bad = tmp_path / "bad.pvd"
    bad.write_text("<VTKFile><Collection>")
    with pytest.raises(InputError, match="not valid XML"):
        read_pvd(bad)


# ----------------------------------------------------------------------------- figures


def assert_png(path: Path) -> None:
    data = path.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 5000
    assert [p.name for p in path.parent.iterdir()] == [path.name]  # no temporary file left


@pytest.mark.parametrize("case", ["series", "orbit", "spacetime", "snapshots", "noref"])
def test_figures(tmp_path: Path, case: str) -> None:
    if case == "series":
        ref = lattice((60,), ("t",))
        train = [ref * 0.5]
    elif case == "orbit":
        ref = lattice((60,), ("t",), ["x", "y"])
        train = [ref * 1.5, ref * 2.0]
    elif case == "spacetime":
        ref, train = lattice((64, 64), ("t", "x")), None
    else:
        ref, train = lattice((8, 32, 32), ("t", "y", "x")), None
    pred = ref + 0.01
    pred[-3:] = np.nan  # stopped early
    out = plot_prediction(tmp_path / "fig.png", pred, None if case == "noref" else ref, title=case, train=train)
    assert_png(out)


def test_figure_large_lattice_draws_rasters(tmp_path: Path, monkeypatch) -> None:
    """A 256 x 256 field is drawn as images, not one artist per site: the figure's cost does not grow with
    the lattice (checked by its structure, not by a clock)."""
    from matplotlib.figure import Figure
    from matplotlib.image import AxesImage

    drawn: list[Figure] = []
    save = Figure.savefig

    def record(self, *args, **kwargs):
        drawn.append(self)
        return save(self, *args, **kwargs)

    monkeypatch.setattr(Figure, "savefig", record)
    ref = lattice((256, 256), ("t", "x"))
    plot_prediction(tmp_path / "big.png", ref + 0.1, ref, title="256 x 256")
    (fig,) = drawn
    images = [a for ax in fig.axes for a in ax.get_images() if isinstance(a, AxesImage)]
    assert len(images) >= 2 and all(im.get_array().shape == (256, 256) for im in images)
    for ax in fig.axes:  # no per-site lines, patches or collections
        assert len(ax.lines) + len(ax.patches) + len(ax.collections) < 50
    assert_png(tmp_path / "big.png")
