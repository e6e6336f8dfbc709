"""Compiled per-cell derivatives of a closed-form ``L_d``: one fused numba kernel generated from its sympy form.

Serving needs, on every cell of a slice, the gradient ``dL/dx`` and the mixed Hessian blocks
``d^2 L / dx_a dx_b`` of the slice's stencil pairs. For a model known in closed form
(:meth:`AbstractLagrangian.symbolic`) these are differentiated once by sympy, their common subexpressions
shared (``sympy.cse``), and printed as one loop over the cells, parallel (``numba.prange``): each cell's
values are read inside the loop and every intermediate is a scalar, so there is no Python per cell and no
array per term. Two entry points are generated, the gradient alone and the gradient with the blocks.

The generated source is written once to the kernel cache folder (``LATTICEDFT_KERNEL_CACHE``, default
``~/.cache/latticedft/kernels``) under the hash of what it computes, and numba caches its machine code
beside it (``cache=True``): the first build of a kernel (differentiation, printing, compilation: seconds)
happens once per ``L_d`` and machine, and is reported apart (:data:`BUILDS`, one info line). A model whose
form cannot be compiled (no numba, a function the printer does not know) returns ``None``: serving keeps its
numpy, torch or autograd path, and one info line says why.
"""

from __future__ import annotations

import hashlib
import importlib.util
import logging
import os
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ._symbolic import SymbolicLd

__all__ = ["BUILDS", "CompiledForms", "cache_dir", "compile_forms"]

log = logging.getLogger("latticedft")

#: Every kernel this process built or loaded: ``(what, seconds, "built" or "cached")``.
BUILDS: list[tuple[str, float, str]] = []

#: Kernels already loaded in this process, by hash.
_LOADED: dict[str, Any] = {}

#: Forms whose build failed in this process, by hash (the failure is reported once).
_FAILED: set[str] = set()

#: Bumped whenever the generated code changes, so that stale cached kernels are not reused.
_VERSION = 2


def cache_dir() -> Path:
    """The folder of generated kernels: ``LATTICEDFT_KERNEL_CACHE``, else ``~/.cache/latticedft/kernels``."""
    env = os.environ.get("LATTICEDFT_KERNEL_CACHE")
    return Path(env) if env else Path.home() / ".cache" / "latticedft" / "kernels"


@dataclass(frozen=True)
class CompiledForms:
    """The compiled kernels of one ``L_d`` for one tuple of pairs.

    ``grad(cells)``: ``(B, K, m) -> (B, K, m)``; ``both(cells)``: ``(grad, [block (B, m, m) per pair])``.
    """

    module: Any
    k: int
    m: int
    npairs: int

    def grad(self, cells: np.ndarray) -> np.ndarray:
        """``dL/dx`` on every cell."""
        cells = np.ascontiguousarray(cells, dtype=np.float64).reshape(-1, self.k, self.m)
        out = np.empty_like(cells)
        _kernel(self.module, "grad", cells.shape[0])(cells, out)
        return out

    def both(self, cells: np.ndarray) -> tuple[np.ndarray, list[np.ndarray]]:
        """``dL/dx`` and the blocks of the pairs on every cell."""
        cells = np.ascontiguousarray(cells, dtype=np.float64).reshape(-1, self.k, self.m)
        out = np.empty_like(cells)
        blocks = np.empty((self.npairs, cells.shape[0], self.m, self.m))
        _kernel(self.module, "both", cells.shape[0])(cells, out, blocks)
        return out, list(blocks)


#: Cells per thread below which the serial kernel runs (starting threads costs more than it saves).
PARALLEL_MIN_CELLS = 65536


def _kernel(module: Any, name: str, cells: int) -> Callable[..., None]:
    """The parallel kernel ``name`` with as many threads as torch has (which :func:`latticedft.limit_threads`
    bounds with the BLAS pools), or the serial one for one thread or few cells."""
    import numba
    import torch

    threads = min(
        torch.get_num_threads(), int(getattr(numba.config, "NUMBA_NUM_THREADS", 1)), cells // PARALLEL_MIN_CELLS
    )
    if threads <= 1:
        return getattr(module, f"{name}_kernel_serial")  # type: ignore[no-any-return]
    numba.set_num_threads(threads)
    return getattr(module, f"{name}_kernel")  # type: ignore[no-any-return]


def _printed(exprs: Sequence[Any]) -> tuple[list[str], list[str]]:
    """``(assignments, values)``: the common subexpressions as ``x = ...`` lines and each expression's value,
    printed as Python that numba compiles (``math`` functions, float literals to the bit)."""
    import sympy
    from sympy.printing.pycode import PythonCodePrinter

    class _Printer(PythonCodePrinter):  # type: ignore[misc]
        def _print_Float(self, expr: Any) -> str:
            return repr(float(expr))

        def _print_Rational(self, expr: Any) -> str:
            return repr(float(expr))

        def _print_Pow(self, expr: Any, rational: bool = False) -> str:
            base, e = expr.args
            if e.is_Integer and 1 < int(e) <= 16:  # repeated products: exact and faster than pow
                b = self.parenthesize(base, 100)
                return "(" + "*".join([b] * int(e)) + ")"
            if e.is_Integer and int(e) == -1:
                return f"(1.0/{self.parenthesize(base, 100)})"
            return str(super()._print_Pow(expr, rational=rational))

    printer = _Printer({"fully_qualified_modules": True, "standard": "python3"})
    subs, reduced = sympy.cse(list(exprs), symbols=sympy.numbered_symbols("t_"), optimizations="basic")
    lines = [f"{s} = {printer.doprint(e)}" for s, e in subs]
    values = [printer.doprint(e) for e in reduced]
    if any("sympy" in v or "numpy" in v for v in lines + values):
        raise ValueError("the closed form uses a function the kernel printer does not know")
    return lines, values


