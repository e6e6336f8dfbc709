"""1D serving in numpy (``_serve._fast1d``) gives what the torch loop gives, and the polynomial's numpy
derivatives equal automatic differentiation.

Every comparison serves the same model twice in one process: once as it is (a polynomial has numpy
closed forms, so the numpy loop serves it) and once with the numpy route switched off (the torch loop).
"""

from __future__ import annotations

import copy

import numpy as np
import pytest
import torch
import xarray as xr

import latticedft as ldft
from latticedft import _serve, systems
from latticedft._action import cell_derivatives
from latticedft._errors import InputError, ServeError
from latticedft._lattice import as_lattice_field, as_lattice_fields, gather_cells
from latticedft._learn._data import as_fields
from latticedft._serve import _fast1d, _onedim

from helpers import oscillator_data, series


@pytest.fixture(scope="module")
def oscillator():
    """A 27-term polynomial learned on the quartic oscillator, and its training trajectories."""
    _, data = oscillator_data()
    model = ldft.PolynomialLagrangian(orders=(2, 8))
    ldft.learn(model, data)
    return model, data


@pytest.fixture(scope="module")
def kepler():
    """A polynomial of a 2-component (planar Kepler-like) field, learned on two orbits."""
    data = [systems.kepler_orbit(1.0, v, dt=0.05, n=120) for v in (1.0, 1.1)]
    model = ldft.PolynomialLagrangian(orders=(2, 4))
    ldft.learn(model, data)
    return model, data


def _serve_both(monkeypatch, model, init, **kw):
    """``serve`` by the numpy loop, then by the torch loop (numpy route switched off)."""
    fast = ldft.serve(model, init, progress=False, **kw)
    with monkeypatch.context() as mp:
        mp.setattr(_onedim, "numpy_derivatives_of", lambda model: None)
        slow = ldft.serve(model, init, progress=False, **kw)
    return fast, slow


def _assert_same(fast: ldft.ServeResult, slow: ldft.ServeResult) -> None:
    a, b = fast.field.values, slow.field.values
    assert a.shape == b.shape
    np.testing.assert_allclose(a, b, rtol=1e-11, atol=1e-12 * np.abs(b).max())
    assert (fast.complete, fast.reason, fast.slices) == (slow.complete, slow.reason, slow.slices)
    assert fast.newton_iterations == slow.newton_iterations
    assert fast.max_newton_iterations == slow.max_newton_iterations
    assert fast.fail_at is None if slow.fail_at is None else fast.fail_at[0] == slow.fail_at[0]
    assert fast.max_residual == pytest.approx(slow.max_residual, rel=1e-6, abs=1e-14)
    assert fast.warnings == slow.warnings
    if slow.extrapolation is not None:
        np.testing.assert_allclose(fast.extrapolation.values, slow.extrapolation.values, rtol=1e-9, atol=1e-12)


def test_a_polynomial_is_served_by_the_numpy_loop_and_an_mlp_is_not(oscillator):
    model, _ = oscillator
    assert _fast1d.numpy_derivatives_of(model) is not None
    mlp = ldft.MLPLagrangian(hidden=[4], seed=0)
    mlp.bind(1, 1, (0.1,))
    assert _fast1d.numpy_derivatives_of(mlp) is None
    formula = ldft.lagrangians.verlet(lambda q: 0.5 * q**2)
    formula.bind(1, 1, (0.1,))
    with ldft.set_options(compiled_kernels=False):
        assert _fast1d.numpy_derivatives_of(formula) is None
    assert _fast1d.numpy_derivatives_of(formula) is not None  # its closed form compiles (latticedft._kernel)
    away = copy.deepcopy(model).to("meta")  # parameters off the CPU (as on an accelerator): the torch loop serves
    assert _fast1d.numpy_derivatives_of(away) is None


