"""Compiled per-cell derivatives of a closed-form ``L_d``: one fused numba kernel generated from its sympy form.

Serving needs, on every cell of a slice, the gradient ``dL/dx`` and the mixed Hessian blocks
``d^2 L / dx_a dx_b`` of the slice's stencil pairs. For a model known in closed form
(:meth:`AbstractLagrangian.symbolic`) these are differentiated once by sympy, their common subexpressions
shared (``sympy.cse``), and printed as one loop over the cells, parallel (``numba.prange``): each cell's
values are read inside the loop and every intermediate is a scalar, so there is no Python per cell and no
array per term (the printers: :mod:`latticedft._kernel_source`). Two entry points are generated, the
gradient alone and the gradient with the blocks, each parallel and serial. For a scalar ``L_d`` whose
slice Jacobian is block diagonal by its form, the module also holds ``slice_newton``: Newton's method on
every unknown site of a slice in one loop, the stencil read inside it at fixed offsets from the site where
the lattice allows, else through the cell maps (``latticedft._serve._fused`` drives it), ``predict``, its
predictor, and ``slice_steps``, a run of slices in one call. For a scalar 0+1D ``L_d`` on the two-point
stencil it holds ``trajectory``: every slice of one trajectory (predictor, Newton with backtracking, the
conditioning, convergence and box tests) in one compiled loop (``latticedft._serve._fast1d``).

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
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ._kernel_source import kernel_source
from ._symbolic import SymbolicLd

__all__ = ["BUILDS", "CompiledForms", "build_lock", "cache_dir", "cached_module", "compile_forms", "write_module"]

log = logging.getLogger("latticedft")

#: Every kernel this process built or loaded: ``(what, seconds, "built" or "cached")``.
BUILDS: list[tuple[str, float, str]] = []

#: Kernels already loaded in this process, by hash.
_LOADED: dict[str, Any] = {}

#: Forms whose build failed in this process, by hash (the failure is reported once).
_FAILED: set[str] = set()

#: How long a process waits for another's build of the same kernel before it builds on its own.
BUILD_WAIT_S = 120.0

#: Bumped whenever the generated code changes, so that stale cached kernels are not reused.
_VERSION = 18


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

    @property
    def block_diagonal(self) -> bool:
        """Whether the kernels hold ``slice_newton`` (a scalar ``L_d`` with a block-diagonal slice Jacobian)."""
        return bool(self.module.BLOCK_DIAGONAL)

    @property
    def quadratic(self) -> bool:
        """Whether the ``L_d`` is a polynomial of degree at most two (its DEL affine), by its form."""
        return bool(self.module.QUADRATIC)

    @property
    def has_trajectory(self) -> bool:
        """Whether the kernels hold ``trajectory`` (a scalar 0+1D ``L_d`` on the two-point stencil)."""
        return bool(self.module.HAS_TRAJECTORY)

    def slice_step(self, sites: int) -> Callable[..., tuple[int, int, float]]:
        """The kernel that solves a slice of ``sites`` unknown sites (predictor, scale, slice Newton, tally;
        parallel or serial as the gradient's)."""
        return _kernel(self.module, "slice_step", sites, suffix="")

    def slice_steps(self, sites: int) -> Callable[..., int]:
        """The kernel that solves a run of slices of ``sites`` unknown sites each (``slice_step`` slice after
        slice; parallel or serial as the gradient's)."""
        return _kernel(self.module, "slice_steps", sites, suffix="")


#: Cells per thread below which the serial kernel runs (starting threads costs more than it saves).
PARALLEL_MIN_CELLS = 65536


def _kernel(module: Any, name: str, cells: int, suffix: str = "_kernel") -> Callable[..., Any]:
    """The parallel kernel ``name`` with as many threads as torch has (which :func:`latticedft.limit_threads`
    bounds with the BLAS pools), or the serial one for one thread or few cells."""
    import numba
    import torch

    threads = min(
        torch.get_num_threads(), int(getattr(numba.config, "NUMBA_NUM_THREADS", 1)), cells // PARALLEL_MIN_CELLS
    )
    if threads <= 1:
        return getattr(module, f"{name}{suffix}_serial")  # type: ignore[no-any-return]
    numba.set_num_threads(threads)
    return getattr(module, f"{name}{suffix}")  # type: ignore[no-any-return]


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
    mod = cached_module(
        key,
        lambda: _build(form, pairs, key),
        what,
        f"compiled DEL kernel for {what}",
        f"compiled DEL kernel unavailable for {what}",
        "serving uses its usual derivatives",
    )
    if mod is None:
        return None
    return CompiledForms(mod, k, m, len(pairs))


def cached_module(
    key: str, build: Callable[[], tuple[Any, str]], what: str, built: str, unavailable: str, fallback: str
) -> Any | None:
    """The kernel module ``key``: the one this process loaded already, else ``build()``'s ``(module, "built" or
    "cached")``, timed into :data:`BUILDS` (as ``what``) and said in one info line (``built``, how, the time).
    A build that fails is said once (``unavailable``, the error, ``fallback``) and not tried again in this
    process: ``None``."""
    mod = _LOADED.get(key)
    if mod is not None or key in _FAILED:
        return mod
    t0 = time.perf_counter()
    try:
        with build_lock(key):
            mod, how = build()
    except Exception as exc:  # noqa: BLE001 - any failure: the caller keeps its other path
        _FAILED.add(key)
        log.info("%s (%s: %s): %s", unavailable, type(exc).__name__, exc, fallback)
        return None
    seconds = time.perf_counter() - t0
    BUILDS.append((what, seconds, how))
    log.info("%s %s in %.2f s", built, how, seconds)
    _LOADED[key] = mod
    return mod


@contextmanager
def build_lock(key: str, wait: float | None = None) -> Iterator[None]:
    """Hold the cache's build lock of kernel ``key`` (an exclusive ``flock`` on ``ldft_{key}.lock`` in
    :func:`cache_dir`) while the block runs, so that processes needing the same kernel on an empty cache (the
    ranks of ``--workers N``, the test processes) compile it once: the others wait, then load what it cached.
    After ``wait`` seconds (:data:`BUILD_WAIT_S`) a waiting process builds on its own (a build that hangs does
    not stop the others); where the folder or ``flock`` is not available the block runs unlocked. The lock
    ends with its holder, killed or not."""
    try:
        import fcntl
    except ImportError:  # pragma: no cover - not POSIX: no lock
        yield
        return
    try:
        folder = cache_dir()
        folder.mkdir(parents=True, exist_ok=True)
        fd = os.open(folder / f"ldft_{key}.lock", os.O_RDWR | os.O_CREAT, 0o644)
    except OSError:  # a read-only or missing cache: the build says why, unlocked
        yield
        return
    try:
        deadline = time.monotonic() + (BUILD_WAIT_S if wait is None else wait)
        while True:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                break
            except BlockingIOError:
                if time.monotonic() >= deadline:
                    log.info("kernel %s: another process's build holds its lock; building here too", key)
                    break
                time.sleep(0.05)
            except OSError:  # a file system without flock: unlocked
                break
        yield
    finally:
        os.close(fd)  # releases the lock


def write_module(key: str, source: str | Callable[[], str]) -> tuple[Any, str]:
    """The kernel module ``key`` of ``source`` (or of what ``source()`` returns, called only where the module
    is not cached yet: generating it means sympy's differentiation and ``cse``), written once into the cache
    (atomically) and loaded: ``(module, "built")`` when it was written now, else ``(module, "cached")``."""
    import numba  # noqa: F401 - fails here, with the reason, where numba is missing

    folder = cache_dir()
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / f"ldft_{key}.py"
    how = "cached"
    if not path.exists():
        how = "built"
        tmp = path.with_suffix(f".{os.getpid()}.tmp")
        tmp.write_text(source if isinstance(source, str) else source())
        os.replace(tmp, path)
    return _load(path, key), how


def _build(form: SymbolicLd, pairs: Sequence[tuple[int, int]], key: str) -> tuple[Any, str]:
    """Write (once) and load the kernel module of ``key``, and run both kernels once on one cell (numba
    compiles, or loads its cached machine code, on the first call): ``(module, "built" or "cached")``."""
    mod, how = write_module(key, lambda: kernel_source(form, pairs))  # the key holds the form: no sympy when cached
    k, m = len(form.offsets), form.m
    cell = np.zeros((1, k, m))
    mod.grad_kernel_serial(cell, np.empty_like(cell))  # the parallel kernels compile on first use
    mod.both_kernel_serial(cell, np.empty_like(cell), np.empty((len(pairs), 1, m, m)))
    if mod.BLOCK_DIAGONAL:
        one, none = np.zeros(1), np.zeros(0, dtype=np.int64)
        idx = np.zeros((k, 1), dtype=np.int64)
        flags = np.zeros(1, dtype=np.bool_)
        args = (idx, idx, flags, np.zeros((k, k), dtype=np.int64), none, flags, 1.0, 1.0, 1.0, 1.0, 1)
        mod.slice_step_serial(one, one, one, one, *args, np.zeros(0), none.copy())  # the parallel one: on first use
        values, tallies = np.zeros((3, 1)), (np.zeros(3, dtype=np.int64), np.zeros(3))
        mod.slice_steps_serial(values, 1, 1, np.zeros(0), *args, np.zeros(0), none.copy(), *tallies)
        mod.site_diagonal(one, one, idx, np.zeros(1))
        mod.cell_maps(idx, idx.copy())
        mod.plain_sites(idx, idx, np.zeros((k, k), dtype=np.int64), np.zeros(1, dtype=np.bool_))
    if mod.HAS_TRAJECTORY:
        mod.trajectory(
            np.zeros(3), 1, 1, 1.0, 1.0, 1, -1.0, 1e-10, np.zeros(3), np.zeros(2, dtype=np.int64), np.zeros(6)
        )
    return mod, how
