"""1D serving: a batch of trajectories stepped together, in numpy (``_fast1d``) when the model has numpy
closed forms, else by torch (``_batch``)."""

from __future__ import annotations

import numpy as np

from .._contract import NumpyForms
from .._lattice import LatticeField
from .._models import AbstractLagrangian
from ._batch import _Batch
from ._fast1d import FastBatch, numpy_derivatives_of, serve_fast, step_fast
from ._options import ServeOptions
from ._result import ServeResult
from ._stepper import step_members


def _serve_batch(
    model: AbstractLagrangian,
    fs: list[LatticeField],
    steps: list[int],
    options: ServeOptions,
) -> list[ServeResult]:
    """Step a batch of 1D trajectories together; a member that fails or leaves the box retires alone.

    ``mode="newton"`` solves all running members' slices in one batched Newton; ``"sweep"`` one member at a
    time (in 1D the site-by-site sweep is that same Newton on the one site). A model with numpy closed forms
    (:meth:`LinearLagrangian.numpy_derivatives`) runs the same loop in numpy (``_fast1d``).
    """
    mode, rtol, max_newton, box = options.mode, options.rtol, options.max_newton, options.box
    progress = options.progress
    derivatives = numpy_derivatives_of(model)
    if derivatives is not None:
        return serve_fast(model, fs, steps, mode, rtol, max_newton, box, progress, derivatives)
    batch = _Batch(model, fs, steps, mode, progress)
    step_members(batch, rtol, max_newton, box)
    return batch.results()


class WindowServing:
    """What :func:`_serve_batch` serves on one 1D field at a time for a model with numpy closed forms, called many
    times with the same model (whose coefficients, and so closed forms, may change between calls) and options, without
    building the results: the slices served, ``(slices, m)``, and whether the serve failed. No training-range
    check, no DataArrays, no warnings: for the held-out serving of a fit, which reads the values alone. One batch,
    restarted on each call (:meth:`FastBatch.restart`) instead of built again, each call's values copied out of it;
    each call's first gradient is taken from the closed forms ``derivatives`` (what :func:`_serve_batch` takes from
    torch's closed forms, equal to round-off). The held-out serving of a sparse fit serves every support a few
    slices at a time."""

    def __init__(self, model: AbstractLagrangian, options: ServeOptions):
        self.model, self.options = model, options
        self._batch: FastBatch | None = None

    def __call__(self, f: LatticeField, derivatives: NumpyForms) -> tuple[np.ndarray, bool]:
        """``(values, failed)`` of ``f`` served with the closed forms ``derivatives`` (:func:`numpy_derivatives_of`
        of the model as it is now), the values a copy."""
        batch, options = self._batch, self.options
        if batch is None or batch.m != f.ncomp:
            batch = self._batch = FastBatch(
                self.model, [f], [f.shape[0]], derivatives, options.mode, options.progress, numpy_first=True
            )
        else:
            batch.restart([f], derivatives)
        step_fast(batch, options.rtol, options.max_newton, options.box)
        return batch.npsi[0, : batch.nlength[0]].copy(), batch.failed[0]
