"""The state check, measured and not kept: how far a test's served cells lie from the training cells' states,
against how well the test is served.

    python -m benchmarks.state_range [--cases A,B] [--no-extra | --extra TEXT] [--cloud N]

The served field is checked against the training range feature by feature (``latticedft._serve._range``: the
stencil mean and the difference along each axis, per component, each against its own training minimum and
maximum). A cell can lie inside every feature's range and still hold a state (its features together: an
oscillator's ``(q, dq)``, i.e. its energy) that no training cell held. This measures, per test field, the largest
distance of a served cell's feature vector to the nearest training cell's (every training cell, a
``scipy.spatial.cKDTree``; each feature in units of its training span), to see whether a tolerance on it tells the
tests served badly from those served well (docs/uncertainty.md, "The state check").

Rows: every repository case (as :mod:`benchmarks.calibration` takes it: its ``case.toml`` model learned with the
case's keywords, no selection, the MLP fits stopped at their 500
iterations) and the calibration table's extra rows, clean. Per
test field: its index and served slices, the largest state distance and the first slice past ``--tol`` (0.05),
the largest excess beyond a feature's training range (``ServeResult.extrapolation``), the largest RMS error of a
slice (the two given slices excluded) over the reference's largest magnitude, and the time of the state check
over the time of serving. ``--cloud N``: the nearest of a uniform sample of ``N`` training cells (seed 0) instead
of every one (a bounded cost, larger distances).
"""

from __future__ import annotations

import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
import xarray as xr
from scipy.spatial import cKDTree

import latticedft as ldft
from latticedft._lattice import as_lattice_field, gather_cells

from .calibration import CASES, Setup, _case, _extra, _rms, _serve

#: The tolerance whose first passing slice is listed (the box check's own, ``EXTRAPOLATION_TOL``).
TOL = 0.05


def _features(model: ldft.AbstractLagrangian, field: xr.DataArray, boundary: Any) -> torch.Tensor:
    """``(slices - 1, cells per slice, features)``: the feature vectors of ``field``'s cells, per anchor slice."""
    f = as_lattice_field(field, boundary=boundary, min_slices=2)
    feats = model.mean_and_differences(gather_cells(f.values.detach().to(torch.float64), model.stencil, f.boundary))
    return feats.reshape(feats.shape[0], -1, feats.shape[-2] * feats.shape[-1])


class StateCloud:
    """The training cells' feature vectors of a learned ``model``, each feature over its training span."""

    def __init__(
        self, model: ldft.AbstractLagrangian, train: list[xr.DataArray], boundary: Any, size: int | None = None
    ) -> None:
        """``size``: keep a uniform sample of that many training cells (seed 0), not every one."""
        self.model = model
        parts = [_features(model, f, boundary) for f in train]
        feats = torch.cat([p.reshape(-1, p.shape[-1]) for p in parts]).numpy()
        lo, hi = feats.min(axis=0), feats.max(axis=0)
        self.span = np.maximum(np.maximum(hi - lo, 1e-12 * np.maximum(abs(lo), abs(hi))), 1e-300)
        if size is not None and feats.shape[0] > size:
            feats = feats[np.sort(np.random.default_rng(0).choice(feats.shape[0], size, replace=False))]
        self.tree = cKDTree(feats / self.span)

    def distance(self, field: xr.DataArray, boundary: Any) -> np.ndarray:
        """``(slices,)``: per slice, the largest distance of the cells holding it to the nearest training cell."""
        feats = _features(self.model, field, boundary).numpy() / self.span
        pts = feats.reshape(-1, feats.shape[-1])
        ok = np.isfinite(pts).all(axis=1)
        dist = np.full(pts.shape[0], np.inf)  # a non-finite cell is infinitely far
        if ok.any():
            dist[ok] = self.tree.query(pts[ok], k=1)[0]
        per_anchor = dist.reshape(feats.shape[0], -1).max(axis=1)
        per_slice = np.zeros(per_anchor.size + 1)
        per_slice[:-1] = per_anchor  # the cells anchored on a slice and those anchored on the one before
        per_slice[1:] = np.maximum(per_slice[1:], per_anchor)
        return per_slice


def rows(s: Setup, tol: float = TOL, size: int | None = None) -> list[list[object]]:
    """One row per test field of ``s`` (printed as it is measured); ``size``: as :class:`StateCloud`'s."""
    model = s.model()
    ldft.learn(model, s.train, boundary=s.boundary, progress=False, **s.learn)
    cloud = StateCloud(model, s.train, s.boundary, size)
    out = []
    for i, (init, ref, slices, boundary) in enumerate(s.tests):
        t0 = time.perf_counter()
        res = _serve(model, init, slices, boundary)
        t_serve = time.perf_counter() - t0
        pred = res.field
        n = min(pred.sizes[pred.dims[0]], ref.sizes[ref.dims[0]])
        err = _rms(np.asarray(pred.values) - np.asarray(ref.values[:n]), n)[2:]
        rel = float(np.max(err)) / float(np.nanmax(np.abs(np.asarray(ref.values[:n])))) if err.size else 0.0
        t0 = time.perf_counter()
        dist = cloud.distance(pred, boundary)
        t_state = time.perf_counter() - t0
        past = np.nonzero(dist > tol)[0]
        excess = float(np.asarray(res.extrapolation.values).max()) if res.extrapolation is not None else None
        out.append(
            [s.label, i, n, float(dist.max()), int(past[0]) if past.size else None, excess, rel, t_state / t_serve]
        )
        print(" | ".join(f"{v:.3g}" if isinstance(v, float) else str(v) for v in out[-1]), flush=True)
    return out


def main(argv: list[str]) -> None:
    cases: tuple[str, ...] = CASES
    keep: str | None = ""
    size: int | None = None
    it = iter(argv)
    for a in it:
        if a == "--cases":
            cases = tuple(c for c in next(it).split(",") if c)
        elif a == "--no-extra":
            keep = None
        elif a == "--extra":
            keep = next(it)
        elif a == "--cloud":
            size = int(next(it))
    print(
        "row | test | slices | state distance | first slice past tol | range excess | rel. error | state / serve time"
    )
    with tempfile.TemporaryDirectory() as tmp:
        setups = [_case(c, Path(tmp)) for c in cases]
        if keep is not None:
            setups += [s for s in _extra() if keep in s.label]
        for s in setups:
            rows(s, size=size)


if __name__ == "__main__":
    main(sys.argv[1:])