def test_mlp_is_served_by_the_torch_loop(monkeypatch):
    _, data = oscillator_data(amplitudes=(0.5,), steps=20)
    mlp = ldft.MLPLagrangian(hidden=[6], activation="tanh", form="kinetic-potential", seed=0)
    ldft.learn(mlp, data, max_iter=2)

    def refuse(*args, **kwargs):
        raise AssertionError("the numpy loop serves models with numpy closed forms only")

    monkeypatch.setattr(_onedim, "serve_fast", refuse)
    out = ldft.serve(mlp, data[0].isel(t=slice(0, 2)), slices=12, progress=False)
    assert out.field.sizes["t"] == 12


def test_one_trajectory_numpy_equals_torch(monkeypatch, oscillator):
    model, data = oscillator
    fast, slow = _serve_both(monkeypatch, model, data[1].isel(t=slice(0, 2)), slices=300)
    assert fast.complete and fast.slices == 300
    _assert_same(fast, slow)
    # and it is the oscillator: the learned L_d reproduces the trajectory it was trained on
    np.testing.assert_allclose(fast.field.values[:120], data[1].values, atol=1e-6)


def test_batch_numpy_equals_torch_member_by_member(monkeypatch, oscillator):
    model, data = oscillator
    inits = [d.isel(t=slice(0, 2)) for d in data] + [series([0.3, 0.3], 0.1), series([-1.0, -0.99], 0.1)]
    fast, slow = _serve_both(monkeypatch, model, inits, slices=150)
    assert len(fast) == len(slow) == 5
    for a, b in zip(fast, slow):
        _assert_same(a, b)


def test_extrapolation_is_recorded_as_by_the_torch_loop(monkeypatch, oscillator):
    model, _ = oscillator
    fast, slow = _serve_both(monkeypatch, model, series([1.5, 1.49], 0.1), slices=80)  # beyond amplitude 1.2
    assert fast.warnings and "extrapolation" in fast.warnings[0]
    _assert_same(fast, slow)


def test_sweep_mode_and_box_numpy_equal_torch(monkeypatch, oscillator):
    model, data = oscillator
    inits = [d.isel(t=slice(0, 2)) for d in data]
    fast, slow = _serve_both(monkeypatch, model, inits, slices=60, mode="sweep")
    for a, b in zip(fast, slow):
        _assert_same(a, b)
    fast, slow = _serve_both(monkeypatch, model, inits, slices=120, box=0.7)
    assert [r.reason.startswith("left the box") for r in fast] == [False, True, True]
    for a, b in zip(fast, slow):
        _assert_same(a, b)


def test_vector_field_numpy_equals_torch(monkeypatch, kepler):
    model, data = kepler
    # orbits inside the training range (where the learned L_d is known, and well conditioned)
    inits = [systems.kepler_orbit(1.0, v, dt=0.05, n=2) for v in (1.0, 1.03)]
    fast, slow = _serve_both(monkeypatch, model, inits, slices=200)
    for a, b in zip(fast, slow):
        assert a.complete and not a.warnings
        _assert_same(a, b)


def _failure(monkeypatch, model, init, **kw) -> list[ServeError]:
    errs = []
    for off in (False, True):
        with monkeypatch.context() as mp:
            if off:
                mp.setattr(_onedim, "numpy_derivatives_of", lambda model: None)
            with pytest.raises(ServeError) as info:
                ldft.serve(model, init, progress=False, **kw)
            errs.append(info.value)
    return errs


def test_non_convergence_is_reported_as_by_the_torch_loop(monkeypatch, oscillator):
    model, data = oscillator
    inits = [data[0].isel(t=slice(0, 2)), data[2].isel(t=slice(0, 2))]
    fast, slow = _failure(monkeypatch, model, inits, slices=40, max_newton=1)
    assert str(fast) == str(slow) and "Newton did not converge in 1 iterations" in str(fast)
    assert (fast.slice, fast.residual) == (slow.slice, pytest.approx(slow.residual, rel=1e-6))
    for a, b in zip(fast.result, slow.result):
        assert a.slices == b.slices == 2 and not a.complete
        assert a.reason == b.reason
        np.testing.assert_array_equal(a.field.values, b.field.values)


