"""Fault injection: the command line never loses a user's files (docs/guarantees.md).

Every scenario runs ``python -m latticedft ...`` as a subprocess on a small copy of cases/wave (12 served
slices, no export formats unless a test needs them) and checks the guarantees: the exit status, one line on
stderr without a traceback, every file of the case folder byte-identical (inputs and earlier results) when the
command was refused or stopped, and no staging folder (``*.tmp*``) left once a command has finished. Kills and
signals come from the test hook ``LATTICEDFT_FAULT`` (see latticedft._results), never from sleeps.
Independent scenarios run concurrently (each in its own case folder) to keep the module quick.
"""

from __future__ import annotations

import errno
import hashlib
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import pytest
import torch

from latticedft._results import ResultsError, check_destination
from latticedft._run._guards import case_inputs

REPO = Path(__file__).resolve().parents[1]
WAVE = REPO / "cases" / "wave"
TIMEOUT = 600  # a generous bound for a hung process, not a measurement
JOBS = 4


# -- helpers -------------------------------------------------------------------------------------------------
def make_case(folder: Path, *, formats: str = "[]", extra: str = "") -> Path:
    """A copy of cases/wave that serves 12 slices with one thread, in the export formats ``formats``."""
    case = folder / "wave"
    shutil.copytree(WAVE, case, ignore=shutil.ignore_patterns("results", "results.tmp*"))
    text = (case / "case.toml").read_text()
    text = text.replace('name = "test"', 'name = "test"\nslices = 12')
    text = text.replace("[export]\nmax_frames = 100", f"[export]\nformats = {formats}\nmax_frames = 3")
    (case / "case.toml").write_text(text + extra + "\n[run]\nthreads = 1\n")
    return case


def _env(fault: str | None) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k != "LATTICEDFT_FAULT"}
    env["PYTHONPATH"] = os.pathsep.join([str(REPO), *filter(None, [os.environ.get("PYTHONPATH")])])
    env["OMP_NUM_THREADS"] = "1"
    if fault:
        env["LATTICEDFT_FAULT"] = fault
    return env


@dataclass
class Done:
    code: int
    out: str
    err: str


def start(*argv: object, fault: str | None = None, cwd: Path | None = None) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, "-m", "latticedft", *map(str, argv)],
        env=_env(fault),
        cwd=cwd,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def finish(proc: subprocess.Popen[str]) -> Done:
    out, err = proc.communicate(timeout=TIMEOUT)
    return Done(proc.returncode, out, err)


def cli(*argv: object, fault: str | None = None, cwd: Path | None = None) -> Done:
    return finish(start(*argv, fault=fault, cwd=cwd))


def run_all(jobs: dict[str, tuple]) -> dict[str, Done]:
    """Run ``name -> (argv, fault)`` jobs, at most JOBS at a time; their outcomes by name."""
    with ThreadPoolExecutor(JOBS) as pool:
        futures = {name: pool.submit(cli, *argv, fault=fault) for name, (argv, fault) in jobs.items()}
        return {name: f.result() for name, f in futures.items()}


def hashes(folder: Path) -> dict[str, str]:
    """sha256 of every file under ``folder`` (a link: where it points)."""
    out = {}
    for p in sorted(folder.rglob("*")):
        rel = str(p.relative_to(folder))
        if p.is_symlink():
            out[rel] = "-> " + os.readlink(p)
        elif p.is_file():
            out[rel] = hashlib.sha256(p.read_bytes()).hexdigest()
    return out


def inputs_of(case: Path) -> dict[str, str]:
    return {k: v for k, v in hashes(case).items() if not k.startswith("results")}


def staging_left(folder: Path) -> list[str]:
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*.tmp*"))


def one_line(err: str, *needles: str, prefix: str = "latticedft: error: ") -> str:
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1, err
    assert "Traceback" not in err
    assert lines[0].startswith(prefix), lines[0]
    for n in needles:
        assert n in lines[0], (n, lines[0])
    return lines[0]


def summary(case: Path) -> dict:
    return json.loads((case / "results" / "summary.json").read_text())


