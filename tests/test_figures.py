"""The figure of a task, read back as matplotlib objects (labels, panels, lines, texts), not as pixels."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import xarray as xr

from latticedft import systems
from latticedft.io import write_field
from latticedft.io.figures import DRIFT_SERIES, task_figure

from case_helpers import run_cli, tiny_wave


def _texts(fig) -> list[str]:
    """Every text of the figure: suptitle, figure and subfigure texts, axes texts and titles."""
    from matplotlib.text import Text

    return [t.get_text() for t in fig.findobj(Text) if t.get_text()]


def _colorbars(fig) -> list:
    return [ax for ax in fig.axes if hasattr(ax, "_colorbar")]


def _panels(fig) -> list:
    return [ax for ax in fig.axes if not hasattr(ax, "_colorbar")]


def _panel(fig, title: str):
    found = [ax for ax in _panels(fig) if title in ax.get_title()]
    assert len(found) == 1, [ax.get_title() for ax in _panels(fig)]
    return found[0]


def _labels(ax) -> list[str]:
    return [str(line.get_label()) for line in ax.get_lines() if not str(line.get_label()).startswith("_")]


def _has_units(label: str) -> bool:
    return "(dimensionless)" in label or ("[" in label and "]" in label)


def _task_file(
    tmp_path: Path,
    *,
    complete: bool = True,
    baseline: bool = True,
    warnings: list[str] | None = None,
    charges: bool = True,
) -> Path:
    """A 1+1D task file as a run writes it, with the attributes and series the figure reads."""
    ref = systems.wave_string([(1, 0.5, 0.3), (3, 0.2)], nx=13, nt=40)
    n = 40 if complete else 25
    pred = (ref[:n] + 1e-3 * np.sin(ref.t.values[:n, None])).assign_attrs(ref.attrs)
    t = pred.t
    fields = {"psi": pred, "psi_ref": ref[:n], "psi_err": (pred - ref[:n]).assign_attrs(units="1")}
    if baseline:
        err = 2e-3 * np.linspace(0, 1, n)
        fields["baseline_err_max"] = xr.DataArray(err, coords={"t": t}, attrs={"baseline": "leapfrog", "units": "1"})
        fields["baseline_err_rms"] = xr.DataArray(err / 2, coords={"t": t}, attrs={"baseline": "leapfrog"})
    energy = 1.0 + 1e-6 * np.sin(t.values)
    fields["invariant"] = xr.DataArray(energy, coords={"t": t}, attrs={"long_name": "discrete field energy"})
    if charges:
        fields["energy"] = xr.DataArray(energy, coords={"t": t}, attrs={"long_name": "Noether energy", "units": "1"})
        fields["charge_momentum"] = xr.DataArray(
            1e-14 * np.arange(n), coords={"t": t}, attrs={"long_name": "momentum", "units": "1"}
        )
        fields["charge_phase"] = xr.DataArray(
            2.0 - 1e-9 * t.values, coords={"t": t}, attrs={"long_name": "phase charge", "units": "1"}
        )
    attrs = {"latticedft_task": "test", "latticedft_complete": "true" if complete else "false", "latticedft_steps": 40}
    if not complete:
        attrs.update(latticedft_stopped_at_slice=25, latticedft_stop_reason="Newton did not converge at slice 25")
    if warnings is not None:
        attrs["latticedft_warnings"] = json.dumps(warnings)
    return write_field(tmp_path / "test.nc", fields, attrs=attrs)


def test_every_axis_and_colour_bar_is_labelled_with_units(tmp_path: Path) -> None:
    fig = task_figure(_task_file(tmp_path))
    panels = _panels(fig)
    assert len(panels) == 5  # prediction, reference, error; error per slice; drift
    for ax in panels:
        assert ax.get_xlabel() and _has_units(ax.get_xlabel()), ax.get_title()
    left = [ax for ax in panels if ax.get_title() in ("prediction",) or "per slice" in ax.get_title()]
    for ax in left:
        assert _has_units(ax.get_ylabel()), ax.get_title()
    assert "time t" in _panel(fig, "prediction").get_ylabel()
    bars = _colorbars(fig)
    assert [ax.get_ylabel() for ax in bars] == [
        "string displacement psi (dimensionless)",
        "string displacement psi (dimensionless)",
        "psi - psi_ref (dimensionless)",
    ]
    assert fig.get_suptitle() == "test"


def test_error_panel_has_the_model_and_the_baseline(tmp_path: Path) -> None:
    fig = task_figure(_task_file(tmp_path))
    ax = _panel(fig, "error against the reference")
    assert ax.get_yscale() == "log"
    assert "|psi - psi_ref|" in ax.get_ylabel()
    labels = _labels(ax)
    assert "learned L_d: max" in labels and "learned L_d: rms" in labels
    assert "leapfrog (baseline): max" in labels and "leapfrog (baseline): rms" in labels
    t = np.asarray(ax.get_lines()[0].get_xdata())
    model_max = np.asarray(ax.get_lines()[labels.index("learned L_d: max")].get_ydata())
    drawn = np.isfinite(model_max)  # log scale: the exact first slice is left out
    assert drawn.sum() == 39
    np.testing.assert_allclose(model_max[drawn], 1e-3 * np.abs(np.sin(t[drawn])), rtol=1e-9)


def test_no_baseline_line_without_a_baseline(tmp_path: Path) -> None:
    fig = task_figure(_task_file(tmp_path, baseline=False))
    labels = _labels(_panel(fig, "error against the reference"))
    assert labels == ["learned L_d: max", "learned L_d: rms"]


def test_drift_panel_draws_every_conserved_series(tmp_path: Path) -> None:
    fig = task_figure(_task_file(tmp_path))
    ax = _panel(fig, "conserved quantities")
    assert ax.get_yscale() == "log" and "Q(0)" in ax.get_ylabel()
    labels = _labels(ax)
    assert labels == [
        "momentum (charge_momentum) (absolute: Q(0) = 0)",
        "phase charge (charge_phase)",
        "Noether energy (energy)",
        "discrete field energy (invariant)",
    ]
    line = ax.get_lines()[1]
    t, phase = np.asarray(line.get_xdata()), np.asarray(line.get_ydata())
    np.testing.assert_allclose(phase[1:], 1e-9 * t[1:] / 2, rtol=1e-6)  # relative to Q(0) = 2
    assert set(DRIFT_SERIES) == {"energy", "invariant"}


def test_no_drift_panel_without_conserved_series(tmp_path: Path) -> None:
    path = _task_file(tmp_path, charges=False)
    with xr.open_dataset(path) as ds:
        ds.load()
    fig = task_figure(ds.drop_vars("invariant"))
    assert not [ax for ax in _panels(fig) if "conserved" in ax.get_title()]
    assert _panel(fig, "error against the reference")


def test_incomplete_task_and_warnings_are_marked(tmp_path: Path) -> None:
    warn = ["poor fit: rel_res 0.79 > 0.01", "extrapolation: psi leaves the training range at slice 12 by 40 %"]
    fig = task_figure(_task_file(tmp_path, complete=False, warnings=warn))
    texts = _texts(fig)
    box = [t for t in texts if t.startswith("INCOMPLETE")]
    assert box and "INCOMPLETE: stopped at slice 25 of 40 (Newton did not converge at slice 25)" in box[0]
    assert all(f"WARNING: {w}" in box[0] for w in warn)
    # hatched on the served field's image, its error's and both panels over time, not on the reference's
    assert texts.count("not served") == 4
    reference = [ax for ax in _panels(fig) if ax.get_title() == "reference"][0]
    assert not [t for t in reference.texts if t.get_text() == "not served"]
    status = [t for t in fig.findobj() if getattr(t, "get_text", None) and t.get_text() == box[0]][0]
    assert status.get_color() != "black"


def test_complete_task_without_warnings_has_no_box(tmp_path: Path) -> None:
    fig = task_figure(_task_file(tmp_path, warnings=[]))
    assert not [t for t in _texts(fig) if "INCOMPLETE" in t or "WARNING" in t]


def test_incomplete_without_stop_attributes_counts_the_slices(tmp_path: Path) -> None:
    path = _task_file(tmp_path, complete=False)
    with xr.open_dataset(path) as ds:
        ds.load()
    for key in ("latticedft_stopped_at_slice", "latticedft_stop_reason", "latticedft_steps"):
        del ds.attrs[key]
    assert "INCOMPLETE: stopped at slice 25" in _texts(task_figure(ds))


@pytest.mark.parametrize("layout", ["series", "orbit", "snapshots"])
def test_other_layouts_are_labelled(tmp_path: Path, layout: str) -> None:
    if layout == "series":
        ref = systems.oscillator_sin(0.4, n=51)
    elif layout == "orbit":
        ref = xr.open_dataarray(Path(__file__).resolve().parents[1] / "cases/kepler/data/earth_0.98.nc")
    else:
        t, y, x = np.arange(6) * 0.1, np.arange(9) * 0.2, np.arange(9) * 0.2
        ref = xr.DataArray(
            np.random.default_rng(0).random((6, 9, 9)),
            coords={"t": ("t", t, {"units": "s"}), "y": ("y", y, {"units": "m"}), "x": ("x", x, {"units": "m"})},
            dims=("t", "y", "x"),
            attrs={"long_name": "membrane displacement", "units": "mm"},
        )
    ref = ref.rename("psi")
    ds = xr.Dataset({"psi": ref + 1e-3, "psi_ref": ref})
    ds["psi"].attrs = dict(ref.attrs)
    fig = task_figure(ds)
    for ax in _panels(fig):
        if ax.get_xlabel():
            assert _has_units(ax.get_xlabel()), (layout, ax.get_xlabel())
    assert all(_has_units(ax.get_ylabel()) for ax in _colorbars(fig))
    assert _panel(fig, "error against the reference")
    if layout == "orbit":
        orbit = [ax for ax in _panels(fig) if not ax.get_title()][0]
        assert orbit.get_xlabel() == "position psi_x [au]" and orbit.get_ylabel() == "position psi_y [au]"
        # time in units of 58.14 days is drawn in days
        error = _panel(fig, "error against the reference")
        assert ref.t.attrs["units"] == "58.14 days" and error.get_xlabel() == "time t [days]"
        drawn = np.asarray(error.get_lines()[0].get_xdata())
        np.testing.assert_allclose(drawn, ref.t.values * 58.14, rtol=1e-15)
    if layout == "series":  # a long quantity label is wrapped to fit its axes (whole words, nothing lost)
        field = [ax for ax in _panels(fig) if "prediction" in _labels(ax)][0]
        ylabel = field.get_ylabel()
        whole = "oscillator displacement (Qin 2020 Example 1) psi (dimensionless)"
        assert "\n" in ylabel and ylabel.split() == whole.split()


def test_run_writes_the_baseline_error_and_draws_it(tmp_path: Path, capsys) -> None:
    case = tiny_wave(tmp_path)
    test = xr.open_dataarray(case / "data" / "test.nc")
    write_field(case / "data" / "base.nc", {"psi": test + 0.01})
    toml = (
        (case / "case.toml")
        .read_text()
        .replace('from = "data/test.nc"', 'from = "data/test.nc"\nbaseline = "data/base.nc"')
    )
    (case / "case.toml").write_text(toml)
    assert run_cli(capsys, "run", case, "-q", '--set=export.formats=["figures"]')[0] == 0
    res = case / "results"
    with xr.open_dataset(res / "test.nc") as ds:
        assert ds.attrs["latticedft_steps"] == 30
        np.testing.assert_allclose(ds["baseline_err_max"].values, 0.01, rtol=1e-9)
        np.testing.assert_allclose(ds["baseline_err_rms"].values, 0.01, rtol=1e-9)
        assert ds["psi"].attrs["long_name"] == "string displacement"
        assert ds["psi_err"].attrs["units"] == ds["psi"].attrs["units"]
    fig = task_figure(res / "test.nc")
    labels = _labels(_panel(fig, "error against the reference"))
    assert any("baseline" in label for label in labels)
    assert fig.get_suptitle() == "test"
    assert (res / "test.png").is_file()
