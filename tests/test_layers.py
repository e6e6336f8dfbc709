"""The package's layers as docs/design.md lists them: no import runs back up.

The layer table of docs/design.md ("## Layers") is the source of truth: every module of the package must
sit in one of its layers, and every import of a package module (at the top of a file or inside a
function) must reach a module of the same layer or of a lower one. The package's ``__init__`` re-exports
the public names and is outside the stack: a module may take only ``__version__`` from it.

Two more rules keep the stack honest. No module imports itself back through others (no import cycle,
imports inside functions included). And an import inside a function, which hides both a cycle and the
cost of a dependency, is kept only for the heavy or optional dependencies of ``DEFERRED_PACKAGES`` and the
few package imports of ``DEFERRED_MODULES``, each with its reason.
"""

from __future__ import annotations

import ast
import re
from pathlib import Path
from typing import NamedTuple

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


class Import(NamedTuple):
    """One import statement's reach: the module it names and where it stands."""

    line: int
    target: str  # the module imported (for `from m import name`, ``m.name`` when that is a module)
    names: tuple[str, ...]  # the names taken by `from m import ...` (empty for `import m`)
    deferred: bool  # inside a function: runs when the function is called, not when the module is imported


def _typing_only(tree: ast.AST) -> set[int]:
    """Ids of the nodes under `if TYPE_CHECKING:`: those imports never run, annotations may name any layer."""
    return {
        id(sub)
        for node in ast.walk(tree)
        if isinstance(node, ast.If) and isinstance(node.test, ast.Name) and node.test.id == "TYPE_CHECKING"
        for stmt in node.body
        for sub in ast.walk(stmt)
    }


def _statements(tree: ast.AST) -> list[tuple[ast.Import | ast.ImportFrom, bool]]:
    """Every import statement of ``tree`` that runs, and whether it sits inside a function."""
    skip = _typing_only(tree)
    out: list[tuple[ast.Import | ast.ImportFrom, bool]] = []

    def visit(node: ast.AST, in_function: bool) -> None:
        for child in ast.iter_child_nodes(node):
            if id(child) in skip:
                continue
            if isinstance(child, (ast.Import, ast.ImportFrom)):
                out.append((child, in_function))
            visit(child, in_function or isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)))

    visit(tree, False)
    return out


