"""The exact-step corrections: the ``O(h^2)`` terms of one step of the continuous flow, as sparse libraries that
``select = "auto"`` tries on a time-only lattice."""

from __future__ import annotations

import math

import pytest
import sympy
import torch
from test_sparse import kepler_one_orbit, pendulum

import latticedft as ldft
from latticedft._models._sparse import exact_step_libraries
from latticedft._models._terms import named, term_forms, term_values
from latticedft._select import (
    EXACT_STEP_THRESHOLD,
    _choose,
    auto_candidates,
    exact_step_candidates,
    is_exact_step,
    sparse_candidates,
)


def test_the_radial_term_is_the_squared_projection_of_the_velocity_on_q():
    (term,) = named("radial").expand(1, 2)
    assert term.name == "(q1*Dtq1+q2*Dtq2)**2"
    z = torch.tensor([[[1.0, 2.0], [0.3, -0.1]]], dtype=torch.float64)  # mean (1, 2), time differences
    value = term_values([term], z, [0.1])
    assert value.item() == pytest.approx((1.0 * 3.0 + 2.0 * -1.0) ** 2)
    q, d = sympy.symbols("q1 q2"), [sympy.symbols("Dtq1 Dtq2")]
    assert term_forms([term], q, d) == [(q[0] * d[0][0] + q[1] * d[0][1]) ** 2]
    with pytest.raises(ldft.InputError, match="'radial' needs a vector field"):
        named("radial").expand(1, 1)


def test_the_exact_step_libraries_expand_to_the_correction_terms():
    kepler, coupled = exact_step_libraries(1, 2)
    assert coupled == "velocities + trig:1 + cosdiff*velocities + coupledstep"
    assert len(ldft.Library.parse(coupled).expand(1, 2)) == 10 + 28
    assert exact_step_libraries(1, 3) == [kepler]  # coupledstep is for two components
    names = [t.name for t in ldft.Library.parse(kepler).expand(1, 2)]
    assert names == [
        "(Dtq1**2+Dtq2**2)",
        "|q|**-1",
        "|q|**-4",
        "(Dtq1**2+Dtq2**2)*|q|**-3",
        "(q1*Dtq1+q2*Dtq2)**2*|q|**-5",
    ]
    (fifth,) = exact_step_libraries(1, 1, order=5)
    assert "Dtq**2*Dtq**2*cos(q)" in [t.name for t in ldft.Library.parse(fifth).expand(1, 1)]
    assert exact_step_libraries(2, 1) == [] and exact_step_libraries(2, 1, order=5) == []


def test_kepler_exact_samples_keep_the_step_corrections_of_the_true_potential():
    gm, h = 0.40038, 0.1
    model = ldft.SparseLagrangian(exact_step_libraries(1, 2)[0], threshold=EXACT_STEP_THRESHOLD, at="average", bags=0)
    ldft.learn(model, kepler_one_orbit(n=31, dt=h), progress=False)
    coef = dict(zip(model.term_names, model.coef.tolist()))
    unit = 0.5 / coef["(Dtq1**2+Dtq2**2)"]  # unit mass
    # h^3 (-|grad V|^2 / 24 + v.Hess(V).v / 12) for V = -gm / |q|, per step h
    assert unit * coef["|q|**-1"] == pytest.approx(gm, rel=1e-4)
    # within 10 %: the fit of one orbit carries the O(h^4) terms too
    assert unit * coef["|q|**-4"] == pytest.approx(-(h**2) * gm**2 / 24, rel=0.1)
    assert unit * coef["(Dtq1**2+Dtq2**2)*|q|**-3"] == pytest.approx(h**2 * gm / 12, rel=0.1)
    assert unit * coef["(q1*Dtq1+q2*Dtq2)**2*|q|**-5"] == pytest.approx(-(h**2) * gm / 4, rel=0.1)


def test_exact_step_corrections_are_chosen_when_they_serve_2x_better_with_the_same_terms():
    step = exact_step_candidates(1, 2)[0]
    rows = [
        {"score": math.inf, "n_parameters": 45, "label": "hand-set", "kind": "polynomial"},
        {"score": 3e-6, "n_parameters": 36, "label": "orders", "kind": "polynomial"},
        {"score": 1.6e-3, "n_parameters": 2, "label": "true", "kind": "sparse", "options": {}, "terms": ["T", "V"]},
        {
            "score": 8e-6,
            "n_parameters": 4,
            "label": "step",
            "kind": "sparse",
            "options": step,
            "terms": ["T", "V", "C"],
        },
    ]
    assert is_exact_step(rows[3]) and not is_exact_step(rows[2])  # the polynomial scores lowest: sparse first
    assert _choose(rows, factor=2.0, keep_below=1e-6)[0] == 3
    rows[3]["score"] = 1e-3  # less than 2x better: the fewest terms
    assert _choose(rows, factor=2.0, keep_below=1e-6)[0] == 2
    rows[3].update(score=8e-6, terms=["T", "W", "C"])  # another potential, not corrections to the same one
    assert _choose(rows, factor=2.0, keep_below=1e-6)[0] == 2


