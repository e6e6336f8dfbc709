"""``benchmarks.calibration_rules`` scores other calibration laws on the slices ``benchmarks.calibration
--record`` wrote: its rule ``today`` must give back the recorded bands and law, or its scores of the other rules
would be of other slices than the table's."""

from __future__ import annotations

import json

import numpy as np
import pytest

import latticedft as ldft
from benchmarks import calibration, calibration_rules
from benchmarks.calibration_rules import RULES, Rule, bands, meets, read, refit, reproduced, score

from helpers import oscillator_data


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    """A row of the calibration benchmark (a quadratic model of the quartic oscillator: an error that grows),
    recorded as ``--record`` records it."""
    _, (low, high, middle) = oscillator_data(amplitudes=(0.4, 1.2, 0.8), steps=60)
    setup = calibration.Setup(
        label="quartic",
        train=[low, high],
        tests=[(middle, middle, 60, None), (high, high, 60, None)],
        model=lambda: ldft.PolynomialLagrangian((2, 2)),
        select=False,
    )
    path = tmp_path_factory.mktemp("rules") / "record.json"
    saved = dict(calibration.ONLY)
    calibration.ONLY["record"] = str(path)
    try:
        calibration.measure(setup, 0.0)
    finally:
        calibration.ONLY.clear()
        calibration.ONLY.update(saved)
    return path


def test_the_rule_today_gives_back_the_recorded_law_and_bands(recorded):
    (row,) = read([str(recorded)])
    assert len(row.tests) == 2 and all("ensemble" in t for t in row.tests)
    law = refit(row, RULES[0])
    assert law.scale == pytest.approx(row.law["scale"], rel=1e-12)
    assert law.exponent == pytest.approx(row.law["exponent"], rel=1e-12, abs=1e-15)
    assert reproduced([row]) <= calibration_rules.REPRODUCED
    # the error grows beyond round-off, so the bands are a measurement and not zero
    assert all(float(np.nanmax(t["error"])) > 1e-8 for t in row.tests)


def test_a_rule_that_changes_the_law_changes_the_band_and_is_told_from_the_record(recorded):
    (row,) = read([str(recorded)])
    base = bands(row, RULES[0])
    narrow = bands(row, Rule("half", quantile=0.5))
    law_base = refit(row, RULES[0])
    assert refit(row, Rule("half", quantile=0.5)).scale < law_base.scale
    assert all(np.all(n["single"] <= b["single"]) for n, b in zip(narrow, base, strict=True))
    # a record whose single band is not the law's: `today` no longer reproduces it
    row.tests[0]["single"] = np.asarray(row.tests[0]["single"]) * 1.5
    assert reproduced([row]) > 0.1


def test_score_counts_the_slices_within_twice_the_band(tmp_path):
    row = calibration_rules.Row("x", 0.0, {}, [], [{"error": np.array([1.0, 1.0, 4.0, np.nan])}])
    s = score(row, [{"single": np.array([1.0, 0.5, 1.0, 1.0])}], "single")
    assert s == pytest.approx((2 / 3, 2.5 / 6))
    assert not meets(s) and meets((0.9, 1.0)) and not meets((1.0, 1.0)) and score(row, [{}], "ensemble") is None


def test_the_script_stops_on_a_record_of_another_law(recorded, tmp_path, capsys):
    data = json.loads(recorded.read_text())
    data[0]["law"]["scale"] *= 3
    other = tmp_path / "other.json"
    other.write_text(json.dumps(data))
    assert calibration_rules.main([str(recorded), "--rows"]) == 0
    out = capsys.readouterr().out
    assert "| today |" in out and "| quartic (noise 0) |" in out
    assert calibration_rules.main([str(other)]) == 1
