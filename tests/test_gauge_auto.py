"""``gauge="auto"``: the better of unit-mass and trace by the training residual; the charged particle in a
magnetic field (a Lagrangian linear in the velocity), which only the trace gauge describes."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

import latticedft as ldft
from latticedft import systems
from latticedft._learn._api import AUTO_EXACT
from latticedft.io import write_field

from case_helpers import run_cli, write_toml

STARTS = [((0.1, 0.2), (0.5, 0.1)), ((-0.3, 0.1), (0.2, -0.4)), ((0.0, 0.0), (0.3, 0.3))]


def _orbits(n: int = 61) -> list:
    return [systems.charged_particle(q, v, B=1.0, n=n, dt=0.1) for q, v in STARTS]


def _test_orbit():
    return systems.charged_particle((0.2, -0.1), (-0.3, 0.2), B=1.0, n=201, dt=0.1)


# -- the system ------------------------------------------------------------------------------------------
def test_charged_particle_is_the_exact_circular_motion() -> None:
    q, v = systems.charged_particle((0.3, -0.2), (0.4, 0.1), B=1.5, n=400, dt=0.01, return_velocity=True)
    assert q.dims == ("t", "component") and list(q["component"].values) == ["x", "y"]
    centre = np.array([0.3 + 0.1 / 1.5, -0.2 - 0.4 / 1.5])  # q0 + (v_y, -v_x) / B
    radius = np.hypot(0.4, 0.1) / 1.5
    assert np.allclose(np.hypot(*(q.values - centre).T), radius, atol=1e-14)
    # the velocity is the time derivative of the position (central differences, O(dt^2)) ...
    dq = (q.values[2:] - q.values[:-2]) / 0.02
    assert np.abs(dq - v.values[1:-1]).max() < 1e-4
    # ... and obeys the Lorentz force x'' = B y', y'' = -B x'
    dv = (v.values[2:] - v.values[:-2]) / 0.02
    assert np.abs(dv - 1.5 * np.stack([v.values[1:-1, 1], -v.values[1:-1, 0]], -1)).max() < 1e-4
    assert np.allclose(systems.cyclotron_energy(v.values), 0.5 * (0.4**2 + 0.1**2))
    straight = systems.charged_particle((1.0, 2.0), (0.5, -1.0), B=0.0, n=3, dt=0.5)
    assert np.allclose(straight.values, [[1.0, 2.0], [1.25, 1.5], [1.5, 1.0]])
    with pytest.raises(ldft.InputError, match="v0"):
        systems.charged_particle(v0=(1.0,))


# -- the gauges ----------------------------------------------------------------------------------------------
def test_unit_mass_cannot_describe_the_magnetic_term_trace_can() -> None:
    unit = ldft.PolynomialLagrangian(orders=(2, 2))
    r_unit = ldft.learn(unit, _orbits(), gauge="unit-mass")
    trace = ldft.PolynomialLagrangian(orders=(2, 2))
    r_trace = ldft.learn(trace, _orbits(), gauge="trace")
    assert r_unit.rel_res > 1e-3 and r_trace.rel_res < 1e-11
    assert ldft.compare(ldft.serve(unit, _test_orbit()).field, _test_orbit())["max_error"] > 0.1


def test_auto_learns_the_charged_particle_exactly_and_serves_it() -> None:
    model = ldft.PolynomialLagrangian(orders=(2, 2))
    report = ldft.learn(model, _orbits(), gauge="auto")
    assert report.gauge == "trace" and report.gauge_requested == "auto"
    assert set(report.gauge_scores) == {"unit-mass", "trace"}
    assert report.gauge_scores["trace"] < 1e-11 < 1e-3 < report.gauge_scores["unit-mass"]
    assert report.rel_res < 1e-11 and "trace" in report.gauge_choice
    assert "gauge trace (auto" in report.summary_line()
    d = report.to_dict()
    assert d["gauge"] == "trace" and d["gauge_requested"] == "auto" and json.dumps(d)
    served = ldft.serve(model, _test_orbit())  # 200 steps, three cyclotron periods
    assert served.complete
    assert ldft.compare(served.field, _test_orbit())["max_error"] < 1e-6
    # the model file records the gauge chosen
    assert model.report_ is report


def test_auto_on_a_scalar_field_is_unit_mass_bit_for_bit() -> None:
    train = [systems.oscillator_wells(a, n=101, dt=0.5) for a in (1.7, 1.2, 0.6)]
    plain = ldft.PolynomialLagrangian(orders=(4, 8), time_symmetric=True)
    auto = ldft.PolynomialLagrangian(orders=(4, 8), time_symmetric=True)
    r_plain, r_auto = ldft.learn(plain, train, gauge="unit-mass"), ldft.learn(auto, train)  # auto: the default
    assert torch.equal(plain.coef, auto.coef)
    assert r_auto.gauge == "unit-mass" and r_auto.gauge_scores == {"unit-mass": r_plain.rel_res}
    assert "one component" in r_auto.gauge_choice and r_plain.gauge_requested is None


def test_auto_keeps_an_exact_unit_mass_fit_on_a_vector_field() -> None:
    orbits = [r.field for r in ldft.serve(ldft.lagrangians.kepler(), _kepler_launches(), slices=40)]
    plain = ldft.PolynomialLagrangian(orders=(2, 2))
    auto = ldft.PolynomialLagrangian(orders=(2, 2))
    r_plain, r_auto = ldft.learn(plain, orbits, gauge="unit-mass"), ldft.learn(auto, orbits, gauge="auto")
    assert torch.equal(plain.coef, auto.coef) and r_auto.gauge == "unit-mass"
    if r_plain.rel_res <= AUTO_EXACT:
        assert list(r_auto.gauge_scores) == ["unit-mass"]
    else:  # fitted trace too and kept unit-mass
        assert r_auto.gauge_scores["trace"] >= 0.1 * r_plain.rel_res or "invertible" in r_auto.gauge_choice


def _kepler_launches() -> list:
    dt = 0.05
    return [
        systems.make_field([[r, 0.0], [r, v * dt]], ["t"], spacing=dt, components=["x", "y"])
        for r, v in ((1.0, 1.0), (1.2, 0.8), (0.8, 1.2))
    ]


def test_auto_with_a_unit_mass_by_construction_model_trains_once() -> None:
    orbits = [r.field for r in ldft.serve(ldft.lagrangians.kepler(), _kepler_launches(), slices=30)]
    model = ldft.MLPLagrangian(preset="radial", hidden=[4], seed=0)
    report = ldft.learn(model, orbits, gauge="auto", max_iter=3)
    assert report.gauge == "unit-mass" and "by construction" in report.gauge_choice
    assert list(report.gauge_scores) == ["unit-mass"]


def test_auto_is_no_gauge_to_measure_with() -> None:
    model = ldft.PolynomialLagrangian(orders=(2, 2))
    ldft.learn(model, _orbits(), gauge="auto")
    with pytest.raises(ldft.InputError, match="gauge"):
        ldft.diagnose(model, _orbits(), gauge="auto")
    assert "auto" in ldft.GAUGES


# -- through a case ------------------------------------------------------------------------------------------
def test_a_case_by_default_chooses_its_gauge_and_records_the_choice(tmp_path: Path, capsys) -> None:
    case = tmp_path / "magnetic"
    (case / "data").mkdir(parents=True)
    for i, orbit in enumerate(_orbits()):
        write_field(case / "data" / f"train_{i}.nc", {"psi": orbit})
    write_field(case / "data" / "test.nc", {"psi": _test_orbit()})
    write_toml(
        case,
        """
        [model]
        kind = "polynomial"
        orders = [2, 2]
        [train]
        data = ["data/train_*.nc"]
        [[serve]]
        name = "test"
        from = "data/test.nc"
        [run]
        threads = 1
        [export]
        formats = []
        """,
    )
    code, _, err = run_cli(capsys, "run", case)
    assert code == 0, err
    summary = json.loads((case / "results" / "summary.json").read_text())
    train = summary["train"]
    assert train["gauge"] == "trace" and train["gauge_requested"] == "auto" and train["rel_res"] < 1e-11
    assert summary["tasks"]["test"]["max_error"] < 1e-6
    assert "gauge trace (auto" in (case / "results" / "run.log").read_text()
    assert "gauge trace (auto" in err
    assert json.loads((case / "results" / "model.json").read_text())["gauge"] == "trace"
