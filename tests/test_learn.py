"""Fields served from a known L_d are learned back; the gauge fix matters."""

from __future__ import annotations

import math

import numpy as np
import pytest

import latticedft as ldft
from latticedft import lagrangians, systems

from helpers import membrane_field, oscillator_data, series, wave_field


def test_polynomial_learns_oscillator_back_to_roundoff():
    truth, data = oscillator_data()
    model = ldft.PolynomialLagrangian(orders=(4, 4))
    rep = ldft.learn(model, data)
    assert rep.method == "exact" and rep.gauge_residual < 1e-12 and rep.rel_res < 1e-10
    assert abs(rep.hessian_min_sv - 1) < 1e-9
    for f in data:  # the training fields
        out = ldft.serve(model, f)
        np.testing.assert_allclose(out.field.values, f.values, atol=1e-10)
    new = ldft.serve(truth, series([0.6, 0.6], 0.1), slices=200).field  # a new field
    np.testing.assert_allclose(ldft.serve(model, new).field.values, new.values, atol=1e-10)


@pytest.mark.parametrize("stencil", [None, "full-cell"])
def test_polynomial_learns_wave_back_1p1d(stencil):
    if stencil is None:
        truth, st = lagrangians.wave(1.0), None
    else:
        st = ldft.Stencil.full_cell(2)

        def full(c, h):  # a wave Lagrangian on the four corners of the cell
            gt = (c[..., 2, 0] + c[..., 3, 0] - c[..., 0, 0] - c[..., 1, 0]) / (2 * h[0])
            gx = (c[..., 1, 0] + c[..., 3, 0] - c[..., 0, 0] - c[..., 2, 0]) / (2 * h[1])
            return 0.5 * gt**2 - 0.5 * gx**2

        truth = ldft.AnalyticLagrangian(full, stencil=st, name="full-cell wave")
    obs = wave_field(nt=30)
    train = ldft.serve(truth, obs).field
    model = ldft.PolynomialLagrangian(orders=(2, 2), stencil=st)
    rep = ldft.learn(model, train)
    assert rep.rel_res < 1e-10
    other = ldft.serve(truth, wave_field(nt=30, modes=((2, 0.5), (5, 0.2)))).field
    out = ldft.serve(model, other)
    np.testing.assert_allclose(out.field.values, other.values, atol=1e-11)


def test_polynomial_learns_wave_back_2p1d():
    obs = membrane_field()
    train = ldft.serve(lagrangians.wave(1.0), obs).field
    model = ldft.PolynomialLagrangian(orders=(2, 1))
    rep = ldft.learn(model, train)
    assert rep.rel_res < 1e-10
    np.testing.assert_allclose(ldft.serve(model, train).field.values, train.values, atol=1e-11)


def test_mlp_kinetic_potential_learns_oscillator_to_stated_error():
    truth, data = oscillator_data(steps=80)
    model = ldft.MLPLagrangian(hidden=[16, 16], activation="tanh", form="kinetic-potential", seed=1)
    rep = ldft.learn(model, data, max_iter=300)
    assert rep.gauge_residual < 1e-12  # unit mass by construction
    assert rep.rel_res < 2e-3
    new = ldft.serve(truth, series([0.7, 0.7 - 0.5 * 0.01 * (0.7 + 0.7**3)], 0.1), slices=80).field
    err = ldft.compare(ldft.serve(model, new).field, new)["max_error"]
    assert err < 2e-2  # stated error of a 2x16 network after 300 L-BFGS iterations


def test_mlp_free_form_with_penalty_keeps_gauge():
    _, data = oscillator_data(steps=60)
    model = ldft.MLPLagrangian(hidden=[12, 12], activation="tanh", seed=0)
    rep = ldft.learn(model, data, max_iter=150)
    assert rep.gauge_residual < 1e-2
    assert rep.hessian_min_sv > 0.5