# -- a case with earlier results, copied per scenario ----------------------------------------------------------
@pytest.fixture(scope="module")
def template(tmp_path_factory: pytest.TempPathFactory) -> Path:
    case = make_case(tmp_path_factory.mktemp("template"))
    done = cli("run", case, "-q")
    assert done.code == 0, done.err
    assert done.err == ""
    return case


def earlier(template: Path, folder: Path) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    return Path(shutil.copytree(template, folder / "wave", symlinks=True))


def _change_model(case: Path, *, nan: bool, record: bool) -> None:
    """Change the weights of results/model.pt (NaN, or a small change); ``record``: update model.json's sha256."""
    pt = case / "results" / "model.pt"
    rec = torch.load(pt, weights_only=True)
    coef = rec["state_dict"]["coef"]
    rec["state_dict"]["coef"] = torch.full_like(coef, float("nan")) if nan else coef + 1e-3
    torch.save(rec, pt)
    if record:
        meta = json.loads((case / "results" / "model.json").read_text())
        meta["sha256"] = hashlib.sha256(pt.read_bytes()).hexdigest()
        (case / "results" / "model.json").write_text(json.dumps(meta))


class _Scenarios:
    """The concurrent scenarios: their case folders, the hashes taken before, and the outcomes."""

    def __init__(self, root: Path, template: Path):
        self.root, self.template = root, template
        self.cases: dict[str, Path] = {}
        self.before: dict[str, dict[str, str]] = {}
        self.done: dict[str, Done] = {}
        self.after: dict[str, Done] = {}
        self.between: dict[str, dict[str, str]] = {}  # the case folders after the first commands

    def case(self, name: str) -> Path:
        self.cases[name] = earlier(self.template, self.root / name)
        return self.cases[name]

    def snapshot(self) -> None:
        self.before = {name: hashes(case) for name, case in self.cases.items()}


