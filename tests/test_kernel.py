"""Compiled DEL kernels: derivatives and served fields equal today's paths; fallback and cache."""

from __future__ import annotations

import copy
import functools
import logging
import math
from collections.abc import Iterator

import numpy as np
import pytest
import sympy
import torch
import xarray as xr

import latticedft as ldft
from latticedft import lagrangians, systems
from latticedft._action import cell_derivatives, compiled_closed_forms, serving_pairs
from latticedft._kernel import _LOADED, BUILDS, compile_forms
from latticedft._serve._fast1d import trajectory_kernel
from latticedft._symbolic import SymbolicLd, cell_symbols

from helpers import sine_gordon, smooth_start


@pytest.fixture(autouse=True, scope="module")
def _kernel_cache(tmp_path_factory: pytest.TempPathFactory) -> Iterator[None]:
    mp = pytest.MonkeyPatch()
    mp.setenv("LATTICEDFT_KERNEL_CACHE", str(tmp_path_factory.mktemp("kernels")))
    yield
    mp.undo()


def _field(ndim: int, n: int, m: int = 1) -> object:
    """Two slices of a smooth periodic field at rest (0+1D: a point at 0.8 moving slowly)."""
    if ndim == 0:
        u0 = 0.8 + 0.1 * np.arange(m)
        vals = np.stack([u0, u0 + 0.01])
        return systems.make_field(
            vals if m > 1 else vals[:, 0],
            ("t",),
            spacing=0.05,
            components=[f"q{c}" for c in range(m)] if m > 1 else None,
        )
    return smooth_start(ndim, n)


@pytest.mark.parametrize("ndim", [1, 2, 3])
def test_compiled_derivatives_equal_autograd(ndim: int) -> None:
    model = sine_gordon()
    model.bind(ndim + 1, 1, (0.04, *[0.1] * ndim))
    cells = torch.from_numpy(np.random.default_rng(ndim).uniform(-2, 2, (300, model.stencil.size, 1)))
    compiled = compiled_closed_forms(model, cells)
    assert compiled is not None
    pairs = serving_pairs(model.stencil)
    g0, b0 = cell_derivatives(model, cells, pairs)
    g1, b1 = compiled.both(cells.numpy())
    assert np.abs(g1 - g0.numpy()).max() <= 1e-12 * float(g0.abs().max())
    for p, b in zip(pairs, b1):
        assert np.abs(b - b0[p].numpy()).max() <= 1e-12 * max(1.0, float(b0[p].abs().max()))
    assert np.array_equal(compiled.grad(cells.numpy()), g1)


def _served(model: ldft.AbstractLagrangian, init: object, slices: int, compiled: bool) -> np.ndarray:
    with ldft.set_options(compiled_kernels=compiled):
        return np.asarray(ldft.serve(model, init, slices=slices, progress=False).field.values)


@pytest.mark.parametrize(
    ("name", "make", "ndim", "m"),
    [
        ("harmonic Verlet 0+1D", lambda: lagrangians.verlet(lambda q: 0.5 * q**2), 0, 1),
        ("Kepler 0+1D", lambda: lagrangians.kepler(), 0, 2),
        ("sine-Gordon 1+1D", sine_gordon, 1, 1),
        ("Klein-Gordon 1+1D", lambda: lagrangians.klein_gordon(1.2), 1, 1),
        ("sine-Gordon 2+1D", sine_gordon, 2, 1),
    ],
)
def test_served_analytic_fields_equal_todays(name: str, make, ndim: int, m: int) -> None:
    init = _field(ndim, 16, m)
    model = make()
    fast = _served(model, init, 40, True)
    assert compiled_closed_forms(model, torch.zeros(0, dtype=torch.float64)) is not None, name
    slow = _served(make(), init, 40, False)
    assert np.abs(fast - slow).max() <= 1e-12 * max(1.0, float(np.abs(slow).max())), name


@pytest.mark.parametrize("ndim", [0, 1, 2])
def test_linear_models_keep_their_numpy_forms(ndim: int) -> None:
    """Polynomial and feature models are not printed into a DEL kernel (``compiled_closed_forms``: their numpy
    closed forms serve, or the folded kernels): 0+1D fields equal to the bit either way (unless
    ``compiled_numpy_models`` asks for the compiled 0+1D trajectory loop); n-D a polynomial is served on the
    folded kernels by default, its numpy forms with ``compiled_kernels=False``, equal to round-off."""
    init = _field(ndim, 8)
    data = ldft.serve(sine_gordon(), init, slices=12, progress=False).field
    models = [ldft.PolynomialLagrangian(orders=(2, 4), time_symmetric=True)]
    if ndim == 0:
        models.append(ldft.FeatureLagrangian(["poly:4"]))
    for model in models:
        ldft.learn(model, data, progress=False)
        assert compiled_closed_forms(model, torch.zeros(0, dtype=torch.float64)) is None
        fast, slow = _served(model, init, 12, True), _served(model, init, 12, False)
        if ndim == 0:
            assert np.array_equal(fast, slow)
        else:
            assert np.abs(fast - slow).max() <= 1e-12 * float(np.abs(slow).max())


def test_a_model_without_closed_form_falls_back() -> None:
    model = ldft.AnalyticLagrangian(
        lambda c, h: 0.5 * ((c[..., 1, 0] - c[..., 0, 0]) / h[0]) ** 2 - torch.cos(c[..., 0, 0])
    )
    init = _field(0, 0)
    assert np.array_equal(_served(model, init, 20, True), _served(model, init, 20, False))
    assert compiled_closed_forms(model, torch.zeros(0, dtype=torch.float64)) is None


def test_a_form_the_printer_cannot_take_is_reported_once(caplog: pytest.LogCaptureFixture) -> None:
    (u0,), (u1,) = cell_symbols(2, 1)
    form = SymbolicLd(sympy.Function("mystery")(u0) + (u1 - u0) ** 2, ((0,), (1,)), 1, (0.1,))
    with caplog.at_level(logging.INFO, logger="latticedft"):
        assert compile_forms(form, [(0, 1)]) is None
        assert compile_forms(form, [(0, 1)]) is None
    assert sum("compiled DEL kernel unavailable" in r.getMessage() for r in caplog.records) == 1


