"""The generated source of the compiled per-cell derivatives of a closed-form ``L_d``
(:mod:`latticedft._kernel` writes, caches and loads it).

From a :class:`~latticedft._symbolic.SymbolicLd` and the slice's stencil pairs: the gradient and the mixed
Hessian blocks differentiated by sympy, their common subexpressions shared, printed as one loop over the cells
(``grad_kernel``, ``both_kernel``, parallel and serial); for a scalar ``L_d`` with a block-diagonal slice
Jacobian, the slice Newton (``slice_newton``, its predictor, scale and tally around it: ``slice_step``, and
``slice_steps`` over a run of slices); for a scalar 0+1D ``L_d`` on the two-point stencil, ``trajectory``.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Sequence
from typing import Any

from ._symbolic import SymbolicLd

__all__ = ["kernel_source"]


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


def kernel_source(form: SymbolicLd, pairs: Sequence[tuple[int, int]]) -> str:
    """The module of the two kernels (``grad_kernel``, ``both_kernel``) of ``form`` and ``pairs``."""
    import sympy

    sym = form.symbols
    k, m = len(form.offsets), form.m
    grads = [sympy.diff(form.expr, sym[p][c]) for p in range(k) for c in range(m)]
    second = [sympy.diff(grads[a * m + i], sym[b][j]) for a, b in pairs for i in range(m) for j in range(m)]
    loads = [f"        {sym[p][c]} = cells[n, {p}, {c}]" for p in range(k) for c in range(m)]
    text = ["import math", "import numba", "import numpy as np", ""]
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
    text += [f"QUADRATIC = {_quadratic(form)}", ""]
    return "\n".join(text + _slice_newton_source(form, grads, pairs, second) + _trajectory_source(form, grads))


def _quadratic(form: SymbolicLd) -> bool:
    """Whether ``form`` is a polynomial of degree at most two in the cell's values (its DEL is affine)."""
    import sympy

    try:
        return bool(sympy.Poly(form.expr, *form.flat_symbols()).total_degree() <= 2)
    except sympy.PolynomialError:
        return False


def _diagonal_pairs(form: SymbolicLd, pairs: Sequence[tuple[int, int]], second: Sequence[Any]) -> list[tuple[int, int]]:
    """The pairs whose two points sit on the same site (the diagonal blocks of a slice Jacobian), or ``[]``
    unless every other pair's block vanishes identically (then each unknown's equation involves that unknown
    alone: the slice Jacobian is block diagonal whatever the field)."""
    mm = form.m * form.m
    diag = []
    for q, (a, b) in enumerate(pairs):
        if form.offsets[a][1:] == form.offsets[b][1:]:
            diag.append((a, b))
        elif any(e != 0 for e in second[q * mm : (q + 1) * mm]):
            return []
    return diag


