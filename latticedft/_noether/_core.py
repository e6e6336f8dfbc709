"""Shared evaluation: fields and binding, per-cell derivatives, slab sums, invariance residuals.

Everything here uses only the model's public behaviour (``model(cells)`` on cells ``(..., K, m)``,
``model.stencil``, ``model.spacing``, ``model.n``, ``model.m``) and torch autograd.

A field with ``N_0`` time slices has ``N_0 - 1`` *slabs*: slab ``i`` holds the cells anchored on slice
``i`` (every stencil spans slices ``i`` and ``i + 1``). The slab Lagrangian is
``L_s(Q_i, Q_{i+1}) = (prod_{k >= 1} h_k) * sum over the slab's cells of L_d``, so that
``A_d = h_0 sum_i L_s`` — a field theory seen as discrete mechanics of whole slices.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
import xarray as xr

from .._contract import AbstractLagrangian
from .._errors import InputError
from .._lattice import LatticeField, as_lattice_field, gather_cells
from ._group import Symmetry

__all__ = ["FieldEval", "interior", "prepare"]


def _listify(data: Any) -> list[Any]:
    if isinstance(data, (xr.DataArray, LatticeField)):
        return [data]
    if hasattr(data, "field") and isinstance(data.field, xr.DataArray):  # a ServeResult
        return [data.field]
    try:
        items = list(data)
    except TypeError:
        raise InputError(
            f"data: expected a DataArray, a LatticeField or a list of them, got {type(data).__name__}"
        ) from None
    if not items:
        raise InputError("data: no field given")
    return [d.field if hasattr(d, "field") and isinstance(d.field, xr.DataArray) else d for d in items]


def prepare(model: AbstractLagrangian, data: Any, boundary: Any = None, min_slices: int = 2) -> list[LatticeField]:
    """Validate the fields, check they share a lattice, and bind (analytic) or check the model."""
    fields = [as_lattice_field(d, boundary=boundary, min_slices=min_slices) for d in _listify(data)]
    f0 = fields[0]
    for f in fields:
        if f.batch:
            raise InputError("data: batched LatticeFields are not supported here; pass the fields one by one")
        if (f.ndim, f.ncomp) != (f0.ndim, f0.ncomp) or not np.allclose(f.spacing, f0.spacing, rtol=1e-9, atol=0):
            raise InputError(
                f"data: fields differ in lattice dims, components or spacing ({f.dims}, m = {f.ncomp}, "
                f"h = {f.spacing} vs {f0.dims}, m = {f0.ncomp}, h = {f0.spacing})"
            )
    if model.rebinds_to_any_lattice:  # a formula in h (an analytic L_d): valid on any lattice
        model.bind(f0.ndim, f0.ncomp, f0.spacing, f0.components)
    elif not model.bound:
        raise InputError(f"{type(model).__name__}: not bound to a lattice yet; learn it first (latticedft.learn)")
    if (model.n, model.m) != (f0.ndim, f0.ncomp):
        raise InputError(f"model: bound to n = {model.n}, m = {model.m}; the data have n = {f0.ndim}, m = {f0.ncomp}")
    if not np.allclose(model.spacing, f0.spacing, rtol=1e-9, atol=0):
        raise InputError(f"model: learned at spacing {tuple(model.spacing)}; the data have {f0.spacing}")
    return fields


def interior(shape: tuple[int, ...], width: np.ndarray, periodic: tuple[bool, ...]) -> tuple[slice, ...]:
    """Sites where every cell ``y - s_a`` exists (those carrying a DEL equation)."""
    return tuple(slice(None) if periodic[k] else slice(int(width[k]), nk - int(width[k])) for k, nk in enumerate(shape))


def _rms_sum(x: torch.Tensor) -> float:
    return float((x.detach() ** 2).sum())


@dataclass
class FieldEval:
    """One field's cells, ``L_d`` per cell and the per-cell gradient ``G_a = dL_d/dpsi_{x+s_a}``."""

    model: AbstractLagrangian
    f: LatticeField

    def __post_init__(self) -> None:
        st = self.model.stencil
        self.values = self.f.values.detach()
        self.H = math.prod(self.f.spacing)
        self.later = torch.as_tensor(st.array[:, 0] == 1)  # stencil arguments on the later slice of a slab
        self.cells = self.gather(self.values)
        x = self.cells.clone().requires_grad_(True)
        with torch.enable_grad():
            lval = self.model(x)
            (g,) = torch.autograd.grad(lval.sum(), x)
        self.lval = lval.detach()
        self.grad = g.detach()

    # -- helpers ------------------------------------------------------------------------------------------------
    def gather(self, psi: torch.Tensor) -> torch.Tensor:
        """Cells of a field-shaped tensor: ``(N_0 - 1, *spatial cells, K, m)``."""
        return gather_cells(psi, self.model.stencil, self.f.periodic)

    def slab_sum(self, per_cell: torch.Tensor) -> torch.Tensor:
        """Sum over every axis but the first (the slab)."""
        return per_cell.reshape(per_cell.shape[0], -1).sum(-1)

    @property
    def times(self) -> np.ndarray:
        tdim = self.f.dims[0]
        t = self.f.coords.get(tdim)
        nt = self.values.shape[0]
        if t is None or len(t) != nt:
            t = self.f.spacing[0] * np.arange(nt, dtype=np.float64)
        return np.asarray(t, dtype=np.float64)

    # -- continuous symmetries ----------------------------------------------------------------------------------
    def generator_cells(self, sym: Symmetry) -> torch.Tensor:
        return self.gather(sym.xi(self.values, self.f.spacing))

    def variation(self, sym: Symmetry) -> tuple[torch.Tensor, torch.Tensor]:
        """Per slab: ``delta_i = H sum_cells sum_a G_a . Xi_a`` and its terms' size ``H sum |G_a| |Xi_a|``.

        ``delta_i`` is ``h_0 d/deps L_s(exp(eps xi) Q_i, exp(eps xi) Q_{i+1})`` at ``eps = 0``: the change
        of the Noether charge across the slab.
        """
        xi = self.generator_cells(sym)
        delta = self.H * self.slab_sum((self.grad * xi).sum(-1))
        size = self.H * self.slab_sum(self.grad.norm(dim=-1) * xi.norm(dim=-1))
        return delta, size

    # -- discrete symmetries ------------------------------------------------------------------------------------
    def discrete_change(self, sym: Symmetry) -> tuple[torch.Tensor, torch.Tensor]:
        """Per slab: ``L_s(g . slab) - L_s(slab)`` (times ``h_0``) and ``H sum_cells |L_d - mean L_d|``."""
        moved = sym.apply(self.values)
        with torch.no_grad():
            lg = self.model(self.gather(moved))
        slab_g = self.H * self.slab_sum(lg)
        if sym.action == "time-reversal":
            slab_g = torch.flip(slab_g, dims=(0,))  # slab j of the reversed field is slab N-2-j, slices swapped
        change = slab_g - self.H * self.slab_sum(self.lval)
        spread = self.H * self.slab_sum((self.lval - self.lval.mean()).abs())
        return change, spread

    # -- equations (gauge-invariant) ----------------------------------------------------------------------------
    def mean_mass(self) -> torch.Tensor:
        """Mean over the cells of the mixed time Hessian ``d^2 L_d / dpsi_x dpsi_{x+e_0}`` ``(m, m)``."""
        st = self.model.stencil
        a, b = st.anchor, st.forward
        x = self.cells.clone().requires_grad_(True)
        m = x.shape[-1]
        cols = []
        with torch.enable_grad():
            (g,) = torch.autograd.grad(self.model(x).sum(), x, create_graph=True)
            for j in range(m):
                (hj,) = torch.autograd.grad(g[..., b, j].sum(), x, retain_graph=True, allow_unused=True)
                hj = torch.zeros_like(x) if hj is None else hj
                cols.append(hj[..., a, :].reshape(-1, m).mean(0))
        return torch.stack(cols, dim=-1).detach()

    def kinetic_sumsq(self) -> float:
        """``sum_y |H Mbar (psi_{y+e0} - 2 psi_y + psi_{y-e0})|^2`` over the interior sites (the inertial term)."""
        cached = getattr(self, "_kinetic", None)
        if cached is None:
            cached = self._kinetic = self._kinetic_sumsq()
        return cached

    def _kinetic_sumsq(self) -> float:
        v = self.values
        if v.shape[0] < 3:
            return 0.0
        d2 = v[2:] - 2 * v[1:-1] + v[:-2]
        inner = interior(tuple(v.shape[:-1]), self.model.stencil.width, self.f.periodic)[1:]
        d2 = d2[(slice(None),) + inner]
        return _rms_sum(self.H * d2 @ self.mean_mass().T)

    def _interior_grad(self, psi: torch.Tensor, scalar: torch.Tensor) -> torch.Tensor:
        (g,) = torch.autograd.grad(scalar, psi, allow_unused=True)
        if g is None:
            g = torch.zeros_like(psi)
        inner = interior(tuple(psi.shape[:-1]), self.model.stencil.width, self.f.periodic)
        return g[inner]

    def equation_change(self, sym: Symmetry) -> tuple[float, float]:
        """``sum |EL[L_d o g - L_d]|^2`` (discrete) or ``sum |EL[delta L_d]|^2`` (continuous) on the interior
        sites, and the matching inertial scale ``sum |H Mbar D_tt psi|^2`` (times ``|Xi|^2 / |psi - mean|^2``
        for a generator)."""
        if self.values.shape[0] < 3:
            return 0.0, 0.0
        psi = self.values.clone().requires_grad_(True)
        with torch.enable_grad():
            if sym.continuous:
                x = self.gather(psi)
                (g,) = torch.autograd.grad(self.model(x).sum(), x, create_graph=True)
                xi = self.gather(sym.xi(psi, self.f.spacing))
                el = self._interior_grad(psi, self.H * (g * xi).sum())
            else:
                diff = self.model(self.gather(sym.apply(psi))).sum() - self.model(self.gather(psi)).sum()
                el = self._interior_grad(psi, self.H * diff)
        scale = self.kinetic_sumsq()
        if sym.continuous:
            xi_v = sym.xi(self.values, self.f.spacing)
            spread = ((self.values - self.values.reshape(-1, self.values.shape[-1]).mean(0)) ** 2).sum(-1).mean()
            ratio = float((xi_v**2).sum(-1).mean() / spread) if float(spread) > 0 else 0.0
            scale *= ratio
        return _rms_sum(el), scale


def ratio(num: float, den: float) -> float:
    """``sqrt(num / den)`` with ``0/0 = 0`` and ``x/0 = inf``."""
    if den > 0:
        return math.sqrt(num / den)
    return 0.0 if num == 0 else math.inf
