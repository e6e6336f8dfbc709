"""The package's layers as docs/design.md lists them: no import runs back up.

The layer table of docs/design.md ("## Layers") is the source of truth: every module of the package must
sit in one of its layers, and every import of a package module (at the top of a file or inside a
function) must reach a module of the same layer or of a lower one. The package's ``__init__`` re-exports
the public names and is outside the stack.
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PACKAGE = REPO / "latticedft"
LAYERS_PAGE = REPO / "docs" / "design.md"


def _layers() -> dict[str, int]:
    """Module (or package) name -> layer number, from the table of docs/design.md."""
    text = LAYERS_PAGE.read_text()
    section = text.split("## Layers", 1)[1].split("\n## ", 1)[0]
    out: dict[str, int] = {}
    for row in section.splitlines():
        match = re.match(r"^\|\s*(\d+)\b[^|]*\|([^|]*)\|", row)
        if match:
            for name in re.findall(r"`(latticedft(?:\.\w+)*)`", match.group(2)):
                out[name] = int(match.group(1))
    return out


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(REPO).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _is_module(name: str) -> bool:
    rel = Path(*name.split("."))
    return (REPO / rel).with_suffix(".py").is_file() or (REPO / rel / "__init__.py").is_file()


def _imports(path: Path) -> list[tuple[int, str]]:
    """(line, module) of every import of a latticedft module in ``path``."""
    me = _module_name(path)
    package = me if path.name == "__init__.py" else me.rpartition(".")[0]
    tree = ast.parse(path.read_text(), str(path))
    typing_only = {  # imports under `if TYPE_CHECKING:` never run: annotations may name any layer
        id(sub)
        for node in ast.walk(tree)
        if isinstance(node, ast.If) and isinstance(node.test, ast.Name) and node.test.id == "TYPE_CHECKING"
        for stmt in node.body
        for sub in ast.walk(stmt)
    }
    out = []
    for node in ast.walk(tree):
        if id(node) in typing_only:
            continue
        if isinstance(node, ast.Import):
            out += [(node.lineno, a.name) for a in node.names if a.name.split(".")[0] == "latticedft"]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - (node.level - 1)]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            if target.split(".")[0] != "latticedft":
                continue
            for alias in node.names:  # `from . import lagrangians` imports a module
                sub = f"{target}.{alias.name}"
                out.append((node.lineno, sub if _is_module(sub) else target))
    return out


def _layer_of(name: str, layers: dict[str, int]) -> int | None:
    """Layer of the longest table entry that is ``name`` or a package holding it."""
    best = None
    for entry, layer in layers.items():
        if (name == entry or name.startswith(entry + ".")) and (best is None or len(entry) > len(best[0])):
            best = (entry, layer)
    return None if best is None else best[1]


MODULES = sorted(p for p in PACKAGE.rglob("*.py") if p != PACKAGE / "__init__.py")


def test_the_layer_table_is_read() -> None:
    layers = _layers()
    assert layers.get("latticedft._errors") == 0 and layers.get("latticedft.cli") == max(layers.values())
    assert len(set(layers.values())) >= 8


@pytest.mark.parametrize("path", MODULES, ids=lambda p: _module_name(p))
def test_module_imports_only_its_layer_and_below(path: Path) -> None:
    layers = _layers()
    me = _module_name(path)
    mine = _layer_of(me, layers)
    assert mine is not None, f"docs/design.md does not place {me} in a layer (add it to the table)"
    for line, target in _imports(path):
        if target == "latticedft":  # the package root: re-exports and __version__
            continue
        theirs = _layer_of(target, layers)
        assert theirs is not None, f"{me} imports {target}, which docs/design.md does not place in a layer"
        assert theirs <= mine, (
            f"{path.relative_to(REPO)}:{line}: {me} (layer {mine}) imports {target} "
            f"(layer {theirs}): an import runs back up the layers of docs/design.md"
        )
