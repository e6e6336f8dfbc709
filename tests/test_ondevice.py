"""Slice-Newton on the model's device (``serve(device="cuda")``), taken on the CPU here (``ON_CPU``): the
served fields equal slice-Newton's, whole or streamed, and a slice it cannot finish is solved as before."""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
import pytest
import torch

import latticedft as ldft
from latticedft import systems
from latticedft._serve import _ondevice

from helpers import sine_gordon, smooth_start


@pytest.fixture
def on_cpu(monkeypatch: pytest.MonkeyPatch) -> Iterator[None]:
    monkeypatch.setattr(_ondevice, "ON_CPU", True)
    yield


def served(model: ldft.AbstractLagrangian, init: object, device_path: bool, **kw: object) -> ldft.ServeResult:
    """``model`` served from ``init``, on the device path or not; the device path must solve every slice."""
    solved = []
    solve = _ondevice.DeviceSlices.solve

    def counted(self: _ondevice.DeviceSlices, *args: object) -> object:
        out = solve(self, *args)
        solved.append(out is not None)
        return out

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(_ondevice, "ON_CPU", device_path)
        mp.setattr(_ondevice.DeviceSlices, "solve", counted)
        out = ldft.serve(model, init, progress=False, **kw)
    assert solved == ([True] * (kw.get("slices", 10) - 2) if device_path else [])  # type: ignore[operator]
    return out


@pytest.mark.parametrize("ndim,n", [(2, 12), (3, 6)])
def test_device_slices_serve_what_slice_newton_serves(ndim: int, n: int) -> None:
    model, init = sine_gordon(False), smooth_start(ndim, n)
    plain = served(model, init, False, slices=12)
    device = served(model, init, True, slices=12)
    assert device.slice_solver == plain.slice_solver == "sitewise"
    assert device.newton_iterations == plain.newton_iterations
    np.testing.assert_allclose(device.field.values, plain.field.values, rtol=0, atol=1e-12)


def test_a_closed_form_is_served_by_its_generated_derivatives(on_cpu: None) -> None:
    """With its closed form, the device path evaluates sympy's derivatives of it (no autograd): the field is
    the one slice-Newton serves by autograd, to round-off."""
    built = []
    closed_terms = _ondevice.closed_terms

    def spied(*args: object) -> object:
        built.append(closed_terms(*args))  # type: ignore[arg-type]
        return built[-1]

    init = smooth_start(2, 10)
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(_ondevice, "closed_terms", spied)
        device = ldft.serve(sine_gordon(), init, slices=10, progress=False)
    plain = served(sine_gordon(False), init, False, slices=10)
    assert len(built) == 1 and built[0] is not None
    np.testing.assert_allclose(device.field.values, plain.field.values, rtol=0, atol=1e-12)


