"""Slice-Newton of a kinetic-plus-potential MLP ``L_d`` with its derivatives in closed form, batched over sites.

``KineticPotentialMLPLagrangian`` is a quadratic kinetic part (constant Hessian) minus the mean over the stencil
points of a network potential ``V`` of one site's values. So the gradient of a cell is its values times the
kinetic Hessian, minus ``V'`` of each point's site over ``K``: ``V'`` is needed once per site of a slice, not
once per stencil point of every cell, and once per slice, not per Newton iteration (the DEL of slice ``i``
reads ``V'`` on slice ``i`` only; the unknowns of slice ``i + 1`` enter it through the kinetic part). ``V'``
comes from one forward and one backward pass of the network written out (numpy's matrix products and
activation, compiled passes for the first layer and the activations' derivative; a part of the sites at a
time), instead of autograd over every cell. The residual and the cells' gradients come from compiled passes
written out for the stencil and the kinetic Hessian's nonzeros (``.._kernel_quadratic``; the folded
polynomial's ``quadratic_residual`` and ``quadratic_grad`` where those do not build), the gradients at a
slice's solution only where the next slice reads them; the predictor and range check come from ``._folded``;
the Hessian blocks slice-Newton asks for (of two points on two slices) are the kinetic Hessian's.
:func:`not_affine` answers the affine recurrence's probe from the same closed forms where they decide it.

The sums run in another order than autograd's, so the fields differ from the default path's by round-off:
this path is the default, as the folded polynomial's, and left where ``set_options(compiled_kernels=False)`` asks.
"""

from __future__ import annotations

import logging
import weakref
from collections.abc import Callable
from typing import Any

import numpy as np
import torch

from .._kernel_folded import folded_kernels
from .._kernel_quadratic import quadratic_kernels
from .._models._mlp import KineticPotentialMLPLagrangian
from .._options import option
from ._folded import FoldedSlices, per_model_state
from ._slices import _SliceSystem

__all__ = ["PotentialNet", "PotentialSlices", "not_affine", "potential_slices"]

log = logging.getLogger("latticedft")


def _tanh(y: np.ndarray) -> np.ndarray:
    return np.tanh(y, out=y)


def _sigmoid(y: np.ndarray) -> np.ndarray:
    np.negative(y, out=y)
    np.exp(y, out=y)
    y += 1.0
    return np.reciprocal(y, out=y)


#: Activations written out: ``name -> (act(y) written over y, its kind in the kernel act_slope)``.
_ACTS: dict[str, tuple[Callable[[np.ndarray], np.ndarray], int]] = {"tanh": (_tanh, 0), "sigmoid": (_sigmoid, 1)}


#: Sites per pass of :class:`PotentialNet` (its layers' values, 16 KiB per site-width of 8, stay in the cache
#: between passes: 2048 sites measured 1.29 ms against 1.70 ms for 16,384 sites in one pass, the same values).
_SITES = 2048


class PotentialNet:
    """``V'(x)``: the gradient of a kinetic-potential MLP's potential ``out_scale * net((x - center) / scale)``
    at values ``x`` ``(sites, m)``, by one forward and one backward pass over the sites, :data:`_SITES` at a
    time: numpy's matrix products and activation, the folded module's kernels (``mod``) for the first layer
    and the derivative of the activations (one pass each)."""

    def __init__(self, model: KineticPotentialMLPLagrangian, mod: Any):
        lin = [layer for layer in model.net if isinstance(layer, torch.nn.Linear)]
        self.layers = [(_np(layer.weight).T.copy(), _np(layer.bias)) for layer in lin[:-1]]
        self.out = _np(lin[-1].weight)[0]
        self.mod = mod
        self.act, self.kind = _ACTS[model.activation]
        self.center, self.scale = _np(model.in_center), _np(model.in_scale)
        self.factor = float(model.out_scale) / self.scale
        widths = [w.shape[1] for w, _ in self.layers]
        self.bufs = [np.empty((_SITES, h)) for h in widths]  # a part's activations per hidden layer
        self.backs = [np.empty((_SITES, h)) for h in widths]  # and the gradient in them

    def grad(self, x: np.ndarray) -> np.ndarray:
        """``dV/dx`` ``(sites, m)`` at ``x`` ``(sites, m)`` (a new array)."""
        if not self.layers:
            return np.tile(self.out * self.factor, (x.shape[0], 1))
        x = np.ascontiguousarray(x)
        out = np.empty_like(x)
        for start in range(0, x.shape[0], _SITES):
            self._part(x[start : start + _SITES], out[start : start + _SITES])
        return out

    def _part(self, x: np.ndarray, out: np.ndarray) -> None:
        """``dV/dx`` of at most :data:`_SITES` sites into ``out``."""
        n = x.shape[0]
        bufs, backs = [b[:n] for b in self.bufs], [b[:n] for b in self.backs]
        w0, b0 = self.layers[0]
        self.mod.layer_in(x, self.center, self.scale, w0, b0, bufs[0])
        self.act(bufs[0])
        for (w, b), y, z in zip(self.layers[1:], bufs, bufs[1:]):
            np.matmul(y, w, out=z)
            z += b
            self.act(z)
        d: np.ndarray = self.out
        for k in range(len(self.layers) - 1, -1, -1):
            (self.mod.act_slope if d.ndim == 2 else self.mod.act_slope_row)(bufs[k], d, self.kind)
            d = np.matmul(bufs[k], self.layers[k][0].T, out=backs[k - 1] if k else out)
        d *= self.factor