def _source(form: SymbolicLd, pairs: Sequence[tuple[int, int]]) -> str:
    """The module of the two kernels (``grad_kernel``, ``both_kernel``) of ``form`` and ``pairs``."""
    import sympy

    sym = form.symbols
    k, m = len(form.offsets), form.m
    grads = [sympy.diff(form.expr, sym[p][c]) for p in range(k) for c in range(m)]
    second = [sympy.diff(grads[a * m + i], sym[b][j]) for a, b in pairs for i in range(m) for j in range(m)]
    loads = [f"        {sym[p][c]} = cells[n, {p}, {c}]" for p in range(k) for c in range(m)]
    text = ["import math", "import numba", ""]
    for name, exprs, extra in (("grad", grads, ""), ("both", grads + second, ", blocks")):
        lines, values = _printed(exprs)
        body = loads + [f"        {line}" for line in lines]
        body += [f"        out[n, {q // m}, {q % m}] = {v}" for q, v in enumerate(values[: k * m])]
        for q, v in enumerate(values[k * m :]):
            pair, rest = divmod(q, m * m)
            body.append(f"        blocks[{pair}, n, {rest // m}, {rest % m}] = {v}")
        for suffix, parallel, loop in (("", "True", "numba.prange"), ("_serial", "False", "range")):
            text += [
                f"@numba.njit(parallel={parallel}, cache=True, fastmath=False, error_model='numpy', nogil=True)",
                f"def {name}_kernel{suffix}(cells, out{extra}):",
                f"    for n in {loop}(cells.shape[0]):",
                *body,
                "",
                "",
            ]
    return "\n".join(text)


def _key(form: SymbolicLd, pairs: Sequence[tuple[int, int]]) -> str:
    """The hash of what a kernel computes: the expression (its exact printed form), the cell shape, the pairs."""
    import sympy

    text = f"{_VERSION}|{sympy.srepr(form.expr)}|{len(form.offsets)}|{form.m}|{tuple(pairs)}"
    return hashlib.sha256(text.encode()).hexdigest()[:24]


def _load(path: Path, key: str) -> Any:
    spec = importlib.util.spec_from_file_location(f"latticedft_kernel_{key}", path)
    if spec is None or spec.loader is None:
        raise ImportError(f"cannot load {path}")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # numba's cache finds the kernels' module by name
    spec.loader.exec_module(module)
    return module


def compile_forms(form: SymbolicLd, pairs: Sequence[tuple[int, int]], what: str = "L_d") -> CompiledForms | None:
    """The compiled kernels of ``form`` for ``pairs``, built on first use (then cached on disk and in the
    process); ``None``, with one info line, where they cannot be built."""
    key = _key(form, pairs)
    k, m = len(form.offsets), form.m
    mod = _LOADED.get(key)
    if mod is None:
        if key in _FAILED:
            return None
        t0 = time.perf_counter()
        try:
            mod, how = _build(form, pairs, key)
        except Exception as exc:  # noqa: BLE001 - any failure: the model keeps its other derivatives
            _FAILED.add(key)
            log.info(
                "compiled DEL kernel unavailable for %s (%s: %s): serving uses its usual derivatives",
                what,
                type(exc).__name__,
                exc,
            )
            return None
        seconds = time.perf_counter() - t0
        BUILDS.append((what, seconds, how))
        log.info("compiled DEL kernel for %s %s in %.2f s", what, how, seconds)
        _LOADED[key] = mod
    return CompiledForms(mod, k, m, len(pairs))


def _build(form: SymbolicLd, pairs: Sequence[tuple[int, int]], key: str) -> tuple[Any, str]:
    """Write (once) and load the kernel module of ``key``, and run both kernels once on one cell (numba
    compiles, or loads its cached machine code, on the first call): ``(module, "built" or "cached")``."""
    import numba  # noqa: F401 - fails here, with the reason, where numba is missing

    folder = cache_dir()
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / f"ldft_{key}.py"
    how = "cached"
    if not path.exists():
        how = "built"
        tmp = path.with_suffix(f".{os.getpid()}.tmp")
        tmp.write_text(_source(form, pairs))
        os.replace(tmp, path)
    mod = _load(path, key)
    k, m = len(form.offsets), form.m
    cell = np.zeros((1, k, m))
    mod.grad_kernel_serial(cell, np.empty_like(cell))  # the parallel kernels compile on first use
    mod.both_kernel_serial(cell, np.empty_like(cell), np.empty((len(pairs), 1, m, m)))
    return mod, how
