"""Error bars calibrated by held-out serving: the law, its coverage, the task's band and its warnings."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
import xarray as xr

import latticedft as ldft
from latticedft import systems
from latticedft._calibrate import (
    NOISE_FAILED,
    Calibration,
    _noise_warnings,
    calibrate,
    disagreement,
    runner_up,
    too_short,
)
from latticedft.io import write_field

from case_helpers import run_cli, tiny_wave, write_toml
from helpers import oscillator_data


def _law(**change: float) -> Calibration:
    base = dict(scale=1e-3, exponent=1.0, quantile=0.95, windows=2, held_out_slices=10, slices=40)
    base.update(low=-1.0, high=1.0, coverage=0.9, std_over_error=0.8, runner_up=None, wall_time=0.0)
    base.update(change)
    return Calibration(**base)  # type: ignore[arg-type]


def test_coverage_on_a_small_synthetic_case() -> None:
    """A quartic oscillator learned by a polynomial: the law is fitted on the held-out slices and twice it
    covers the quantile's share of them; the random state is left as it was."""
    _, data = oscillator_data(amplitudes=(0.4, 0.8, 1.2), steps=60)
    expected = _after_seed(3), np.random.RandomState(3).rand()
    torch.manual_seed(3)
    np.random.seed(3)
    record: list[dict] = []
    cal, warnings, trial = calibrate(ldft.PolynomialLagrangian((2, 4)), data, record=record)
    assert (torch.rand(1).item(), np.random.rand()) == expected
    assert [r["field"] for r in record] == [0, 1, 2] and len(record[0]["k"]) == 58 and sum(record[2]["held"]) == 18
    assert warnings == []
    assert cal.windows == 3 and cal.slices == 60 and cal.held_out_slices == 3 * 18
    assert cal.scale > 0 and 0 <= cal.exponent <= 3
    assert 0.9 <= cal.coverage <= 1.0  # the 95 % quantile of the held-out targets: at least 95 % within 2 std
    assert cal.low == pytest.approx(min(float(f.min()) for f in data))
    est = cal.estimate(np.arange(60), 1.2)
    assert est[0] == est[1] == 0 and np.all(np.diff(est[2:]) >= 0)
    assert trial.report_ is not None  # the trial learned on the first 70 % of every field
    d = disagreement(trial, data[0], data[0])
    assert d.shape == (60,) and np.all(d[:2] == 0)


def test_an_ensembles_spread_is_scaled_by_the_held_out_error() -> None:
    """With the learned ensemble, the law records the factor on its spread: twice the scaled spread covers the
    quantile's share of the trial's held-out errors."""
    _, data = oscillator_data(amplitudes=(0.4, 0.8, 1.2), steps=40)
    ens = ldft.EnsembleLagrangian(ldft.PolynomialLagrangian((2, 4)), members=3, seed=0)
    ldft.learn(ens, data, progress=False)
    cal, _, _ = calibrate(ldft.PolynomialLagrangian((2, 4)), data, ensemble_model=ens)
    assert cal.spread_scale is not None and 0 < cal.spread_scale < np.inf
    assert cal.spread_std_over_error is not None and 0 < cal.spread_std_over_error < np.inf
    alone, _, _ = calibrate(ldft.PolynomialLagrangian((2, 4)), data)
    assert alone.spread_scale is None and alone.spread_std_over_error is None and alone.scale == cal.scale