def _slice_newton_source(
    form: SymbolicLd, grads: Sequence[Any], pairs: Sequence[tuple[int, int]], second: Sequence[Any]
) -> list[str]:
    """``slice_newton`` (and ``slice_newton_serial``): Newton's method on every unknown site of a slice at
    once, for a scalar ``L_d`` whose slice Jacobian is block diagonal (:func:`_diagonal_pairs`); nothing
    (``BLOCK_DIAGONAL = False``) otherwise.

    Per equation site ``y``: the residual is the cells' gradients at the stencil points that sit on ``y``
    (the cells anchored on slice ``i - 1`` once, those anchored on ``i`` at every iteration), each cell's
    values read from the slices through ``site_of`` and ``cell_at`` inside the loop; the Jacobian is the sum of
    the diagonal pairs' second derivatives. It stops where the residual is below ``tol``, one evaluation
    after a step below ``step_tol``; ``its[q]`` is the evaluations made, ``-1`` for a Jacobian below ``smin``
    in size, ``-2`` for no convergence in ``maxit`` evaluations (or a residual that is not a number)."""
    k = len(form.offsets)
    diag = _diagonal_pairs(form, pairs, second) if form.m == 1 else []
    if not diag:
        return ["BLOCK_DIAGONAL = False", ""]
    args = ", ".join(str(s) for s in form.flat_symbols())
    text = ["BLOCK_DIAGONAL = True", ""]
    nxt = [a for a in range(k) if form.offsets[a][0] == 1]
    now = [a for a in range(k) if form.offsets[a][0] == 0]
    unknowns = {s for a in nxt for s in form.symbols[a]}
    functions = [(f"g{a}", grads[a]) for a in range(k)]
    moving = []  # the points whose gradient the unknown moves: split into the part it moves and the rest
    for a in now:
        fixed, varying = _split(grads[a], unknowns)
        if varying != 0:
            moving.append(a)
            functions += [(f"g{a}_fixed", fixed), (f"g{a}_varying", varying)]
    hessians = {(a, b): second[pairs.index((a, b))] for a, b in diag if a in moving}
    functions += [(f"h{a}_{b}", e) for (a, b), e in hessians.items()]
    for name, expr in functions:
        lines, (value,) = _printed([expr])
        text += ["@numba.njit(cache=True, error_model='numpy', nogil=True, inline='always')", f"def {name}({args}):"]
        text += [f"    {line}" for line in lines] + [f"    return {value}", "", ""]
    constant = {pair for pair, e in hessians.items() if not e.free_symbols & unknowns}
    affine = all((a, b) in constant for a in moving for aa, b in diag if aa == a)
    fixed = _fixed_body(form, nxt, now, moving)
    plain = _newton_body(form, list(hessians), nxt, now, moving, constant, True, affine)
    mapped = _newton_body(form, list(hessians), nxt, now, moving, constant, False, affine)
    # every site an unknown (a periodic lattice): rows is 0, 1, ... and the loop reads no index per site
    site = ["        y = q if dense else rows[q]", "        if plain[y]:"]
    first = [*site, *["    " + x for x in fixed]]
    body = [*site, *["    " + x for x in plain], "        else:"]
    body += ["    " + x for x in mapped]
    # the fixed offsets read once into scalars (the loop writes nxt: loads from delta would not be hoisted)
    hoisted = [f"    d{a}_{p} = delta[{a}, {p}]" for a in range(k) for p in range(k)]
    text += [f"AFFINE = {affine}", ""]
    for suffix, parallel, loop in (("", "True", "numba.prange"), ("_serial", "False", "range")):
        text += [
            f"@numba.njit(parallel={parallel}, cache=True, error_model='numpy', nogil=True)",
            f"def slice_newton{suffix}(prev, cur, nxt, site_of, cell_at, plain, delta, rows, vol, tol, step_tol,"
            " smin, maxit, res, its):",
            *hoisted,
            "    dense = rows.shape[0] == plain.shape[0]",
            f"    for q in {loop}(rows.shape[0]):",
            *first,
            f"    for q in {loop}(rows.shape[0]):",
            *body,
            "",
            "",
        ]
    return text + _diagonal_source(form, list(hessians)) + _slice_step_source()


def _diagonal_source(form: SymbolicLd, diag: list[tuple[int, int]]) -> list[str]:
    """``site_diagonal(lo, hi, site_of, diag)``: the diagonal of a slice's Jacobian at the values of its two
    slices (``lo``, ``hi``), added into ``diag`` per site pair after pair, cell after cell (the order of
    ``_fused.FusedSlices.scales``); returns the largest block in size, ``-1.0`` at a block that is not finite.
    The pairs of ``diag`` are those whose block the unknown can move; the others' blocks vanish."""
    k = len(form.offsets)
    text = ["@numba.njit(cache=True, error_model='numpy', nogil=True)", "def site_diagonal(lo, hi, site_of, diag):"]
    text += ["    dmax = 0.0"]
    for a, b in diag:
        args = ", ".join(f"{'hi' if form.offsets[p][0] else 'lo'}[_u(site_of[{p}, n])]" for p in range(k))
        text += [
            "    for n in range(site_of.shape[1]):",
            f"        v = h{a}_{b}({args})",
            "        if not math.isfinite(v):",
            "            return -1.0",
            "        dmax = abs(v) if abs(v) > dmax else dmax",
            f"        diag[_u(site_of[{a}, n])] += v",
        ]
    return text + ["    return dmax", "", ""]


