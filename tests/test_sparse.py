"""Sparse, symbolic L_d: term libraries, the sparse fit, the equation it prints, model files, bad inputs."""

from __future__ import annotations

import math

import numpy as np
import pytest
import sympy
import torch
import xarray as xr
from scipy.integrate import solve_ivp

import latticedft as ldft
from latticedft import Library, systems
from latticedft._lattice import gather_cells
from latticedft._models._terms import term_forms, term_values
from latticedft._select import COUPLED_LIBRARY, sparse_candidates


def _ode(rhs, y0, n: int, dt: float) -> np.ndarray:
    t = np.arange(n) * dt
    sol = solve_ivp(lambda _, y: rhs(y), (0, t[-1]), y0, t_eval=t, rtol=1e-12, atol=1e-12, method="DOP853")
    return sol.y


def pendulum(a: float, n: int = 80, dt: float = 0.1) -> xr.DataArray:
    q = _ode(lambda y: [y[1], -np.sin(y[0])], [a, 0.0], n, dt)[0]
    return xr.DataArray(q, dims="t", coords={"t": np.arange(n) * dt}, name="psi")


def kepler_one_orbit(gm: float = 0.40038, n: int = 51, dt: float = 0.1, q0=(1.0, 0.0), v0=(0.0, 0.6)):
    def rhs(y):
        r3 = np.hypot(y[0], y[1]) ** 3
        return [y[2], y[3], -gm * y[0] / r3, -gm * y[1] / r3]

    y = _ode(rhs, [*q0, *v0], n, dt)
    t = np.arange(n) * dt
    return xr.DataArray(y[:2].T, dims=("t", "component"), coords={"t": t, "component": ["x", "y"]}, name="q")


def klein_gordon_string(amplitude: float, nx: int = 41, nt: int = 60, lam: float = 0.3) -> xr.DataArray:
    """psi_tt = psi_xx - psi - lam psi^3 with fixed ends, by leapfrog at a fine step, sampled."""
    dx, dt, sub = 0.1, 0.05, 10
    x = np.arange(nx) * dx
    psi = amplitude * np.sin(np.pi * x / x[-1])
    h = dt / sub
    prev = psi.copy()
    frames = [psi.copy()]
    for i in range((nt - 1) * sub):
        lap = np.zeros_like(psi)
        lap[1:-1] = (psi[2:] - 2 * psi[1:-1] + psi[:-2]) / dx**2
        acc = lap - psi - lam * psi**3
        acc[[0, -1]] = 0.0
        new = psi + h * (psi - prev) / h + h**2 * acc if i else psi + 0.5 * h**2 * acc
        prev, psi = psi, new
        if (i + 1) % sub == 0:
            frames.append(psi.copy())
    return xr.DataArray(
        np.array(frames),
        dims=("t", "x"),
        coords={"t": np.arange(nt) * dt, "x": x},
        name="psi",
    )


def kept(model: ldft.SparseLagrangian) -> dict[str, float]:
    return {name: c for name, c in zip(model.term_names, model.coef.tolist()) if c != 0.0}


# -- libraries ---------------------------------------------------------------------------------------------
def test_library_union_products_and_shorthands():
    lib = Library.parse("kinetic") + Library.parse("poly:2") * "kinetic" + "trig:1"
    assert [t.name for t in lib.expand(1, 1)] == ["Dtq**2", "q*Dtq**2", "q**2*Dtq**2", "sin(q)", "cos(q)"]
    assert Library.parse("kinetic + poly:2*kinetic + trig:1").labels == lib.labels
    names = [t.name for t in Library.parse("kinetic + norm:-1,2 + log + cross + cosdiff*velocities").expand(1, 2)]
    assert names[:5] == ["(Dtq1**2+Dtq2**2)", "|q|**-1", "|q|**2", "log|q|", "(q1*Dtq2-q2*Dtq1)"]
    assert "cos(q1-q2)*Dtq1*Dtq2" in names
    assert [t.name for t in Library.parse("gradient").expand(3, 1)] == ["Dxq**2", "Dyq**2"]
    # trig of another family's terms: cos(q^2 - 1) = cos(1) cos(q^2) + sin(1) sin(q^2)
    names = [t.name for t in Library.parse("kinetic + trig:1(poly:2)").expand(1, 1)]
    assert names == ["Dtq**2", "sin(q)", "cos(q)", "sin(q**2)", "cos(q**2)"]