@pytest.fixture(scope="module")
def scenarios(template: Path, tmp_path_factory: pytest.TempPathFactory) -> Iterator[_Scenarios]:
    s = _Scenarios(tmp_path_factory.mktemp("scenarios"), template)
    c = s.case
    long_name = "a" * 240
    mlp = c("hidden-memory")
    text = (mlp / "case.toml").read_text().replace('kind = "polynomial"', 'kind = "mlp"')
    (mlp / "case.toml").write_text(text.replace("orders = [2, 2]", "hidden = [1000000000, 1000000000]"))
    nan_case, changed = c("nan-weights"), c("changed-model")
    _change_model(nan_case, nan=True, record=True)
    _change_model(changed, nan=False, record=False)
    (s.root / "afile").write_text("a file, not a folder\n")
    jobs = {
        # 1. results must not replace the case's inputs
        "out-case": (("run", c("out-case"), "--out", s.root / "out-case" / "wave", "--overwrite", "-q"), None),
        "out-data": (("run", c("out-data"), "--out", s.root / "out-data" / "wave" / "data", "--overwrite", "-q"), None),
        "out-sibling": (("check", c("out-sibling"), "--out", s.root / "out-sibling" / "wave" / "results2", "-q"), None),
        # 5. --out naming a regular file
        "out-file": (("run", c("out-file"), "--out", s.root / "afile", "-q"), None),
        # 8, 9. limits checked before anything runs
        "long-name": (("check", c("long-name"), "-q", "--set", f"serve.test.name={long_name}"), None),
        "steps-memory": (
            (
                "run",
                c("steps-memory"),
                "--overwrite",
                "-q",
                "--set",
                "serve.test.slices=10000000000",
                "--set",
                "serve.test.boundary=periodic",
            ),
            None,
        ),
        "hidden-memory": (("check", mlp, "-q"), None),
        "orders-memory": (("run", c("orders-memory"), "--overwrite", "-q", "--set", "model.orders=[200,200]"), None),
        "threads": (("run", c("threads"), "--overwrite", "-q", "--set", "run.threads=100000"), None),
        # 10. model files verified
        "nan-weights": (("serve", nan_case, "-q"), None),
        "changed-model": (("info", changed, "-q"), None),
        # 11. overrides that would not take effect; nothing to export
        "serve-model-override": (("serve", c("serve-model-override"), "-q", "--set", "model.orders=[2,4]"), None),
        "export-train-override": (
            (
                "export",
                c("export-train-override"),
                "-q",
                "--set",
                "train.ridge=1e-3",
                "--set",
                'export.formats=["figures"]',
            ),
            None,
        ),
        "export-nothing": (("export", c("export-nothing"), "-q"), None),
        # 7. disk full, no permission (injected in the staged writes)
        "enospc": (("run", c("enospc"), "--overwrite", "-q"), "enospc:write"),
        "eacces": (("serve", c("eacces"), "-q"), "eacces:stage"),
        "enospc-publish": (("run", c("enospc-publish"), "--overwrite"), "enospc:after-stage"),
        # 4. signals
        "sigterm": (("run", c("sigterm"), "--overwrite", "-q"), "term:after-stage"),
        "sigint": (("serve", c("sigint"), "-q"), "int:stage"),
        "int-loading": (("run", c("int-loading"), "--overwrite", "-q"), "int:loading"),
        "term-loading": (("serve", c("term-loading"), "-q"), "term:loading"),
        "int-exit": (("serve", c("int-exit"), "-q"), "int:exit"),
        "term-exit": (("serve", c("term-exit"), "-q"), "term:exit"),
        "sigterm-mid-publish": (("run", c("sigterm-mid-publish"), "--overwrite", "-q"), "no-exchange,term:mid-publish"),
        # 2. kills
        "kill-after-stage": (("serve", c("kill-after-stage"), "-q"), "kill:after-stage"),
        "kill-mid-publish-fallback": (
            ("run", c("kill-mid-publish-fallback"), "--overwrite", "-q"),
            "no-exchange,kill:mid-publish",
        ),
        "kill-mid-publish-exchange": (("serve", c("kill-mid-publish-exchange"), "-q"), "kill:mid-publish"),
    }
    # 3. a run that finds the case held by another process: this test holds the lock meanwhile
    locked = c("locked")
    jobs["locked"] = (("run", locked, "--overwrite", "-q"), None)
    s.snapshot()
    import fcntl

    fd = os.open(locked, os.O_RDONLY)
    fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    try:
        s.done = run_all(jobs)
    finally:
        os.close(fd)
    s.between = {name: hashes(case) for name, case in s.cases.items()}
    # the next command after a kill recovers
    s.after = run_all(
        {
            "kill-after-stage": (("serve", s.cases["kill-after-stage"], "-q"), None),
            "kill-mid-publish-fallback": (("run", s.cases["kill-mid-publish-fallback"], "-q"), None),
            "kill-mid-publish-exchange": (("serve", s.cases["kill-mid-publish-exchange"], "-q"), None),
        }
    )
    yield s


def _refused(s: _Scenarios, name: str, *needles: str, code: int = 1, prefix: str = "latticedft: error: ") -> str:
    done = s.done[name]
    assert done.code == code, (done.code, done.err)
    line = one_line(done.err, *needles, prefix=prefix)
    assert hashes(s.cases[name]) == s.before[name]  # inputs and earlier results untouched
    assert staging_left(s.cases[name].parent) == []
    return line


# -- 1. --out is never the case's inputs ---------------------------------------------------------------------------
def test_out_is_the_case_folder(scenarios: _Scenarios) -> None:
    _refused(scenarios, "out-case", "--out", "is the case folder")


def test_out_is_the_data_folder(scenarios: _Scenarios) -> None:
    _refused(scenarios, "out-data", "--out", "is the case's input folder", "data")


def test_out_beside_the_results_is_fine(scenarios: _Scenarios) -> None:
    done = scenarios.done["out-sibling"]
    assert done.code == 0, done.err
    assert "results2 does not exist yet" in done.out


