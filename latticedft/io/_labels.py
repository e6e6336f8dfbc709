"""Labels of quantities for figures and ParaView views, from the CF attributes ``long_name`` and ``units``.

>>> import numpy as np, xarray as xr
>>> da = xr.DataArray(np.zeros(3), dims="t", coords={"t": ("t", [0.0, 1, 2], {"long_name": "time", "units": "s"})},
...                   attrs={"long_name": "string displacement", "units": "1"})
>>> coord_label(da, "t"), quantity_label(da, "psi")
('time t [s]', 'string displacement psi (dimensionless)')
"""

from __future__ import annotations

import textwrap
from typing import Any

import xarray as xr

__all__ = ["units_text", "named", "coord_label", "quantity_label"]


def units_text(units: Any) -> str:
    """``" [au]"``; ``" (dimensionless)"`` for the CF unit ``"1"``; ``""`` when there are none."""
    if units is None or str(units).strip() == "":
        return ""
    return " (dimensionless)" if str(units).strip() == "1" else f" [{units}]"


def named(long_name: Any, symbol: str) -> str:
    """``"time t"`` from (``"time"``, ``"t"``); just the symbol when the long name adds nothing."""
    if long_name is None or str(long_name).strip() in ("", symbol):
        return symbol
    return f"{long_name} {symbol}"


def coord_label(da: xr.DataArray, dim: str) -> str:
    """Axis label of a coordinate: its long name, symbol and units."""
    attrs = da.coords[dim].attrs if dim in da.coords else {}
    return named(attrs.get("long_name"), dim) + units_text(attrs.get("units"))


def quantity_label(da: xr.DataArray, variable: str, suffix: str = "", width: int | None = None) -> str:
    """Label of a field's values, ``"string displacement psi (dimensionless)"``; wrapped at ``width`` characters."""
    text = named(da.attrs.get("long_name"), variable + suffix) + units_text(da.attrs.get("units"))
    return "\n".join(textwrap.wrap(text, width)) or text if width else text
