"""Discrete Lagrangians written by hand as Python functions (ground truths)."""

from __future__ import annotations

from collections.abc import Callable

import torch

from .._contract import AbstractLagrangian
from .._errors import InputError
from .._stencil import Stencil

__all__ = ["AnalyticLagrangian"]


class AnalyticLagrangian(AbstractLagrangian):
    """``L_d`` from a function ``fn(cells, h)``.

    ``cells`` has shape ``(..., K, m)`` in stencil order and ``h`` is the tuple
    of spacings; ``fn`` returns ``(...)`` using torch operations (it is
    differentiated twice). Analytic models have no parameters to learn and
    cannot be written to a model file.

    >>> import torch
    >>> verlet = AnalyticLagrangian(
    ...     lambda c, h: 0.5 * ((c[..., 1, 0] - c[..., 0, 0]) / h[0]) ** 2
    ...     - 0.25 * (c[..., 0, 0] ** 2 + c[..., 1, 0] ** 2), name="harmonic Verlet")
    >>> verlet.bind(1, 1, (0.1,))
    >>> float(verlet(torch.tensor([[[0.0], [0.1]]], dtype=torch.float64))[0])
    0.4975
    """

    kind = "analytic"
    saveable = False
    rebinds_to_any_lattice = True  # a formula in h, valid on any lattice

    def __init__(
        self,
        fn: Callable[[torch.Tensor, tuple[float, ...]], torch.Tensor],
        *,
        stencil: Stencil | None = None,
        name: str | None = None,
    ):
        super().__init__(stencil)
        if not callable(fn):
            raise InputError.at("fn", f"expected a callable fn(cells, h), got {type(fn).__name__}")
        if name is not None and not isinstance(name, str):
            raise InputError.at("name", f"expected a string or None, got {type(name).__name__}")
        self.fn = fn
        self.name = name or getattr(fn, "__name__", "analytic")
        self._given_stencil = stencil

    def bind(self, n: int, m: int, spacing: tuple[float, ...], components: tuple[str, ...] | None = None) -> None:
        """Analytic models have no parameters: they rebind to any lattice they are served on."""
        self._stencil = self._given_stencil
        self._n = self._m = self._spacing = None
        super().bind(n, m, spacing, components)

    def forward(self, cells: torch.Tensor) -> torch.Tensor:
        self._require_bound()
        return self.fn(cells, self.spacing)

    def options(self) -> dict[str, object]:
        return {"name": self.name}

    def describe(self, max_terms: int | None = 12) -> str:
        return super().describe(max_terms) + f"\n  L_d = {self.name} (analytic)"