def test_trig_and_exp_of_a_power_of_each_component():
    names = [t.name for t in Library.parse("trig:2@2 + exp@3 + exp:0.5@2 + trig:1:0.5@3").expand(1, 1)]
    assert names == [
        "sin(q**2)",
        "cos(q**2)",
        "sin(2*q**2)",
        "cos(2*q**2)",
        "exp(q**3)",
        "exp(0.5*q**2)",
        "sin(0.5*q**3)",
        "cos(0.5*q**3)",
    ]
    assert [t.name for t in Library.parse("trig:1@2").expand(2, 2)] == [
        "sin(q1**2)",
        "cos(q1**2)",
        "sin(q2**2)",
        "cos(q2**2)",
    ]
    assert [t.name for t in Library.parse("trig:1@1 + exp@1").expand(1, 1)] == ["sin(q)", "cos(q)", "exp(q)"]


def test_trig_of_a_power_has_the_values_of_its_closed_form():
    terms = Library.parse("trig:2:0.5@2 + exp:0.5@3 + kinetic*trig:1@2").expand(1, 2)
    z = torch.rand(5, 2, 2, dtype=torch.float64, generator=torch.Generator().manual_seed(3)) - 0.5
    got = term_values(terms, z, [0.1]).numpy()
    q1, q2, v1 = z[:, 0, 0].numpy(), z[:, 0, 1].numpy(), z[:, 1, 0].numpy() / 0.1
    v2 = z[:, 1, 1].numpy() / 0.1
    names = [t.name for t in terms]
    np.testing.assert_allclose(got[:, names.index("sin(0.5*q1**2)")], np.sin(0.5 * q1**2), rtol=1e-15)
    np.testing.assert_allclose(got[:, names.index("cos(q2**2)")], np.cos(q2**2), rtol=1e-15)
    np.testing.assert_allclose(got[:, names.index("exp(0.5*q2**3)")], np.exp(0.5 * q2**3), rtol=1e-15)
    kinetic_sin = names.index("(Dtq1**2+Dtq2**2)*sin(q1**2)")
    np.testing.assert_allclose(got[:, kinetic_sin], (v1**2 + v2**2) * np.sin(q1**2), rtol=1e-13)
    u = sympy.Symbol("u", real=True)
    forms = term_forms(terms, [u, u], [[u, u]])
    assert forms is not None and forms[names.index("cos(q2**2)")] == sympy.cos(u**2)


@pytest.mark.parametrize(
    ("spec", "n", "m", "words"),
    [
        ("", 1, 1, "is empty"),
        ([], 1, 1, "is empty"),
        ("kinetic + + poly:2", 1, 1, "empty term"),
        ("wobble", 1, 1, "unknown term 'wobble'"),
        ("norm:-1", 1, 1, "needs a vector field"),
        ("cross", 1, 3, "needs a field of 2 components"),
        ("gradient", 1, 1, "needs a space axis"),
        ("norm:0", 1, 2, "power 0"),
        ("trig:1(wobble)", 1, 1, "unknown term 'wobble'"),
        ("trig:0(poly:2)", 1, 1, "K >= 1"),
        ("trig:1@0", 1, 1, "power P >= 1 after '@' in 'trig:1@0'"),
        ("exp:0.5@0", 1, 1, "power P >= 1 after '@' in 'exp:0.5@0'"),
        ("trig:1@x", 1, 1, "expected trig:K\\[:w\\]@P or exp\\[:w\\]@P .* got 'trig:1@x'"),
        ("exp@-2", 1, 1, "got 'exp@-2'"),
        ("trig:1(poly:2)@2", 1, 1, "got 'trig:1\\(poly:2\\)@2'"),
        ("trig:0@2", 1, 1, "K >= 1"),
        ("trig:1:0@2", 1, 1, "positive frequency"),
    ],
)
def test_library_bad_inputs_name_the_key(spec, n, m, words):
    with pytest.raises(ldft.InputError, match=words) as info:
        Library.parse(spec).expand(n, m)
    assert info.value.key == "library" and "\n" not in str(info.value)


def test_model_option_errors_name_the_key():
    with pytest.raises(ldft.InputError) as info:
        ldft.SparseLagrangian("kinetic", threshold=2.0)
    assert info.value.key == "threshold"
    with pytest.raises(ldft.InputError) as info:
        ldft.SparseLagrangian("kinetic", bags=-1)
    assert info.value.key == "bags"
    with pytest.raises(ldft.InputError) as info:  # a vector term on a scalar field, found when learning binds
        ldft.learn(ldft.SparseLagrangian("kinetic + norm:-1"), pendulum(1.0, 20), progress=False)
    assert info.value.key == "library"


@pytest.mark.parametrize(("at", "shift"), [("anchor", 0.0), ("mean", 0.5)])
def test_a_term_undefined_on_the_data_is_named(at, shift):
    # a straight line through the origin: one site (anchor) or one cell's mean is q = 0, where |q|^-1 and
    # log|q| are undefined
    x = np.arange(-10, 10) + shift
    q = xr.DataArray(
        np.stack([x, 0 * x], 1),
        dims=("t", "component"),
        coords={"t": np.arange(20) * 0.1, "component": ["x", "y"]},
        name="q",
    )
    for term in ("norm:-1", "log"):
        with pytest.raises(ldft.InputError, match="not finite on the training data") as info:
            ldft.learn(ldft.SparseLagrangian(f"kinetic + {term}", bags=0, at=at), q, progress=False)
        assert info.value.key == "library"


