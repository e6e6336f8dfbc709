"""Symmetries and Noether charges in case runs: ``[[serve]] charges``, ``[train] symmetries``, ``parity = "even"``.

Tiny Kepler and Klein-Gordon cases in tmp_path, run through the command line in-process: the charges are
variables of the task file, their drifts in summary.json meet the targets of docs/symmetries.md, bad names
are refused at ``check`` in one line, and the training symmetries are recorded.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
import xarray as xr

import latticedft as ldft
from latticedft import systems
from latticedft.io import write_field

from case_helpers import oscillator_case, run_cli, snapshot, tiny_wave, write_toml
from helpers import oscillator_data


@pytest.fixture(autouse=True)
def _one_thread():
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def kepler_case(tmp: Path) -> Path:
    """A radial Kepler theory learned briefly from three planets; one launch served for one period."""
    case = tmp / "kepler"
    (case / "data").mkdir(parents=True)
    for p in ("Venus", "Earth", "Mars"):
        write_field(case / "data" / f"train_{p}.nc", {"psi": systems.planet_orbit(p)})
    write_field(case / "data" / "earth.nc", {"psi": systems.kepler_orbit(1.0167, 1.13)})
    return write_toml(
        case,
        """
        [model]
        kind = "mlp"
        preset = "radial"
        hidden = [8]
        [train]
        data = ["data/train_*.nc"]
        max_iter = 30
        symmetries = true
        [[serve]]
        name = "earth"
        from = "data/earth.nc"
        charges = ["rotation-xy", "energy"]
        [run]
        threads = 1
        [export]
        formats = []
        """,
    )


def klein_gordon_case(tmp: Path) -> Path:
    """The periodic Klein-Gordon lattice: ten training fields, a travelling wave (modes 1 and 3) served."""
    case = tmp / "kg"
    (case / "data").mkdir(parents=True)
    for i, f in enumerate(systems.klein_gordon_training_set(n=10, steps=20, seed=0)):
        write_field(case / "data" / f"train_{i}.nc", {"psi": f})
    x = 0.05 * np.arange(20)

    def wave(s: float) -> np.ndarray:
        return np.sin(2 * np.pi * (x - s)) + 0.3 * np.cos(6 * np.pi * (x - s))

    write_field(case / "data" / "travelling.nc", {"psi": systems.klein_gordon(wave(0.0), wave(0.03), steps=1)})
    return write_toml(
        case,
        """
        [model]
        kind = "polynomial"
        orders = [2, 2]
        [train]
        data = ["data/train_*.nc"]
        boundary = "periodic"
        [[serve]]
        name = "travelling"
        from = "data/travelling.nc"
        slices = 201
        boundary = "periodic"
        charges = ["auto", "energy"]
        [run]
        threads = 1
        [export]
        formats = []
        """,
    )


@pytest.fixture(scope="module")
def kepler_run(tmp_path_factory) -> Path:
    case = kepler_case(tmp_path_factory.mktemp("charges"))
    assert ldft.cli.main(["run", str(case)]) == 0
    return case


def test_charges_are_variables_of_the_task_file(kepler_run: Path) -> None:
    with xr.open_dataset(kepler_run / "results" / "earth.nc") as ds:
        assert {"psi", "charge_rotation_xy", "energy"} <= set(ds.data_vars)
        j = ds["charge_rotation_xy"]
        assert j.dims == ("t",) and j.sizes["t"] == ds["psi"].sizes["t"]
        assert np.isnan(j.values[0]) and np.isfinite(j.values[1:]).all()  # a slab's charge, at its later slice
        assert "angular momentum" in j.attrs["long_name"] and j.attrs["symmetry"] == "rotation-xy"
        assert j.attrs["units"] == "au^2/(58.14 days)"  # psi in au, t in units of 58.14 days, unit mass
        assert ds["energy"].attrs["units"] == "au^2/(58.14 days)^2"
        for var in ("charge_rotation_xy", "energy"):
            assert ds[var].attrs["relative_drift"] >= 0 and ds[var].attrs["scale"] > 0
        # L = x v_y - y v_x of the launch (r0 = 1.0167, v0 = 1.13), to the accuracy of the discrete momentum
        assert abs(float(j.values[1]) - 1.0167 * 1.13) < 1e-2


def test_charge_drifts_in_summary_log_and_info(kepler_run: Path, capsys) -> None:
    res = kepler_run / "results"
    summary = json.loads((res / "summary.json").read_text())
    charges = summary["tasks"]["earth"]["charges"]
    assert set(charges) == {"rotation-xy", "energy"}
    assert charges["rotation-xy"]["variable"] == "charge_rotation_xy"
    assert charges["rotation-xy"]["relative_drift"] < 1e-10  # the target of docs/symmetries.md
    assert charges["energy"]["relative_drift"] < 1e-2  # bounded oscillation, O(dt^2)
    log = (res / "run.log").read_text()
    assert "drift rotation-xy" in log
    code, out, _ = run_cli(capsys, "info", kepler_run)
    assert code == 0 and "rotation-xy drift" in out


def test_training_symmetries_recorded(kepler_run: Path, capsys) -> None:
    res = kepler_run / "results"
    summary = json.loads((res / "summary.json").read_text())
    reports = {r["name"]: r for r in summary["train"]["symmetries"]}
    assert set(reports) == {"shift-x", "shift-y", "reflection", "rotation-xy", "time-reversal"}
    assert reports["rotation-xy"]["verdict"] == "exact" and reports["rotation-xy"]["residual"] < 1e-12
    assert reports["shift-x"]["verdict"] == "broken"
    assert set(reports["rotation-xy"]) == {"name", "kind", "residual", "residual_equations", "verdict"}
    model = json.loads((res / "model.json").read_text())
    assert model["training"]["symmetries"] == summary["train"]["symmetries"]
    log = (res / "run.log").read_text()
    assert "symmetries of the learned L_d over the training data" in log
    assert any("rotation-xy" in ln and ln.rstrip().endswith("exact") for ln in log.splitlines())
    code, out, _ = run_cli(capsys, "info", kepler_run)
    assert code == 0 and "symmetries of the learned L_d" in out


def test_no_symmetries_key_unless_asked(tmp_path: Path) -> None:
    case = tiny_wave(tmp_path)
    assert ldft.cli.main(["train", str(case), "-q"]) == 0
    summary = json.loads((case / "results" / "summary.json").read_text())
    assert "symmetries" not in summary["train"]


def test_pseudo_momentum_of_the_periodic_klein_gordon_theory(tmp_path: Path, capsys) -> None:
    case = klein_gordon_case(tmp_path)
    code, _, err = run_cli(capsys, "run", case)
    assert code == 0, err
    task = json.loads((case / "results" / "summary.json").read_text())["tasks"]["travelling"]
    # "auto": the continuous symmetries exact on the served field. The mass term breaks the field shift,
    # though not on this wave of zero mean (its strict residual vanishes): the equations residual tells
    verdicts = {r["name"]: r["verdict"] for r in task["charges_auto"]}
    assert verdicts == {"shift": "on the data only", "momentum-x": "exact"}
    assert list(task["charges"]) == ["energy", "momentum-x"]
    assert task["charges"]["momentum-x"]["relative_drift"] < 1e-10  # target: 1e-10
    assert task["charges"]["energy"]["relative_drift"] < 1e-10  # quadratic L_d: conserved to round-off
    assert "drift energy" in err and "momentum-x" in err
    with xr.open_dataset(case / "results" / "travelling.nc") as ds:
        p = ds["charge_momentum_x"]
        assert p.attrs["long_name"].startswith("lattice pseudo-momentum along x")
        assert p.attrs["units"] == "1"  # the lattice is in dimensionless units
        assert np.ptp(p.values[1:]) <= 1e-10 * p.attrs["scale"]


def test_charges_of_an_incomplete_task_cover_its_solved_slices(tmp_path: Path) -> None:
    case = oscillator_case(tmp_path)
    charges = 'serve.outside.charges=["energy", "auto"]'
    assert ldft.cli.main(["run", str(case), "-q", "--set", charges, "--set", "export.formats=[]"]) == 3
    task = json.loads((case / "results" / "summary.json").read_text())["tasks"]["outside"]
    assert not task["complete"] and task["slices"] < task["requested_slices"]
    assert list(task["charges"]) == ["energy"]  # "auto": the shift is broken, nothing else to test in 1D
    assert [r["verdict"] for r in task["charges_auto"]] == ["broken"]
    with xr.open_dataset(case / "results" / "outside.nc") as ds:
        e = ds["energy"].values
        assert e.shape == (task["slices"],) and np.isnan(e[0]) and np.isfinite(e[1:]).all()


def _refused(capsys, case: Path, charges: str, *needles: str) -> None:
    before = snapshot(case)
    code, _, err = run_cli(capsys, "check", case, "--set", f"serve.earth.charges={charges}")
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert code != 0 and len(lines) == 1 and "Traceback" not in err, err
    assert lines[0].startswith("latticedft: error: ") and "serve[0].charges" in lines[0]
    for n in needles:
        assert n in lines[0], (n, lines[0])
    assert snapshot(case) == before


def test_bad_charge_names_refused_at_check(tmp_path: Path, capsys) -> None:
    case = kepler_case(tmp_path)
    _refused(capsys, case, '["rotaton-xy"]', "unknown charge 'rotaton-xy'", "did you mean 'rotation-xy'?")
    _refused(capsys, case, '["reflection"]', "'reflection' is a discrete symmetry")
    _refused(capsys, case, '["energy", "energy"]', "'energy' listed twice")
    _refused(capsys, case, '["momentum-x"]', "unknown charge 'momentum-x'", "rotation-xy")
    code, out, _ = run_cli(capsys, "check", case)
    assert code == 0 and "charges ['rotation-xy', 'energy']" in out


def test_momentum_on_a_dirichlet_axis_refused(tmp_path: Path, capsys) -> None:
    case = tiny_wave(tmp_path)
    code, _, err = run_cli(capsys, "check", case, "--set", 'serve.test.charges=["momentum-x"]')
    assert code != 0 and len(err.strip().splitlines()) == 1, err
    assert "'momentum-x' needs a periodic axis 'x'" in err and "dirichlet" in err
    code, _, err = run_cli(capsys, "check", case, "--set", "train.symmetries=1")
    assert code != 0 and "train.symmetries: expected true or false" in err


def test_diagnose_reports_symmetries() -> None:
    orbits = [systems.planet_orbit(p) for p in ("Earth", "Mars")]
    model = ldft.MLPLagrangian(preset="radial", hidden=[8])
    report = ldft.learn(model, orbits, max_iter=3, symmetries=True)
    assert [r["name"] for r in report.symmetries] == [
        "shift-x",
        "shift-y",
        "reflection",
        "rotation-xy",
        "time-reversal",
    ]
    assert any(line.startswith("rotation-xy") and line.endswith("exact") for line in report.symmetry_lines())
    plain = ldft.diagnose(model, orbits)
    assert "symmetries" not in plain
    diag = ldft.diagnose(model, orbits, symmetries=["rotation-xy"])
    assert [r["verdict"] for r in diag["symmetries"]] == ["exact"]
    assert diag["rel_res"] == plain["rel_res"]
    with pytest.raises(ldft.InputError, match="symmetries"):
        ldft.learn(model, orbits, max_iter=1, symmetries="yes")


# -- a symmetric model by construction -------------------------------------------------------------------
def test_even_parity_polynomial_is_reflection_invariant_exactly() -> None:
    _, data = oscillator_data()
    free = ldft.PolynomialLagrangian((4, 8))
    even = ldft.PolynomialLagrangian((4, 8), parity="even")
    r_free, r_even = ldft.learn(free, data), ldft.learn(even, data)
    assert r_even.rel_res < 1e-8 and r_free.rel_res < 1e-8
    exps = {tuple(e) for e in free.exponents.tolist()}
    assert {tuple(e) for e in even.exponents.tolist()} == {e for e in exps if sum(e) % 2 == 0}
    assert float(even.center[0]) == 0.0  # the mean is scaled about 0
    refl = {r.name: r for r in ldft.symmetries(even, data)}["reflection"]
    assert refl.residual == 0.0 and refl.residual_equations == 0.0 and refl.verdict == "exact"
    # the free polynomial holds the symmetry only up to its fit
    assert {r.name: r for r in ldft.symmetries(free, data)}["reflection"].residual > 0
    cells = torch.randn(50, 2, 1, dtype=torch.float64)
    assert torch.equal(even(cells), even(-cells))
    served = ldft.serve(even, data[0].isel(t=slice(0, 2)), slices=60).field
    assert float(abs(served - data[0].isel(t=slice(0, 60))).max()) < 1e-6
    assert "even in psi" in even.describe()


def test_default_polynomial_is_unchanged() -> None:
    """``parity`` defaults to None: the paper's 45-term model, its options and its fit as before."""
    _, data = oscillator_data()
    model = ldft.PolynomialLagrangian((4, 8))
    assert model.options() == {
        "orders": [4, 8],
        "time_symmetric": False,
        "parity": None,
        "scale": True,
        "basis": "legendre",
    }
    ldft.learn(model, data)
    assert model.n_terms == 45 and float(model.center[0]) != 0.0
    again = ldft.PolynomialLagrangian((4, 8), parity=None)
    ldft.learn(again, data)
    assert torch.equal(model.coef, again.coef)


def test_parity_option_in_case_toml(tmp_path: Path, capsys) -> None:
    case = tiny_wave(tmp_path)
    code, _, err = run_cli(capsys, "check", case, "--set", 'model.parity="odd"')
    assert code != 0 and "model.parity" in err and "'even'" in err, err
    code, _, err = run_cli(capsys, "run", case, "-q", "--set", 'model.parity="even"', "--set", "export.formats=[]")
    assert code == 0, err
    model = ldft.load_model(case / "results" / "model.pt")
    assert model.parity == "even"
    test = ldft.io.read_field(case / "data" / "test.nc")
    refl = {r.name: r for r in ldft.symmetries(model, test)}["reflection"]
    assert refl.verdict == "exact" and refl.residual == 0.0
