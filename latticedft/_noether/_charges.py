"""Noether charges and the discrete energy along (served) fields, from the derivatives of ``L_d``.

With ``P^+_{i+1} = h_0 dL_s/dQ_{i+1}(Q_i, Q_{i+1})`` and ``P^-_i = -h_0 dL_s/dQ_i(Q_i, Q_{i+1})`` (the
discrete Legendre transforms of the slab Lagrangian; ``h_0 dL_s/dQ = H sum_cells dL_d/dpsi``):

* the **Noether charge** of a generator ``xi`` on slab ``i`` is ``J_i = P^+_{i+1} . xi(Q_{i+1}) =
  H sum_cells sum_{a on the later slice} dL_d/dpsi_a . xi(psi_a)`` (Marsden & West's discrete momentum
  map; in 1D ``J_k = h_0 sum_a dL_d/dq_a . xi(q_a)`` over the stencil arguments at time ``k + 1``);
* the **discrete energy** of slab ``i`` is ``E_i = (P^-_i + P^+_{i+1})/2 . (Q_{i+1} - Q_i)/h_0 - L_s(Q_i, Q_{i+1})``,
  the discrete analogue of ``p . qdot - L``.

Both are returned as DataArrays over the slabs, at the time of the slab's later slice ``t_{i+1}``.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
import xarray as xr

from .._contract import AbstractLagrangian
from .._errors import InputError
from .._lattice import gather_cells
from ._core import FieldEval, prepare
from ._group import Symmetry, resolve_symmetries

__all__ = ["discrete_energy", "noether_charge", "noether_charges", "relative_drift"]


def _one_field(model: AbstractLagrangian, field: Any, boundary: Any) -> FieldEval:
    fields = prepare(model, field, boundary)
    if len(fields) != 1:
        raise InputError(f"field: expected one field, got {len(fields)}")
    return FieldEval(model, fields[0])


def _series(
    ev: FieldEval, values: torch.Tensor, scale: float, name: str, long_name: str, attrs: dict[str, Any]
) -> xr.DataArray:
    tdim = ev.f.dims[0]
    t = ev.times[1:]
    v = values.detach().cpu().numpy().astype(np.float64)
    drift = float(v.max() - v.min()) / scale if scale > 0 else (0.0 if np.ptp(v) == 0 else np.inf)
    coord_attrs = dict(ev.f.coord_attrs.get(tdim, {}))
    return xr.DataArray(
        v,
        dims=[tdim],
        coords={tdim: (tdim, t, coord_attrs)},
        name=name,
        attrs={"long_name": long_name, "scale": float(scale), "relative_drift": drift, **attrs},
    )


def _charge(ev: FieldEval, sym: Symmetry) -> xr.DataArray:
    if not sym.continuous:
        raise InputError(
            f"symmetry {sym.name!r}: a discrete symmetry has no Noether charge; pass a continuous one "
            "(a shift, a rotation, an affine generator or a momentum)"
        )
    sym.check(ev.f.ndim, ev.f.ncomp, ev.f.periodic)
    xi = ev.generator_cells(sym)
    later = ev.later.to(xi.device)
    terms = (ev.grad * xi).sum(-1)[..., later]  # (slabs, *cells, K_later)
    charge = ev.H * ev.slab_sum(terms)
    scale = float((ev.H * ev.slab_sum(terms.abs())).mean())
    return _series(
        ev,
        charge,
        scale,
        f"J_{sym.name}",
        f"Noether charge of {sym.name}",
        {"symmetry": sym.name, "generator": sym.description},
    )


def noether_charge(
    model: AbstractLagrangian, field: Any, symmetry: Symmetry | str, *, boundary: Any = None
) -> xr.DataArray:
    """The discrete Noether charge of a continuous symmetry on every slab of a field.

    ``J_i = H sum_cells sum_{a: later slice} dL_d/dpsi_a . xi(psi_a)`` (``H`` the cell volume), the
    momentum map of Marsden & West applied to whole time slices. It is exactly conserved along fields
    that solve the DEL equations of ``L_d`` when ``L_d`` is invariant (``symmetries(...)`` reports
    ``invariant``), the spatial axes are periodic or ``xi`` vanishes on the boundary sites.

    Returns a DataArray over the field's time dim at ``t_{i+1}`` (``N_0 - 1`` values), named
    ``J_<symmetry>``; ``attrs["scale"]`` is the mean over slabs of the summed magnitudes of its terms
    and ``attrs["relative_drift"]`` is ``(max - min) / scale``.
    """
    ev = _one_field(model, field, boundary)
    sym = _resolve_one(symmetry, ev)
    return _charge(ev, sym)


def _resolve_one(symmetry: Any, ev: FieldEval) -> Symmetry:
    f = ev.f
    (sym,) = resolve_symmetries([symmetry], f.ndim, f.ncomp, f.periodic, f.dims, f.components)
    return sym


def _energy(ev: FieldEval) -> xr.DataArray:
    h0 = ev.f.spacing[0]
    delta = ev.values[1:] - ev.values[:-1]  # Q_{i+1} - Q_i, (slabs, *spatial, m)
    doubled = torch.stack([delta, delta], dim=1)  # a two-slice field per slab, so that cells see delta at their sites
    dcells = gather_cells(doubled, ev.model.stencil, (False,) + tuple(ev.f.periodic[1:]), batch=1)[:, 0]
    sign = torch.where(ev.later, 1.0, -1.0).to(dtype=ev.grad.dtype)[:, None]  # +1 later slice, -1 earlier
    pq = 0.5 * ((ev.grad * dcells) * sign).sum((-1, -2))  # (P^- + P^+)/2 . (Q1 - Q0)/h0 per cell, over H/h0
    volume = ev.H / h0
    energy = volume * ev.slab_sum(pq - ev.lval)
    scale = float((volume * ev.slab_sum(pq.abs())).mean())
    return _series(
        ev,
        energy,
        scale,
        "energy",
        "discrete energy (P^- + P^+)/2 . (Q1 - Q0)/h0 - L_s",
        {"scale_of": "the p . qdot term"},
    )


def discrete_energy(model: AbstractLagrangian, field: Any, *, boundary: Any = None) -> xr.DataArray:
    """The discrete energy ``E_i = (P^-_i + P^+_{i+1})/2 . (Q_{i+1} - Q_i)/h_0 - L_s(Q_i, Q_{i+1})`` per slab.

    Variational integrators do not conserve it exactly; on a served field it oscillates in a bounded
    band. ``attrs["scale"]`` is the mean over slabs of the magnitude of the ``p . qdot`` term (unchanged
    by a constant added to ``L_d``), ``attrs["relative_drift"]`` is ``(max - min) / scale``.
    """
    return _energy(_one_field(model, field, boundary))


def noether_charges(model: AbstractLagrangian, field: Any, charges: Any = None, *, boundary: Any = None) -> xr.Dataset:
    """Several charges and the discrete energy of one field as a Dataset over time.

    ``charges``: names of built-in symmetries, :class:`Symmetry` objects and ``"energy"`` (one or a list;
    default: every continuous built-in symmetry of the field — shifts, rotations, momenta along periodic
    axes — and the energy). Variables are named ``J_<symmetry>`` and ``energy``; each carries its
    ``relative_drift`` in ``attrs``.
    """
    ev = _one_field(model, field, boundary)
    f = ev.f
    if charges is None:
        syms = [s for s in resolve_symmetries(None, f.ndim, f.ncomp, f.periodic, f.dims, f.components) if s.continuous]
        energy = True
    else:
        if isinstance(charges, (str, Symmetry)):
            charges = [charges]
        charges = list(charges)
        names = [c for c in charges if not (isinstance(c, str) and c == "energy")]
        energy = len(names) < len(charges)
        syms = resolve_symmetries(names, f.ndim, f.ncomp, f.periodic, f.dims, f.components) if names else []
    out = {f"J_{s.name}": _charge(ev, s) for s in syms}
    if energy:
        out["energy"] = _energy(ev)
    return xr.Dataset(out)


def relative_drift(series: xr.DataArray) -> float:
    """``(max - min) / attrs["scale"]`` of a charge or energy series (how well it is conserved)."""
    return float(series.attrs["relative_drift"])
