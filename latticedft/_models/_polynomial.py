"""The paper's polynomial ``L_d = sum a_pq d^p s^q``, generalised to n-D stencils and vector fields."""

from __future__ import annotations

import itertools
from typing import Any

import numpy as np
import torch

from .._errors import InputError
from .._stencil import Stencil
from ._base import AbstractLagrangian

__all__ = ["PolynomialLagrangian"]


def _multi_indices(nvars: int, max_total: int) -> list[tuple[int, ...]]:
    return [e for e in itertools.product(range(max_total + 1), repeat=nvars) if sum(e) <= max_total]


class PolynomialLagrangian(AbstractLagrangian):
    """Polynomial ``L_d`` in the stencil mean and the per-axis differences (Qin 2020, Eq. 12).

    Variables per cell: the mean ``psibar`` of the ``K`` stencil values (the
    paper's ``s = q_i + q_{i+1}`` up to a factor 2) and the differences
    ``g_k`` along each lattice axis (the paper's ``d = q_{i+1} - q_i``), each
    with ``m`` components. ``L_d`` spans all products of total degree
    ``<= P`` in the differences and ``<= Q`` in the mean; ``(P, Q) = (4, 8)``
    on a 1D scalar field is the paper's 45-parameter model.

    Parameters
    ----------
    orders : (P, Q)
        Maximum total degree in the differences and in the mean.
    time_symmetric : bool
        Keep only terms of even degree in the time difference ``g_0``
        (``L_d`` invariant under time reversal ``q_i <-> q_{i+1}`` in 1D).
    scale : bool
        Map every variable to ``[-1, 1]`` over the training data before
        building the basis (same span, far better conditioning).
    basis : "legendre" or "monomial"
        Legendre polynomials of the scaled variables (default) span exactly
        the same space as the monomials and are better conditioned.
    stencil : Stencil, optional
        Default: the first-order stencil.

    ``L_d`` is linear in ``coef``, so :func:`latticedft.learn` solves for it
    exactly (an equality-constrained least-squares problem).

    >>> PolynomialLagrangian(orders=(4, 8)).options()["orders"]
    [4, 8]
    """

    kind = "polynomial"
    linear = True

    def __init__(self, orders: tuple[int, int] | list[int] = (4, 8), *, time_symmetric: bool = False,
                 scale: bool = True, basis: str = "legendre", stencil: Stencil | None = None):
        super().__init__(stencil)
        if (not isinstance(orders, (tuple, list)) or len(orders) != 2
                or not all(isinstance(o, int) and not isinstance(o, bool) and o >= 0 for o in orders)):
            raise InputError(f"orders: expected two non-negative integers [P, Q], got {orders!r}")
        if basis not in ("legendre", "monomial"):
            raise InputError(f"basis: expected 'legendre' or 'monomial', got {basis!r}")
        self.orders = (int(orders[0]), int(orders[1]))
        self.time_symmetric = bool(time_symmetric)
        self.scale = bool(scale)
        self.basis = basis

    def options(self) -> dict[str, Any]:
        return {"orders": list(self.orders), "time_symmetric": self.time_symmetric, "scale": self.scale,
                "basis": self.basis}

    # -- structure ---------------------------------------------------------------------------------------
    def _build(self) -> None:
        n, m = self.n, self.m
        p_max, q_max = self.orders
        s_idx = _multi_indices(m, q_max)
        d_idx = _multi_indices(n * m, p_max)
        if self.time_symmetric:
            d_idx = [e for e in d_idx if sum(e[:m]) % 2 == 0]  # g_0 components come first
        exps = [s + d for d in d_idx for s in s_idx]
        self.register_buffer("exponents", torch.tensor(exps, dtype=torch.long))
        nvar = (n + 1) * m
        self.register_buffer("center", torch.zeros(nvar, dtype=torch.float64))
        self.register_buffer("halfwidth", torch.ones(nvar, dtype=torch.float64))
        self.coef = torch.nn.Parameter(torch.zeros(len(exps), dtype=torch.float64))

    @property
    def n_terms(self) -> int:
        return int(self.exponents.shape[0])

    def variables(self, cells: torch.Tensor) -> torch.Tensor:
        """Unscaled variables ``(..., (n+1) m)``: mean components, then ``g_0``, ``g_1``, ...."""
        z = self.mean_and_differences(cells)
        return z.reshape(*z.shape[:-2], -1)

    def prepare(self, cells: list[torch.Tensor]) -> None:
        if not self.scale:
            return
        z = torch.cat([self.variables(c).reshape(-1, self.center.numel()) for c in cells])
        m = self.m
        lo, hi = z.min(0).values, z.max(0).values
        center = (hi + lo) / 2
        half = (hi - lo) / 2
        center[m:] = 0.0  # differences are only scaled, so the time-reversal parity is kept
        half[m:] = z[:, m:].abs().max(0).values
        half = torch.where(half > 0, half, torch.ones_like(half))
        self.center.copy_(center)
        self.halfwidth.copy_(half)

    def _tables(self, z: torch.Tensor, order: int) -> list[torch.Tensor]:
        """Basis polynomials of every variable and their first ``order`` derivatives: each ``(..., V, D+1)``."""
        deg = int(max(self.orders))
        one, zero = torch.ones_like(z), torch.zeros_like(z)
        val, d1, d2 = [one, z], [zero, one], [zero, zero]
        for k in range(1, deg):
            if self.basis == "legendre":  # (k+1) P_{k+1} = (2k+1) z P_k - k P_{k-1}
                val.append(((2 * k + 1) * z * val[k] - k * val[k - 1]) / (k + 1))
                if order >= 1:
                    d1.append(((2 * k + 1) * (val[k] + z * d1[k]) - k * d1[k - 1]) / (k + 1))
                if order >= 2:
                    d2.append(((2 * k + 1) * (2 * d1[k] + z * d2[k]) - k * d2[k - 1]) / (k + 1))
            else:
                val.append(z * val[k])
                if order >= 1:
                    d1.append(val[k] + z * d1[k])
                if order >= 2:
                    d2.append(2 * d1[k] + z * d2[k])
        tables = [val, d1, d2][: order + 1]
        return [torch.stack(t[: deg + 1], dim=-1) for t in tables]

    def _select(self, table: torch.Tensor) -> torch.Tensor:
        """Per term and variable, the table entry of that variable's exponent: ``(..., C, V)``."""
        nvar, width = table.shape[-2], table.shape[-1]
        flat = table.reshape(*table.shape[:-2], nvar * width)
        idx = torch.arange(nvar, device=table.device) * width + self.exponents
        return flat[..., idx]

    def features(self, cells: torch.Tensor) -> torch.Tensor:
        """All basis functions on every cell: ``(..., n_terms)``."""
        z = (self.variables(cells) - self.center) / self.halfwidth
        return self._select(self._tables(z, 0)[0]).prod(dim=-1)

    def fast_derivatives(self, cells: torch.Tensor, pairs: list[tuple[int, int]]):
        """Closed-form ``dL/dx`` and Hessian blocks (no autograd): what serving needs, several times faster."""
        with torch.no_grad():
            z = (self.variables(cells) - self.center) / self.halfwidth
            order = 2 if pairs else 1
            tabs = [self._select(t) for t in self._tables(z, order)]
            val, d1 = tabs[0], tabs[1]
            nvar = z.shape[-1]
            coef = self.coef
            gz = []
            for v in range(nvar):
                f = val.clone()
                f[..., v] = d1[..., v]
                gz.append(f.prod(-1) @ coef)
            n1, m = self.n + 1, self.m
            scale = self.halfwidth.reshape(n1, m)
            gzt = torch.stack(gz, -1).reshape(*z.shape[:-1], n1, m) / scale
            grad = torch.einsum("pk,...pm->...km", self.proj, gzt)
            blocks: dict[tuple[int, int], torch.Tensor] = {}
            if pairs:
                d2 = tabs[2]
                hz = torch.zeros(*z.shape, nvar, dtype=z.dtype)
                for v in range(nvar):
                    for w in range(v, nvar):
                        f = val.clone()
                        if v == w:
                            f[..., v] = d2[..., v]
                        else:
                            f[..., v] = d1[..., v]
                            f[..., w] = d1[..., w]
                        hz[..., v, w] = hz[..., w, v] = f.prod(-1) @ coef
                hz = hz.reshape(*z.shape[:-1], n1, m, n1, m) / (scale[:, :, None, None] * scale[None, None])
                for a, b in pairs:
                    blocks[(a, b)] = torch.einsum("p,q,...piqj->...ij", self.proj[:, a], self.proj[:, b], hz)
        return grad, blocks

    def forward(self, cells: torch.Tensor) -> torch.Tensor:
        return self.features(cells) @ self.coef

    # -- description -------------------------------------------------------------------------------------
    def _variable_names(self) -> list[str]:
        axes = ["t"] + [f"x{k}" for k in range(1, self.n)] if self.n > 1 else ["t"]
        if self.n == 2:
            axes = ["t", "x"]
        elif self.n == 3:
            axes = ["t", "y", "x"]
        comps = list(self.components) if self.components else ([""] if self.m == 1 else [str(c) for c in range(self.m)])
        sub = [f"_{c}" if c else "" for c in comps]
        names = [f"mean{s}" for s in sub]
        for a in axes:
            names += [f"D{a}{s}" for s in sub]
        return names

    def monomials(self) -> dict[tuple[int, ...], float]:
        """``L_d`` as monomial coefficients in the unscaled variables (exponent tuple -> coefficient)."""
        self._require_bound()
        deg = int(max(self.orders))
        nvar = self.center.numel()
        per_var = []
        for v in range(nvar):
            c, h = float(self.center[v]), float(self.halfwidth[v])
            rows = np.zeros((deg + 1, deg + 1))
            for e in range(deg + 1):
                onehot = np.zeros(e + 1)
                onehot[e] = 1.0
                kind = np.polynomial.Legendre if self.basis == "legendre" else np.polynomial.Polynomial
                poly = kind(onehot, domain=[c - h, c + h]).convert(kind=np.polynomial.Polynomial)
                rows[e, : len(poly.coef)] = poly.coef
            per_var.append(rows)
        out: dict[tuple[int, ...], float] = {}
        coef = self.coef.detach().cpu().numpy()
        for a, e in zip(coef, self.exponents.cpu().numpy()):
            if a == 0.0:
                continue
            choices = [[(k, per_var[v][e[v], k]) for k in range(e[v] + 1) if per_var[v][e[v], k] != 0.0]
                       for v in range(nvar)]
            for combo in itertools.product(*choices):
                key = tuple(k for k, _ in combo)
                out[key] = out.get(key, 0.0) + a * float(np.prod([w for _, w in combo]))
        return out

    def describe(self, max_terms: int = 12) -> str:
        head = super().describe()
        if not self.bound:
            return head
        p, q = self.orders
        lines = [head, f"  basis: {self.basis} polynomials, degree <= {p} in the differences, <= {q} in the mean"
                 + (", even in the time difference" if self.time_symmetric else "")
                 + f" ({self.n_terms} terms)"]
        terms = self.monomials()
        big = max((abs(v) for v in terms.values()), default=0.0)
        keep = sorted(((k, v) for k, v in terms.items() if abs(v) > 1e-9 * big and any(k)),
                      key=lambda kv: -abs(kv[1]))
        names = self._variable_names()
        lines.append("  L_d = (constant)" if not keep else "  L_d =")
        for k, v in keep[:max_terms]:
            mono = " ".join(n if e == 1 else f"{n}^{e}" for n, e in zip(names, k) if e)
            lines.append(f"      {v:+.6g} {mono}")
        if len(keep) > max_terms:
            lines.append(f"      ... and {len(keep) - max_terms} smaller terms")
        lines.append("  where mean = average of the stencil values, D<axis> = difference along <axis> "
                     "(psi[x + e] - psi[x])")
        return "\n".join(lines)
