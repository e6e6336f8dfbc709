"""Known discrete Lagrangians (ground truths): wave, Störmer–Verlet, Klein–Gordon, Kepler.

Each returns an :class:`~latticedft.AnalyticLagrangian` for the first-order
stencil (docs/mathematics.md, sections 1 and 9).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import torch

from ._models import AnalyticLagrangian

__all__ = ["wave", "verlet", "klein_gordon", "kepler"]


def wave(c: float = 1.0) -> AnalyticLagrangian:
    """``L_d = ((psi_{x+e0} - psi_x)/h_0)^2 - c^2 sum_k ((psi_{x+e_k} - psi_x)/h_k)^2``.

    Serves exactly the explicit leapfrog scheme of ``psi_tt = c^2 Laplacian psi``
    (Qin 2020, Eq. 5, with ``c = 1``).
    """

    def fn(cells: torch.Tensor, h: tuple[float, ...]) -> torch.Tensor:
        x0 = cells[..., 0, :]
        out = (((cells[..., 1, :] - x0) / h[0]) ** 2).sum(-1)
        for k in range(1, len(h)):
            out = out - c**2 * (((cells[..., k + 1, :] - x0) / h[k]) ** 2).sum(-1)
        return out

    return AnalyticLagrangian(fn, name=f"wave, c = {c:g}")


def verlet(
    potential: Callable[[torch.Tensor], torch.Tensor],
    mass: float = 1.0,
    *,
    symbolic_potential: Callable[[Any], Any] | None = None,
) -> AnalyticLagrangian:
    """``L_d = m |q_{i+1} - q_i|^2 / (2 h^2) - (V(q_i) + V(q_{i+1})) / 2``: serves Störmer–Verlet.

    ``potential`` maps positions ``(..., m)`` (or a scalar field's values) to
    the potential energy; it is called on ``(..., m)`` tensors and summed over
    a trailing singleton if it returns one. ``symbolic_potential``, the same
    potential written with sympy functions, gives the closed form where
    ``potential`` calls torch (arithmetic alone is traced through ``potential``).
    """

    def with_potential(v: Callable[[Any], Any]) -> Callable[[Any, tuple[float, ...]], Any]:
        def fn(cells: Any, h: tuple[float, ...]) -> Any:
            q0, q1 = cells[..., 0, :], cells[..., 1, :]
            pot0 = v(q0[..., 0] if q0.shape[-1] == 1 else q0)
            pot1 = v(q1[..., 0] if q1.shape[-1] == 1 else q1)
            return 0.5 * mass * (((q1 - q0) / h[0]) ** 2).sum(-1) - 0.5 * (pot0 + pot1)

        return fn

    closed = with_potential(symbolic_potential) if symbolic_potential is not None else None
    return AnalyticLagrangian(with_potential(potential), name="Störmer–Verlet", closed_form=closed)


def klein_gordon(mass: float = 1.0) -> AnalyticLagrangian:
    """``L_d = L(u_x, (u_{x+e0} - u_x)/h_0, (u_{x+e1} - u_x)/h_1)`` with ``L = u_t^2/2 - u_x^2/2 - mass^2 u^2/2``.

    The discrete Lagrangian of the peers' Klein–Gordon benchmark; it serves the
    explicit scheme ``d_tt u = d_xx u - mass^2 u``.
    """

    def fn(cells: torch.Tensor, h: tuple[float, ...]) -> torch.Tensor:
        u = cells[..., 0, 0]
        out = 0.5 * ((cells[..., 1, 0] - u) / h[0]) ** 2 - 0.5 * mass**2 * u**2
        for k in range(1, len(h)):
            out = out - 0.5 * ((cells[..., k + 1, 0] - u) / h[k]) ** 2
        return out

    return AnalyticLagrangian(fn, name=f"Klein-Gordon, mass = {mass:g}")


def kepler(gm: float = 1.0) -> AnalyticLagrangian:
    """Störmer–Verlet for the Kepler problem, ``V(q) = -gm / |q|``."""

    def symbolic_potential(q: Any) -> Any:
        import sympy

        return -gm / sympy.sqrt((q * q).sum(-1))

    return verlet(lambda q: -gm / torch.sqrt((q * q).sum(-1)), symbolic_potential=symbolic_potential)
