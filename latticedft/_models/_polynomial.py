"""The paper's polynomial ``L_d = sum a_pq d^p s^q``, generalised to n-D stencils and vector fields."""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable, Iterable, Mapping, Sequence
from typing import Any

import numpy as np
import torch

from .._collective import merged_max, merged_min
from .._contract import NumpyForms
from .._errors import InputError
from .._options import option
from .._stencil import Stencil
from .._symbolic import SymbolicLd, cell_symbols
from . import _polynumpy
from ._linear import LinearLagrangian
from ._polybasis import _VANDERMONDE_MAX_DEGREE, _coefficient_matrix_f64, _pairs

__all__ = ["PolynomialLagrangian", "AUTO_ORDERS"]

#: Orders of the polynomial candidates of ``select = "auto"`` (beside the hand-set ones).
AUTO_ORDERS = ((2, 2), (2, 4), (4, 4), (4, 8), (2, 8), (4, 12))


def _multi_indices(nvars: int, max_total: int) -> list[tuple[int, ...]]:
    return [e for e in itertools.product(range(max_total + 1), repeat=nvars) if sum(e) <= max_total]


def _coefficient_matrix(basis: str, deg: int, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    """``(D+1, 3 (D+1))``: the Vandermonde row of ``z`` times this is the basis table and its two derivatives."""
    mat = _coefficient_matrix_f64(basis, deg)
    return mat if mat.dtype == dtype and mat.device == device else mat.to(dtype=dtype, device=device)


def _times(a: torch.Tensor | None, b: torch.Tensor | None) -> torch.Tensor | None:
    """Product where ``None`` stands for 1 (an empty product)."""
    return b if a is None else a if b is None else a * b


class PolynomialLagrangian(LinearLagrangian):
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
    parity : "even", optional
        ``"even"``: keep only terms of even total degree (in the mean and the
        differences together), with the mean scaled about 0, so that
        ``L_d(-psi) = L_d(psi)`` exactly: the point reflection
        ``psi -> -psi`` is a symmetry by construction (docs/symmetries.md).
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

    prepare_merges_processes = True

    kind = "polynomial"
    #: Buffers set by :meth:`_build`: per term, the exponent of each variable ``(C, V)``; the scaling of the
    #: variables, ``z = (variable - center) / halfwidth``.
    exponents: torch.Tensor
    center: torch.Tensor
    halfwidth: torch.Tensor

    def __init__(
        self,
        orders: Sequence[int] = (4, 8),
        *,
        time_symmetric: bool = False,
        parity: str | None = None,
        scale: bool = True,
        basis: str = "legendre",
        stencil: Stencil | None = None,
    ):
        super().__init__(stencil)
        if (
            not isinstance(orders, (tuple, list))
            or len(orders) != 2
            or not all(isinstance(o, int) and not isinstance(o, bool) and o >= 0 for o in orders)
        ):
            raise InputError.at("orders", f"expected two non-negative integers [P, Q], got {orders!r}")
        for name, flag in (("time_symmetric", time_symmetric), ("scale", scale)):
            if not isinstance(flag, (bool, np.bool_)):
                raise InputError.at(name, f"expected True or False, got {flag!r}")
        if basis not in ("legendre", "monomial"):
            raise InputError.at("basis", f"expected 'legendre' or 'monomial', got {basis!r}")
        if parity not in (None, "even"):
            raise InputError.at("parity", f"expected 'even' (L_d(-psi) = L_d(psi)) or none, got {parity!r}")
        self.orders = (int(orders[0]), int(orders[1]))
        self.time_symmetric = bool(time_symmetric)
        self.parity = parity
        self.scale = bool(scale)
        self.basis = basis

    def options(self) -> dict[str, Any]:
        return {
            "orders": list(self.orders),
            "time_symmetric": self.time_symmetric,
            "parity": self.parity,
            "scale": self.scale,
            "basis": self.basis,
        }

    @classmethod
    def parameter_lower_bound(cls, options: Mapping[str, Any], n: int, m: int) -> tuple[int, str] | None:
        """The monomials of the orders (half of them when time-symmetric: the even powers of the time
        differences)."""
        try:
            model = cls(**options)  # resolves the defaults; tensors come with bind()
        except Exception:  # noqa: BLE001 - bad options are the case reader's to report
            return None
        p, q = model.orders
        terms = math.comb(q + m, m) * math.comb(p + n * m, n * m)
        if model.time_symmetric:
            terms //= 2  # the even powers of the time differences: at least half
        return terms, "model.orders"

    def auto_candidates(self, n: int, ridge: Any = 0.0) -> list[dict[str, Any]]:
        """The orders of :data:`AUTO_ORDERS`, then the candidates every linear kind shares."""
        return [{"orders": list(o)} for o in AUTO_ORDERS] + self._auto_tail(self.orders[0], n, ridge)

    # -- structure ---------------------------------------------------------------------------------------
    def _build(self) -> None:
        n, m = self.n, self.m
        p_max, q_max = self.orders
        s_idx = _multi_indices(m, q_max)
        d_idx = _multi_indices(n * m, p_max)
        if self.time_symmetric:
            d_idx = [e for e in d_idx if sum(e[:m]) % 2 == 0]  # g_0 components come first
        exps = [s + d for d in d_idx for s in s_idx]
        if self.parity == "even":  # every variable is odd under psi -> -psi, and so is P_k for odd k
            exps = [e for e in exps if sum(e) % 2 == 0]
        self.register_buffer("exponents", torch.tensor(exps, dtype=torch.long))
        nvar = (n + 1) * m
        self.register_buffer("center", torch.zeros(nvar, dtype=torch.float64))
        self.register_buffer("halfwidth", torch.ones(nvar, dtype=torch.float64))
        super()._build()  # coef, one per term

    @property
    def n_terms(self) -> int:
        return int(self.exponents.shape[0])

    def variables(self, cells: torch.Tensor) -> torch.Tensor:
        """Unscaled variables ``(..., (n+1) m)``: mean components, then ``g_0``, ``g_1``, ...."""
        z = self.mean_and_differences(cells)
        return z.reshape(*z.shape[:-2], -1)

    def prepare(self, cells: Iterable[torch.Tensor]) -> None:
        if not self.scale:
            return
        m = self.m
        lo = hi = amax = None
        for c in cells:  # chunk by chunk: the cells may be read from files one slab at a time
            if c.numel() == 0:
                continue
            z = self.variables(c).reshape(-1, self.center.numel())
            zlo, zhi, zabs = z.min(0).values, z.max(0).values, z.abs().max(0).values
            lo = zlo if lo is None else torch.minimum(lo, zlo)
            hi = zhi if hi is None else torch.maximum(hi, zhi)
            amax = zabs if amax is None else torch.maximum(amax, zabs)
        size = (self.center.numel(),)  # several processes: each read its share of the cells
        lo, hi, amax = merged_min(lo, size), merged_max(hi, size), merged_max(amax, size)
        if lo is None or hi is None or amax is None:
            return
        center = (hi + lo) / 2
        half = (hi - lo) / 2
        center[m:] = 0.0  # differences are only scaled, so the time-reversal parity is kept
        half[m:] = amax[m:]
        if self.parity == "even":  # the mean too, so that psi -> -psi maps every scaled variable to minus itself
            center[:m] = 0.0
            half[:m] = amax[:m]
        half = torch.where(half > 0, half, torch.ones_like(half))
        self.center.copy_(center)
        self.halfwidth.copy_(half)

    def _tables(self, z: torch.Tensor, order: int) -> list[torch.Tensor]:
        """Basis polynomials of every variable and their first ``order`` derivatives: each ``(..., V, D+1)``.

        A Vandermonde matrix of ``z`` times constant coefficient matrices (a handful of tensor operations
        whatever the degree); above degree 12 the three-term recurrence, whose round-off does not grow with
        the monomial coefficients of high-degree Legendre polynomials.
        """
        deg = int(max(self.orders))
        if deg > _VANDERMONDE_MAX_DEGREE:
            return self._tables_recurrence(z, order)
        width = deg + 1
        # powers by repeated products (autograd-safe at z = 0 to any order, unlike pow with a zero exponent)
        pw = [torch.ones_like(z), z]
        for _ in range(2, width):
            pw.append(pw[-1] * z)
        table = (
            torch.stack(pw[:width], dim=-1)
            @ _coefficient_matrix(self.basis, deg, z.dtype, z.device)[:, : (order + 1) * width]
        )
        return list(table.split(width, dim=-1))

    def _tables_recurrence(self, z: torch.Tensor, order: int) -> list[torch.Tensor]:
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
        factors = self._select(self._tables(z, 0)[0]).unbind(-1)
        # explicit products, not prod(): autograd's second derivatives of prod() divide by the factors and
        # lose all accuracy where one nearly vanishes (a mean at the centre, a zero difference)
        out = factors[0]
        for f in factors[1:]:
            out = out * f
        return out

    # -- closed-form derivatives (no autograd) --------------------------------------------------------------
    def _affine(self) -> dict[str, Any]:
        """Constant matrices of the chain rule, cached until ``proj`` or ``halfwidth`` change.

        ``P[(k, i), (p, i)] = proj[p, k]`` gives ``z = (cells.flatten(-2) @ P - center) / halfwidth``;
        ``W = dz/dx = P / halfwidth`` (``(K m, V)``), so ``dL/dx = W @ dL/dz``.
        """
        key = tuple((t.data_ptr(), t._version, t.dtype) for t in (self.proj, self.halfwidth))
        cached = self.__dict__.get("_affine_cache")
        if cached is None or cached[0] != key:
            hw = self.halfwidth
            eye = torch.eye(self.m, dtype=hw.dtype, device=hw.device)
            p = torch.einsum("pk,ij->kipj", self.proj.to(hw.dtype), eye).reshape(-1, hw.numel())
            cached = (key, {"P": p, "W": p / hw, "pairs": {}})
            self.__dict__["_affine_cache"] = cached
        return cached[1]

    def _pair_matrix(self, aff: dict[str, Any], a: int, b: int) -> torch.Tensor:
        """``(npairs, m m)``: the block ``d^2/dx_a dx_b`` (flattened) from the second derivatives in ``z``
        listed once per unordered pair ``v <= w`` (the order of :func:`_pairs`)."""
        mat: torch.Tensor | None = aff["pairs"].get((a, b))
        if mat is None:
            rows = aff["W"].unflatten(0, (-1, self.m))  # (K, m, V): dz/dx_a
            full = torch.einsum("iv,jw->vwij", rows[a], rows[b])  # block[i, j] = sum_vw full[v, w, i, j] H[v, w]
            mat = torch.stack(
                [full[v, w] + full[w, v] if v != w else full[v, v] for v, w in _pairs(rows.shape[-1])]
            ).reshape(-1, self.m**2)
            aff["pairs"][(a, b)] = mat
        return mat

    def _scaled(self, cells: torch.Tensor, aff: dict[str, Any]) -> torch.Tensor:
        z: torch.Tensor = (cells.detach().flatten(-2) @ aff["P"] - self.center) / self.halfwidth  # (..., V)
        return z

    def _factors(self, z: torch.Tensor, order: int) -> list[torch.Tensor]:
        """Per variable and term, the basis factor and its first ``order`` derivatives in the scaled
        variable ``z`` (``(..., V)``): each ``(..., V, C)``, a term being the product of its factors."""
        deg = int(max(self.orders))
        width, r = deg + 1, order + 1
        key = (self.exponents.data_ptr(), self.exponents._version, z.dtype, z.device)
        cache = self.__dict__.get("_factor_cache")
        if cache is None or cache[0] != key:
            tables: dict[int, tuple[torch.Tensor, torch.Tensor]] = {}
            cache = (key, tables)
            self.__dict__["_factor_cache"] = cache
        if r not in cache[1]:  # where each term's factors sit in the flattened tables; per variable, the matrix
            exps = self.exponents.T.to(z.device)  # from its powers to its factor of every term (fused: no lookups)
            offs = (torch.arange(exps.shape[0], device=z.device) * (r * width))[None, :, None] + (
                torch.arange(r, device=z.device) * width
            )[:, None, None]
            fused = _polynumpy.fused_factor_matrix(
                _coefficient_matrix_f64(self.basis, deg).numpy(), self.exponents.cpu().numpy(), order
            )
            cache[1][r] = ((offs + exps[None]).reshape(-1), torch.from_numpy(fused).to(z.dtype).to(z.device))
        index, fused_t = cache[1][r]
        if deg > _VANDERMONDE_MAX_DEGREE:  # the recurrence's tables, then the factors picked from them
            picked = torch.cat(self._tables_recurrence(z, order), dim=-1).flatten(-2).index_select(-1, index)
            return list(picked.unflatten(-1, (r, z.shape[-1], -1)).unbind(-3))
        pw = torch.cumprod(torch.cat([torch.ones_like(z)[..., None], z[..., None].expand(*z.shape, width - 1)], -1), -1)
        out = (pw.movedim(-2, 0).reshape(z.shape[-1], -1, width) @ fused_t).reshape(z.shape[-1], *z.shape[:-1], -1)
        return list(out.movedim(0, -2).unflatten(-1, (r, -1)).unbind(-2))  # powers by products, one product per var

    def _term_derivatives(self, z: torch.Tensor, second: bool) -> torch.Tensor:
        """``(..., V [+ npairs], C)``: ``d phi_c / dz_v`` for every ``v``, then (``second``)
        ``d^2 phi_c / dz_v dz_w`` for the pairs ``v <= w`` of :func:`_pairs`.

        Each term is a product of one factor per variable; the products of the other factors are built
        from prefix and suffix products (no division: factors may vanish).
        """
        tabs = self._factors(z, 2 if second else 1)
        val, d1 = tabs[0].unbind(-2), tabs[1].unbind(-2)
        nvar = len(val)
        pre: list[torch.Tensor | None] = [None] * nvar  # product of the factors before v
        suf: list[torch.Tensor | None] = [None] * nvar  # ... and after v
        for v in range(1, nvar):
            pre[v] = _times(pre[v - 1], val[v - 1])
        for v in range(nvar - 2, -1, -1):
            suf[v] = _times(suf[v + 1], val[v + 1])
        excl = [_times(pre[v], suf[v]) for v in range(nvar)]
        out = [d1[v] if (e := excl[v]) is None else d1[v] * e for v in range(nvar)]
        if second:
            d2 = tabs[2].unbind(-2)
            for v in range(nvar):
                out.append(d2[v] if (e := excl[v]) is None else d2[v] * e)
                between = pre[v]  # times the factors strictly between v and w
                for w in range(v + 1, nvar):
                    if w > v + 1:
                        between = _times(between, val[w - 1])
                    others = _times(between, suf[w])
                    dd = d1[v] * d1[w]
                    out.append(dd if others is None else dd * others)
        return torch.stack(out, dim=-2)

    def _by_chunks(
        self, z: torch.Tensor, per_cell: int, fn: Callable[[torch.Tensor], Sequence[torch.Tensor]]
    ) -> list[torch.Tensor]:
        """``fn`` on the cells of ``z``, in chunks (of the flattened cells) that bound the intermediates."""
        size = max(1, option("poly_chunk_elements") // max(per_cell, 1))
        if z.numel() <= size * z.shape[-1]:
            return list(fn(z))
        zf = z.reshape(-1, z.shape[-1])
        parts = [fn(zf[s : s + size]) for s in range(0, zf.shape[0], size)]
        return [torch.cat(p).reshape(*z.shape[:-1], *p[0].shape[1:]) for p in zip(*parts)]

    def derivatives_of_features(
        self, cells: torch.Tensor, pairs: Sequence[tuple[int, int]], first: bool
    ) -> tuple[torch.Tensor | None, dict[tuple[int, int], torch.Tensor]]:
        """Closed-form derivatives of every basis function (:meth:`LinearLagrangian.feature_derivatives`).

        The chain rule of :meth:`fast_derivatives`, term by term instead of summed with ``coef``.
        """
        self._require_bound()
        k, m = cells.shape[-2], cells.shape[-1]
        pairs = list(pairs)
        with torch.no_grad():
            aff = self._affine()
            z = self._scaled(cells, aff)
            lead, nvar, c = z.shape[:-1], z.shape[-1], self.n_terms
            w = aff["W"]
            mats = [self._pair_matrix(aff, a, b).T for a, b in pairs]

            def part(zc: torch.Tensor) -> list[torch.Tensor]:
                t = self._term_derivatives(zc, bool(pairs))
                res = [w @ t[..., :nvar, :]] if first else []  # (..., K m, C)
                return res + [mat @ t[..., nvar:, :] for mat in mats]  # (..., m m, C)

            npairs = nvar * (nvar + 1) // 2 if pairs else 0
            per_cell = c * (4 * nvar + 2 * npairs + (k * m if first else 0) + len(pairs) * m * m)
            outs = self._by_chunks(z, per_cell, part)
            d = outs.pop(0).reshape(*lead, k, m, c) if first else None
            blocks = {pr: o.reshape(*lead, m, m, c) for pr, o in zip(pairs, outs)}
        return d, blocks

    def fast_derivatives(
        self, cells: torch.Tensor, pairs: list[tuple[int, int]]
    ) -> tuple[torch.Tensor, dict[tuple[int, int], torch.Tensor]]:
        """Closed-form ``dL/dx`` and Hessian blocks (no autograd): what serving needs, several times faster."""
        k, m = cells.shape[-2], cells.shape[-1]
        with torch.no_grad():
            aff = self._affine()
            coef = self.coef.detach()
            z = self._scaled(cells, aff)
            nvar = z.shape[-1]
            npairs = nvar * (nvar + 1) // 2 if pairs else 0
            (s,) = self._by_chunks(
                z, self.n_terms * (4 * nvar + 2 * npairs), lambda zc: (self._term_derivatives(zc, bool(pairs)) @ coef,)
            )
            return self._chained(s, aff, k, m, pairs)

    def _chained(
        self, s: torch.Tensor, aff: dict[str, Any], k: int, m: int, pairs: Sequence[tuple[int, int]]
    ) -> tuple[torch.Tensor, dict[tuple[int, int], torch.Tensor]]:
        """:meth:`fast_derivatives` from ``s``, the derivatives of ``L_d`` in the scaled variables (``dL/dz_v``,
        then ``d^2L/dz_v dz_w``, ``v <= w``): through the chain rule to the cells' values."""
        nvar = aff["W"].shape[-1]
        grad = (s[..., :nvar] @ aff["W"].T).unflatten(-1, (k, m))
        blocks = {(a, b): (s[..., nvar:] @ self._pair_matrix(aff, a, b)).unflatten(-1, (m, m)) for a, b in pairs}
        return grad, blocks

    def _shares_tables(self, other: PolynomialLagrangian) -> bool:
        """Whether :meth:`_term_derivatives` of ``other`` takes the same recurrence's basis tables (above degree
        :data:`_VANDERMONDE_MAX_DEGREE`) and the same terms: the same basis, degree and exponents."""
        deg = int(max(self.orders))
        return (
            deg > _VANDERMONDE_MAX_DEGREE
            and other.basis == self.basis
            and int(max(other.orders)) == deg
            and other.exponents.shape == self.exponents.shape
            and bool(torch.equal(other.exponents, self.exponents))
        )

    def numpy_derivatives(self, pairs: Sequence[tuple[int, int]]) -> NumpyForms | None:
        """The closed forms of :meth:`fast_derivatives` in numpy, with fused basis tables (see ``_polynumpy``)."""
        self._require_bound()
        return _polynumpy.numpy_derivatives(self, pairs)

    def symbolic(self) -> SymbolicLd | None:
        """``L_d = sum_c coef_c prod_v B_{e_vc}(z_v)`` in closed form, with ``z_v = (variable_v - center_v) /
        halfwidth_v`` written out in the stencil values (the basis polynomials ``B_k`` exact, the learned
        numbers as the doubles they are): the model's own scaling folded in. ``None`` until bound."""
        if not self.bound:
            return None
        import sympy

        m, k = self.m, self.stencil.size
        sym = cell_symbols(k, m)
        proj = self.proj.detach().cpu().double().numpy()
        center = self.center.detach().cpu().numpy()
        half = self.halfwidth.detach().cpu().numpy()
        z = sympy.Symbol("z")
        basis = [
            sympy.Poly(sympy.legendre(e, z) if self.basis == "legendre" else z**e, z)
            for e in range(int(max(self.orders)) + 1)
        ]
        scaled = []
        for p in range(proj.shape[0]):
            for i in range(m):
                v = p * m + i
                lin = sympy.Add(*[sympy.Float(float(proj[p, a])) * sym[a][i] for a in range(k) if proj[p, a] != 0])
                scaled.append((lin - sympy.Float(float(center[v]))) / sympy.Float(float(half[v])))
        factor = [[basis[e].as_expr().subs(z, zv) for e in range(len(basis))] for zv in scaled]
        terms = []
        for a, exps in zip(self.coef.detach().cpu().numpy(), self.exponents.cpu().numpy()):
            if a != 0.0:
                terms.append(sympy.Float(float(a)) * sympy.Mul(*[factor[v][int(e)] for v, e in enumerate(exps) if e]))
        spacing = tuple(float(h) for h in self.spacing)
        return SymbolicLd(sympy.Add(*terms), tuple(tuple(o) for o in self.stencil.offsets), m, spacing)

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
            choices = [
                [(k, per_var[v][e[v], k]) for k in range(e[v] + 1) if per_var[v][e[v], k] != 0.0] for v in range(nvar)
            ]
            for combo in itertools.product(*choices):
                key = tuple(k for k, _ in combo)
                out[key] = out.get(key, 0.0) + a * float(np.prod([w for _, w in combo]))
        return out

    def describe(self, max_terms: int | None = 12) -> str:
        """The learned ``L_d``: its largest ``max_terms`` monomials by magnitude (``None``: every one), in the
        unscaled variables."""
        head = super().describe(max_terms)
        if not self.bound:
            return head
        p, q = self.orders
        lines = [
            head,
            f"  basis: {self.basis} polynomials, degree <= {p} in the differences, <= {q} in the mean"
            + (", even in the time difference" if self.time_symmetric else "")
            + (", even in psi" if self.parity == "even" else "")
            + f" ({self.n_terms} terms)",
        ]
        terms = self.monomials()
        big = max((abs(v) for v in terms.values()), default=0.0)
        keep = sorted(((k, v) for k, v in terms.items() if abs(v) > 1e-9 * big and any(k)), key=lambda kv: -abs(kv[1]))
        names = self._variable_names()
        lines.append("  L_d = (constant)" if not keep else "  L_d =")
        shown = keep if max_terms is None else keep[:max_terms]
        for k, v in shown:
            mono = " ".join(n if e == 1 else f"{n}^{e}" for n, e in zip(names, k) if e)
            lines.append(f"      {v:+.6g} {mono}")
        if len(keep) > len(shown):
            lines.append(
                f"      ... {len(keep) - len(shown)} more terms, smaller (use --all, or model.describe(max_terms=None))"
            )
        lines.append(
            "  where mean = average of the stencil values, D<axis> = difference along <axis> (psi[x + e] - psi[x])"
        )
        return "\n".join(lines)


def stacked_fast_derivatives(
    members: Sequence[PolynomialLagrangian], cells: Sequence[torch.Tensor], pairs: list[tuple[int, int]]
) -> list[tuple[torch.Tensor, dict[tuple[int, int], torch.Tensor]]] | None:
    """Every member's :meth:`PolynomialLagrangian.fast_derivatives` on its own ``cells`` (one tensor per member,
    of one shape), the members' basis tables evaluated together: the recurrence's tables and the terms' products
    (elementwise operations, the same on every element whatever the batch) once on the members' scaled variables
    stacked, each member's products with its coefficients and chain rule on its own part, as its own call makes
    them (a matrix product's rounding may depend on its shape). The same values as the calls one by one, with one
    evaluation of the tables instead of one per member: a 1D ensemble of high-degree polynomials spends its serving
    there. None unless the members share the recurrence's tables (:meth:`PolynomialLagrangian._shares_tables`)
    and their cells, stacked, fit in one chunk (``poly_chunk_elements``)."""
    first = members[0]
    if len(members) < 2 or not all(first._shares_tables(p) for p in members):
        return None
    k, m = cells[0].shape[-2], cells[0].shape[-1]
    with torch.no_grad():
        affs = [p._affine() for p in members]
        zs = [p._scaled(c, aff) for p, c, aff in zip(members, cells, affs, strict=True)]
        nvar = zs[0].shape[-1]
        npairs = nvar * (nvar + 1) // 2 if pairs else 0
        size = max(1, option("poly_chunk_elements") // max(first.n_terms * (4 * nvar + 2 * npairs), 1))
        if len(zs) * zs[0].numel() > size * nvar:  # the stacked tables would exceed one chunk
            return None
        terms = first._term_derivatives(torch.stack(zs), bool(pairs))
        return [
            p._chained(terms[j].clone() @ p.coef.detach(), aff, k, m, pairs)
            for j, (p, aff) in enumerate(zip(members, affs, strict=True))
        ]
