"""Smoke test of the benchmark runner: ``--quick`` runs end to end and prints its tables.

No timing is asserted: the benchmarks are run by hand (docs/performance.md).
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from collections.abc import Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

ROOT = Path(__file__).resolve().parent.parent


@dataclass
class Quick:
    """One run of ``python -m benchmarks --quick --out DIR``: what it printed, its results.json, DIR."""

    out: str
    results: dict[str, Any]
    folder: Path

    def table(self, name: str) -> dict[str, Any]:
        """The table of benchmark ``name`` as results.json holds it (``Table.to_dict``)."""
        return next(b for b in self.results["benchmarks"] if b["name"] == name)


def _python(*argv: str, timeout: float = 1200) -> subprocess.CompletedProcess[str]:
    """``python ARGV`` in a fresh Python at the repository's root, one thread."""
    return subprocess.run(
        [sys.executable, *argv],
        cwd=ROOT,
        env=dict(os.environ, OMP_NUM_THREADS="1"),
        capture_output=True,
        text=True,
        timeout=timeout,
        check=False,
    )


def _commands() -> dict[str, tuple[str, ...]]:
    """The short commands of this module by name, each run in its own fresh Python (each start imports torch:
    seconds of one core)."""
    cmds = {f"help {m}": ("-m", f"benchmarks.{m}", "--help") for m in ALONE}
    cmds["alone"] = ("-m", "benchmarks.serve_2p1d", "--quick")
    cmds["unknown"] = ("-m", "benchmarks", "--only", "nope")
    cmds["noise"] = ("-m", "benchmarks.noise", "duffing", "kepler-coarse", "--ratios", "--sigmas", "1e-3,1e-2")
    cmds["compiled default"] = ("-m", "benchmarks.compiled_default", "--quick")
    return cmds


@dataclass
class Started:
    """The runner's ``--quick`` run and the short commands, started together: the runner keeps one core busy
    (one thread) while the short commands run one after another beside it."""

    runner: subprocess.Popen[str]
    folder: Path  # the runner's --out
    log: Path  # its stdout and stderr
    pool: ThreadPoolExecutor
    jobs: dict[str, Future[subprocess.CompletedProcess[str]]]

    def result(self, name: str) -> subprocess.CompletedProcess[str]:
        return self.jobs[name].result()


@pytest.fixture(scope="module")
def started(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Started]:
    folder, log = tmp_path_factory.mktemp("quick"), tmp_path_factory.mktemp("quick-log")
    with open(log / "stdout", "w") as out, open(log / "stderr", "w") as err:  # files: no pipe to fill up
        runner = subprocess.Popen(
            [sys.executable, "-m", "benchmarks", "--quick", "--out", str(folder)],
            cwd=ROOT,
            env=dict(os.environ, OMP_NUM_THREADS="1"),
            stdout=out,
            stderr=err,
            text=True,
        )
    pool = ThreadPoolExecutor(1)
    jobs = {name: pool.submit(_python, *argv) for name, argv in _commands().items()}
    try:
        yield Started(runner, folder, log, pool, jobs)
    finally:
        pool.shutdown(cancel_futures=True)
        if runner.poll() is None:  # not waited for (a test chosen alone): stopped
            runner.kill()
            runner.wait()


@pytest.fixture(scope="module")
def quick(started: Started) -> Quick:
    """The runner's ``--quick`` tables, run once for every test of this module that reads them."""
    code = started.runner.wait(timeout=3600)  # a guard against a hang only: on a busy machine it takes minutes
    assert code == 0, (started.log / "stderr").read_text()[-3000:]
    out = (started.log / "stdout").read_text()
    return Quick(out, json.loads((started.folder / "results.json").read_text()), started.folder)


@pytest.mark.slow
def test_quick_run_prints_every_table_and_writes_results(quick: Quick) -> None:
    out, tmp_path = quick.out, quick.folder
    for title in (
        "1+1D serving",
        "2+1D serving",
        "1D serving",
        "Training",
        "Long-run fidelity",
        "Peak resident memory",
        "Symmetries of learned theories",
        "Scale: training",
        "n-D serving",
        "1D serving in numpy",
        "Ensemble serving",
        "Discovery",
        "Calibrated error bars",
        "Targets",
    ):
        assert f"== {title}" in out, f"table {title!r} missing from:\n{out}"
    results = quick.results
    names = [b["name"] for b in results["benchmarks"]]
    assert names == [
        "serve-1+1d",
        "serve-2+1d",
        "serve-1d",
        "train",
        "fidelity",
        "memory",
        "noether",
        "train_scale",
        "serve-nd",
        "serve-fast1d",
        "ensemble",
        "serve_scale",
        "serve-dist",
        "discovery",
        "calibration",
    ]
    assert not results["failed"]
    assert all(b["rows"] for b in results["benchmarks"])
    checks = [c for b in results["benchmarks"] for c in b["checks"]]
    assert len(checks) >= 8 and all(isinstance(c["met"], bool) for c in checks)
    assert "| serve sites/s | Newton sites/s (affine=False) |" in (tmp_path / "results.md").read_text()
    assert (tmp_path / "fidelity_energy.png").stat().st_size > 0