def test_the_spread_scale_takes_the_members_still_served_on_each_slice() -> None:
    """A member that stops while the ensemble serves a training field leaves the spread scale's samples as it
    leaves ``psi_std``: on each held-out slice the trial's error is measured against the spread of the members
    still served there (each served alone), and a slice with fewer than 2 of them gives no sample (no spread
    at all: no factor)."""
    import copy

    from latticedft._serve._ensemble import MIN_MEMBERS

    _, data = oscillator_data(amplitudes=(0.4, 0.8, 1.2), steps=40)
    ens = ldft.EnsembleLagrangian(ldft.PolynomialLagrangian((2, 4)), members=4, seed=0)
    ldft.learn(ens, data, progress=False)

    def broken(*members: int) -> ldft.EnsembleLagrangian:  # L_d = 0: singular from the first step
        out = copy.deepcopy(ens)
        with torch.no_grad():
            for k in members:
                out.member(k).coef.zero_()
        return out

    record: list[dict] = []
    cal, _, _ = calibrate(ldft.PolynomialLagrangian((2, 4)), data, ensemble_model=broken(2), record=record)
    z, errs, spreads = [], [], []
    for r in record:
        f = data[r["field"]]
        kept = [ldft.serve(ens.member(k), f.isel(t=slice(0, 2)), slices=f.sizes["t"]).field.values for k in (0, 1, 3)]
        assert len(kept) >= MIN_MEMBERS
        spread = np.sqrt(np.mean(np.stack(kept).std(axis=0, ddof=1).reshape(f.sizes["t"], -1) ** 2, axis=1))
        k = np.asarray(r["k"], dtype=int)[np.asarray(r["held"])]
        rel = np.asarray(r["rel"])[np.asarray(r["held"])]
        z.append(rel / (spread[k] / float(np.abs(f.values).max())))
        errs.append(rel)
        spreads.append(spread[k] / float(np.abs(f.values).max()))
    expected = float(np.quantile(np.concatenate(z), 0.95, method="higher")) / 2
    assert cal.spread_scale == pytest.approx(expected, rel=1e-9)
    # the scaled spread's mean over the mean error on the same slices (the law's std_over_error, for the spread)
    sharp = expected * np.concatenate(spreads).mean() / np.concatenate(errs).mean()
    assert cal.spread_std_over_error == pytest.approx(sharp, rel=1e-9)
    lone, _, _ = calibrate(ldft.PolynomialLagrangian((2, 4)), data, ensemble_model=broken(1, 2, 3))
    assert lone.spread_scale is None


def test_the_trials_selection_learned_are_taken_as_they_are() -> None:
    """Selection learns every candidate on the held-in slices: given those of the chosen one and the runner-up,
    the calibration takes them instead of learning them again, and measures the same law and samples."""
    _, data = oscillator_data(amplitudes=(0.4, 0.8, 1.2), steps=40)
    sel = ldft.select(ldft.PolynomialLagrangian((2, 2)), data, [{"orders": [2, 4]}])
    assert len(sel.trials) == 2 and all(t is not None and t.report_ is not None for t in sel.trials)
    fresh = [ldft.PolynomialLagrangian((2, 2)), ldft.PolynomialLagrangian((2, 4))]
    runner = (fresh[1 - sel.chosen], {"ridge": 0.0}, "other")
    again: list[dict] = []
    cal, _, trial = calibrate(fresh[sel.chosen], data, runner_up=runner, record=again, ridge=0.0)
    taken: list[dict] = []
    pair = (sel.trials[sel.chosen], sel.trials[1 - sel.chosen])
    reused, _, same = calibrate(fresh[sel.chosen], data, runner_up=runner, record=taken, learned=pair, ridge=0.0)
    assert same is sel.trials[sel.chosen] and taken == again
    assert {**reused.to_dict(), "wall_time": 0} == {**cal.to_dict(), "wall_time": 0}
    assert all(torch.equal(a, b) for a, b in zip(trial.state_dict().values(), same.state_dict().values()))


