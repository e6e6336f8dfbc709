"""Field files: round trip, validation messages, atomic writes (latticedft.io.fields)."""

from __future__ import annotations

import os
from pathlib import Path

import netCDF4
import numpy as np
import pytest
import xarray as xr

from latticedft import InputError
from latticedft.io import (
    field_periodic,
    field_spacing,
    lattice_dims,
    read_field,
    validate_field,
    write_field,
)
from latticedft.testing import assert_fields_close


def wave(nt: int = 6, nx: int = 8) -> xr.DataArray:
    t = np.arange(nt) * 0.1
    x = np.arange(nx) * 0.25
    da = xr.DataArray(
        np.sin(np.add.outer(t, x)),
        dims=["t", "x"],
        coords={"t": t, "x": x},
        name="psi",
        attrs={"long_name": "field", "units": "1"},
    )
    da.x.attrs["periodic"] = "true"
    return da


def orbit(nt: int = 10) -> xr.DataArray:
    t = np.linspace(0.0, 1.0, nt)
    return xr.DataArray(
        np.c_[np.cos(t), np.sin(t)], dims=["t", "component"], coords={"t": t, "component": ["x", "y"]}, name="psi"
    )


def message(exc: pytest.ExceptionInfo[InputError]) -> str:
    msg = str(exc.value)
    assert "\n" not in msg, msg
    return msg


def raw_write(path: Path, ds: xr.Dataset) -> Path:
    """Write a file without write_field's help (for building bad inputs)."""
    ds.to_netcdf(path, engine="netcdf4")
    return path


# ----------------------------------------------------------------------------- round trip


@pytest.mark.parametrize("make", [wave, orbit])
def test_round_trip(tmp_path: Path, make) -> None:
    da = make()
    p = write_field(tmp_path / "f.nc", {"psi": da, "psi_ref": da * 2}, history="unit test")
    back = read_field(p)
    xr.testing.assert_identical(back.reset_coords(drop=True).drop_attrs(), da.reset_coords(drop=True).drop_attrs())
    assert back.dtype == np.float64
    assert_fields_close(read_field(p, "psi_ref"), 2 * da, atol=0.0)
    assert field_spacing(back) == pytest.approx(field_spacing(da))


def test_read_returns_float64_from_float32_and_int(tmp_path: Path) -> None:
    t = np.arange(5, dtype=np.float32) * np.float32(0.1)
    ds = xr.Dataset({"psi": ("t", np.arange(5, dtype=np.int32))}, coords={"t": t})
    back = read_field(raw_write(tmp_path / "i.nc", ds))
    assert back.dtype == np.float64
    assert field_spacing(back) == pytest.approx((0.1,))


def test_cf_attributes_and_encoding(tmp_path: Path) -> None:
    da = wave()
    da.attrs.update(flag=True, nothing=None, shape=[2, 3])
    p = write_field(
        tmp_path / "f.nc",
        {"psi": da},
        attrs={"config": {"model": {"kind": "polynomial"}}, "history": "old line", "dry_run": False},
    )
    with netCDF4.Dataset(p) as nc:
        g = {k: nc.getncattr(k) for k in nc.ncattrs()}
        assert g["Conventions"] == "CF-1.8"
        assert g["source"].startswith("latticedft")
        assert g["config"] == '{"model": {"kind": "polynomial"}}'
        assert g["dry_run"] == "false"
        assert g["history"] == "old line"  # no history text given: nothing appended
        assert nc["psi"].filters()["zlib"]
        assert nc["psi"].getncattr("flag") == "true"
        assert nc["psi"].getncattr("nothing") == "none"
        assert nc["psi"].getncattr("shape") == "[2, 3]"
        for c in ("t", "x"):
            assert "_FillValue" not in nc[c].ncattrs()
        assert nc["t"].getncattr("axis") == "T"
        assert nc["x"].getncattr("axis") == "X"
        assert nc["x"].getncattr("periodic") == "true"
    assert field_periodic(read_field(p)) == (None, True)


