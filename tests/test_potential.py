"""A kinetic-potential MLP served with its derivatives in closed form (``_serve._potential``, the default)
equals today's autograd path to round-off."""

from __future__ import annotations

import functools
from typing import Any

import numpy as np
import pytest
import torch
import xarray as xr

import latticedft as ldft
from latticedft import systems


def _field(ndim: int, n: int, slices: int = 2, periodic: bool = True) -> xr.DataArray:
    """A smooth field of ``n`` sites per axis, its first ``slices`` leapfrog slices of sine-Gordon."""
    x = np.arange(n) / n
    u = np.ones([n] * ndim)
    for k in range(ndim):
        u = u * np.sin(2 * np.pi * x + k).reshape([n if j == k else 1 for j in range(ndim)])
    u = 0.8 * u
    out = [u, u]
    c = (0.04 / 0.1) ** 2
    for _ in range(slices - 2):
        b = out[-1]
        lap = sum(np.roll(b, s, k) for k in range(ndim) for s in (1, -1)) - 2 * ndim * b
        out.append(2 * b - out[-2] + c * lap - 0.04**2 * np.sin(b))
    dims = ("t", *"zyx"[3 - ndim :])
    attrs = {d: {"periodic": "true" if periodic else "false", "period": n * 0.1} for d in dims[1:]}
    return systems.make_field(np.stack(out), dims, spacing=(0.04, *[0.1] * ndim), coord_attrs=attrs)


@functools.lru_cache(maxsize=4)
def _mlp(ndim: int, activation: str = "tanh") -> ldft.MLPLagrangian:
    model = ldft.MLPLagrangian(hidden=[6, 5], activation=activation, form="kinetic-potential", seed=1)
    ldft.learn(model, _field(ndim, 6, slices=8), max_iter=5, progress=False)
    return model


def _both(model: ldft.MLPLagrangian, init: xr.DataArray, **keywords: Any) -> tuple[ldft.ServeResult, ldft.ServeResult]:
    fast = ldft.serve(model, init, progress=False, **keywords)  # the default
    with ldft.set_options(compiled_kernels=False):
        return fast, ldft.serve(model, init, progress=False, **keywords)


@pytest.mark.parametrize(
    ("ndim", "activation", "periodic", "keywords"),
    [
        (2, "tanh", True, {}),
        (1, "sigmoid", True, {}),
        (1, "tanh", False, {}),
        (2, "tanh", True, {"every": 3}),
    ],
)
def test_the_closed_form_potential_serves_as_autograd(
    ndim: int, activation: str, periodic: bool, keywords: dict, monkeypatch: pytest.MonkeyPatch
) -> None:
    from latticedft._serve import _potential

    calls = []
    evaluate = _potential.PotentialSlices.evaluate
    monkeypatch.setattr(
        _potential.PotentialSlices, "evaluate", lambda s, *a, **k: calls.append(1) or evaluate(s, *a, **k)
    )
    model = _mlp(ndim, activation)
    init = _field(ndim, 7, slices=2 if periodic else 10, periodic=periodic)  # Dirichlet: the whole field's strips
    fast, slow = _both(model, init, slices=10, **keywords)
    assert calls
    a, b = np.asarray(fast.field.values), np.asarray(slow.field.values)
    assert np.abs(a - b).max() <= 1e-12 * max(1.0, float(np.abs(b).max()))
    assert fast.newton_iterations == slow.newton_iterations and fast.slice_solver == slow.slice_solver
    assert fast.extrapolation is not None and slow.extrapolation is not None
    assert np.allclose(fast.extrapolation.values, slow.extrapolation.values, rtol=1e-9, atol=1e-12)


def test_two_components_serve_as_autograd() -> None:
    def two(f: xr.DataArray) -> xr.DataArray:
        out = xr.concat([f, 0.5 * f + 0.1], dim="component").transpose(..., "component")
        return out.assign_coords(component=["a", "b"])

    model = ldft.MLPLagrangian(hidden=[5], activation="tanh", form="kinetic-potential", seed=2)
    ldft.learn(model, two(_field(1, 6, slices=8)), max_iter=5, progress=False)
    fast, slow = _both(model, two(_field(1, 7)), slices=8)
    a, b = np.asarray(fast.field.values), np.asarray(slow.field.values)
    assert np.abs(a - b).max() <= 1e-12 * max(1.0, float(np.abs(b).max()))
    assert fast.newton_iterations == slow.newton_iterations


def test_the_potential_gradient_equals_autograd() -> None:
    from latticedft._kernel_folded import folded_kernels
    from latticedft._serve._potential import PotentialNet

    model = _mlp(2)
    x = torch.linspace(-2.0, 2.0, 41, dtype=torch.float64).reshape(-1, 1).requires_grad_(True)
    (want,) = torch.autograd.grad(model._net(model._inputs(x)).sum(), x)
    got = PotentialNet(model, folded_kernels()).grad(x.detach().numpy())
    assert np.allclose(got, want.numpy(), rtol=1e-13, atol=1e-13 * float(want.abs().max()))