@pytest.mark.parametrize(
    "where, needle",
    [
        (".", "is the case folder"),
        ("..", "contains the case folder"),
        ("data", "is the case's input folder"),
        ("data/new", "lies inside the case's input folder"),
        ("data/train.nc", "is the case's input file"),
        ("case.toml", "is the case's input file"),
        ("myinvariant.py", "is the case's input file"),
        ("results/nested", "lies inside the results folder"),
        ("loop", "is a link that loops"),
    ],
)
def test_destinations_refused(tmp_path: Path, where: str, needle: str) -> None:
    from latticedft._case import load_case

    case = make_case(tmp_path)
    (case / "myinvariant.py").write_text("def energy(field):\n    return field.sum('x')\n")
    text = (case / "case.toml").read_text().replace('"latticedft.systems:wave_energy"', '"myinvariant:energy"')
    (case / "case.toml").write_text(text)
    (case / "loop").symlink_to(case / "loop")
    loaded = load_case(case)
    with pytest.raises(ResultsError, match=needle):
        check_destination(case / where, inputs=case_inputs(loaded), root=loaded.root, what="--out")
    for fine in ("results", "results2", "../elsewhere"):
        check_destination(case / fine, inputs=case_inputs(loaded), root=loaded.root)


def test_out_inside_any_results_folder_is_refused(tmp_path: Path, template: Path) -> None:
    case = earlier(template, tmp_path / "a")
    done = cli("run", case, "--out", tmp_path / "a" / "wave" / "results" / "deeper" / "nested", "-q")
    one_line(done.err, "lies inside the results folder")
    other = tmp_path / "other"
    assert cli("train", case, "--out", other, "-q").code == 0
    done = cli("run", case, "--out", other / "sub", "-q")
    one_line(done.err, "lies inside the results folder", "other")
    assert (other / ".latticedft-results").is_file() and not (other / "sub").exists()


def test_overwrite_replaces_only_folders_latticedft_wrote(tmp_path: Path, template: Path) -> None:
    """A summary.json alone does not make a folder ours: the user's files beside it are never deleted. A results
    folder of an earlier version (no marker, only files a run writes) is still replaced."""
    case = earlier(template, tmp_path / "a")
    mine = tmp_path / "mine"
    mine.mkdir()
    shutil.copyfile(case / "results" / "summary.json", mine / "summary.json")
    (mine / "thesis.tex").write_text("years of work\n")
    done = cli("run", case, "--out", mine, "--overwrite", "-q")
    one_line(done.err, "holds files that latticedft did not write")
    assert (mine / "thesis.tex").read_text() == "years of work\n"
    (case / "results" / ".latticedft-results").unlink()  # as an earlier version wrote it
    done = cli("run", case, "--overwrite", "-q")
    assert done.code == 0, done.err
    assert (case / "results" / ".latticedft-results").is_file()


# -- 2. publishing is atomic, and the next run recovers ------------------------------------------------------------
def test_kill_before_publishing_keeps_the_old_results(scenarios: _Scenarios) -> None:
    s, name = scenarios, "kill-after-stage"
    case = s.cases[name]
    assert s.done[name].code == -signal.SIGKILL
    assert inputs_of(case) == inputs_of(s.template)
    left = {k: v for k, v in s.between[name].items() if ".tmp-" in k}
    assert left and {k: v for k, v in s.between[name].items() if k not in left} == s.before[name]
    after = s.after[name]  # the next serve removes the dead staging folder (one warning) and runs
    assert after.code == 0, after.err
    one_line(after.err, "interrupted run left", "removed", prefix="latticedft: warning: ")
    assert staging_left(case.parent) == [] and summary(case)["stage"] == "serve"


def test_kill_between_the_renames_restores_the_old_results(scenarios: _Scenarios) -> None:
    """The two-rename fallback: killed with the old results parked and the new ones not yet in place."""
    s, name = scenarios, "kill-mid-publish-fallback"
    case = s.cases[name]
    assert s.done[name].code == -signal.SIGKILL
    assert not any(k.startswith("results/") for k in s.between[name])  # no results/ at all, but ...
    assert any(k.startswith("results.tmp-old-") for k in s.between[name])  # ... the old ones parked beside
    after = s.after[name]  # the next run puts them back, then refuses to replace them without --overwrite
    assert after.code == 1
    lines = after.err.splitlines()
    assert len(lines) == 2 and "Traceback" not in after.err
    assert lines[0].startswith("latticedft: warning: ") and "restored the earlier results" in lines[0]
    assert lines[1].startswith("latticedft: error: ") and "exists; use --overwrite" in lines[1]
    assert hashes(case) == s.before[name]
    assert staging_left(case.parent) == []


