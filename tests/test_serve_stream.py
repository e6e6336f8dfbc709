"""Serving with an output cadence (``every``): the kept slices equal whole-field serving's."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import xarray as xr

import latticedft as ldft
from latticedft import lagrangians
from latticedft._serve import _stream

from case_helpers import run_wave_every
from helpers import membrane_field, oscillator_data, series, wave_field


def _sine_gordon():
    def fn(c, h):
        u = c[..., 0, 0]
        return 0.5 * ((c[..., 1, 0] - u) / h[0]) ** 2 - 0.5 * ((c[..., 2, 0] - u) / h[1]) ** 2 - (1 - torch.cos(u))

    return ldft.AnalyticLagrangian(fn, name="sine-Gordon")


def _coupled_strings():
    """Two strings on one lattice, coupled through a quartic term: a vector field the DEL of which is not affine."""

    def fn(c, h):
        u, v = c[..., 0, 0], c[..., 0, 1]
        kin = sum(0.5 * ((c[..., 1, k] - c[..., 0, k]) / h[0]) ** 2 for k in range(2))
        grad = sum(0.5 * ((c[..., 2, k] - c[..., 0, k]) / h[1]) ** 2 for k in range(2))
        return kin - grad - 0.5 * u**2 - 0.5 * v**2 - 0.1 * (u * v) ** 2

    return ldft.AnalyticLagrangian(fn, name="coupled strings")


def _vector_field(nx: int = 17, nt: int = 30) -> xr.DataArray:
    f = wave_field(nx=nx, nt=nt, modes=((1, 0.5),))
    g = wave_field(nx=nx, nt=nt, modes=((2, 0.3),))
    return xr.concat([f, g], dim="component").assign_coords(component=["u", "v"]).transpose("t", "x", "component")


def _assert_kept_equal(full: ldft.ServeResult, thin: ldft.ServeResult, every: int) -> None:
    n = full.field.sizes["t"]
    idx = _stream.kept_slices(n, every)
    assert thin.field["slice"].values.tolist() == idx.tolist()
    assert thin.field.attrs["latticedft_every"] == every
    np.testing.assert_array_equal(thin.field["t"].values, full.field["t"].values[idx])
    np.testing.assert_array_equal(thin.field.values, full.field.values[idx])  # bit for bit
    assert thin.slices == full.slices and thin.complete and full.complete
    assert (thin.solver, thin.newton_iterations, thin.max_newton_iterations) == (
        full.solver,
        full.newton_iterations,
        full.max_newton_iterations,
    )
    assert thin.max_residual == full.max_residual


@pytest.mark.parametrize(
    "model, field, boundary, every",
    [
        (lagrangians.wave(1.0), wave_field(nx=33, nt=61), "dirichlet", 7),  # affine recurrence
        (lagrangians.wave(1.0), wave_field(nx=32, nt=61), "periodic", 10),
        (_sine_gordon(), wave_field(nx=17, nt=23), "dirichlet", 4),  # slice-Newton
        (_sine_gordon(), wave_field(nx=16, nt=23), "periodic", 5),
        (lagrangians.wave(1.0), membrane_field(n=10, nt=30), "dirichlet", 3),  # 2+1D
        (_sine_gordon(), membrane_field(n=8, nt=14), "periodic", 4),
        (_coupled_strings(), _vector_field(), "dirichlet", 6),  # vector field
    ],
)
def test_cadenced_serving_equals_full_serving_on_the_kept_slices(model, field, boundary, every):
    ldft.set_options(serve_window_bytes=1)  # a window of a few slices: many refills
    full = ldft.serve(model, field, boundary=boundary)
    thin = ldft.serve(model, field, boundary=boundary, every=every)
    _assert_kept_equal(full, thin, every)
    if full.extrapolation is not None:
        xr.testing.assert_identical(full.extrapolation, thin.extrapolation)


def test_sweep_and_affine_handover_are_served_the_same_with_a_cadence():
    ldft.set_options(serve_window_bytes=1)
    field = wave_field(nx=17, nt=15)
    full = ldft.serve(_sine_gordon(), field, mode="sweep")
    _assert_kept_equal(full, ldft.serve(_sine_gordon(), field, mode="sweep", every=3), 3)

    def kg_kink(c, h):  # affine below psi = 0.6, not above: the recurrence hands over to Newton mid-run
        u = c[..., 0, 0]
        return (
            0.5 * ((c[..., 1, 0] - u) / h[0]) ** 2
            - 0.5 * ((c[..., 2, 0] - u) / h[1]) ** 2
            - 0.5 * u**2
            + 3.0 * torch.relu(u - 0.6) ** 3
        )

    field = wave_field(nx=33, nt=80, modes=((1, 0.45),))
    field[1] = field[0] * 1.02
    model = ldft.AnalyticLagrangian(kg_kink)
    full = ldft.serve(model, field, boundary="periodic")
    thin = ldft.serve(model, field, boundary="periodic", every=9)
    assert full.solver == "affine+newton"
    _assert_kept_equal(full, thin, 9)


def test_1d_trajectories_are_thinned_to_the_kept_slices():
    truth, fields = oscillator_data(steps=50)
    inits = [f.isel(t=slice(0, 2)) for f in fields]
    full = ldft.serve(truth, inits, slices=50)
    thin = ldft.serve(truth, inits, slices=50, every=8)
    for a, b in zip(full, thin):
        _assert_kept_equal(a, b, 8)


def test_on_slice_sees_each_kept_slice_in_order():
    field = membrane_field(n=8, nt=25)
    seen: list[tuple[int, np.ndarray]] = []
    out = ldft.serve(lagrangians.wave(1.0), field, every=5, on_slice=lambda i, v: seen.append((i, v.copy())))
    assert [i for i, _ in seen] == [0, 5, 10, 15, 20, 24]
    for k, (_, v) in enumerate(seen):
        np.testing.assert_array_equal(v, out.field.values[k])


def test_on_block_sees_every_slice_once():
    field = wave_field(nx=20, nt=40)
    full = ldft.serve(_sine_gordon(), field, boundary="periodic")

    class Sink:
        def __init__(self):
            self.blocks = []

        def __call__(self, index, values):
            pass

        def on_block(self, start, block):
            self.blocks.append((start, block))

    sink = Sink()
    ldft.serve(_sine_gordon(), field, boundary="periodic", every=6, on_slice=sink)
    starts = [s for s, _ in sink.blocks]
    sizes = [b.sizes["t"] for _, b in sink.blocks]
    assert starts[0] == 0 and all(a + n == b for a, n, b in zip(starts, sizes, starts[1:]))
    whole = xr.concat([b for _, b in sink.blocks], dim="t")
    np.testing.assert_array_equal(whole.values, full.field.values)
    np.testing.assert_allclose(whole["t"].values, full.field["t"].values, rtol=0, atol=1e-12)


def test_every_beyond_the_slices_keeps_the_first_and_the_last():
    field = wave_field(nx=17, nt=12)
    out = ldft.serve(lagrangians.wave(1.0), field, every=100)
    assert out.field["slice"].values.tolist() == [0, 11]
    full = ldft.serve(lagrangians.wave(1.0), field)
    np.testing.assert_array_equal(out.field.values, full.field.values[[0, 11]])


@pytest.mark.parametrize("every", [0, -3, 2.0, True, "10"])
def test_invalid_every_is_refused_in_one_line(every):
    with pytest.raises(ldft.InputError, match=r"^every: expected an integer >= 1") as exc:
        ldft.serve(lagrangians.wave(1.0), wave_field(nx=9, nt=5), every=every)
    assert "\n" not in str(exc.value)


def test_invalid_on_slice_is_refused():
    with pytest.raises(ldft.InputError, match=r"^on_slice: expected a function"):
        ldft.serve(lagrangians.wave(1.0), wave_field(nx=9, nt=5), on_slice=3)


def test_a_failed_run_keeps_the_slices_served_and_the_last_one():
    field = wave_field(nx=17, nt=40)
    model = ldft.AnalyticLagrangian(lambda c, h: 0.5 * ((c[..., 1, 0] - c[..., 0, 0]) / h[0]) ** 2 * 0.0)
    with pytest.raises(ldft.ServeError) as full_err:
        ldft.serve(model, field)
    with pytest.raises(ldft.ServeError) as thin_err:
        ldft.serve(model, field, every=3)
    assert str(full_err.value) == str(thin_err.value)
    part = thin_err.value.result
    assert not part.complete and part.field["slice"].values[-1] == full_err.value.result.slices - 1


def test_dirichlet_strips_are_needed_on_every_slice():
    field = membrane_field(n=8, nt=10)
    with pytest.raises(ldft.InputError, match="strips on all 30 slices"):
        ldft.serve(lagrangians.wave(1.0), field, slices=30, every=4)


def test_periodic_cadence_from_two_slices():
    field = wave_field(nx=32, nt=50)
    two = field.isel(t=slice(0, 2))
    full = ldft.serve(lagrangians.wave(1.0), two, boundary="periodic", slices=50)
    thin = ldft.serve(lagrangians.wave(1.0), two, boundary="periodic", slices=50, every=7)
    _assert_kept_equal(full, thin, 7)
    assert series is not None


# -- a case task with every ------------------------------------------------------------------------------------


def test_a_case_task_with_every_keeps_the_slices_and_the_errors_of_every_1(tmp_path, capsys):
    whole, whole_ds = run_wave_every(tmp_path, capsys, 1)
    thin, thin_ds = run_wave_every(tmp_path, capsys, 7)
    idx = _stream.kept_slices(60, 7)
    assert (whole["every"], whole["kept_slices"]) == (1, 60)
    assert (thin["every"], thin["kept_slices"]) == (7, len(idx))
    assert thin_ds["slice"].values.tolist() == idx.tolist()
    # the file holds the kept slices of the whole-field file, variable by variable
    for name in ("psi", "psi_ref", "psi_err", "baseline_err_max", "baseline_err_rms", "extrapolation"):
        if name in whole_ds:
            np.testing.assert_array_equal(thin_ds[name].values, whole_ds[name].isel(t=idx).values, err_msg=name)
    # the invariant is evaluated on windows of slices: the time step is read from each window's coordinate
    np.testing.assert_allclose(thin_ds["invariant"].values, whole_ds["invariant"].isel(t=idx).values, rtol=1e-13)
    assert set(thin_ds.data_vars) == set(whole_ds.data_vars)
    # errors, invariant drift and extrapolation measured on every slice, not on the kept ones
    assert thin["max_error"] == whole["max_error"] and thin["compared_slices"] == whole["compared_slices"]
    assert thin["rms_error"] == pytest.approx(whole["rms_error"], rel=1e-12)  # summed in another order
    assert thin["invariant_drift"] == pytest.approx(whole["invariant_drift"], rel=1e-9, abs=1e-15)
    assert thin["extrapolation"] == whole["extrapolation"]
    assert thin["baseline"] == whole["baseline"]


def test_every_with_charges_is_refused_at_check(tmp_path, capsys):
    from case_helpers import copy_wave, run_cli

    case = copy_wave(tmp_path)
    code, _, err = run_cli(
        capsys, "check", case, "--set", "serve.test.every=10", "--set", 'serve.test.charges=["energy"]'
    )
    assert code != 0
    assert "serve[0].every: the Noether charges" in err and len(err.strip().splitlines()) == 1


@pytest.mark.parametrize("value", ["0", "2.5", '"ten"'])
def test_invalid_every_in_the_case_file_is_refused(tmp_path, capsys, value):
    from case_helpers import copy_wave, run_cli

    case = copy_wave(tmp_path)
    code, _, err = run_cli(capsys, "check", case, "--set", f"serve.test.every={value}")
    assert code != 0 and "every" in err and "positive integer" in err


def test_a_killed_cadenced_run_leaves_a_readable_part_file(tmp_path):
    import os
    import subprocess
    import sys
    from pathlib import Path

    from case_helpers import FAST, copy_wave

    case = copy_wave(tmp_path)
    repo = Path(__file__).resolve().parents[1]
    env = dict(os.environ, LATTICEDFT_FAULT="kill:slice", OMP_NUM_THREADS="1")
    env["PYTHONPATH"] = os.pathsep.join([str(repo), *filter(None, [os.environ.get("PYTHONPATH")])])
    argv = ["run", case, "-q", *FAST, "--set", "serve.test.every=7", "--set", "export.formats=[]"]
    proc = subprocess.run(
        [sys.executable, "-m", "latticedft", *map(str, argv)], env=env, capture_output=True, text=True, check=False
    )
    assert proc.returncode == -9, proc.stderr[-2000:]  # killed at the first kept slice appended
    assert not (case / "results").exists()
    (part,) = case.glob("results.tmp-*/.test.nc.part")
    with xr.open_dataset(part, engine="netcdf4", decode_times=False) as ds:
        psi = ds["psi"].load()
    assert psi["slice"].values.tolist() == [0] and psi.attrs == {} and ds.attrs["latticedft_every"] == 7
    with xr.open_dataset(case / "data" / "test.nc", engine="netcdf4", decode_times=False) as data:
        np.testing.assert_array_equal(psi.values[0], data["psi"].values[0])
        np.testing.assert_array_equal(psi["x"].values, data["x"].values)


def test_a_finished_cadenced_run_leaves_no_part_file(tmp_path, capsys):
    run_wave_every(tmp_path, capsys, 5)
    assert not list(tmp_path.rglob("*.part"))


@pytest.mark.parametrize("appended", [4, 3, 0])
def test_a_completed_part_file_is_the_file_written_whole(tmp_path, appended):
    """The part file completed into ``<task>.nc`` holds what ``write_task`` writes whole, bit for bit: with
    every kept slice appended, without the last one (a task stopped between two kept slices), or none."""
    from latticedft import systems
    from latticedft._part_file import PartFile
    from latticedft._results import write_task

    template = systems.wave_string([(1, 1.0)], nx=9, nt=12)
    idx = np.array([0, 3, 6, 8])
    pred = template.isel(t=idx).assign_coords(slice=("t", idx, {"long_name": "time slice index"}))
    pred.attrs = {**pred.attrs, "latticedft_every": 3, "source": "served"}
    ref = template.isel(t=slice(0, 9))
    inv = xr.DataArray(np.arange(4.0), dims="t", coords={"t": pred["t"].values}, name="invariant")
    kw = dict(attrs={"latticedft_task": "test", "latticedft_complete": "false"}, history="h", steps=12)
    whole = write_task(tmp_path, "whole", "psi", pred, ref, inv, **kw)
    part = PartFile(tmp_path, "test", "psi", template, 3)
    for k in range(appended):
        part(int(idx[k]), template.values[idx[k]])
    part.close()
    done = write_task(tmp_path, "test", "psi", pred, ref, inv, part=part.path, **kw)
    assert done == tmp_path / "test.nc" and not part.path.exists()
    with xr.open_dataset(whole, decode_times=False) as a, xr.open_dataset(done, decode_times=False) as b:
        assert b["psi"].encoding["chunksizes"] == (1, 9)  # the part file's variable, completed in place
        a.attrs.pop("history"), b.attrs.pop("history")
        xr.testing.assert_identical(a.load(), b.load())