def _np(t: torch.Tensor) -> np.ndarray:
    return np.ascontiguousarray(t.detach().to(torch.float64).numpy())


def _kinetic_hessian(model: KineticPotentialMLPLagrangian, k: int, m: int) -> np.ndarray:
    """The constant Hessian ``(K m, K m)`` of the model's kinetic part in the flat cell values."""

    def kin(x: torch.Tensor) -> torch.Tensor:
        return model.kinetic(x.reshape(k, m))

    with torch.enable_grad():
        hess = torch.autograd.functional.hessian(kin, torch.zeros(k * m, dtype=torch.float64))
    return np.ascontiguousarray(hess.detach().numpy())


#: Per model, its closed forms with the parameters and buffers they were built from.
_FORMS: weakref.WeakKeyDictionary[Any, tuple[list[tuple[torch.Tensor, int]], tuple[Any, ...], Any]] = (
    weakref.WeakKeyDictionary()
)


def _closed_forms(
    model: KineticPotentialMLPLagrangian, mod: Any, upper: np.ndarray, m: int
) -> tuple[PotentialNet, np.ndarray, Any]:
    """``(PotentialNet(model, mod), kinetic Hessian, quad)``, ``quad`` the residual and gradient passes generated
    for the stencil (``upper``: which points lie on the next slice) and the Hessian's pattern (``None`` where they
    do not build); built once per model state, stencil and spacing."""
    key = (tuple(int(u) for u in upper), m, tuple(float(h) for h in model.spacing))  # the Hessian holds the spacing

    def build() -> tuple[PotentialNet, np.ndarray, Any]:
        hess = _kinetic_hessian(model, len(upper), m)
        return PotentialNet(model, mod), hess, quadratic_kernels(hess, upper, m)

    forms: tuple[PotentialNet, np.ndarray, Any]
    forms, _ = per_model_state(_FORMS, model, key, build)
    return forms


class PotentialCells:
    """The cells anchored on a slice (``lo``; ``hi`` the next) at the current state: their gradients ``grad``
    ``(cells, K m)`` and their Hessian blocks. ``grad`` is :class:`DeferredGrad`, evaluated where it is used:
    slice-Newton returns it at the solution for the next slice, and after the last slice nothing reads it."""

    def __init__(self, owner: PotentialSlices, lo: np.ndarray, hi: np.ndarray):
        self.owner, self.lo, self.hi = owner, lo, hi
        self.vlo = owner.potential(lo)

    @property
    def grad(self) -> DeferredGrad:
        return DeferredGrad(self.owner, self.lo.copy(), self.hi.copy(), self.vlo)

    def blocks(self, pairs: list[tuple[int, int]]) -> dict[tuple[int, int], torch.Tensor]:
        """The Hessian blocks ``(cells, m, m)`` of ``pairs`` (two points on two slices: the potential, one site's,
        has none), the kinetic Hessian's on every cell."""
        o, m = self.owner, self.owner.m
        n = o.site_of.shape[1]
        return {
            (a, b): torch.from_numpy(np.tile(o.hess[a * m : (a + 1) * m, b * m : (b + 1) * m], (n, 1, 1)))
            for a, b in pairs
        }