def test_the_fields_selection_served_are_taken_as_served_again(monkeypatch) -> None:
    """Selection keeps the fields its chosen candidate's and runner-up's trials served when scored (no other
    candidate's): each equals the same trial served again from the same field (to the bit), and the calibration
    given them measures the same law and samples as serving the trials itself, without serving them; a list that
    does not fit the fields is served again, and with ``selection_served_bytes = 0`` none is kept."""
    import latticedft._calibrate as calibrate_module

    _, data = oscillator_data(amplitudes=(0.4, 0.8, 1.2), steps=40)
    orders = [(2, 4), (2, 6), (2, 8)]
    sel = ldft.select(ldft.PolynomialLagrangian(orders[0]), data, [{"orders": list(o)} for o in orders[1:]])
    second = runner_up(sel.rows, sel.chosen)
    assert second is not None
    (dropped,) = {0, 1, 2} - {sel.chosen, second}
    assert sel.served[dropped] is None
    for i in (sel.chosen, second):
        assert sel.served[i] is not None and len(sel.served[i]) == len(data)
        for kept, f in zip(sel.served[i], data, strict=True):
            assert np.array_equal(kept, calibrate_module._served(sel.trials[i], f, None))
    fresh = ldft.PolynomialLagrangian(orders[sel.chosen])
    runner = (ldft.PolynomialLagrangian(orders[second]), {"ridge": 0.0}, "other")
    pair = (sel.trials[sel.chosen], sel.trials[second])
    again: list[dict] = []
    cal, _, _ = calibrate(fresh, data, runner_up=runner, record=again, learned=pair, ridge=0.0)
    calls = []
    serve_again = calibrate_module._served
    monkeypatch.setattr(calibrate_module, "_served", lambda *a: calls.append(a) or serve_again(*a))
    taken: list[dict] = []
    kept = (sel.served[sel.chosen], sel.served[second])
    reused, _, _ = calibrate(fresh, data, runner_up=runner, record=taken, learned=pair, served=kept, ridge=0.0)
    assert not calls and taken == again and reused.runner_up == "other"
    assert {**reused.to_dict(), "wall_time": 0} == {**cal.to_dict(), "wall_time": 0}
    unfit: list[dict] = []
    calibrate(fresh, data, runner_up=runner, record=unfit, learned=pair, served=(kept[0][:2], None), ridge=0.0)
    assert len(calls) == 2 * len(data) and unfit == again  # the chosen one's list is short: both served again
    with ldft.set_options(selection_served_bytes=0):
        none = ldft.select(ldft.PolynomialLagrangian(orders[0]), data, [{"orders": list(o)} for o in orders[1:]])
    assert none.served == [None, None, None] and none.chosen == sel.chosen


def _after_seed(seed: int) -> float:
    torch.manual_seed(seed)
    return torch.rand(1).item()


def test_the_scale_follows_the_measured_error_not_the_runner_up() -> None:
    """On held-out slices the trial's error is measured against the data: a runner-up that disagrees 100 times
    more shapes the exponent, not the scale."""
    from latticedft._calibrate import _fit, _Sample

    k = np.arange(2.0, 22.0)
    rel = 1e-6 * (k - 1)  # linear in the steps served
    held = k >= 16
    own = _fit([_Sample(k, held, rel, rel, False)], 0.95)
    wide = _fit([_Sample(k, held, rel, 100 * rel, True)], 0.95)
    assert own.exponent == pytest.approx(1.0) and wide.exponent == pytest.approx(1.0)
    assert wide.scale == pytest.approx(own.scale) == pytest.approx(1e-6 / 2)
    assert wide.coverage == own.coverage == 1.0


def test_a_trial_that_stops_on_many_held_out_slices_keeps_a_band_and_warns() -> None:
    """One field of ten whose trial stopped (10 % of the held-out slices, above 1 - 0.95): the scale is the
    quantile over the served slices, not the smallest float, and a warning says what it does not bound."""
    from latticedft._calibrate import _fit, _Sample, _stopped

    k = np.arange(2.0, 22.0)
    held = k >= 16
    rel = 1e-6 * (k - 1)
    stopped = np.where(k < 10, rel, np.nan)
    samples = [_Sample(k, held, rel, rel, False) for _ in range(9)] + [_Sample(k, held, stopped, stopped, False)]
    law = _fit(samples, 0.95)
    assert law.scale == pytest.approx(1e-6 / 2) and law.coverage == pytest.approx(0.9)
    (warning,) = _stopped(samples, 0.95)
    assert "stopped before 6 of 60 held-out slices (1 of 10 training fields)" in warning
    assert _stopped(samples[:9], 0.95) == []