# -- recovery ----------------------------------------------------------------------------------------------
def test_pendulum_terms_are_found_and_serve_beyond_the_training_range():
    model = ldft.SparseLagrangian("kinetic + poly:2 + trig:1")
    ldft.learn(model, [pendulum(2.0), pendulum(2.6)], progress=False)
    terms = kept(model)
    assert set(terms) == {"Dtq**2", "cos(q)"}
    assert terms["cos(q)"] / (2 * terms["Dtq**2"]) == pytest.approx(1.0, rel=1e-3)
    assert model.inclusion.tolist()[model.term_names.index("cos(q)")] == 1.0
    assert model.report_.sparse["kept"] == ["Dtq**2", "cos(q)"]
    test = pendulum(2.9, 60)
    served = ldft.serve(model, test, progress=False).field.values
    assert np.max(np.abs(served - test.values)) < 0.05


def test_kepler_from_one_orbit():
    # the default vector library; "auto" would keep small terms that absorb the midpoint rule's O(h^2) error
    model = ldft.SparseLagrangian(threshold=1e-2)
    ldft.learn(model, kepler_one_orbit(), progress=False)
    terms = kept(model)
    assert set(terms) == {"(Dtq1**2+Dtq2**2)", "|q|**-1"}
    assert terms["|q|**-1"] / (2 * terms["(Dtq1**2+Dtq2**2)"]) == pytest.approx(0.40038, rel=2e-3)


def test_charged_particle_magnetic_term():
    # one circle is also an isotropic oscillator about its centre: two orbits of other centres tell them apart
    q = [
        systems.charged_particle(q0=(0.0, 0.0), v0=(1.0, 0.5), B=0.8, n=60, dt=0.1),
        systems.charged_particle(q0=(1.0, -1.0), v0=(-0.3, 0.8), B=0.8, n=60, dt=0.1),
    ]
    model = ldft.SparseLagrangian("kinetic + poly:2 + cross")
    ldft.learn(model, q, progress=False)
    terms = kept(model)
    assert set(terms) == {"(Dtq1**2+Dtq2**2)", "(q1*Dtq2-q2*Dtq1)"}
    assert terms["(q1*Dtq2-q2*Dtq1)"] / (2 * terms["(Dtq1**2+Dtq2**2)"]) == pytest.approx(0.4, rel=1e-2)
    # the gauge is chosen on the dense fits of the library, before the support: unit-mass cannot hold q x Dq
    assert model.report_.gauge == "trace" and "dense fits of the library" in model.report_.gauge_choice


def test_nonlinear_klein_gordon_string():
    data = [klein_gordon_string(a) for a in (0.6, 1.1)]
    model = ldft.SparseLagrangian("kinetic + gradient + poly:4")
    ldft.learn(model, data, progress=False)
    terms = kept(model)
    assert set(terms) == {"Dtq**2", "Dxq**2", "q**2", "q**4"}
    k = 2 * terms["Dtq**2"]
    assert -2 * terms["Dxq**2"] / k == pytest.approx(1.0, rel=2e-2)
    assert -2 * terms["q**2"] / k == pytest.approx(1.0, rel=2e-2)
    assert -4 * terms["q**4"] / k == pytest.approx(0.3, rel=2e-2)


# -- the equation ------------------------------------------------------------------------------------------
def _cells(model, field):
    lf = ldft.as_lattice_field(field)
    return gather_cells(torch.as_tensor(lf.values), model.stencil, lf.boundary).reshape(-1, model.stencil.size, model.m)


def test_symbolic_matches_the_model_to_round_off():
    data = [klein_gordon_string(0.8, nx=11, nt=12)]
    for model in (
        ldft.SparseLagrangian("kinetic + gradient + poly:4 + trig:1", threshold=0.0, bags=0),
        ldft.SparseLagrangian("kinetic + gradient + poly:2*gradient + exp + trig:1", threshold=0.0, at="mean"),
        ldft.SparseLagrangian(
            "kinetic + poly:2*kinetic + gradient + trig:1(poly:2)", threshold=0.0, bags=0, at="average"
        ),
        ldft.SparseLagrangian("kinetic + gradient + trig:2@2 + exp:0.5@2 + kinetic*trig:1@3", threshold=0.0, bags=0),
        ldft.FeatureLagrangian(["poly:3", "trig:1"], differences=2),
    ):
        ldft.learn(model, data, progress=False)
        form = model.symbolic()
        cells = _cells(model, data[0])[:7]
        expected = model(cells).detach().numpy()
        got = [form.evaluate(c.tolist()) for c in cells]
        np.testing.assert_allclose(got, expected, rtol=1e-10, atol=1e-10 * np.abs(expected).max())