def test_a_kernel_is_built_once_then_loaded_from_the_cache(monkeypatch: pytest.MonkeyPatch) -> None:
    from latticedft import _kernel

    (u0,), (u1,) = cell_symbols(2, 1)
    form = SymbolicLd((u1 - u0) ** 2 / 2 - sympy.Rational(3, 7) * u0**4, ((0,), (1,)), 1, (0.1,))
    first = compile_forms(form, [(0, 1)])
    assert first is not None and BUILDS[-1][2] == "built"
    _LOADED.clear()  # as a new process would
    monkeypatch.setattr(_kernel, "kernel_source", lambda *a: pytest.fail("the cached module's source was generated"))
    again = compile_forms(form, [(0, 1)])
    assert again is not None and BUILDS[-1][2] == "cached"
    cells = np.random.default_rng(0).standard_normal((5, 2, 1))
    assert np.array_equal(first.both(cells)[0], again.both(cells)[0])


def test_a_build_waits_for_another_build_of_the_same_kernel() -> None:
    """Two builders of one kernel on an empty cache: the second waits until the first's lock is released (a
    flock on a descriptor of its own conflicts within the process too, as between processes)."""
    import threading

    from latticedft._kernel import build_lock, cached_module

    started = threading.Event()

    def build() -> tuple[object, str]:
        started.set()
        return object(), "cached"

    key = "lock-test-" + str(np.random.default_rng().integers(1 << 40))
    with build_lock(key):
        worker = threading.Thread(target=cached_module, args=(key, build, "t", "built", "unavailable", "none"))
        worker.start()
        assert not started.wait(0.5), "the build ran while another held its lock"
    assert started.wait(60)
    worker.join(60)
    assert _LOADED.pop(key) is not None


def test_a_build_lock_held_too_long_is_passed_with_one_info_line(caplog: pytest.LogCaptureFixture) -> None:
    from latticedft._kernel import build_lock

    held, passed = build_lock("lock-test-held"), build_lock("lock-test-held", wait=0.1)
    with held, caplog.at_level(logging.INFO, logger="latticedft"), passed:
        pass
    assert "another process's build holds its lock; building here too" in caplog.text


def _dirichlet(ndim: int, n: int) -> object:
    """Two slices of a smooth field with Dirichlet ends (no periodic attribute)."""
    x = (np.arange(n) + 0.5) / n
    u = np.ones([n] * ndim)
    for k in range(ndim):
        shape = [1] * ndim
        shape[k] = n
        u = u * np.sin(np.pi * x + 0.3 * k).reshape(shape)
    return systems.make_field(np.stack([0.8 * u, 0.8 * u]), ("t", *"zyx"[3 - ndim :]), spacing=(0.04, *[0.1] * ndim))


@pytest.mark.parametrize(
    ("name", "init", "keywords"),
    [
        ("periodic 1+1D", lambda: _field(1, 24), {}),
        ("periodic 3+1D", lambda: _field(3, 6), {}),
        ("Dirichlet 2+1D", lambda: _dirichlet(2, 8), {"boundary_value": 0.0}),
        ("periodic 2+1D, streamed", lambda: _field(2, 8), {"every": 3}),
    ],
)
def test_the_compiled_slice_newton_serves_todays_fields(
    name: str, init, keywords: dict, monkeypatch: pytest.MonkeyPatch
) -> None:
    from latticedft._serve import _fused

    calls = []  # per slice the compiled kernel solved: the sites it read at fixed offsets
    solve, many = _fused.FusedSlices.solve, _fused.FusedSlices.solve_many

    def solve_many(self: _fused.FusedSlices, *a: object) -> tuple[int, list[int], list[float]]:
        out = many(self, *a)  # type: ignore[arg-type]
        calls.extend([self.plain] * len(out[1]))
        return out

    monkeypatch.setattr(_fused.FusedSlices, "solve", lambda self, *a: calls.append(self.plain) or solve(self, *a))
    monkeypatch.setattr(_fused.FusedSlices, "solve_many", solve_many)
    field = init()
    with ldft.set_options(compiled_kernels=True):
        fast = ldft.serve(sine_gordon(), field, slices=30, progress=False, **keywords)
    assert len(calls) >= 20, name  # the first Newton slice chooses the solver; the compiled kernel serves the rest
    with ldft.set_options(compiled_kernels=False):
        slow = ldft.serve(sine_gordon(), field, slices=30, progress=False, **keywords)
    a, b = np.asarray(fast.field.values), np.asarray(slow.field.values)
    assert np.abs(a - b).max() <= 1e-12 * max(1.0, float(np.abs(b).max())), name
    assert fast.slice_solver == slow.slice_solver == "sitewise"
    assert fast.newton_iterations == slow.newton_iterations, name
    plain = calls[0]  # the sites read at fixed offsets: all but those whose cells wrap or leave the lattice
    assert plain.any() and not plain.all(), name


def test_the_tables_kept_per_lattice_serve_each_lattice_its_own() -> None:
    """The slice system and the kernel's index tables kept from the last lattices are those of the lattice
    served: fields on lattices that alternate (size, boundary) serve as each does in a fresh process, and one
    lattice served again reuses its tables."""
    from latticedft._serve import _field as field_module
    from latticedft._serve import _fused

    inits = [(_field(2, 8), {}), (_field(2, 6), {}), (_dirichlet(2, 8), {"boundary_value": 0.0}), (_field(2, 6), {})]
    slow = []
    for init, keywords in inits:
        with ldft.set_options(compiled_kernels=False):
            slow.append(ldft.serve(sine_gordon(), init, slices=8, progress=False, **keywords).field.values)
    built = []
    for (init, keywords), expected in zip(inits, slow):
        with ldft.set_options(compiled_kernels=True):
            fast = ldft.serve(sine_gordon(), init, slices=8, progress=False, **keywords).field.values
        assert np.abs(np.asarray(fast) - np.asarray(expected)).max() <= 1e-12
        built.append({id(tables) for tables in _fused._TABLES.values()})
    assert built[3] == built[2]  # the 6 x 6 lattice served again, its tables still kept: none built
    assert len(_fused._TABLES) == _fused.TABLES_KEPT and len(field_module._SYSTEMS) == 1