def test_the_law_round_trips_and_warns_beyond_its_windows() -> None:
    law = _law()
    assert Calibration.from_dict(json.loads(json.dumps(law.to_dict()))) == law
    inside = np.linspace(-0.9, 0.9, 30)
    assert law.warnings(40, inside) == []
    longer, outside = law.warnings(41, inside), law.warnings(20, np.array([0.0, 1.5]))
    assert len(longer) == 1 and "serves 41 slices" in longer[0] and "at most 40" in longer[0]
    assert len(outside) == 1 and "outside the range" in outside[0]
    std = xr.DataArray(np.full((3, 2), 3.0), dims=("t", "x"))
    band = law.band(std, np.array([0.0, 4.0, 2.0]))  # the spread widened to the estimate where narrower
    np.testing.assert_allclose(band.values, [[3, 3], [4, 4], [3, 3]])
    # a measured spread scale: the scaled spread replaces the law, widened to the trial's disagreement only
    scaled = _law(spread_scale=0.5)
    two = xr.DataArray([[0.0, 0.0], [3.0, 1.0], [0.2, 0.2]], dims=("t", "x"))
    out = scaled.band(two, np.array([9.0, 9.0, 9.0]), np.array([1.0, 1.0, 0.5]))
    np.testing.assert_allclose(out.values, [[1, 1], [1.5, 0.5], [0.5, 0.5]])  # members that agree: the floor


def test_the_law_counts_the_steps_served() -> None:
    """A law measured now grows in the steps served, ``k - 1`` (slice 2 is the first step, error ``A * scale``); a
    law recorded before it (no ``origin``) keeps the slice index ``k``; the fit recovers an error ``c (k - 1)^p``."""
    from latticedft._calibrate import _fit, _Sample
    from latticedft._calibration_law import ORIGIN

    k = np.arange(2.0, 42.0)
    rel = 1e-6 * (k - 1) ** 1.5
    cal = _fit([_Sample(k, k >= 30, rel, rel, False)], 0.95)
    assert cal.origin == ORIGIN == 1.0 and "(k - 1)^exponent" in cal.law
    assert cal.exponent == pytest.approx(1.5, abs=1e-9) and 2 * cal.scale == pytest.approx(1e-6, rel=1e-9)
    np.testing.assert_allclose(cal.estimate(np.array([0, 1, 2, 5]), 2.0), [0, 0, 2 * cal.scale, 2 * cal.scale * 8])
    old = {k: v for k, v in _law(exponent=2.0).to_dict().items() if k != "origin"}
    np.testing.assert_allclose(Calibration.from_dict(old).estimate(np.array([2, 5]), 1.0), [4e-3, 25e-3])


def test_a_task_of_another_amplitude_than_the_training_fields_is_told() -> None:
    """Training fields of amplitudes 0.8 to 2.4 (cases/oscillator-sin's 0.4, 0.8, 1.2 launches): a task of range
    0.2 (its 0.1 launch) is told that the band does not bound it; one of range 1.2 inside is not."""
    law = _law(low=-1.2, high=1.2, span_low=0.8, span_high=2.4)
    assert law.warnings(40, np.linspace(-0.6, 0.6, 30)) == []
    (small,) = law.warnings(40, np.linspace(-0.1, 0.1, 30))
    assert "amplitude (range of values) 0.2 is outside the training fields' [0.8, 2.4]" in small
    assert law.warnings(40, np.linspace(-0.39, 0.39, 30)) == []  # within 5 % of the smallest
    assert len(law.warnings(40, np.linspace(-1.25, 1.3, 30))) == 1  # wider than the widest: 2.55 > 1.05 * 2.4