def test_bounded_lattice_keeps_its_known_sites() -> None:
    """Fixed ends: the boundary sites of each slice come from the input, the interior from the device path."""
    init = smooth_start(2, 10, periodic=False)
    whole = systems.make_field(
        np.repeat(init.values[:1], 10, axis=0), init.dims, spacing=(0.04, 0.1, 0.1)
    )  # the fixed ends hold their first values on every slice
    whole.values[1] = init.values[1]
    model = sine_gordon(False)
    plain = served(model, whole, False)
    device = served(model, whole, True)
    assert plain.complete and device.complete
    np.testing.assert_allclose(device.field.values, plain.field.values, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(device.field.values[:, 0], whole.values[:, 0])


def test_streamed_window_reads_the_slices_it_holds() -> None:
    """A rolling window of one slice at a time (every chunk shifts it): the device keeps slices by their index
    in the whole field, so the kept slices equal those of the whole field served the same way."""
    model, init = sine_gordon(False), smooth_start(2, 8)
    whole = served(model, init, True, slices=15)
    with ldft.set_options(serve_window_bytes=1):  # four slices in the window
        kept = served(model, init, True, slices=15, every=2)
    np.testing.assert_array_equal(kept.field.values, whole.field.sel(t=kept.field.t).values)


def test_a_slice_the_device_cannot_finish_goes_to_slice_newton(on_cpu: None, monkeypatch: pytest.MonkeyPatch) -> None:
    model, init = sine_gordon(False), smooth_start(2, 8)
    plain = served(model, init, False, slices=10)
    calls = []
    iterate = _ondevice.DeviceSlices._iterate

    def failing(self: _ondevice.DeviceSlices, *args: object) -> object:
        calls.append(1)
        return None if len(calls) == 3 else iterate(self, *args)

    monkeypatch.setattr(_ondevice.DeviceSlices, "_iterate", failing)
    out = ldft.serve(model, init, slices=10, progress=False)
    assert len(calls) == 8  # every slice, the third by slice-Newton too (the window read afresh after)
    np.testing.assert_allclose(out.field.values, plain.field.values, rtol=0, atol=1e-12)


def test_a_coupled_jacobian_is_left_to_slice_newton() -> None:
    """Time and space differences mixed (``eps dt dx``): the slice Jacobian couples neighbours, the probe at the
    first slice says so, and slice-Newton serves every slice as it does without the device path."""

    def fn(c: torch.Tensor, h: tuple[float, ...]) -> torch.Tensor:
        u = c[..., 0, 0]
        dt = (c[..., 1, 0] - u) / h[0]
        out = 0.5 * dt**2 - (1 - torch.cos(u))
        for k in range(1, len(h)):
            dk = (c[..., k + 1, 0] - u) / h[k]
            out = out - 0.5 * dk**2 + 0.2 * dt * dk
        return out

    model, init = ldft.AnalyticLagrangian(fn, name="coupled"), smooth_start(2, 8)
    plain = ldft.serve(model, init, slices=6, progress=False)
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(_ondevice, "ON_CPU", True)
        device = ldft.serve(model, init, slices=6, progress=False)
    assert plain.slice_solver == device.slice_solver == "krylov"
    np.testing.assert_array_equal(device.field.values, plain.field.values)


def test_not_taken_for_vector_fields_or_on_the_cpu() -> None:
    model, init = sine_gordon(False), smooth_start(2, 6)
    model.bind(3, 1, (0.04, 0.1, 0.1))
    from latticedft._lattice import as_lattice_field
    from latticedft._serve._slices import _SliceSystem

    sys = _SliceSystem(model, as_lattice_field(init, source="init", min_slices=2))
    flat = torch.zeros(3, sys.nsite, 1, dtype=torch.float64)
    assert _ondevice.device_slices(model, sys, flat, torch.device("cpu")) is None
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(_ondevice, "ON_CPU", True)
        assert _ondevice.device_slices(model, sys, flat, torch.device("cpu")) is not None
        assert _ondevice.device_slices(model, sys, flat.float(), torch.device("cpu")) is None


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
@pytest.mark.parametrize(
    "ndim,n,periodic,closed", [(2, 16, True, False), (3, 8, True, False), (2, 10, False, False), (3, 8, True, True)]
)
def test_on_cuda_the_field_is_the_cpu_field(ndim: int, n: int, periodic: bool, closed: bool) -> None:
    model, init = sine_gordon(closed), smooth_start(ndim, n, periodic)
    if not periodic:
        init = systems.make_field(np.repeat(init.values[:1], 8, axis=0), init.dims, spacing=(0.04, 0.1, 0.1))
        init.values[1] = smooth_start(ndim, n, periodic).values[1]
    cpu = ldft.serve(model, init, slices=8, progress=False)
    cuda = ldft.serve(model, init, slices=8, progress=False, device="cuda")
    assert cuda.device.startswith("cuda") and cuda.slice_solver == "sitewise"
    np.testing.assert_allclose(cuda.field.values, cpu.field.values, rtol=0, atol=1e-12)