class DeferredGrad:
    """The gradients ``(cells, K m)`` of the cells anchored on a slice at the values ``lo`` and ``hi`` (copies:
    a rolling window moves its slices), evaluated by ``numpy()`` on its first call."""

    def __init__(self, owner: PotentialSlices, lo: np.ndarray, hi: np.ndarray, vlo: np.ndarray):
        self.owner, self.lo, self.hi, self.vlo = owner, lo, hi, vlo
        self._grad: np.ndarray | None = None

    def numpy(self) -> np.ndarray:
        if self._grad is None:
            o = self.owner
            self._grad = np.empty((o.site_of.shape[1], o.k * o.m))
            o.grad_pass(self.lo, self.hi, self.vlo, o.potential(self.hi), self._grad)
        return self._grad


class PotentialSlices(FoldedSlices):
    """A kinetic-potential MLP's slice-Newton evaluation on one served field (:class:`FoldedSlices`' index maps,
    predictor and range check; the residual and gradients by the folded module's quadratic kernels)."""

    def __init__(self, mod: Any, sys: _SliceSystem, model: KineticPotentialMLPLagrangian):
        super().__init__(mod, sys, (), ())
        self.model = model
        self.net, self.hess, self.quad = _closed_forms(model, mod, self.upper, self.m)
        self.known: list[tuple[np.ndarray, np.ndarray]] = []  # (a slice's values, -V'/K on its sites)

    def grad_pass(self, lo: np.ndarray, hi: np.ndarray, vlo: np.ndarray, vhi: np.ndarray, out: np.ndarray) -> None:
        """The cells' gradients into ``out``, by the passes generated for the stencil (else the folded module's)."""
        if self.quad is not None:
            self.quad.quadratic_grad(lo, hi, self.site_of, self.hess, vlo, vhi, out)
        else:
            self.mod.quadratic_grad(lo, hi, self.site_of, self.upper, self.hess, vlo, vhi, out)

    def potential(self, values: np.ndarray) -> np.ndarray:
        """``-V'/K`` on every site of a slice at ``values`` (``(sites, m)``); the last two slices' are kept (the
        DEL of slice ``i`` and the cells anchored on slice ``i - 1`` read those of slice ``i``; a field at rest
        starts with two equal slices)."""
        for seen, out in reversed(self.known):
            if np.array_equal(seen, values):
                return out
        out = np.ascontiguousarray(self.net.grad(values) * (-1.0 / self.k))
        self.known = [*self.known[-1:], (values.copy(), out)]
        return out

    def grad(self, flat: torch.Tensor, i: int) -> np.ndarray:
        return PotentialCells(self, flat[i].numpy(), flat[i + 1].numpy()).grad.numpy()

    def evaluate(
        self, flat: torch.Tensor, vol: float, i: int, g_prev: Any, blocks: bool = False
    ) -> tuple[Any, np.ndarray]:
        """As :meth:`FoldedSlices.evaluate`; the blocks (the kinetic Hessian's) are not evaluated with the cells."""
        ev = PotentialCells(self, flat[i].numpy(), flat[i + 1].numpy())
        gp = g_prev.numpy() if isinstance(g_prev, (torch.Tensor, DeferredGrad)) else g_prev
        gp = np.ascontiguousarray(gp).reshape(self.site_of.shape[1], self.k * self.m)
        r = np.empty(self.rows.size * self.m)
        self.residual_pass(gp, ev, vol, r)
        return ev, r

    def residual_pass(self, gp: np.ndarray, ev: PotentialCells, vol: float, r: np.ndarray) -> None:
        """Slice ``i``'s DEL residual into ``r`` from the older cells' gradients ``gp`` and the cells ``ev``
        anchored on it, by the passes generated for the stencil (else the folded module's)."""
        if self.quad is not None:
            self.quad.quadratic_residual(gp, ev.lo, ev.hi, self.site_of, self.hess, ev.vlo, self.rows, vol, self.el, r)
        else:
            self.mod.quadratic_residual(
                gp, ev.lo, ev.hi, self.site_of, self.upper, self.hess, ev.vlo, self.rows, vol, self.el, r
            )


