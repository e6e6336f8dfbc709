"""A wrong field is never "complete": degenerate fits are refused, poor fits and extrapolation are reported,
partial results say so in their files, and bad API arguments raise the library's own one-line errors."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
import xarray as xr

import latticedft as ldft
from latticedft import io, systems
from latticedft._learn._report import POOR_FIT_REL_RES
from latticedft._run import RELATIVE_ERROR_LIMIT
from latticedft._serve._range import EXTRAPOLATION_TOL

from case_helpers import WAVE, oscillator_case, run_cli, tiny_wave, write_toml
from helpers import oscillator_data, series, wave_field

REPO = Path(__file__).resolve().parents[1]
DATA = Path(__file__).with_name("data") / "models-v1"
NO_EXPORT = ["--set", "export.figures=false", "--set", "export.paraview=false", "--set", "run.threads=1"]


def _attrs(path: Path) -> dict:
    with xr.open_dataset(path, engine="netcdf4") as ds:
        return dict(ds.attrs)


def _one_line(text: str) -> str:
    assert text and "\n" not in text, text
    return text


# -- 1. a degenerate fit is never served as a success ---------------------------------------------------------


def test_gauge_none_is_flagged_degenerate_at_learn_time():
    field = wave_field(nx=13, nt=12)
    report = ldft.learn(ldft.PolynomialLagrangian((2, 2)), field, gauge="none")
    assert report.degenerate and report.hessian_max_sv == 0.0
    assert report.warnings[0].startswith("degenerate fit: the mixed time Hessian M is singular")
    assert report.to_dict()["degenerate"] is True
    fine = ldft.learn(ldft.PolynomialLagrangian((2, 2)), field)
    assert not fine.degenerate and fine.warnings == [] and abs(fine.hessian_max_sv - 1) < 1e-6


@pytest.mark.parametrize("options", [{}, {"affine": False}, {"mode": "sweep"}])
def test_degenerate_model_is_refused_when_served(options):
    field = wave_field(nx=13, nt=12)
    model = ldft.PolynomialLagrangian((2, 2))
    ldft.learn(model, field, gauge="none")
    with pytest.raises(ldft.ServeError) as err:
        ldft.serve(model, field, **options)
    assert "mixed Hessian" in _one_line(str(err.value)) and "singular" in str(err.value)
    assert err.value.slice == 2 and not err.value.result.complete and err.value.result.slices == 2


@pytest.mark.parametrize("mode", ["newton", "sweep"])
def test_degenerate_model_is_refused_in_1d(mode):
    _, data = oscillator_data(steps=30)
    model = ldft.PolynomialLagrangian((2, 2))
    assert ldft.learn(model, data, gauge="none").degenerate
    with pytest.raises(ldft.ServeError, match="mixed Hessian singular: it is zero") as err:
        ldft.serve(model, data[0].isel(t=slice(0, 2)), slices=10, mode=mode)
    assert err.value.result.slices == 2


def test_a_model_without_time_coupling_is_refused_on_the_affine_path_too():
    spatial_only = ldft.AnalyticLagrangian(lambda c, h: -0.5 * ((c[..., 2, 0] - c[..., 0, 0]) / h[1]) ** 2)
    for affine in (True, False):
        with pytest.raises(ldft.ServeError, match="mixed Hessian singular"):
            ldft.serve(spatial_only, wave_field(nx=13, nt=12), affine=affine)


def test_mixed_hessian_singular_at_one_site_relative_to_the_others():
    """``M = -g'(a) g'(b) / h0^2`` with ``g = q - q^3/3`` vanishes where a slice holds ``q = 1``."""

    def g(q):
        return q - q**3 / 3

    model = ldft.AnalyticLagrangian(
        lambda c, h: -g(c[..., 0, 0]) * g(c[..., 1, 0]) / h[0] ** 2 - 0.5 * ((c[..., 2, 0] - c[..., 0, 0]) / h[1]) ** 2
    )
    v = np.full((8, 9), 0.3)
    v[:, 0] = v[:, -1] = 0.0
    t, x = np.arange(8) * 0.05, np.arange(9) * 0.1
    init = xr.DataArray(v, dims=("t", "x"), coords={"t": t, "x": x}, name="psi")
    assert ldft.serve(model, init).complete  # M of every site far from zero: served
    v[1, 4] = 1.0
    with pytest.raises(ldft.ServeError) as err:
        ldft.serve(model, init.copy(data=v))
    assert "smallest singular value 0.000e+00" in str(err.value) and "relative to its scale" in str(err.value)
    assert err.value.site == (1, 4) and err.value.slice == 2


def test_cli_gauge_none_on_the_wave_case_stops_with_exit_3(tmp_path, capsys):
    out = tmp_path / "out"
    code, _, err = run_cli(capsys, "run", WAVE, "--out", out, "--set", 'train.gauge="none"', *NO_EXPORT)
    assert code == 3
    assert "degenerate fit" in err and "mixed Hessian singular" in err
    summary = json.loads((out / "summary.json").read_text())
    task = summary["tasks"]["test"]
    assert task["complete"] is False and task["slices"] == 2 and summary["incomplete_tasks"] == ["test"]
    assert task["stop_reason"].startswith("slice 2 ") and "mixed Hessian singular" in task["stop_reason"]
    assert summary["train"]["degenerate"] is True
    assert any(w.startswith("degenerate fit") for w in summary["warnings"])
    attrs = _attrs(out / "test.nc")
    assert attrs["latticedft_complete"] == "false"
    assert int(attrs["latticedft_stopped_at_slice"]) == 2 and int(attrs["latticedft_steps"]) == 401
    assert "mixed Hessian singular" in attrs["latticedft_stop_reason"]
    warnings = json.loads(attrs["latticedft_warnings"])
    assert isinstance(warnings, list) and any(w.startswith("degenerate fit") for w in warnings)
    assert "degenerate fit" in (out / "run.log").read_text()
    assert "verdict: unusable: the learned L_d has no usable kinetic term" in err  # after the training line
    assert "task test: verdict: stopped: the learned L_d cannot step the field there" in err
    assert "the first 2 of 401 slices are written; next: " in err


# -- 2. a poor fit warns loudly ---------------------------------------------------------------------------------


def test_poor_fit_is_reported():
    _, data = oscillator_data(steps=60)
    report = ldft.learn(ldft.PolynomialLagrangian((2, 0)), data)  # a free particle for an oscillator
    assert report.rel_res > POOR_FIT_REL_RES and not report.degenerate
    assert [w for w in report.warnings if w.startswith("poor fit: rel_res = ")]
    good = ldft.learn(ldft.PolynomialLagrangian((2, 4)), data)
    assert good.rel_res < POOR_FIT_REL_RES and good.warnings == []


def test_cli_poor_fit_warns_on_stderr_in_the_log_and_the_summary(tmp_path, capsys):
    case = oscillator_case(tmp_path)
    out = tmp_path / "out"
    code, _, err = run_cli(capsys, "run", case, "--out", out, "--set", "model.orders=[2,0]", *NO_EXPORT)
    assert "latticedft: warning: poor fit: rel_res = " in err
    assert "WARNING poor fit: rel_res = " in (out / "run.log").read_text()
    summary = json.loads((out / "summary.json").read_text())
    assert summary["train"]["rel_res"] > POOR_FIT_REL_RES
    assert any(w.startswith("poor fit") for w in summary["warnings"])
    assert any(w.startswith("poor fit") for w in summary["train"]["warnings"])
    assert summary["exit_status"] == code
    for name, task in summary["tasks"].items():
        warnings = json.loads(_attrs(out / f"{name}.nc")["latticedft_warnings"])
        assert any(w.startswith("poor fit") for w in warnings)  # the model's warnings travel with every task
        assert task["file"] == f"{name}.nc"


# -- 2b. complete is not accurate: a field far from its reference warns -------------------------------------------


def test_a_complete_task_far_from_its_reference_warns(tmp_path, capsys):
    case = tiny_wave(tmp_path)
    test = io.read_field(case / "data" / "test.nc")
    io.write_field(case / "data" / "flipped.nc", {"psi": -test})  # a reference the served field cannot match
    toml = (
        (case / "case.toml")
        .read_text()
        .replace('from = "data/test.nc"', 'from = "data/test.nc"\nreference = "data/flipped.nc"')
    )
    write_toml(case, toml)
    out = tmp_path / "out"
    code, _, err = run_cli(capsys, "run", case, "--out", out, *NO_EXPORT)
    summary = json.loads((out / "summary.json").read_text())
    task = summary["tasks"]["test"]
    assert code == 0 and task["complete"] is True  # complete: the solver converged on every slice
    assert task["relative_error"] > RELATIVE_ERROR_LIMIT and task["relative_error"] == pytest.approx(2.0, rel=0.05)
    keys = list(task)
    assert keys[keys.index("compared_slices") + 1] == "relative_error"  # beside the errors it divides
    warning = next(w for w in task["warnings"] if w.startswith("inaccurate: "))
    assert "times the reference's largest magnitude" in warning and "next: " in warning
    assert f"task test: {warning}" in summary["warnings"]
    assert f"latticedft: warning: task test: {warning}" in err
    assert warning in (out / "run.log").read_text()
    assert warning in json.loads(_attrs(out / "test.nc")["latticedft_warnings"])


def test_an_accurate_task_records_its_relative_error_and_no_warning(tmp_path, capsys):
    case, out = tiny_wave(tmp_path), tmp_path / "out"
    code, _, err = run_cli(capsys, "run", case, "--out", out, *NO_EXPORT)
    task = json.loads((out / "summary.json").read_text())["tasks"]["test"]
    assert code == 0 and task["reference"] == "test.nc" and 0 < task["relative_error"] < RELATIVE_ERROR_LIMIT
    size = float(np.abs(io.read_field(case / "data" / "test.nc").values).max())  # the reference is its from file
    assert task["relative_error"] == pytest.approx(task["max_error"] / size, rel=1e-12)
    assert not [w for w in task["warnings"] if w.startswith("inaccurate")] and "inaccurate" not in err
    assert "verdict: good: the data obey the learned equations" in err


# -- 3. serving outside the training range is reported ----------------------------------------------------------


def _small_oscillator():
    _, data = oscillator_data(amplitudes=(0.4, 0.8), steps=60)
    model = ldft.PolynomialLagrangian((2, 4))
    ldft.learn(model, data)
    return model


def test_training_range_is_recorded_and_saved(tmp_path):
    model = _small_oscillator()
    rng = model.trained_range()
    assert rng is not None and tuple(rng.shape) == (2, 2, 1)  # (min/max, mean and d_t, component)
    assert float(rng[1, 0, 0]) == pytest.approx(0.8, abs=1e-2) and float(rng[0, 0, 0]) < -0.7
    back = ldft.load_model(ldft.save_model(model, tmp_path / "m.pt"))
    assert torch.equal(back.trained_range(), rng)


def test_old_model_files_load_without_a_range():
    model = ldft.load_model(DATA / "poly.pt")
    assert model.trained_range() is None
    out = ldft.serve(model, series([0.5, 0.49], model.spacing[0]), slices=10)
    assert out.extrapolation is None and out.warnings == [] and out.extrapolation_summary() is None


def test_serving_inside_the_range_is_quiet():
    model = _small_oscillator()
    _, test = oscillator_data(amplitudes=(0.6,), steps=60)
    out = ldft.serve(model, test[0].isel(t=slice(0, 2)), slices=60)
    assert out.warnings == []
    assert out.extrapolation.dims == ("t", "feature") and list(out.extrapolation["feature"].values) == ["mean", "d_t"]
    assert out.extrapolation.sizes["t"] == 60 and float(out.extrapolation.max()) <= EXTRAPOLATION_TOL
    summary = out.to_dict()["extrapolation"]
    assert summary["first_slice"] is None and set(summary["max"]) == {"mean", "d_t"}


def test_serving_outside_the_range_warns():
    model = _small_oscillator()
    _, test = oscillator_data(amplitudes=(1.2,), steps=60)
    out = ldft.serve(model, test[0].isel(t=slice(0, 2)), slices=60)
    assert out.complete
    summary = out.extrapolation_summary()
    assert summary["first_slice"] == 0 and summary["max"]["mean"] == pytest.approx((1.2 - 0.8) / 1.6, rel=0.05)
    assert _one_line(out.warnings[0]).startswith("extrapolation: the served field leaves the training range")
    assert out.to_dict()["warnings"] == out.warnings


def test_extrapolation_labels_of_a_vector_field_in_2d():
    from latticedft._serve._range import feature_labels

    model = ldft.PolynomialLagrangian((2, 2))
    model.bind(3, 2, (0.1, 0.1, 0.1), ("x", "y"))
    labels = feature_labels(model, ("t", "y", "x"), ("x", "y"))
    assert labels[:2] == ["mean[x]", "mean[y]"] and labels[-1] == "d_x[y]" and len(labels) == 8


def test_cli_extrapolation_goes_to_the_task_file_and_the_summary(tmp_path, capsys):
    case = oscillator_case(tmp_path)  # task `outside` starts at 3.0, far outside training amplitudes 0.6, 1.2
    out = tmp_path / "out"
    code, _, err = run_cli(capsys, "run", case, "--out", out, *NO_EXPORT)
    summary = json.loads((out / "summary.json").read_text())
    outside, inside = summary["tasks"]["outside"], summary["tasks"]["inside"]
    assert code == (0 if outside["complete"] else 3)
    assert outside["extrapolation"]["first_slice"] == 0 and outside["extrapolation"]["max"]["mean"] > 0.5
    assert outside["warnings"][0].startswith("extrapolation:")
    assert inside["warnings"] == [] and inside["extrapolation"]["first_slice"] is None
    assert "latticedft: warning: task outside: extrapolation:" in err
    assert "task outside: extrapolation:" in (out / "run.log").read_text()
    assert [w for w in summary["warnings"] if w.startswith("task outside: extrapolation")]
    with xr.open_dataset(out / "outside.nc", engine="netcdf4") as ds:
        ext = ds["extrapolation"].load()
        assert ext.dims == ("t", "feature") and list(ext["feature"].values) == ["mean", "d_t"]
        assert ext.sizes["t"] == ds["psi"].sizes["t"] and float(ext.max()) > 0.5
        assert json.loads(ds.attrs["latticedft_warnings"])[-1].startswith("extrapolation:")
        if not outside["complete"]:  # the partial field says so
            assert ds.attrs["latticedft_complete"] == "false"
            assert int(ds.attrs["latticedft_stopped_at_slice"]) == ds["psi"].sizes["t"] == outside["slices"]
            assert ds.attrs["latticedft_stop_reason"] == outside["stop_reason"]
    inside_attrs = _attrs(out / "inside.nc")
    assert inside_attrs["latticedft_complete"] == "true" and json.loads(inside_attrs["latticedft_warnings"]) == []
    assert "latticedft_stopped_at_slice" not in inside_attrs


def test_cli_serve_stage_keeps_the_model_warnings(tmp_path, capsys):
    case = oscillator_case(tmp_path)
    out = tmp_path / "out"
    run_cli(capsys, "run", case, "--out", out, "--set", "model.orders=[2,0]", *NO_EXPORT)
    run_cli(capsys, "serve", case, "--out", out, *NO_EXPORT[:4])
    summary = json.loads((out / "summary.json").read_text())
    assert summary["stage"] == "serve" and any(w.startswith("poor fit") for w in summary["warnings"])
    assert any(w.startswith("poor fit") for w in json.loads(_attrs(out / "inside.nc")["latticedft_warnings"]))


# -- 5. the Python API raises the library's own exceptions -------------------------------------------------------


@pytest.fixture(scope="module")
def learned():
    _, data = oscillator_data(amplitudes=(0.4, 0.8), steps=30)
    model = ldft.PolynomialLagrangian((2, 2))
    ldft.learn(model, data)
    return model, data


def _mlp():
    return ldft.MLPLagrangian(hidden=[4])


BAD_CALLS = {
    # learn
    "learn: lr < 0": (lambda m, d: ldft.learn(_mlp(), d, optimizer="adam", lr=-1), "lr"),
    "learn: lr not a number": (lambda m, d: ldft.learn(_mlp(), d, lr="fast"), "lr"),
    "learn: max_time < 0": (lambda m, d: ldft.learn(_mlp(), d, max_time=-1), "max_time"),
    "learn: tol < 0": (lambda m, d: ldft.learn(_mlp(), d, tol=-1.0), "tol"),
    "learn: rel_tol 0": (lambda m, d: ldft.learn(_mlp(), d, rel_tol=0), "rel_tol"),
    "learn: penalty nan": (lambda m, d: ldft.learn(_mlp(), d, penalty=float("nan")), "penalty"),
    "learn: max_iter bool": (lambda m, d: ldft.learn(_mlp(), d, max_iter=True), "max_iter"),
    "learn: progress": (lambda m, d: ldft.learn(ldft.PolynomialLagrangian((2, 2)), d, progress="yes"), "progress"),
    "learn: optimizer": (lambda m, d: ldft.learn(ldft.PolynomialLagrangian((2, 2)), d, optimizer="sgd"), "optimizer"),
    "learn: model": (lambda m, d: ldft.learn("polynomial", d), "model"),
    "learn: data": (lambda m, d: ldft.learn(ldft.PolynomialLagrangian((2, 2)), None), "data"),
    "learn: time dim not first": (
        lambda m, d: ldft.learn(ldft.PolynomialLagrangian((2, 2)), systems.wave_string([(1, 1.0)], 9, 9).T),
        "the time dim 't' is in place 2",
    ),
    # diagnose
    "diagnose: model": (lambda m, d: ldft.diagnose(None, d), "model"),
    "diagnose: unbound": (lambda m, d: ldft.diagnose(ldft.PolynomialLagrangian((2, 2)), d), "not bound"),
    "diagnose: gauge": (lambda m, d: ldft.diagnose(m, d, gauge="unit"), "gauge"),
    # serve
    "serve: max_newton 0": (lambda m, d: ldft.serve(m, d[0], max_newton=0), "max_newton"),
    "serve: max_newton 0, n-D": (
        lambda m, d: ldft.serve(ldft.lagrangians.wave(), wave_field(nx=9, nt=5), max_newton=0, affine=False),
        "max_newton",
    ),
    "serve: affine": (lambda m, d: ldft.serve(m, d[0], affine="no"), "affine"),
    "serve: progress": (lambda m, d: ldft.serve(m, d[0], progress=1), "progress"),
    "serve: init": (lambda m, d: ldft.serve(m, np.zeros(4)), "init"),
    "serve: slices beyond the memory": (lambda m, d: ldft.serve(m, d[0], slices=10**12), "slices"),
    "serve: time dim not first": (
        lambda m, d: ldft.serve(m, d[0].expand_dims(x=[0.0, 1.0]).transpose("x", "t")),
        "the time dim 't' is in place 2",
    ),
    "serve: model": (lambda m, d: ldft.serve(None, d[0]), "model"),
    "serve: box": (lambda m, d: ldft.serve(m, d[0], box=True), "box"),
    # compare
    "compare: numpy": (lambda m, d: ldft.compare(np.zeros(3), d[0]), "pred"),
    "compare: None": (lambda m, d: ldft.compare(d[0], None), "ref"),
    "compare: another lattice": (lambda m, d: ldft.compare(d[0], wave_field(nx=9, nt=5)), "shapes"),
    # del_residual and action
    "del_residual: None": (lambda m, d: ldft.del_residual(m, None), "field"),
    "del_residual: model": (lambda m, d: ldft.del_residual("model", d[0]), "model"),
    "del_residual: unbound": (lambda m, d: ldft.del_residual(ldft.PolynomialLagrangian((2, 2)), d[0]), "not bound"),
    "action: numpy": (lambda m, d: ldft.action(m, np.zeros((5, 1)), (0.1,), (False,)), "psi"),
    "action: shape": (lambda m, d: ldft.action(m, torch.zeros(5, dtype=torch.float64), (0.1,), (False,)), "psi"),
    "action: spacing": (
        lambda m, d: ldft.action(m, torch.zeros(5, 1, dtype=torch.float64), (-1.0,), (False,)),
        "spacing",
    ),
    "action: periodic": (lambda m, d: ldft.action(m, torch.zeros(5, 1, dtype=torch.float64), (0.1,), None), "periodic"),
    # model files
    "save_model: missing folder": (
        lambda m, d: ldft.save_model(m, "/nonexistent-folder/sub/model.pt"),
        "does not exist",
    ),
    "save_model: model": (lambda m, d: ldft.save_model("model", "model.pt"), "model"),
    "save_model: path": (lambda m, d: ldft.save_model(m, None), "path"),
    "load_model: path": (lambda m, d: ldft.load_model(3), "path"),
    "load_model: missing": (lambda m, d: ldft.load_model("/nonexistent-folder/model.pt"), "not found"),
    # model constructors
    "PolynomialLagrangian: orders": (lambda m, d: ldft.PolynomialLagrangian(orders=(2,)), "orders"),
    "PolynomialLagrangian: time_symmetric": (
        lambda m, d: ldft.PolynomialLagrangian(time_symmetric="yes"),
        "time_symmetric",
    ),
    "PolynomialLagrangian: stencil": (lambda m, d: ldft.PolynomialLagrangian(stencil=[[0], [1]]), "stencil"),
    "MLPLagrangian: hidden": (lambda m, d: ldft.MLPLagrangian(hidden=[0]), "hidden"),
    "MLPLagrangian: scale": (lambda m, d: ldft.MLPLagrangian(scale="on"), "scale"),
    "MLPLagrangian: preset": (lambda m, d: ldft.MLPLagrangian(preset="huge"), "preset"),
    "AnalyticLagrangian: fn": (lambda m, d: ldft.AnalyticLagrangian(3), "fn"),
    "AnalyticLagrangian: name": (lambda m, d: ldft.AnalyticLagrangian(lambda c, h: c.sum((-1, -2)), name=3), "name"),
    "Stencil: offsets": (lambda m, d: ldft.Stencil([[0], [2]]), "stencil"),
    # field files
    "read_field: path": (lambda m, d: io.read_field(None), "path"),
    "read_field: missing": (lambda m, d: io.read_field("/nonexistent-folder/f.nc"), "not found"),
    "read_field: components": (lambda m, d: io.read_field(WAVE / "data" / "train.nc", components=3), "components"),
    "write_field: not a DataArray": (lambda m, d: io.write_field("f.nc", {"psi": np.zeros(3)}), "fields"),
    "write_field: missing folder": (lambda m, d: io.write_field("/nonexistent-folder/f.nc", {"psi": d[0]}), "folder"),
    "write_field: attrs": (lambda m, d: io.write_field("f.nc", {"psi": d[0]}, attrs=["a"]), "attrs"),
    "as_lattice_field: None": (lambda m, d: ldft.as_lattice_field(None), "DataArray"),
}


@pytest.mark.parametrize("name", sorted(BAD_CALLS))
def test_bad_api_arguments_raise_one_line_library_errors(name, learned, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # relative paths of the table land here
    call, needle = BAD_CALLS[name]
    model, data = learned
    with pytest.raises(ldft.LatticeDFTError) as err:
        call(model, data)
    assert needle in _one_line(str(err.value)), (name, str(err.value))


def test_del_residual_accepts_a_dataarray(learned):
    model, data = learned
    el = ldft.del_residual(model, data[0])
    assert torch.equal(el, ldft.del_residual(model, ldft.as_lattice_field(data[0])))


def test_partial_results_of_the_api_carry_their_extrapolation():
    model = _small_oscillator()
    init = series([3.0, 3.0], model.spacing[0])
    try:
        out = ldft.serve(model, init, slices=40)
    except ldft.ServeError as err:
        out = err.result
    assert out.extrapolation is not None and out.extrapolation.sizes["t"] == out.slices
    assert out.warnings and out.warnings[0].startswith("extrapolation")
