"""The field layout has one owner (latticedft._layout): dims, component dim, spacing, periodic attribute.

Also the layering: the core never imports latticedft.io (io builds on the core, not the reverse).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import xarray as xr

import latticedft as ldft
import latticedft.io as lio
import latticedft.io.fields as iofields
from latticedft import _layout, systems
from latticedft._errors import InputError
from latticedft._layout import (
    COMPONENT_DIM,
    PERIODIC_ATTR,
    axis_periodic,
    component_labels,
    coordinate_spacing,
    field_periodic,
    field_spacing,
    lattice_dims,
    parse_periodic,
    periodic_attr,
)

PACKAGE = Path(ldft.__file__).resolve().parent


def _field(t: np.ndarray, x: np.ndarray | None = None, components=None) -> xr.DataArray:
    dims, coords, shape = ["t"], {"t": t}, [t.size]
    if x is not None:
        dims.append("x")
        coords["x"] = x
        shape.append(x.size)
    if components is not None:
        dims.append(COMPONENT_DIM)
        coords[COMPONENT_DIM] = list(components)
        shape.append(len(components))
    return xr.DataArray(np.zeros(shape), dims=dims, coords=coords, name="psi")


# -- one owner, re-exported ----------------------------------------------------------------------------------
def test_io_reexports_the_layout() -> None:
    for name in ("COMPONENT_DIM", "lattice_dims", "field_spacing", "field_periodic", "validate_field"):
        assert getattr(iofields, name) is getattr(_layout, name)
        assert getattr(lio, name) is getattr(_layout, name)
    assert COMPONENT_DIM == "component" and PERIODIC_ATTR == "periodic"


def test_dims_and_components() -> None:
    orbit = _field(np.arange(4) * 0.1, components=["x", "y"])
    assert lattice_dims(orbit) == ("t",) and component_labels(orbit) == ("x", "y")
    wave = _field(np.arange(4) * 0.1, np.arange(5) * 0.2)
    assert lattice_dims(wave) == ("t", "x") and component_labels(wave) is None
    f = ldft.as_lattice_field(orbit)
    assert f.components == ("x", "y") and f.to_dataarray().dims == ("t", COMPONENT_DIM)


# -- spacing: one formula, the engine's ------------------------------------------------------------------------
def test_spacing_is_the_first_step_everywhere() -> None:
    # 0.05 * arange: the first step is 0.05 exactly; the end-to-end mean (c[-1] - c[0]) / (n - 1) is not
    t = np.arange(400) * 0.05
    assert (t[-1] - t[0]) / (t.size - 1) != 0.05
    da = _field(t)
    assert coordinate_spacing(t) == 0.05
    assert field_spacing(da) == (0.05,) == ldft.as_lattice_field(da).spacing
    # an offset origin: the step as stored, bit for bit, in the engine and in io
    x = -10.0 + 0.1 * np.arange(201)
    wave = _field(np.arange(3) * 0.05, x)
    assert field_spacing(wave) == ldft.as_lattice_field(wave).spacing == (0.05, float(x[1] - x[0]))


def test_spacing_errors_name_the_dim() -> None:
    with pytest.raises(InputError, match="dim 't' has 1 site"):
        field_spacing(_field(np.array([0.0])), "a.nc")
    da = _field(np.arange(3.0)).assign_coords(t=["a", "b", "c"])
    with pytest.raises(InputError, match="coordinate 't' has dtype"):
        field_spacing(da, "a.nc")


def test_uniformity_check() -> None:
    t = np.arange(6) * 0.1
    t[3] += 1e-4
    with pytest.raises(InputError, match="not uniformly spaced") as err:
        ldft.as_lattice_field(_field(t), source="f.nc")
    assert str(err.value).startswith("f.nc: coordinate 't'")
    # float32 round-off is no reason to reject a coordinate
    _layout.validate_field(_field(np.arange(50, dtype=np.float32) * np.float32(0.1)))


# -- the periodic attribute: one parser, one writer -------------------------------------------------------------
@pytest.mark.parametrize(
    "value,flag",
    [
        ("true", True),
        ("false", False),
        (" TRUE ", True),
        ("False", False),
        (True, True),
        (False, False),
        (np.bool_(True), True),
        (1, True),
        (0, False),
        (np.int32(1), True),
        (np.array([1]), True),
        (np.array(["true"]), True),
    ],
)
def test_parse_periodic(value, flag) -> None:
    assert parse_periodic(value) is flag


@pytest.mark.parametrize("value", ["yes", "periodic", "1", 2, 1.0, None, [1]])
def test_parse_periodic_rejects(value) -> None:
    with pytest.raises(InputError) as err:
        parse_periodic(value, "x", "a.nc")
    text = str(err.value)
    assert "\n" not in text and text.startswith("a.nc: attribute 'periodic' of coordinate 'x'")


@pytest.mark.parametrize("flag", [True, False])
def test_periodic_attribute_round_trip(tmp_path: Path, flag: bool) -> None:
    assert parse_periodic(periodic_attr(flag)) is flag
    da = _field(np.arange(3) * 0.1, np.arange(4) * 0.25)
    da.x.attrs[PERIODIC_ATTR] = periodic_attr(flag)
    back = lio.read_field(lio.write_field(tmp_path / "f.nc", {"psi": da}))
    assert field_periodic(back) == (None, flag) and axis_periodic(back, "x") is flag
    assert ldft.as_lattice_field(back).periodic == (False, flag)
    assert ldft.as_lattice_field(back).boundary == ("open", "periodic" if flag else "dirichlet")


def test_periodic_attribute_written_by_the_systems() -> None:
    x = np.arange(8) * 0.05
    u = systems.klein_gordon(np.sin(2 * np.pi * x / 0.4), np.sin(2 * np.pi * x / 0.4), steps=4)
    assert u.x.attrs[PERIODIC_ATTR] == periodic_attr(True) and axis_periodic(u, "x")
    v = systems.leapfrog(u.isel(t=0).drop_vars("t"), u.isel(t=1).drop_vars("t"), 3, 0.1, boundary="periodic")
    assert field_periodic(v) == (None, True)


def test_time_axis_cannot_be_periodic() -> None:
    da = _field(np.arange(3) * 0.1)
    da.t.attrs[PERIODIC_ATTR] = "true"
    with pytest.raises(InputError, match="the time axis 't' cannot be periodic"):
        ldft.as_lattice_field(da, source="f.nc")


# The layering (the engine never imports latticedft.io) is checked by tests/test_layers.py.