def test_print_shows_the_equation_and_the_del():
    model = ldft.SparseLagrangian("kinetic + trig:1", bags=4)
    ldft.learn(model, [pendulum(2.0), pendulum(2.6)], progress=False)
    text = str(model)
    assert "L_d = 0.5" in text and "cos(q)" in text and "LaTeX:" in text and "DEL:" in text
    assert "q[t+1]" in text and "inclusion 1.00" in text
    assert model.equation_text()["latex"].startswith("0.5")


def test_a_trig_of_a_power_prints_in_closed_form():
    model = ldft.SparseLagrangian("kinetic + poly:1 + trig:1@2", threshold=0.0, bags=0)
    model.bind(1, 1, (1.0,))
    with torch.no_grad():
        model.coef.copy_(torch.tensor([0.5, 0.003, 0.0126, 0.0081], dtype=torch.float64))
    text = model.equation_text()
    assert "sin(q**2)" in text["L_d"] and "cos(q**2)" in text["L_d"]
    assert r"\sin{\left(q^{2} \right)}" in text["latex"]
    u0 = sympy.Symbol("u0_0", real=True)
    assert model.to_sympy().has(sympy.sin(u0**2))


def test_model_file_round_trip(tmp_path):
    model = ldft.SparseLagrangian("kinetic + trig:1")
    ldft.learn(model, [pendulum(2.0), pendulum(2.6)], progress=False)
    path = ldft.save_model(model, tmp_path / "m.pt")
    back = ldft.load_model(path)
    assert isinstance(back, ldft.SparseLagrangian) and back.options() == model.options()
    assert torch.equal(back.coef, model.coef) and torch.equal(back.inclusion, model.inclusion)
    assert str(back.to_sympy()) == str(model.to_sympy())


def test_a_user_function_is_a_term_but_not_saveable(tmp_path):
    lib = Library.parse("kinetic") + Library.function(lambda q: 1 - torch.cos(q[..., 0]), "1-cos(q)")
    model = ldft.SparseLagrangian(lib)
    ldft.learn(model, [pendulum(2.0), pendulum(2.6)], progress=False)
    assert set(kept(model)) == {"Dtq**2", "1-cos(q)"}
    assert model.symbolic() is None
    with pytest.raises(ldft.ModelFileError, match="Python functions"):
        ldft.save_model(model, tmp_path / "m.pt")


def sine_gordon_2d(amplitude: float, n: int = 10, nt: int = 16, h: float = 0.5, dt: float = 0.2) -> xr.DataArray:
    """psi_tt = psi_xx + psi_yy - sin psi on a periodic n x n lattice, by the leapfrog at the sampled step."""
    x = np.arange(n) * h
    xx, yy = np.meshgrid(x, x, indexing="ij")
    psi = amplitude * np.cos(2 * np.pi * xx / (n * h)) * np.sin(2 * np.pi * yy / (n * h)) + 0.3
    frames = [psi, psi]
    for _ in range(nt - 2):
        p = frames[-1]
        lap = sum(np.roll(p, s, a) for s in (1, -1) for a in (0, 1)) - 4 * p
        frames.append(2 * p - frames[-2] + dt**2 * (lap / h**2 - np.sin(p)))
    coords = {"t": np.arange(nt) * dt, "x": x, "y": x}
    da = xr.DataArray(np.array(frames), dims=("t", "x", "y"), coords=coords, name="psi")
    for axis in ("x", "y"):
        da[axis].attrs["periodic"] = 1
    return da


def test_sine_gordon_2d_is_exact_when_the_data_obey_the_leapfrog():
    model = ldft.SparseLagrangian("kinetic + gradient + poly:2 + trig:1")
    report = ldft.learn(model, [sine_gordon_2d(0.8), sine_gordon_2d(1.5)], progress=False)
    terms = kept(model)
    assert set(terms) == {"Dtq**2", "Dxq**2", "Dyq**2", "cos(q)"}
    assert report.rel_res < 1e-10
    for name, value in (("Dxq**2", -0.5), ("Dyq**2", -0.5), ("cos(q)", 1.0)):
        assert terms[name] == pytest.approx(value, rel=1e-9)


