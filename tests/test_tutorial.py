"""The notebook docs/tutorial.ipynb runs from top to bottom, and the progress bar shows in Jupyter and on a
terminal (not elsewhere)."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import nbformat
import pytest
from nbclient import NotebookClient

REPO = Path(__file__).resolve().parents[1]
NOTEBOOK = REPO / "docs" / "tutorial.ipynb"
ENV = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO), *filter(None, [os.environ.get("PYTHONPATH")])])}


def _outputs(nb: nbformat.NotebookNode) -> list[nbformat.NotebookNode]:
    return [o for c in nb.cells if c.cell_type == "code" for o in c.outputs]


def test_the_tutorial_runs_and_shows_its_results(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("PYTHONPATH", ENV["PYTHONPATH"])  # the kernel imports this checkout
    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    nb = nbformat.read(NOTEBOOK, as_version=4)
    NotebookClient(
        nb, timeout=600, kernel_name="python3", resources={"metadata": {"path": str(NOTEBOOK.parent)}}
    ).execute()
    outputs = _outputs(nb)
    assert not [o for o in outputs if o.output_type == "error"]
    text = "".join(o.get("text", "") for o in outputs if o.output_type == "stream")
    stderr = "".join(o.get("text", "") for o in outputs if o.output_type == "stream" and o.name == "stderr")
    assert "learned by exact" in text and "max_error" in text and "within_2std" in text
    assert "serve (newton" in stderr and "49/49" in stderr, stderr  # the bar, shown by default
    assert sum("image/png" in o.get("data", {}) for o in outputs) == 2  # both figures drawn


def test_the_committed_tutorial_is_executed() -> None:
    """The notebook in the repository carries its outputs (they render where it is read); made by
    ``python docs/make_tutorial.py``."""
    nb = nbformat.read(NOTEBOOK, as_version=4)
    code = [c for c in nb.cells if c.cell_type == "code"]
    assert code and all(c.outputs for c in code)


@pytest.mark.skipif(not hasattr(os, "openpty"), reason="needs a pseudo-terminal")
def test_the_progress_bar_shows_on_a_terminal_and_not_in_a_pipe() -> None:
    script = textwrap.dedent(
        """
        import latticedft as ldft
        from latticedft import systems
        model = ldft.PolynomialLagrangian(orders=(4, 8))
        ldft.learn(model, [systems.oscillator_sin(a) for a in (1.2, 0.8)])
        ldft.serve(model, systems.oscillator_sin(-0.6))
        """
    )
    from helpers import on_a_terminal

    code, tty = on_a_terminal([sys.executable, "-c", script], ENV)
    assert code == 0, tty
    assert "serve (newton" in tty and "/49 [" in tty and "\r" in tty, tty  # drawn in place, then cleared
    piped = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=ENV, timeout=300)
    assert piped.returncode == 0 and piped.stderr == "", piped.stderr
