"""Testing helpers, like ``xarray.testing``: failures read as a diff, not a traceback of numbers."""

from __future__ import annotations

import numpy as np
import xarray as xr

__all__ = ["assert_fields_close"]


def assert_fields_close(
    actual: xr.DataArray, desired: xr.DataArray, *, atol: float = 1e-12, rtol: float = 0.0, check_coords: bool = True
) -> None:
    """Assert two fields agree on dims, coordinates and values within ``atol + rtol |desired|``.

    The message names the worst site by its coordinates.

    >>> import numpy as np, xarray as xr
    >>> a = xr.DataArray(np.zeros((3, 2)), dims=("t", "x"), coords={"t": [0.0, 1.0, 2.0], "x": [0.0, 0.5]})
    >>> assert_fields_close(a, a + 1e-14)
    >>> assert_fields_close(a, a + 1e-3)
    Traceback (most recent call last):
    ...
    AssertionError: fields differ: max |actual - desired| = 0.001 at t=0, x=0 (tolerance 1e-12); 6 of 6 values outside
    """
    __tracebackhide__ = True
    if actual.dims != desired.dims:
        raise AssertionError(f"dims differ: {actual.dims} vs {desired.dims}")
    if actual.shape != desired.shape:
        raise AssertionError(f"shapes differ: {dict(actual.sizes)} vs {dict(desired.sizes)}")
    if check_coords:
        for d in actual.dims:
            if d in actual.coords and d in desired.coords:
                ca, cd = actual[d].values, desired[d].values
                same = np.array_equal(ca, cd) if ca.dtype.kind in "OUS" else np.allclose(ca, cd, rtol=1e-12, atol=0)
                if not same:
                    raise AssertionError(f"coordinate {d!r} differs")
    a, b = np.asarray(actual.values, dtype=float), np.asarray(desired.values, dtype=float)
    diff = np.abs(a - b)
    tol = atol + rtol * np.abs(b)
    bad = ~(diff <= tol)
    if bad.any():
        score = np.where(np.isnan(diff), np.inf, diff - tol)
        idx = np.unravel_index(int(np.argmax(score)), diff.shape)
        where = ", ".join(
            f"{d}={actual[d].values[i]:g}" if d in actual.coords and actual[d].dtype.kind == "f" else f"{d}={i}"
            for d, i in zip(actual.dims, idx)
        )
        raise AssertionError(
            f"fields differ: max |actual - desired| = {diff[idx]:.3g} at {where} "
            f"(tolerance {float(tol[idx]):.3g}); {int(bad.sum())} of {bad.size} values outside"
        )
