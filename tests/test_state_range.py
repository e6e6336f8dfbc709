"""The state check measured by ``benchmarks.state_range`` (not kept as a warning: docs/uncertainty.md): a served
cell inside every feature's training range whose state (its features together) no training cell held lies far
from the training cells' states, one on a training orbit does not."""

from __future__ import annotations

import latticedft as ldft
from benchmarks.state_range import TOL, StateCloud
from latticedft._serve._range import EXTRAPOLATION_TOL

from helpers import oscillator_data


def test_a_state_between_the_training_orbits_is_far_and_one_on_them_is_near():
    # the quartic oscillator launched at 0.4 and 1.2 (training), and at 0.8: an orbit between them
    _, (low, high, middle) = oscillator_data(amplitudes=(0.4, 1.2, 0.8), steps=120)
    model = ldft.PolynomialLagrangian((2, 4))
    ldft.learn(model, [low, high])
    cloud = StateCloud(model, [low, high], None)
    between = ldft.serve(model, middle.isel(t=slice(0, 2)), slices=120)
    assert between.warnings == [] and float(between.extrapolation.max()) <= EXTRAPOLATION_TOL  # inside the box
    on = ldft.serve(model, high.isel(t=slice(30, 32)), slices=80)  # the 1.2 orbit from another phase
    far, near = cloud.distance(between.field, None), cloud.distance(on.field, None)
    assert far.shape == (120,) and near.shape == (80,)
    assert far.max() > 2 * TOL and near.max() < TOL / 10
