"""Compiled kernels of a dense polynomial ``L_d``'s derivatives in its scaled variables, one generated per pattern
(``latticedft._serve._folded``, ``FoldedSlices._zpass``): the polynomial's tails, chains and their degrees are
written out, its coefficients stay data. Modules are written into and loaded from the kernel cache of
``latticedft._kernel``, as the folded kernels of ``latticedft._kernel_folded``; a module that cannot be built
leaves the polynomial on those, with one info line.
"""

from __future__ import annotations

import hashlib
from collections.abc import Callable
from typing import Any

import numpy as np

from ._kernel import _VERSION, cached_module, write_module

__all__ = ["ZCHAIN_GROUP", "zchain_kernel", "zchain_source"]


#: The derivatives in the scaled variables (:func:`zchain_kernel`): per chunk of cells the stencil gathered and
#: its variables ``z = x.flat @ w - shift`` (as ``chunk_variables``), then each derivative ``d L / d z...`` that
#: some column reads as a sum over its tails (monomials of the variables but the head) of the tail times a
#: Horner chain in the head, written out for the polynomial's pattern (its tails, chains and their degrees; the
#: coefficients stay data), and the columns from those derivatives by the chain rule (``cmat``, data): the
#: first ``split`` into ``out`` ``(cells, split)``, the others into ``rest`` ``(columns - split, cells)``, one
#: contiguous row per column (a Hessian block's entries where ``m = 1``).
_ZCHAIN = """
@numba.njit(cache=True, error_model='numpy', nogil=True, fastmath={'contract'})
def zchain_cells(lo, hi, site_of, upper, w, shift, coef, cmat, out, rest):
    ncell = site_of.shape[1]
    m = lo.shape[1]
    ch = _CHUNK
    x = np.empty((site_of.shape[0] * m, ch))
    z = np.empty((w.shape[1], ch))
    zc = np.empty((NCOMB, ch))
    for start in range(0, ncell, ch):
        n = min(ch, ncell - start)
        for a in range(site_of.shape[0]):
            src = hi if upper[a] else lo
            for j in range(n):
                s = site_of[a, start + j]
                for c in range(m):
                    x[a * m + c, j] = src[s, c]
        for v in range(w.shape[1]):
            for j in range(n):
                z[v, j] = 0.0
            for r in range(w.shape[0]):
                wr = w[r, v]
                if wr != 0.0:
                    for j in range(n):
                        z[v, j] += x[r, j] * wr
            for j in range(n):
                z[v, j] -= shift[v]
{groups}
{outputs}
"""

#: Chains per pass over a chunk's cells in :func:`zchain_kernel` (whole derivatives at a time, so that each
#: derivative's sum is written the same way whatever else a kernel evaluates). 4 to 64 timed the same on the
#: (2, 12) class in 2+1D and 3+1D (docs/performance.md).
ZCHAIN_GROUP = 8


def _tail_expr(texp: tuple[int, ...]) -> str:
    """A tail's value in the cell loop: the product of its variables (``z1 * z1 * z2``), ``""`` for 1."""
    return " * ".join(f"z{v}" for v, e in enumerate(texp) for _ in range(e))


