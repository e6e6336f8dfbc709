"""A linear ``L_d`` over a library of features of the stencil mean times monomials of the differences."""

from __future__ import annotations

import itertools
import re
from collections.abc import Callable, Iterable, Sequence
from typing import Any, cast

import numpy as np
import torch

from .._collective import merged_max, merged_min
from .._errors import InputError
from .._stencil import Stencil
from .._symbolic import SymbolicLd
from ._library import cell_variables
from ._linear import LinearLagrangian

__all__ = ["FeatureLagrangian", "FeatureFunction"]

#: A user feature: the stencil mean ``(..., m)`` (unscaled) -> one feature ``(...)`` or several ``(..., k)``,
#: built from smooth torch operations (learning and serving differentiate it twice).
FeatureFunction = Callable[[torch.Tensor], torch.Tensor]

_NAMED = re.compile(r"^(poly):(\d+)$|^(trig):(\d+)(?::([0-9.eE+-]+))?$")


def _parse(entry: Any) -> tuple[str, int, float] | FeatureFunction:
    """``"poly:K"`` -> ("poly", K, 1), ``"trig:K[:w]"`` -> ("trig", K, w); a callable is kept as it is."""
    if callable(entry):
        return cast(FeatureFunction, entry)  # a user's callable, taken as the contract above says
    match = _NAMED.match(entry) if isinstance(entry, str) else None
    if match is None:
        raise InputError.at(
            "features",
            f"expected 'poly:K', 'trig:K', 'trig:K:w' (K a positive integer, w a positive number) or a Python "
            f"function of the stencil mean, got {entry!r}",
        )
    if match.group(1):
        kind, k, w = "poly", int(match.group(2)), 1.0
    else:
        kind, k = "trig", int(match.group(4))
        try:
            w = float(match.group(5)) if match.group(5) else 1.0
        except ValueError:
            w = float("nan")
        if not (np.isfinite(w) and w > 0):
            raise InputError.at("features", f"expected a positive frequency w in 'trig:K:w', got {entry!r}")
    if k < 1:
        raise InputError.at("features", f"expected K >= 1 in {entry!r}")
    return kind, k, w


def _name_of(fn: FeatureFunction) -> str:
    return f"{getattr(fn, '__module__', '?')}:{getattr(fn, '__qualname__', type(fn).__name__)}"