def test_sine_gordon_breather_1d():
    data = [systems.sine_gordon_breather(w, nx=81, nt=40, xlim=(-10.0, 10.0), dt=0.1) for w in (0.5, 0.8)]
    model = ldft.SparseLagrangian("kinetic + gradient + poly:2 + trig:1", threshold=1e-2)
    ldft.learn(model, data, progress=False)
    terms = kept(model)
    assert set(terms) == {"Dtq**2", "Dxq**2", "cos(q)"}
    assert -2 * terms["Dxq**2"] == pytest.approx(1.0, rel=1e-2)
    assert terms["cos(q)"] == pytest.approx(1.0, rel=1e-2)


@pytest.mark.parametrize(("sigma", "rel"), [(1e-3, 2e-3), (1e-2, 5e-2)])
def test_noisy_pendulum_terms_with_noise_auto(sigma, rel):
    rng = np.random.default_rng(1)
    noisy = [p + sigma * 2.6 * rng.standard_normal(p.shape) for p in (pendulum(2.0, 120), pendulum(2.6, 120))]
    model = ldft.SparseLagrangian("kinetic + poly:2 + trig:1")
    report = ldft.learn(model, noisy, noise="auto", progress=False)
    assert report.noise["method"] != "none"
    terms = kept(model)
    assert set(terms) == {"Dtq**2", "cos(q)"}
    assert terms["cos(q)"] / (2 * terms["Dtq**2"]) == pytest.approx(1.0, rel=rel)


def double_pendulum(y0, n: int = 150, dt: float = 0.05) -> xr.DataArray:
    """Two unit masses on unit rods, g = 1: L = q1'^2 + q2'^2/2 + q1' q2' cos(q1 - q2) + 2 cos q1 + cos q2."""

    def rhs(y):
        t1, t2, w1, w2 = y
        d = t1 - t2
        den = 3 - np.cos(2 * d)
        a1 = (-3 * np.sin(t1) - np.sin(t1 - 2 * t2) - 2 * np.sin(d) * (w2**2 + w1**2 * np.cos(d))) / den
        a2 = 2 * np.sin(d) * (2 * w1**2 + 2 * np.cos(t1) + w2**2 * np.cos(d)) / den
        return [w1, w2, a1, a2]

    y = _ode(rhs, y0, n, dt)
    coords = {"t": np.arange(n) * dt, "component": ["a", "b"]}
    return xr.DataArray(y[:2].T, dims=("t", "component"), coords=coords, name="theta")


def test_double_pendulum_with_the_trace_gauge():
    data = [double_pendulum([0.8, -0.5, 0.0, 0.0]), double_pendulum([0.3, 1.0, 0.5, 0.0])]
    model = ldft.SparseLagrangian("velocities + cosdiff*velocities + trig:1")
    ldft.learn(model, data, gauge="trace", progress=False)  # unequal masses: unit-mass cannot hold
    terms = kept(model)
    assert set(terms) == {"Dtq1**2", "Dtq2**2", "cos(q1-q2)*Dtq1*Dtq2", "cos(q1)", "cos(q2)"}
    a = terms["Dtq1**2"]
    for name, ratio in (("Dtq2**2", 0.5), ("cos(q1-q2)*Dtq1*Dtq2", 1.0), ("cos(q1)", 2.0), ("cos(q2)", 1.0)):
        assert terms[name] / a == pytest.approx(ratio, rel=1e-2)


def test_double_pendulum_at_both_ends_of_the_step_with_the_gauge_auto():
    # the trapezoid rule (at = "average") meets a mass cos(q1 - q2) that depends on the positions; the gauge is
    # chosen on the dense fits of the library (unequal masses: trace)
    data = [double_pendulum([0.8, -0.5, 0.0, 0.0], n=60), double_pendulum([0.3, 1.0, 0.5, 0.0], n=60)]
    model = ldft.SparseLagrangian(COUPLED_LIBRARY, threshold=0.1, bags=0, at="average")
    ldft.learn(model, data, progress=False)
    assert model.report_.gauge == "trace" and "dense fits of the library" in model.report_.gauge_choice
    terms = kept(model)
    assert set(terms) == {"Dtq1**2", "Dtq2**2", "cos(q1-q2)*Dtq1*Dtq2", "cos(q1)", "cos(q2)"}
    a = terms["Dtq1**2"]
    for name, ratio in (("Dtq2**2", 0.5), ("cos(q1-q2)*Dtq1*Dtq2", 1.0), ("cos(q1)", 2.0), ("cos(q2)", 1.0)):
        assert terms[name] / a == pytest.approx(ratio, rel=1e-2)
    form = model.symbolic()  # the average of the terms at both ends of the step
    cells = _cells(model, data[0])[:5]
    expected = model(cells).detach().numpy()
    np.testing.assert_allclose([form.evaluate(c.tolist()) for c in cells], expected, rtol=1e-12)