def test_label_coordinates_are_character_arrays_without_an_axis(tmp_path: Path) -> None:
    """Coordinates of strings (``component``, ``feature``) are CF character arrays, not netCDF-4 strings that
    ParaView's readers fail to read as numbers, and carry no CF ``axis``; ``spatial_axes=False`` leaves the
    spatial coordinates without one (ParaView's CF reader reads X and Y as longitude and latitude)."""
    o = orbit()
    extra = xr.DataArray(
        np.zeros((o.sizes["t"], 2)), dims=("t", "feature"), coords={"t": o.t, "feature": ["mean", "d_t"]}
    )
    p = write_field(tmp_path / "o.nc", {"psi": o, "extrapolation": extra})
    with netCDF4.Dataset(p) as nc:
        for name in ("component", "feature"):
            assert nc[name].dtype == np.dtype("S1") and "axis" not in nc[name].ncattrs()
        assert nc["t"].getncattr("axis") == "T"
    back = read_field(p, components=["x", "y"])
    np.testing.assert_array_equal(back.values, o.values)
    with xr.open_dataset(p) as ds:
        assert ds["feature"].values.tolist() == ["mean", "d_t"]
        assert float(ds["extrapolation"].sel(feature="d_t")[0]) == 0.0
    w = wave()
    p = write_field(tmp_path / "w.nc", {"psi": w.assign_coords(x=w.x.assign_attrs(axis="X"))}, spatial_axes=False)
    with netCDF4.Dataset(p) as nc:
        assert "axis" not in nc["x"].ncattrs() and nc["t"].getncattr("axis") == "T"


def test_history_is_appended(tmp_path: Path) -> None:
    ds = xr.Dataset({"psi": wave()}, attrs={"history": "2020-01-01: made"})
    p = write_field(tmp_path / "f.nc", ds, history="served")
    with netCDF4.Dataset(p) as nc:
        lines = nc.getncattr("history").split("\n")
    assert lines[0] == "2020-01-01: made"
    assert lines[1].endswith(": served") and lines[1][:4].isdigit()
    assert ds.attrs == {"history": "2020-01-01: made"}  # input untouched


def test_uncompressed_and_plain_dataset(tmp_path: Path) -> None:
    p = write_field(tmp_path / "f.nc", xr.Dataset({"q": orbit()}), compress=False)
    with netCDF4.Dataset(p) as nc:
        assert not nc["q"].filters()["zlib"]
    assert read_field(p, "q", components=["x", "y"]).shape == (10, 2)


def test_helpers() -> None:
    assert lattice_dims(orbit()) == ("t",)
    assert lattice_dims(wave()) == ("t", "x")
    assert field_spacing(wave()) == pytest.approx((0.1, 0.25))
    assert validate_field(wave()).dtype == np.float64


# ----------------------------------------------------------------------------- atomic writes


def test_atomic_write_keeps_existing_file_on_failure(tmp_path: Path) -> None:
    target = tmp_path / "f.nc"
    write_field(target, {"psi": wave()})
    before = target.read_bytes()
    bad = wave().astype(object)  # object dtype cannot be encoded
    bad[0, 0] = {"a": 1}
    with pytest.raises(ValueError):  # xarray cannot encode it
        write_field(target, {"psi": bad})
    assert target.read_bytes() == before
    assert sorted(os.listdir(tmp_path)) == ["f.nc"]  # no temporary file left


def test_write_into_missing_folder(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="does not exist") as e:
        write_field(tmp_path / "nope" / "f.nc", {"psi": wave()})
    message(e)


def test_write_misaligned_fields(tmp_path: Path) -> None:
    a = wave()
    b = a.assign_coords(x=a.x + 1.0)
    with pytest.raises(InputError, match="do not share coordinates") as e:
        write_field(tmp_path / "f.nc", {"psi": a, "psi_ref": b})
    message(e)
    assert not list(tmp_path.iterdir())


# ----------------------------------------------------------------------------- bad input


def test_missing_file(tmp_path: Path) -> None:
    with pytest.raises(InputError) as e:
        read_field(tmp_path / "absent.nc")
    msg = message(e)
    assert "absent.nc" in msg and "not found" in msg


def test_not_netcdf(tmp_path: Path) -> None:
    p = tmp_path / "junk.nc"
    p.write_text("this is not\na netCDF file\n")
    with pytest.raises(InputError) as e:
        read_field(p)
    msg = message(e)
    assert "junk.nc" in msg and "not a readable netCDF file" in msg
    assert "Traceback" not in msg
    assert e.value.__suppress_context__


def test_missing_variable(tmp_path: Path) -> None:
    p = write_field(tmp_path / "f.nc", {"u": wave(), "v": wave()})
    with pytest.raises(InputError) as e:
        read_field(p)
    msg = message(e)
    assert "f.nc" in msg and "'psi'" in msg and "['u', 'v']" in msg