def zchain_source(
    head: int,
    tails: tuple[tuple[int, ...], ...],
    chains: tuple[tuple[int, int, int], ...],
    outputs: tuple[tuple[int, ...], ...],
    ncomb: int,
    split: int,
) -> str:
    """The ``zchain_cells`` kernel of one pattern: ``chains`` ``(tail, derivative, degree)`` in the order of the
    rows of ``coef`` (each derivative's chains together, in the order of its tails), ``outputs[c]`` the
    derivatives column ``c`` reads through ``cmat``, the columns from ``split`` on written into ``rest``."""
    groups: list[list[int]] = []  # chain indices per pass, whole derivatives
    q_chains: dict[int, list[int]] = {}
    for i, (_, q, _) in enumerate(chains):
        q_chains.setdefault(q, []).append(i)
    for q in sorted(q_chains):
        if not groups or len(groups[-1]) >= ZCHAIN_GROUP:
            groups.append([])
        groups[-1].extend(q_chains[q])
    lines: list[str] = []
    for g in groups:
        for i in g:
            deg = chains[i][2]
            names = ", ".join(f"k{i}_{e}" for e in range(deg + 1))
            lines.append(f"{names} = " + ", ".join(f"coef[{i}, {e}]" for e in range(deg + 1)))
        used = sorted({v for i in g for v, e in enumerate(tails[chains[i][0]]) if e})
        lines += ["for j in range(n):", f"    y = z[{head}, j]"] + [f"    z{v} = z[{v}, j]" for v in used]
        for q in sorted({chains[i][1] for i in g}):
            terms = []
            for i in q_chains[q]:
                t, _, deg = chains[i]
                chain = f"k{i}_{deg}"
                for e in range(deg - 1, -1, -1):
                    chain = f"({chain} * y + k{i}_{e})"
                tail = _tail_expr(tails[t])
                terms.append(f"{tail} * {chain}" if tail else chain)
            lines.append(f"    zc[{q}, j] = " + " + ".join(terms))
    out = []
    for c, qs in enumerate(outputs):
        out += [f"m{c}_{q} = cmat[{q}, {c}]" for q in qs]
    out.append("for j in range(n):")
    for c, qs in enumerate(outputs):
        place = f"out[start + j, {c}]" if c < split else f"rest[{c - split}, start + j]"
        out.append(f"    {place} = " + (" + ".join(f"m{c}_{q} * zc[{q}, j]" for q in qs) or "0.0"))
    body = "\n".join("        " + x for x in lines)
    tail = "\n".join("        " + x for x in out)
    return _ZCHAIN.replace("{groups}", body).replace("{outputs}", tail).replace("NCOMB", str(max(ncomb, 1)))


def zchain_kernel(
    head: int,
    tails: tuple[tuple[int, ...], ...],
    chains: tuple[tuple[int, int, int], ...],
    outputs: tuple[tuple[int, ...], ...],
    ncomb: int,
    split: int,
) -> Callable[..., None] | None:
    """``zchain_cells`` for one pattern (:func:`zchain_source`): ``kernel(lo, hi, site_of, upper, w, shift, coef,
    cmat, out, rest)``; built once per pattern and cached as the other kernels; ``None`` where numba cannot build
    it."""
    source = "\nimport numba\nimport numpy as np\n\n_CHUNK = 256\n\n" + zchain_source(
        head, tails, chains, outputs, ncomb, split
    )
    key = hashlib.sha256(f"{_VERSION}|{source}".encode()).hexdigest()[:24]
    what = f"folded polynomial (scaled variables, {len(chains)} chains, {len(outputs)} columns)"

    def build() -> tuple[Any, str]:
        mod, how = write_module(key, source)
        nvar = len(tails[0]) if tails else head + 1
        deg = max((c[2] for c in chains), default=0)
        one, idx = np.zeros((1, 1)), np.zeros((1, 1), dtype=np.int64)
        coef, cmat = np.zeros((max(len(chains), 1), deg + 1)), np.zeros((max(ncomb, 1), max(len(outputs), 1)))
        w = np.zeros((1, max(nvar, head + 1)))
        out, rest = np.empty((1, split)), np.empty((len(outputs) - split, 1))
        mod.zchain_cells(one, one, idx, np.zeros(1, dtype=np.int64), w, np.zeros(w.shape[1]), coef, cmat, out, rest)
        return mod, how

    mod = cached_module(
        key,
        build,
        what,
        f"compiled {what} kernel",
        f"compiled {what} kernel unavailable",
        "serving uses its Horner forms",
    )
    return None if mod is None else mod.zchain_cells
