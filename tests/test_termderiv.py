"""The sparse library's closed-form term derivatives equal forward-mode differentiation of its features."""

from __future__ import annotations

import warnings

import pytest
import torch

import latticedft as ldft
from latticedft import Library
from latticedft._action import CellDerivatives, cell_derivatives, numpy_closed_forms
from latticedft._models._linear import LinearLagrangian
from latticedft._stencil import Stencil

CASES = [
    ("kinetic + trig:3 + kinetic*trig:2 + kinetic*kinetic*trig:1", 1, 1, "average"),
    ("kinetic + norm:-1,-4 + kinetic*norm:-3 + radial*norm:-5 + log + cross", 1, 2, "average"),
    ("kinetic + gradient + poly:4 + trig:1 + kinetic*gradient + exp:0.5", 2, 1, "anchor"),
    ("velocities + trig:1 + cosdiff*velocities + sindiff + poly:2", 1, 2, "mean"),
    ("kinetic + gradient + trig:2(poly:2)", 3, 1, "average"),
    ("kinetic + poly:4 + trig:2:0.5@2 + exp:0.5@2 + kinetic*trig:1@3", 1, 1, "average"),
    ("kinetic + gradient + trig:1@2 + exp@2 + gradient*trig:1@2", 2, 2, "anchor"),
]
#: The cases whose serving derivatives are compared with autograd (the on-site trig and exp of powers among them).
SERVED = CASES[:3] + CASES[5:]


def _bound(library: object, n: int, m: int, at: str) -> LinearLagrangian:
    model = ldft.MODELS["sparse"](library=library, at=at, stencil=Stencil.first_order(n))
    model.bind(n, m, (0.1, 0.2, 0.3)[:n])
    return model


@pytest.mark.parametrize(("library", "n", "m", "at"), CASES)
def test_closed_form_derivatives_equal_forward_mode(library: str, n: int, m: int, at: str) -> None:
    model = _bound(library, n, m, at)
    k = model.stencil.size
    x = 0.5 + torch.rand(4, 3, k, m, dtype=torch.float64, generator=torch.Generator().manual_seed(n + m))
    pairs = [(a, b) for a in range(k) for b in range(k)]
    d, blocks = model.feature_derivatives(x, pairs)
    d_ref, blocks_ref = LinearLagrangian.derivatives_of_features(model, x, pairs, True)
    torch.testing.assert_close(d, d_ref, rtol=1e-13, atol=1e-13 * float(d_ref.abs().max()))
    for p in pairs:
        torch.testing.assert_close(blocks[p], blocks_ref[p], rtol=1e-13, atol=1e-13 * float(blocks_ref[p].abs().max()))
    _, only = model.feature_derivatives(x, pairs[:1], first=False)
    assert only.keys() == {pairs[0]}


