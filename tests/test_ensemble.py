"""Ensembles: members on resamples of the data, served together, with an error bar that is calibrated."""

from __future__ import annotations

import copy
import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
import xarray as xr

import latticedft as ldft
from latticedft import systems
from latticedft._action import cell_derivatives
from latticedft._case import load_case
from latticedft._learn._ensemble import time_windows
from latticedft._learn._source import as_sources
from latticedft._models._ensemble import stacked
from latticedft._serve._fast1d import numpy_derivatives_of

from case_helpers import run_cli, tiny_wave
from helpers import oscillator_data


@pytest.fixture
def stacked_run(monkeypatch: pytest.MonkeyPatch) -> None:
    """The stacked run of an n-D polynomial ensemble forced (``MEMBERWISE`` off; its members are served one by
    one otherwise), for the tests of its own machinery."""
    import latticedft._serve._ensemble as ensemble_serving

    monkeypatch.setattr(ensemble_serving, "MEMBERWISE", False)


@pytest.fixture(scope="module")
def quartic() -> ldft.EnsembleLagrangian:
    """A quartic oscillator learned with a polynomial that cannot hold it exactly (a fit with an error)."""
    _, train = oscillator_data(amplitudes=(0.3, 0.6, 0.9), steps=120)
    ens = ldft.EnsembleLagrangian(ldft.PolynomialLagrangian((2, 6)), members=5, seed=0)
    ldft.learn(ens, train)
    return ens


@pytest.fixture(scope="module")
def paper() -> ldft.EnsembleLagrangian:
    """The paper's oscillator (Qin 2020, Example 1) with its 45-term polynomial, 5 members."""
    train = [systems.oscillator_sin(a) for a in (1.2, 0.8, 0.4)]
    ens = ldft.EnsembleLagrangian(ldft.PolynomialLagrangian((4, 8)), members=5, seed=0)
    ldft.learn(ens, train)
    return ens


def test_members_differ_and_member_0_is_the_plain_model(quartic: ldft.EnsembleLagrangian) -> None:
    _, train = oscillator_data(amplitudes=(0.3, 0.6, 0.9), steps=120)
    plain = ldft.PolynomialLagrangian((2, 6))
    ldft.learn(plain, train)
    coefs = [quartic.member(k).coef.detach() for k in range(len(quartic))]
    assert torch.equal(coefs[0], plain.coef.detach())
    for k in range(1, len(coefs)):
        assert not torch.allclose(coefs[k], coefs[0], rtol=1e-6, atol=0)
    assert quartic.report_.ensemble["members"] == 5 and len(quartic.report_.ensemble["rel_res"]) == 5


def test_learn_ensemble_keyword(tmp_path: Path) -> None:
    _, train = oscillator_data(amplitudes=(0.3, 0.9), steps=60)
    model = ldft.PolynomialLagrangian((2, 4))
    report = ldft.learn(model, train, ensemble=3, ensemble_seed=4)
    ens = model.ensemble_
    assert isinstance(ens, ldft.EnsembleLagrangian) and ens.member(0) is model and ens.seed == 4
    assert report.ensemble["members"] == 3 and model.report_ is report
    with pytest.raises(ldft.InputError, match="^ensemble: expected an integer >= 2"):
        ldft.learn(ldft.PolynomialLagrangian((2, 4)), train, ensemble=1)
    with pytest.raises(ldft.InputError, match="^members: expected an integer >= 2"):
        ldft.EnsembleLagrangian(ldft.PolynomialLagrangian((2, 4)), members=1)


@pytest.mark.parametrize("cells_per_call", [1, 7, 300])  # 300: from _MANY_CELLS each member on its own
def test_stacked_polynomials_evaluate_together_as_their_closed_forms(
    paper: ldft.EnsembleLagrangian, cells_per_call: int
) -> None:
    """The numpy forms of a stacked ensemble of polynomials (all members in one batched product) equal the
    members' torch closed forms side by side, blocks on the diagonal and zero elsewhere; also for a vector
    field. Serving an ensemble of polynomials takes them."""
    orbit = systems.kepler_orbit(1.0, 0.9, n=80)
    planar = ldft.EnsembleLagrangian(ldft.PolynomialLagrangian((2, 4)), members=3, seed=1)
    ldft.learn(planar, [orbit])
    rng = np.random.default_rng(cells_per_call)
    pairs = [(0, 1), (0, 0), (1, 1)]
    for ens in (paper, planar):
        model = stacked(ens, tuple(f"c{i}" for i in range(len(ens) * ens.m)))
        form = model.numpy_derivatives(pairs)
        assert form is not None and form.__qualname__.startswith("stacked_numpy_derivatives")
        assert numpy_derivatives_of(model) is not None  # 1D serving runs the numpy loop
        cells = rng.uniform(-1.0, 1.0, (cells_per_call, 2, model.m))
        grad, blocks = form(cells)
        tgrad, tblocks = model.fast_derivatives(torch.tensor(cells), pairs)
        np.testing.assert_allclose(grad, tgrad.numpy(), rtol=0, atol=1e-11)
        for q, pair in enumerate(pairs):
            np.testing.assert_allclose(blocks[q], tblocks[pair].numpy(), rtol=0, atol=1e-11)
            mask = np.kron(np.eye(len(ens)), np.ones((ens.m, ens.m))) == 0
            assert not blocks[q][:, mask].any()


def test_stacked_networks_evaluate_together_as_one_by_one() -> None:
    """An ensemble of MLPs is evaluated by one vectorised call over its members: its L_d, gradient and
    block-diagonal Hessian blocks equal the members' own side by side, and serving it equals serving each
    member alone."""
    orbit = systems.kepler_orbit(1.0, 0.9, n=60)
    model = ldft.MLPLagrangian(preset="radial", hidden=[8])
    ldft.learn(model, orbit, progress=False, max_iter=20, ensemble=3)
    ens = model.ensemble_
    st = stacked(ens, tuple(f"c{i}" for i in range(6)))
    assert st._batched is not None
    cells = torch.tensor(np.random.default_rng(3).uniform(0.5, 1.2, (7, 2, 6)))
    pairs = [(0, 1), (0, 0), (1, 1)]
    grad, blocks = st.fast_derivatives(cells, pairs)
    value = st(cells)
    for k in range(3):
        part = cells[..., 2 * k : 2 * k + 2]
        g, b = cell_derivatives(ens.member(k), part, pairs)
        np.testing.assert_allclose(grad[..., 2 * k : 2 * k + 2].numpy(), g.numpy(), rtol=0, atol=1e-12)
        for pair in pairs:
            block = blocks[pair][..., 2 * k : 2 * k + 2, 2 * k : 2 * k + 2]
            np.testing.assert_allclose(block.numpy(), b[pair].numpy(), rtol=0, atol=1e-12)
    loop = sum(ens.member(k)(cells[..., 2 * k : 2 * k + 2]) for k in range(3))
    np.testing.assert_allclose(value.detach().numpy(), loop.detach().numpy(), rtol=0, atol=1e-12)
    out = ldft.serve(ens, orbit, slices=40, progress=False)
    for k in range(3):
        alone = ldft.serve(ens.member(k), orbit, slices=40, progress=False).field.values
        np.testing.assert_allclose(out.members.values[k], alone, rtol=0, atol=1e-12)


