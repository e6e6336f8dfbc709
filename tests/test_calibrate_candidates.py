"""The candidates' check: the two best candidates' trials, served from a task's start, disagree far more on a
task between the training orbits than on the training fields, and the task draws a warning."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import xarray as xr

import latticedft as ldft
from latticedft import systems
from latticedft._calibrate import (
    Calibration,
    calibrate,
    candidates_disagreement,
    served_along,
)
from latticedft._calibration_law import CANDIDATES_RATIO
from latticedft._run._calib import task_band
from latticedft.io import write_field

from case_helpers import run_cli, write_toml

ROOT = Path(__file__).resolve().parent.parent
WARNING = "calibration: the two best candidates"


def _launch(a: float) -> xr.DataArray:
    """The oscillator of ``cases/oscillator-sin`` from rest at ``a`` (51 slices, dt = 1)."""
    return systems.oscillator_sin(a, 0.0, n=51, dt=1.0)


@pytest.fixture(scope="module")
def learned() -> tuple[Calibration, ldft.AbstractLagrangian, ldft.AbstractLagrangian, ldft.AbstractLagrangian]:
    """The law, the trial, the runner-up's trial (orders (4, 12) beside the chosen (4, 8)) and the model learned
    on all of three launches (1.2, 0.8, 0.4)."""
    train = [_launch(a) for a in (1.2, 0.8, 0.4)]
    second: list[ldft.AbstractLagrangian] = []
    runner = (ldft.PolynomialLagrangian((4, 12)), {"ridge": 0.0}, "orders=[4, 12]")
    cal, _, trial = calibrate(
        ldft.PolynomialLagrangian((4, 8)), train, runner_up=runner, chosen="hand-set", runner_trial=second, ridge=0.0
    )
    model = ldft.PolynomialLagrangian((4, 8))
    ldft.learn(model, train, ridge=0.0, progress=False)
    return cal, trial, second[0], model


def _band(learned, a: float, between: bool = True):  # noqa: ANN001, ANN202
    cal, trial, runner, model = learned
    field = ldft.serve(model, _launch(a)[:2], slices=51, progress=False).field
    mine = served_along(trial, field[:2], field, slices=51)
    other = candidates_disagreement(np.asarray(field.values), mine, 51)
    theirs = served_along(runner, field[:2], field, slices=51)
    d = candidates_disagreement(mine, theirs, 51) if between else None
    return task_band(cal.to_dict(), field, None, other, between=d)


def test_the_law_records_the_training_disagreement_of_the_two_trials(learned) -> None:  # noqa: ANN001
    """Per slice of the longest training field, the largest over the training fields of the two trials'
    relative disagreement: 0 on the two given slices, positive beyond; the runner-up's trial is handed back."""
    cal, trial, runner, _ = learned
    assert cal.chosen == "hand-set" and cal.runner_up == "orders=[4, 12]"
    assert cal.candidates is not None and len(cal.candidates) == cal.slices == 51
    assert cal.candidates[:2] == [0.0, 0.0] and all(c is not None and c > 0 for c in cal.candidates[2:])
    assert runner is not trial and runner.report_ is not None


def test_a_task_between_the_training_orbits_warns_and_one_on_a_training_orbit_does_not(learned) -> None:  # noqa: ANN001
    """The launch from 1.2 (a training orbit) is served as the training fields are: no warning; -0.6 (inside the
    training range and amplitudes, between the orbits) warns, naming both candidates. The band is the same with
    or without the check (a warning, not a band)."""
    on, between = _band(learned, 1.2), _band(learned, -0.6)
    assert on.record["candidates_ratio"] < CANDIDATES_RATIO and not any(WARNING in w for w in on.warnings)
    assert between.record["candidates_ratio"] > CANDIDATES_RATIO
    (warning,) = [w for w in between.warnings if WARNING in w]
    assert "(hand-set, orders=[4, 12])" in warning and "median over its first 49 slices" in warning
    plain = _band(learned, -0.6, between=False)
    assert "candidates_ratio" not in plain.record and not any(WARNING in w for w in plain.warnings)
    assert np.array_equal(plain.err_est.values, between.err_est.values)