def _split(expr: Any, unknowns: set[Any]) -> tuple[Any, Any]:
    """``(fixed, varying)``: the terms of the sum ``expr`` free of the ``unknowns``, and the others."""
    import sympy

    terms = expr.args if expr.is_Add else (expr,)
    fixed = [t for t in terms if not t.free_symbols & unknowns]
    return sympy.Add(*fixed), sympy.Add(*[t for t in terms if t.free_symbols & unknowns])


def _newton_body(
    form: SymbolicLd,
    diag: list[tuple[int, int]],
    nxt: list[int],
    now: list[int],
    moving: list[int],
    constant: set[tuple[int, int]],
    plain: bool,
    affine: bool,
) -> list[str]:
    """The loop body of ``slice_newton`` for site ``y``: once, the part of its residual (and of its
    Jacobian: the ``constant`` diagonal pairs) the unknown does not move (the cells anchored on the slice
    before; the gradients of the cells anchored on this slice at the points not ``moving``, and the fixed
    terms of those ``moving``; where ``plain``, summed by the pass before into ``res[q]`` and read back); then
    Newton's iterations on the rest.

    ``plain``: the stencil is read at fixed offsets from ``y`` (``delta[a, p]``: from the site of point ``a``
    to that of point ``p`` of one cell), for the sites where that is what the cell maps say (no wrap, every
    cell present); otherwise through the maps. ``affine`` (the residual is affine in the unknown: every
    Jacobian term constant): after the first step the residual is that of the linear update, not evaluated
    afresh (the evaluation Newton would make, counted as such)."""
    term = functools.partial(_term, form, plain)
    if plain:  # the fixed part, summed by the pass before (:func:`_fixed_body`), read back from ``res``
        body = ["fixed = res[q]", "jac0 = 0.0"]
    else:
        body = ["fixed = 0.0", "jac0 = 0.0", *_fixed_terms(form, nxt, now, moving, term)]
    body += [line for a, b in diag if (a, b) in constant for line in term(a, f"jac0 += h{a}_{b}", False)]
    body += ["it = 0", "small = False", "r = 0.0", "while True:", "    r = fixed", "    jac = jac0"]
    for a in moving:
        body += ["    " + line for line in term(a, f"r += g{a}_varying", False)]
        pairs = [(a, b) for aa, b in diag if aa == a and (a, b) not in constant]
        body += ["    " + line for a_, b in pairs for line in term(a_, f"jac += h{a_}_{b}", False)]
    body += [
        "    r *= vol",
        "    jac *= vol",
        "    it += 1",
        "    if not (abs(r) > tol) or small:",
        "        break",
        "    if it >= maxit or r != r:",
        "        it = -2",
        "        break",
        "    if not (abs(jac) > smin):",
        "        it = -1",
        "        break",
        "    step = -r / jac",
        "    nxt[_u(y)] += step",
        "    small = abs(step) <= step_tol",
    ]
    if affine:
        body += ["    r += jac * step", "    it += 1", "    break"]
    body += ["res[q] = abs(r) if r == r else math.inf", "its[q] = it"]
    return ["        " + line for line in body]


def _term(form: SymbolicLd, plain: bool, a: int, fn: str, anchored_before: bool) -> list[str]:
    """The lines that add ``fn`` (``"fixed += g0"``, ...) of the cell whose point ``a`` sits on site ``y``: its
    stencil read at fixed offsets from ``y`` where ``plain``, else through the cell maps (no cell: nothing)."""
    k = len(form.offsets)
    low, high = ("prev", "cur") if anchored_before else ("cur", "nxt")
    if plain:  # unsigned indices: no test for a negative index per load
        args = ", ".join(f"{high if form.offsets[p][0] else low}[_u(y + d{a}_{p})]" for p in range(k))
        return [f"{fn}({args})"]
    args = ", ".join(f"{high if form.offsets[p][0] else low}[_u(site_of[{p}, c])]" for p in range(k))
    return [f"c = cell_at[{a}, y]", "if c >= 0:", f"    {fn}({args})"]