def test_singular_hessian_is_reported_as_by_the_torch_loop(monkeypatch, oscillator):
    model, data = oscillator
    zero = ldft.PolynomialLagrangian(orders=(2, 8))
    ldft.learn(zero, data)
    with torch.no_grad():
        zero.coef.zero_()  # L_d = 0: its mixed Hessian vanishes
    fast, slow = _failure(monkeypatch, zero, data[0].isel(t=slice(0, 2)), slices=20)
    assert str(fast) == str(slow) and "mixed Hessian singular" in str(fast)
    assert fast.result.reason == slow.result.reason and fast.result.slices == slow.result.slices


# -- the polynomial's numpy derivatives -------------------------------------------------------------------------
CASES = {
    "scalar-(2,8)": (lambda: systems.oscillator_sin(1.2, n=51, dt=1.0), {"orders": (2, 8)}),
    "scalar-(4,8)-monomial": (
        lambda: systems.oscillator_sin(1.2, n=51, dt=1.0),
        {"orders": (4, 8), "basis": "monomial"},
    ),
    "time-symmetric": (lambda: systems.oscillator_sin(1.2, n=51, dt=1.0), {"orders": (4, 6), "time_symmetric": True}),
    "even": (lambda: systems.oscillator_sin(1.2, n=51, dt=1.0), {"orders": (2, 6), "parity": "even"}),
    "vector-(2,4)": (lambda: systems.kepler_orbit(1.0, 1.1, dt=0.05, n=60), {"orders": (2, 4)}),
    "degree-12": (lambda: systems.oscillator_sin(1.2, n=51, dt=1.0), {"orders": (2, 12)}),
}


def _random_model(case: str):
    make, opts = CASES[case]
    fields = as_fields(make(), None)
    f0 = fields[0]
    model = ldft.PolynomialLagrangian(**opts)
    model.bind(f0.ndim, f0.ncomp, f0.spacing, f0.components)
    model.prepare([gather_cells(f.values, model.stencil, f.periodic) for f in fields])
    gen = torch.Generator().manual_seed(1)
    with torch.no_grad():
        model.coef.copy_(torch.randn(model.n_terms, generator=gen, dtype=torch.float64))
    # random cells around the training range, and cells where every scaled variable is 0
    x = gather_cells(f0.values, model.stencil, f0.periodic)
    x = x[:30] * (1 + 0.3 * torch.randn(30, *x.shape[1:], generator=gen, dtype=torch.float64))
    flat = torch.ones(2, *x.shape[1:], dtype=x.dtype) * model.center[: model.m]
    return model, torch.cat([x, flat])


@pytest.mark.parametrize("folded", [True, False])
@pytest.mark.parametrize("case", list(CASES))
def test_numpy_derivatives_equal_autograd(case, folded):
    if not folded:  # term by term with the fused factor matrices (what large models use)
        ldft.set_options(folded_max_powers=0)
    model, x = _random_model(case)
    pairs = [(0, 1), (0, 0), (1, 1), (1, 0)]
    fn = model.numpy_derivatives(pairs)
    assert fn is not None
    grad, blocks = fn(x.numpy())
    g_ref, b_ref = cell_derivatives(model, x, pairs, create_graph=True)  # autograd
    scale = float(g_ref.detach().abs().max())
    assert grad.shape == tuple(g_ref.shape)
    assert np.abs(grad - g_ref.detach().numpy()).max() <= 1e-12 * scale
    for block, pair in zip(blocks, pairs):
        ref = b_ref[pair].detach().numpy()
        assert block.shape == ref.shape
        assert np.abs(block - ref).max() <= 1e-12 * np.abs(ref).max()