def test_too_short_data_say_so_in_one_line() -> None:
    short = [systems.oscillator_sin(1.0, n=3)]
    msg = too_short(short)
    assert msg is not None and "\n" not in msg and "too short for a held-out window" in msg
    assert too_short([systems.oscillator_sin(1.0, n=10)]) is None


def test_a_failed_noise_aware_fit_is_reported() -> None:
    """A noise-corrected trial that misses its held-out slices warns, whatever the second-difference share."""

    class Report:
        noise = {"method": "errors in variables", "second_difference_ratio": 0.49}

    class Trial:
        report_ = Report()

    bad = _noise_warnings(Trial(), [np.array([0.01, 2 * NOISE_FAILED])])  # type: ignore[arg-type]
    assert len(bad) == 1 and "failed its held-out check" in bad[0] and "0.49" in bad[0]
    assert _noise_warnings(Trial(), [np.array([0.01, NOISE_FAILED / 2])]) == []  # type: ignore[arg-type]
    stopped = _noise_warnings(Trial(), [np.array([0.01, np.nan])])  # type: ignore[arg-type]
    assert len(stopped) == 1 and "(it stopped;" in stopped[0]
    Report.noise = {"method": "none"}
    assert _noise_warnings(Trial(), [np.array([0.5])]) == []  # type: ignore[arg-type]


def test_a_calibrated_run_writes_the_estimate_and_its_coverage(tmp_path: Path, capsys) -> None:
    """``[train] calibrate = true``: summary.json holds the law and its held-out coverage, each task its estimate
    (``psi_err_est``) and how well it held; the figure is drawn; the served field is the uncalibrated run's."""
    case = tiny_wave(tmp_path)
    code, _, _ = run_cli(capsys, "run", case, "--out", tmp_path / "plain", "--set", "export.paraview=false")
    assert code == 0
    code, _, err = run_cli(
        capsys,
        "run",
        case,
        "--out",
        tmp_path / "cal",
        "--set",
        "train.calibrate=true",
        "--set",
        "export.paraview=false",
    )
    assert code == 0, err
    assert "calibration: err(k)" in err
    summary = json.loads((tmp_path / "cal" / "summary.json").read_text())
    law = summary["train"]["calibration"]
    assert 0 <= law["coverage"] <= 1 and law["held_out_slices"] > 0
    task = summary["tasks"]["test"]
    assert task["error_estimate"]["band"] == "held-out error"
    assert task["error_estimate"]["terms"] == ["law", "trial disagreement"]
    assert set(task["calibration"]) >= {"within_2std", "std_over_error"}
    with xr.open_dataset(tmp_path / "cal" / "test.nc") as ds, xr.open_dataset(tmp_path / "plain" / "test.nc") as p:
        assert ds["psi_err_est"].dims == ("t",) and np.all(ds["psi_err_est"].values[2:] > 0)
        xr.testing.assert_identical(ds["psi"], p["psi"])
    assert (tmp_path / "cal" / "test.png").stat().st_size > 0
    assert (tmp_path / "cal" / "calibration.pt").is_file()


def test_an_ensembles_calibrated_std_is_its_scaled_spread(tmp_path: Path, capsys) -> None:
    """``[train] ensemble`` (calibrated by default): the law records ``spread_scale``, and ``psi_std`` is the
    members' own (``psi_std_members``) times it, widened on no slice below the members' scaled spread."""
    case = tiny_wave(tmp_path)
    code, _, err = run_cli(
        capsys, "run", case, "--out", tmp_path / "ens", "--set", "train.ensemble=3", "--set", "export.paraview=false"
    )
    assert code == 0, err
    law = json.loads((tmp_path / "ens" / "summary.json").read_text())["train"]["calibration"]
    scale = law["spread_scale"]
    assert 0 < scale < np.inf
    with xr.open_dataset(tmp_path / "ens" / "test.nc") as ds:
        std, own = ds["psi_std"].values, ds["psi_std_members"].values
    rms = lambda a: np.sqrt(np.mean(a.reshape(a.shape[0], -1) ** 2, axis=1))  # noqa: E731
    assert np.all(rms(std)[2:] >= scale * rms(own)[2:] * (1 - 1e-12))
    kept = rms(std) <= scale * rms(own) * (1 + 1e-9)  # not widened to the trial's disagreement
    kept[:2] = False
    a, b = std[kept], own[kept]
    assert kept.any() and np.all(a[b == 0] == 0)
    np.testing.assert_allclose(a[b > 0] / b[b > 0], scale, rtol=1e-12)