def test_kill_after_the_swap_has_the_new_results(scenarios: _Scenarios) -> None:
    s, name = scenarios, "kill-mid-publish-exchange"
    case = s.cases[name]
    assert s.done[name].code == -signal.SIGKILL
    between = s.between[name]  # the swap happened: the new results are in place, the old ones beside them
    assert between["results/summary.json"] != s.before[name]["results/summary.json"]
    assert any(k.startswith("results.tmp-") for k in between)
    assert inputs_of(case) == inputs_of(s.template)
    after = s.after[name]
    assert after.code == 0, after.err
    one_line(after.err, "removed", prefix="latticedft: warning: ")
    assert staging_left(case.parent) == []


# -- 3. one run at a time --------------------------------------------------------------------------------------------
def test_a_held_case_is_refused(scenarios: _Scenarios) -> None:
    _refused(scenarios, "locked", "another latticedft run holds")


def test_two_runs_never_both_publish(tmp_path: Path, template: Path) -> None:
    """Run A stops itself (SIGSTOP) once its stage is done; run B, started then, is refused; A goes on."""
    if not Path("/proc/self/stat").exists():
        pytest.skip("needs /proc to see that the first run has stopped")
    case = earlier(template, tmp_path)
    first = start("run", case, "--overwrite", "-q", fault="stop:after-stage")
    try:
        state, deadline = "", time.monotonic() + TIMEOUT
        while state != "T" and first.poll() is None and time.monotonic() < deadline:
            stat = Path(f"/proc/{first.pid}/stat").read_text()
            state = stat.rsplit(")", 1)[1].split()[0]
            time.sleep(0.05)
        assert state == "T", "the first run did not reach its stopping point"
        before = hashes(case)
        second = cli("run", case, "--overwrite", "-q")
        assert second.code == 1
        one_line(second.err, "another latticedft run holds", "wave")
        assert hashes(case) == before
    finally:
        os.kill(first.pid, signal.SIGCONT)
    done = finish(first)
    assert done.code == 0, done.err
    assert staging_left(tmp_path) == [] and summary(case)["exit_status"] == 0


# -- 4. signals --------------------------------------------------------------------------------------------------
def test_sigterm_publishes_nothing(scenarios: _Scenarios) -> None:
    _refused(scenarios, "sigterm", "nothing was published", code=143, prefix="latticedft: terminated (SIGTERM)")


def test_sigint_publishes_nothing(scenarios: _Scenarios) -> None:
    _refused(scenarios, "sigint", "nothing was published", code=130, prefix="latticedft: interrupted")


@pytest.mark.parametrize("name, code", [("int-loading", 130), ("term-loading", 143)])
def test_a_signal_while_the_engine_loads_is_one_line(scenarios: _Scenarios, name: str, code: int) -> None:
    _refused(scenarios, name, "nothing was published", code=code, prefix="latticedft: ")


@pytest.mark.parametrize("name", ["int-exit", "term-exit"])
def test_a_signal_after_the_outcome_changes_nothing(scenarios: _Scenarios, name: str) -> None:
    done = scenarios.done[name]
    assert done.code == 0 and done.err == "", (done.code, done.err)
    assert summary(scenarios.cases[name])["exit_status"] == 0
    assert staging_left(scenarios.cases[name].parent) == []


def test_sigterm_during_publishing_waits_for_it(scenarios: _Scenarios) -> None:
    s, name = scenarios, "sigterm-mid-publish"
    case = s.cases[name]
    done = s.done[name]
    assert done.code == 143
    one_line(done.err, "after publishing", prefix="latticedft: terminated")
    assert "--overwrite" in summary(case)["command"]  # the new results (the earlier run had no --overwrite)
    assert inputs_of(case) == inputs_of(s.template)
    assert staging_left(case.parent) == []


# -- 5. links and files ------------------------------------------------------------------------------------------
def test_symlinked_results_are_followed(tmp_path: Path, template: Path) -> None:
    case = earlier(template, tmp_path / "a")
    target = tmp_path / "elsewhere" / "res"
    target.parent.mkdir()
    shutil.move(case / "results", target)
    (case / "results").symlink_to(target)
    old = hashes(target)
    done = cli("run", case, "--overwrite", "-q")
    assert done.code == 0, done.err
    assert (case / "results").is_symlink() and (case / "results").resolve() == target.resolve()
    assert hashes(target) != old and (target / "summary.json").is_file()
    assert inputs_of(case) == inputs_of(template)
    assert staging_left(tmp_path) == []