def test_the_slice_steps_scale_and_tally_are_those_of_the_sequential_loops() -> None:
    """The predictor's scale (maxima in independent chains) equals the sequential loop's, a value that is not
    a number included (it then runs that loop); the tally equals numpy's minimum and maxima."""
    model = sine_gordon()
    model.bind(3, 1, (0.02, 0.05, 0.05))
    mod = compiled_closed_forms(model, torch.zeros(0, dtype=torch.float64)).module  # type: ignore[union-attr]
    rng = np.random.default_rng(0)
    prev, cur, older = (rng.standard_normal(37) for _ in range(3))
    interior = rng.random(37) < 0.7
    rows = np.nonzero(interior)[0]
    for bad in (None, 5, 30):
        if bad is not None:
            cur[bad] = math.nan
        for old in (older, np.zeros(0)):
            fast, slow = np.full(37, 9.0), np.full(37, 9.0)
            a = mod.predict(prev, cur, fast, old, rows, interior)
            b = mod.predict_exact(prev, cur, slow, old, rows)
            assert (a == b or (math.isnan(a) and math.isnan(b))) and np.array_equal(fast, slow, equal_nan=True)
    res, its = rng.random(13), rng.integers(-2, 5, 13)
    assert mod.tally(res, its) == (its.min(), its.max(), res.max())


def test_a_coupled_l_d_has_no_compiled_slice_newton() -> None:
    """A time difference mixed with a spatial one couples neighbouring unknowns: slice-Newton's Krylov steps."""

    def fn(c: torch.Tensor, h: tuple[float, ...]) -> torch.Tensor:
        dt, dx = (c[..., 1, 0] - c[..., 0, 0]) / h[0], (c[..., 2, 0] - c[..., 0, 0]) / h[1]
        return 0.5 * dt**2 - 0.5 * dx**2 + 0.2 * dt * dx - 0.5 * c[..., 0, 0] ** 2

    model = ldft.AnalyticLagrangian(fn)
    model.bind(2, 1, (0.04, 0.1))
    compiled = compiled_closed_forms(model, torch.zeros(0, dtype=torch.float64))
    assert compiled is not None and not compiled.block_diagonal
    init = _field(1, 16)
    fast = _served(model, init, 20, True)
    slow = _served(fn_model := ldft.AnalyticLagrangian(fn), init, 20, False)
    assert fn_model is not None
    assert np.abs(fast - slow).max() <= 1e-12 * max(1.0, float(np.abs(slow).max()))


def test_a_slice_the_kernel_cannot_finish_goes_back_to_slice_newton(monkeypatch: pytest.MonkeyPatch) -> None:
    """A site the kernel cannot finish (here: every slice refused one by one, and a run of slices stopped every
    third slice) hands the slice to slice-Newton, which starts from the predictor afresh: the same field."""
    from latticedft._serve import _fused

    solve, many = _fused.FusedSlices.solve, _fused.FusedSlices.solve_many

    def refused(self: _fused.FusedSlices, *args: object) -> None:
        solve(self, *args)  # type: ignore[arg-type]  # leaves the unknowns moved: slice-Newton must overwrite them
        return None

    def stopped(self: _fused.FusedSlices, flat: torch.Tensor, i: int, stop: int, *rest: object) -> object:
        j, its, res = many(self, flat, i, min(stop, i + 2), *rest)  # type: ignore[arg-type]
        if j < stop:  # the slice it stopped before, its unknowns moved as a failed kernel leaves them
            flat[j + 1, torch.from_numpy(self.rows)] += 1.0
        return j, its, res

    init = _field(2, 8)
    with ldft.set_options(compiled_kernels=False):
        slow = ldft.serve(sine_gordon(), init, slices=20, progress=False)
    monkeypatch.setattr(_fused.FusedSlices, "solve", refused)
    monkeypatch.setattr(_fused.FusedSlices, "solve_many", stopped)
    with ldft.set_options(compiled_kernels=True):
        served = ldft.serve(sine_gordon(), init, slices=20, progress=False)
    assert served.newton_iterations == slow.newton_iterations
    fast, slow = np.asarray(served.field.values), np.asarray(slow.field.values)
    assert np.abs(fast - slow).max() <= 1e-12 * max(1.0, float(np.abs(slow).max()))


def _oscillator() -> tuple[ldft.PolynomialLagrangian, object]:
    """A polynomial oscillator learned from a quartic Verlet trajectory, and a start inside its range."""
    truth = lagrangians.verlet(lambda q: 0.5 * q**2 + 0.25 * q**4)
    init = _field(0, 0)
    model = ldft.PolynomialLagrangian(orders=(2, 6))
    ldft.learn(model, ldft.serve(truth, init, slices=80, progress=False).field, progress=False)
    return model, init


def _both(model: ldft.AbstractLagrangian, init: object, **kw: object) -> tuple[ldft.ServeResult, ldft.ServeResult]:
    with ldft.set_options(compiled_kernels=True, compiled_numpy_models=True):
        fast = ldft.serve(model, init, progress=False, **kw)  # type: ignore[arg-type]
    with ldft.set_options(compiled_kernels=False):
        slow = ldft.serve(model, init, progress=False, **kw)  # type: ignore[arg-type]
    return fast, slow


@pytest.mark.parametrize("which", ["polynomial", "Verlet"])
def test_one_trajectory_is_served_by_its_compiled_loop(which: str) -> None:
    model, init = _oscillator()
    if which == "Verlet":
        model = lagrangians.verlet(lambda q: 0.5 * q**2 + 0.25 * q**4)
    fast, slow = _both(model, init, slices=60)
    with ldft.set_options(compiled_numpy_models=True):
        assert trajectory_kernel(model) is not None
    assert (trajectory_kernel(model) is None) == (which == "polynomial")  # a polynomial asks for it
    a, b = np.asarray(fast.field.values), np.asarray(slow.field.values)
    assert np.abs(a - b).max() <= 1e-12 * float(np.abs(b).max())
    assert fast.newton_iterations == slow.newton_iterations
    assert fast.max_newton_iterations == slow.max_newton_iterations
    assert fast.max_residual == pytest.approx(slow.max_residual, rel=1e-3, abs=1e-13)
    assert (fast.extrapolation is None) == (slow.extrapolation is None) == (which == "Verlet")
    if fast.extrapolation is not None and slow.extrapolation is not None:
        assert np.allclose(fast.extrapolation.values, slow.extrapolation.values, rtol=1e-9, atol=1e-12)


