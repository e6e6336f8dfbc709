"""The abstract discrete Lagrangian density ``L_d`` and the shared features."""

from __future__ import annotations

import abc
import math
from typing import Any, ClassVar

import numpy as np
import torch

from .._errors import InputError
from .._stencil import Stencil

__all__ = ["AbstractLagrangian"]


class AbstractLagrangian(torch.nn.Module, abc.ABC):
    """A discrete Lagrangian density ``L_d(psi[x+s_0], ..., psi[x+s_{K-1}])``.

    Subclasses implement :meth:`forward` on a batch of cells ``(..., K, m)``
    returning ``(...)``. A model is *bound* to a lattice (dimension ``n``,
    components ``m``, spacings ``h``) when it is first learned; a discrete
    theory belongs to its lattice spacing, so serving checks the spacing.

    Subclasses set ``kind`` (the name used in ``case.toml`` and model files)
    and list their constructor keywords in :meth:`options`.
    """

    kind: ClassVar[str] = "abstract"
    #: True when ``L_d`` is linear in its parameters (``coef``): learned exactly.
    linear: ClassVar[bool] = False
    #: True when the mixed time Hessian is ``-I / h_0^2`` by construction.
    unit_mass_by_construction: ClassVar[bool] = False
    #: True when every block coupling two different stencil sites is constant (1D serving then assembles
    #: the Newton Jacobian once).
    constant_mixed_hessian: ClassVar[bool] = False
    #: False for models that cannot be written to a model file.
    saveable: ClassVar[bool] = True

    def __init__(self, stencil: Stencil | None = None):
        super().__init__()
        self.stencil: Stencil | None = stencil
        self.n: int | None = None
        self.m: int | None = None
        self.spacing: tuple[float, ...] | None = None
        self.components: tuple[str, ...] | None = None

    # -- binding to a lattice -----------------------------------------------------------------------------
    @property
    def bound(self) -> bool:
        return self.spacing is not None

    def bind(self, n: int, m: int, spacing: tuple[float, ...], components: tuple[str, ...] | None = None) -> None:
        """Fix the lattice dimension, number of components and spacings; build parameters."""
        if self.stencil is None:
            self.stencil = Stencil.first_order(n)
        if self.stencil.ndim != n:
            raise InputError(f"stencil: has offsets in {self.stencil.ndim} dimensions but the data have {n} lattice dims")
        if self.bound and (self.n, self.m) != (n, m):
            raise InputError(f"model: bound to n={self.n}, m={self.m}; data have n={n}, m={m}")
        first = not self.bound
        self.n, self.m = n, m
        self.spacing = tuple(float(h) for h in spacing)
        self.components = components
        if first:
            self.register_buffer("proj", self._projection(), persistent=False)
            self._build()
        self.double()

    def _build(self) -> None:
        """Create parameters and buffers once ``n``, ``m`` and the stencil are known."""

    def prepare(self, cells: list[torch.Tensor]) -> None:
        """Data-dependent set-up before training (input scaling), from the training cells."""

    def _require_bound(self) -> None:
        if not self.bound:
            raise InputError(f"{type(self).__name__}: not bound to a lattice yet; learn it first (latticedft.learn)")

    # -- evaluation ---------------------------------------------------------------------------------------
    @abc.abstractmethod
    def forward(self, cells: torch.Tensor) -> torch.Tensor:
        """``L_d`` on cells ``(..., K, m)``, returning ``(...)``."""

    # -- features shared by models ------------------------------------------------------------------------
    def _projection(self) -> torch.Tensor:
        """Matrix ``(n + 1, K)`` mapping stencil values to (mean, per-axis differences).

        Least-squares fit of ``c + sum_k g_k (s_k - centroid_k)`` over the
        stencil; exact for the first-order stencil, where ``g_k`` is
        ``psi[x + e_k] - psi[x]`` and ``c`` the mean of the ``K`` values.
        """
        s = self.stencil.array.astype(np.float64)
        s = s - s.mean(axis=0)
        a = np.hstack([np.ones((s.shape[0], 1)), s])
        return torch.from_numpy(np.linalg.pinv(a))

    def mean_and_differences(self, cells: torch.Tensor) -> torch.Tensor:
        """``(..., n + 1, m)``: the stencil mean then ``g_0 ... g_{n-1}``."""
        return torch.einsum("pk,...km->...pm", self.proj, cells)

    # -- description -------------------------------------------------------------------------------------
    def options(self) -> dict[str, Any]:
        """Constructor keywords that rebuild this model (JSON-compatible)."""
        return {}

    def n_parameters(self) -> int:
        return sum(p.numel() for p in self.parameters())

    def describe(self) -> str:
        """The learned ``L_d`` in words; subclasses add their terms."""
        lines = [f"{type(self).__name__} (kind {self.kind!r}), {self.n_parameters()} parameters"]
        if self.bound:
            lines.append(f"  lattice: n = {self.n} (time first), m = {self.m} component(s), "
                         f"spacing = {tuple(float(f'{h:.6g}') for h in self.spacing)}")
            lines.append(f"  stencil: {self.stencil.to_list()}")
        else:
            lines.append("  not bound to a lattice yet")
        report = getattr(self, "report_", None)
        if report is not None:
            lines.append("  " + report.summary_line())
        return "\n".join(lines)

    def __str__(self) -> str:  # print(model) shows the learned theory
        return self.describe()

    def extra_repr(self) -> str:
        return ", ".join(f"{k}={v!r}" for k, v in self.options().items())

    @property
    def cell_volume(self) -> float:
        self._require_bound()
        return math.prod(self.spacing)
