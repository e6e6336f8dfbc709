"""Smoke test of ``python -m benchmarks.threads``: one workload through the four settings prints its table.

No timing is asserted (docs/performance.md holds the measured figures).
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


@pytest.mark.slow
def test_threads_benchmark_runs() -> None:
    env = dict(os.environ, OMP_NUM_THREADS="1", PYTHONPATH=str(ROOT))
    proc = subprocess.run(
        [sys.executable, "-m", "benchmarks.threads", "--only", "exact-small"],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
        check=False,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    out = proc.stdout
    assert "load average" in out and "2/1 idle" in out and "2/1 busy" in out
    row = next(ln for ln in out.splitlines() if ln.startswith("exact solve, polynomial (4, 8)"))
    assert len(row.split()) >= 6 + 6  # the workload's words, then six figures