class FeatureLagrangian(LinearLagrangian):
    """``L_d = sum_{f, e} a_{f e} f(psibar) g^e``: a library of features of the stencil mean, each times the
    monomials of the per-axis differences (PySINDy's custom libraries, for a discrete Lagrangian).

    The variables are those of :class:`PolynomialLagrangian`: the mean ``psibar`` of the stencil values and
    the difference ``g_k`` along each axis. The mean features are a constant plus, per library entry:

    - ``"poly:K"``: Legendre polynomials ``P_1 .. P_K`` of the mean (scaled to ``[-1, 1]`` over the training
      data when ``scale``), all products of total degree ``<= K`` for a vector field;
    - ``"trig:K"`` / ``"trig:K:w"``: ``sin(j w psibar_i)`` and ``cos(j w psibar_i)``, ``j = 1 .. K``, of each
      component, unscaled (``w`` defaults to 1);
    - a Python function of the unscaled mean ``(..., m)`` returning ``(...)`` or ``(..., k)`` (API only: a
      case.toml names only the strings above, and a model with a function cannot be saved to a model file).

    Every mean feature multiplies every monomial of the differences of total degree ``<= differences``.
    ``features=["poly:8"]`` with ``differences=4`` spans the paper's 45-term polynomial.

    Parameters
    ----------
    features : list of str or callables
        The library (see above); default ``["poly:8"]``.
    differences : int
        Maximum total degree in the differences (>= 2: a kinetic term needs the square of ``g_0``).
    time_symmetric : bool
        Keep only monomials of even degree in the time difference ``g_0``.
    scale : bool
        Scale the differences (by their largest magnitude) and the polynomial mean features (to ``[-1, 1]``)
        over the training data; trigonometric and user features see the unscaled mean.
    stencil : Stencil, optional
        Default: the first-order stencil.

    >>> FeatureLagrangian(["trig:1"], differences=2).options()["features"]
    ['trig:1']
    """

    prepare_merges_processes = True

    kind = "features"
    #: Buffers set by :meth:`_build`: difference exponents per monomial ``(D, n m)``; the mean's scaling.
    dexp: torch.Tensor
    center: torch.Tensor
    halfwidth: torch.Tensor
    dscale: torch.Tensor

    def __init__(
        self,
        features: Sequence[str | FeatureFunction] = ("poly:8",),
        *,
        differences: int = 4,
        time_symmetric: bool = False,
        scale: bool = True,
        stencil: Stencil | None = None,
    ):
        super().__init__(stencil)
        if isinstance(features, str) or callable(features) or not isinstance(features, (list, tuple)):
            raise InputError.at("features", f"expected a list of features, e.g. ['poly:4', 'trig:1'], got {features!r}")
        if not features:
            raise InputError.at("features", "expected at least one feature, e.g. ['poly:4']")
        if not isinstance(differences, int) or isinstance(differences, bool) or differences < 2:
            raise InputError.at("differences", f"expected an integer >= 2, got {differences!r}")
        for name, flag in (("time_symmetric", time_symmetric), ("scale", scale)):
            if not isinstance(flag, (bool, np.bool_)):
                raise InputError.at(name, f"expected True or False, got {flag!r}")
        self.library = [_parse(f) for f in features]
        self.feature_names = [f if isinstance(f, str) else _name_of(f) for f in features]
        self.differences = int(differences)
        self.time_symmetric = bool(time_symmetric)
        self.scale = bool(scale)

    @property
    def has_functions(self) -> bool:
        """True when the library holds Python functions (the model cannot then be written to a model file)."""
        return any(callable(f) for f in self.library)

    def options(self) -> dict[str, Any]:
        return {
            "features": list(self.feature_names),
            "differences": self.differences,
            "time_symmetric": self.time_symmetric,
            "scale": self.scale,
        }

    def auto_candidates(self, n: int, ridge: Any = 0.0) -> list[dict[str, Any]]:
        """Differences of degree 2 and 4, then the candidates every linear kind shares."""
        return [{"differences": d} for d in (2, 4)] + self._auto_tail(self.differences, n, ridge)

    # -- structure ---------------------------------------------------------------------------------------
    def _build(self) -> None:
        n, m = self.n, self.m
        dexp = [e for e in itertools.product(range(self.differences + 1), repeat=n * m) if sum(e) <= self.differences]
        if self.time_symmetric:
            dexp = [e for e in dexp if sum(e[:m]) % 2 == 0]  # g_0 components come first
        self.register_buffer("dexp", torch.tensor(dexp, dtype=torch.long))
        self.register_buffer("center", torch.zeros(m, dtype=torch.float64))
        self.register_buffer("halfwidth", torch.ones(m, dtype=torch.float64))
        self.register_buffer("dscale", torch.ones(n * m, dtype=torch.float64))
        probe = torch.zeros(1, m, dtype=torch.float64)
        self._n_mean = int(self._mean_features(probe).shape[-1])
        super()._build()

    @property
    def n_terms(self) -> int:
        return self._n_mean * int(self.dexp.shape[0])

    def prepare(self, cells: Iterable[torch.Tensor]) -> None:
        if not self.scale:
            return
        m = self.m
        lo = hi = amax = None
        for c in cells:
            if c.numel() == 0:
                continue
            z = self.mean_and_differences(c).reshape(-1, (self.n + 1) * m)
            zlo, zhi, zabs = z.min(0).values, z.max(0).values, z.abs().max(0).values
            lo = zlo if lo is None else torch.minimum(lo, zlo)
            hi = zhi if hi is None else torch.maximum(hi, zhi)
            amax = zabs if amax is None else torch.maximum(amax, zabs)
        size = ((self.n + 1) * m,)  # several processes: each read its share of the cells
        lo, hi, amax = merged_min(lo, size), merged_max(hi, size), merged_max(amax, size)
        if lo is None or hi is None or amax is None:
            return
        half = (hi[:m] - lo[:m]) / 2
        self.center.copy_((hi[:m] + lo[:m]) / 2)
        self.halfwidth.copy_(torch.where(half > 0, half, torch.ones_like(half)))
        self.dscale.copy_(torch.where(amax[m:] > 0, amax[m:], torch.ones_like(amax[m:])))

    # -- evaluation ---------------------------------------------------------------------------------------
    def _mean_features(self, mean: torch.Tensor) -> torch.Tensor:
        """``(..., m)`` -> ``(..., F)``: the constant, then each library entry's features."""
        cols = [torch.ones_like(mean[..., 0])]
        for entry in self.library:
            if callable(entry):
                out = entry(mean)
                if (
                    not isinstance(out, torch.Tensor)
                    or out.dim() not in (mean.dim() - 1, mean.dim())
                    or out.shape[: mean.dim() - 1] != mean.shape[:-1]
                ):
                    raise InputError.at(
                        "features",
                        f"{_name_of(entry)} returned {getattr(out, 'shape', type(out).__name__)}; expected a tensor "
                        f"of shape {tuple(mean.shape[:-1])} or {(*mean.shape[:-1], 'k')}",
                    )
                cols.extend([out] if out.dim() == mean.dim() - 1 else list(out.unbind(-1)))
            elif entry[0] == "poly":
                z = (mean - self.center) / self.halfwidth
                tables = [_legendre(z[..., i], entry[1]) for i in range(mean.shape[-1])]
                for e in itertools.product(range(entry[1] + 1), repeat=mean.shape[-1]):
                    if 0 < sum(e) <= entry[1]:
                        term = None
                        for i, k in enumerate(e):
                            if k:
                                term = tables[i][k] if term is None else term * tables[i][k]
                        assert term is not None
                        cols.append(term)
            else:
                _, k, w = entry
                for i in range(mean.shape[-1]):
                    for j in range(1, k + 1):
                        cols += [torch.sin(j * w * mean[..., i]), torch.cos(j * w * mean[..., i])]
        return torch.stack(cols, -1)

    def _difference_monomials(self, g: torch.Tensor) -> torch.Tensor:
        """``(..., n m)`` scaled differences -> ``(..., D)``, products written out (smooth at zero)."""
        powers = [torch.ones_like(g), g]
        for _ in range(2, self.differences + 1):
            powers.append(powers[-1] * g)
        table = torch.stack(powers, -1)  # (..., V, deg + 1)
        nvar, width = table.shape[-2], table.shape[-1]
        flat = table.reshape(*table.shape[:-2], nvar * width)
        idx = torch.arange(nvar, device=g.device) * width + self.dexp  # (D, V): where each factor sits
        factors = flat[..., idx].unbind(-1)  # V tensors (..., D)
        out = factors[0]
        for f in factors[1:]:  # explicit products: smooth second derivatives where a factor vanishes
            out = out * f
        return out

    def features(self, cells: torch.Tensor) -> torch.Tensor:
        z = self.mean_and_differences(cells)
        mean = z[..., 0, :]
        g = z[..., 1:, :].reshape(*z.shape[:-2], -1) / self.dscale
        mf = self._mean_features(mean)
        dm = self._difference_monomials(g)
        return (mf[..., :, None] * dm[..., None, :]).reshape(*mf.shape[:-1], -1)

    def symbolic(self) -> SymbolicLd | None:
        """``L_d`` in the cell symbols, its scaling folded in (None when the library holds a Python function)."""
        import sympy

        self._require_bound()
        if self.has_functions:
            return None
        q, g = cell_variables(self.proj, (1.0,) * self.n, self.m)
        mf = self._mean_forms(q)
        scaled = [
            g[k][i] / sympy.Float(float(self.dscale[k * self.m + i])) for k in range(self.n) for i in range(self.m)
        ]
        coef = self.coef.detach().tolist()
        terms = []
        for f, base in enumerate(mf):
            for e, exps in enumerate(self.dexp.tolist()):
                a = coef[f * len(self.dexp) + e]
                if a != 0.0:
                    terms.append(sympy.Float(a) * base * sympy.Mul(*[x**k for x, k in zip(scaled, exps) if k]))
        expr = sympy.Add(*terms)
        return SymbolicLd(expr, tuple(tuple(o) for o in self.stencil.to_list()), self.m, self.spacing)

    def _mean_forms(self, mean: list[Any]) -> list[Any]:
        """The mean features of :meth:`_mean_features` as sympy expressions of the unscaled mean."""
        import sympy

        cols: list[Any] = [sympy.Integer(1)]
        for entry in self.library:
            assert not callable(entry)
            if entry[0] == "poly":
                z = [(x - float(c)) / float(h) for x, c, h in zip(mean, self.center.tolist(), self.halfwidth.tolist())]
                tables = [_legendre_forms(zi, entry[1]) for zi in z]
                for e in itertools.product(range(entry[1] + 1), repeat=len(mean)):
                    if 0 < sum(e) <= entry[1]:
                        cols.append(sympy.Mul(*[tables[i][k] for i, k in enumerate(e) if k]))
            else:
                _, k, w = entry
                for x in mean:
                    for j in range(1, k + 1):
                        cols += [sympy.sin(j * w * x), sympy.cos(j * w * x)]
        return cols

    def describe(self, max_terms: int | None = 12) -> str:
        head = super().describe(max_terms)
        lib = ", ".join(self.feature_names)
        return (
            f"{head}\n  library: constant, {lib}; times difference monomials of degree <= {self.differences}"
            + (", even in the time difference" if self.time_symmetric else "")
            + (f" ({self.n_terms} terms)" if self.bound else "")
        )


def _legendre_forms(z: Any, deg: int) -> list[Any]:
    """``[P_0(z), ..., P_deg(z)]`` of a sympy expression, by the same recurrence as :func:`_legendre`."""
    out = [z**0, z]
    for k in range(1, deg):
        out.append(((2 * k + 1) * z * out[k] - k * out[k - 1]) / (k + 1))
    return out[: deg + 1]


def _legendre(z: torch.Tensor, deg: int) -> list[torch.Tensor]:
    """``[P_0(z), ..., P_deg(z)]`` by the three-term recurrence."""
    out = [torch.ones_like(z), z]
    for k in range(1, deg):
        out.append(((2 * k + 1) * z * out[k] - k * out[k - 1]) / (k + 1))
    return out[: deg + 1]