def test_the_compiled_loop_reports_a_failure_and_the_box_as_today() -> None:
    model, init = _oscillator()
    errors = []
    for compiled in (True, False):
        options = ldft.set_options(compiled_kernels=compiled, compiled_numpy_models=compiled)
        with options, pytest.raises(ldft.ServeError) as err:
            ldft.serve(model, init, slices=30, max_newton=1, progress=False)
        errors.append(err.value)
    fast, slow = errors
    assert str(fast) == str(slow) and "slice 2" in str(fast) and "residual" in str(fast)
    assert fast.slice == slow.slice and fast.residual == pytest.approx(slow.residual, rel=1e-9)
    a, b = np.asarray(fast.result.field.values), np.asarray(slow.result.field.values)
    assert np.array_equal(np.isnan(a), np.isnan(b)) and np.nanmax(np.abs(a - b)) <= 1e-12
    fast_box, slow_box = _both(model, init, slices=60, box=0.805)
    assert fast_box.reason == slow_box.reason and "left the box" in fast_box.reason
    assert fast_box.slices == slow_box.slices
    a, b = np.asarray(fast_box.field.values), np.asarray(slow_box.field.values)
    assert np.array_equal(np.isnan(a), np.isnan(b)) and np.nanmax(np.abs(a - b)) <= 1e-12


@functools.lru_cache(maxsize=8)
def _polynomial(ndim: int, m: int = 1) -> ldft.PolynomialLagrangian:
    """The sine-Gordon case's polynomial class learned on a few leapfrog slices of a small sine-Gordon field
    (one component per copy of it, shifted)."""
    n = {1: 16, 2: 8, 3: 5}[ndim]
    init = _field(ndim, n)
    u = np.asarray(init.values)
    slices = [u[0], u[1]]
    c = (0.04 / 0.1) ** 2
    for _ in range(8):  # the leapfrog of psi_tt = Laplacian psi - sin psi on the periodic lattice
        b = slices[-1]
        lap = sum(np.roll(b, s, k) for k in range(ndim) for s in (1, -1)) - 2 * ndim * b
        slices.append(2 * b - slices[-2] + c * lap - 0.04**2 * np.sin(b))
    served = init.isel(t=[0] * len(slices)).copy(data=np.stack(slices))
    served = served.assign_coords(t=0.04 * np.arange(len(slices)))
    if m > 1:
        served = xr.concat([served + 0.1 * c for c in range(m)], dim="component").transpose(..., "component")
        served = served.assign_coords(component=[f"c{c}" for c in range(m)])
    poly = ldft.PolynomialLagrangian(orders=(2, 6 if m > 1 else 12), time_symmetric=True)
    ldft.learn(poly, served, progress=False)
    return poly


@pytest.mark.parametrize(
    ("name", "ndim", "m", "keywords"),
    [
        ("periodic 1+1D", 1, 1, {}),
        ("periodic 2+1D", 2, 1, {}),
        ("periodic 3+1D", 3, 1, {}),
        ("periodic 2+1D, streamed", 2, 1, {"every": 3}),
        ("periodic 1+1D, two components", 1, 2, {}),
    ],
)
def test_a_polynomial_served_on_the_folded_kernels_equals_its_numpy_forms(
    name: str, ndim: int, m: int, keywords: dict, monkeypatch: pytest.MonkeyPatch
) -> None:
    from latticedft._serve import _folded

    calls = []
    evaluate = _folded.FoldedSlices.evaluate
    monkeypatch.setattr(
        _folded.FoldedSlices, "evaluate", lambda self, *a, **k: calls.append(1) or evaluate(self, *a, **k)
    )
    model = _polynomial(ndim, m)
    init = _field(ndim, {1: 16, 2: 8, 3: 5}[ndim])
    if m > 1:
        init = xr.concat([init + 0.1 * c for c in range(m)], dim="component").transpose(..., "component")
        init = init.assign_coords(component=[f"c{c}" for c in range(m)])
    fast = ldft.serve(model, init, slices=12, progress=False, **keywords)  # the default
    assert len(calls) >= 10, name
    with ldft.set_options(compiled_kernels=False):
        slow = ldft.serve(model, init, slices=12, progress=False, **keywords)
    a, b = np.asarray(fast.field.values), np.asarray(slow.field.values)
    assert np.abs(a - b).max() <= 1e-12 * max(1.0, float(np.abs(b).max())), name
    assert fast.slice_solver == slow.slice_solver, name
    assert fast.newton_iterations == slow.newton_iterations, name
    assert fast.extrapolation is not None and slow.extrapolation is not None
    assert np.allclose(fast.extrapolation.values, slow.extrapolation.values, rtol=1e-9, atol=1e-12), name
    assert fast.warnings == slow.warnings, name


