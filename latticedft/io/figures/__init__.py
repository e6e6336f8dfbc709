"""Figures of a served task: the field against its reference, its error over time, the drift of its invariants.

One figure per task (the ``figures`` export format, ``<task>.png``), drawn on
matplotlib's Agg canvas directly (no pyplot, no ``show``), so it works on
headless machines and touches no global state. From top to bottom:

* a red box when the task is incomplete ("INCOMPLETE: stopped at slice k of
  N (reason)") or carries warnings (the task file's ``latticedft_*``
  attributes);
* the field, in the style of Qin (2020):

  - 1D scalar ``psi(t)``: prediction as solid circles, reference as empty
    squares, against t (Figs 2-4);
  - 1D orbits ``psi(t, component)`` with 2+ components: the x-y plane,
    prediction in red, reference in blue (Figs 8-9);
  - 1+1D ``psi(t, x)``: space-time images of prediction, reference and
    error side by side;
  - 2+1D and 3+1D: snapshots at a few times (rows prediction / reference /
    error; 3+1D shows the middle slice of the extra dims);

  vector fields on 1+1D and higher lattices show their first component;
* the error over time, when a reference covers the task: max and RMS of
  ``psi - psi_ref`` per slice on a log scale, and the same for the baseline
  when the task file has ``baseline_err_max``/``baseline_err_rms``;
* the drift of the conserved quantities the task file holds (``invariant``,
  ``energy``, ``charge_<name>``: every series over time of these names), as
  ``|Q(t) - Q(0)| / |Q(0)|`` on a log scale.

Every axis and colour bar names its quantity and units, from the CF
attributes ``long_name`` and ``units`` of the arrays when present (units
``"1"`` read "dimensionless"). :func:`task_figure` builds the figure of a
task file (or of an export task) without saving it; :func:`plot_prediction`
draws and saves one from arrays.
"""

from __future__ import annotations

from ._figure import FigureExporter as FigureExporter
from ._figure import plot_prediction as plot_prediction
from ._figure import save_figure as save_figure
from ._figure import task_figure as task_figure
from ._panels import DRIFT_SERIES as DRIFT_SERIES
from ._panels import drift_series as drift_series

__all__ = [
    "DRIFT_SERIES",
    "FigureExporter",
    "drift_series",
    "plot_prediction",
    "save_figure",
    "task_figure",
]