def _fixed_terms(
    form: SymbolicLd, nxt: list[int], now: list[int], moving: list[int], term: Callable[[int, str, bool], list[str]]
) -> list[str]:
    """The lines that sum the part of site ``y``'s residual the unknown does not move into ``fixed``: the cells
    anchored on the slice before, then those anchored on this slice (their fixed terms where ``moving``)."""
    body = []
    for a in nxt:
        body += term(a, f"fixed += g{a}", True)
    for a in now:
        body += term(a, f"fixed += g{a}_fixed" if a in moving else f"fixed += g{a}", False)
    return body


def _fixed_body(form: SymbolicLd, nxt: list[int], now: list[int], moving: list[int]) -> list[str]:
    """The loop body of ``slice_newton``'s first pass for a site read at fixed offsets: the fixed part of its
    residual (:func:`_fixed_terms`, the same sums in the same order) stored in ``res[q]``, which the Newton
    pass reads back and overwrites with the residual. A pass of its own: the Newton loop then calls no
    function (the sine of sine-Gordon), so its values are not spilled around a call, and the loads of the
    pass run ahead of the calls' latency."""
    term = functools.partial(_term, form, True)
    body = ["fixed = 0.0", *_fixed_terms(form, nxt, now, moving, term), "res[q] = fixed"]
    return ["        " + line for line in body]


#: Around ``slice_newton``: its predictor and scale, and the tally of its sites, so that one call solves a
#: slice (``slice_step``). The slices are 1D arrays over the sites (a scalar field).
_SLICE_STEP = """
@numba.njit(cache=True, error_model='numpy', nogil=True, inline='always')
def _u(i):
    return numba.uint64(i)


@numba.njit(cache=True, error_model='numpy', nogil=True)
def predict_exact(prev, cur, nxt, older, rows):
    top = 1e-300
    for s in range(prev.shape[0]):
        top = max(top, abs(prev[s]), abs(cur[s]))
    if older.shape[0]:
        for q in range(rows.shape[0]):
            y = rows[q]
            v = (2.0 * cur[y] - prev[y]) + (cur[y] - 2.0 * prev[y] + older[y])
            nxt[y] = v
            top = max(top, abs(v))
        return top
    for q in range(rows.shape[0]):
        y = rows[q]
        v = 2.0 * cur[y] - prev[y]
        nxt[y] = v
        top = max(top, abs(v))
    return top


@numba.njit(cache=True, error_model='numpy', nogil=True)
def predict(prev, cur, nxt, older, rows, interior):
    t0, t1, t2 = 1e-300, 1e-300, 1e-300
    bad = False
    before = older.shape[0] > 0
    for s in range(prev.shape[0]):
        p = prev[s]
        c = cur[s]
        x0 = abs(p)
        x1 = abs(c)
        t0 = x0 if x0 > t0 else t0
        t1 = x1 if x1 > t1 else t1
        bad = bad | (x0 != x0) | (x1 != x1)
        if interior[s]:
            if before:
                v = (2.0 * c - p) + (c - 2.0 * p + older[s])
            else:
                v = 2.0 * c - p
            nxt[s] = v
            x2 = abs(v)
            t2 = x2 if x2 > t2 else t2
            bad = bad | (x2 != x2)
    if bad:  # the order of the maxima matters only where a value is not a number
        return predict_exact(prev, cur, nxt, older, rows)
    t0 = t1 if t1 > t0 else t0
    return t2 if t2 > t0 else t0


@numba.njit(cache=True, error_model='numpy', nogil=True)
def cell_maps(site_of, cell_at):
    for a in range(site_of.shape[0]):
        for c in range(site_of.shape[1]):
            y = site_of[a, c]
            if cell_at[a, y] >= 0:
                return False
            cell_at[a, y] = c
    return True


@numba.njit(cache=True, error_model='numpy', nogil=True)
def plain_sites(site_of, cell_at, delta, plain):
    unwrapped = np.ones(site_of.shape[1], dtype=np.bool_)
    for c in range(site_of.shape[1]):
        for p in range(1, site_of.shape[0]):
            if site_of[p, c] - site_of[0, c] != delta[0, p]:
                unwrapped[c] = False
    for y in range(cell_at.shape[1]):
        ok = True
        for a in range(cell_at.shape[0]):
            c = cell_at[a, y]
            if c < 0 or not unwrapped[c]:
                ok = False
        plain[y] = ok


@numba.njit(cache=True, error_model='numpy', nogil=True)
def tally(res, its):
    lo, hi = 1 << 62, -(1 << 62)
    for q in range(its.shape[0]):
        lo = min(lo, its[q])
        hi = max(hi, its[q])
    w0, w1, w2, w3 = 0.0, 0.0, 0.0, 0.0  # no residual is below zero or not a number
    whole = res.shape[0] - res.shape[0] % 4
    for q in range(0, whole, 4):
        w0 = res[q] if res[q] > w0 else w0
        w1 = res[q + 1] if res[q + 1] > w1 else w1
        w2 = res[q + 2] if res[q + 2] > w2 else w2
        w3 = res[q + 3] if res[q + 3] > w3 else w3
    for q in range(whole, res.shape[0]):
        w0 = res[q] if res[q] > w0 else w0
    w0 = w1 if w1 > w0 else w0
    w2 = w3 if w3 > w2 else w2
    return lo, hi, w2 if w2 > w0 else w0
"""


