"""Symmetries and Noether charges of discrete Lagrangians (ldft.symmetries, ldft.noether_charges, docs/symmetries.md).

Each built-in symmetry is tested on Lagrangians whose symmetries are known; discovery must find the
rotation generator of a Kepler theory; charges of exact symmetries must be conserved along served
fields, and the ones that are not symmetries must visibly drift.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

import latticedft as ldft
from latticedft import lagrangians, systems

ROTATION = np.array([[0.0, -1.0], [1.0, 0.0]])
DOCS = Path(__file__).resolve().parents[1] / "docs"


def _by_name(reports):
    return {r.name: r for r in reports}


def _sine_gordon():
    """The explicit sine-Gordon scheme: L_d = u_t^2/2 - u_x^2/2 - (1 - cos u), forward differences, u at the anchor."""

    def fn(c, h):
        u = c[..., 0, 0]
        return 0.5 * ((c[..., 1, 0] - u) / h[0]) ** 2 - 0.5 * ((c[..., 2, 0] - u) / h[1]) ** 2 - (1.0 - torch.cos(u))

    return ldft.AnalyticLagrangian(fn, name="sine-Gordon")


def _quartic_oscillator_orbits():
    """Orbits of the isotropic quartic oscillator V = |q|^2/2 + |q|^4/4 served by its Stormer-Verlet L_d."""
    truth = lagrangians.verlet(lambda q: 0.5 * (q * q).sum(-1) + 0.25 * ((q * q).sum(-1)) ** 2)
    rng = np.random.default_rng(0)
    starts = []
    for _ in range(6):
        q0, v = rng.normal(size=2), rng.normal(size=2)
        starts.append(systems.make_field([q0, q0 + 0.1 * v], ["t"], spacing=0.1, components=["x", "y"]))
    return [r.field for r in ldft.serve(truth, starts, slices=60)]


def _periodic_breather(nt):
    """A breather moving at v = 0.3 on a periodic lattice x in [-20, 20), dx = 0.25, dt = 0.05."""
    b = systems.sine_gordon_breather(0.7, velocity=0.3, x0=-3.0, nx=161, nt=nt).isel(x=slice(0, 160))
    b["x"].attrs["periodic"] = "true"
    return b


@pytest.fixture(scope="module")
def radial_kepler():
    """A small learned radial Kepler theory (the case's model class: kinetic term + MLP potential of 1/|q|)."""
    torch.manual_seed(0)
    train = [systems.planet_orbit(p) for p in ("Venus", "Earth", "Mars")]
    model = ldft.MLPLagrangian(hidden=[16], activation="tanh", form="kinetic-potential", features="inverse-radius")
    ldft.learn(model, train, max_iter=20)
    return model, train


# -- invariance tests ---------------------------------------------------------------------------------------------
def test_builtin_names_follow_the_labels():
    orbit = systems.kepler_orbit(1.0, 1.0, n=5)
    assert [s.name for s in ldft.builtin_symmetries(orbit)] == [
        "shift-x",
        "shift-y",
        "reflection",
        "rotation-xy",
        "time-reversal",
    ]
    kg = systems.klein_gordon_training_set(n=1, steps=3)[0]
    names = [s.name for s in ldft.builtin_symmetries(kg)]
    assert names == ["shift", "reflection", "time-reversal", "translation-x", "momentum-x"]
    string = systems.wave_string([(1, 1.0)], nx=9, nt=4)  # Dirichlet: no translation, no momentum
    assert [s.name for s in ldft.builtin_symmetries(string)] == ["shift", "reflection", "time-reversal"]


def test_wave_is_shift_and_reflection_invariant():
    field = systems.wave_string([(1, 1.0), (3, 0.3)], nx=21, nt=30)
    rep = _by_name(ldft.symmetries(lagrangians.wave(), field))
    assert rep["shift"].invariant and rep["shift"].residual < 1e-14
    assert rep["reflection"].invariant and rep["reflection"].residual < 1e-14
    # the first-order stencil swaps time slices only up to a time divergence: the equations are symmetric
    assert rep["time-reversal"].verdict == "up to a null Lagrangian"
    assert rep["time-reversal"].residual > 1e-3 and rep["time-reversal"].residual_equations < 1e-13


def test_kepler_is_rotation_invariant_not_shift_invariant():
    data = [systems.planet_orbit(p) for p in ("Earth", "Mars")]
    rep = _by_name(ldft.symmetries(lagrangians.kepler(), data))
    assert rep["rotation-xy"].invariant and rep["rotation-xy"].residual < 1e-14
    assert rep["reflection"].invariant and rep["time-reversal"].invariant  # Verlet is time symmetric in 1D
    for name in ("shift-x", "shift-y"):
        assert rep[name].verdict == "broken" and rep[name].residual > 1e-3 and rep[name].residual_equations > 0.1
    d = rep["rotation-xy"].to_dict()
    assert d["generator"] == {"matrix": ROTATION.tolist(), "offset": [0.0, 0.0]} and d["invariant"] is True


def test_klein_gordon_is_not_shift_invariant_but_has_a_momentum():
    data = systems.klein_gordon_training_set(n=3, steps=10)
    rep = _by_name(ldft.symmetries(lagrangians.klein_gordon(), data))
    assert rep["shift"].verdict == "broken" and rep["shift"].residual_equations > 1e-3
    assert rep["reflection"].invariant
    assert rep["translation-x"].invariant  # every L_d of latticedft is homogeneous
    assert rep["momentum-x"].invariant and rep["momentum-x"].residual_equations < 1e-12  # quadratic L_d
    # the nonlinear on-site potential of sine-Gordon breaks the lattice pseudo-momentum
    breather = _periodic_breather(nt=12)
    rep = _by_name(ldft.symmetries(_sine_gordon(), breather, ["momentum-x"]))["momentum-x"]
    assert rep.verdict == "broken" and rep.residual_equations > 1e-4


def test_time_symmetric_polynomial_and_given_symmetries():
    train = [systems.oscillator_wells(a, n=41, dt=0.5) for a in (1.7, 1.2)]
    sym = ldft.PolynomialLagrangian(orders=(4, 6), time_symmetric=True)
    ldft.learn(sym, train)
    assert _by_name(ldft.symmetries(sym, train))["time-reversal"].invariant
    two_pi = ldft.Symmetry.linear_map([[1.0]], [2 * np.pi], name="shift by 2 pi")  # a symmetry of sine-Gordon
    field = systems.sine_gordon_breather(0.5, nx=41, nt=6)
    (rep,) = ldft.symmetries(_sine_gordon(), field, [two_pi])
    assert rep.invariant and rep.kind == "discrete"
    with pytest.raises(ldft.InputError, match="unknown 'rotation-xy'"):
        ldft.symmetries(_sine_gordon(), field, ["rotation-xy"])
    with pytest.raises(ldft.InputError, match="not periodic"):
        ldft.symmetries(_sine_gordon(), field, [ldft.Symmetry.momentum(1)])
    with pytest.raises(ldft.InputError, match="tol"):
        ldft.symmetries(_sine_gordon(), field, tol=-1.0)
    with pytest.raises(ldft.InputError, match="not bound"):
        ldft.symmetries(ldft.PolynomialLagrangian(), field)


# -- discovery ------------------------------------------------------------------------------------------------------
def test_discovery_finds_the_rotation_of_a_learned_kepler_theory(radial_kepler):
    model, train = radial_kepler
    found = ldft.discover_symmetries(model, train)
    assert len(found.symmetries) == 1 and found.best.invariant
    m, w = np.array(found.best.generator["matrix"]), np.array(found.best.generator["offset"])
    assert np.abs(m - ROTATION).max() < 1e-3 and np.abs(w).max() < 1e-3  # measured: 1e-15
    assert found.gap < 1e-6
    assert found.unknowns == ["M[0,0]", "M[0,1]", "M[1,0]", "M[1,1]", "w[0]", "w[1]"]


def test_discovery_on_a_polynomial_that_is_not_invariant_by_construction():
    orbits = _quartic_oscillator_orbits()
    model = ldft.PolynomialLagrangian(orders=(4, 4))  # holds the truth; nothing in it knows about rotations
    ldft.learn(model, orbits)
    found = ldft.discover_symmetries(model, orbits)
    m, w = np.array(found.best.generator["matrix"]), np.array(found.best.generator["offset"])
    assert np.abs(m - ROTATION).max() < 1e-8 and np.abs(w).max() < 1e-8  # measured: 1.3e-11, 2.8e-11
    assert found.best.invariant and found.gap < 1e-6
    # the shifts of the wave equation: a one-dimensional null space with w = 1
    field = systems.wave_string([(1, 1.0), (2, 0.5)], nx=15, nt=12)
    wave = ldft.discover_symmetries(lagrangians.wave(), field)
    assert len(wave.symmetries) == 1 and wave.best.generator["offset"] == [1.0]
    assert abs(wave.best.generator["matrix"][0][0]) < 1e-12


# -- charges --------------------------------------------------------------------------------------------------------
def test_angular_momentum_of_a_learned_kepler_theory_is_conserved(radial_kepler):
    model, _ = radial_kepler
    launch = systems.kepler_orbit(1.0167, 1.13, n=2)
    served = ldft.serve(model, launch, slices=300, box=10.0).field
    charge = ldft.noether_charge(model, served, "rotation-xy")
    assert charge.sizes["t"] == served.sizes["t"] - 1
    assert np.allclose(charge["t"].values, served["t"].values[1:])
    assert ldft.relative_drift(charge) < 1e-10  # measured: ~1e-14
    assert abs(float(charge[0]) - 1.0167 * 1.13) < 0.05  # ~ r v of the launch
    energy = ldft.discrete_energy(model, served)
    assert 0 < ldft.relative_drift(energy) < 0.05  # bounded oscillation, not conserved


def test_kepler_verlet_energy_oscillates_in_a_bounded_band():
    served = ldft.serve(lagrangians.kepler(), systems.kepler_orbit(1.0, 1.0, n=2), slices=400).field  # 3 periods
    energy = ldft.discrete_energy(lagrangians.kepler(), served)
    assert abs(float(energy.mean()) + 0.5) < 1e-3  # the circular orbit's E = -1/2
    first, last = (float(energy[s].max() - energy[s].min()) for s in (slice(0, 130), slice(-130, None)))
    assert ldft.relative_drift(energy) < 1e-3 and last < 1.5 * first + 1e-15  # no secular growth


def test_momentum_of_a_learned_klein_gordon_theory_is_conserved():
    train = systems.klein_gordon_training_set(n=12, steps=20)
    model = ldft.PolynomialLagrangian(orders=(2, 2))
    ldft.learn(model, train, boundary="periodic")
    x = 0.05 * np.arange(20)
    travelling = systems.klein_gordon(
        np.sin(2 * np.pi * x) + 0.3 * np.cos(6 * np.pi * x),
        np.sin(2 * np.pi * (x - 0.03)) + 0.3 * np.cos(6 * np.pi * (x - 0.03)),
        steps=1,
    )
    served = ldft.serve(model, travelling, slices=300, boundary="periodic").field
    ds = ldft.noether_charges(model, served)
    assert set(ds.data_vars) == {"J_shift", "J_momentum-x", "energy"}
    assert float(ds["J_momentum-x"].mean()) > 1.0  # a travelling wave carries momentum
    assert ldft.relative_drift(ds["J_momentum-x"]) < 1e-10  # measured: ~1e-14
    assert ldft.relative_drift(ds["energy"]) < 1e-10  # quadratic L_d: E is exact too
    # the same on an analytic L_d; and the sine-Gordon lattice does not conserve it (no exact symmetry)
    assert ldft.relative_drift(ldft.noether_charge(lagrangians.klein_gordon(), served, "momentum-x")) < 1e-10


def test_sine_gordon_lattice_momentum_drifts():
    sg = _sine_gordon()
    served = ldft.serve(sg, _periodic_breather(nt=2), slices=200, boundary="periodic").field
    momentum = ldft.noether_charge(sg, served, "momentum-x")
    assert float(momentum.mean()) > 1.0  # the breather moves to the right
    assert ldft.relative_drift(momentum) > 1e-6  # not a symmetry of the lattice


def test_rotation_charge_with_fixed_ends():
    a = systems.wave_string([(1, 1.0), (2, 0.4)], nx=17, nt=40)
    b = systems.wave_string([(2, 0.7), (3, 0.2)], nx=17, nt=40)
    field = systems.make_field(
        np.stack([a.values, b.values], -1), ["t", "x"], spacing=(float(a.t[1]), float(a.x[1])), components=["u", "v"]
    )
    wave = lagrangians.wave()
    served = ldft.serve(wave, field).field  # Dirichlet: the strips are the data's
    assert ldft.relative_drift(ldft.noether_charge(wave, served, "rotation-uv")) < 1e-12  # xi = 0 at fixed ends
    assert ldft.relative_drift(ldft.noether_charge(wave, served, "shift-u")) > 1e-3  # xi = 1 at the ends


def test_charge_errors():
    orbit = systems.kepler_orbit(1.0, 1.0, n=20)
    with pytest.raises(ldft.InputError, match="no Noether charge"):
        ldft.noether_charge(lagrangians.kepler(), orbit, "reflection")
    with pytest.raises(ldft.InputError, match="unknown 'momentum-x'"):
        ldft.noether_charge(lagrangians.kepler(), orbit, "momentum-x")
    with pytest.raises(ldft.InputError, match="components"):
        ldft.noether_charge(lagrangians.kepler(), orbit, ldft.Symmetry.rotation(0, 1, 3))
    radial = ldft.MLPLagrangian(hidden=[4], form="kinetic-potential", features="inverse-radius")
    ldft.learn(radial, orbit, max_iter=1)
    with pytest.raises(ldft.InputError, match="spacing"):
        ldft.noether_charge(radial, systems.kepler_orbit(1.0, 1.0, dt=0.1, n=20), "rotation-xy")
    ds = ldft.noether_charges(lagrangians.kepler(), orbit, ["rotation-xy", "energy"])
    assert set(ds.data_vars) == {"J_rotation-xy", "energy"} and ds["energy"].attrs["scale"] > 0


# docs/symmetries.md's examples run in tests/test_docs.py, with every other page.
