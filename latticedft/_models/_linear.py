"""Models linear in their parameters, ``L_d = features(cells) @ coef``: learned by an exact solve."""

from __future__ import annotations

import abc
from collections.abc import Callable, Sequence
from typing import Any, Literal, overload

import torch

from .._contract import _LINEAR_BASE, AbstractLagrangian

__all__ = ["LinearLagrangian", "AUTO_LIBRARIES"]

#: Feature libraries of the ``select = "auto"`` candidates of a linear model on a 1D field.
AUTO_LIBRARIES = (("trig:1",), ("trig:2",), ("poly:4", "trig:1"))


def _unit(x: torch.Tensor, a: int, i: int) -> torch.Tensor:
    """The tangent that moves component ``i`` of stencil point ``a`` on every cell."""
    t = torch.zeros_like(x)
    t[..., a, i] = 1.0
    return t


class LinearLagrangian(AbstractLagrangian):
    """``L_d = sum_c coef[c] phi_c(cells)``: a model linear in its parameters.

    The DEL residual and the gauge are then linear in ``coef``, so :func:`latticedft.learn` solves for it
    exactly (an equality-constrained least-squares problem) instead of training.

    A subclass implements, besides ``kind`` and its constructor (see :class:`AbstractLagrangian`):

    - :attr:`n_terms`: the number of basis functions (a property or a class attribute);
    - :meth:`features`: every basis function on a batch of cells.

    It may override :meth:`_build` (create what :meth:`features` needs, then call ``super()._build()``,
    which creates ``coef``), :meth:`derivatives_of_features` (what :meth:`feature_derivatives` returns, in
    closed form, for the exact solve; the default is forward-mode automatic differentiation of :meth:`features`;
    overriding :meth:`feature_derivatives` itself works too) and :meth:`fast_derivatives` (closed
    forms for serving; the default ``None`` lets serving differentiate :meth:`forward` by autograd) and
    :meth:`numpy_derivatives` (closed forms in numpy: 1D serving then runs Newton's method in numpy, and n-D
    slice-Newton evaluates its cells with them while the model is on the CPU).

    Attributes
    ----------
    coef : torch.nn.Parameter
        The coefficients, shape ``(n_terms,)``, float64; zeros until learned.
    """

    linear = True
    numpy_ready = True
    bridged = (*AbstractLagrangian.bridged, "features", "feature_derivatives")

    @property
    @abc.abstractmethod
    def n_terms(self) -> int:
        """The number of basis functions ``C`` (known once the model is bound to a lattice)."""

    @abc.abstractmethod
    def features(self, cells: torch.Tensor) -> torch.Tensor:
        """Every basis function on every cell: ``(..., K, m)`` -> ``(..., n_terms)``, smooth torch operations."""

    def _build(self) -> None:
        """Create ``coef`` (zeros, one per basis function); subclasses build their buffers first."""
        self.coef = torch.nn.Parameter(torch.zeros(self.n_terms, dtype=torch.float64))

    def forward(self, cells: torch.Tensor) -> torch.Tensor:
        return self.features(cells) @ self.coef

    @overload
    def feature_derivatives(
        self, cells: torch.Tensor, pairs: Sequence[tuple[int, int]] = (), *, first: Literal[True] = True
    ) -> tuple[torch.Tensor, dict[tuple[int, int], torch.Tensor]]: ...

    @overload
    def feature_derivatives(
        self, cells: torch.Tensor, pairs: Sequence[tuple[int, int]] = (), *, first: bool
    ) -> tuple[torch.Tensor | None, dict[tuple[int, int], torch.Tensor]]: ...

    def feature_derivatives(
        self, cells: torch.Tensor, pairs: Sequence[tuple[int, int]] = (), *, first: bool = True
    ) -> tuple[torch.Tensor | None, dict[tuple[int, int], torch.Tensor]]:
        """Derivatives of every basis function with respect to the stencil values.

        Returns ``(d, blocks)``: ``d[..., a, i, c] = d phi_c / d x_{a,i}`` with shape ``(*cells, K, m, C)``
        (``None`` when ``first`` is false), and for each ``(a, b)`` in ``pairs`` the mixed second
        derivatives ``blocks[(a, b)][..., i, j, c] = d^2 phi_c / d x_{a,i} d x_{b,j}`` with shape
        ``(*cells, m, m, C)``. The exact solve's residual and gauge matrices are linear in these.

        A kind overrides :meth:`derivatives_of_features` (the same, positional) where it knows them in closed
        form.
        """
        return self.derivatives_of_features(cells, pairs, first)

    def derivatives_of_features(
        self, cells: torch.Tensor, pairs: Sequence[tuple[int, int]], first: bool
    ) -> tuple[torch.Tensor | None, dict[tuple[int, int], torch.Tensor]]:
        """:meth:`feature_derivatives`' work. This default differentiates :meth:`features` in forward mode: one
        pass per stencil point and component for ``d``, one per pair of components for each block."""
        k, m = cells.shape[-2], cells.shape[-1]
        d = None
        if first:
            d = torch.stack(
                [
                    torch.stack(
                        [torch.func.jvp(self.features, (cells,), (_unit(cells, a, i),))[1] for i in range(m)], -2
                    )
                    for a in range(k)
                ],
                -3,
            )
        blocks = {}
        for a, b in pairs:
            rows = []
            for i in range(m):
                along = self._directional(_unit(cells, a, i))
                rows.append(
                    torch.stack([torch.func.jvp(along, (cells,), (_unit(cells, b, j),))[1] for j in range(m)], -2)
                )
            blocks[(a, b)] = torch.stack(rows, -3)
        return d, blocks

    def _auto_tail(self, degree: int, n: int, ridge: Any) -> list[dict[str, Any]]:
        """The ``select = "auto"`` candidates every linear kind shares (after its own): time symmetry and input
        scaling flipped, ``ridge="auto"``, and on a 1D lattice the feature libraries of :data:`AUTO_LIBRARIES`
        (``kind = "features"``, with ``degree`` in the differences, at least 2)."""
        opts = self.options()
        out: list[dict[str, Any]] = [{"time_symmetric": not opts["time_symmetric"]}, {"scale": not opts["scale"]}]
        if ridge != "auto":
            out.append({"ridge": "auto"})
        if n == 1:
            out += [
                {"kind": "features", "features": list(lib), "differences": max(degree, 2)} for lib in AUTO_LIBRARIES
            ]
        return out

    def _directional(self, t: torch.Tensor) -> Callable[[torch.Tensor], torch.Tensor]:
        """``y -> d features(y) / d y . t``, to be differentiated once more."""

        def along(y: torch.Tensor) -> torch.Tensor:
            derivative: torch.Tensor = torch.func.jvp(self.features, (y,), (t,))[1]
            return derivative

        return along


_LINEAR_BASE.append(LinearLagrangian)
