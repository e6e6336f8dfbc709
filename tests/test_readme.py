"""The README's Python example runs and does what it says."""

from __future__ import annotations

import contextlib
import io
import re
from pathlib import Path

README = Path(__file__).resolve().parents[1] / "README.md"


def _blocks(lang: str) -> list[str]:
    return re.findall(rf"```{lang}\n(.*?)```", README.read_text(), flags=re.S)


def test_readme_python_example_runs() -> None:
    (code,) = _blocks("python")
    assert len(code.strip().splitlines()) <= 12
    out = io.StringIO()
    namespace: dict = {}
    with contextlib.redirect_stdout(out):
        exec(compile(code, str(README), "exec"), namespace)
    assert "learned by exact" in out.getvalue() and "L_d =" in out.getvalue()
    errors = namespace["ldft"].compare(namespace["served"].field, namespace["test"])
    assert errors["slices"] == 201 and errors["max_error"] < 0.05


def test_readme_commands_match_ci() -> None:
    (bash,) = _blocks("bash")
    install, tests = bash.strip().splitlines()
    assert install.startswith('pip install -e ".[test]"') and tests == "python -m pytest -q"
    ci = (README.parent / ".ci" / "run").read_text()
    assert 'pip install -e ".[test]"' in ci and "python -m pytest -q" in ci