def test_a_fresh_jacobians_blocks_come_with_the_gradients(monkeypatch: pytest.MonkeyPatch) -> None:
    """Where slice-Newton reads a fresh Jacobian at an iteration (its first slice's first), the blocks are evaluated
    with the gradients in one pass: the gradients equal the pass without the blocks to the bit, the blocks those
    evaluated afterwards, and in a serve each fresh Jacobian's blocks are evaluated
    once."""
    from latticedft._lattice import as_lattice_field
    from latticedft._serve import _folded, _newton
    from latticedft._serve._slices import _SliceSystem

    model = _polynomial(2)
    f = as_lattice_field(_field(2, 8), source="init", min_slices=2)
    sys_ = _SliceSystem(model, f)
    flat = torch.cat([f.values, f.values[1:] * 1.01]).reshape(3, -1, 1).contiguous()
    folded = _folded.folded_slices(model, sys_, flat)
    assert folded is not None
    together, _ = folded.evaluate(flat, 0.01, 1, folded.grad(flat, 0), True)
    alone, _ = folded.evaluate(flat, 0.01, 1, folded.grad(flat, 0), False)
    assert together.both is not None and alone.both is None
    np.testing.assert_array_equal(together.grad, alone.grad)
    for p, block in together.blocks(sys_.pairs).items():
        np.testing.assert_array_equal(block.numpy(), alone.blocks(sys_.pairs)[p].numpy())
    passes: list[str] = []
    columns = _folded.FoldedSlices.columns

    def counted(self, lo, hi, data):  # a pass with the blocks counts once, by both_columns
        if data is not self.both_data:
            passes.append("grad")
        return columns(self, lo, hi, data)

    monkeypatch.setattr(_folded.FoldedSlices, "columns", counted)
    both_columns = _folded.FoldedSlices.both_columns
    monkeypatch.setattr(
        _folded.FoldedSlices, "both_columns", lambda self, lo, hi: passes.append("both") or both_columns(self, lo, hi)
    )
    block_columns = _folded.FoldedSlices.block_columns
    monkeypatch.setattr(
        _folded.FoldedSlices,
        "block_columns",
        lambda self, lo, hi: passes.append("blocks") or block_columns(self, lo, hi),
    )
    fresh = []
    factorise = _newton._factorise
    monkeypatch.setattr(_newton, "_factorise", lambda *a: fresh.append(1) or factorise(*a))
    served = ldft.serve(model, _field(2, 8), slices=8, progress=False)
    # each fresh Jacobian's blocks evaluated once: with the gradients, or alone after a chord step
    assert passes.count("both") + passes.count("blocks") == len(fresh) >= 1 and passes.count("both") >= 1
    # a pass per iteration and the first slice's older cells, and one of the blocks alone only for a Jacobian
    # refreshed after a chord step (not at the first iteration)
    assert len(passes) < served.newton_iterations + 1 + len(fresh)


def _served_with_states(monkeypatch: pytest.MonkeyPatch, model, init, **keywords) -> tuple[object, list]:
    """The serve and, per Newton slice, its evaluations and ``cache["fresh_first"]`` after it."""
    from latticedft._serve import _stepper

    states = []
    newton = _stepper._newton_slice

    def recorded(*a, **k):
        out = newton(*a, **k)
        states.append((out[0], a[11].get("fresh_first", 0)))
        return out

    monkeypatch.setattr(_stepper, "_newton_slice", recorded)
    return ldft.serve(model, init, slices=24, progress=False, **keywords), states


def test_after_a_slow_chord_slices_start_from_a_fresh_jacobian(monkeypatch: pytest.MonkeyPatch) -> None:
    """A 3+1D polynomial whose chord steps from an older slice's Jacobian take four evaluations: the next slices
    start from a fresh Jacobian (fewer evaluations in all), and the field moves by what Newton's tolerance leaves
    (a hundredth of it where ``rtol`` is a hundredth)."""
    from latticedft._serve import _newton

    model, init = _polynomial(3), _field(3, 6)
    monkeypatch.setattr(_newton, "CHORD_PREDICT", False)  # a slow chord told by its evaluations alone
    fresh, states = _served_with_states(monkeypatch, model, init)
    assert any(it >= _newton.FRESH_FIRST_ON and on == 1 for it, on in states[1:])
    monkeypatch.setattr(_newton, "FRESH_FIRST_ON", 10**9)  # the chord from the last Jacobian, as before
    chord, states = _served_with_states(monkeypatch, model, init)
    assert all(on == 0 for _, on in states)
    assert fresh.newton_iterations < chord.newton_iterations
    a, b = np.asarray(fresh.field.values), np.asarray(chord.field.values)
    scale = float(np.abs(b).max())
    assert 0 < np.abs(a - b).max() <= 24 * 1e-10 * scale  # each slice within rtol = 1e-10 of its solution
    tight = [np.asarray(ldft.serve(model, init, slices=24, progress=False, rtol=1e-12).field.values) for _ in range(2)]
    monkeypatch.setattr(_newton, "FRESH_FIRST_ON", 4)
    tight[0] = np.asarray(ldft.serve(model, init, slices=24, progress=False, rtol=1e-12).field.values)
    assert np.abs(tight[0] - tight[1]).max() <= 0.1 * np.abs(a - b).max()


def test_fresh_starts_try_the_chord_again_every_few_slices(monkeypatch: pytest.MonkeyPatch) -> None:
    """Every ``FRESH_FIRST_RETRY``-th slice started fresh starts with the chord again, and its evaluations decide
    whether the next slices start fresh."""
    from latticedft._serve import _newton

    monkeypatch.setattr(_newton, "FRESH_FIRST_RETRY", 3)
    monkeypatch.setattr(_newton, "CHORD_PREDICT", False)  # the evaluations alone decide
    _, states = _served_with_states(monkeypatch, _polynomial(3), _field(3, 6))
    retries = 0
    for (_, before), (it, after) in zip(states[1:], states[2:]):
        if before and before % 3:
            assert after == before + 1
        else:  # a chord start
            retries += before > 0
            assert after == int(it >= _newton.FRESH_FIRST_ON)
    assert retries >= 2


def test_the_chord_is_kept_only_where_its_rate_reaches_the_target() -> None:
    """A chord step follows one that cut the residual a hundredfold only where that rate reaches the target in
    one more step."""
    from latticedft._serve import _newton

    assert _newton._chord_pays(1e-6, 1e-3, 1e-9)
    assert not _newton._chord_pays(1e-6, 1e-3, 1e-10)  # 1e-9 after one more chord step: a fresh Jacobian
    assert not _newton._chord_pays(1e-6, 1e-5, 1.0)  # cut tenfold only


