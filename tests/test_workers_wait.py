"""The ``--workers`` launcher's wait: an error every rank met is said once, by rank 0; another rank's own
failure is said as ``worker N failed: ...`` (stand-in ranks: small Python processes, no process group)."""

from __future__ import annotations

import subprocess
import sys
import tempfile
from pathlib import Path

import pytest

from latticedft.cli import _workers

LINE = "latticedft: error: data/train_bad.nc: not a readable netCDF file"


def _rank(folder: Path, rank: int, line: str | None, *, after: float = 0.0, hang: bool = False):
    """A stand-in rank: after ``after`` seconds it writes ``line`` (if any) to its error file and stderr and
    exits 1 (``hang``: it never ends by itself)."""
    code = "import sys, time\n"
    code += "time.sleep(3600)\n" if hang else f"time.sleep({after})\n"
    if line is not None:
        code += f"open({str(folder / f'rank{rank}')!r}, 'w').write({line!r} + '\\n')\n"
        code += f"print({line!r}, file=sys.stderr)\n"
    code += "sys.exit(1)\n"
    log = None if rank == 0 else tempfile.TemporaryFile()  # noqa: SIM115 - closed by the test
    return subprocess.Popen([sys.executable, "-c", code], stdout=log, stderr=log), log


def _wait(tmp_path: Path, ranks: list[tuple]) -> int:
    started = [_rank(tmp_path, r, *spec[:1], **spec[1]) for r, spec in enumerate(ranks)]
    procs, logs = [p for p, _ in started], [f for _, f in started]
    try:
        return _workers._wait(procs, logs, str(tmp_path))
    finally:
        for p in procs:
            p.kill()
            p.wait()
        for f in logs:
            if f is not None:
                f.close()


def test_an_error_every_rank_met_is_said_once_by_rank_0(tmp_path: Path, capfd) -> None:
    # rank 1 fails at once, rank 0 a moment later with the same line: only rank 0's own line is printed
    code = _wait(tmp_path, [(LINE, {"after": 0.5}), (LINE, {})])
    assert code == 1
    err = capfd.readouterr().err
    assert err.count("latticedft: error:") == 1 and "worker 1 failed" not in err, err


def test_another_ranks_own_error_is_said_as_its_failure(tmp_path: Path, capfd) -> None:
    code = _wait(tmp_path, [("latticedft: error: something else", {"after": 0.5}), (LINE, {})])
    assert code == 1
    err = capfd.readouterr().err
    assert f"latticedft: error: worker 1 failed: {LINE}" in err, err


def test_a_rank_0_that_does_not_end_is_not_waited_for_beyond_the_grace(
    tmp_path: Path, capfd, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(_workers, "RANK0_GRACE_S", 0.2)
    code = _wait(tmp_path, [(None, {"hang": True}), (LINE, {})])
    assert code == 1
    assert f"worker 1 failed: {LINE}" in capfd.readouterr().err
