"""The discovery benchmark: the leapfrog baseline of the true equations and the term comparison (its quick table:
tests/test_benchmarks.py, from the runner's ``--quick`` run).

No timing is asserted.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from unittest import mock

import numpy as np
import pytest
import sympy

import latticedft as ldft
from benchmarks import _discovery_systems as systems
from benchmarks import discovery
from benchmarks._terms import coefficient_error, normalised_terms
from latticedft._lattice import as_lattice_field
from latticedft._symbolic import SymbolicLd, cell_symbols


def _pendulum_ld(h: float, mass: float = 1.0, gravity: float = 1.0, extra: object = 0) -> SymbolicLd:
    """A hand-made closed form of the pendulum's trapezoid ``L_d``, scaled, with optional extra terms."""
    (u0,), (u1,) = cell_symbols(2, 1)
    expr = mass * (u1 - u0) ** 2 / (2 * h * h) + gravity * (sympy.cos(u0) + sympy.cos(u1)) / 2 + extra
    return SymbolicLd(expr, ((0,), (1,)), 1, (h,))


@dataclass
class _Closed:
    """A stand-in for a model with a closed form (``symbolic()`` in the symbols ``u{p}_{c}``)."""

    form: SymbolicLd | None

    def symbolic(self) -> SymbolicLd | None:
        return self.form


def test_term_recovery_of_a_hand_made_pendulum_form():
    system = systems.build("pendulum", quick=True)
    (u0,), (u1,) = cell_symbols(2, 1)
    gauge = 0.3 * (sympy.sin(u1) - sympy.sin(u0)) + 7  # a total difference and a constant change nothing
    same = _pendulum_ld(0.1, mass=3.7, gravity=3.7, extra=3.7 * gauge)
    assert discovery.recovery(_Closed(same), system)[0] == "4/4"
    assert discovery.recovery(_Closed(same), system)[1] < 1e-12
    off = _pendulum_ld(0.1, gravity=1.01)  # the sin term 1 % off
    assert coefficient_error(off, system.true_ld)[0] == pytest.approx(0.01, rel=1e-9)
    spurious = _pendulum_ld(0.1, extra=1e-3 * u0**4)  # u^3 in the DEL, relative to the smallest true term
    err, n_got, n_want = coefficient_error(spurious, system.true_ld)
    assert (n_got, n_want) == (5, 4)
    smallest = min(abs(v) for v in normalised_terms(system.true_ld)[0].values())
    assert err == pytest.approx(4e-3 * 0.01 / smallest, rel=1e-9)
    assert discovery.recovery(_Closed(None), system) == ("n/a: no closed form", "n/a")


def test_term_recovery_of_a_hand_made_kepler_form_with_float_powers():
    """A closed form written as a model might print it (float exponents, the cell scaled by h) matches."""
    system = systems.build("kepler", quick=True)
    (x0, y0), (x1, y1) = cell_symbols(2, 2)
    h, gm = 0.1, systems.KEPLER_GM
    kinetic = ((x1 - x0) ** 2 + (y1 - y0) ** 2) / (2.0 * h)
    potential = 0.5 * h * gm * ((x0**2 + y0**2) ** -0.5 + (x1**2 + y1**2) ** -0.5)
    form = SymbolicLd(2.5 * (kinetic + potential), ((0,), (1,)), 2, (h,))
    err, n_got, n_want = coefficient_error(form, system.true_ld)
    assert (n_got, n_want) == (8, 8) and err < 1e-12
    assert discovery.recovery(_Closed(SymbolicLd(kinetic, ((0,), (1,)), 2, (h,))), system)[0] == "6/8"


def test_term_recovery_splits_a_constant_phase_of_a_trig_potential():
    """Paper Example 2's ``cos(q^2 - 1)`` written as a library writes it, ``cos 1 cos q^2 + sin 1 sin q^2``, has the
    same terms and coefficients; ``cos q^2`` alone does not."""
    system = systems.build("oscillator-wells", quick=True)
    (u0,), (u1,) = cell_symbols(2, 1)

    def well(potential: object) -> SymbolicLd:
        kinetic = (u1 - u0) ** 2 / 2
        return SymbolicLd(
            kinetic + 0.0075 * (potential(u0) + potential(u1)) + 0.0015 * (u0 + u1), ((0,), (1,)), 1, (1.0,)
        )

    split = well(lambda q: math.cos(1) * sympy.cos(q**2) + math.sin(1) * sympy.sin(q**2))
    err, n_got, n_want = coefficient_error(split, system.true_ld)
    assert (n_got, n_want) == (6, 6) and err < 1e-12
    err, _, _ = coefficient_error(well(lambda q: sympy.cos(q**2)), system.true_ld)
    assert err > 0.1