def test_numpy_derivatives_in_chunks_equal_one_pass():
    model, x = _random_model("vector-(2,4)")
    whole = model.numpy_derivatives([(0, 1)])(x.numpy())
    with ldft.set_options(folded_chunk=7 * 5**4):  # 7 cells per chunk
        parts = model.numpy_derivatives([(0, 1)])(x.numpy())
    np.testing.assert_allclose(whole[0], parts[0], rtol=1e-14, atol=1e-14 * np.abs(whole[0]).max())
    np.testing.assert_allclose(whole[1][0], parts[1][0], rtol=1e-14, atol=1e-14 * np.abs(whole[1][0]).max())


def test_above_degree_12_the_torch_closed_forms_serve():
    make, _ = CASES["scalar-(2,8)"]
    f0 = as_fields(make(), None)[0]
    model = ldft.PolynomialLagrangian(orders=(2, 14))
    model.bind(f0.ndim, f0.ncomp, f0.spacing, f0.components)
    assert model.numpy_derivatives([(0, 1)]) is None
    assert _fast1d.numpy_derivatives_of(model) is None


def _one_by_one(monkeypatch):
    """Switch the batch's shortcuts off: each input checked, each result built by xarray's own constructor."""
    from latticedft import _lattice
    from latticedft._serve import _batch, _range

    monkeypatch.setattr(
        _serve,
        "as_lattice_fields",
        lambda items, sources, **kw: [_lattice.as_lattice_field(d, source=s, **kw) for d, s in zip(items, sources)],
    )
    monkeypatch.setattr(_batch, "to_dataarrays", lambda fields: [f.to_dataarray() for f in fields])
    real = _range._extrapolation_array
    monkeypatch.setattr(_range, "_extrapolation_array", lambda model, f, per, shared=None: real(model, f, per))


def _mixed_batch(data):
    """Inits of mixed starts, attributes and lengths: some laid out alike, some not."""
    a = data[0].isel(t=slice(0, 2)).assign_attrs(source="first")
    b = data[1].isel(t=slice(0, 2))
    b["t"].attrs["units"] = "s"
    c = series([1.1, 1.09], 0.1).assign_coords(t=[0.5, 0.6])  # another start
    d = data[2].isel(t=slice(0, 5))  # five slices given
    e = series([1.6, 1.59], 0.1)  # beyond the training range: a warning
    return [a, b, c, d, a.copy(), b.copy(), e, series([0.7, 0.69], 0.1, name="q")]


def test_batch_results_are_those_built_one_by_one(monkeypatch, oscillator):
    """Inputs checked and results built for the batch at once: the same results, identical DataArrays, as
    checking and building each alone (mixed lengths, starts, names, attributes and a range warning)."""
    model, data = oscillator
    inits = _mixed_batch(data)
    fast = ldft.serve(model, inits, progress=False)  # each member as long as its init: 2 or 5 slices
    longer = ldft.serve(model, inits, slices=60, progress=False)
    with monkeypatch.context() as mp:
        _one_by_one(mp)
        slow = ldft.serve(model, inits, progress=False)
        slow_longer = ldft.serve(model, inits, slices=60, progress=False)
    assert [r.slices for r in fast] == [2, 2, 2, 5, 2, 2, 2, 2]
    assert any(r.warnings for r in longer) and not all(r.warnings for r in longer)
    for a, b in [*zip(fast, slow), *zip(longer, slow_longer)]:
        xr.testing.assert_identical(a.field, b.field)
        assert a.field["t"].attrs == b.field["t"].attrs
        if b.extrapolation is None:
            assert a.extrapolation is None
        else:
            xr.testing.assert_identical(a.extrapolation, b.extrapolation)
        assert a.to_dict() | {"wall_time": 0, "sites_per_second": 0} == b.to_dict() | {
            "wall_time": 0,
            "sites_per_second": 0,
        }


