"""The peers of the discovery benchmark, from the ``bench`` extra: PySINDy and py-xl-sindy.

Both fit continuous equations of motion, so they take the ODE systems only, from the same training samples as
latticedft, and are served from the test's exact initial state ``(q, q')`` (latticedft gets the first two
slices instead):

- PySINDy: ``x'' = f(x, x')`` on a library of polynomials of degree 3 and one Fourier frequency, sequentially
  thresholded least squares (its default threshold 0.1); the velocity is the second-order finite difference of
  the positions, and PySINDy differentiates the state ``(x, x')`` itself. The test is integrated with DOP853
  from its ``predict``.
- py-xl-sindy: a Lagrangian catalog (:data:`XL_CATALOGS`: velocities to degree 2 crossed with functions of the
  positions to degree 2, as its own examples build them), velocities and accelerations by central differences,
  its implicit regression (SINDy-PI, no external force in these data); the test integrated with DOP853 from the
  acceleration function it derives. On its own systems (:func:`xl_own_rows`: single and double pendulum and
  cart-pole driven by known forces, at its noise levels) it runs its mixed (explicit) regression.

Term recovery: the equations of motion each implies, normalised so that the acceleration's coefficient is 1,
against the true Euler-Lagrange equations (:mod:`benchmarks._terms`).
"""

from __future__ import annotations

import contextlib
import logging
import os
import sys
import time
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np
import sympy
from scipy.integrate import solve_ivp

from ._discovery_systems import OdeSpec, System, max_errors, ode_spec
from ._terms import acceleration_terms, euler_lagrange_terms, term_error, terms_cell

NOT_INSTALLED = "not installed"


def rows_for(
    system: System, label: str, terms: str, coef: Any, pred: np.ndarray, fit: Any, dense: Any, samples: Any = "-"
) -> list[list]:
    """Table rows of one model on ``system``: one per error horizon, with the leapfrog of the true equation
    (``samples``: the coefficient error of the model learned on the samples, where ``coef`` is another's)."""
    ref = np.asarray(system.test.values, dtype=float)
    mine = max_errors(pred, ref, system.slices, system.at)
    base = max_errors(system.leapfrog(system.test, system.slices), ref, system.slices, system.at)
    cost = fit / dense if isinstance(fit, float) and isinstance(dense, float) else None
    horizons = [(f" ({k} steps)", i + 1) for i, k in enumerate(system.at)] or [("", 0)]
    return [
        [
            system.name + sfx,
            system.range_note,
            label,
            terms,
            coef,
            samples,
            mine[i],
            base[i],
            mine[i] / base[i],
            fit,
            dense,
            cost,
        ]
        for sfx, i in horizons
    ]


@contextlib.contextmanager
def quiet() -> Iterator[None]:
    """Silence a peer: Python logging and everything written to the process's stdout and stderr (its solvers
    print from compiled code)."""
    sys.stdout.flush()
    sys.stderr.flush()
    saved = [os.dup(1), os.dup(2)]
    null = os.open(os.devnull, os.O_WRONLY)
    logging.disable(logging.CRITICAL)
    try:
        os.dup2(null, 1)
        os.dup2(null, 2)
        with open(os.devnull, "w") as sink, contextlib.redirect_stdout(sink), contextlib.redirect_stderr(sink):
            yield
    finally:
        sys.stdout.flush()
        sys.stderr.flush()
        os.dup2(saved[0], 1)
        os.dup2(saved[1], 2)
        for fd in (*saved, null):
            os.close(fd)
        logging.disable(logging.NOTSET)


def positions(field: Any) -> np.ndarray:
    """A field's values as ``(slices, m)``."""
    vals = np.asarray(field.values, dtype=float)
    return vals.reshape(vals.shape[0], -1)