# -- threshold = "auto" by held-out serving ----------------------------------------------------------------
@pytest.mark.parametrize(
    ("library", "data", "true"),
    [
        ("auto", lambda: kepler_one_orbit(), {"(Dtq1**2+Dtq2**2)", "|q|**-1"}),
        ("kinetic + trig:1", lambda: [pendulum(2.0), pendulum(2.6)], {"Dtq**2", "cos(q)"}),
        (
            "kinetic + gradient + poly:4",
            lambda: [klein_gordon_string(a) for a in (0.6, 1.1)],
            {"Dtq**2", "Dxq**2", "q**2", "q**4"},
        ),
    ],
    ids=["kepler-one-orbit", "pendulum", "klein-gordon"],
)
def test_threshold_auto_finds_the_true_terms_alone_on_clean_data(library, data, true):
    # held-out serving: extra terms absorbing the lattice's truncation error serve no better than SERVE_FLOOR
    model = ldft.SparseLagrangian(library, bags=0)
    report = ldft.learn(model, data(), progress=False)
    assert set(kept(model)) == true
    assert report.validation  # the served error of each support tried


def test_held_out_serving_stops_early_and_chooses_as_serving_whole(monkeypatch):
    # serving each support only as far as the rule needs keeps its choice (the sparsest within SERVE_FLOOR, or
    # else within SERVE_SLACK of the best) and serves fewer slices
    from latticedft._learn import _heldout, _sparse

    data = [pendulum(2.6, n=30)]
    served = []
    by_window = _heldout.WindowServing.__call__

    def counting(self, f, derivatives):
        served.append(f.shape[0] - 2)
        return by_window(self, f, derivatives)

    monkeypatch.setattr(_heldout.WindowServing, "__call__", counting)  # how 1D tails are served
    whole = _heldout.SupportServing.advance
    for floor in (_sparse.SERVE_FLOOR, 0.0):  # 0: no support within the floor, the best decides
        monkeypatch.setattr(_sparse, "SERVE_FLOOR", floor)
        coefs, counts = [], []
        for bounded in (True, False):
            advance = whole if bounded else (lambda self, model, bound: whole(self, model, math.inf))
            monkeypatch.setattr(_heldout.SupportServing, "advance", advance)
            served.clear()
            model = ldft.SparseLagrangian("kinetic + poly:2 + trig:1", bags=0)
            ldft.learn(model, data, progress=False)
            coefs.append(model.coef.clone())
            counts.append(sum(served))
        assert torch.equal(coefs[0], coefs[1])
        assert counts[0] < counts[1]


def test_held_out_serving_in_chunks_matches_serving_whole():
    from latticedft._learn._heldout import SupportServing, held_out_score

    model = ldft.SparseLagrangian("kinetic + trig:1", bags=0)
    ldft.learn(model, [pendulum(2.0), pendulum(2.6)], progress=False)
    tails = [pendulum(a).isel(t=slice(50, None)) for a in (2.0, 2.9)]
    run = SupportServing(model.coef.detach().numpy().copy(), tails, None)
    assert run.advance(model, math.inf) == pytest.approx(held_out_score(model, tails, None), rel=1e-8)
    assert run.finished