def test_the_record_round_trips_through_json_and_an_older_one_loads(learned) -> None:  # noqa: ANN001
    """The law with its training disagreement goes through JSON (a serve that stopped: None) and back; a law
    recorded before it loads without one, and gives no ratio and no warning."""
    cal = learned[0]
    d = cal.to_dict()
    d["candidates"] = [*d["candidates"][:-1], None]
    back = Calibration.from_dict(json.loads(json.dumps(d)))
    assert back.candidates == d["candidates"] and back.chosen == "hand-set"
    ratio = back.candidates_ratio(np.full(51, 1e-3), np.arange(51))
    assert ratio is not None and np.isfinite(ratio)
    old = Calibration.from_dict({k: v for k, v in d.items() if k not in ("candidates", "chosen")})
    assert old.candidates is None and old.candidates_ratio(np.ones(51), np.arange(51)) is None
    assert old.candidates_warning(None, 49) is None


def test_without_a_runner_up_nothing_is_recorded() -> None:
    """No runner-up: no training disagreement, no runner-up trial."""
    second: list[ldft.AbstractLagrangian] = []
    cal, _, _ = calibrate(ldft.PolynomialLagrangian((4, 8)), [_launch(a) for a in (1.2, 0.4)], runner_trial=second)
    assert cal.candidates is None and cal.chosen is None and second == []


def _case(tmp: Path) -> Path:
    """``cases/oscillator-sin``'s training data, the training launch served again and the launch from -0.6 given
    by its first two slices alone (no reference: no warning of its error, the candidates' is the only one)."""
    case = tmp / "osc"
    (case / "data").mkdir(parents=True)
    for name in ("train_0.40", "train_0.80", "train_1.20"):
        shutil.copy(ROOT / "cases" / "oscillator-sin" / "data" / f"{name}.nc", case / "data")
    write_field(case / "data" / "start_m0.60.nc", {"psi": _launch(-0.6)[:2]})
    write_toml(
        case,
        """
        [model]
        kind = "polynomial"
        orders = [4, 8]
        select = "auto"
        [train]
        data = ["data/train_*.nc"]
        ridge = "auto"
        [[serve]]
        name = "train"
        from = "data/train_1.20.nc"
        [[serve]]
        name = "between"
        from = "data/start_m0.60.nc"
        slices = 51
        [export]
        paraview = false
        """,
    )
    return case


@pytest.mark.slow
def test_a_run_warns_on_the_task_between_the_orbits_and_strict_exits_4(tmp_path: Path, capsys) -> None:  # noqa: ANN001
    """With ``[model] select`` the runner-up's trial is written beside the trial; the launch from -0.6 warns
    (console, run.log, summary.json, the task file, its figure) and ``--strict`` exits 4; the training launch
    does not. Served again (``latticedft serve``), the same; without the runner-up's file (a run before the
    check), nothing warns, the exit status is 0 and the band is the same to the bit."""
    case, out = _case(tmp_path), tmp_path / "r"
    code, _, err = run_cli(capsys, "run", case, "--out", out, "--strict")
    assert code == 4 and f"task between: {WARNING}" in err
    assert (out / "calibration_runner_up.pt").is_file()
    summary = json.loads((out / "summary.json").read_text())
    assert summary["train"]["calibration"]["candidates"] is not None
    tasks = summary["tasks"]
    assert [w for w in tasks["between"]["warnings"] if WARNING not in w] == [] and tasks["between"]["warnings"]
    assert tasks["train"]["warnings"] == [] and summary["train"]["warnings"] == []
    assert tasks["between"]["error_estimate"]["candidates_ratio"] > CANDIDATES_RATIO
    assert WARNING in (out / "run.log").read_text() and (out / "between.png").stat().st_size > 0
    with xr.open_dataset(out / "between.nc") as ds:
        assert WARNING in ds.attrs["latticedft_warnings"]
        band = ds["psi_err_est"].load()
    code, _, err = run_cli(capsys, "serve", case, "--out", out, "--strict")  # the runner-up read back
    assert code == 4 and f"task between: {WARNING}" in err
    (out / "calibration_runner_up.pt").unlink()
    code, _, err = run_cli(capsys, "serve", case, "--out", out, "--strict")
    assert code == 0 and WARNING not in err, err
    with xr.open_dataset(out / "between.nc") as ds:
        xr.testing.assert_identical(ds["psi_err_est"], band)
