"""The documentation runs: every ```python block of README.md, docs/*.md and the case READMEs.

One runner for every page: the blocks of a page are executed in order in one namespace (later blocks use
names defined by earlier ones), in a temporary working directory, with tracebacks pointing at the line of
the Markdown file. The blocks assert what they claim; a page may add checks of its own below (``CHECKS``).
Also: README.md's commands are the ones CI runs, and docs/index.md links every page.
"""

from __future__ import annotations

import contextlib
import io
import os
import re
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
DOCS = REPO / "docs"
README = REPO / "README.md"


def _blocks(page: Path, lang: str) -> list[tuple[int, str]]:
    """(first line number, code) of every ```lang block."""
    text = page.read_text()
    out = []
    for match in re.finditer(rf"^```{lang}\n(.*?)^```", text, flags=re.S | re.M):
        out.append((text.count("\n", 0, match.start(1)) + 1, match.group(1)))
    return out


def _check_readme(namespace: dict, printed: str, blocks: list[tuple[int, str]]) -> None:
    """The ten-line example is (about) ten lines, learns exactly and serves within its error."""
    ((_, code),) = blocks
    assert len(code.strip().splitlines()) <= 12
    assert "learned by exact" in printed and "L_d =" in printed
    errors = namespace["ldft"].compare(namespace["served"].field, namespace["test"])
    assert errors["slices"] == 201 and errors["max_error"] < 0.05


#: Extra checks of a page, beyond "its blocks run and print something".
CHECKS = {"README.md": _check_readme}
#: Pages that must hold python blocks (so the runner cannot silently find none).
REQUIRED = ["README.md", "docs/api.md", "docs/mathematics.md"]

PAGES = sorted(
    str(p.relative_to(REPO))
    for p in [README, *DOCS.glob("*.md"), *REPO.glob("cases/*/README.md")]
    if _blocks(p, "python")
)


def test_required_pages_hold_python_blocks() -> None:
    assert set(REQUIRED) <= set(PAGES), f"no python blocks found in {sorted(set(REQUIRED) - set(PAGES))}"


@pytest.mark.parametrize("page", PAGES)
def test_python_blocks_run(page: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = REPO / page
    blocks = _blocks(path, "python")
    monkeypatch.chdir(tmp_path)  # blocks that write files write them here
    namespace: dict = {"__name__": "docs_" + re.sub(r"\W", "_", page)}
    out = io.StringIO()
    for line, code in blocks:
        # pad with newlines so tracebacks show the line number in the Markdown file
        compiled = compile("\n" * (line - 1) + code, str(path), "exec")
        with contextlib.redirect_stdout(out):
            exec(compiled, namespace)
    assert out.getvalue(), f"{page}: the examples printed nothing"
    if page in CHECKS:
        CHECKS[page](namespace, out.getvalue(), blocks)


def test_readme_commands_match_ci() -> None:
    (_, bash), *_ = _blocks(README, "bash")  # the first: the two commands (a quick subset of the tests follows)
    install, tests = bash.strip().splitlines()
    assert install.startswith('pip install -e ".[test]"') and tests.startswith("python -m pytest -q")
    ci = (REPO / ".ci" / "run").read_text()
    assert 'pip install -e ".[test]"' in ci and tests in ci.splitlines()  # exactly the README's test command


def test_index_links_every_page() -> None:
    index = (DOCS / "index.md").read_text()
    linked = set(re.findall(r"\]\(([\w.-]+\.md)\)", index))
    for page in os.listdir(DOCS):
        if page.endswith(".md") and page != "index.md" and (DOCS / page).is_file():
            assert page in linked, f"docs/index.md does not link {page}"


def test_the_product_refers_to_nothing_outside_itself() -> None:
    """No text names a design note or an issue number that a reader of the repository does not have."""
    import subprocess

    pattern = re.compile("DESIGN" + r"(\.md| §)|\b[Ii]ssue" + r" #?\d+")
    files = subprocess.run(["git", "ls-files"], cwd=REPO, capture_output=True, text=True, check=False).stdout.split()
    if not files:  # not a git checkout (e.g. an sdist): scan the tree
        files = [str(p.relative_to(REPO)) for p in REPO.rglob("*") if p.is_file() and ".git" not in p.parts]
    found = []
    for name in files:
        path = REPO / name
        if path.suffix not in {".py", ".md", ".toml", ".txt", ".cfg", ""} or not path.is_file():
            continue
        for k, line in enumerate(path.read_text(errors="replace").splitlines(), 1):
            if pattern.search(line):
                found.append(f"{name}:{k}: {line.strip()[:80]}")
    assert not found, "\n".join(found)