def _term_by_term(model: LinearLagrangian, x: torch.Tensor, pairs: list[tuple[int, int]]) -> tuple[torch.Tensor, dict]:
    """The closed-form derivatives written into place one derivative and pair at a time (the order of summation
    that :func:`closed_derivatives` keeps)."""
    rule = model._closed_rule(model.terms)  # type: ignore[operator]
    maps, spacing, c = model._input_maps(), model.spacing, model.n_terms  # type: ignore[operator]
    k, m = x.shape[-2], x.shape[-1]
    scale = [1.0] + [1.0 / h for h in spacing]
    d_out = x.new_zeros(*x.shape[:-2], k, m, c)
    blocks = {p: x.new_zeros(*x.shape[:-2], m, m, c) for p in pairs}
    for a_map in maps:
        w = torch.einsum("rk,...km->...rm", a_map, x)
        args = [w[..., r, i] / spacing[r - 1] if r else w[..., r, i] for r in range(len(scale)) for i in range(m)]
        values = rule.fn(*args)
        nf = len(rule.first)
        grad = x.new_zeros(*x.shape[:-2], rule.n_vars, c)
        for (v, t), val in zip(rule.first, values[:nf]):
            grad[..., v, t] = val * scale[v // m]
        d_out += torch.einsum("ra,...ric->...aic", a_map, grad.unflatten(-2, (len(scale), m)))
        for (v, u, t), val in zip(rule.second, values[nf:]):
            (rv, iv), (ru, iu) = divmod(v, m), divmod(u, m)
            h = val * (scale[rv] * scale[ru])
            for a, b in pairs:
                blocks[(a, b)][..., iv, iu, t] += (a_map[rv, a] * a_map[ru, b]).item() * h
                if v != u:
                    blocks[(a, b)][..., iu, iv, t] += (a_map[ru, a] * a_map[rv, b]).item() * h
    if len(maps) > 1:
        d_out = d_out / len(maps)
        blocks = {p: b / len(maps) for p, b in blocks.items()}
    return d_out, blocks


@pytest.mark.parametrize(("library", "n", "m", "at"), CASES)
def test_closed_form_derivatives_equal_the_term_by_term_sum_to_the_bit(library: str, n: int, m: int, at: str) -> None:
    model = _bound(library, n, m, at)
    k = model.stencil.size
    x = 0.5 + torch.rand(5, k, m, dtype=torch.float64, generator=torch.Generator().manual_seed(7 + n + m))
    x[..., 0, 0] *= -1.3
    pairs = [(a, b) for a in range(k) for b in range(k)]
    want_d, want_blocks = _term_by_term(model, x, pairs)
    got_d, got_blocks = model.feature_derivatives(x, pairs)
    assert torch.equal(got_d, want_d)
    assert all(torch.equal(got_blocks[p], want_blocks[p]) for p in pairs)
    alone, _ = model.feature_derivatives(x)  # without the Hessian blocks: the same first derivatives
    assert torch.equal(alone, want_d)


def test_a_user_term_is_differentiated_in_forward_mode() -> None:
    model = _bound(Library.parse("kinetic") + Library.function(lambda q: q[..., 0] ** 3, "cube"), 1, 1, "anchor")
    x = torch.rand(5, 2, 1, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    d, _ = model.feature_derivatives(x)
    d_ref, _ = LinearLagrangian.derivatives_of_features(model, x, (), True)
    torch.testing.assert_close(d, d_ref)


@pytest.mark.parametrize(("library", "n", "m", "at"), SERVED)
def test_serving_derivatives_of_the_kept_terms_equal_autograd(library: str, n: int, m: int, at: str) -> None:
    model = _bound(library, n, m, at)
    coef = torch.rand(model.n_terms, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    with torch.no_grad():
        model.coef.copy_(torch.where(torch.arange(model.n_terms) % 3 == 1, 0.0, coef))
    k = model.stencil.size
    x = 0.5 + torch.rand(6, k, m, dtype=torch.float64, generator=torch.Generator().manual_seed(2))
    pairs = [(0, 0), (0, k - 1), (k - 1, 0)]
    closed = model.fast_derivatives(x, pairs)
    assert closed is not None
    grad, blocks = cell_derivatives(model, x, pairs, create_graph=True)  # autograd (closed forms skipped)
    torch.testing.assert_close(closed[0], grad.detach(), rtol=1e-13, atol=1e-13)
    for p in pairs:
        torch.testing.assert_close(closed[1][p], blocks[p].detach(), rtol=1e-13, atol=1e-13)


@pytest.mark.parametrize(("library", "n", "m", "at"), CASES)
def test_numpy_forms_equal_the_torch_closed_forms(library: str, n: int, m: int, at: str) -> None:
    model = _bound(library, n, m, at)
    coef = torch.rand(model.n_terms, dtype=torch.float64, generator=torch.Generator().manual_seed(3))
    with torch.no_grad():
        model.coef.copy_(torch.where(torch.arange(model.n_terms) % 3 == 2, 0.0, coef - 0.5))
    k = model.stencil.size
    x = 0.5 + torch.rand(7, k, m, dtype=torch.float64, generator=torch.Generator().manual_seed(4))
    pairs = [(a, b) for a in range(k) for b in range(k)]
    closed = model.fast_derivatives(x, pairs)
    forms = model.numpy_derivatives(pairs)
    assert closed is not None and forms is not None
    grad, blocks = forms(x.numpy())
    assert grad.shape == (7, k, m) and len(blocks) == len(pairs)
    torch.testing.assert_close(torch.from_numpy(grad), closed[0], rtol=1e-13, atol=1e-13 * float(closed[0].abs().max()))
    for p, b in zip(pairs, blocks):
        ref = closed[1][p]
        torch.testing.assert_close(torch.from_numpy(b), ref, rtol=1e-13, atol=1e-13 * float(ref.abs().max()))
    only, none = model.numpy_derivatives(())(x.numpy())  # the gradient alone
    assert none == [] and (only == grad).all()


def test_a_user_term_has_no_numpy_forms() -> None:
    model = _bound(Library.parse("kinetic") + Library.function(lambda q: q[..., 0] ** 3, "cube"), 1, 1, "anchor")
    with torch.no_grad():
        model.coef.fill_(1.0)
    assert model.numpy_derivatives([(0, 1)]) is None
    assert model.fast_derivatives(torch.rand(3, 2, 1, dtype=torch.float64), [(0, 1)]) is None


@pytest.mark.parametrize("kind", ["sparse", "polynomial"])
def test_numpy_forms_on_diverging_cells_are_non_finite_without_a_warning(kind: str) -> None:
    """Serving evaluates numpy closed forms (``CellDerivatives``) on a diverging field silently: the values turn
    non-finite, which serving tests for, as with the torch forms."""
    if kind == "sparse":
        model = _bound(Library.parse("kinetic + gradient + poly:4 + trig:1"), 2, 1, "anchor")
    else:
        model = ldft.PolynomialLagrangian(orders=[2, 4], stencil=Stencil.first_order(2))
        model.bind(2, 1, (0.1, 0.1), None)
    with torch.no_grad():
        for p in model.parameters():
            p.fill_(1.0)
    k = model.stencil.size
    cells = torch.full((3, k, 1), 1e200, dtype=torch.float64)
    assert numpy_closed_forms(model, cells, [(0, 0)]) is not None  # the numpy forms serve these cells
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a numpy RuntimeWarning would fail the test
        derivatives = CellDerivatives(model, cells)
        blocks = derivatives.blocks([(0, 0)])
    assert not torch.isfinite(derivatives.grad).all() and not torch.isfinite(blocks[(0, 0)]).all()