def _slice_step_source() -> list[str]:
    """``predict``: slice-Newton's predictor on the unknown sites (``2 psi_i - psi_{i-1}``, plus
    ``psi_i - 2 psi_{i-1} + psi_{i-2}`` where ``older``, slice ``i - 2``, is given), in the order of
    ``_stepper.solve_and_tally``, returning the scale of a Newton step (``_slices._scale``: the largest value
    in size of the two slices and the predictor), in one pass over the sites (``interior``: those with an
    equation), the maxima of each in its own chain; ``tally``: the least and most evaluations of the sites
    and their largest residual, in a pass of its own (a running maximum inside the Newton loop waits on
    each site's sine: it costs more than the pass); ``slice_step`` (and ``slice_step_serial``): the three
    around ``slice_newton``, the tolerances formed from the scale as ``_fused`` did in Python;
    ``slice_steps`` (and ``slice_steps_serial``): ``slice_step`` on slices ``start .. stop - 1`` of
    ``values`` (``(slices, sites)``), the older slice given from the third on, each slice's most evaluations
    and largest residual written into ``most`` and ``worst`` at its index; it stops before the first slice a
    site could not finish and returns the index of the slice it stopped at (``stop`` when every one was
    solved). Beside them, the per-lattice maps of ``_fused``: ``cell_maps`` (``cell_at`` from ``site_of``; ``False``
    where two cells have a point on one site) and ``plain_sites`` (the sites read at fixed offsets)."""
    text = _SLICE_STEP.splitlines()
    for suffix in ("", "_serial"):
        text += [
            "",
            "@numba.njit(cache=True, error_model='numpy', nogil=True)",
            f"def slice_step{suffix}(prev, cur, nxt, older, site_of, cell_at, plain, delta, rows, interior, vol,"
            " rtol, dmax, smin, maxit, res, its):",
            "    scale = predict(prev, cur, nxt, older, rows, interior)",
            "    tol = rtol * vol * dmax * scale",
            f"    slice_newton{suffix}(prev, cur, nxt, site_of, cell_at, plain, delta, rows, vol, tol, rtol * scale,"
            " smin, maxit, res, its)",
            "    return tally(res, its)",
            "",
            "",
            "@numba.njit(cache=True, error_model='numpy', nogil=True)",
            f"def slice_steps{suffix}(values, start, stop, none, site_of, cell_at, plain, delta, rows, interior,"
            " vol, rtol, dmax, smin, maxit, res, its, most, worst):",
            "    for j in range(start, stop):",
            "        older = values[j - 2] if j >= 2 else none",
            f"        lo, hi, top = slice_step{suffix}(values[j - 1], values[j], values[j + 1], older, site_of,"
            " cell_at, plain, delta, rows, interior, vol, rtol, dmax, smin, maxit, res, its)",
            "        if lo < 0:",
            "            return j",
            "        most[j] = hi",
            "        worst[j] = top",
            "    return stop",
            "",
        ]
    return text