def test_auto_tries_the_exact_step_candidates_on_a_time_only_lattice():
    for m in (1, 2):
        assert all(c in sparse_candidates(1, m) for c in exact_step_candidates(1, m))
    assert not any(is_exact_step({"kind": "sparse", "options": c}) for c in sparse_candidates(2, 1))
    cands = auto_candidates(ldft.PolynomialLagrangian((2, 2)), n=1, m=1)
    assert sum(is_exact_step({"kind": "sparse", "options": c}) for c in cands) == 3


def test_select_keeps_the_pendulum_step_corrections_and_drops_them_on_leapfrog_data():
    h = 0.1
    data = [pendulum(2.0, 40, h), pendulum(2.6, 40, h)]
    cands = [sparse_candidates(1, 1)[0], {**exact_step_candidates(1, 1)[0], "bags": 0}]
    sel = ldft.select(ldft.PolynomialLagrangian((2, 2)), data, cands, progress=False)
    assert sel.chosen == 2, sel.reason
    coef = dict(zip(sel.model.term_names, sel.model.coef.tolist()))
    unit = 0.5 / coef["Dtq**2"]
    assert unit * coef["cos(2*q)"] == pytest.approx(h**2 / 48, rel=5e-2)  # -h^2/24 sin^2 q
    assert unit * coef["Dtq**2*cos(q)"] == pytest.approx(h**2 / 12, rel=5e-2)  # h^2/12 V'' v^2
    # on the leapfrog's own data (the trapezoid L_d's) the corrections fit to round-off and are dropped
    frames = [2.0, 2.0 - h**2 * math.sin(2.0) / 2]
    for _ in range(38):
        frames.append(2 * frames[-1] - frames[-2] - h**2 * math.sin(frames[-1]))
    leap = data[0].copy(data=frames)
    model = ldft.SparseLagrangian(exact_step_libraries(1, 1)[0], threshold=EXACT_STEP_THRESHOLD, at="average", bags=0)
    ldft.learn(model, leap, progress=False)
    assert model.report_.sparse["kept"] == ["Dtq**2", "cos(q)"]


def test_a_quartic_oscillator_keeps_the_step_corrections_of_its_potential():
    import numpy as np
    import xarray as xr
    from test_sparse import _ode

    h, lam = 0.1, 0.3  # V = q^2/2 + lam q^4/4: V'^2 = q^2 + 2 lam q^4 + lam^2 q^6, V'' = 1 + 3 lam q^2
    data = [
        xr.DataArray(_ode(lambda y: [y[1], -y[0] - lam * y[0] ** 3], [a, 0.0], 60, h)[0], dims="t", name="psi")
        for a in (1.0, 1.5)
    ]
    model = ldft.SparseLagrangian(exact_step_libraries(1, 1)[1], threshold=EXACT_STEP_THRESHOLD, at="average", bags=0)
    ldft.learn(model, [d.assign_coords(t=np.arange(60) * h) for d in data], progress=False)
    coef = dict(zip(model.term_names, model.coef.tolist()))
    mass = 1 + h**2 / 6  # the kinetic coefficient 1/2 + h^2/12 V''(0), normalised to 1/2
    unit = 0.5 / coef["Dtq**2"]
    assert unit * coef["q**2"] == pytest.approx((-0.5 - h**2 / 24) / mass, rel=1e-4)
    assert unit * coef["q**4"] == pytest.approx((-lam / 4 - 2 * lam * h**2 / 24) / mass, rel=1e-3)
    assert unit * coef["q**6"] == pytest.approx(-(lam**2) * h**2 / 24 / mass, rel=0.1)
    assert unit * coef["Dtq**2*q**2"] == pytest.approx(3 * lam * h**2 / 12 / mass, rel=0.1)
    assert set(model.report_.sparse["kept"]) == {"Dtq**2", "q**2", "q**4", "q**6", "Dtq**2*q**2"}