@pytest.mark.parametrize("command", ["export", "serve"])
def test_links_inside_the_results_are_never_written_through(tmp_path: Path, template: Path, command: str) -> None:
    """A results file that links elsewhere (here run.log to the case's own data, and a task file to a file
    outside the case) is replaced by a copy: the file it pointed to stays byte-identical."""
    case = earlier(template, tmp_path / "a")
    data = case / "data" / "test_leapfrog.nc"
    outside = tmp_path / "outside.nc"
    shutil.copyfile(case / "results" / "test.nc", outside)
    (case / "results" / "run.log").unlink()
    (case / "results" / "run.log").symlink_to(data)
    (case / "results" / "test.nc").unlink()
    (case / "results" / "test.nc").symlink_to(outside)
    (case / "results" / "dangling").symlink_to(tmp_path / "nowhere")
    before, outside_before = hashes(case / "data"), hashes(tmp_path)["outside.nc"]
    done = cli(command, case, *(["--set", 'export.formats=["xdmf"]'] if command == "export" else []))
    assert done.code == 0, done.err
    assert "Traceback" not in done.err
    assert "run.log was a link to" in done.err + done.out and "left out of the updated results" in done.err + done.out
    assert hashes(case / "data") == before and hashes(tmp_path)["outside.nc"] == outside_before
    results = case / "results"
    assert not any(p.is_symlink() for p in results.rglob("*"))
    assert b"DEBUG" in (results / "run.log").read_bytes()
    assert staging_left(tmp_path) == []


def test_a_model_file_linked_to_a_device_is_named_as_such(tmp_path: Path, template: Path) -> None:
    case = earlier(template, tmp_path / "a")
    (case / "results" / "model.pt").unlink()
    (case / "results" / "model.pt").symlink_to("/dev/zero")
    done = cli("serve", case, "-q")
    one_line(done.err, "model.pt: is not a regular file", "/dev/zero")


def test_check_beside_a_run_in_progress_does_not_call_it_interrupted(tmp_path: Path, template: Path) -> None:
    import fcntl

    case = earlier(template, tmp_path / "a")
    (case / "results.tmp-0123456789").mkdir()  # the staging folder of a run that holds the lock
    fd = os.open(case, os.O_RDONLY)
    fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    try:
        done = cli("check", case)
    finally:
        os.close(fd)
    assert done.code == 0, done.err
    assert "a run in progress is writing results.tmp-0123456789" in done.out and "interrupted" not in done.out
    done = cli("check", case)  # the lock released: now it is a leftover
    assert "an interrupted run left results.tmp-0123456789" in done.out


def test_a_leftover_that_cannot_be_removed_is_not_called_removed(tmp_path: Path, template: Path) -> None:
    case = earlier(template, tmp_path / "a")
    stuck = case / "results.tmp-0123456789"
    stuck.mkdir()
    (stuck / "f").write_text("x")
    if shutil.which("chattr") is None or subprocess.run(["chattr", "+i", str(stuck / "f")]).returncode != 0:
        pytest.skip("chattr +i is not available here (needs root and a file system with attributes)")
    try:
        done = cli("serve", case)
        second = cli("serve", case)
    finally:
        subprocess.run(["chattr", "-i", str(stuck / "f")])
    for d in (done, second):
        assert d.code == 0, d.err
        assert "could not remove results.tmp-0123456789" in d.err and "removed (" not in d.err, d.err


def test_out_that_is_a_file_is_refused(scenarios: _Scenarios) -> None:
    _refused(scenarios, "out-file", "--out", "exists and is not a folder")
    assert (scenarios.root / "afile").read_text() == "a file, not a folder\n"