def test_without_gauge_the_trainer_collapses():
    _, data = oscillator_data(steps=60)
    free = ldft.MLPLagrangian(hidden=[12, 12], activation="tanh", seed=0)
    rep_free = ldft.learn(free, data, gauge="none", max_iter=150)
    fixed = ldft.MLPLagrangian(hidden=[12, 12], activation="tanh", seed=0)
    rep_fixed = ldft.learn(fixed, data, max_iter=150)
    # the loss falls further without the gauge ... because L_d collapses towards a constant:
    assert rep_free.loss < rep_fixed.loss
    assert rep_free.hessian_min_sv < 1e-2 * rep_fixed.hessian_min_sv
    # the same for the exact solver: the unconstrained minimiser has no mixed time Hessian
    poly = ldft.PolynomialLagrangian(orders=(4, 4))
    rep = ldft.learn(poly, data, gauge="none")
    assert rep.hessian_min_sv < 1e-8 and rep.loss < 1e-20
    rep2 = ldft.learn(ldft.PolynomialLagrangian(orders=(4, 4)), data)
    assert abs(rep2.hessian_min_sv - 1) < 1e-9


def test_ridge_auto_picks_by_held_out_residual():
    _, data = oscillator_data()
    model = ldft.PolynomialLagrangian(orders=(4, 8))
    rep = ldft.learn(model, data, ridge="auto")
    assert len(rep.validation) > 1
    assert f"{rep.ridge:g}" == min(rep.validation, key=rep.validation.get)
    assert rep.rel_res < 1e-6


def test_adam_reduces_the_objective():
    _, data = oscillator_data(steps=60)
    model = ldft.MLPLagrangian(hidden=[8], activation="tanh", form="kinetic-potential", seed=0)
    rep = ldft.learn(model, data, optimizer="adam", max_iter=200, lr=1e-2)
    assert rep.history[-1][1] < 0.1 * rep.history[0][1]
    assert len(rep.history) == 200 and rep.stop_reason == "max_iter"


def test_rel_tol_stops_early():
    _, data = oscillator_data(steps=60)
    model = ldft.MLPLagrangian(hidden=[8], activation="tanh", form="kinetic-potential", seed=0)
    rep = ldft.learn(model, data, rel_tol=1e-2, max_iter=1000)
    assert rep.iterations < 1000 and "reduced" in rep.stop_reason
    assert rep.history[-1][1] <= 1e-2 * rep.initial_loss


def test_print_shows_the_learned_theory():
    _, data = oscillator_data()
    model = ldft.PolynomialLagrangian(orders=(4, 4))
    ldft.learn(model, data)
    text = str(model)
    assert "Dt^2" in text and "rel_res" in text and "gauge residual" in text
    # the kinetic coefficient: the unit mass 1/(2 h^2) = 50 for h = 0.1, plus -1/8 from V(q0)+V(q1)
    assert math.isclose(model.monomials()[(0, 2)], 50.0 - 0.125, rel_tol=1e-9)  # V(q)=q^2/2 adds -d^2/8


@pytest.mark.parametrize("stencil", [None, "full-cell"])
def test_kinetic_potential_has_unit_mass_on_any_stencil(stencil):
    st = ldft.Stencil.full_cell(2) if stencil else None
    train = ldft.serve(lagrangians.wave(1.0), wave_field(nt=16)).field
    model = ldft.MLPLagrangian(hidden=[6], activation="tanh", form="kinetic-potential", stencil=st)
    rep = ldft.learn(model, train, max_iter=5)
    assert model.unit_mass_by_construction
    assert rep.gauge_residual < 1e-12 and abs(rep.hessian_min_sv - 1) < 1e-12


def test_the_verdict_says_the_fit_in_words() -> None:
    from latticedft._learn._report import POOR_FIT_REL_RES, fit_verdict

    good = ldft.learn(ldft.PolynomialLagrangian((2, 2)), systems.wave_string([(1, 1.0), (2, 0.3)], nx=21, nt=41))
    assert good.verdict().startswith("verdict: good:") and "next: serve it" in good.verdict()
    poor = fit_verdict(False, 10 * POOR_FIT_REL_RES)
    assert poor.startswith("verdict: poor:") and "next:" in poor and "select" in poor
    assert "train longer" in fit_verdict(False, 10 * POOR_FIT_REL_RES, "lbfgs") and "train longer" not in poor
    dead = fit_verdict(True, 0.0)
    assert dead.startswith("verdict: unusable:") and "gauge" in dead
    assert all("\n" not in v for v in (poor, dead, good.verdict()))