#: every benchmark module of the runner, each runnable alone (``python -m benchmarks.<module> --quick``)
ALONE = [
    "serve_1p1d",
    "serve_2p1d",
    "serve_1d",
    "train",
    "fidelity",
    "memory",
    "noether",
    "train_scale",
    "serve_nd",
    "serve_fast1d",
    "ensemble",
    "serve_scale",
    "serve_dist",
    "discovery",
    "calibration",
]


def test_every_runner_module_is_listed_here():
    from benchmarks.run import BENCHMARKS

    assert ALONE == BENCHMARKS


@pytest.mark.parametrize("module", ALONE)
def test_each_module_runs_alone(started: Started, module: str) -> None:
    """Every module answers ``--help`` alone with its own usage (its ``--quick`` tables are the runner's, run
    once above: running each again alone would double the suite's longest test)."""
    proc = started.result(f"help {module}")
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert proc.stdout.startswith("usage:") and "--quick" in proc.stdout, proc.stdout[-3000:]


@pytest.mark.slow
def test_a_module_alone_prints_its_table(started: Started) -> None:
    """``python -m benchmarks.serve_2p1d --quick``: a module run alone prints its table (the shared path of the
    modules that are also in the runner)."""
    proc = started.result("alone")
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "== 2+1D serving" in proc.stdout, proc.stdout[-3000:]


def test_calibration_counts_silent_misses_and_the_candidates_check_cost() -> None:
    """A test field whose single band covers less than half of its slices is a silent miss unless a calibration
    warning (the candidates' among them) fired on it; the check's cost is the runner-up's serves over the model's."""
    import numpy as np

    from benchmarks import calibration

    pool = calibration._Pool()
    covered, missed = np.full(6, 1.0), np.full(6, 10.0)
    for err, warnings, runner in ((covered, [], 0.5), (missed, ["the two best candidates"], 1.5), (missed, [], None)):
        pool.add(err, single=np.ones(6))
        pool.facts.append({"warnings": warnings, "serve_s": 1.0, "runner_s": runner})
    assert pool.silent() == 1 and pool.check_cost() == pytest.approx(1.0)
    assert calibration._Pool().check_cost() is None


@pytest.mark.slow
def test_calibration_quick_prints_one_row_with_its_columns_and_targets(quick: Quick) -> None:
    """The runner's ``--quick`` calibration table (``benchmarks.calibration.run(Config(quick=True))``): one small
    case, the table's structure (no timing)."""
    table = quick.table("calibration")
    columns, rows = table["columns"], table["rows"]
    assert columns[:6] == ["row", "noise", "tests", "slices", "coverage, single", "std/error, single"]
    assert "cost" in columns and "coverage, ensemble" in columns
    assert len(rows) == 1 and rows[0][0] == "oscillator-sin"
    row = rows[0]
    assert len(row) == len(columns), row
    assert 0 <= row[4] <= 1 and row[5] > 0 and 0 <= row[6] <= 1
    assert [c["target"] for c in table["checks"]] == [
        "single: 2-sigma coverage 80-99 % and std/error 0.5-2",
        "ensemble: 2-sigma coverage 80-99 % and std/error 0.5-2",
        "cost of calibration <= 1.5x selection alone",
    ]


def test_calibration_record_appends_each_rows_per_slice_bands(tmp_path: Path) -> None:
    """``--record FILE``: each row's law and per-slice errors and bands are appended to one JSON file."""
    import numpy as np

    from benchmarks import calibration

    law = calibration.Calibration(1e-3, 1.0, 0.95, 1, 4, 9, -1.0, 1.0, 0.9, 0.8, None, 0.0)
    pool = calibration._Pool()
    pool.add(np.arange(6.0), single=np.ones(6), trial=np.full(6, np.nan))
    pool.facts.append({"slices": 6, "low": -1.0, "high": 2.0, "warnings": ["outside"], "excess": [0.0] * 4})
    path = tmp_path / "rows.json"
    for sigma in (0.0, 1e-3):
        calibration._record(str(path), "a row", sigma, law, pool, [{"k": [2.0], "rel": [0.1]}])
    rows = json.loads(path.read_text())
    assert [r["noise"] for r in rows] == [0.0, 1e-3] and rows[0]["law"]["slices"] == 9
    assert rows[1]["held_out"] == [{"k": [2.0], "rel": [0.1]}]
    assert rows[1]["tests"][0]["error"] == [2.0, 3.0, 4.0, 5.0] and rows[1]["tests"][0]["single"] == [1.0] * 4
    assert all(math.isnan(x) for x in rows[0]["tests"][0]["trial"])
    assert rows[1]["tests"][0]["high"] == 2.0 and rows[1]["tests"][0]["warnings"] == ["outside"]
    assert calibration._part(["--record", "x.json", "--quick"]) == ["--quick"] and calibration.ONLY.pop("record")