def test_a_chord_predicted_slow_takes_a_fresh_jacobian(monkeypatch: pytest.MonkeyPatch) -> None:
    """With the chord's rate predicting the target (the default), a 3+1D polynomial whose chord steps are slow
    takes a fresh Jacobian within the slice, its next slices start fresh, and it serves in fewer evaluations
    than with the evaluations alone deciding; the field moves by what Newton's tolerance leaves (a hundredth
    of it where ``rtol`` is a hundredth)."""
    from latticedft._serve import _newton

    model, init = _polynomial(3), _field(3, 6)
    predicted, states = _served_with_states(monkeypatch, model, init)
    assert all(it < _newton.FRESH_FIRST_ON for it, _ in states[1:])
    assert any(on == 1 for _, on in states[1:])
    monkeypatch.setattr(_newton, "CHORD_PREDICT", False)
    counted, _ = _served_with_states(monkeypatch, model, init)
    assert predicted.newton_iterations < counted.newton_iterations
    a, b = np.asarray(predicted.field.values), np.asarray(counted.field.values)
    moved = float(np.abs(a - b).max())
    assert 0 < moved <= 24 * 1e-10 * float(np.abs(b).max())  # each slice within rtol = 1e-10 of its solution
    tight = [np.asarray(ldft.serve(model, init, slices=24, progress=False, rtol=1e-12).field.values)]
    monkeypatch.setattr(_newton, "CHORD_PREDICT", True)
    tight.append(np.asarray(ldft.serve(model, init, slices=24, progress=False, rtol=1e-12).field.values))
    assert np.abs(tight[0] - tight[1]).max() <= 0.1 * moved


def test_the_folded_range_check_equals_todays_outside_the_range() -> None:
    """A field well outside the training range: the compiled excess per slice equals ``_range._excess``'s."""
    from latticedft._lattice import as_lattice_field
    from latticedft._serve._folded import folded_slices
    from latticedft._serve._range import _excess
    from latticedft._serve._slices import _SliceSystem

    model = _polynomial(2)
    f = as_lattice_field(_field(2, 8), source="init", min_slices=2)
    values = f.values * torch.tensor([1.0, 3.0], dtype=torch.float64).reshape(2, 1, 1, 1)
    values[1, 2, 3, 0] = math.nan
    folded = folded_slices(model, _SliceSystem(model, f), values.reshape(2, -1, 1))
    assert folded is not None
    rng = model.trained_range()
    assert rng is not None
    want = _excess(model, rng.to(torch.float64), f, values)
    got = folded.excess(model, values)
    assert got is not None and np.isinf(got).any()
    assert np.allclose(got, want, rtol=1e-12, atol=0.0)


def test_the_folded_feature_extremes_equal_numpy_on_every_cell() -> None:
    """The compiled range pass (``feature_extremes``, no array of the features) gives per slice the least and
    largest feature over the cells to the bit, as numpy's min and max of every cell's features summed over the
    points in order, a not-a-number wherever one is; an infinite value reads as itself; over more cells than
    one chunk, with a last chunk in part."""
    from latticedft._lattice import as_lattice_field, gather_cells
    from latticedft._serve._folded import folded_slices
    from latticedft._serve._slices import _SliceSystem

    model = _polynomial(2)
    f = as_lattice_field(_field(2, 23), source="init", min_slices=2)  # 529 cells: two chunks and a part
    rng = np.random.default_rng(3)
    values = torch.from_numpy(rng.uniform(-2, 2, (5, 23, 23, 1)))
    values[1, 4, 5, 0] = math.nan
    values[3, 7, 0, 0] = math.inf
    values[2] = 0.0  # zeros of both signs: their extremes are equal numbers
    values[2, 1, 1, 0] = -0.0
    folded = folded_slices(model, _SliceSystem(model, f), values.reshape(5, -1, 1))
    assert folded is not None
    proj = np.ascontiguousarray(model.proj.detach().to(torch.float64).numpy())
    fmin, fmax = folded._feature_range(values.numpy().reshape(5, -1, 1), proj)
    cells = gather_cells(values, model.stencil, f.boundary).numpy()  # (slices - 1, *cells, K, 1)
    feats = np.zeros((4, *cells.shape[1:3], proj.shape[0]))
    for a in range(proj.shape[1]):  # the points in order, as the kernel sums them
        feats += proj[:, a] * cells[..., a, 0][..., None]
    feats = feats.reshape(4, -1, proj.shape[0])
    assert np.array_equal(fmin, feats.min(axis=1), equal_nan=True)
    assert np.array_equal(fmax, feats.max(axis=1), equal_nan=True)
    assert np.isnan(fmin[0]).any() and np.isnan(fmax[1]).any() and np.isinf(fmax[2:]).any()
    assert not np.isnan(fmin[3]).all() and np.isfinite(fmin[2]).all()


@pytest.mark.parametrize("ndim", [1, 2, 3])
def test_the_folded_forms_find_a_polynomial_not_affine_as_the_probe_does(ndim: int) -> None:
    """The affine probe's shortcut for a polynomial: its folded Hessian blocks at the probe's states equal
    autograd's to far below the shortcut's margin; a learned (2, 12) polynomial is found not affine by them
    (and by the probe without them), one learned from Klein-Gordon is not, and the probe then answers as
    before."""
    from latticedft._kernel_folded import folded_kernels
    from latticedft._serve._affine import _AffineSlices
    from latticedft._serve._folded import _ALL_PAIRS, NOT_AFFINE_MARGIN, not_affine_by_forms

    model = _polynomial(ndim)
    k = model.stencil.size
    gen = torch.Generator().manual_seed(12345)
    x = 0.8 * (2 * torch.rand(12, k, 1, generator=gen, dtype=torch.float64) - 1)
    x[0] = 0.0
    pairs = [(a, b) for a in range(k) for b in range(k)]
    want = torch.stack([cell_derivatives(model, x, pairs)[1][p] for p in pairs], 1).numpy().reshape(12, -1)
    assert not_affine_by_forms(model, x.numpy())
    data = _ALL_PAIRS[model][2]  # the folded forms of every pair it evaluated
    out, flat = np.empty((12, data[3].shape[1])), np.ascontiguousarray(x.numpy().reshape(12 * k, 1))
    site_of = np.ascontiguousarray(np.arange(12 * k).reshape(12, k).T)
    folded_kernels().folded_cells(flat, flat, site_of, np.zeros(k, dtype=np.int64), *data, out)
    big = np.abs(want[0]).max()
    assert np.abs(out[:, k:] - want).max() <= 1e-4 * NOT_AFFINE_MARGIN * big  # round-off, far below the margin
    assert np.abs(want - want[0]).max() > NOT_AFFINE_MARGIN * big
    assert _AffineSlices.probe(model, model.stencil, 1, 0.8) is None
    with ldft.set_options(compiled_kernels=False):  # the probe alone: the same answer
        assert not not_affine_by_forms(model, x.numpy())
        assert _AffineSlices.probe(model, model.stencil, 1, 0.8) is None
    quad = ldft.PolynomialLagrangian(orders=(2, 2))  # learned from Klein-Gordon: its DEL affine
    ldft.learn(quad, ldft.serve(lagrangians.klein_gordon(1.0), _field(ndim, 8), slices=8, progress=False).field)
    assert not not_affine_by_forms(quad, x.numpy())
    found = _AffineSlices.probe(quad, quad.stencil, 1, 0.8)
    with ldft.set_options(compiled_kernels=False):
        alone = _AffineSlices.probe(quad, quad.stencil, 1, 0.8)
    assert found is not None and alone is not None
    assert all(np.array_equal(a, b) for a, b in zip(found, alone))