def test_too_short_training_data_serve_without_a_band(tmp_path: Path, capsys) -> None:
    """Training fields of 3 slices: one warning line, no estimate; strict makes it exit status 4."""
    case = tmp_path / "short"
    (case / "data").mkdir(parents=True)
    write_field(case / "data" / "train.nc", {"psi": systems.wave_string([(1, 1.0)], nx=13, nt=3)})
    write_field(case / "data" / "test.nc", {"psi": systems.wave_string([(1, 0.5)], nx=13, nt=10)})
    write_toml(
        case,
        """
        [model]
        kind = "polynomial"
        orders = [2, 0]
        [train]
        data = ["data/train.nc"]
        calibrate = true
        [[serve]]
        name = "test"
        from = "data/test.nc"
        [run]
        threads = 1
        [export]
        paraview = false
        """,
    )
    code, _, err = run_cli(capsys, "run", case, "--out", tmp_path / "r", "--strict")
    assert code == 4, err
    lines = [ln for ln in err.splitlines() if "too short for a held-out window" in ln]
    assert len(lines) == 1
    summary = json.loads((tmp_path / "r" / "summary.json").read_text())
    assert "calibration" not in summary["train"]
    assert any("too short" in w for w in summary["warnings"])
    with xr.open_dataset(tmp_path / "r" / "test.nc") as ds:
        assert "psi_err_est" not in ds.data_vars
        assert any("too short" in w for w in json.loads(ds.attrs["latticedft_warnings"]))


def test_serve_again_uses_the_recorded_law_and_trial(tmp_path: Path, capsys) -> None:
    """``latticedft serve`` after a calibrated run: the law from summary.json, the trial from calibration.pt."""
    case = tiny_wave(tmp_path)
    toml = case / "case.toml"
    toml.write_text(toml.read_text().replace('data = ["data/train.nc"]', 'data = ["data/train.nc"]\ncalibrate = true'))
    out = tmp_path / "r"
    assert run_cli(capsys, "run", case, "--out", out, "--set", "export.paraview=false")[0] == 0
    with xr.open_dataset(out / "test.nc") as ds:
        first = ds["psi_err_est"].load()
    code, _, err = run_cli(capsys, "serve", case, "--out", out, "--set", "export.paraview=false")
    assert code == 0, err
    with xr.open_dataset(out / "test.nc") as ds:
        xr.testing.assert_identical(ds["psi_err_est"], first)


def test_auto_calibrates_after_selection_with_the_runner_up(tmp_path: Path, capsys, monkeypatch) -> None:
    """``calibrate = "auto"`` is on with ``[model] select``; the runner-up candidate's label is recorded when its
    score was within reach of the chosen one's. The trial and the runner-up are those selection learned, and the
    fields they served are those selection served (neither learned nor served again)."""
    import latticedft._calibrate as calibration

    def refit(*args: object) -> None:
        raise AssertionError("the calibration learned again a candidate that selection had learned")

    def serve_again(*args: object) -> None:
        raise AssertionError("the calibration served again a trial that selection had served")

    monkeypatch.setattr(calibration, "_trial", refit)
    monkeypatch.setattr(calibration, "_served", serve_again)
    case = tiny_wave(tmp_path)
    code, _, err = run_cli(
        capsys, "run", case, "--out", tmp_path / "r", "--set", 'model.select="auto"', "--set", "export.paraview=false"
    )
    assert code == 0, err
    summary = json.loads((tmp_path / "r" / "summary.json").read_text())
    law, sel = summary["train"]["calibration"], summary["train"]["selection"]
    labels = [r["label"] for r in sel["candidates"]]
    assert law["runner_up"] is None or (law["runner_up"] in labels and law["runner_up"] != sel["chosen_label"])
    with xr.open_dataset(tmp_path / "r" / "test.nc") as ds:
        assert "psi_err_est" in ds.data_vars