@pytest.mark.parametrize("cells_per_call", [1, 7])
def test_high_degree_members_take_their_tables_together_with_the_same_values(cells_per_call: int, monkeypatch) -> None:
    """Above degree 12 (the basis by its recurrence) a stacked ensemble of polynomials evaluates the members'
    basis tables once for all of them: its gradient and blocks equal every member's own closed forms to the bit,
    for a scalar and a planar field, and serving it equals serving it member by member (the tables one member at
    a time), to the bit."""
    import latticedft._models._ensemble as ensemble_module
    from latticedft._models._polynomial import stacked_fast_derivatives

    _, train = oscillator_data(amplitudes=(0.3, 0.6, 0.9), steps=60)
    scalar = ldft.EnsembleLagrangian(ldft.PolynomialLagrangian((2, 14)), members=3, seed=0)
    ldft.learn(scalar, train, ridge=1e-10)
    planar = ldft.EnsembleLagrangian(ldft.PolynomialLagrangian((2, 13)), members=3, seed=1)
    ldft.learn(planar, [systems.kepler_orbit(1.0, 0.9, n=60)], ridge=1e-10)
    rng = np.random.default_rng(cells_per_call)
    pairs = [(0, 1), (0, 0), (1, 1)]
    for ens in (scalar, planar):
        m, n = ens.m, len(ens)
        model = stacked(ens, tuple(f"c{i}" for i in range(n * m)))
        cells = torch.tensor(rng.uniform(-1.0, 1.0, (cells_per_call, 2, n * m)))
        parts = [cells[..., k * m : (k + 1) * m] for k in range(n)]
        assert stacked_fast_derivatives([ens.member(k) for k in range(n)], parts, pairs) is not None
        grad, blocks = model.fast_derivatives(cells, pairs)
        for k in range(n):
            g, b = ens.member(k).fast_derivatives(parts[k], pairs)
            assert torch.equal(grad[..., k * m : (k + 1) * m], g)
            for pair in pairs:
                assert torch.equal(blocks[pair][..., k * m : (k + 1) * m, k * m : (k + 1) * m], b[pair])
    together = ldft.serve(scalar, train[2], slices=40, progress=False)
    monkeypatch.setattr(ensemble_module, "stacked_fast_derivatives", lambda *args: None)
    one_by_one = ldft.serve(scalar, train[2], slices=40, progress=False)
    assert together.slices == one_by_one.slices == 40
    assert np.array_equal(together.members.values, one_by_one.members.values)
    assert np.array_equal(together.std.values, one_by_one.std.values)


def test_windows_hold_every_equation_once() -> None:
    _, train = oscillator_data(amplitudes=(0.3, 0.9), steps=57)
    windows = time_windows(as_sources(train, None), 1)
    assert len(windows) == 2 * 5
    owned = sum(w.nt - 2 for w in windows)  # first-order stencil: every slice but the first and last
    assert owned == 2 * (57 - 2)