@pytest.mark.parametrize("ndim", [1, 2, 3])
def test_the_earlier_cells_gradients_are_the_later_points_columns_to_the_bit(ndim: int) -> None:
    """The first Newton slice's earlier cells: ``FoldedSlices.grad`` runs the chains of the columns of the points
    on the later slice only; those columns equal the whole gradients' to the bit, the others are zero, and the
    slice's residual from them is the same. A second field of the same model state reuses the Horner forms; a
    changed state builds its own."""
    from latticedft._lattice import as_lattice_field
    from latticedft._serve._folded import FoldedCells, folded_slices
    from latticedft._serve._slices import _SliceSystem

    model, m = _polynomial(ndim), 1
    f = as_lattice_field(_field(ndim, {1: 40, 2: 9, 3: 5}[ndim]), source="init", min_slices=2)
    sys_ = _SliceSystem(model, f)
    flat = (f.values * torch.tensor([1.0, 1.01], dtype=torch.float64).reshape(2, *[1] * (ndim + 1))).reshape(2, -1, m)
    flat = flat.contiguous()
    folded = folded_slices(model, sys_, flat)
    assert folded is not None
    whole = FoldedCells(folded, flat[0].numpy(), flat[1].numpy()).grad
    got = folded.grad(flat, 0)
    later = np.repeat(folded.upper.astype(bool), m)
    assert later.any() and not later.all()
    assert np.array_equal(got[:, later], whole[:, later]) and not got[:, ~later].any()
    assert np.abs(whole[:, ~later]).max() > 0  # the columns left out are not zero themselves
    _, r_got = folded.evaluate(flat, 0.01, 0, got)
    _, r_whole = folded.evaluate(flat, 0.01, 0, whole)
    assert np.array_equal(r_got, r_whole)
    again = folded_slices(model, sys_, flat)
    assert again is not None and again.kept is folded.kept
    assert folded.kept.get("z later", folded.kept.get("later")) is not None
    with torch.no_grad():
        model.coef.mul_(1.0)  # the same values, a new state
    changed = folded_slices(model, sys_, flat)
    assert changed is not None and changed.horner is not folded.horner
    assert np.array_equal(changed.grad(flat, 0), got)


@pytest.mark.parametrize("every", [True, False])
def test_the_folded_predictor_measures_the_step_scale_as_slices_scale(every: bool) -> None:
    """The folded predictor writes ``2 psi_i - psi_{i-1}`` (plus the older slice's term) on the unknown sites and
    returns ``_slices._scale`` of the slice at its predictor, equal to it in every case: finite values (over more
    sites than its lanes, with a remainder), an infinity, a not-a-number on each slice (``_scale`` keeps one on
    the earliest slice only, as Python's ``max`` does); every site unknown, or some (a Dirichlet frame)."""
    from latticedft._kernel_folded import folded_kernels
    from latticedft._serve._slices import _scale

    mod = folded_kernels()
    rng = np.random.default_rng(5)
    nsite = 203
    rows = np.arange(nsite) if every else np.arange(3, nsite - 3)
    unk = torch.from_numpy(rows)
    for case in range(6):
        flat = torch.from_numpy(rng.uniform(-2, 2, (4, nsite, 1)))
        if case == 1:
            flat[2, 50, 0] = -math.inf
        elif case in (2, 3, 4):
            flat[case - 1, 7 if case != 4 else 0, 0] = math.nan  # slices 1, 2; an older slice's on the predictor
        elif case == 5:
            flat[:3] = 0.0
        older = flat[0].clone()
        want_next = flat[3].clone()
        want_next[unk] = (2 * flat[2, unk] - flat[1, unk]) + (flat[2, unk] - 2 * flat[1, unk] + older[unk])
        got = mod.predict(flat[1].numpy(), flat[2].numpy(), flat[3].numpy(), older.numpy(), rows)
        assert np.array_equal(flat[3].numpy(), want_next.numpy(), equal_nan=True)
        scale = max(float(got[0]), float(got[1]), float(got[2]), 1e-300)
        want = _scale(flat, 2, unk)
        assert scale == want or (math.isnan(scale) and math.isnan(want)), case


