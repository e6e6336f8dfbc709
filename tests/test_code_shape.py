"""The shape of the code: no function in latticedft/ has a body (docstring excluded) over 80 lines, and no
module imports itself through others when it is imported (no import circle).

``TOO_LONG`` lists the functions still over the limit while they are being split; it only shrinks, and
the test fails when an entry is split already (so that the list is kept exact).
"""

from __future__ import annotations

import ast
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PACKAGE = REPO / "latticedft"
MAX_BODY_LINES = 80

#: (file, function) still over the limit: split by other steps of the same change; the list must end empty.
TOO_LONG: set[tuple[str, str]] = set()


def _body_lines(fn: ast.FunctionDef | ast.AsyncFunctionDef) -> int:
    """Lines from the first statement after the docstring to the end of the function."""
    body = fn.body
    first = body[0] if body else None
    if isinstance(first, ast.Expr) and isinstance(first.value, ast.Constant) and isinstance(first.value.value, str):
        body = body[1:]
    if not body:
        return 0
    return int(fn.end_lineno or fn.lineno) - body[0].lineno + 1


def _long_functions() -> dict[tuple[str, str], int]:
    out = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                n = _body_lines(node)
                if n > MAX_BODY_LINES:
                    out[(path.relative_to(PACKAGE).as_posix(), node.name)] = n
    return out


def test_body_lines_leave_out_the_docstring() -> None:
    tree = ast.parse('def f():\n    """Doc\n    string."""\n    a = 1\n\n    return a\n')
    fn = tree.body[0]
    assert isinstance(fn, ast.FunctionDef) and _body_lines(fn) == 3


def test_no_function_body_over_80_lines() -> None:
    long = {k: n for k, n in _long_functions().items() if k not in TOO_LONG}
    assert not long, "functions over 80 lines of body (split them): " + "; ".join(
        f"latticedft/{f} {name}: {n} lines" for (f, name), n in sorted(long.items())
    )


def test_the_list_of_long_functions_is_exact() -> None:
    split = sorted(TOO_LONG - set(_long_functions()))
    assert not split, f"TOO_LONG lists functions no longer over 80 lines (remove them): {split}"


def _import_time_imports(body: list[ast.stmt]) -> list[ast.Import | ast.ImportFrom]:
    """The import statements a module runs when it is imported: at its top level, and in top-level ``try``
    and ``if`` blocks but those under ``if TYPE_CHECKING`` (which type checkers alone read)."""
    out: list[ast.Import | ast.ImportFrom] = []
    for node in body:
        if isinstance(node, (ast.Import, ast.ImportFrom)):
            out.append(node)
        elif isinstance(node, ast.If):
            test = node.test
            checking = isinstance(test, ast.Name) and test.id == "TYPE_CHECKING"
            checking |= isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING"
            out += _import_time_imports(node.orelse if checking else node.body + node.orelse)
        elif isinstance(node, ast.Try):
            out += _import_time_imports(node.body + node.orelse + node.finalbody)
            for handler in node.handlers:
                out += _import_time_imports(handler.body)
    return out


def _import_graph(package: Path) -> dict[str, set[str]]:
    """Module -> the modules of the package it imports when it is imported (relative and absolute imports; a
    name imported from a package that is one of its modules counts as that module)."""
    root = package.name
    names = {}
    for path in sorted(package.rglob("*.py")):
        parts = list(path.relative_to(package.parent).with_suffix("").parts)
        names[path] = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
    modules = set(names.values())
    graph: dict[str, set[str]] = {}
    for path, name in names.items():
        here = name if path.name == "__init__.py" else name.rpartition(".")[0]
        deps: set[str] = set()
        for node in _import_time_imports(ast.parse(path.read_text(), str(path)).body):
            if isinstance(node, ast.Import):
                deps |= {a.name for a in node.names if a.name.split(".")[0] == root}
                continue
            if node.level:
                base = here.split(".")[: len(here.split(".")) - (node.level - 1)]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            if target.split(".")[0] != root:
                continue
            subs = {f"{target}.{a.name}" for a in node.names} & modules
            deps |= subs if subs and not node.module else subs | {target}
        graph[name] = {d for d in deps if d in modules and d != name}
    return graph


def _circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The import circles of ``graph``: its strongly connected components of more than one module."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    out: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def test_a_circle_is_found(tmp_path: Path) -> None:
    pkg = tmp_path / "pkg"
    (pkg / "sub").mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "sub" / "__init__.py").write_text("from ._b import x\n")
    (pkg / "sub" / "_a.py").write_text("from typing import TYPE_CHECKING\nfrom ._b import x\n")
    (pkg / "sub" / "_b.py").write_text("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from ._a import y\n")
    assert _circles(_import_graph(pkg)) == []  # an import for type checking only is no circle
    (pkg / "sub" / "_b.py").write_text("def f():\n    from ._a import y\n")
    assert _circles(_import_graph(pkg)) == []  # nor one inside a function
    (pkg / "sub" / "_b.py").write_text("try:\n    from . import _a\nexcept ImportError:\n    pass\n")
    assert _circles(_import_graph(pkg)) == [["pkg.sub._a", "pkg.sub._b"]]


def test_no_import_circle() -> None:
    graph = _import_graph(PACKAGE)
    assert "latticedft._serve._stepper" in graph["latticedft._serve._field"]
    circles = _circles(graph)
    assert not circles, "modules that import each other when imported: " + "; ".join(" -> ".join(c) for c in circles)