def _all_imports(path: Path) -> list[Import]:
    """Every import that runs in ``path`` (of any module: the package's, the standard library's, others')."""
    me = _module_name(path)
    package = me if path.name == "__init__.py" else me.rpartition(".")[0]
    out = []
    for node, deferred in _statements(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            out += [Import(node.lineno, a.name, (), deferred) for a in node.names]
            continue
        if node.level:
            base = package.split(".")
            base = base[: len(base) - (node.level - 1)]
            target = ".".join(base + ([node.module] if node.module else []))
        else:
            target = node.module or ""
        names = tuple(a.name for a in node.names)
        if target.split(".")[0] != "latticedft":
            out.append(Import(node.lineno, target, names, deferred))
            continue
        for name in names:  # `from . import lagrangians` imports a module
            sub = f"{target}.{name}"
            out.append(
                Import(node.lineno, sub, (), deferred)
                if _is_module(sub)
                else Import(node.lineno, target, (name,), deferred)
            )
    return out


def _imports(path: Path) -> list[Import]:
    """Every import of a latticedft module that runs in ``path``."""
    return [i for i in _all_imports(path) if i.target.split(".")[0] == "latticedft"]


def _layer_of(name: str, layers: dict[str, int]) -> int | None:
    """Layer of the longest table entry that is ``name`` or a package holding it."""
    best = None
    for entry, layer in layers.items():
        if (name == entry or name.startswith(entry + ".")) and (best is None or len(entry) > len(best[0])):
            best = (entry, layer)
    return None if best is None else best[1]


MODULES = sorted(p for p in PACKAGE.rglob("*.py") if p != PACKAGE / "__init__.py")

#: Packages a function may import when it is called rather than at the top of its module, and why: each is
#: heavy to import or optional, and the module is useful without it.
DEFERRED_PACKAGES: dict[str, str] = {
    "torch": "about a second to import: the command line, latticedft.systems and io answer without it",
    "scipy": "systems: only the reference solutions that integrate or quadrature need it",
    "matplotlib": "figures: only when a figure is drawn",
    "meshio": "XDMF export: an optional dependency",
    "h5py": "XDMF export: an optional dependency",
    "netCDF4": "part files: written through the netCDF4 library itself only when a task is served with a cadence",
    "tqdm": "progress bars: tqdm.notebook needs ipywidgets and serves only in a notebook; tqdm.std with the first bar",
    "sympy": "about half a second to import: only closed-form L_d (printing, to_sympy, compiled kernels) needs it",
    "numba": "compiled DEL kernels: a second to import and seconds to compile, only when a closed-form L_d is served",
    "fcntl": "POSIX only: where it is missing, the results folder is not locked",
}

#: Imports of package modules inside functions: (importing module or package, imported module) -> why.
#: Keep it short: an entry here is a dependency the layer test and the cycle test see only when it runs.
DEFERRED_MODULES: dict[tuple[str, str], str] = {
    ("latticedft.cli", "latticedft"): "the command line answers --help and usage errors before torch and xarray "
    "load: each command imports the engine when it runs",
    ("latticedft.io", "latticedft.io.vtk"): "a public attribute loaded on first use: pyvista",
    ("latticedft.io", "latticedft.io.figures"): "a public attribute loaded on first use: matplotlib",
    ("latticedft.io", "latticedft.io.xdmf"): "a public attribute loaded on first use: meshio and h5py",
    ("latticedft._results._files", "latticedft._modelfile"): "torch, only when a model file is read or written",
}

#: Import cycles left for now, as sets of modules, and why.
CYCLES_ALLOWED: dict[frozenset[str], str] = {}


def _matches(name: str, entry: str) -> bool:
    return name == entry or name.startswith(entry + ".")


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
    for imp in _imports(path):
        where = f"{path.relative_to(REPO)}:{imp.line}"
        if imp.target == "latticedft":  # the package root re-exports everything: only its version is below all
            assert imp.names == ("__version__",), (
                f"{where}: {me} imports {', '.join(imp.names) or 'latticedft'} from the package root; "
                "import it from the module that owns it (only __version__ may come from the root)"
            )
            continue
        theirs = _layer_of(imp.target, layers)
        assert theirs is not None, f"{me} imports {imp.target}, which docs/design.md does not place in a layer"
        assert theirs <= mine, (
            f"{where}: {me} (layer {mine}) imports {imp.target} "
            f"(layer {theirs}): an import runs back up the layers of docs/design.md"
        )


def _graph() -> dict[str, set[str]]:
    """Module -> the package modules it imports (at the top or inside functions; the root left out)."""
    graph: dict[str, set[str]] = {}
    for path in MODULES:
        graph[_module_name(path)] = {i.target for i in _imports(path) if i.target != "latticedft"}
    return graph


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """One cycle through every strongly connected group of modules (Tarjan), as a closed path."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    groups: list[set[str]] = []

    def connect(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                connect(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            group = set()
            while True:
                w = stack.pop()
                group.add(w)
                if w == v:
                    break
            if len(group) > 1 or v in graph.get(v, ()):
                groups.append(group)

    for v in sorted(graph):
        if v not in index:
            connect(v)
    cycles = []
    for group in groups:  # the shortest way back to the group's first module, inside the group
        first = min(group)
        paths = {first: [first]}
        queue = [first]
        while queue:
            v = queue.pop(0)
            for w in sorted(graph[v] & group):
                if w == first:
                    cycles.append([*paths[v], first])
                    queue = []
                    break
                if w not in paths:
                    paths[w] = [*paths[v], w]
                    queue.append(w)
    return cycles


def test_the_cycle_finder_finds_a_cycle() -> None:
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a", "d"}, "d": set(), "e": {"e"}}
    assert sorted(_cycles(graph)) == [["a", "b", "c", "a"], ["e", "e"]]


def test_no_import_cycle() -> None:
    cycles = [c for c in _cycles(_graph()) if frozenset(c) not in CYCLES_ALLOWED]
    assert not cycles, "import cycles between package modules: " + "; ".join(" -> ".join(c) for c in cycles)


def test_allowed_cycles_still_exist() -> None:
    found = {frozenset(c) for c in _cycles(_graph())}
    stale = [sorted(c) for c in CYCLES_ALLOWED if c not in found]
    assert not stale, f"CYCLES_ALLOWED lists cycles that are gone (remove them): {stale}"


def _deferred() -> list[tuple[str, Import]]:
    return [(_module_name(path), i) for path in MODULES for i in _all_imports(path) if i.deferred]


def test_imports_inside_functions_are_only_the_listed_ones() -> None:
    bad = []
    for me, imp in _deferred():
        if imp.target.split(".")[0] == "latticedft":
            ok = any(_matches(me, a) and _matches(imp.target, b) for a, b in DEFERRED_MODULES)
        else:
            ok = imp.target.split(".")[0] in DEFERRED_PACKAGES
        if not ok:
            bad.append(f"{me}:{imp.line} imports {imp.target}")
    assert not bad, (
        "imports inside functions that DEFERRED_PACKAGES / DEFERRED_MODULES do not list "
        "(move them to the top of the module, or break the cycle they dodge): " + "; ".join(bad)
    )


def test_deferred_lists_are_not_stale() -> None:
    deferred = _deferred()
    packages = {i.target.split(".")[0] for _, i in deferred}
    stale: list[object] = [name for name in DEFERRED_PACKAGES if name not in packages]
    stale += [
        key
        for key in DEFERRED_MODULES
        if not any(_matches(me, key[0]) and _matches(i.target, key[1]) for me, i in deferred)
    ]
    assert not stale, f"entries no function imports any more (remove them): {stale}"