@pytest.mark.parametrize("ndim", [2, 3])
def test_a_fresh_folded_jacobian_is_read_from_its_columns_as_from_its_blocks(ndim: int) -> None:
    """A fresh Jacobian on the folded kernels: the slice matrix read from the evaluated columns in CSR order and
    the diagonal kept with the blocks (summed once for the singular values and the factorisation) equal those
    of the blocks as a plain dict to the bit, and blocks evaluated by the pass of their columns alone (a fresh
    Jacobian after an iteration evaluated without them) equal those evaluated with the gradients; on a
    Dirichlet frame too (fewer unknowns than cells)."""
    from latticedft._lattice import as_lattice_field
    from latticedft._serve._folded import FoldedCells, folded_slices
    from latticedft._serve._slices import Blocks, _SliceSystem

    model = _polynomial(ndim)
    init = _field(ndim, {2: 9, 3: 5}[ndim])
    frame = init.copy()
    for d in frame.dims[1:]:
        frame[d].attrs = {}  # no periodic attribute: a Dirichlet frame
    for f0 in (init, frame):
        f = as_lattice_field(f0, source="init", min_slices=2)
        sys_ = _SliceSystem(model, f)
        flat = (f.values * torch.tensor([1.0, 1.02], dtype=torch.float64).reshape(2, *[1] * (ndim + 1))).contiguous()
        flat = flat.reshape(2, -1, 1)
        folded = folded_slices(model, sys_, flat)
        assert folded is not None
        blocks = FoldedCells(folded, flat[0].numpy(), flat[1].numpy(), with_blocks=True).blocks(sys_.pairs)
        assert isinstance(blocks, Blocks) and blocks.columns is not None
        alone = FoldedCells(folded, flat[0].numpy(), flat[1].numpy()).blocks(sys_.pairs)  # the blocks' pass alone
        assert alone.columns is not None and alone.columns[1] == 0
        assert folded.kept.get("z blocks", folded.kept.get("blocks")) is not None
        assert all(torch.equal(alone[p], blocks[p]) for p in sys_.pairs)
        assert np.array_equal(sys_.csr(alone, 0.003).data, sys_.csr(blocks, 0.003).data)
        plain = dict(blocks)
        got, want = sys_.csr(blocks, 0.003), sys_.csr(plain, 0.003)
        assert np.array_equal(got.indptr, want.indptr) and np.array_equal(got.indices, want.indices)
        assert np.array_equal(got.data, want.data) and np.abs(want.data).max() > 0
        diag = sys_.diagonal(blocks)
        assert sys_.diagonal(blocks) is diag and torch.equal(diag, sys_.diagonal(plain))
        assert sys_.site_singular_values(blocks) == sys_.site_singular_values(plain)


def test_the_folded_kernels_are_on_by_default_and_not_for_other_models() -> None:
    from latticedft._lattice import as_lattice_field
    from latticedft._serve._folded import folded_slices
    from latticedft._serve._slices import _SliceSystem

    model = _polynomial(1)
    f = as_lattice_field(_field(1, 16), source="init", min_slices=2)
    sys_ = _SliceSystem(model, f)
    flat = f.values.reshape(2, -1, 1).contiguous()
    assert folded_slices(model, sys_, flat) is not None
    assert folded_slices(sine_gordon().bind(2, 1, (0.04, 0.1)), sys_, flat) is None
    with ldft.set_options(compiled_kernels=False):
        assert folded_slices(model, sys_, flat) is None
    with ldft.set_options(folded_max_powers=1):  # the same model, an option that no longer lets it fold
        assert folded_slices(model, sys_, flat) is None
    assert folded_slices(model, sys_, flat) is not None


def test_a_polynomial_that_does_not_fold_keeps_its_numpy_forms_with_one_info_line(
    caplog: pytest.LogCaptureFixture,
) -> None:
    model = copy.deepcopy(_polynomial(1))  # its own folded data: built afresh under the option below
    init = _field(1, 16)
    with ldft.set_options(folded_max_powers=1), caplog.at_level(logging.INFO, "latticedft"):
        fast = ldft.serve(model, init, slices=6, progress=False)
        ldft.serve(model, init, slices=6, progress=False)
    with ldft.set_options(compiled_kernels=False, folded_max_powers=1):  # the numpy forms, as the fallback serves
        slow = ldft.serve(model, init, slices=6, progress=False)
    assert np.array_equal(np.asarray(fast.field.values), np.asarray(slow.field.values))
    lines = [r.getMessage() for r in caplog.records if "compiled polynomial kernels unavailable" in r.getMessage()]
    assert len(lines) == 1


def test_a_class_kernel_equals_the_generic_folded_kernel() -> None:
    """The monomial loop unrolled for a class (variables, columns) sums the same monomials as the generic one."""
    from latticedft._kernel_folded import folded_cells_kernel, folded_kernels

    rng = np.random.default_rng(3)
    nvar, cols, k, ncell = 3, 5, 4, 300
    lo, hi = rng.standard_normal((ncell, 1)), rng.standard_normal((ncell, 1))
    site_of = rng.integers(0, ncell, size=(k, ncell))
    upper = np.array([0, 1, 0, 0])
    w, shift = rng.standard_normal((k, nvar)), rng.standard_normal(nvar)
    expo = rng.integers(0, 4, size=(7, nvar))  # seven monomials: one unrolled pass of four and three alone
    gc = rng.standard_normal((7, cols))
    want, got = np.empty((ncell, cols)), np.empty((ncell, cols))
    folded_kernels().folded_cells(lo, hi, site_of, upper, w, shift, expo, gc, want)
    kernel = folded_cells_kernel(nvar, cols)
    assert kernel is not None
    kernel(lo, hi, site_of, upper, w, shift, expo, gc, got)
    assert np.allclose(got, want, rtol=1e-13, atol=1e-13 * float(np.abs(want).max()))


def test_a_windowed_run_solves_each_window_in_runs_of_slices(monkeypatch: pytest.MonkeyPatch) -> None:
    """Served through small windows (``every = 3``, windows of four slices), every slice after the first Newton slice is
    solved by runs of slices, each window's first position too (its older slice the one before the window):
    the whole field's values, iterations and residual, to the bit."""
    from latticedft._serve import _fused

    single = []
    solve = _fused.FusedSlices.solve
    monkeypatch.setattr(_fused.FusedSlices, "solve", lambda self, *a: single.append(1) or solve(self, *a))
    field = _field(2, 6)
    with ldft.set_options(compiled_kernels=True):
        whole = ldft.serve(sine_gordon(), field, slices=40, progress=False)
        with ldft.set_options(serve_window_bytes=1):
            windowed = ldft.serve(sine_gordon(), field, slices=40, progress=False, every=3)
    assert len(single) == 2  # the first Newton slice of each run chooses the solver
    kept = np.asarray(whole.field.values)[np.asarray(windowed.field["slice"].values)]
    np.testing.assert_array_equal(np.asarray(windowed.field.values), kept)
    assert (windowed.newton_iterations, windowed.max_residual) == (whole.newton_iterations, whole.max_residual)