def test_missing_coordinate(tmp_path: Path) -> None:
    ds = xr.Dataset({"psi": (("t", "x"), np.zeros((3, 4)))}, coords={"t": [0.0, 1.0, 2.0]})
    with pytest.raises(InputError) as e:
        read_field(raw_write(tmp_path / "f.nc", ds))
    msg = message(e)
    assert "f.nc" in msg and "'x'" in msg and "no coordinate" in msg


def test_non_numeric_coordinate(tmp_path: Path) -> None:
    ds = xr.Dataset({"psi": (("t",), np.zeros(3))}, coords={"t": ["a", "b", "c"]})
    with pytest.raises(InputError) as e:
        read_field(raw_write(tmp_path / "f.nc", ds))
    msg = message(e)
    assert "f.nc" in msg and "'t'" in msg and "numeric" in msg


def test_non_uniform_coordinate(tmp_path: Path) -> None:
    da = wave().assign_coords(x=[0.0, 0.25, 0.5, 0.75, 1.0, 1.3, 1.5, 1.75])
    with pytest.raises(InputError) as e:
        read_field(write_field(tmp_path / "f.nc", {"psi": da}))
    msg = message(e)
    assert "f.nc" in msg and "'x'" in msg and "not uniformly spaced" in msg
    assert "0.2 to 0.3" in msg


def test_decreasing_coordinate(tmp_path: Path) -> None:
    da = wave().isel(t=slice(None, None, -1))
    with pytest.raises(InputError) as e:
        read_field(write_field(tmp_path / "f.nc", {"psi": da}))
    msg = message(e)
    assert "'t'" in msg and "not strictly increasing" in msg and "-0.1" in msg


def test_float32_coordinate_round_off_is_accepted(tmp_path: Path) -> None:
    t = (np.arange(2000) * 0.01).astype(np.float32)
    ds = xr.Dataset({"psi": (("t",), np.zeros(2000))}, coords={"t": t})
    assert read_field(raw_write(tmp_path / "f.nc", ds)).sizes["t"] == 2000


def test_nan_values(tmp_path: Path) -> None:
    da = wave()
    da[2, 3] = np.nan
    da[4, 1] = np.inf
    p = write_field(tmp_path / "f.nc", {"psi": da})
    with pytest.raises(InputError) as e:
        read_field(p)
    msg = message(e)
    assert "f.nc" in msg and "2 NaN/inf" in msg and "index t=2, x=3 (t = " in msg
    assert np.isnan(read_field(p, allow_nan=True)[2, 3])


def test_too_few_sites(tmp_path: Path) -> None:
    da = wave().isel(x=slice(0, 1))
    with pytest.raises(InputError) as e:
        read_field(write_field(tmp_path / "f.nc", {"psi": da}))
    msg = message(e)
    assert "'x'" in msg and "1 site" in msg and "at least 2" in msg


def test_component_not_last(tmp_path: Path) -> None:
    da = orbit().transpose("component", "t")
    with pytest.raises(InputError) as e:
        read_field(write_field(tmp_path / "f.nc", {"psi": da}))
    msg = message(e)
    assert "f.nc" in msg and "'component'" in msg and "expected it last" in msg


def test_component_without_string_labels(tmp_path: Path) -> None:
    da = orbit().assign_coords(component=[0, 1])
    with pytest.raises(InputError) as e:
        read_field(write_field(tmp_path / "f.nc", {"psi": da}))
    assert "string labels" in message(e)
    with pytest.raises(InputError) as e:
        validate_field(orbit().drop_vars("component"), "mem")
    assert message(e).startswith("mem:") and "string labels" in str(e.value)


def test_component_labels_mismatch(tmp_path: Path) -> None:
    p = write_field(tmp_path / "f.nc", {"psi": orbit().assign_coords(component=["x", "z"])})
    with pytest.raises(InputError) as e:
        read_field(p, components=["x", "y"])
    msg = message(e)
    assert "f.nc" in msg and "expected ['x', 'y'], found ['x', 'z']" in msg
    with pytest.raises(InputError, match="no 'component' dim") as e:
        validate_field(wave(), "w.nc", components=["x", "y"])
    message(e)


def test_bad_periodic_attribute() -> None:
    da = wave()
    da.x.attrs["periodic"] = "maybe"
    with pytest.raises(InputError) as e:
        validate_field(da, "w.nc")
    msg = message(e)
    assert "w.nc" in msg and "periodic" in msg and "'x'" in msg


def test_in_memory_source_name() -> None:
    da = wave()
    da[0, 0] = np.nan
    with pytest.raises(InputError) as e:
        validate_field(da, source="data/train.nc")
    assert message(e).startswith("data/train.nc:")