@pytest.mark.slow
def test_discovery_quick_table_and_its_pendulum_row(quick: Quick) -> None:
    """The runner's ``--quick`` discovery table (the pendulum, Kepler after 50 and 200 steps, sine-Gordon 1+1D;
    no peers): its columns, and the pendulum's row against the true leapfrog (no timing)."""
    from benchmarks import discovery

    table = quick.table("discovery")
    assert table["columns"] == discovery.COLUMNS
    rows = [dict(zip(table["columns"], r)) for r in table["rows"]]
    assert [r["system"] for r in rows] == [
        "pendulum",
        "Kepler, one orbit (50 steps)",
        "Kepler, one orbit (200 steps)",
        "sine-Gordon 1+1D",
    ]
    row = rows[0]
    assert row["leapfrog"] == pytest.approx(1.67e-3, rel=0.05)  # the true leapfrog at h = 0.1, 150 steps
    assert math.isfinite(row["served"]) and row["ratio"] == pytest.approx(row["served"] / row["leapfrog"])
    assert row["cost"] == pytest.approx(row["fit (s)"] / row["dense (s)"])
    assert row["terms"] == "n/a: no closed form" or "/" in row["terms"]
    assert any("load average" in n for n in table["notes"])
    assert len(table["checks"]) == 3 and all(isinstance(c["met"], bool) for c in table["checks"])


def test_unknown_benchmark_is_refused(started: Started) -> None:
    proc = started.result("unknown")
    assert proc.returncode == 2
    assert "unknown benchmark 'nope'" in proc.stderr


def test_noise_benchmark_ratios_and_systems(started: Started) -> None:
    """``python -m benchmarks.noise --ratios`` prints the noise's share of the second differences; the Kepler
    systems sample the case's orbits at their own steps."""
    from benchmarks import noise

    proc = started.result("noise")
    assert proc.returncode == 0, proc.stderr[-3000:]
    rows = [line for line in proc.stdout.splitlines() if line.startswith("| double-well") or "dt = 0.2" in line]
    assert len(rows) == 2
    shares = [[float(v) for v in row.strip("|").split("|")[1:]] for row in rows]
    assert all(0 < a < b <= 1 for a, b in shares)  # more noise, a larger share
    for name, dt in (("kepler", 0.05), ("kepler-coarse", 0.2)):
        field = noise.SYSTEMS[name].test()[0]
        assert abs(float(field.t[1] - field.t[0]) - dt) < 1e-12


def test_compiled_default_prints_its_row(started: Started) -> None:
    """``python -m benchmarks.compiled_default --quick``: a case's model trained and served both ways; the two
    fields agree to round-off."""
    proc = started.result("compiled default")
    assert proc.returncode == 0, proc.stderr[-3000:]
    row = next(ln for ln in proc.stdout.splitlines() if ln.startswith("| sine-gordon kink_antikink"))
    assert float(row.strip("| \n").split("|")[-1]) <= 1e-12, row


def test_serve_nd_rows_chosen_by_words_and_dimensions(capsys: pytest.CaptureFixture[str]) -> None:
    """``--only`` keeps the rows whose L_d holds a word (any case), ``--dims`` those of a dimension; a filter that
    keeps no row is an exit status 2 with a line saying so, and learns nothing."""
    from benchmarks import serve_nd

    keep = serve_nd.keeper(["Polynomial"], [3])
    assert keep(serve_nd.POLY + ", compiled", 3) and not keep(serve_nd.POLY + ", compiled", 2)
    assert not keep("sine-Gordon, analytic, compiled", 3) and not keep(serve_nd.MLP, 2)
    assert serve_nd.keeper()(serve_nd.MLP, 2) and serve_nd.keeper((), [2])(serve_nd.MLP, 2)
    assert serve_nd.main(["--quick", "--only", "no such row"]) == 2
    assert "no row matches" in capsys.readouterr().err


def test_serve_nd_repeat_reports_the_least_of_several_serves(
    capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """``--repeat N`` times N serves of each row and reports the least (the note says so); a count below 1 is
    refused by name."""
    from benchmarks import serve_nd

    served: list[int] = []
    real = serve_nd.ldft.serve

    def counted(*args: object, **kwargs: object) -> object:
        served.append(1)
        return real(*args, **kwargs)  # type: ignore[arg-type]

    monkeypatch.setattr(serve_nd.ldft, "serve", counted)
    assert serve_nd.main(["--quick", "--only", "analytic, compiled", "--dims", "1", "--repeat", "3"]) == 0
    out = capsys.readouterr().out
    assert "the least of 3 timed serves of each row" in out
    assert len(served) == 1 + 3 + 1  # the warm-up, three timed serves, once more on a lattice not seen before
    with pytest.raises(SystemExit):
        serve_nd.main(["--quick", "--repeat", "0"])
    assert "--repeat" in capsys.readouterr().err
