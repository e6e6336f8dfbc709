"""Learning an ensemble: member 0 on all the data, the others on bootstrap resamples of its time windows."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from typing import Any

import numpy as np

from .._models import AbstractLagrangian, EnsembleLagrangian
from ._report import LearnReport
from ._source import FieldSource
from ._stream import TrainingData

__all__ = ["learn_ensemble", "time_windows", "EQUATION_SLICES_PER_WINDOW", "MAX_WINDOWS_PER_FIELD"]

#: A training field is cut into windows of about this many time slices that carry DEL equations ...
EQUATION_SLICES_PER_WINDOW = 10
#: ... and at most this many windows.
MAX_WINDOWS_PER_FIELD = 8


def time_windows(sources: list[FieldSource], width: int) -> list[FieldSource]:
    """Every field cut along time into windows; together they hold every DEL equation of the data once.

    ``width`` is the stencil's reach along time (1 for the first-order stencil): equations sit on slices
    ``width .. nt - 1 - width``; a window owning the equation slices ``[a, b)`` holds the slices
    ``[a - width, b + width)``.
    """
    out: list[FieldSource] = []
    for s in sources:
        first, last = width, s.nt - width  # equation slices [first, last)
        count = last - first
        if count <= 0:
            out.append(s)
            continue
        parts = max(1, min(MAX_WINDOWS_PER_FIELD, count // EQUATION_SLICES_PER_WINDOW))
        edges = np.linspace(first, last, parts + 1).round().astype(int)
        out += [s.window(int(a) - width, int(b) + width) for a, b in zip(edges[:-1], edges[1:])]
    return out


def learn_ensemble(
    ens: EnsembleLagrangian,
    fit_first: Callable[[Any], tuple[LearnReport, TrainingData]],
    fit: Callable[[AbstractLagrangian, TrainingData, LearnReport | None], LearnReport],
) -> LearnReport:
    """Fit member 0 on all the data and every other member on a bootstrap resample of its time windows.

    ``fit_first(member)`` learns member 0 as :func:`latticedft.learn` was asked to (noise correction
    included) and returns its report and the data it was last fitted on (the corrected fields after a noise
    correction): the resampled members learn on windows of those. ``fit(model, data, main)`` binds and
    learns one model with the call's settings (``main``: member 0's report, whose ridge and gauge choice the
    members take). Returns member 0's report with ``ensemble`` filled in (members, seed, windows, the
    members' ``rel_res``) and a warning when the data give a single window (the members cannot differ).
    """
    m0 = ens.member(0)
    first, fields = fit_first(m0)
    ens.bind(m0.n, m0.m, m0.spacing, m0.components)
    windows = time_windows(fields.sources, int(m0.stencil.width[0]))
    rng = np.random.default_rng(ens.seed)
    reports = [first]
    for k in range(1, len(ens)):
        pick = rng.integers(0, len(windows), size=len(windows))
        data = TrainingData([windows[i] for i in pick], fields.chunk_sites)
        data.held_at_home = fields.held_at_home
        reports.append(fit(ens.member(k), data, first))
    warnings = list(first.warnings)
    if len(windows) < 2:
        warnings.append(
            "ensemble: the training data give a single time window, so every resample is the data itself and "
            "the members do not differ (spread 0); give more or longer training fields"
        )
    bad = [k for k, r in enumerate(reports) if k and r.warnings]
    if bad:
        warnings.append(f"ensemble: resampled member(s) {bad} fit with warnings: {reports[bad[0]].warnings[0]}")
    info = {
        "members": len(ens),
        "seed": ens.seed,
        "windows": len(windows),
        "rel_res": [r.rel_res for r in reports],
        "wall_time": sum(r.wall_time for r in reports),
    }
    report = replace(first, ensemble=info, warnings=warnings)
    ens.report_ = report
    return report
