"""Compiled residual and gradient passes of an ``L_d`` quadratic but for one-site terms, generated per stencil.

``latticedft._serve._potential`` serves a kinetic-potential MLP: a cell's gradient is its values times a constant
kinetic Hessian plus a one-site term per point. The folded module's ``quadratic_residual`` and ``quadratic_grad``
loop over every stencil point and every Hessian entry at run time; the module generated here has those loops
written out for one stencil (points, components, which points lie on the upper slice) and the Hessian's nonzero
pattern, the entries read once into scalars. The additions are the same, in the same order (a zero entry's
product, which adds nothing, left out), so the results equal the folded module's. One module per pattern is
built once per machine and cached as the other kernels.
"""

from __future__ import annotations

import hashlib
from collections.abc import Sequence
from typing import Any

import numpy as np

from ._kernel import _VERSION, cached_module, write_module

__all__ = ["quadratic_kernels"]

_HEAD = """
import numba
import numpy as np


@numba.njit(cache=True, error_model='numpy', nogil=True)
def quadratic_grad(lo, hi, site_of, hess, vlo, vhi, out):
{entries}
    for n in range(site_of.shape[1]):
{gather}
{grad}


@numba.njit(cache=True, error_model='numpy', nogil=True)
def quadratic_residual(gprev, lo, hi, site_of, hess, vlo, rows, vol, el, r):
{entries}
    el[:] = 0.0
{upper}
    for n in range(site_of.shape[1]):
{gather}
{lower}
    for q in range(rows.shape[0]):
        for c in range({m}):
            r[q * {m} + c] = vol * el[rows[q], c]
"""


def _source(pattern: np.ndarray, upper: Sequence[int], m: int) -> str:
    """The module's source for the nonzero ``pattern`` ``(K m, K m)`` of the Hessian, the points on the upper
    slice (``upper[a]``) and ``m`` components."""
    k = len(upper)
    km = k * m
    cols = {q: [b for b in range(km) if pattern[b, q]] for q in range(km)}
    used = sorted({(b, q) for q, bs in cols.items() for b in bs})
    entries = "\n".join(f"    h{b}_{q} = hess[{b}, {q}]" for b, q in used) or "    pass"
    gather = []
    for a in range(k):
        gather.append(f"        s{a} = site_of[{a}, n]")
        src = "hi" if upper[a] else "lo"
        gather += [f"        x{a * m + c} = {src}[s{a}, {c}]" for c in range(m)]

    def column(q: int, v: str) -> str:
        return " + ".join([f"{v}[s{q // m}, {q % m}]", *(f"x{b} * h{b}_{q}" for b in cols[q])])

    grad = []
    for q in range(km):
        grad.append(f"        out[n, {q}] = " + column(q, "vhi" if upper[q // m] else "vlo"))
    up = []
    for a in range(k):
        if upper[a]:
            up += ["    for n in range(site_of.shape[1]):", f"        s = site_of[{a}, n]"]
            up += [f"        el[s, {c}] += gprev[n, {a * m + c}]" for c in range(m)]
    lower = []
    for q in range(km):
        if not upper[q // m]:
            lower.append(f"        el[s{q // m}, {q % m}] += " + column(q, "vlo"))
    text = _HEAD.replace("{entries}", entries).replace("{gather}", "\n".join(gather))
    text = text.replace("{grad}", "\n".join(grad)).replace("{upper}", "\n".join(up) or "    pass")
    text = text.replace("{lower}", "\n".join(lower) or "        pass").replace("{m}", str(m))
    return text


def quadratic_kernels(hess: np.ndarray, upper: Sequence[int] | np.ndarray, m: int) -> Any:
    """The module of ``quadratic_grad(lo, hi, site_of, hess, vlo, vhi, out)`` and ``quadratic_residual(gprev, lo,
    hi, site_of, hess, vlo, rows, vol, el, r)`` (the folded module's, less ``upper``) written out for the stencil
    (``upper``, ``m``) and the nonzero pattern of ``hess``; built once per machine and pattern, cached; ``None``,
    with one info line, where numba cannot build it."""
    pattern = np.asarray(hess) != 0.0
    source = _source(pattern, [int(u) for u in upper], m)
    key = hashlib.sha256(f"{_VERSION}|{source}".encode()).hexdigest()[:24]
    k = len(upper)
    return cached_module(
        key,
        lambda: _build(key, source, k, m),
        f"quadratic passes ({k} points, {m} components)",
        "compiled quadratic passes",
        "compiled quadratic passes unavailable",
        "serving uses the folded module's",
    )


def _build(key: str, source: str, k: int, m: int) -> tuple[Any, str]:
    """Write (once) and load the module, and run its kernels once on one cell."""
    mod, how = write_module(key, source)
    one, idx, hess = np.zeros((1, m)), np.zeros((k, 1), dtype=np.int64), np.zeros((k * m, k * m))
    mod.quadratic_grad(one, one, idx, hess, one, one, np.empty((1, k * m)))
    rows = np.zeros(1, dtype=np.int64)
    mod.quadratic_residual(np.zeros((1, k * m)), one, one, idx, hess, one, rows, 1.0, np.empty((1, m)), np.empty(m))
    return mod, how
