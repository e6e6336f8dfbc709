"""The affine recurrence's check against the model's own DEL, on every slice or every k-th."""

from __future__ import annotations

import numpy as np

import latticedft as ldft
from latticedft import lagrangians, systems
from latticedft._serve._affine import passing_prefix


def test_the_passing_prefix_stops_at_the_last_check_before_a_failure() -> None:
    bound = np.full(9, 1.0)
    assert passing_prefix(np.array([0.1] * 9), bound) == 9
    assert passing_prefix(np.array([0.1, 0.1, 5.0, 0.1, 0.1, 0.1, 0.1, 0.1, 0.1]), bound) == 2
    assert passing_prefix(np.array([np.inf] + [0.1] * 8), bound) == 0
    every3 = np.array([np.nan, np.nan, 0.1, np.nan, np.nan, 0.2, np.nan, np.nan, 3.0])
    assert passing_prefix(every3, bound) == 6  # slices 7 and 8 are not vouched for by a passing check
    assert passing_prefix(np.array([np.nan, np.nan, 9.0]), np.full(3, 1.0)) == 0


def test_checking_every_kth_slice_serves_the_same_field() -> None:
    n = 12
    x = np.arange(n) / n
    u = 0.8 * np.sin(2 * np.pi * x)[:, None] * np.cos(2 * np.pi * x)[None, :]
    attrs = {d: {"periodic": "true", "period": n * 0.1} for d in ("y", "x")}
    init = systems.make_field(np.stack([u, u]), ("t", "y", "x"), spacing=(0.04, 0.1, 0.1), coord_attrs=attrs)
    data = ldft.serve(lagrangians.klein_gordon(1.0), init, slices=16, progress=False).field
    model = ldft.PolynomialLagrangian(orders=(2, 2))
    ldft.learn(model, data, progress=False)
    every = ldft.serve(model, init, slices=40, progress=False)
    with ldft.set_options(affine_check_every=7):
        sparse = ldft.serve(model, init, slices=40, progress=False)
    assert every.solver == sparse.solver == "affine"
    assert np.array_equal(np.asarray(every.field.values), np.asarray(sparse.field.values))
    assert sparse.max_residual <= every.max_residual


def test_the_probe_kept_per_model_state_follows_a_change_of_parameters() -> None:
    # the probe's answer (Hessian and constant gradient) is kept per model state: a model whose coefficients
    # are replaced in place is probed afresh, and serves what a model holding those coefficients from the start
    # serves, to the bit
    import copy

    from latticedft._serve import _affine

    n = 12
    x = np.arange(n) / n
    u = 0.8 * np.sin(2 * np.pi * x)[:, None] * np.cos(2 * np.pi * x)[None, :]
    attrs = {d: {"periodic": "true", "period": n * 0.1} for d in ("y", "x")}
    init = systems.make_field(np.stack([u, u]), ("t", "y", "x"), spacing=(0.04, 0.1, 0.1), coord_attrs=attrs)
    models = []
    for mass in (1.0, 2.0):
        data = ldft.serve(lagrangians.klein_gordon(mass), init, slices=16, progress=False).field
        model = ldft.PolynomialLagrangian(orders=(2, 2))
        ldft.learn(model, data, progress=False)
        models.append(model)
    first, second = models
    fresh = copy.deepcopy(second)  # its own tensors: nothing kept for it
    before = ldft.serve(first, init, slices=30, progress=False)
    assert first in _affine._PROBED
    again = ldft.serve(first, init, slices=30, progress=False)  # the kept answer: the same field
    assert np.array_equal(np.asarray(again.field.values), np.asarray(before.field.values))
    first.load_state_dict(second.state_dict())  # the coefficients replaced in place
    after = ldft.serve(first, init, slices=30, progress=False)
    alone = ldft.serve(fresh, init, slices=30, progress=False)
    assert before.solver == after.solver == alone.solver == "affine"
    assert np.array_equal(np.asarray(after.field.values), np.asarray(alone.field.values))
    assert float(np.abs(np.asarray(after.field.values) - np.asarray(before.field.values)).max()) > 1e-3