@pytest.mark.parametrize(
    "library, data",
    [("kinetic + poly:2 + trig:1", lambda: [pendulum(2.0), pendulum(2.6)]), (None, lambda: [kepler_one_orbit()])],
    ids=["scalar", "vector"],
)
def test_held_out_serving_without_results_equals_the_public_serve(monkeypatch, library, data):
    # 1D tails are served by the numpy loop without serve's results (training range, DataArrays, warnings):
    # the held-out errors are those of serving each chunk by the public serve, to round-off (each chunk's first
    # gradient from the numpy closed forms, the public serve's from torch's; the errors are relative to the
    # tail's scale, so 1e-12 here is 1e-12 of the field); a support whose serving stops (no kinetic term: a
    # singular mixed Hessian) scores inf on both
    from latticedft._learn import _heldout

    model = ldft.SparseLagrangian(*[library] if library else [], bags=0, threshold=1e-2)
    fields = data()
    ldft.learn(model, fields, progress=False)
    theta = model.coef.detach().numpy().copy()
    smallest = np.where(theta != 0, np.abs(theta), np.inf).argmin()
    kinetic = [k for k, name in enumerate(model.kept_terms()) if name.startswith(("Dtq", "(Dtq"))]
    supports = [theta, np.where(np.arange(theta.size) == smallest, 0.0, theta), theta.copy()]
    supports[2][np.flatnonzero(theta)[kinetic]] = 0.0
    tails = [f.isel(t=slice(f.sizes["t"] // 3, None)) for f in fields]
    errors = []
    for public in (False, True):
        if public:
            monkeypatch.setattr(_heldout.SupportServing, "_numpy_forms", lambda self, model: None)
        runs = [_heldout.SupportServing(s, tails, None) for s in supports]
        errors.append([run.advance(model, math.inf) for run in runs])
        assert all(run.finished and (run._forms is None) == public for run in runs)
    assert [math.isfinite(e) for e in errors[0]] == [math.isfinite(e) for e in errors[1]]
    assert all(a == b or abs(a - b) <= 1e-12 for a, b in zip(*errors))
    assert math.isfinite(errors[0][0]) and errors[0][0] < errors[0][1] and errors[0][2] == math.inf


@pytest.mark.parametrize("library", ["kinetic + poly:2 + trig:1", None], ids=["scalar", "vector"])
def test_a_restarted_window_batch_serves_as_a_new_one(library):
    # the held-out serving restarts one batch on every window (other supports' coefficients, longer and shorter
    # windows, a support whose serving stops): the same values, to the bit, and the same failures as a new batch
    from latticedft._lattice import as_lattice_fields
    from latticedft._serve._fast1d import FastBatch, numpy_derivatives_of, step_fast
    from latticedft._serve._onedim import WindowServing
    from latticedft._serve._options import ServeOptions

    model = ldft.SparseLagrangian(*[library] if library else [], bags=0, threshold=1e-2)
    fields = [pendulum(2.0), pendulum(2.6)] if library else [kepler_one_orbit()]
    ldft.learn(model, fields, progress=False)
    theta = model.coef.detach().clone()
    no_kinetic = theta.clone()
    no_kinetic[[k for k, t in enumerate(model.terms) if t.name.startswith(("Dtq", "(Dtq"))]] = 0.0
    windows = as_lattice_fields(
        [f.isel(t=slice(i0, i0 + n)) for f in fields for i0, n in ((0, 6), (3, 18), (10, 3), (20, 10))],
        ["f"] * (4 * len(fields)),
        min_slices=2,
    )
    options = ServeOptions.from_keywords(None, progress=False)
    window = WindowServing(model, options)
    outcomes = []
    for coef in (theta, no_kinetic, 0.5 * theta, theta):
        with torch.no_grad():
            model.coef.copy_(coef)
        forms = numpy_derivatives_of(model)
        for f in windows:
            fresh_batch = FastBatch(model, [f], [f.shape[0]], forms, options.mode, False, numpy_first=True)
            step_fast(fresh_batch, options.rtol, options.max_newton, options.box)
            fresh, fresh_failed = fresh_batch.npsi[0, : fresh_batch.nlength[0]], fresh_batch.failed[0]
            again, failed = window(f, forms)
            assert failed == fresh_failed and np.array_equal(again, fresh, equal_nan=True)
            outcomes.append(failed)
    assert any(outcomes) and not all(outcomes)


@pytest.mark.parametrize(
    "gauge",
    [
        ([[-2.0, 0.0, 0.0, 0.0, 0.0, 0.0]], [-1.0]),  # unit mass: zero columns but one
        ([[1.0, 0.0, 2.0, 2.0, 0.0, 1.0], [0.0, 3.0, 1.0, 1.0, 0.0, 0.0]], [1.0, 2.0]),  # repeated columns
    ],
    ids=["one-row", "two-rows"],
)
def test_gauge_parts_kept_by_their_columns_equal_each_supports_own(gauge):
    # the feasibility test and the gauge's split are kept by the gauge rows' columns on a support (supports
    # whose columns hold the same numbers share them): every support's fit and feasibility as computed for it
    from itertools import product

    from latticedft._learn._exact import _gauge_split, _null_solve
    from latticedft._learn._sparse import _Constraint, _feasible

    g = (np.array(gauge[0]), np.array(gauge[1]))
    t = np.random.default_rng(3).normal(size=(9, 6))
    con = _Constraint(g)
    for bits in product([False, True], repeat=6):
        keep = np.array(bits)
        assert con.feasible(keep) == _feasible(g, keep)
        if not con.feasible(keep):
            continue
        split = _gauge_split(g[0][:, keep], g[1])
        if split is None:
            continue
        own = np.zeros(6)
        own[keep] = _null_solve(t[:, keep], *split, 0.0)
        assert np.array_equal(con.fit(t, keep, 0.0), own)
    shared = len(con._columns) - len(con._split)
    assert shared > 0  # some supports met a split computed for another


def test_held_out_tails_as_lattice_fields_and_dataarrays(monkeypatch):
    # the tails' lattice fields are the fields sliced, as the DataArrays' (made only where serve needs them)
    # read back; 1D tails are served from the lattice fields, without making a DataArray
    from latticedft._lattice import as_lattice_fields
    from latticedft._learn import _heldout

    fields = as_lattice_fields([pendulum(2.0), kepler_one_orbit()], ["a", "b"])
    tails = _heldout.Tails(fields, [30, 40])
    back = as_lattice_fields(list(tails), ["a", "b"], min_slices=2)
    for got, want in zip(tails.fields(), back):
        assert torch.equal(got.values, want.values) and got.dims == want.dims and got.boundary == want.boundary
        assert all(np.array_equal(got.coords[d], want.coords[d]) for d in want.coords)

    def no_arrays(self, i):
        raise AssertionError("a DataArray made for a 1D tail")

    monkeypatch.setattr(_heldout.Tails, "__getitem__", no_arrays)
    model = ldft.SparseLagrangian("kinetic + poly:2 + trig:1", bags=0)
    report = ldft.learn(model, [pendulum(2.0), pendulum(2.6)], progress=False)
    assert report.validation


def test_only_the_kept_model_prints_its_equation():
    data = [pendulum(2.0, 40), pendulum(2.6, 40)]
    sel = ldft.select(ldft.PolynomialLagrangian((2, 2)), data, sparse_candidates(1, 1)[:2], progress=False)
    assert all(t.report_._equation is not None for t in sel.trials if isinstance(t, ldft.SparseLagrangian))
    report = sel.model.report_
    assert "cos(q)" in report.sparse["equation"]["L_d"] and report._equation is None
    assert "cos" in report.to_dict()["sparse"]["equation"]["latex"]


def test_a_report_prints_the_equation_learned_even_after_the_model_changes():
    model = ldft.SparseLagrangian("kinetic + poly:2 + trig:1")
    ldft.learn(model, pendulum(2.0, 40), progress=False)
    text = model.equation_text()
    with torch.no_grad():
        model.coef.mul_(2.0)
    assert model.report_.sparse["equation"] == text != model.equation_text()


# -- serving by the numpy closed forms ------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("library", "at", "data"),
    [
        ("kinetic + poly:2 + trig:1", "average", lambda: [pendulum(2.0, 60), pendulum(2.6, 60)]),
        ("velocities + cosdiff*velocities + trig:1", "average", lambda: [double_pendulum([0.8, -0.5, 0.0, 0.0], 60)]),
        ("kinetic + poly:2 + cross", "anchor", lambda: [systems.charged_particle(q0=(0.0, 0.0), v0=(1.0, 0.5), n=60)]),
        ("kinetic + norm:-1 + exp:0.5", "mean", lambda: [kepler_one_orbit()]),
    ],
)
def test_numpy_loop_serves_a_sparse_model_as_the_torch_loop(library, at, data, monkeypatch):
    from latticedft._serve._fast1d import numpy_derivatives_of

    fields = data()
    model = ldft.SparseLagrangian(library, at=at, threshold=0.0, bags=0)
    ldft.learn(model, fields, gauge="trace", progress=False)
    assert numpy_derivatives_of(model) is not None  # served by the numpy loop
    fast = ldft.serve(model, fields[0], progress=False)
    monkeypatch.setattr(ldft.SparseLagrangian, "numpy_derivatives", lambda self, pairs: None)
    assert numpy_derivatives_of(model) is None  # served by the torch loop
    slow = ldft.serve(model, fields[0], progress=False)
    assert fast.complete and slow.complete
    assert fast.newton_iterations == slow.newton_iterations
    scale = np.abs(slow.field.values).max()
    np.testing.assert_allclose(fast.field.values, slow.field.values, rtol=0, atol=1e-12 * scale)


@pytest.mark.parametrize("library", ["kinetic + poly:2 + trig:1", None], ids=["scalar", "vector"])
def test_numpy_first_gradient_equals_torch(library):
    # the held-out serving's batches take each member's first gradient from the numpy closed forms: what the
    # torch closed forms give, to round-off
    from latticedft._lattice import as_lattice_fields
    from latticedft._serve._fast1d import FastBatch, numpy_derivatives_of

    model = ldft.SparseLagrangian(*[library] if library else [], bags=0, threshold=1e-2)
    fields = [pendulum(2.0), pendulum(2.6)] if library else [kepler_one_orbit()]
    ldft.learn(model, fields, progress=False)
    fs = as_lattice_fields(
        [f.isel(t=slice(k, None)) for f in fields for k in (0, 7)], ["f"] * (2 * len(fields)), min_slices=2
    )
    forms = numpy_derivatives_of(model)
    steps = [f.shape[0] for f in fs]
    torch_first = FastBatch(model, fs, steps, forms, "newton", False).ngprev
    numpy_first = FastBatch(model, fs, steps, forms, "newton", False, numpy_first=True).ngprev
    assert np.all(np.isfinite(numpy_first)) and np.abs(torch_first).max() > 0
    np.testing.assert_allclose(numpy_first, torch_first, rtol=1e-12, atol=1e-14 * np.abs(torch_first).max())
