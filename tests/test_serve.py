"""Serving: slice-Newton against the site-by-site sweep, 1D batches, escapes, failures."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import latticedft as ldft
from latticedft import lagrangians

from helpers import membrane_field, oscillator_data, quartic, series, wave_field


def _sine_gordon():
    def fn(c, h):
        u = c[..., 0, 0]
        return 0.5 * ((c[..., 1, 0] - u) / h[0]) ** 2 - 0.5 * ((c[..., 2, 0] - u) / h[1]) ** 2 - (1 - torch.cos(u))

    return ldft.AnalyticLagrangian(fn, name="sine-Gordon")


@pytest.mark.parametrize("boundary", ["dirichlet", "periodic"])
def test_newton_and_sweep_agree_nonlinear_1p1d(boundary):
    field = wave_field(nx=17, nt=12)
    sg = _sine_gordon()
    a = ldft.serve(sg, field, boundary=boundary)
    b = ldft.serve(sg, field, boundary=boundary, mode="sweep")
    assert a.mode == "newton" and b.mode == "sweep"
    np.testing.assert_allclose(a.field.values, b.field.values, atol=1e-12)


def test_newton_and_sweep_agree_2p1d():
    field = membrane_field(n=8, nt=8)
    a = ldft.serve(lagrangians.wave(1.0), field)
    b = ldft.serve(lagrangians.wave(1.0), field, mode="sweep")
    np.testing.assert_allclose(a.field.values, b.field.values, atol=1e-12)


def test_non_triangular_stencil_serves_in_both_modes():
    st = ldft.Stencil.full_cell(2)

    def full(c, h):
        gt = (c[..., 2, 0] + c[..., 3, 0] - c[..., 0, 0] - c[..., 1, 0]) / (2 * h[0])
        gx = (c[..., 1, 0] + c[..., 3, 0] - c[..., 0, 0] - c[..., 2, 0]) / (2 * h[1])
        return 0.5 * gt**2 - 0.5 * gx**2 - 0.5 * c[..., 0, 0] ** 2

    model = ldft.AnalyticLagrangian(full, stencil=st)
    field = wave_field(nx=15, nt=10)
    a = ldft.serve(model, field)
    b = ldft.serve(model, field, mode="sweep")  # Gauss-Seidel sweeps: the slice system is tridiagonal
    np.testing.assert_allclose(a.field.values, b.field.values, atol=1e-9)
    assert np.isfinite(a.field.values).all()


def test_batch_equals_one_by_one_and_sweep():
    _, data = oscillator_data(steps=50)
    model = ldft.PolynomialLagrangian(orders=(4, 4))
    ldft.learn(model, data)
    inits = [f.isel(t=slice(0, 2)) for f in data]
    batch = ldft.serve(model, inits, slices=50)
    for r, f in zip(batch, inits):
        one = ldft.serve(model, f, slices=50)
        sweep = ldft.serve(model, f, slices=50, mode="sweep")
        np.testing.assert_allclose(r.field.values, one.field.values, atol=1e-14)
        np.testing.assert_allclose(r.field.values, sweep.field.values, atol=1e-12)


def test_box_stops_an_escaping_trajectory_as_complete():
    dt = 0.05
    kep = lagrangians.kepler()
    fast = series([[1.0, 0.0], [1.0, 1.6 * dt]], dt, components=["x", "y"])
    slow = series([[1.0, 0.0], [1.0, 1.0 * dt]], dt, components=["x", "y"])
    out = ldft.serve(kep, [fast, slow], slices=400, box=3.0)
    assert out[0].complete and "box" in out[0].reason and out[0].slices < 400
    assert np.linalg.norm(out[0].field.values[-1]) > 3.0 >= np.linalg.norm(out[0].field.values[-2])
    assert out[1].complete and out[1].slices == 400


def test_singular_mixed_hessian_is_reported_with_slice_and_partial_result():
    def no_kinetic(c, h):  # L_d without a term coupling psi_x and psi_{x+e0}
        return -0.5 * c[..., 0, 0] ** 2 - 0.5 * c[..., 1, 0] ** 2

    model = ldft.AnalyticLagrangian(no_kinetic)
    with pytest.raises(ldft.ServeError) as err:
        ldft.serve(model, series([1.0, 0.9], 0.1), slices=10)
    assert "slice 2" in str(err.value) and "\n" not in str(err.value)
    assert err.value.result.slices == 2 and not err.value.result.complete


def test_singular_slice_jacobian_1p1d_names_slice_and_site():
    def no_kinetic(c, h):
        return -0.5 * ((c[..., 2, 0] - c[..., 0, 0]) / h[1]) ** 2

    model = ldft.AnalyticLagrangian(no_kinetic)
    with pytest.raises(ldft.ServeError) as err:
        ldft.serve(model, wave_field(nx=9, nt=6))
    msg = str(err.value)
    assert "slice 2" in msg and "site" in msg and "singular" in msg
    part = err.value.result
    assert part.field.sizes["t"] == 2 and not part.complete


def test_newton_failure_keeps_the_solved_part():
    osc = lagrangians.verlet(quartic)
    with pytest.raises(ldft.ServeError) as err:
        ldft.serve(osc, series([1.0, 0.99], 0.1), slices=40, max_newton=1)
    msg = str(err.value)
    assert "did not converge" in msg and "residual" in msg
    assert err.value.slice == 2


def test_periodic_serving_from_two_slices_only():
    field = wave_field(nx=16, nt=30)
    full = ldft.serve(lagrangians.wave(1.0), field, boundary="periodic")
    short = ldft.serve(lagrangians.wave(1.0), field.isel(t=slice(0, 2)), boundary="periodic", slices=30)
    np.testing.assert_allclose(short.field.values, full.field.values, atol=1e-14)
    assert short.field.sizes["t"] == 30 and np.allclose(short.field.t.values, field.t.values)


def test_dirichlet_needs_the_strips():
    field = wave_field(nx=16, nt=30)
    with pytest.raises(ldft.InputError, match="Dirichlet boundary along 'x'"):
        ldft.serve(lagrangians.wave(1.0), field.isel(t=slice(0, 2)), slices=30)


def test_serve_reports_throughput():
    out = ldft.serve(lagrangians.wave(1.0), wave_field(nx=64, nt=64))
    assert out.sites_per_second > 0 and out.newton_iterations >= 62 and out.max_residual >= 0


def test_quadratic_ld_is_served_by_its_affine_recurrence():
    # the wave L_d (first-order stencil: diagonal slice matrix) and a full-cell Klein-Gordon L_d (tridiagonal)
    def full(c, h):
        gt = (c[..., 2, 0] + c[..., 3, 0] - c[..., 0, 0] - c[..., 1, 0]) / (2 * h[0])
        gx = (c[..., 1, 0] + c[..., 3, 0] - c[..., 0, 0] - c[..., 2, 0]) / (2 * h[1])
        return 0.5 * gt**2 - 0.5 * gx**2 - 0.5 * c[..., 0, 0] ** 2 + 0.1 * c[..., 0, 0]

    cases = [
        (lagrangians.wave(1.0), wave_field(nx=33, nt=60), "dirichlet"),
        (lagrangians.wave(1.0), wave_field(nx=32, nt=60), "periodic"),
        (ldft.AnalyticLagrangian(full, stencil=ldft.Stencil.full_cell(2)), wave_field(nx=15, nt=30), "dirichlet"),
        (lagrangians.wave(1.0), membrane_field(n=10, nt=20), "dirichlet"),
    ]
    for model, field, boundary in cases:
        fast = ldft.serve(model, field, boundary=boundary)
        slow = ldft.serve(model, field, boundary=boundary, affine=False)
        assert fast.solver == "affine" and slow.solver == "newton"
        assert fast.max_newton_iterations == 1 and fast.complete
        np.testing.assert_allclose(fast.field.values, slow.field.values, rtol=0, atol=1e-12)
        assert fast.max_residual <= 1e-10 * np.abs(field.values).max() * 1e4  # residual of the model's own DEL


def test_nonquadratic_ld_is_served_by_newton():
    res = ldft.serve(_sine_gordon(), wave_field(nx=17, nt=12))
    assert res.solver == "newton" and res.max_newton_iterations >= 2


def test_affine_recurrence_hands_over_to_newton_where_the_del_stops_being_affine():
    # quadratic for psi < 0.6 (all the probe sees: the initial data stay below 0.5), a cubic force above:
    # the affine recurrence is wrong from the first slice where psi exceeds 0.6, which the check finds
    def kg_kink(c, h):
        u = c[..., 0, 0]
        return (
            0.5 * ((c[..., 1, 0] - u) / h[0]) ** 2
            - 0.5 * ((c[..., 2, 0] - u) / h[1]) ** 2
            - 0.5 * u**2
            + 3.0 * torch.relu(u - 0.6) ** 3
        )

    model = ldft.AnalyticLagrangian(kg_kink)
    field = wave_field(nx=33, nt=80, modes=((1, 0.45),))
    field[1] = field[0] * 1.02  # starts growing: psi exceeds 0.6 after some slices
    mixed = ldft.serve(model, field, boundary="periodic", slices=80)
    newton = ldft.serve(model, field, boundary="periodic", slices=80, affine=False)
    assert np.abs(newton.field.values).max() > 0.6
    assert mixed.solver == "affine+newton" and mixed.complete
    np.testing.assert_allclose(mixed.field.values, newton.field.values, rtol=0, atol=1e-11)


def test_constant_mixed_hessian_assembles_the_1d_jacobian_once(monkeypatch):
    from latticedft import systems
    from latticedft._serve import _batch

    orbits = [systems.kepler_orbit(r, 1.0 / np.sqrt(r), dt=0.05, n=40) for r in (0.8, 1.0, 1.3)]
    model = ldft.MLPLagrangian(
        hidden=[8, 8], activation="tanh", form="kinetic-potential", features="inverse-radius", seed=0
    )
    ldft.learn(model, orbits, max_iter=5)
    assert model.constant_mixed_hessian
    inits = [o.isel(t=slice(0, 2)) for o in orbits]
    calls = []
    real = _batch.cell_derivatives
    monkeypatch.setattr(_batch, "cell_derivatives", lambda *a, **k: calls.append(a[2]) or real(*a, **k))
    fast = ldft.serve(model, inits, slices=60)
    hessians = sum(1 for pairs in calls if pairs)
    monkeypatch.setattr(type(model), "constant_mixed_hessian", False)
    calls.clear()
    slow = ldft.serve(model, inits, slices=60)
    assert hessians == 1 and sum(1 for pairs in calls if pairs) > 58
    for a, b in zip(fast, slow):
        np.testing.assert_allclose(a.field.values, b.field.values, rtol=0, atol=1e-12)


def test_an_analytic_model_served_again_on_its_lattice_is_not_bound_again() -> None:
    """Serving an analytic model on the lattice it is bound to leaves it as it is (its projection kept); a
    model turned to single precision, or another spacing, is bound again."""
    model = ldft.AnalyticLagrangian(lambda c, h: 0.5 * ((c[..., 1, 0] - c[..., 0, 0]) / h[0]) ** 2)
    model.bind(2, 1, (0.1, 0.2))
    proj = model.proj
    model.bind(2, 1, (0.1, 0.2))
    assert model.proj is proj
    model.float()
    model.bind(2, 1, (0.1, 0.2))
    assert model.proj.dtype == torch.float64
    model.bind(2, 1, (0.1, 0.25))
    assert model.spacing == (0.1, 0.25)


@pytest.mark.parametrize("kept", [True, False])
def test_served_fields_of_one_lattice_are_built_as_xarray_builds_them(kept: bool, monkeypatch) -> None:
    """The served DataArray, built around the kept coordinates of its lattice, is identical to the one
    xarray's constructor builds, for a second call and another number of slices; so is one whose lattice's
    coordinates are too large to be kept."""
    import xarray as xr

    from latticedft import _lattice
    from latticedft._lattice import as_lattice_field

    _lattice._TEMPLATES.clear()
    _lattice._CHECKED.clear()
    if not kept:
        monkeypatch.setattr(_lattice, "KEPT_COORD_BYTES", 8)

    from helpers import sine_gordon

    model = sine_gordon(closed=False)
    init = wave_field(nx=9, nt=6)
    for slices in (4, 6, 4):
        res = ldft.serve(model, init, slices=slices, progress=False)
        f = as_lattice_field(res.field, min_slices=2)
        xr.testing.assert_identical(res.field, f.to_dataarray())
    assert bool(_lattice._TEMPLATES) == bool(_lattice._CHECKED) == kept