def test_the_closed_form_potential_is_the_default_and_falls_back() -> None:
    from latticedft._lattice import as_lattice_field
    from latticedft._serve._potential import PotentialSlices, potential_slices
    from latticedft._serve._slices import _SliceSystem

    model = _mlp(1)
    f = as_lattice_field(_field(1, 7), source="init", min_slices=2)
    flat = f.values.reshape(2, -1, 1)
    assert isinstance(potential_slices(model, _SliceSystem(model, f), flat), PotentialSlices)
    with ldft.set_options(compiled_kernels=False):
        assert potential_slices(model, _SliceSystem(model, f), flat) is None
    silu = ldft.MLPLagrangian(hidden=[4], activation="silu", form="kinetic-potential")
    silu.bind(2, 1, (0.04, 0.1))
    assert potential_slices(silu, _SliceSystem(silu, f), flat) is None  # no closed form: autograd serves


def test_the_affine_probe_is_answered_by_the_closed_forms() -> None:
    """Where the closed forms say the DEL is not affine, so does autograd's probe; a constant potential (an
    affine DEL) is left to the probe."""
    from latticedft._serve._affine import _AffineSlices
    from latticedft._serve._potential import _second, not_affine

    model = _mlp(2)
    k, scale = model.stencil.size, 0.8
    x = torch.linspace(-1.0, 1.0, 9, dtype=torch.float64).reshape(-1, 1).requires_grad_(True)
    with torch.enable_grad():
        (g,) = torch.autograd.grad(model._net(model._inputs(x)).sum(), x, create_graph=True)
        (h,) = torch.autograd.grad(g.sum(), x)
    assert np.allclose(_second(model, x.detach().numpy().reshape(-1)), h.numpy().reshape(-1), rtol=1e-12, atol=1e-12)
    with ldft.set_options(compiled_kernels=False):
        assert not not_affine(model, k, 1, scale)  # the probe decides
    assert not_affine(model, k, 1, scale)
    assert _AffineSlices.probe(model, model.stencil, 1, scale) is None
    flat = ldft.MLPLagrangian(hidden=[3], activation="tanh", form="kinetic-potential", seed=0)
    flat.bind(3, 1, (0.04, 0.1, 0.1))
    with torch.no_grad():
        flat.net[-1].weight.zero_()
    assert not not_affine(flat, k, 1, scale)
    assert _AffineSlices.probe(flat, flat.stencil, 1, scale) is not None


@pytest.mark.parametrize(("k", "m", "upper"), [(4, 1, (0, 1, 0, 0)), (3, 2, (0, 1, 1))])
def test_the_generated_quadratic_passes_equal_the_folded_ones(k: int, m: int, upper: tuple[int, ...]) -> None:
    """The passes written out for one stencil and Hessian pattern give the folded module's results to the bit."""
    from latticedft._kernel_folded import folded_kernels
    from latticedft._kernel_quadratic import quadratic_kernels

    rng = np.random.default_rng(3)
    km, sites, cells = k * m, 7, 9
    hess = rng.normal(size=(km, km)) * (rng.random((km, km)) < 0.6)
    quad, mod = quadratic_kernels(hess, upper, m), folded_kernels()
    assert quad is not None and mod is not None
    lo, hi, vlo, vhi = (rng.normal(size=(sites, m)) for _ in range(4))
    site_of = rng.integers(0, sites, size=(k, cells))
    up = np.asarray(upper, dtype=np.int64)
    out, ref = np.empty((cells, km)), np.empty((cells, km))
    quad.quadratic_grad(lo, hi, site_of, hess, vlo, vhi, out)
    mod.quadratic_grad(lo, hi, site_of, up, hess, vlo, vhi, ref)
    assert np.array_equal(out, ref)
    gprev, rows = rng.normal(size=(cells, km)), np.array([0, 2, 3, 6])
    r, rref = np.empty(rows.size * m), np.empty(rows.size * m)
    quad.quadratic_residual(gprev, lo, hi, site_of, hess, vlo, rows, 0.3, np.empty((sites, m)), r)
    mod.quadratic_residual(gprev, lo, hi, site_of, up, hess, vlo, rows, 0.3, np.empty((sites, m)), rref)
    assert np.array_equal(r, rref)


def test_the_extrapolation_array_built_around_kept_coordinates_is_identical() -> None:
    """A later field's extrapolation array, built around the kept feature coordinate with its own time
    coordinate, equals the one xarray's constructor builds."""
    from latticedft._serve import _range

    model, init = _mlp(1), _field(1, 8)
    for slices in (5, 7):
        kept = ldft.serve(model, init, slices=slices, progress=False)
        _range._KEPT.clear()
        fresh = ldft.serve(model, init, slices=slices, progress=False)
        assert kept.extrapolation is not None and fresh.extrapolation is not None
        xr.testing.assert_identical(kept.extrapolation, fresh.extrapolation)