# -- 6. one task's clean-up never touches another's files --------------------------------------------------------------
def test_tasks_test_and_test_spacetime(tmp_path: Path) -> None:
    second = '\n[[serve]]\nname = "test_spacetime"\nfrom = "data/test.nc"\nslices = 12\n'
    case = make_case(tmp_path, formats='["paraview"]', extra=second)
    assert cli("run", case, "-q").code == 0
    res = case / "results"
    files = summary(case)["tasks"]
    assert "test_spacetime.vtr" in files["test"]["exports"]
    assert "test_spacetime.pvd" in files["test_spacetime"]["exports"]
    before = hashes(res)
    done = cli("export", case, "-q")
    assert done.code == 0, done.err
    after = hashes(res)
    assert set(after) == set(before)  # every file of both tasks is there again
    assert after["test.nc"] == before["test.nc"] and after["test_spacetime.nc"] == before["test_spacetime.nc"]
    for task in ("test", "test_spacetime"):
        assert all((res / f).is_file() for f in summary(case)["tasks"][task]["exports"])
    assert staging_left(tmp_path) == []


# -- 7. disk full, permissions ------------------------------------------------------------------------------------
def test_disk_full_injected(scenarios: _Scenarios) -> None:
    line = _refused(scenarios, "enospc", "cannot write", "No space left on device", "nothing was published")
    assert "results/model.pt" in line  # the path as it would be in the results folder


def test_permission_denied_injected(scenarios: _Scenarios) -> None:
    _refused(scenarios, "eacces", "cannot write", "Permission denied", "results")


def test_read_only_case_folder(tmp_path: Path, template: Path) -> None:
    case = earlier(template, tmp_path)
    before = hashes(case)
    os.chmod(case, 0o555)
    try:
        if os.access(case, os.W_OK):
            pytest.skip("chmod does not stop this user (root) from writing; the injected test covers it")
        done = cli("run", case, "--overwrite", "-q")
        assert done.code == 1
        one_line(done.err, "Permission denied")
    finally:
        os.chmod(case, 0o755)
    assert hashes(case) == before and staging_left(tmp_path) == []


def test_disk_full_on_a_small_tmpfs(tmp_path: Path) -> None:
    """A real full disk (a 1 MB tmpfs, left with a few kB free): needs root and mount; skipped otherwise."""
    mnt = tmp_path / "small"
    mnt.mkdir()
    if os.geteuid() != 0 or shutil.which("mount") is None:
        pytest.skip("mounting a tmpfs needs root")
    if subprocess.run(
        ["mount", "-t", "tmpfs", "-o", "size=1m", "tmpfs", str(mnt)], capture_output=True, check=False
    ).returncode:
        pytest.skip("cannot mount a tmpfs here")
    try:
        case = mnt / "w"
        (case / "data").mkdir(parents=True)
        for f in ("train.nc", "test.nc"):
            shutil.copy(WAVE / "data" / f, case / "data" / f)
        text = "\n".join(
            ln
            for ln in make_case(tmp_path).joinpath("case.toml").read_text().splitlines()
            if not ln.startswith("baseline")
        )
        (case / "case.toml").write_text(text + "\n")
        before = hashes(case)
        free = shutil.disk_usage(mnt).free
        with open(mnt / "filler", "wb") as fh:
            try:
                fh.write(b"\0" * (free - 12 * 1024))
            except OSError as exc:  # pragma: no cover - the tmpfs rounds to pages
                assert exc.errno == errno.ENOSPC
        done = cli("run", case, "-q")
        assert done.code == 1, done.err
        one_line(done.err, "cannot write", "nothing was published")
        assert hashes(case) == before and staging_left(mnt) == []
    finally:
        subprocess.run(["umount", str(mnt)], capture_output=True, check=False)


# -- 8, 9. limits checked by `check`, before training ------------------------------------------------------------------
def test_long_task_name_refused_at_check(scenarios: _Scenarios) -> None:
    _refused(scenarios, "long-name", "serve[0].name", "too long", "at most 255")


def test_task_too_big_for_memory_refused_before_training(scenarios: _Scenarios) -> None:
    _refused(scenarios, "steps-memory", "serve[0].slices", "of memory", "available")


def test_a_polynomial_too_big_to_solve_is_refused_before_training(scenarios: _Scenarios) -> None:
    """[200, 200] has 4.1e6 terms: 65 MB of parameters, but the exact solve's least-squares triangle alone needs
    133 TB (it was accepted, then training allocated 18 GiB and died)."""
    _refused(scenarios, "orders-memory", "model.orders", "4.08e+06 parameters", "least-squares triangle")


