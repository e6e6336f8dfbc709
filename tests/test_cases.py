"""Every case meets the figures of tests/case_expectations.toml, on a fast variant of it.

Each variant below (``RUNNERS``) runs a case -- the oscillators and the 2+1D membrane whole through the
command line, the others through the Python API on smaller lattices, fewer steps or fewer iterations --
and returns what it measured; one test checks those figures against the bounds of the expectations file,
the one place that holds them. The full-size runs are the commands in each case's README.md.
"""

from __future__ import annotations

import importlib.util
import json
import math
import shutil
import tomllib
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch

import latticedft as ldft
from latticedft import systems
from latticedft.cli import main
from latticedft.io import read_field

REPO = Path(__file__).resolve().parents[1]
CASES = REPO / "cases"
EXPECTATIONS = Path(__file__).with_name("case_expectations.toml")
NO_EXPORT = ["--set", "export.figures=false", "--set", "export.paraview=false", "-q"]


@pytest.fixture(autouse=True)
def _one_thread():
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def _module(case: str):
    """The case's make_data.py as a module."""
    spec = importlib.util.spec_from_file_location(f"make_data_{case.replace('-', '_')}", CASES / case / "make_data.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _run(case: str, out: Path, *extra: str) -> tuple[int, dict]:
    code = main(["run", str(CASES / case), "--out", str(out), *NO_EXPORT, *extra])
    return code, json.loads((out / "summary.json").read_text())


# -- the variants: each returns its measured figures ---------------------------------------------------------


def klein_gordon_polynomial(tmp_path: Path) -> dict[str, Any]:
    data = systems.klein_gordon_training_set(n=10, steps=20, seed=0)
    test = systems.klein_gordon_test_field(steps=100)
    model = ldft.PolynomialLagrangian(orders=(2, 2))
    report = ldft.learn(model, data)
    res = ldft.serve(model, test.isel(t=slice(0, 2)), slices=101, boundary="periodic")
    energy = systems.klein_gordon_energy(res.field).values
    return {
        "rel_res": report.rel_res,
        "max_error": ldft.compare(res.field, test)["max_error"],
        "energy_range_over_initial": float(np.ptp(energy) / energy[0]),
    }


def klein_gordon_mlp(tmp_path: Path) -> dict[str, Any]:
    data = systems.klein_gordon_training_set(n=20, steps=20, seed=0)
    test = systems.klein_gordon_test_field(steps=20)
    model = ldft.MLPLagrangian(hidden=[10, 10], activation="tanh", form="kinetic-potential", seed=0)
    report = ldft.learn(model, data, optimizer="lbfgs", max_iter=40)
    res = ldft.serve(model, test.isel(t=slice(0, 2)), slices=21, boundary="periodic")
    return {"rel_res": report.rel_res, "max_error": ldft.compare(res.field, test)["max_error"]}


def sine_gordon(tmp_path: Path) -> dict[str, Any]:
    lat = {"xlim": (-10.0, 10.0), "nx": 201, "dt": 0.05}
    train = systems.sine_gordon_breather(0.3, nt=401, **lat)
    kk = systems.kink_antikink(0.5, nt=81, t0=-2.0, **lat)
    model = ldft.PolynomialLagrangian(orders=(2, 12), time_symmetric=True)
    report = ldft.learn(model, train, ridge="auto")
    res = ldft.serve(model, kk, boundary="dirichlet")
    return {
        "rel_res": report.rel_res,
        "max_error": ldft.compare(res.field, kk)["max_error"],
        "baseline_max_error": ldft.compare(_module("sine-gordon")._leapfrog(kk), kk)["max_error"],
    }


def wave_2d(tmp_path: Path) -> dict[str, Any]:
    case = tmp_path / "wave-2d"
    case.mkdir()
    shutil.copy(CASES / "wave-2d" / "case.toml", case / "case.toml")
    _module("wave-2d").main(["--size", "33", "--steps", "60", "--out", str(case / "data")])
    rc = main(
        [
            "run",
            str(case),
            "-q",
            "--set",
            "export.max_frames=4",
            "--set",
            "export.figures=false",
            "--set",
            "run.threads=1",
        ]
    )
    task = json.loads((case / "results" / "summary.json").read_text())["tasks"]["test"]
    return {
        "exit_status": rc,
        "complete": task["complete"],
        "slices": task["slices"],
        "max_error": task["max_error"],
        "baseline_max_error": task["baseline"]["max_error"],
        "invariant_drift": task["invariant_drift"],
        "pvd_written": (case / "results" / "test.pvd").is_file(),
    }


def _oscillator(case: str) -> Callable[[Path], dict[str, Any]]:
    def run(tmp_path: Path) -> dict[str, Any]:
        code, summary = _run(case, tmp_path / "results")
        tasks = summary["tasks"]
        return {
            "exit_status": code,
            "rel_res": summary["train"]["rel_res"],
            "tasks": len(tasks),
            "task_complete": {n: t["complete"] for n, t in tasks.items()},
            "task_slices": {n: t["slices"] for n, t in tasks.items()},
            "task_max_error": {n: t["max_error"] for n, t in tasks.items()},
            "warnings": summary["warnings"],
        }

    return run


def oscillator_sin_single_sequence(tmp_path: Path) -> dict[str, Any]:
    code, summary = _run("oscillator-sin", tmp_path / "results", "--set", 'train.data=["data/train_1.20.nc"]')
    tasks = summary["tasks"]
    tests = {n: t for n, t in tasks.items() if n != "train"}
    return {
        "rel_res": summary["train"]["rel_res"],
        "train_complete": tasks["train"]["complete"],
        "train_max_error": tasks["train"]["max_error"],
        "test_tasks": sorted(tests),
        "test_max_error": {n: t["max_error"] if t["complete"] else math.inf for n, t in tests.items()},
        "exit_status": code,
        "exit_status_from_tasks": 3 if any(not t["complete"] for t in tasks.values()) else 0,
    }


def kepler(tmp_path: Path) -> dict[str, Any]:
    cfg = tomllib.loads((CASES / "kepler" / "case.toml").read_text())
    tasks = [(t["name"], CASES / "kepler" / t["from"], float(t["box"])) for t in cfg["serve"]]
    train = [read_field(p) for p in sorted((CASES / "kepler" / "data").glob("train_*.nc"))]
    model = ldft.MLPLagrangian(preset=cfg["model"]["preset"])
    report = ldft.learn(model, train, max_iter=200)
    refs = [read_field(p) for _, p, _ in tasks]
    served = ldft.serve(model, refs, box=10.0)  # one batch; raises ServeError on a Newton failure
    out: dict[str, Any] = {
        "train_files": len(train),
        "rel_res": report.rel_res,
        "boxes": sorted({b for _, _, b in tasks}),
        "served": len(served),
        "task_complete": {},
        "escapes_like_truth": {},
        "crossing_offset": {},
        "earth_max_error_100": {},
    }
    for (name, _, _), ref, res in zip(tasks, refs, served):
        pred = res.field.values
        escaped = bool((np.hypot(*pred.T) > 10).any())
        truth = bool((np.hypot(*ref.values.T) > 10).any())
        out["task_complete"][name] = res.complete
        out["escapes_like_truth"][name] = escaped == truth
        if escaped:
            crossing = int(np.argmax(np.hypot(*ref.values.T) > 10))
            out["crossing_offset"][name] = abs(res.slices - 1 - crossing) / res.slices
        if name.startswith("earth_") and not truth:
            out["earth_max_error_100"][name] = float(np.abs(pred[:101] - ref.values[:101]).max())
    return out


RUNNERS: dict[str, Callable[[Path], dict[str, Any]]] = {
    "klein-gordon-polynomial": klein_gordon_polynomial,
    "klein-gordon-mlp": klein_gordon_mlp,
    "sine-gordon": sine_gordon,
    "wave-2d": wave_2d,
    "oscillator-sin": _oscillator("oscillator-sin"),
    "oscillator-wells": _oscillator("oscillator-wells"),
    "oscillator-sin-single-sequence": oscillator_sin_single_sequence,
    "kepler": kepler,
}


# -- the check ------------------------------------------------------------------------------------------------

EXPECT = tomllib.loads(EXPECTATIONS.read_text())
_OPS: dict[str, Callable[[Any, Any], bool]] = {
    "lt": lambda a, b: a < b,
    "le": lambda a, b: a <= b,
    "gt": lambda a, b: a > b,
    "ge": lambda a, b: a >= b,
    "eq": lambda a, b: a == b,
}


def _bounds(op: str, spec: Any) -> list[Any]:
    """The bounds of one operator: a list of several (not for ``eq``, whose value may be a list)."""
    return list(spec) if isinstance(spec, list) and op != "eq" else [spec]


def _references(expect: dict[str, dict[str, Any]]) -> set[str]:
    """Figures named as bounds of other figures."""
    return {b for ops in expect.values() for op, spec in ops.items() for b in _bounds(op, spec) if isinstance(b, str)}


def test_every_variant_has_expectations_and_a_runner() -> None:
    assert sorted(EXPECT) == sorted(RUNNERS)
    for name, table in EXPECT.items():
        assert set(table) == {"case", "what", "expect"}, name
        assert (REPO / table["case"] / "case.toml").is_file(), (name, table["case"])
        for figure, ops in table["expect"].items():
            assert ops and set(ops) <= set(_OPS), (name, figure, ops)


@pytest.mark.parametrize("name", sorted(EXPECT))
def test_case_meets_its_expected_figures(name: str, tmp_path: Path) -> None:
    expect: dict[str, dict[str, Any]] = EXPECT[name]["expect"]
    measured = RUNNERS[name](tmp_path)
    unchecked = set(measured) - set(expect) - _references(expect)
    assert not unchecked, f"{name}: figures measured but not in {EXPECTATIONS.name}: {sorted(unchecked)}"
    failures = []
    for figure, ops in expect.items():
        assert figure in measured, f"{name}: {EXPECTATIONS.name} expects {figure!r}, which the variant does not measure"
        value = measured[figure]
        per_item = value.items() if isinstance(value, dict) else [(None, value)]
        for op, spec in ops.items():
            for bound in _bounds(op, spec):
                target = measured[bound] if isinstance(bound, str) else bound
                for item, v in per_item:
                    if not _OPS[op](v, target):
                        where = figure if item is None else f"{figure}[{item}]"
                        failures.append(
                            f"{where} = {v!r}, expected {op} {bound!r}"
                            + (f" (= {target!r})" if isinstance(bound, str) else "")
                        )
    assert not failures, f"{name} ({EXPECT[name]['case']}): " + "; ".join(failures)