def test_true_forms_of_every_system_agree_with_themselves_and_keep_unit_mass():
    for name in systems.SYSTEMS:
        true = systems.build(name, quick=True).true_ld
        assert coefficient_error(true, true)[0] == 0.0
        for terms in normalised_terms(true):
            assert terms, name  # each component has a linear term in its next value


@pytest.mark.parametrize("name", ["pendulum", "charged-particle", "double-pendulum"])
def test_true_leapfrog_converges_at_second_order(name):
    """Halving the step divides the leapfrog's error over a fixed time by about four (second order): the
    explicit scheme (pendulum) and the fixed-point solve of a velocity-dependent force (the others)."""
    spec = systems.build(name, quick=True).ode
    assert spec is not None
    q0, v0 = ([2.0], [0.0]) if name == "pendulum" else ((0.5, -0.3), (0.2, 0.1))
    errs = []
    for h in (0.1, 0.05, 0.025):
        n = int(round(4.0 / h)) + 1
        exact = np.asarray(systems.ode_field(spec, q0, v0, n, h).values).reshape(n, -1)
        lf = systems.ode_leapfrog(spec.accel, spec.velocity_dependent, exact[0], exact[1], n, h)
        errs.append(np.abs(lf - exact).max())
    assert spec.velocity_dependent == (name != "pendulum")
    for coarse, fine in zip(errs, errs[1:]):
        assert 3.3 < coarse / fine < 4.7, errs


def test_field_leapfrog_reproduces_the_lattice_equation():
    """The field data are the lattice equation stepped ten times finer: its leapfrog at the data's step stays
    close to them over 40 slices."""
    system = systems.build("sine-gordon-1d", quick=True)
    ref = np.asarray(system.test.values)
    err = np.abs(system.leapfrog(system.test, 40) - ref[:40]).max()
    assert 0 < err < 1e-2


def test_peer_rows_say_not_installed_when_the_peers_are_missing(monkeypatch):
    """Without the ``bench`` extra the peers' rows say so and the benchmark goes on."""
    import sys

    from benchmarks import _discovery_peers as peers

    monkeypatch.setitem(sys.modules, "pysindy", None)  # ``import pysindy`` raises ImportError
    monkeypatch.setitem(sys.modules, "xlsindy", None)
    system = systems.build("pendulum", quick=True)
    rows = peers.peer_rows(system)
    assert [r[2] for r in rows] == ["PySINDy: not installed", "py-xl-sindy: not installed"]
    assert all(r[6] == math.inf for r in rows)  # no prediction
    assert peers.xl_own_rows()[0][2] == "py-xl-sindy: not installed"


def test_variational_data_obey_the_true_del():
    """For a constant mass the trapezoid ``L_d``'s DEL is the Stormer-Verlet leapfrog: the regenerated training
    data are that leapfrog from the same two slices."""
    system = systems.build("pendulum", quick=True)
    field = systems.variational_data(system)[0]
    want = system.leapfrog(system.train[0], system.train[0].sizes["t"])
    assert np.abs(np.asarray(field.values) - want).max() < 1e-12
    assert field.dims == system.train[0].dims


def test_noisy_samples_are_seeded_and_scaled_by_the_largest_magnitude():
    from benchmarks.discovery_noise import noisy

    system = systems.build("pendulum", quick=True)
    a, scale = noisy(system.train, 1e-2, seed=3)
    b, _ = noisy(system.train, 1e-2, seed=3)
    largest = max(float(np.abs(f.values).max()) for f in system.train)
    assert scale == pytest.approx(1e-2 * largest)
    assert all(np.array_equal(x.values, y.values) for x, y in zip(a, b, strict=True))
    diff = np.concatenate([(x.values - f.values).ravel() for x, f in zip(a, system.train, strict=True)])
    assert np.std(diff) == pytest.approx(scale, rel=0.15)  # 200 samples: the deviation to about 10 %
    assert a[0].dims == system.train[0].dims and a[0].coords["t"].equals(system.train[0].coords["t"])