def test_batch_results_own_their_attributes(oscillator):
    """Members built around one set of coordinates do not share what a user may change."""
    model, data = oscillator
    init = data[0].isel(t=slice(0, 2))
    first, second = ldft.serve(model, [init, init.copy()], slices=20, progress=False)
    first.field.attrs["note"] = 1
    first.field["t"].attrs["units"] = "s"
    first.field.values[3] = 99.0
    first.extrapolation.attrs["note"] = 1
    assert "note" not in second.field.attrs and "units" not in second.field["t"].attrs
    assert second.field.values[3] != 99.0 and "note" not in second.extrapolation.attrs


def test_a_bad_member_of_a_batch_is_named_as_one_by_one(oscillator):
    model, data = oscillator
    init = data[0].isel(t=slice(0, 2))
    bad = init.copy()
    bad.values[1] = np.nan
    with pytest.raises(InputError, match=r"^init\[2\]: field 'psi' holds 1 NaN/inf value\(s\), the first at index t=1"):
        ldft.serve(model, [init, init.copy(), bad, init.copy()], progress=False)
    short = init.isel(t=slice(0, 1))
    with pytest.raises(InputError, match=r"^init\[1\]: dim 't' has 1 site"):
        ldft.serve(model, [init, short], progress=False)


def test_a_layout_checked_before_has_only_its_values_checked_later() -> None:
    """A field laid out as one a call checked before is not checked again (only its values), the same
    lattice field as the full check; a changed attribute the checks read, a value that is not a number or
    another ``min_slices`` is checked in full."""
    from latticedft import _lattice

    _lattice._CHECKED.clear()
    a = series([0.2, 0.1, 0.0], 0.1)
    first = as_lattice_fields([a], ["init"], min_slices=2)[0]
    assert len(_lattice._CHECKED) == 1
    b = a.copy()
    b.values[:] = [0.3, 0.2, 0.1]
    again = as_lattice_fields([b.assign_attrs(source="b")], ["init"], min_slices=2)[0]
    full = as_lattice_field(b.assign_attrs(source="b"), source="init", min_slices=2)
    assert torch.equal(again.values, full.values) and again.attrs == full.attrs == {"source": "b"}
    assert (again.spacing, again.boundary, again.dims, again.coord_attrs) == (
        full.spacing,
        full.boundary,
        full.dims,
        full.coord_attrs,
    )
    assert again.coords["t"] is not first.coords["t"]
    np.testing.assert_array_equal(again.coords["t"], full.coords["t"])
    b.values[1] = np.nan
    with pytest.raises(InputError, match=r"^init: field 'psi' holds 1 NaN/inf value"):
        as_lattice_fields([b], ["init"], min_slices=2)
    with pytest.raises(InputError, match=r"at least 4 are needed"):
        as_lattice_fields([a], ["init"], min_slices=4)
    c = a.copy()
    c["t"].attrs["periodic"] = "true"
    with pytest.raises(InputError, match=r"cannot be periodic"):
        as_lattice_fields([c], ["init"], min_slices=2)


def test_lattice_fields_of_a_batch_equal_those_one_by_one(oscillator):
    _, data = oscillator
    inits = _mixed_batch(data)
    periodic = series([0.2, 0.1, 0.0], 0.1)
    inits.append(periodic)
    fast = as_lattice_fields(inits, [f"init[{k}]" for k in range(len(inits))], min_slices=2)
    for k, (f, d) in enumerate(zip(fast, inits)):
        g = as_lattice_field(d, source=f"init[{k}]", min_slices=2)
        assert torch.equal(f.values, g.values)
        assert (f.spacing, f.boundary, f.dims, f.components, f.name) == (
            g.spacing,
            g.boundary,
            g.dims,
            g.components,
            g.name,
        )
        assert f.attrs == g.attrs and f.coord_attrs == g.coord_attrs and f.coords.keys() == g.coords.keys()
        for name in f.coords:
            np.testing.assert_array_equal(f.coords[name], g.coords[name])