def test_a_law_with_no_held_out_error_measured_is_degenerate() -> None:
    """Every held-out slice unserved: no scale was measured, so the law is marked failed (it was recorded with a
    scale of the smallest float and 0 % held-out coverage); one served held-out slice is enough for a law."""
    from latticedft._calibrate import _degenerate, _Sample

    k = np.arange(2.0, 22.0)
    held = k >= 16
    stopped = np.where(k < 6, 1e-6 * k, np.nan)
    reason = _degenerate([_Sample(k, held, stopped, stopped, False) for _ in range(3)])
    assert reason is not None and "stopped before all 18 held-out slices" in reason
    one = np.where(k < 17, 1e-6 * k, np.nan)
    assert _degenerate([_Sample(k, held, stopped, stopped, False), _Sample(k, held, one, one, False)]) is None
    assert _degenerate([]) == "no held-out slice was measured"


def test_a_degenerate_law_is_a_failed_calibration(tmp_path: Path, capsys, monkeypatch) -> None:
    """A trial that serves no held-out slice: the run reports a failed calibration (exit status 4 when strict),
    records no law and writes no estimate."""
    import latticedft._calibrate as calibration

    measure = calibration._measure

    def stops(*args: object, **kwargs: object) -> list[object]:
        out = measure(*args, **kwargs)  # type: ignore[arg-type]
        for x in out:
            x.rel = np.where(x.held, np.nan, x.rel)
        return out  # type: ignore[return-value]

    monkeypatch.setattr(calibration, "_measure", stops)
    case = tiny_wave(tmp_path)
    code, _, err = run_cli(
        capsys,
        "run",
        case,
        "--out",
        tmp_path / "r",
        "--set",
        "train.calibrate=true",
        "--set",
        "export.paraview=false",
        "--strict",
    )
    assert code == 4, err
    assert "calibration: failed (the trial model's serve stopped before all" in err
    summary = json.loads((tmp_path / "r" / "summary.json").read_text())
    assert "calibration" not in summary["train"]
    with xr.open_dataset(tmp_path / "r" / "test.nc") as ds:
        assert "psi_err_est" not in ds.data_vars


def test_a_trial_takes_the_ridge_the_models_fit_chose(tmp_path: Path, capsys, monkeypatch) -> None:
    """``ridge = "auto"`` without model selection: the trial learns with the weight the served model's fit chose
    (as selection's trials and an ensemble's members do), not a weight chosen again on its 70 % of the data."""
    import latticedft._calibrate as calibration

    seen: list[object] = []
    trial = calibration._trial

    def record(fresh: object, train: object, boundary: object, kwargs: dict) -> object:
        seen.append(kwargs["ridge"])
        return trial(fresh, train, boundary, kwargs)  # type: ignore[arg-type]

    monkeypatch.setattr(calibration, "_trial", record)
    case = tiny_wave(tmp_path)
    sets = ["train.calibrate=true", 'train.ridge="auto"', "export.paraview=false"]
    code, _, err = run_cli(capsys, "run", case, "--out", tmp_path / "r", *[x for s in sets for x in ("--set", s)])
    assert code == 0, err
    chosen = json.loads((tmp_path / "r" / "summary.json").read_text())["train"]["ridge"]
    assert isinstance(chosen, float) and seen == [chosen]
    assert calibration.trial_keywords({"ridge": 0.5}, 1e-4) == {"ridge": 0.5}  # a weight given is kept
    assert calibration.trial_keywords({"ridge": "auto"}, None) == {"ridge": "auto"}