def test_noise_targets_read_recovery_bound_and_warnings():
    from benchmarks.discovery_noise import targets

    low = {"sigma": 1e-3, "recovered": True, "within": True, "warned": False}
    checks = targets([low, {**low, "sigma": 1e-2, "recovered": False, "warned": True}], (1e-3, 1e-2))
    assert [c.met for c in checks] == [True, True, True]
    checks = targets([{**low, "within": False}, {**low, "sigma": 1e-2, "recovered": False}], (1e-3, 1e-2))
    assert [c.met for c in checks] == [True, False, False]
    assert checks[1].measured == "0 of 1 systems" and checks[2].measured.startswith("0 of 1")
    assert len(targets([low], (1e-3,))) == 2  # one level: no high-noise target


def test_a_noisy_sparse_fit_whose_coefficients_vary_over_its_bags_warns():
    """Learned from samples with noise 1e-3: the exact-step library of paper Example 1 at threshold 1e-5 keeps
    terms whose coefficients vary over the bagged fits far beyond 5 %, and the learning report says so; the
    pendulum's true terms vary by far less, and it does not."""
    from benchmarks.discovery_noise import noisy
    from latticedft._learn._noise import SPREAD_WARN

    def learned(name: str, library: str, at: str, threshold: float | str) -> tuple[ldft.SparseLagrangian, list[str]]:
        train, _ = noisy(systems.build(name, quick=True).train, 1e-3, seed=0)
        model = ldft.SparseLagrangian(library, threshold=threshold, at=at)  # type: ignore[arg-type]
        return model, ldft.learn(model, train, progress=False, noise="auto").warnings

    wide, warned = learned("oscillator-sin", "kinetic + trig:2 + kinetic*trig:1", "average", 1e-5)
    assert wide.bag_spread is not None and np.nanmax(wide.bag_spread) > 10 * SPREAD_WARN
    assert any("vary by up to" in w and "over the fits on resampled time blocks" in w for w in warned)
    true, warned = learned("pendulum", "kinetic + trig:1", "anchor", "auto")
    assert true.bag_spread is not None and np.nanmax(true.bag_spread) < SPREAD_WARN / 10
    assert not any("vary by up to" in w for w in warned)
    assert np.all(true.bag_spread[true.coef.detach().numpy() == 0] == 0)