#: The 0+1D trajectory loop: ``_fast1d.FastBatch.step_one`` slice after slice, the same IEEE operations in
#: the same order, around the model's own ``derivatives`` (``dL/dx`` at both points and the mixed block).
_TRAJECTORY = """
@numba.njit(cache=True, error_model='numpy', nogil=True)
def trajectory(psi, start, stop, vol, rtol, maxit, box, srtol, fst, ist, fail):
    gprev, mscale, worst = fst[0], fst[1], fst[2]
    iters, most = ist[0], ist[1]
    i = start
    status = 0
    while i < stop:
        q_now = psi[i]
        q_old = psi[i - 1]
        u = 2 * q_now - q_old
        mag = _fmax(_fmax(abs(q_now), abs(q_old)), abs(u))
        rtol_mag = rtol * mag
        rscale = math.nan
        count, sing, prev, last, halved, small = 1, False, math.inf, 0.0, 0, -1
        smin = math.inf
        ok = False
        rabs = math.nan
        g1 = math.nan
        it = 0
        for it in range(1, maxit + 1):
            g0, g1, block = derivatives(q_now, u)
            jac = vol * block
            r = vol * (g0 + gprev)
            rabs = abs(r)
            if it == 1:
                rscale = rtol * (_fmax(abs(jac), 1e-300) * _fmax(mag, 1e-300))
            sv = abs(jac)
            if not math.isfinite(sv):
                sv = 0.0 if sv != sv else 1.7976931348623157e308
            mscale = _fmax(mscale, sv)
            smin = _fmin(smin, sv)
            sing = sing or not sv > srtol * mscale
            ok = rabs <= rscale
            if small >= 0:
                ok = ok or (small == 1 and math.isfinite(rabs))
            ok = ok and not sing
            if it > 1 and not ok:
                count += 1
            if ok or it == maxit:
                break
            worse = not (ok or sing or rabs < prev) and halved < 12
            step = -r / jac if jac != 0 else math.nan
            sing = sing or (not worse and not math.isfinite(step))
            if not (ok or sing or worse):
                u = u + step
                prev, last, halved = rabs, step, 0
                small = 1 if abs(step) <= rtol_mag else 0
                continue
            if worse:
                last = last / 2
                u = u - last
                halved += 1
            small = 1 if worse and abs(last) <= rtol_mag else 0
        iters += count
        if not ok:
            fail[0], fail[1], fail[2], fail[3], fail[4], fail[5] = u, rabs, 1.0 if sing else 0.0, smin, float(it), g1
            status = 1
            break
        psi[i + 1] = u
        gprev = g1
        most = max(most, it)
        worst = _fmax(worst, rabs)
        i += 1
        if box >= 0 and math.sqrt(u * u) > box:
            status = 2
            break
    fst[0], fst[1], fst[2] = gprev, mscale, worst
    ist[0], ist[1] = iters, most
    return i, status


@numba.njit(cache=True, error_model='numpy', nogil=True)
def _fmax(a, b):
    return a if a >= b or a != a else b


@numba.njit(cache=True, error_model='numpy', nogil=True)
def _fmin(a, b):
    return a if a <= b or a != a else b
"""


def _trajectory_source(form: SymbolicLd, grads: Sequence[Any]) -> list[str]:
    """``trajectory``: every slice of one 0+1D trajectory solved in one compiled loop (:data:`_TRAJECTORY`,
    the predictor, Newton with backtracking, the conditioning, convergence and box tests of
    ``_fast1d.FastBatch.step_one``), for a scalar ``L_d`` on the two-point stencil; nothing
    (``HAS_TRAJECTORY = False``) otherwise. It stops at the first slice that fails or leaves the box."""
    import sympy

    if form.m != 1 or sorted(form.offsets) != [(0,), (1,)]:
        return ["HAS_TRAJECTORY = False", ""]
    a0, a1 = form.offsets.index((0,)), form.offsets.index((1,))
    block = sympy.diff(grads[a0], form.symbols[a1][0])
    lines, values = _printed([grads[a0], grads[a1], block])
    text = ["HAS_TRAJECTORY = True", ""]
    text += ["@numba.njit(cache=True, error_model='numpy', nogil=True)"]
    text += [f"def derivatives({form.symbols[a0][0]}, {form.symbols[a1][0]}):"]
    text += [f"    {line}" for line in lines] + [f"    return {values[0]}, {values[1]}, {values[2]}", ""]
    return text + _TRAJECTORY.splitlines()
