"""Discrete Lagrangians written by hand as Python functions (ground truths)."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
import torch

from .._contract import AbstractLagrangian
from .._errors import InputError
from .._stencil import Stencil
from .._symbolic import SymbolicLd, cell_symbols

__all__ = ["AnalyticLagrangian"]


class AnalyticLagrangian(AbstractLagrangian):
    """``L_d`` from a function ``fn(cells, h)``.

    ``cells`` has shape ``(..., K, m)`` in stencil order and ``h`` is the tuple
    of spacings; ``fn`` returns ``(...)`` using torch operations (it is
    differentiated twice). Analytic models have no parameters to learn and
    cannot be written to a model file.

    Its closed form (:meth:`symbolic`) is traced: ``closed_form`` (default: ``fn`` itself) is called once
    with a ``(K, m)`` numpy array of sympy symbols, which indexing, arithmetic and ``.sum`` go through; a
    function that calls torch (``torch.cos``) needs a ``closed_form`` written with sympy. The expression is
    kept only where it agrees with ``fn`` on random cells.

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
        closed_form: Callable[[Any, tuple[float, ...]], Any] | None = None,
    ):
        super().__init__(stencil)
        if not callable(fn):
            raise InputError.at("fn", f"expected a callable fn(cells, h), got {type(fn).__name__}")
        if name is not None and not isinstance(name, str):
            raise InputError.at("name", f"expected a string or None, got {type(name).__name__}")
        if closed_form is not None and not callable(closed_form):
            raise InputError.at("closed_form", f"expected a callable or None, got {type(closed_form).__name__}")
        self.fn = fn
        self.closed_form = closed_form
        self.name = name or getattr(fn, "__name__", "analytic")
        self._given_stencil = stencil

    def bind(self, n: int, m: int, spacing: tuple[float, ...], components: tuple[str, ...] | None = None) -> None:
        """Analytic models have no parameters: they rebind to any lattice they are served on (a lattice they are
        bound to already, in double precision, leaves them as they are: serving it again binds nothing)."""
        if self._bound_to(n, m, spacing, components):
            return
        self._stencil = self._given_stencil
        self._n = self._m = self._spacing = None
        super().bind(n, m, spacing, components)

    def _bound_to(self, n: int, m: int, spacing: tuple[float, ...], components: tuple[str, ...] | None) -> bool:
        """Whether the model is bound to this lattice with its own stencil, every tensor in double precision
        (what :meth:`bind` would leave)."""
        if not self.bound or (self._given_stencil is not None and self._stencil is not self._given_stencil):
            return False
        lattice = (self._n, self._m, self._spacing, self.components)
        if lattice != (n, m, tuple(float(h) for h in spacing), components):
            return False
        return all(t.dtype == torch.float64 for t in (*self.parameters(), *self.buffers()))

    def forward(self, cells: torch.Tensor) -> torch.Tensor:
        self._require_bound()
        return self.fn(cells, self.spacing)

    def symbolic(self) -> SymbolicLd | None:
        """``L_d`` traced through ``closed_form`` (or ``fn``) on sympy symbols, checked against ``fn`` on random
        cells to 1e-10 (relative); ``None`` where the trace fails or disagrees (``fn`` calls torch)."""
        if not self.bound:
            return None
        cached = self.__dict__.get("_symbolic_cache")
        key = (tuple(self.spacing), self.m, self.stencil.offsets)
        if cached is not None and cached[0] == key:
            return cached[1]  # type: ignore[no-any-return]
        form = _traced(self)
        self.__dict__["_symbolic_cache"] = (key, form)
        return form

    def options(self) -> dict[str, object]:
        return {"name": self.name}

    def describe(self, max_terms: int | None = 12) -> str:
        return super().describe(max_terms) + f"\n  L_d = {self.name} (analytic)"


def _traced(model: AnalyticLagrangian) -> SymbolicLd | None:
    """The closed form of ``model`` by tracing (see :meth:`AnalyticLagrangian.symbolic`)."""
    import sympy

    k, m = model.stencil.size, model.m
    sym = cell_symbols(k, m)
    cells = np.empty((k, m), dtype=object)
    for p in range(k):
        for c in range(m):
            cells[p, c] = sym[p][c]
    try:
        with np.errstate(all="ignore"):
            trace: Callable[[Any, tuple[float, ...]], Any] = model.closed_form or model.fn
            out = trace(cells, model.spacing)
        expr = sympy.sympify(out.item() if isinstance(out, np.ndarray) else out)
        flat = [s for row in sym for s in row]
        if not expr.free_symbols <= set(flat):
            return None
        fn = sympy.lambdify(flat, expr, "numpy")
        rng = np.random.default_rng(0)
        probe = rng.uniform(0.5, 1.5, (16, k, m)) * rng.choice([-1.0, 1.0], (16, k, m))
        got = np.broadcast_to(np.asarray(fn(*probe.reshape(16, -1).T), dtype=np.float64), (16,))
        want = model(torch.from_numpy(probe)).detach().numpy()
    except Exception:  # noqa: BLE001 - any failure of the trace means: no closed form
        return None
    if not np.allclose(got, want, rtol=1e-10, atol=1e-10 * max(1.0, float(np.abs(want).max()))):
        return None
    offsets = tuple(tuple(int(v) for v in o) for o in model.stencil.offsets)
    return SymbolicLd(expr, offsets, m, tuple(float(h) for h in model.spacing))