def differences(system: System, h: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Positions, velocities and accelerations of every training field at its interior slices (central
    differences of second order)."""
    qs, vs, accs = [], [], []
    for f in system.train:
        q = positions(f)
        qs.append(q[1:-1])
        vs.append((q[2:] - q[:-2]) / (2 * h))
        accs.append((q[2:] - 2 * q[1:-1] + q[:-2]) / (h * h))
    return np.concatenate(qs), np.concatenate(vs), np.concatenate(accs)


class _TooLong(Exception):
    """An integration past its wall-time limit."""


def integrate(
    acc: Callable[[float, np.ndarray, np.ndarray], np.ndarray], q0: Any, v0: Any, n: int, h: float, limit: float = 30.0
) -> np.ndarray:
    """Positions at ``n`` times ``0, h, ..`` of ``q'' = acc(t, q, q')`` (DOP853, ``rtol = atol = 1e-10``);
    no rows where the integration failed or ran past ``limit`` seconds (a stiff, diverging model)."""
    m = len(q0)
    start = time.perf_counter()

    def rhs(t: float, y: np.ndarray) -> np.ndarray:
        if time.perf_counter() - start > limit:
            raise _TooLong
        return np.concatenate([y[m:], acc(t, y[:m], y[m:])])

    t = h * np.arange(n)
    try:
        sol = solve_ivp(rhs, (0.0, t[-1]), [*q0, *v0], t_eval=t, method="DOP853", rtol=1e-10, atol=1e-10)
    except Exception:  # noqa: BLE001 - a model that cannot be integrated is a lost prediction
        return np.zeros((0, m))
    return sol.y[:m].T


def _symbols(m: int) -> tuple[tuple[Any, ...], tuple[Any, ...], tuple[Any, ...]]:
    return (
        tuple(sympy.symbols(f"q0:{m}", real=True)),
        tuple(sympy.symbols(f"v0:{m}", real=True)),
        tuple(sympy.symbols(f"a0:{m}", real=True)),
    )


# ----------------------------------------------------------------------------------------------------------
# PySINDy
# ----------------------------------------------------------------------------------------------------------


def _sindy_terms(model: Any, m: int) -> list[dict[Any, float]]:
    """The acceleration rows of a fitted SINDy model as normalised equations in ``q``, ``v``, ``a``."""
    q, v, a = _symbols(m)
    names = {f"x{i}": q[i] for i in range(m)} | {f"x{m + i}": v[i] for i in range(m)}
    feats = [sympy.sympify(n.replace("^", "**").replace(" ", "*"), locals=names) for n in model.get_feature_names()]
    coefs = model.coefficients()
    rhs = [sum(float(c) * f for c, f in zip(coefs[m + i], feats) if c != 0) for i in range(m)]
    return acceleration_terms(rhs, a)


def pysindy_rows(system: System, spec: OdeSpec) -> list[list]:
    try:
        import pysindy as ps
    except ImportError:
        return rows_for(system, f"PySINDy: {NOT_INSTALLED}", "-", "-", np.zeros((0, 1)), None, None)
    h = float(system.test["t"][1] - system.test["t"][0])
    m = len(spec.q)
    states = [np.hstack([positions(f), np.gradient(positions(f), h, axis=0, edge_order=2)]) for f in system.train]
    lib = ps.PolynomialLibrary(degree=3) + ps.FourierLibrary(n_frequencies=1)
    model = ps.SINDy(optimizer=ps.STLSQ(), feature_library=lib, differentiation_method=ps.FiniteDifference())
    t0 = time.perf_counter()
    with quiet():
        model.fit(states, t=h)
    fit = time.perf_counter() - t0
    assert system.test_state is not None
    q0, v0 = system.test_state

    def acc(t: float, q: np.ndarray, v: np.ndarray) -> np.ndarray:
        return np.asarray(model.predict(np.concatenate([q, v])[None, :]))[0, m:]

    pred = integrate(acc, q0, v0, system.slices, h)
    q, v, a = _symbols(m)
    want = euler_lagrange_terms(spec.lagrangian.xreplace(dict(zip(spec.q + spec.v, q + v))), q, v, a)
    err, n_got, n_want = term_error(_sindy_terms(model, m), want)
    return rows_for(system, "PySINDy (poly 3 + Fourier 1, STLSQ 0.1)", terms_cell(n_got, n_want), err, pred, fit, None)


# ----------------------------------------------------------------------------------------------------------
# py-xl-sindy
# ----------------------------------------------------------------------------------------------------------

#: per system, the functions of one position coordinate its catalog combines (to degree 2, crossed with the
#: velocities to degree 2), and extra position terms (``r`` is ``|q|``)
XL_CATALOGS: dict[str, tuple[tuple[str, ...], tuple[str, ...]]] = {
    "oscillator-sin": (("q", "sin", "cos"), ()),
    "oscillator-wells": (("q", "sin2", "cos2"), ()),
    "kepler": (("q",), ("1/r",)),
    "charged-particle": (("q",), ()),
    "pendulum": (("sin", "cos"), ()),
    "double-pendulum": (("sin", "cos"), ()),
}


def xl_catalog(S: np.ndarray, funcs: tuple[str, ...], extra: tuple[str, ...]) -> np.ndarray:
    """A py-xl-sindy Lagrangian catalog in its symbol matrix ``S`` (rows: force, q, q', q'')."""
    from xlsindy.symbolic_util import cross_catalog, generate_full_catalog

    m = S.shape[1]
    make = {
        "q": lambda i: S[1, i],
        "sin": lambda i: sympy.sin(S[1, i]),
        "cos": lambda i: sympy.cos(S[1, i]),
        "sin2": lambda i: sympy.sin(S[1, i] ** 2),
        "cos2": lambda i: sympy.cos(S[1, i] ** 2),
    }
    vel = generate_full_catalog([lambda i: S[2, i]], m, 2)
    pos = list(generate_full_catalog([make[f] for f in funcs], m, 2))
    if "1/r" in extra:
        pos.append(1 / sympy.sqrt(sum(S[1, i] ** 2 for i in range(m))))
    return np.asarray(cross_catalog(np.asarray(vel), np.asarray(pos)))


def _xl_model(
    solution: np.ndarray, cat: Any, S: np.ndarray, t_sym: Any
) -> Callable[[float, np.ndarray, np.ndarray], np.ndarray] | None:
    """The acceleration of a py-xl-sindy solution (None when it derives none), forces 0."""
    from xlsindy.dynamics_modeling import generate_acceleration_function

    fn, valid = generate_acceleration_function(solution, cat, S, t_sym)
    if not valid:
        return None
    m = S.shape[1]

    def acc(t: float, q: np.ndarray, v: np.ndarray, force: Callable[[float], np.ndarray] | None = None) -> np.ndarray:
        inp = np.zeros((4, m))
        inp[0] = force(t) if force is not None else 0.0
        inp[1], inp[2] = q, v
        return np.asarray(fn(inp), dtype=float).reshape(m)

    return acc


def xl_lagrangian_terms(solution: np.ndarray, lag: np.ndarray, S: np.ndarray) -> list[dict[Any, float]]:
    """The Euler-Lagrange terms of the Lagrangian a solution vector picks from the catalog ``lag``."""
    m = S.shape[1]
    q, v, a = _symbols(m)
    subs = {S[1, i]: q[i] for i in range(m)} | {S[2, i]: v[i] for i in range(m)}
    L = sum(float(c) * term.xreplace(subs) for c, term in zip(solution.ravel(), lag) if c != 0)
    return euler_lagrange_terms(sympy.sympify(L), q, v, a)


def xl_rows(system: System, spec: OdeSpec) -> list[list]:
    try:
        import xlsindy
        from xlsindy.catalog import CatalogRepartition
        from xlsindy.catalog_base import Lagrange
    except ImportError:
        return rows_for(system, f"py-xl-sindy: {NOT_INSTALLED}", "-", "-", np.zeros((0, 1)), None, None)
    h = float(system.test["t"][1] - system.test["t"][0])
    m = len(spec.q)
    t_sym = sympy.Symbol("t")
    S = xlsindy.symbolic_util.generate_symbolic_matrix(m, t_sym)
    lag = xl_catalog(S, *XL_CATALOGS[system.key])
    cat = CatalogRepartition([Lagrange(lag, S, t_sym)])
    q, v, acc = differences(system, h)
    t0 = time.perf_counter()
    with quiet():
        sol, _ = xlsindy.simulation.regression_implicite(q, v, acc, t_sym, S, cat)
    fit = time.perf_counter() - t0
    label = f"py-xl-sindy (implicit, {len(lag)} terms)"
    if sol.shape[1] == 0:
        return rows_for(system, label + ": no solution", "0", "-", np.zeros((0, m)), fit, None)
    sol = sol.sum(axis=1, keepdims=True)  # as its mixed regression stacks the implicit solutions
    sol = np.where(np.abs(sol) < 1e-2 * np.linalg.norm(sol), 0.0, sol)  # its examples' threshold
    model = _xl_model(sol, cat, S, t_sym)
    assert system.test_state is not None
    pred = integrate(model, *system.test_state, system.slices, h) if model is not None else np.zeros((0, m))
    qs, vs, a_s = _symbols(m)
    want = euler_lagrange_terms(spec.lagrangian.xreplace(dict(zip(spec.q + spec.v, qs + vs))), qs, vs, a_s)
    err, n_got, n_want = term_error(xl_lagrangian_terms(sol, lag, S), want)
    return rows_for(system, label, terms_cell(n_got, n_want), err, pred, fit, None)


def peer_rows(system: System) -> list[list]:
    """PySINDy's and py-xl-sindy's rows on an ODE system."""
    assert system.ode is not None
    rows = pysindy_rows(system, system.ode)
    if system.key in XL_CATALOGS:
        rows += xl_rows(system, system.ode)
    return rows


# ----------------------------------------------------------------------------------------------------------
# py-xl-sindy on its own systems: driven by known forces, at its noise levels
# ----------------------------------------------------------------------------------------------------------

XL_NOISE = (0.0, 1e-3, 1e-2)


def _own_specs() -> dict[str, OdeSpec]:
    """Its example systems: a pendulum, a double pendulum (masses 0.8, unit lengths) and the cart-pole (cart
    0.8, pole 0.5, length 1), g = 9.81."""

    def double(q: Any, v: Any) -> Any:
        m1 = m2 = sympy.Rational(4, 5)
        kin = (m1 + m2) / 2 * v[0] ** 2 + m2 / 2 * v[1] ** 2 + m2 * v[0] * v[1] * sympy.cos(q[0] - q[1])
        return kin + sympy.Float(9.81) * ((m1 + m2) * sympy.cos(q[0]) + m2 * sympy.cos(q[1]))

    def cart_pole(q: Any, v: Any) -> Any:
        mb, ml = sympy.Rational(4, 5), sympy.Rational(1, 2)
        kin = (mb + ml) / 2 * v[0] ** 2 + ml / 2 * v[1] ** 2 - ml * sympy.cos(q[1]) * v[1] * v[0]
        return kin - ml * sympy.Float(9.81) * sympy.cos(q[1])

    return {
        "pendulum": ode_spec(1, lambda q, v: v[0] ** 2 / 2 + sympy.Float(9.81) * sympy.cos(q[0])),
        "double pendulum": ode_spec(2, double),
        "cart-pole": ode_spec(2, cart_pole),
    }


def _forcing(m: int, rng: np.random.Generator, scale: float = 2.0) -> Callable[[float], np.ndarray]:
    """A sum of three sines per coordinate, random amplitudes (up to ``scale``), periods and phases."""
    amp = rng.uniform(-scale, scale, (3, m))
    omega = 2 * np.pi / rng.uniform(1.0, 4.0, (3, m))
    phase = rng.uniform(0, 2 * np.pi, (3, m))
    return lambda t: np.sum(amp * np.sin(omega * t + phase), axis=0)


def _forced_run(spec: OdeSpec, rng: np.random.Generator, seconds: float, h: float):
    """``(t, q, v, a, f)`` of one driven trajectory from a random start near rest (exact derivatives)."""
    m = len(spec.q)
    force = _forcing(m, rng)
    y0 = np.concatenate([rng.uniform(-0.5, 0.5, m), np.zeros(m)])
    t = h * np.arange(int(round(seconds / h)) + 1)

    def rhs(tt: float, y: np.ndarray) -> np.ndarray:
        return np.concatenate([y[m:], spec.forced(y[:m], y[m:], force(tt))])

    sol = solve_ivp(rhs, (0.0, t[-1]), y0, t_eval=t, method="DOP853", rtol=1e-10, atol=1e-10)
    q, v = sol.y[:m].T, sol.y[m:].T
    f = np.array([force(tt) for tt in t])
    a = np.array([spec.forced(qq, vv, ff) for qq, vv, ff in zip(q, v, f)])
    return t, q, v, a, f, force


def _noisy(x: np.ndarray, level: float, rng: np.random.Generator) -> np.ndarray:
    """Its noise: normal, scaled by ``level * |x| / samples`` (the Frobenius norm over the sample count)."""
    return x + rng.normal(0.0, level, x.shape) * np.linalg.norm(x) / x.shape[0]


def xl_own_row(name: str, spec: OdeSpec, noise: float, seed: int = 1) -> list:
    """py-xl-sindy's mixed regression on one of its driven systems; served on a new start and force for 10 s."""
    import xlsindy
    from xlsindy.catalog import CatalogRepartition
    from xlsindy.catalog_base import ExternalForces, Lagrange
    from xlsindy.optimization import lasso_regression

    m = len(spec.q)
    rng = np.random.default_rng(seed)
    t_sym = sympy.Symbol("t")
    S = xlsindy.symbolic_util.generate_symbolic_matrix(m, t_sym)
    lag = xl_catalog(S, ("sin", "cos"), ())
    cat = CatalogRepartition([ExternalForces([[i + 1] for i in range(m)], S), Lagrange(lag, S, t_sym)])
    runs = [_forced_run(spec, rng, 10.0, 0.01)[1:5] for _ in range(2)]
    data = [np.concatenate([r[k] for r in runs]) for k in range(4)]
    keep = np.linspace(0, len(data[0]) - 1, 2 * cat.catalog_length, dtype=int)  # its data ratio 2
    q, v, a, f = (_noisy(x[keep], noise, rng) for x in data)
    t0 = time.perf_counter()
    with quiet():
        sol, _ = xlsindy.simulation.regression_mixed(
            q, v, a, t_sym, S, cat, f, regression_function=lasso_regression, noise_level=noise,
            pre_knowledge_type="external_forces_manual", pre_knowledge_indices=np.arange(m),
        )  # fmt: skip
    fit = time.perf_counter() - t0
    sol = np.where(np.abs(sol) < 1e-2 * np.linalg.norm(sol), 0.0, sol)
    qs, vs, a_s = _symbols(m)
    want = euler_lagrange_terms(spec.lagrangian.xreplace(dict(zip(spec.q + spec.v, qs + vs))), qs, vs, a_s)
    err, n_got, n_want = term_error(xl_lagrangian_terms(sol[m:], lag, S), want)
    t, qv, vv, _, _, force = _forced_run(spec, np.random.default_rng(seed + 100), 10.0, 0.01)
    with quiet():
        model = _xl_model(sol, cat, S, t_sym)
    served = np.inf
    if model is not None:
        pred = integrate(lambda tt, x, y: model(tt, x, y, force), qv[0], vv[0], len(t), 0.01)
        served = max_errors(pred, qv, len(t))[0]
    label = f"py-xl-sindy (mixed, {len(lag)} terms)" + ("" if model is not None else ": no model")
    system = f"xl-sindy's {name}, noise {noise:g}"
    return [
        system,
        "driven; new start and force, 10 s",
        label,
        terms_cell(n_got, n_want),
        err,
        "-",
        served,
        None,
        None,
        fit,
        None,
        None,
    ]


def xl_own_rows() -> list[list]:
    """py-xl-sindy on its single and double pendulum and cart-pole at noise 0, 1e-3 and 1e-2."""
    try:
        import xlsindy  # noqa: F401
    except ImportError:
        return [["xl-sindy's own systems", "-", f"py-xl-sindy: {NOT_INSTALLED}"] + [None] * 8]
    return [xl_own_row(name, spec, noise) for name, spec in _own_specs().items() for noise in XL_NOISE]
