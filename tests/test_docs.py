"""The Python examples of docs/api.md and docs/mathematics.md run, so the docs cannot rot.

Every fenced ```python block of a page is executed in order, in one namespace per page (later
blocks use names defined by earlier ones). The blocks assert what they claim.
"""

from __future__ import annotations

import contextlib
import io
import os
import re
from pathlib import Path

import pytest

DOCS = Path(__file__).resolve().parents[1] / "docs"
PAGES = ["api.md", "mathematics.md"]


def _python_blocks(page: Path) -> list[tuple[int, str]]:
    """(first line number, code) of every ```python block."""
    text = page.read_text()
    out = []
    for match in re.finditer(r"^```python\n(.*?)^```", text, flags=re.S | re.M):
        line = text.count("\n", 0, match.start(1)) + 1
        out.append((line, match.group(1)))
    return out


@pytest.mark.parametrize("page", PAGES)
def test_python_blocks_run(page: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = DOCS / page
    blocks = _python_blocks(path)
    assert blocks, f"{page}: no python blocks found"
    monkeypatch.chdir(tmp_path)  # blocks that write files write them here
    namespace: dict = {"__name__": f"docs_{page.replace('.', '_')}"}
    out = io.StringIO()
    for line, code in blocks:
        # pad with newlines so tracebacks show the line number in the Markdown file
        compiled = compile("\n" * (line - 1) + code, str(path), "exec")
        with contextlib.redirect_stdout(out):
            exec(compiled, namespace)
    assert out.getvalue(), f"{page}: the examples printed nothing"


def test_index_links_every_page() -> None:
    index = (DOCS / "index.md").read_text()
    linked = set(re.findall(r"\]\(([\w.-]+\.md)\)", index))
    for page in os.listdir(DOCS):
        if page.endswith(".md") and page != "index.md" and (DOCS / page).is_file():
            assert page in linked, f"docs/index.md does not link {page}"