@pytest.mark.parametrize("command", ["serve", "export"])
def test_an_edited_model_table_is_not_served_as_if_used(tmp_path: Path, template: Path, command: str) -> None:
    """After an edit of [model] in case.toml, serve would record orders [3, 3] in summary.json while serving the
    model learned with [2, 2]: refused, naming the key and both values."""
    case = earlier(template, tmp_path / "a")
    text = (case / "case.toml").read_text()
    (case / "case.toml").write_text(text.replace("orders = [2, 2]", "orders = [3, 3]"))
    before = hashes(case)
    done = cli(command, case, *(["--set", 'export.formats=["xdmf"]'] if command == "export" else []))
    one_line(done.err, "model.orders: is [3, 3] now", "learned with [2, 2]", f"`{command}` uses the learned model")
    assert done.code == 1 and hashes(case) == before
    # a key given with --set at training is not an edit: the model learned with it is served
    assert cli("run", case, "--overwrite", "-q", "--set", "model.orders=[2,4]").code == 0
    done = cli(command, case, "-q", *(["--set", 'export.formats=["xdmf"]'] if command == "export" else []))
    assert done.code == 0, done.err


def test_no_success_line_when_publishing_fails(scenarios: _Scenarios) -> None:
    done = scenarios.done["enospc-publish"]
    assert done.code == 1 and "No space left on device" in done.err, done.err
    assert "results in" not in done.out + done.err  # it was printed before publishing, then publishing failed


def test_threads_beyond_the_cores_refused(scenarios: _Scenarios) -> None:
    _refused(scenarios, "threads", "run.threads", "an integer from 1 to", "got 100000")


def test_model_too_big_for_memory_refused_at_check(scenarios: _Scenarios) -> None:
    _refused(scenarios, "hidden-memory", "model.hidden", "parameters", "available")


# -- 10. model files are verified ------------------------------------------------------------------------------------
def test_non_finite_weights_refused(scenarios: _Scenarios) -> None:
    _refused(scenarios, "nan-weights", "model.pt", "non-finite weight")


def test_changed_model_file_refused(scenarios: _Scenarios) -> None:
    _refused(scenarios, "changed-model", "model.pt", "sha256", "model.json")


# -- 11. overrides that would not take effect; nothing to export -------------------------------------------------------
def test_serve_refuses_model_overrides(scenarios: _Scenarios) -> None:
    _refused(scenarios, "serve-model-override", "--set model.orders", "`latticedft train` and `run`")


def test_export_refuses_train_overrides(scenarios: _Scenarios) -> None:
    _refused(scenarios, "export-train-override", "--set train.ridge", "`latticedft train` and `run`")


def test_export_with_every_format_off(scenarios: _Scenarios) -> None:
    _refused(scenarios, "export-nothing", "nothing to export", "export.formats")


# -- the registry declares every file its exporters write --------------------------------------------------------------
@pytest.mark.parametrize("shape", ["1d", "1+1d", "2+1d"])
def test_export_file_names_cover_the_exporters(tmp_path: Path, shape: str) -> None:
    import numpy as np

    from latticedft import systems
    from latticedft.io.exporters import EXPORTERS, ExportTask, export_file_names, get_exporter

    if shape == "1d":
        field = systems.oscillator_sin(1.0, n=7)
    elif shape == "1+1d":
        field = systems.wave_string([(1, 1.0)], nx=5, nt=7)
    else:
        field = systems.make_field(np.zeros((7, 3, 4)), ("t", "y", "x"), spacing=0.1)
    field = field.rename("psi")
    for fmt in EXPORTERS:
        folder = tmp_path / fmt / shape
        folder.mkdir(parents=True)
        written = get_exporter(fmt).write(ExportTask(folder=folder, name="task", field=field, max_frames=3))
        declared = set(export_file_names("task", field.shape[0], [fmt]))
        names = {p.name for p in written}
        assert {p.name for p in folder.iterdir()} == names

        # frame numbers vary; their width does not: compare with the frame digits replaced
        def pattern(n: str) -> str:
            return "".join("#" if ch.isdigit() else ch for ch in n)

        assert {pattern(n) for n in names} <= {pattern(n) for n in declared}, (fmt, names, declared)
