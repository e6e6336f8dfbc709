"""Fast modes of the field cases of issue 5 (cases/klein-gordon-periodic, sine-gordon, wave-2d).

Each builds a smaller version of its case (fewer sites, fewer steps) and asserts the accuracy figure the
full case documents; the full-size runs are the commands in each case's README.md and docs/field-cases.md.
"""

from __future__ import annotations

import importlib.util
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

import latticedft as ldft
from latticedft import systems
from latticedft.cli import main

REPO = Path(__file__).resolve().parents[1]
CASES = REPO / "cases"


def _module(case: str):
    spec = importlib.util.spec_from_file_location(f"make_data_{case.replace('-', '_')}", CASES / case / "make_data.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_klein_gordon_polynomial_round_off():
    """The true L_d lies in the span of orders (2, 2): learned and served to round-off."""
    data = systems.klein_gordon_training_set(n=10, steps=20, seed=0)
    test = systems.klein_gordon_test_field(steps=100)
    model = ldft.PolynomialLagrangian(orders=(2, 2))
    report = ldft.learn(model, data)
    assert report.rel_res < 1e-10
    res = ldft.serve(model, test.isel(t=slice(0, 2)), steps=101, boundary="periodic")
    err = ldft.compare(res.field, test)
    assert err["max_error"] < 1e-11
    energy = systems.klein_gordon_energy(res.field).values
    assert np.ptp(energy) < 1e-11 * energy[0]


def test_klein_gordon_mlp_beats_the_peers():
    """Kinetic-potential MLP (1 -> 10 -> 10 -> 1 tanh) on 20 of the peers' fields, 40 L-BFGS iterations:
    the unseen k = 2 field over 20 steps within the issue's target 5e-3 (peers' NN: 0.057)."""
    data = systems.klein_gordon_training_set(n=20, steps=20, seed=0)
    test = systems.klein_gordon_test_field(steps=20)
    model = ldft.MLPLagrangian(hidden=[10, 10], activation="tanh", form="kinetic-potential", seed=0)
    report = ldft.learn(model, data, optimizer="lbfgs", max_iter=40)
    assert report.rel_res < 1e-2
    res = ldft.serve(model, test.isel(t=slice(0, 2)), steps=21, boundary="periodic")
    assert ldft.compare(res.field, test)["max_error"] < 5e-3


def test_sine_gordon_one_breather_serves_a_collision():
    """The case's lattice (dx = 0.1, dt = 0.05) on a shorter window x in [-10, 10]:
    trained on one breather, the structured polynomial serves the kink-antikink collision closer to the exact
    solution than the leapfrog of the true equation."""
    lat = {"xlim": (-10.0, 10.0), "nx": 201, "dt": 0.05}
    train = systems.sine_gordon_breather(0.3, nt=401, **lat)
    kk = systems.kink_antikink(0.5, nt=81, t0=-2.0, **lat)
    model = ldft.PolynomialLagrangian(orders=(2, 12), time_symmetric=True)
    report = ldft.learn(model, train, ridge="auto")
    assert report.rel_res < 1e-2
    res = ldft.serve(model, kk, boundary="dirichlet")
    ours = ldft.compare(res.field, kk)["max_error"]
    base = ldft.compare(_module("sine-gordon")._leapfrog(kk), kk)["max_error"]
    assert ours < base
    assert ours < 2e-2


def test_wave_2d_case_fast_mode(tmp_path):
    """The wave-2d case folder on a 33 x 33 membrane, 60 steps, through `latticedft run`."""
    case = tmp_path / "wave-2d"
    case.mkdir()
    shutil.copy(CASES / "wave-2d" / "case.toml", case / "case.toml")
    _module("wave-2d").main(["--size", "33", "--steps", "60", "--out", str(case / "data")])
    rc = main(["run", str(case), "-q", "--set", "export.max_frames=4", "--set", "export.figures=false",
               "--set", "run.threads=1"])
    assert rc == 0
    task = json.loads((case / "results" / "summary.json").read_text())["tasks"]["test"]
    assert task["complete"] and task["slices"] == 61
    assert task["max_error"] < 2e-2
    assert task["max_error"] < task["baseline"]["max_error"]
    assert task["invariant_drift"] < 1e-2
    assert (case / "results" / "test.pvd").is_file()