def test_weak_rows_are_test_function_sums_that_average_out_second_difference_noise():
    from benchmarks.noise_weak import weak

    rng = np.random.default_rng(0)
    nt, sites = 60, 3
    noise = rng.standard_normal((nt + 2, sites))
    rows = (noise[2:] - 2 * noise[1:-1] + noise[:-2]).reshape(-1, 1)  # one column: second differences of noise
    assert weak(rows, nt, 0) is rows  # w = 0: the plain rows
    w = 4
    out = weak(rows, nt, w)
    assert out.shape == (len(range(0, nt - 2 * w, w // 2)) * sites, 1)
    s = np.linspace(-1, 1, 2 * w + 3)[1:-1]
    phi = (1 - s**2) ** 4 / np.linalg.norm((1 - s**2) ** 4)
    assert out[:sites, 0] == pytest.approx(phi @ rows.reshape(nt, sites)[: 2 * w + 1])
    # summed by parts the differences fall on phi: the noise shrinks far below that of a plain row (sqrt(6))
    assert np.std(out) < 0.2 * np.std(rows)


def test_weak_patch_reaches_the_rows_the_sparse_fit_uses():
    """``benchmarks.noise_weak``'s patch makes the sparse fit's blocks (every training field's rows) the weak rows:
    the fit's rows come from ``residual_matrices``, which a patch of ``residual_matrix`` alone did not reach."""
    from benchmarks.noise_weak import _interior_times, _weak_patch, weak
    from latticedft._learn import _sparse
    from latticedft._learn._exact import residual_matrix

    system = systems.build("pendulum", True)
    model = ldft.SparseLagrangian("kinetic + trig:1", threshold=0.1, bags=0)
    seen: list[list[np.ndarray]] = []
    real = _sparse._blocks

    def spy(rs: list[np.ndarray], c: int) -> list[np.ndarray]:
        seen.append(rs)
        return real(rs, c)

    with _weak_patch(4), mock.patch.object(_sparse, "_blocks", spy):
        ldft.learn(model, system.train, boundary=system.boundary, progress=False)
    fields = [as_lattice_field(f, boundary=system.boundary) for f in system.train]
    want = sorted(weak(residual_matrix(model, f), _interior_times(model, f), 4).shape[0] for f in fields)
    assert want and sorted(r.shape[0] for r in seen[-1]) == want
    assert want[0] < min(residual_matrix(model, f).shape[0] for f in fields)


def test_gauges_mode_reads_the_gauge_auto_chose_on_noisy_samples():
    """``--gauges``: the library in each gauge, without and with the noise correction; on the charged particle at
    1e-3 ``auto`` takes trace after the correction (its row's scores name both gauges) and keeps ``q x Dq``."""
    from benchmarks._common import Config
    from benchmarks.discovery_noise import GAUGE_COLUMNS, gauges

    table = gauges(Config(quick=True), ("charged-particle",), (1e-3,), "kinetic + poly:2 + cross", "anchor", 0)
    rows = {(r[2], r[3]): dict(zip(GAUGE_COLUMNS, r, strict=True)) for r in table.rows}
    assert len(rows) == 6
    chosen = rows["auto", "auto"]
    assert chosen["gauge used"] == "trace" and "unit-mass" in chosen["gauge_scores"]
    assert chosen["kept"] == "(Dtq1**2+Dtq2**2), (q1*Dtq2-q2*Dtq1)"
    assert "(q1*Dtq2-q2*Dtq1)" not in rows["auto", "unit-mass"]["kept"]
    assert chosen["rel_res"] == rows["auto", "trace"]["rel_res"]


def test_midpoint_rule_and_exact_step_of_the_pendulum_are_the_documented_forms():
    """``ode_ld(..., "midpoint")`` is ``h L((u0 + u1)/2, v)``; the exact step's ``L_d`` of ``L = v^2/2 + cos q`` in the
    trapezoid rule is ``h L_avg + h^3/12 v^2 cos q - h^3/24 sin^2 q`` averaged over the step's ends."""
    from benchmarks._pendulum_corrections import exact_step_ld

    h = 0.1
    spec = systems.build("pendulum", quick=True).ode
    assert spec is not None
    (u0,), (u1,) = cell_symbols(2, 1)
    v = (u1 - u0) / h
    midpoint = systems.ode_ld(spec, h, "midpoint").expr
    assert sympy.simplify(midpoint - h * (v**2 / 2 + sympy.cos((u0 + u1) / 2))) == 0
    avg = [
        (h * (v**2 / 2 + sympy.cos(u)) + h**3 / 12 * v**2 * sympy.cos(u) - h**3 / 24 * sympy.sin(u) ** 2) / 2
        for u in (u0, u1)
    ]
    assert sympy.simplify(exact_step_ld(spec, h).expr - sum(avg)) == 0
    assert sympy.simplify(systems.ode_ld(spec, h).expr - systems.build("pendulum", quick=True).true_ld.expr) == 0


def test_exact_step_of_the_double_pendulum_serves_at_fourth_order_and_its_rules_at_second():
    """Served by their variational integrators over t <= 4, halving the step divides the error of the exact step to
    ``O(h^5)`` by about 16 and that of the trapezoid and midpoint rules by about 4."""
    from benchmarks._pendulum_corrections import exact_step_ld

    spec = systems.build("double-pendulum", quick=True).ode
    assert spec is not None
    errs: dict[str, list[float]] = {"trapezoid": [], "midpoint": [], "exact": []}
    for h in (0.1, 0.05):
        n = int(round(4.0 / h)) + 1
        field = systems.ode_field(spec, (0.5, -0.3), (0.2, 0.1), n, h)
        exact = np.asarray(field.values).reshape(n, -1)
        forms = {"trapezoid": systems.ode_ld(spec, h), "midpoint": systems.ode_ld(spec, h, "midpoint")}
        forms["exact"] = exact_step_ld(spec, h)
        for rule, form in forms.items():
            errs[rule].append(float(np.abs(systems.variational_served(form, field, n).reshape(n, -1) - exact).max()))
    assert 3.3 < errs["trapezoid"][0] / errs["trapezoid"][1] < 4.7, errs
    assert 3.3 < errs["midpoint"][0] / errs["midpoint"][1] < 4.7, errs
    assert 12 < errs["exact"][0] / errs["exact"][1] < 20, errs


def test_correction_library_spans_the_double_pendulum_exact_step_with_a_constant_determinant():
    """The 28 correction terms with the coupled library hold ``-v.L_qq.v/12 - E.adj(M).E/24`` of the double pendulum
    (``M^-1 = adj(M)/det M``, ``det M`` taken constant): a least-squares fit at random points leaves round-off."""
    from benchmarks._pendulum_corrections import CORRECTIONS, correction_library
    from latticedft._models._terms import term_forms

    spec = systems.build("double-pendulum", quick=True).ode
    assert spec is not None
    q, v, lag = spec.q, spec.v, spec.lagrangian
    terms = correction_library("velocities + trig:1 + cosdiff*velocities").expand(1, 2)
    assert len(terms) == 10 + CORRECTIONS and len({t.name for t in terms}) == len(terms)
    forms = term_forms(terms, list(q), [list(v)])
    assert forms is not None
    vv = sympy.Matrix(v)
    mass = sympy.Matrix(2, 2, lambda i, j: sympy.diff(lag, v[i], v[j]))
    e = sympy.Matrix([sympy.diff(lag, s) for s in q]) - sympy.Matrix([sympy.diff(lag, s) for s in v]).jacobian(q) * vv
    lqq = sympy.Matrix(2, 2, lambda i, j: sympy.diff(lag, q[i], q[j]))
    target = -(vv.T * lqq * vv)[0] / 12 - (e.T * mass.adjugate() * e)[0] / 24
    cols = sympy.lambdify([*q, *v], forms, "numpy")
    want = sympy.lambdify([*q, *v], target, "numpy")
    points = np.random.default_rng(0).uniform(-1.5, 1.5, size=(200, 4))
    a = np.array([np.broadcast_to(np.asarray(cols(*p), dtype=float), (len(terms),)) for p in points])
    b = np.array([want(*p) for p in points])
    coef = np.linalg.lstsq(a, b, rcond=None)[0]
    assert np.abs(a @ coef - b).max() < 1e-10 * np.abs(b).max()
    assert np.abs(np.linalg.lstsq(a[:, :10], b, rcond=None)[0] @ a[:, :10].T - b).max() > 1e-2 * np.abs(b).max()


def test_discovery_gap_runs_the_double_pendulum_convergence_check(capsys):
    """``--convergence`` prints the three steps and the drift of a moved start; ``--corrections`` is refused for
    another system."""
    from benchmarks import discovery_gap

    assert discovery_gap.main(["--only", "double-pendulum", "--convergence"]) == 0
    out = capsys.readouterr().out
    assert "h = 0.1:" in out and "h = 0.025:" in out and "start moved by 1e-07 in q2" in out
    with pytest.raises(SystemExit):
        discovery_gap.main(["--only", "kepler", "--corrections"])


def test_the_coupled_exact_step_library_serves_the_double_pendulum_below_the_leapfrog_and_drops_to_the_true_terms():
    """``select``'s exact-step candidate of two components, learned on the double pendulum's training samples, serves
    the (quick) test below the leapfrog's error; learned on the variational integrator's data it keeps exactly the
    five true terms."""
    from latticedft._select import COUPLED_LIBRARY, EXACT_STEP_THRESHOLD
    from latticedft._stencil import Stencil

    system = systems.build("double-pendulum", quick=True)
    ref = np.asarray(system.test.values)
    base = systems.max_errors(system.leapfrog(system.test, system.slices), ref, system.slices)[0]
    options = {"library": f"{COUPLED_LIBRARY} + coupledstep", "at": "average", "threshold": EXACT_STEP_THRESHOLD}
    kept = {}
    for label, data in (("samples", system.train), ("variational", systems.variational_data(system))):
        model = ldft.SparseLagrangian(**options, stencil=Stencil.first_order(1))
        ldft.learn(model, data, progress=False)
        kept[label] = model.kept_terms()
        if label == "samples":
            err = systems.max_errors(discovery.served(model, system), ref, system.slices)[0]
            assert err < 0.6 * base, (err, base)
    true = {"Dtq1**2", "Dtq2**2", "cos(q1)", "cos(q2)", "cos(q1-q2)*Dtq1*Dtq2"}
    assert set(kept["variational"]) == true and len(kept["samples"]) > 5