def test_batched_serve_equals_members_one_by_one(quartic: ldft.EnsembleLagrangian) -> None:
    _, (ref,) = oscillator_data(amplitudes=(0.75,), steps=120)
    out = ldft.serve(quartic, ref)
    assert out.complete and out.members.sizes["member"] == 5
    for k in range(len(quartic)):
        alone = ldft.serve(quartic.member(k), ref).field.values
        np.testing.assert_allclose(out.members.values[k], alone, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(out.field.values, out.members.values[0])
    np.testing.assert_allclose(out.std.values, out.members.values.std(axis=0, ddof=1))
    ds = out.to_dataset()
    assert set(ds.data_vars) == {"psi", "psi_mean", "psi_std"}


def test_batched_serve_in_1p1d() -> None:
    train = systems.wave_string([(1, 1.0), (2, 0.4)], nx=13, nt=40)
    test = systems.wave_string([(1, 0.5, 0.3), (3, 0.2)], nx=13, nt=30)
    ens = ldft.EnsembleLagrangian(ldft.PolynomialLagrangian((2, 2)), members=3, seed=2)
    ldft.learn(ens, train)
    out = ldft.serve(ens, test)
    for k in range(3):
        alone = ldft.serve(ens.member(k), test).field.values
        np.testing.assert_allclose(out.members.values[k], alone, rtol=0, atol=1e-9)


def test_spread_grows_outside_the_training_range(quartic: ldft.EnsembleLagrangian) -> None:
    _, (inside,) = oscillator_data(amplitudes=(0.75,), steps=120)
    _, (outside,) = oscillator_data(amplitudes=(1.5,), steps=120)
    s_in = float(ldft.serve(quartic, inside).std.mean())
    s_out = float(ldft.serve(quartic, outside).std.mean())
    assert s_out > 20 * s_in > 0


def test_coverage_on_the_paper_oscillator(paper: ldft.EnsembleLagrangian) -> None:
    """Inside the training range the error of the served field lies within 3 std on (nearly) every slice."""
    for a in (1.0, 0.6):
        ref = systems.oscillator_sin(a)
        out = ldft.serve(paper, ref)
        cal = ldft.calibration(out.field, out.std, ref)
        assert cal["slices"] == 49
        assert cal["within_3std"] >= 0.9, (a, cal)
        assert 0.5 < cal["std_over_error"] < 50, (a, cal)


def test_calibration_counts_slices() -> None:
    t = np.arange(7.0)
    ref = xr.DataArray(np.zeros(7), dims="t", coords={"t": t})
    pred = ref.copy(data=[0, 0, 1.0, 1.0, 2.5, 1.0, np.nan])
    cal = ldft.calibration(pred, ref + 1.0, ref)
    assert cal["slices"] == 4 and cal["within_2std"] == 0.75 and cal["within_3std"] == 1.0
    assert cal["std_over_error"] == pytest.approx(1 / 1.375)


def test_model_file_round_trip(quartic: ldft.EnsembleLagrangian, tmp_path: Path) -> None:
    path = ldft.save_model(quartic, tmp_path / "ens.pt")
    back = ldft.load_model(path)
    assert isinstance(back, ldft.EnsembleLagrangian) and len(back) == 5
    for k in range(5):
        assert torch.equal(back.member(k).coef, quartic.member(k).coef)
    assert torch.equal(back.trained_range(), quartic.trained_range())
    _, (ref,) = oscillator_data(amplitudes=(0.75,), steps=40)
    np.testing.assert_array_equal(ldft.serve(back, ref).std.values, ldft.serve(quartic, ref).std.values)


def test_case_keys_are_validated(tmp_path: Path) -> None:
    case = tiny_wave(tmp_path)
    text = (case / "case.toml").read_text()
    (case / "case.toml").write_text(text.replace('data = ["data/train.nc"]', 'data = ["data/train.nc"]\nensemble = 1'))
    with pytest.raises(ldft.ConfigError, match=r"train\.ensemble.*integer >= 2"):
        load_case(case)
    with pytest.raises(ldft.ConfigError, match=r"train\.ensemble_seed"):
        load_case(case, ["train.ensemble=3", "train.ensemble_seed=-1"])
    assert load_case(case, ["train.ensemble=3"]).train.learn["ensemble"] == 3


def test_run_writes_the_spread(tmp_path: Path, capsys) -> None:
    case = tiny_wave(tmp_path)
    text = (case / "case.toml").read_text()
    (case / "case.toml").write_text(text.replace('data = ["data/train.nc"]', 'data = ["data/train.nc"]\nensemble = 3'))
    code, _, err = run_cli(capsys, "run", case)
    assert code == 0, err
    res = case / "results"
    with xr.open_dataset(res / "test.nc") as ds:
        assert {"psi", "psi_mean", "psi_std", "psi_ref"} <= set(ds.data_vars)
        assert ds["psi_std"].dims == ds["psi"].dims
    summary = json.loads((res / "summary.json").read_text())
    task = summary["tasks"]["test"]
    assert task["ensemble_members"] == 3
    assert set(task["calibration"]) >= {"within_2std", "within_3std", "std_over_error", "slices"}
    assert summary["train"]["ensemble"]["members"] == 3
    pyvista = pytest.importorskip("pyvista")
    frame = sorted(res.glob("test_*.vtr"))[1]
    assert "psi_std" in pyvista.read(frame).point_data
    assert (res / "test.png").is_file()
    back = ldft.load_model(res / "model.pt")
    assert isinstance(back, ldft.EnsembleLagrangian)


def test_bad_calibration_warns(tmp_path: Path) -> None:
    """A spread far below the error: the task is flagged in the record a run writes."""
    t = np.arange(10.0)
    ref = xr.DataArray(np.zeros(10), dims="t", coords={"t": t})
    from latticedft._serve._ensemble import calibration_warning

    cal = ldft.calibration(ref + 1.0, ref + 0.01, ref)
    assert cal["within_2std"] == 0.0
    assert "calibration:" in calibration_warning(cal)
    assert calibration_warning(ldft.calibration(ref + 1.0, ref + 1.0, ref)) is None


def _broken(ens: ldft.EnsembleLagrangian, *members: int) -> ldft.EnsembleLagrangian:
    """A copy of ``ens`` whose ``members`` are degenerate (L_d = 0: a singular mixed Hessian from the first step)."""
    out = copy.deepcopy(ens)
    with torch.no_grad():
        for k in members:
            out.member(k).coef.zero_()
    return out


def test_a_member_that_stops_leaves_the_others_served(quartic: ldft.EnsembleLagrangian) -> None:
    """A resampled member that cannot step stops the stacked run; every member is then served alone: member 0
    is the model served alone, the spread is over the members still served, and the result names the member
    that stopped, where and why."""
    broken = _broken(quartic, 2)
    _, (ref,) = oscillator_data(amplitudes=(0.75,), steps=60)
    out = ldft.serve(broken, ref)
    assert out.complete and out.field.sizes["t"] == 60
    np.testing.assert_array_equal(out.field.values, ldft.serve(quartic.member(0), ref).field.values)
    (stop,) = out.members_stopped
    assert stop["member"] == 2 and stop["slice"] == 2 and "singular" in stop["reason"]
    assert out.to_dict()["members_stopped"] == [stop]
    survivors = np.stack([ldft.serve(quartic.member(k), ref).field.values for k in (0, 1, 3, 4)])
    np.testing.assert_allclose(out.std.values[2:], survivors.std(axis=0, ddof=1)[2:], rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(out.mean.values[2:], survivors.mean(axis=0)[2:], rtol=1e-12, atol=1e-15)
    assert np.isfinite(out.std.values).all() and np.isnan(out.members.values[2, 2:]).all()
    (warning,) = [w for w in out.warnings if w.startswith("ensemble:")]
    assert "1 of 5 members stopped: member 2 at slice 2" in warning and "singular" in warning
    assert list(out.std.attrs["stopped_members"]) == [2] and list(out.std.attrs["stopped_at_slice"]) == [2]


def test_fewer_than_two_members_leave_no_spread(quartic: ldft.EnsembleLagrangian) -> None:
    """With one member left the spread is undefined: NaN from the slice where the second-to-last one stopped."""
    _, (ref,) = oscillator_data(amplitudes=(0.75,), steps=40)
    out = ldft.serve(_broken(quartic, 1, 2, 3, 4), ref)
    assert out.complete and [s["member"] for s in out.members_stopped] == [1, 2, 3, 4]
    assert np.isnan(out.std.values[2:]).all() and np.isfinite(out.std.values[:2]).all()
    assert "(NaN: fewer than 2)" in out.warnings[-1]


def test_a_member_that_goes_non_finite_leaves_the_spread() -> None:
    """A member whose field goes non-finite without a ServeError leaves the spread from that slice on."""
    from latticedft._serve._ensemble import _spread, _stops

    rng = np.random.default_rng(0)
    full = rng.normal(size=(4, 8, 3, 1))
    full[1, 5, 2, 0] = np.inf  # one site of one slice is enough
    lost = _stops(full, [""] * 4)
    assert lost == [{"member": 1, "slice": 5, "reason": "its field is not finite there"}]
    mean, std = _spread(full)
    keep = full[[0, 2, 3], 5:]
    np.testing.assert_allclose(std[5:], keep.std(axis=0, ddof=1), rtol=1e-12)
    np.testing.assert_allclose(mean[:5], full[:, :5].mean(axis=0), rtol=1e-12)


def test_batched_serve_reports_the_stop_per_field(quartic: ldft.EnsembleLagrangian) -> None:
    _, refs = oscillator_data(amplitudes=(0.5, 0.75), steps=40)
    outs = ldft.serve(_broken(quartic, 3), list(refs))
    alone = ldft.serve(quartic.member(0), list(refs))
    for out, own in zip(outs, alone, strict=True):
        assert [s["member"] for s in out.members_stopped] == [3] and np.isfinite(out.std.values).all()
        np.testing.assert_array_equal(out.field.values, own.field.values)


def test_every_member_served_reports_none_stopped(quartic: ldft.EnsembleLagrangian) -> None:
    _, (ref,) = oscillator_data(amplitudes=(0.75,), steps=40)
    out = ldft.serve(quartic, ref)
    assert out.members_stopped is None and out.to_dict()["members_stopped"] == []
    assert "stopped_members" not in out.std.attrs and not out.warnings


def test_run_reports_a_member_that_stopped(tmp_path: Path, capsys, monkeypatch) -> None:
    """A run whose ensemble loses a member: the task is complete, the warning is in the console, run.log and
    summary.json (``members_stopped``), ``--strict`` makes the exit status 4, and the spread is written."""
    import latticedft._serve as serving

    real = serving.serve_ensemble

    def breaking(ens, fs, run, batch, *rest):  # member 2 degenerate when served (learned as usual)
        return real(_broken(ens, 2), fs, run, batch, *rest)

    monkeypatch.setattr(serving, "serve_ensemble", breaking)
    case = tiny_wave(tmp_path)
    text = (case / "case.toml").read_text()
    (case / "case.toml").write_text(text.replace('data = ["data/train.nc"]', 'data = ["data/train.nc"]\nensemble = 3'))
    code, _, err = run_cli(capsys, "run", case, "--strict")
    assert code == 4, err
    assert (
        "members stopped: member 2" in err
        and "complete, 30 slices" in err
        and "(1 of 3 ensemble members stopped)" in err
    )
    res = case / "results"
    assert "members stopped: member 2" in (res / "run.log").read_text()
    summary = json.loads((res / "summary.json").read_text())
    task = summary["tasks"]["test"]
    assert task["complete"] and [s["member"] for s in task["members_stopped"]] == [2]
    assert any("members stopped" in w for w in summary["warnings"]) and summary["exit_status"] == 4
    with xr.open_dataset(res / "test.nc") as ds:
        assert np.isfinite(ds["psi_std"].values[2:]).all()
        assert list(np.atleast_1d(ds["psi_std"].attrs["stopped_members"])) == [2]
    # the figure the run drew marks it on the error panel (a dotted line and its label)
    from matplotlib.text import Text

    from latticedft.io.figures import task_figure

    assert (res / "test.png").stat().st_size > 0
    fig = task_figure(res / "test.nc")
    panel = [ax for ax in fig.axes if "error against the reference" in ax.get_title()][0]
    assert "member 2 stops" in [t.get_text() for t in panel.findobj(Text)]
    assert "member(s) stopped" in [str(line.get_label()) for line in panel.get_lines()]


def test_members_take_member_0s_ridge() -> None:
    train = [systems.oscillator_sin(a) for a in (1.2, 0.6)]
    ens = ldft.EnsembleLagrangian(ldft.PolynomialLagrangian((2, 4)), members=3, seed=0)
    report = ldft.learn(ens, train, ridge="auto")
    assert all(ens.member(k).report_.ridge == report.ridge for k in range(3))


def test_memory_check_counts_the_members(tmp_path: Path) -> None:
    from latticedft._run import check_case
    from latticedft._run._guards import check_task_memory

    case = tiny_wave(tmp_path)
    plain = load_case(case)
    data = check_case(plain)
    values = 30 * 13 * 8  # the task's field in bytes
    check_task_memory(plain, data, available=4 * values)  # field, reference, error, written copy
    with pytest.raises(ldft.ConfigError, match="3 ensemble members"):
        check_task_memory(load_case(case, ["train.ensemble=3"]), data, available=4 * values)


def test_mlp_members_start_from_their_own_seeds() -> None:
    _, train = oscillator_data(amplitudes=(0.3, 0.9), steps=40)
    mlp = ldft.MLPLagrangian(hidden=[8], activation="tanh", form="kinetic-potential", seed=0)
    ens = ldft.EnsembleLagrangian(mlp, members=3, seed=0)
    ldft.learn(ens, train, max_iter=3, progress=False)
    seeds = [ens.member(k).seed for k in range(3)]
    assert seeds[0] == 0 and len(set(seeds)) == 3
    weights = [torch.cat([p.detach().flatten() for p in ens.member(k).parameters()]) for k in range(3)]
    assert not torch.allclose(weights[1], weights[2])
    assert ens.options()["model"]["options"]["seed"] == 0  # member 0 keeps the model's own seed


@pytest.mark.parametrize("m", [1, 2])
def test_the_box_measures_member_0s_own_field(m: int) -> None:
    """serve(ensemble, init, box=b) stops where member 0 served alone stops: the box tested the norm of all the
    members' stacked components (a 5-member Kepler ensemble stopped at r = b / sqrt(5))."""
    train = [systems.oscillator_sin(a) for a in (1.2, 0.8, 0.4)]
    if m == 2:  # two uncoupled copies: a vector field
        train = [xr.concat([f, 0.5 * f], "component").transpose("t", "component") for f in train]
        train = [f.assign_coords(component=["x", "y"]) for f in train]
    ens = ldft.EnsembleLagrangian(ldft.PolynomialLagrangian((2, 4)), members=3, seed=0)
    ldft.learn(ens, train)
    k = int(abs(train[0].isel(component=0) if m == 2 else train[0]).argmin())  # start near a zero crossing
    init, box = train[0].isel(t=slice(k, None)), 0.9
    alone = ldft.serve(ens.member(0), init, box=box)
    together = ldft.serve(ens, init, box=box)
    assert "left the box" in alone.reason and 2 < alone.field.sizes["t"] < init.sizes["t"]
    assert together.field.sizes["t"] == alone.field.sizes["t"]
    np.testing.assert_allclose(together.field.values, alone.field.values, rtol=0, atol=1e-12)


@pytest.mark.parametrize("power", [-40, 40])
def test_each_member_is_judged_on_its_own_scale(quartic: ldft.EnsembleLagrangian, monkeypatch, power: int) -> None:
    """A member whose L_d is ``2**power`` times its own (the same equations; a mixed Hessian and residual of another
    size) is served in the stacked run as alone: neither it nor another member is declared singular, or converged,
    on another member's scale (the stacked run declared the smaller ones singular, and every member was served
    again alone). Every member's field equals the member served alone, with the same warnings."""
    import latticedft._serve._ensemble as ensemble_serving

    scaled = copy.deepcopy(quartic)
    with torch.no_grad():
        scaled.member(2).coef.mul_(2.0**power)  # a power of 2: the member alone serves bit for bit as before

    def alone(*args):
        raise AssertionError("the stacked run stopped: its members were served alone")

    monkeypatch.setattr(ensemble_serving, "_alone", alone)
    _, refs = oscillator_data(amplitudes=(0.75, 0.5), steps=80)
    for init in (refs[0], list(refs)):
        outs = ldft.serve(scaled, init)
        own = [ldft.serve(quartic.member(k), init) for k in range(len(quartic))]
        for i, out in enumerate(outs if isinstance(init, list) else [outs]):
            assert out.complete and out.members_stopped is None
            for k in range(len(quartic)):
                mine = own[k][i] if isinstance(init, list) else own[k]
                assert mine.complete and mine.field.sizes["t"] == out.members.sizes["t"]
                np.testing.assert_allclose(out.members.values[k], mine.field.values, rtol=0, atol=1e-12)
            first = own[0][i] if isinstance(init, list) else own[0]
            np.testing.assert_array_equal(out.field.values, first.field.values)
            assert [w for w in out.warnings if not w.startswith("ensemble:")] == first.warnings


@pytest.mark.usefixtures("stacked_run")
@pytest.mark.parametrize("orders", [(2, 0), (2, 4)])  # (2, 0): the affine recurrence; (2, 4): slice-Newton
def test_each_member_of_a_field_is_judged_on_its_own_scale(orders: tuple[int, int], monkeypatch) -> None:
    """On a 1+1D lattice too, the singularity test of the stacked slice solve takes each member on its own
    scale: a member whose L_d is ``2**-40`` or ``2**40`` times its own is served by the stacked run, and every
    member's field equals the member served alone (it was declared singular on another member's scale)."""
    import latticedft._serve._ensemble as ensemble_serving

    train = systems.wave_string([(1, 1.0), (2, 0.4)], nx=13, nt=20)
    test = systems.wave_string([(1, 0.5, 0.3), (3, 0.2)], nx=13, nt=30)
    ens = ldft.EnsembleLagrangian(ldft.PolynomialLagrangian(orders), members=3, seed=0)
    ldft.learn(ens, [train])
    own = [ldft.serve(ens.member(k), test) for k in range(3)]

    def alone(*args):
        raise AssertionError("the stacked run stopped: its members were served alone")

    monkeypatch.setattr(ensemble_serving, "_alone", alone)
    for power in (-40, 40):
        scaled = copy.deepcopy(ens)
        with torch.no_grad():
            scaled.member(2).coef.mul_(2.0**power)
        out = ldft.serve(scaled, test)
        assert out.complete and out.members_stopped is None
        assert [w for w in out.warnings if not w.startswith("ensemble:")] == own[0].warnings
        for k in range(3):
            assert own[k].complete
            np.testing.assert_allclose(out.members.values[k], own[k].field.values, rtol=0, atol=1e-12)


def _served(model: ldft.AbstractLagrangian, init: xr.DataArray, **kw) -> ldft.ServeResult:
    """``model`` serving ``init``: its result, or the one its ServeError carries."""
    try:
        return ldft.serve(model, init, **kw)
    except ldft.ServeError as err:
        return err.result


@pytest.mark.parametrize("broken", [False, True])  # True: another member stops the stacked run (served alone)
def test_the_box_stops_each_member_where_it_stops_alone(quartic: ldft.EnsembleLagrangian, broken: bool) -> None:
    """A box that one resampled member leaves and member 0 does not: that member's field ends where it ends
    served alone (the slice that left the box its last), the result names it with the box's reason, and the
    spread after it is over the others (the stacked run tested member 0's components alone, and the member
    went on past the box)."""
    _, (ref,) = oscillator_data(amplitudes=(0.75,), steps=60)
    peaks = [float(np.abs(ldft.serve(quartic.member(k), ref).field.values[2:]).max()) for k in range(5)]
    k = int(np.argmax(peaks[1:])) + 1
    others = max(p for j, p in enumerate(peaks) if j != k)
    assert peaks[k] > others
    box = (peaks[k] + others) / 2  # member k alone leaves it
    ens = _broken(quartic, 4 if k != 4 else 3) if broken else quartic
    out = ldft.serve(ens, ref, box=box)
    alone = [_served(ens.member(j), ref, box=box) for j in range(5)]
    own = alone[k]
    assert own.reason.startswith("left the box") and 2 < own.field.sizes["t"] < 60
    assert out.complete and out.field.sizes["t"] == 60
    assert [w for w in out.warnings if not w.startswith("ensemble:")] == alone[0].warnings
    assert f"member {k} at slice {own.field.sizes['t']} ({own.reason})" in out.warnings[-1]
    np.testing.assert_array_equal(out.field.values, alone[0].field.values)
    stops = {s["member"]: s for s in out.members_stopped}
    assert stops[k] == {"member": k, "slice": own.field.sizes["t"], "reason": own.reason}
    assert sorted(stops) == sorted([k, *([4 if k != 4 else 3] if broken else [])])
    end = own.field.sizes["t"]
    np.testing.assert_allclose(out.members.values[k, :end], own.field.values, rtol=0, atol=1e-12)
    assert np.isnan(out.members.values[k, end:]).all()
    kept = [j for j in range(5) if j not in stops]
    for j in kept:
        np.testing.assert_allclose(out.members.values[j], alone[j].field.values, rtol=0, atol=1e-12)
    survivors = np.stack([alone[j].field.values for j in kept])
    np.testing.assert_allclose(out.std.values[end:], survivors.std(axis=0, ddof=1)[end:], rtol=1e-12, atol=1e-15)


def test_every_member_served_together_equals_itself_served_alone(paper: ldft.EnsembleLagrangian) -> None:
    """Every member of a stacked run is converged on its own residual scale and left as it is once converged,
    as alone: its field equals the member served alone, to the bit in the numpy loop (the stacked run's one
    convergence test over all members left the resampled members of the paper's oscillator up to 1.2e-9 from
    their own fields in 49 steps), with the same warnings for member 0."""
    init = systems.oscillator_sin(1.0)
    out = ldft.serve(paper, init, slices=51)
    assert out.complete and out.members_stopped is None
    for k in range(len(paper)):
        alone = ldft.serve(paper.member(k), init, slices=51)
        np.testing.assert_allclose(out.members.values[k], alone.field.values, rtol=0, atol=1e-12)
        if k == 0:
            assert [w for w in out.warnings if not w.startswith("ensemble:")] == alone.warnings


@pytest.mark.parametrize("power", [20, -30])
def test_networks_served_together_are_each_judged_on_their_own(power: int) -> None:
    """An ensemble of MLPs (the torch loop) whose member 2 has its last layer scaled by ``2**power`` (another
    potential, the kinetic term kept): every member's field equals the member served alone (the joint
    convergence test left member 2 2.5e-4 (power 20) and 1.1e-9 (power -30) from its own field)."""
    orbit = systems.kepler_orbit(1.0, 0.9, n=60)
    model = ldft.MLPLagrangian(preset="radial", hidden=[8])
    ldft.learn(model, orbit, progress=False, max_iter=20, ensemble=3)
    ens = copy.deepcopy(model.ensemble_)
    last = [m for m in ens.member(2).modules() if isinstance(m, torch.nn.Linear)][-1]
    with torch.no_grad():
        last.weight.mul_(2.0**power)
        last.bias.mul_(2.0**power)
    out = ldft.serve(ens, orbit, slices=40, progress=False)
    assert out.complete and out.members_stopped is None
    for k in range(3):
        alone = ldft.serve(ens.member(k), orbit, slices=40, progress=False)
        assert alone.complete
        np.testing.assert_allclose(out.members.values[k], alone.field.values, rtol=0, atol=1e-12)


@pytest.fixture(scope="module")
def breathers() -> tuple[ldft.EnsembleLagrangian, xr.DataArray]:
    """An ensemble of a nonlinear L_d on a 1+1D string (a sine-Gordon breather learned by a polynomial (2, 4):
    slice-Newton takes several iterations a slice, with chord steps) and a test field."""
    train = systems.sine_gordon_breather(0.5, xlim=(-10, 10), nx=41, nt=40, dt=0.1)
    test = systems.sine_gordon_breather(0.6, 0.2, xlim=(-10, 10), nx=41, nt=40, dt=0.1)
    ens = ldft.EnsembleLagrangian(ldft.PolynomialLagrangian((2, 4)), members=3, seed=0)
    ldft.learn(ens, [train])
    return ens, test


@pytest.mark.usefixtures("stacked_run")
@pytest.mark.parametrize("power", [0, -40, 40])
def test_each_member_of_a_field_converges_on_its_own_scale(breathers, monkeypatch, power: int) -> None:
    """n-D slice-Newton judges each stacked member on its own: its residual against its own scale, its step
    against its own values, its chord or fresh Jacobian by its own residuals, left as it is once converged.
    Every member's field equals the member served alone to 1e-12, also with member 2's L_d scaled by
    ``2**power`` (the joint test over the stacked slice left members 2.7e-7 (power -40), 3.7e-9 (40) and 3.9e-9
    (0) from their own fields)."""
    import latticedft._serve._ensemble as ensemble_serving

    ens, test = breathers
    own = [ldft.serve(ens.member(k), test) for k in range(3)]

    def alone(*args):
        raise AssertionError("the stacked run stopped: its members were served alone")

    monkeypatch.setattr(ensemble_serving, "_alone", alone)
    scaled = copy.deepcopy(ens)
    with torch.no_grad():
        scaled.member(2).coef.mul_(2.0**power)
    out = ldft.serve(scaled, test)
    assert out.complete and out.members_stopped is None and out.solver == "newton"
    for k in range(3):
        assert own[k].complete and own[k].solver == "newton"
        np.testing.assert_allclose(out.members.values[k], own[k].field.values, rtol=0, atol=1e-12)


@pytest.mark.usefixtures("stacked_run")
@pytest.mark.parametrize("power", [40, -40])
def test_the_affine_check_takes_each_member_on_its_own_scale(monkeypatch, power: int) -> None:
    """The affine recurrence's DEL check holds each stacked member's residual to its own scale: a recurrence
    that went wrong in one member (member 0 perturbed by 1e-9 of its values from slice 10 on, in the stacked run
    only) is caught although member 2's L_d is ``2**power`` times its own, and Newton serves from there, so that
    every member equals itself served alone (the stacked check kept the perturbed slices when member 2's scale
    was the larger, 6.0e-10 from member 0's own field)."""
    ens, test = _wave_ensemble()
    own = [ldft.serve(ens.member(k), test) for k in range(3)]
    assert all(o.solver == "affine" for o in own)
    _fault_affine(monkeypatch, test, 0)
    out = ldft.serve(_scaled(ens, 2, power), test)
    assert out.complete and out.members_stopped is None and out.solver == "affine+newton"
    for k in range(3):
        np.testing.assert_allclose(out.members.values[k], own[k].field.values, rtol=0, atol=1e-12)


def _narrowed(ens: ldft.EnsembleLagrangian, k: int, share: float = 0.5) -> ldft.EnsembleLagrangian:
    """A copy of ``ens`` whose member ``k`` keeps the middle ``share`` of its training range (as if it had been
    learned on narrower data)."""
    out = copy.deepcopy(ens)
    lo, hi = out.member(k).trained_range()
    mid, half = (lo + hi) / 2, (hi - lo) / 2 * share
    out.member(k).set_feature_range(torch.stack([mid - half, mid + half]))
    return out


def test_every_member_is_checked_against_its_own_training_range(quartic: ldft.EnsembleLagrangian) -> None:
    """Every member's field is checked against its own training range (the served result checked member 0's
    alone): the members that leave it are named, each from the first slice it leaves it, as served alone, in
    one warning, in ``members_outside`` and in the spread's attributes (for the figure); member 0's own
    warnings are those of the model served alone."""
    _, (ref,) = oscillator_data(amplitudes=(0.75,), steps=60)
    ens = _narrowed(quartic, 3)
    out = ldft.serve(ens, ref)
    alone = [ldft.serve(ens.member(k), ref) for k in range(5)]
    first = [a.extrapolation_summary()["first_slice"] for a in alone]
    leave = [k for k in range(5) if first[k] is not None]
    assert first[0] is None and 3 in leave
    assert out.warnings[:-1] == alone[0].warnings and out.members_stopped is None
    assert [s["member"] for s in out.members_outside] == leave
    assert [s["slice"] for s in out.members_outside] == [first[k] for k in leave]
    line = out.warnings[-1]
    assert line.startswith(f"ensemble: {len(leave)} of 4 resampled members leave their own training range")
    assert f"member 3 from slice {first[3]} (by up to" in line
    assert out.to_dict()["members_outside"] == out.members_outside
    assert list(np.atleast_1d(out.std.attrs["outside_members"])) == leave
    inside = ldft.serve(quartic, ref)  # no member narrowed: none leaves (the resampled members stay inside)
    assert inside.members_outside is None and inside.to_dict()["members_outside"] == []


def test_the_calibration_names_the_members_outside_the_training_fields() -> None:
    """The calibrated band's range check (values and amplitude against the training fields') is made on every
    member's field, not member 0's alone, and names the members outside."""
    from latticedft._calibrate import Calibration

    law = Calibration(
        scale=1e-3, exponent=1.0, quantile=0.95, windows=3, held_out_slices=30, slices=60, low=-1.0, high=1.0,
        coverage=0.95, std_over_error=1.0, runner_up=None, wall_time=0.0, span_low=1.0, span_high=2.0,
    )  # fmt: skip
    t = np.linspace(0, 6, 40)
    fields = np.stack([0.8 * np.sin(t), 0.9 * np.sin(t), 1.3 * np.sin(t), 0.3 * np.sin(t)])
    assert law.warnings(40, fields[0]) == []  # member 0 inside: the task's own check says nothing
    line = law.members_warning(fields)
    assert line is not None and line.startswith("calibration: 2 of 3 resampled ensemble members serve outside")
    assert "member 2 (values [-1.3, 1.3], amplitude 2.6)" in line and "member 3 (amplitude 0.599)" in line
    assert "member 0" not in line and "member 1" not in line
    assert law.members_warning(fields[:2]) is None
    assert law.members_warning(fields[[2, 1]]) is None  # member 0 outside: the task's own check names it


def test_run_reports_the_members_outside_their_training_range(tmp_path: Path, capsys, monkeypatch) -> None:
    """A run whose ensemble member leaves its own training range: the warning names it in the console, run.log
    and summary.json (``members_outside``), the task line counts it, ``--strict`` makes the exit status 4 and
    the figure marks where it leaves."""
    import latticedft._serve as serving

    real = serving.serve_ensemble

    def narrowing(ens, fs, run, batch, *rest):  # member 2 keeps a tenth of its range (learned as usual)
        return real(_narrowed(ens, 2, 0.1), fs, run, batch, *rest)

    monkeypatch.setattr(serving, "serve_ensemble", narrowing)
    case = tiny_wave(tmp_path)
    text = (case / "case.toml").read_text()
    (case / "case.toml").write_text(text.replace('data = ["data/train.nc"]', 'data = ["data/train.nc"]\nensemble = 3'))
    code, _, err = run_cli(capsys, "run", case, "--strict")
    assert code == 4, err
    res = case / "results"
    summary = json.loads((res / "summary.json").read_text())
    task = summary["tasks"]["test"]
    outside = {s["member"]: s for s in task["members_outside"]}
    assert task["complete"] and task["members_stopped"] == [] and 2 in outside
    assert outside[2]["slice"] < min([s["slice"] for k, s in outside.items() if k != 2], default=30)
    line = f"ensemble: {len(outside)} of 2 resampled members leave their own training range (tolerance 0.05): "
    assert line in err and f"member 2 from slice {outside[2]['slice']} (by up to" in err
    assert f"({len(outside)} of 2 resampled members left their training range)" in err
    assert 0 not in outside  # member 0's range is the task's own warning
    assert line in (res / "run.log").read_text()
    assert any("leave their own training range" in w for w in summary["warnings"])
    from matplotlib.text import Text

    from latticedft.io.figures import task_figure

    fig = task_figure(res / "test.nc")
    panel = [ax for ax in fig.axes if "error against the reference" in ax.get_title()][0]
    assert "member 2 leaves its range" in [t.get_text() for t in panel.findobj(Text)]


def test_the_solver_choice_takes_each_members_off_diagonal_share(breathers) -> None:
    """``solver = "auto"`` chooses each stacked member's solver on its own Jacobian, as alone: member 0's
    coupling (1e-9 of its diagonal: LU, served alone) is not measured against member 1's diagonal, ``2**40``
    times larger (the stacked slice was solved site-wise: member 0 then took quasi-Newton steps), and the
    members not coupled are solved site-wise."""
    from latticedft._lattice import as_lattice_field
    from latticedft._serve._ensemble import _labels, _stack
    from latticedft._serve._field import slice_system
    from latticedft._serve._solvers import factor_members, factor_step

    ens, test = breathers
    f = as_lattice_field(test)
    labels = _labels(ens, f)
    sys = slice_system(stacked(ens, labels), _stack(f, 3, labels))
    size, share = [1.0, 2.0**40, 1.0], [1e-9, 0.0, 0.0]  # per member: diagonal, off-diagonal share
    ncell = sys.site_of[0].size
    blocks = {}
    for p in sys.pairs:
        b = torch.zeros(ncell, 3, 3, dtype=torch.float64)
        for k in range(3):
            b[:, k, k] = size[k] * (1.0 if p in sys.diag_pairs else share[k])
        blocks[p] = b
    solves: list = [None] * 3
    assert factor_members(sys, blocks, 1.0, "auto", np.full(3, 1e-10), solves) == ["lu", "sitewise", "sitewise"]
    assert factor_step(sys, blocks, 1.0, "auto", 1e-10)[1] == "lu+sitewise"
    share[0] = 0.0  # no member coupled: site-wise
    for p in sys.pairs:
        if p not in sys.diag_pairs:
            blocks[p][:, 0, 0] = 0.0
    assert factor_members(sys, blocks, 1.0, "auto", np.full(3, 1e-10), solves) == ["sitewise"] * 3
    assert factor_step(sys, blocks, 1.0, "auto", 1e-10)[1] == "sitewise"


def _wave_ensemble() -> tuple[ldft.EnsembleLagrangian, xr.DataArray]:
    """A 3-member quadratic ensemble learned on a wave string, and a test field that its members serve by the
    affine recurrence."""
    train = systems.wave_string([(1, 1.0), (2, 0.4)], nx=13, nt=20)
    test = systems.wave_string([(1, 0.5, 0.3), (3, 0.2)], nx=13, nt=30)
    ens = ldft.EnsembleLagrangian(ldft.PolynomialLagrangian((2, 0)), members=3, seed=0)
    ldft.learn(ens, [train])
    return ens, test


def _fault_affine(monkeypatch: pytest.MonkeyPatch, test: xr.DataArray, member: int) -> None:
    """Make the affine recurrence go wrong in one member of a stacked 3-member serve of ``test``: that member's
    values times ``1 + 1e-9`` from slice 10 on (a field served alone is left as it is)."""
    from latticedft._serve._affine import _AffineSlices

    run = _AffineSlices.run

    def faulty(self: Any, v: np.ndarray, start: int, stop: int) -> None:
        run(self, v, start, stop)
        if v.shape[1] == 3 * test.sizes["x"] and stop > 10:  # the stacked run: the member's components (of 3 x 1)
            v[10 : stop + 1, member::3] *= 1 + 1e-9

    monkeypatch.setattr(_AffineSlices, "run", faulty)


def _scaled(ens: ldft.EnsembleLagrangian, k: int, power: int) -> ldft.EnsembleLagrangian:
    """A copy of the polynomial ensemble ``ens`` whose member ``k``'s L_d is ``2**power`` times its own (the same
    equations; a Jacobian and residual of another size: served alone, bit for bit as before)."""
    out = copy.deepcopy(ens)
    with torch.no_grad():
        out.member(k).coef.mul_(2.0**power)
    return out


@pytest.mark.usefixtures("stacked_run")
@pytest.mark.parametrize("power", [0, -40, 40])
def test_gmres_stops_on_each_members_own_residual(breathers, power: int) -> None:
    """``solver = "krylov"`` on a stacked slice runs GMRES on each member's own Jacobian, preconditioner and
    right-hand side, to its own tolerance, as alone: every member's field equals the member served alone to 1e-12
    (GMRES on the stacked system, stopped on the stacked linear residual, left members 2.3e-10 (member 0) to
    6.0e-10 (member 2) from their own fields, at every ``power``)."""
    ens, test = breathers
    scaled = _scaled(ens, 2, power)
    out = ldft.serve(scaled, test, solver="krylov")
    assert out.complete and out.slice_solver == "krylov"
    for k in range(3):
        own = ldft.serve(scaled.member(k), test, solver="krylov")
        assert own.complete and own.slice_solver == "krylov"
        np.testing.assert_allclose(out.members.values[k], own.field.values, rtol=0, atol=1e-12)


@pytest.mark.usefixtures("stacked_run")
@pytest.mark.parametrize("solver", ["lu", "krylov"])
def test_each_member_takes_its_own_linear_solve_to_the_bit(breathers, monkeypatch, solver: str) -> None:
    """Where the stacked run and the member alone evaluate the L_d alike (the torch loop: the folded kernels serve
    one model only), every member's field equals the member served alone to the bit, also with member 2's L_d
    ``2**-40`` times its own: the 1+1D band LU refuses a pivot against the member's own largest entry (the
    stacked one's refused member 2's pivots against the others' and the sparse LU served the slice, 2.0e-15 from
    its own field), and GMRES runs on each member's own system."""
    import latticedft._serve._stepper as stepper

    monkeypatch.setattr(stepper, "_folded_of", lambda run: None)
    ens, test = breathers
    scaled = _scaled(ens, 2, -40)
    out = ldft.serve(scaled, test, solver=solver)
    assert out.complete
    for k in range(3):
        own = ldft.serve(scaled.member(k), test, solver=solver)
        np.testing.assert_array_equal(out.members.values[k], own.field.values)


@pytest.mark.usefixtures("stacked_run")
@pytest.mark.parametrize("power", [0, 40, -40])
def test_a_member_failing_the_affine_check_leaves_the_others_affine(monkeypatch, power: int) -> None:
    """One member's affine recurrence failing its DEL check (member 2 perturbed by 1e-9 of its values from slice 10
    on, in the stacked run only) sends that member alone to Newton from there: the others keep their recurrence's
    slices, as served alone, to the bit and with member 0's solver ``"affine"``, also with member 1's L_d ``2**power``
    times its own (every member went to Newton from slice 10: ``"affine+newton"``); member 2 equals itself served
    alone to 1e-12."""
    ens, test = _wave_ensemble()
    scaled = _scaled(ens, 1, power)
    own = [ldft.serve(scaled.member(k), test) for k in range(3)]
    assert all(o.solver == "affine" for o in own)
    _fault_affine(monkeypatch, test, 2)
    out = ldft.serve(scaled, test)
    assert out.complete and out.members_stopped is None and out.solver == "affine"
    for k in (0, 1):
        np.testing.assert_array_equal(out.members.values[k], own[k].field.values)
    np.testing.assert_allclose(out.members.values[2], own[2].field.values, rtol=0, atol=1e-12)
    assert not np.array_equal(out.members.values[2], own[2].field.values)  # Newton served it from slice 10


@pytest.fixture(scope="module")
def membrane() -> tuple[ldft.EnsembleLagrangian, xr.DataArray]:
    """An ensemble of a nonlinear L_d on a 2+1D periodic membrane (the sine-Gordon class (2, 12), time
    symmetric, learned on a field at rest: slice-Newton with chord steps) and a longer field to serve."""
    from test_ndpoly_fast import _field, _sine_gordon

    ens = ldft.EnsembleLagrangian(ldft.PolynomialLagrangian((2, 12), time_symmetric=True), members=3, seed=0)
    ldft.learn(ens, _field(_sine_gordon(2, 10, 24)), progress=False)
    return ens, _field(_sine_gordon(2, 10, 30))


def _spy_folded(monkeypatch: pytest.MonkeyPatch) -> list[str]:
    """The kinds of the folded kernels every slice-Newton run takes from now on, in order (``_folded_of`` of
    ``latticedft._serve._stepper`` spied on)."""
    import latticedft._serve._stepper as stepper

    kinds: list[str] = []
    real = stepper._folded_of

    def spy(run):
        got = real(run)
        kinds.append(type(got).__name__)
        return got

    monkeypatch.setattr(stepper, "_folded_of", spy)
    return kinds


@pytest.mark.usefixtures("stacked_run")
@pytest.mark.parametrize("dims", ["1+1d", "2+1d"])
@pytest.mark.parametrize("solver", ["lu", "krylov"])
def test_each_member_on_the_folded_kernels_equals_itself_alone_to_the_bit(
    breathers, membrane, monkeypatch, dims: str, solver: str
) -> None:
    """A stacked ensemble of polynomials is served on the folded kernels, each member's cells evaluated by its own
    ``FoldedSlices`` on its own components (``_stackfold``): every member's residual, gradients and Hessian
    blocks are those it has alone, so its field equals the member served alone to the bit, also with member
    2's L_d ``2**-40`` times its own (the torch evaluation of the stack left members up to 1.0e-14 (1+1D) and
    1.7e-15 (2+1D) from their own fields)."""
    from latticedft._serve._stackfold import StackedFolded

    ens, test = breathers if dims == "1+1d" else membrane
    scaled = _scaled(ens, 2, -40)
    kinds = _spy_folded(monkeypatch)
    out = ldft.serve(scaled, test, solver=solver, progress=False)
    assert out.complete and out.solver == "newton" and set(kinds) == {StackedFolded.__name__}
    for k in range(3):
        own = ldft.serve(scaled.member(k), test, solver=solver, progress=False)
        assert own.complete
        np.testing.assert_array_equal(out.members.values[k], own.field.values)
    assert not np.array_equal(out.members.values[1], out.members.values[0])  # members of their own


@pytest.mark.usefixtures("stacked_run")
@pytest.mark.parametrize("switch", ["CHORD_PREDICT", "FRESH_FIRST_ON"])
def test_slice_newtons_chord_switches_reach_the_stacked_run(breathers, membrane, monkeypatch, switch: str) -> None:
    """The chord rules' module switches (``_newton.CHORD_PREDICT``, ``_newton.FRESH_FIRST_ON``) are read when a
    stacked run counts each member's slow chords, as slice-Newton reads them for one model: with a switch turned,
    every member of the stack still equals itself served alone with it (a copy taken at import kept the default
    for the stack)."""
    import latticedft._serve._newton as newton

    monkeypatch.setattr(newton, switch, False if switch == "CHORD_PREDICT" else 1)
    for ens, test in (breathers, membrane):
        out = ldft.serve(ens, test, solver="lu", progress=False)
        assert out.complete
        for k in range(3):
            own = ldft.serve(ens.member(k), test, solver="lu", progress=False)
            np.testing.assert_array_equal(out.members.values[k], own.field.values)


def test_a_stack_that_cannot_fold_keeps_the_torch_evaluation(breathers) -> None:
    """The folded kernels serve a stack only where they serve every member: a stack of networks, of polynomials
    whose coefficients do not fold (``folded_max_powers``), or with ``compiled_kernels=False`` keeps the torch
    evaluation of ``CellDerivatives`` (``stacked_folded`` gives None); a single model is not a stack."""
    from latticedft._lattice import as_lattice_field
    from latticedft._serve._ensemble import _labels, _stack
    from latticedft._serve._field import slice_system
    from latticedft._serve._stackfold import StackedFolded, stacked_folded

    ens, test = breathers
    f = as_lattice_field(test)

    def built(e: ldft.EnsembleLagrangian) -> Any:
        labels = _labels(e, f)
        model = stacked(e, labels)
        field = _stack(f, len(e), labels)
        return stacked_folded(model, slice_system(model, field), field.values.reshape(f.shape[0], -1, len(e)))

    assert isinstance(built(ens), StackedFolded)
    with ldft.set_options(compiled_kernels=False):
        assert built(ens) is None
    with ldft.set_options(folded_max_powers=1):
        assert built(ens) is None
    single = ens.member(0)
    sys = slice_system(single, f)
    assert stacked_folded(single, sys, f.values.reshape(f.shape[0], -1, 1)) is None
    net = ldft.MLPLagrangian(hidden=[4])
    ldft.learn(net, test, progress=False, max_iter=5, ensemble=2)
    assert built(net.ensemble_) is None
    with ldft.set_options(compiled_kernels=False):  # served as before: each member on its own scale, to 1e-12
        out = ldft.serve(ens, test, solver="lu", progress=False)
        for k in range(3):
            own = ldft.serve(ens.member(k), test, solver="lu", progress=False)
            np.testing.assert_allclose(out.members.values[k], own.field.values, rtol=0, atol=1e-12)


#: The figures of a served result that a stacked ensemble reports as member 0 served alone reports them.
FIGURES = ("newton_iterations", "max_newton_iterations", "max_residual", "solver", "slice_solver")


def _figures(r: ldft.ServeResult) -> dict[str, Any]:
    return {k: getattr(r, k) for k in FIGURES}


@pytest.mark.usefixtures("stacked_run")
@pytest.mark.parametrize("solver", ["lu", "krylov"])
def test_a_stacked_field_reports_member_0s_figures(breathers, solver: str) -> None:
    """A stacked n-D run reports member 0's own figures, as the member served alone reports them: its Newton
    evaluations (the stacked run counted each slice's evaluations until every member converged: 120 against
    member 0's 114, the scaled member 2 moving it further), the most on one slice, the largest residual it
    converged to (the stacked run's was the largest over the members) and its linear solver."""
    ens, test = breathers
    scaled = _scaled(ens, 2, -40)
    out = ldft.serve(scaled, test, solver=solver, progress=False)
    own = ldft.serve(scaled.member(0), test, solver=solver, progress=False)
    assert out.complete and _figures(out) == _figures(own)
    assert out.to_dict()["newton_iterations"] == own.newton_iterations


@pytest.mark.usefixtures("stacked_run")
def test_a_member_served_affine_reports_no_other_members_newton(monkeypatch) -> None:
    """Member 0 served by the affine recurrence throughout while member 2 goes to Newton from slice 10 (its
    recurrence failed its own check): the stacked result reports member 0's figures, ``"affine"``, one
    evaluation a slice and no slice solver, as member 0 alone (it reported member 2's Newton evaluations added
    to member 0's affine slices, and member 2's linear solver)."""
    ens, test = _wave_ensemble()
    own = ldft.serve(ens.member(0), test)
    assert own.solver == "affine" and own.slice_solver is None
    _fault_affine(monkeypatch, test, 2)
    out = ldft.serve(ens, test)
    assert out.complete and out.members_stopped is None
    assert _figures(out) == _figures(own)
    assert out.newton_iterations == test.sizes["t"] - 2 and out.max_newton_iterations == 1


@pytest.mark.parametrize("loop", ["numpy", "torch"])
def test_a_stacked_batch_of_trajectories_reports_member_0s_figures(paper, monkeypatch, loop: str) -> None:
    """A 1D stacked batch (two trajectories) reports each trajectory's member 0 figures, as member 0 served alone
    on the same batch reports them (the numpy loop and the torch one): its evaluations, the most on one slice and
    the largest residual it converged to (the stacked batch reported the largest over the members: 1.1e-10
    against member 0's own 5.6e-11 on the first trajectory)."""
    import latticedft._serve._onedim as onedim

    if loop == "torch":
        monkeypatch.setattr(onedim, "numpy_derivatives_of", lambda model: None)
    inits = [systems.oscillator_sin(1.0), systems.oscillator_sin(0.6)]
    out = ldft.serve(paper, inits, slices=51, progress=False)
    own = ldft.serve(paper.member(0), inits, slices=51, progress=False)
    for r, o in zip(out, own, strict=True):
        assert r.complete and _figures(r) == _figures(o)


def _both_ways(
    monkeypatch: pytest.MonkeyPatch, model: ldft.EnsembleLagrangian, init: Any, **kw: Any
) -> tuple[Any, Any, list[str]]:
    """``model`` serving ``init`` by the stacked run and by its members one by one (``MEMBERWISE`` off, then on):
    each way's result (or the ServeError it raised) and the kinds of the folded kernels each slice-Newton run
    took, in order."""
    import latticedft._serve._ensemble as ensemble_serving

    kinds = _spy_folded(monkeypatch)
    out = []
    for memberwise in (False, True):
        monkeypatch.setattr(ensemble_serving, "MEMBERWISE", memberwise)
        try:
            out.append(ldft.serve(model, init, progress=False, **kw))
        except ldft.ServeError as err:
            out.append(err)
        kinds.append("|")
    return out[0], out[1], kinds


def _assert_same_result(a: ldft.ServeResult, b: ldft.ServeResult) -> None:
    """Every field of two results equal to the bit (NaN where NaN), the times apart."""
    import dataclasses

    for f in dataclasses.fields(a):
        if f.name in ("wall_time", "sites_per_second"):
            continue
        x, y = getattr(a, f.name), getattr(b, f.name)
        if isinstance(x, xr.DataArray):
            assert x.identical(y), f.name
            assert np.array_equal(np.asarray(x.values), np.asarray(y.values), equal_nan=True), f.name
        else:
            assert x == y, f.name


@pytest.mark.parametrize("dims", ["1+1d", "2+1d"])
@pytest.mark.parametrize("solver", ["lu", "krylov"])
def test_members_served_one_by_one_equal_the_stacked_run_to_the_bit(
    breathers, membrane, monkeypatch, dims: str, solver: str
) -> None:
    """A polynomial ensemble whose members all fold is served member by member, each on its own folded kernels
    (``MEMBERWISE``), and its result assembled as the stacked run's: the same field, mean, std, members, figures,
    extrapolation, warnings and attributes, to the bit, also with member 2's L_d ``2**-40`` times its own; the
    stacked run (the switch off) evaluated the stack (``StackedFolded``), the members one by one their own
    ``FoldedSlices``. The wall time is the members' together."""
    ens, test = breathers if dims == "1+1d" else membrane
    stacked_out, alone_out, kinds = _both_ways(monkeypatch, _scaled(ens, 2, -40), test, solver=solver)
    assert set(kinds[: kinds.index("|")]) == {"StackedFolded"}
    assert set(kinds[kinds.index("|") + 1 : -1]) == {"FoldedSlices"}
    assert stacked_out.complete and stacked_out.members_stopped is None and stacked_out.slice_solver == solver
    _assert_same_result(stacked_out, alone_out)
    assert stacked_out.field.attrs["source"].endswith("by a ensemble-stack L_d")
    own = [ldft.serve(_scaled(ens, 2, -40).member(k), test, solver=solver, progress=False) for k in range(3)]
    assert alone_out.wall_time >= sum(o.wall_time for o in own) / 10  # the members' together, not member 0's


def test_a_batch_and_an_affine_ensemble_one_by_one_equal_the_stacked_run(breathers, monkeypatch) -> None:
    """A batch of two 1+1D fields, and a quadratic ensemble served by the affine recurrence (``MEMBERWISE_AFFINE``):
    the members served one by one give every result as the stacked run does, to the bit."""
    ens, test = breathers
    other = systems.sine_gordon_breather(0.7, -0.1, xlim=(-10, 10), nx=41, nt=30, dt=0.1)
    stacked_out, alone_out, _ = _both_ways(monkeypatch, ens, [test, other], solver="lu")
    assert len(stacked_out) == len(alone_out) == 2
    for a, b in zip(stacked_out, alone_out, strict=True):
        _assert_same_result(a, b)
    import latticedft._serve._ensemble as ensemble_serving

    monkeypatch.setattr(ensemble_serving, "MEMBERWISE_AFFINE", True)  # by default the stacked recurrence serves it
    wave, field = _wave_ensemble()
    stacked_out, alone_out, _ = _both_ways(monkeypatch, wave, field)
    assert stacked_out.solver == "affine"
    _assert_same_result(stacked_out, alone_out)


@pytest.mark.parametrize("dims", ["1+1d", "2+1d"])
@pytest.mark.parametrize("broken", [2, 0])  # 2: a resampled member stops; 0: member 0 stops (a ServeError)
def test_a_member_that_stops_one_by_one_as_in_the_stacked_run(
    breathers, membrane, monkeypatch, dims: str, broken: int
) -> None:
    """A member that cannot step (its L_d zero: a singular mixed Hessian) stops the stacked run, whose members are
    then served alone; served one by one, the result is the same to the bit: the spread over the others,
    ``members_stopped`` and its warning, and where member 0 stops, the ServeError's message, slice, residual and
    result (member 0's slices so far)."""
    ens, test = breathers if dims == "1+1d" else membrane
    stacked_out, alone_out, _ = _both_ways(monkeypatch, _broken(ens, broken), test, solver="krylov")
    if broken == 0:
        assert isinstance(stacked_out, ldft.ServeError) and isinstance(alone_out, ldft.ServeError)
        assert str(stacked_out) == str(alone_out) and stacked_out.slice == alone_out.slice
        assert stacked_out.residual == alone_out.residual
        stacked_out, alone_out = stacked_out.result, alone_out.result
        assert not stacked_out.complete  # member 0's slices so far, the others' beside them
    else:
        assert [s["member"] for s in stacked_out.members_stopped] == [broken]
    _assert_same_result(stacked_out, alone_out)


def test_the_switch_and_the_stacks_served_one_by_one(breathers, monkeypatch) -> None:
    """``serves_alone`` takes the members one by one only for n-D slice-Newton on the CPU with every member a
    polynomial on the folded kernels, and ``MEMBERWISE`` on: not a 1D field, the sweep, ``compiled_kernels=False``,
    coefficients that do not fold, nor a stack of networks; nor members whose DEL is affine (the stacked
    recurrence), unless ``affine=False`` or ``MEMBERWISE_AFFINE``."""
    import latticedft._serve._ensemble as ensemble_serving
    from latticedft._lattice import as_lattice_field
    from latticedft._serve import ServeOptions

    ens, test = breathers
    fs, cpu, newton = [as_lattice_field(test)], torch.device("cpu"), ServeOptions()
    assert ensemble_serving.serves_alone(ens, fs, newton, cpu)
    assert not ensemble_serving.serves_alone(ens, fs, ServeOptions(mode="sweep"), cpu)
    with ldft.set_options(compiled_kernels=False):
        assert not ensemble_serving.serves_alone(ens, fs, newton, cpu)
    with ldft.set_options(folded_max_powers=1):
        assert not ensemble_serving.serves_alone(ens, fs, newton, cpu)
    one_d = [as_lattice_field(systems.oscillator_sin(1.0))]
    paper = ldft.EnsembleLagrangian(ldft.PolynomialLagrangian((2, 4)), members=2, seed=0)
    ldft.learn(paper, [systems.oscillator_sin(a) for a in (1.2, 0.6)], progress=False)
    assert not ensemble_serving.serves_alone(paper, one_d, newton, cpu)
    net = ldft.MLPLagrangian(hidden=[4])
    ldft.learn(net, test, progress=False, max_iter=5, ensemble=2)
    assert not ensemble_serving.serves_alone(net.ensemble_, fs, newton, cpu)
    wave, field = _wave_ensemble()  # an affine DEL: the stacked recurrence, unless asked or affine=False
    assert not ensemble_serving.serves_alone(wave, [as_lattice_field(field)], newton, cpu)
    assert ensemble_serving.serves_alone(wave, [as_lattice_field(field)], ServeOptions(affine=False), cpu)
    monkeypatch.setattr(ensemble_serving, "MEMBERWISE_AFFINE", True)
    assert ensemble_serving.serves_alone(wave, [as_lattice_field(field)], newton, cpu)
    monkeypatch.setattr(ensemble_serving, "MEMBERWISE", False)
    assert not ensemble_serving.serves_alone(ens, fs, newton, cpu)