def _second(model: KineticPotentialMLPLagrangian, x: np.ndarray) -> np.ndarray:
    """``V''(x)`` of a scalar field's potential at the values ``x`` (1-D), by second-order forward mode
    through the network."""
    act, _ = _ACTS[model.activation]
    lin = [layer for layer in model.net if isinstance(layer, torch.nn.Linear)]
    y = ((x - float(model.in_center[0])) / float(model.in_scale[0]))[:, None]
    dy, d2y = np.full_like(y, 1.0 / float(model.in_scale[0])), np.zeros_like(y)
    for layer in lin[:-1]:
        w, b = _np(layer.weight).T, _np(layer.bias)
        z, dz, d2z = y @ w + b, dy @ w, d2y @ w
        a = act(z)
        slope = 1.0 - a * a if model.activation == "tanh" else a * (1.0 - a)
        curve = -2.0 * a * slope if model.activation == "tanh" else slope * (1.0 - 2.0 * a)
        y, dy, d2y = a, slope * dz, curve * dz * dz + slope * d2z
    out: np.ndarray = float(model.out_scale) * (d2y @ _np(lin[-1].weight)[0])
    return out


def not_affine(model: Any, k: int, m: int, scale: float) -> bool:
    """Whether the affine recurrence's probe (``_affine._AffineSlices.probe``: Hessian blocks at random cells of
    size ``scale``) would find a kinetic-potential MLP's DEL not affine, known from its closed forms without
    autograd: ``V''`` varies between the probe's states by a hundred times its tolerance (round-off cannot
    decide it). ``False`` where unsure (the probe then runs): with ``compiled_kernels`` off, for another
    model, activation, network inputs or a field of several components. The answer is kept per model state
    and probe (one per model: a serve asks once)."""
    if not option("compiled_kernels") or m != 1:
        return False
    if not isinstance(model, KineticPotentialMLPLagrangian) or model.features != "values":
        return False
    if model.activation not in _ACTS:
        return False
    key = (k, m, float(scale), tuple(float(h) for h in model.spacing), model.activation)
    answer: bool
    answer, _ = per_model_state(_PROBES, model, key, lambda: _probe(model, k, m, scale))
    return answer


#: Per model, :func:`not_affine`'s last answer with the parameters, buffers and probe it was found for.
_PROBES: weakref.WeakKeyDictionary[Any, tuple[list[tuple[torch.Tensor, int]], tuple[Any, ...], Any]] = (
    weakref.WeakKeyDictionary()
)


def _probe(model: KineticPotentialMLPLagrangian, k: int, m: int, scale: float) -> bool:
    """:func:`not_affine`'s answer, computed."""
    gen = torch.Generator().manual_seed(12345)  # the probe's states
    x = (scale * (2 * torch.rand(3, 4, k, m, generator=gen, dtype=torch.float64) - 1)).numpy().reshape(-1)
    second = _second(model, np.concatenate([[0.0], x]))
    h0 = _kinetic_hessian(model, k, m) - np.diag(np.full(k, second[0] / k))
    big = float(np.abs(h0).max())
    return big > 0.0 and float(np.abs(second[1:] - second[0]).max()) / k > 1e-8 * big  # the probe: 1e-10


def potential_slices(model: Any, sys: _SliceSystem, flat: torch.Tensor) -> PotentialSlices | None:
    """The closed-form evaluation for a kinetic-potential MLP on the values themselves (``features="values"``)
    with a ``tanh`` or ``sigmoid`` network, on the CPU in double precision, where the ``compiled_kernels`` option
    is on (the default); ``None`` otherwise (or where the folded kernels do not build)."""
    if not option("compiled_kernels"):
        return None
    if not isinstance(model, KineticPotentialMLPLagrangian) or model.features != "values":
        return None
    if model.activation not in _ACTS:
        log.info("closed-form potential unavailable for activation %r: serving uses autograd", model.activation)
        return None
    if flat.dtype != torch.float64 or flat.device.type != "cpu" or not flat.is_contiguous():
        return None
    tensors = [*model.parameters(), *model.buffers()]
    if any(t.device.type != "cpu" or (t.is_floating_point() and t.dtype != torch.float64) for t in tensors):
        return None
    mod = folded_kernels()
    return None if mod is None else PotentialSlices(mod, sys, model)
