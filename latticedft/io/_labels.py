"""Labels of quantities for figures and ParaView views, from the CF attributes ``long_name`` and ``units``.

>>> import numpy as np, xarray as xr
>>> da = xr.DataArray(np.zeros(3), dims="t", coords={"t": ("t", [0.0, 1, 2], {"long_name": "time", "units": "s"})},
...                   attrs={"long_name": "string displacement", "units": "1"})
>>> coord_label(da, "t"), quantity_label(da, "psi")
('time t [s]', 'string displacement psi (dimensionless)')
>>> unit_scale("58.14 days"), unit_scale("au"), unit_scale("1")
((58.14, 'days'), (1.0, 'au'), (1.0, '1'))
"""

from __future__ import annotations

import math
import re
import textwrap
from typing import Any

import xarray as xr

__all__ = ["units_text", "unit_scale", "named", "coord_label", "quantity_label"]

_SCALED_UNIT = re.compile(r"^\s*(\d*\.?\d+(?:[eE][-+]?\d+)?)\s+([^\d\s].*?)\s*$")


def units_text(units: Any) -> str:
    """``" [au]"``; ``" (dimensionless)"`` for the CF unit ``"1"``; ``""`` when there are none."""
    if units is None or str(units).strip() == "":
        return ""
    return " (dimensionless)" if str(units).strip() == "1" else f" [{units}]"


def unit_scale(units: Any) -> tuple[float, Any]:
    """``(58.14, "days")`` for a scaled unit such as ``"58.14 days"`` (values in it, times 58.14, are in days);
    ``(1.0, units)`` for any other."""
    match = _SCALED_UNIT.match(str(units)) if units is not None else None
    if match is None:
        return 1.0, units
    factor = float(match.group(1))
    return (factor, match.group(2)) if factor > 0 and math.isfinite(factor) else (1.0, units)


def named(long_name: Any, symbol: str) -> str:
    """``"time t"`` from (``"time"``, ``"t"``); just the symbol when the long name adds nothing."""
    if long_name is None or str(long_name).strip() in ("", symbol):
        return symbol
    return f"{long_name} {symbol}"


def coord_label(da: xr.DataArray, dim: str, scaled: bool = False) -> str:
    """Axis label of a coordinate: its long name, symbol and units; with ``scaled``, the units of its values
    times :func:`unit_scale`'s factor (``"time t [days]"`` for ``units = "58.14 days"``)."""
    attrs = da.coords[dim].attrs if dim in da.coords else {}
    units = unit_scale(attrs.get("units"))[1] if scaled else attrs.get("units")
    return named(attrs.get("long_name"), dim) + units_text(units)


def quantity_label(da: xr.DataArray, variable: str, suffix: str = "", width: int | None = None) -> str:
    """Label of a field's values, ``"string displacement psi (dimensionless)"``; wrapped at ``width`` characters."""
    text = named(da.attrs.get("long_name"), variable + suffix) + units_text(da.attrs.get("units"))
    return "\n".join(textwrap.wrap(text, width)) or text if width else text
