"""What learning measured: :class:`LearnReport`, and :func:`diagnose`, the residual and gauge measures."""

from __future__ import annotations

import copy
import math
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from typing import Any

import torch

from .._action import del_residual, mixed_hessian
from .._contract import DEFAULT_GAUGE
from .._errors import InputError
from .._lattice import BoundaryKinds, LatticeField
from .._models import AbstractLagrangian
from .._noether import symmetries as _symmetries
from ._data import as_fields, kinetic_scale
from ._gauge import gauge_named

__all__ = [
    "LearnReport",
    "diagnose",
    "symmetry_lines",
    "POOR_FIT_REL_RES",
    "DEGENERATE_RTOL",
    "fit_verdict",
    "fit_warnings",
]

#: A fit whose relative DEL residual ``rel_res`` exceeds this is reported as poor (a warning): its DEL
#: equations do not hold on the training data to 1 %, and a field served with it is unreliable. The repo's
#: cases sit at 1e-10 to 3.5e-3.
POOR_FIT_REL_RES = 1e-2

#: The mixed time Hessian ``h_0^2 M`` over the training cells is degenerate (a theory that cannot step) when
#: its largest singular value is below this (``L_d`` collapsed to a constant or a null Lagrangian: no
#: kinetic term), or its smallest is below this times its largest.
DEGENERATE_RTOL = 1e-8


@dataclass
class LearnReport:
    """What :func:`learn` measured. ``loss`` is the paper's ``F`` (mean squared DEL residual)."""

    method: str
    loss: float
    rel_res: float
    iterations: int
    wall_time: float
    gauge: str
    gauge_residual: float
    hessian_min_sv: float
    hessian_cond: float
    ridge: float = 0.0
    initial_loss: float | None = None
    n_fields: int = 0
    n_sites: int = 0
    n_parameters: int = 0
    stop_reason: str = ""
    history: list[tuple[int, float, float]] = field(default_factory=list)
    validation: dict[str, float] = field(default_factory=dict)
    #: ``learn(..., symmetries=True)``: the invariance of the learned ``L_d`` under each built-in symmetry
    #: over the training data (name, kind, residual, residual_equations, verdict; see :func:`diagnose`)
    symmetries: list[dict[str, Any]] | None = None
    #: largest singular value of ``h_0^2 M`` over the training cells (the scale ``hessian_min_sv`` is judged by)
    hessian_max_sv: float = math.nan
    #: True when ``M`` is degenerate over the data (see :data:`DEGENERATE_RTOL`): serving it will refuse
    degenerate: bool = False
    #: One-line warnings: a degenerate ``M``, a poor fit (``rel_res`` above :data:`POOR_FIT_REL_RES`)
    warnings: list[str] = field(default_factory=list)
    #: ``"auto"`` when the gauge was chosen by ``gauge="auto"`` (``gauge`` is then the one chosen), else None.
    gauge_requested: str | None = None
    #: ``gauge="auto"``: the training ``rel_res`` of every candidate fitted.
    gauge_scores: dict[str, float] = field(default_factory=dict)
    #: ``gauge="auto"``: why ``gauge`` was chosen, in words.
    gauge_choice: str = ""
    #: ``noise="auto"`` or ``"correct"``: the noise estimate (sigma, relative, resolved) and the correction
    #: applied (method, rounds, rms shift of the training fields); None when ``noise="none"``.
    noise: dict[str, Any] | None = None
    #: Where training evaluated the model: ``"cpu"`` or ``"cuda:N (GPU name)"`` (``learn(device=...)``).
    device: str = "cpu"
    #: ``learn`` of an ensemble (:class:`latticedft.EnsembleLagrangian`): members, seed, the number of time
    #: windows resampled, every member's ``rel_res`` (member 0 first) and their total wall time; else None.
    ensemble: dict[str, Any] | None = None
    #: ``select``: the candidate table and the choice (see ``latticedft.select``), else None.
    selection: dict[str, Any] | None = None
    #: What :attr:`sparse` returns, its ``"equation"`` built by ``_equation`` when first read.
    _sparse: dict[str, Any] | None = None
    _equation: Callable[[], dict[str, Any]] | None = field(default=None, repr=False, compare=False)

    @property
    def sparse(self) -> dict[str, Any] | None:
        """A sparse model (``kind = "sparse"``): the threshold used, every term's coefficient and inclusion
        probability over the bagged fits, the terms kept and the equation with its DEL (sympy's printing, built
        when first read: selection learns many candidates and keeps one); else None."""
        if self._sparse is not None and self._equation is not None:
            self._sparse["equation"] = self._equation()
            self._equation = None
        return self._sparse

    def summary_line(self) -> str:
        auto = f", gauge {self.gauge} (auto: {self.gauge_choice})" if self.gauge_requested == "auto" else ""
        return (
            f"learned by {self.method}: F = {self.loss:.3e}, rel_res = {self.rel_res:.3e}, "
            f"gauge residual = {self.gauge_residual:.1e}, min sv(h0^2 M) = {self.hessian_min_sv:.3g}, "
            f"cond(M) = {self.hessian_cond:.3g}, {self.iterations} iterations, {self.wall_time:.2f} s{auto}"
        )

    def verdict(self) -> str:
        """The fit in plain words, with the next step to try: one line (the figures behind it are in
        :meth:`summary_line`; the thresholds are :data:`DEGENERATE_RTOL` and :data:`POOR_FIT_REL_RES`)."""
        return fit_verdict(self.degenerate, self.rel_res, self.method)

    def symmetry_lines(self) -> list[str]:
        """One line per tested symmetry (empty when none was tested)."""
        return symmetry_lines(self.symmetries or [])

    def to_dict(self) -> dict[str, Any]:
        sparse = self.sparse  # its equation built
        d = asdict(self)
        del d["_sparse"], d["_equation"]
        if sparse is not None:
            d["sparse"] = copy.deepcopy(sparse)
        d["history"] = [list(h) for h in self.history]
        if self.symmetries is None:
            del d["symmetries"]
        if self.ensemble is None:
            del d["ensemble"]
        if self.selection is None:
            del d["selection"]
        if self.noise is None:
            del d["noise"]
        return d


def symmetry_lines(reports: list[dict[str, Any]]) -> list[str]:
    """``"rotation-xy  continuous  residual 5.6e-17  equations 2.1e-13  exact"`` per report of :func:`diagnose`."""
    return [
        f"{r['name']:<16} {r['kind']:<10} residual {_e(r['residual'])}   equations {_e(r['residual_equations'])}   "
        f"{r['verdict']}"
        for r in reports
    ]


def _e(x: Any) -> str:
    return f"{x:8.1e}" if isinstance(x, (int, float)) else f"{x!s:>8}"


def diagnose(
    model: AbstractLagrangian,
    data: Any,
    *,
    gauge: str = DEFAULT_GAUGE.value,
    boundary: BoundaryKinds | None = None,
    symmetries: bool | Sequence[Any] = False,
) -> dict[str, Any]:
    """Residual and gauge diagnostics of ``model`` on fields ``data``.

    Returns ``loss`` (mean squared DEL residual), ``rel_res`` (rms residual
    over rms of the M-weighted second time difference), ``gauge_residual``
    (``||h_0^2 mean M + I||_F / sqrt(m)``, or the trace version; ``none`` is
    measured as ``unit-mass``), ``hessian_min_sv`` (smallest singular value of
    ``h_0^2 M`` over the cells; 1 for a unit mass), ``hessian_max_sv`` (the
    largest) and ``hessian_cond`` (largest condition number of ``M`` over the
    cells).

    With ``symmetries=True`` (every built-in symmetry of the data's lattice) or a list of symmetries
    (names or ``latticedft.Symmetry`` objects) it also returns ``symmetries``: per symmetry a dict
    ``name``, ``kind``, ``residual``, ``residual_equations``, ``verdict`` of :func:`latticedft.symmetries`
    over ``data`` (docs/symmetries.md §4).
    """
    fix = gauge_named(gauge)
    if not isinstance(model, AbstractLagrangian):
        raise InputError.at("model", f"expected a latticedft model, got {type(model).__name__}")
    fields = (
        data if isinstance(data, list) and all(isinstance(f, LatticeField) for f in data) else as_fields(data, boundary)
    )
    model._require_bound()
    h0 = model.spacing[0]
    sq, nsites = 0.0, 0
    ms = []
    for f in fields:
        el = del_residual(model, f)
        sq += float((el**2).sum())
        nsites += el[..., 0].numel()
        ms.append(mixed_hessian(model, f))
    mcat = torch.cat(ms)
    mbar = mcat.mean(0)
    gres = fix.residual(mbar, h0)
    sv = torch.linalg.svdvals(h0**2 * mcat)
    smin = float(sv[:, -1].min())
    cond = float((sv[:, 0] / sv[:, -1]).max()) if smin > 0 else math.inf
    loss = sq / max(nsites, 1)
    scale = kinetic_scale(fields, model, mbar)
    rel = math.sqrt(loss) / scale if scale > 0 else math.inf
    out: dict[str, Any] = {
        "loss": loss,
        "rel_res": rel,
        "gauge_residual": gres,
        "hessian_min_sv": smin,
        "hessian_cond": cond,
        "hessian_max_sv": float(sv[:, 0].max()),
    }
    if symmetries is not False:
        out["symmetries"] = symmetry_reports(model, fields, None if symmetries is True else symmetries)
    return out


def symmetry_reports(model: AbstractLagrangian, fields: list[LatticeField], candidates: Any) -> list[dict[str, Any]]:
    """:func:`latticedft.symmetries` of ``model`` over ``fields`` as JSON-ready dicts."""
    keys = ("name", "kind", "residual", "residual_equations", "verdict")
    return [
        {k: (r.verdict if k == "verdict" else r.to_dict()[k]) for k in keys}
        for r in _symmetries(model, fields, candidates)
    ]


def fit_verdict(degenerate: bool, rel_res: float, method: str = "exact") -> str:
    """One plain line on a fit, and what to try next (see :meth:`LearnReport.verdict`)."""
    if degenerate:
        return (
            "verdict: unusable: the learned L_d has no usable kinetic term, so it cannot step a field; next: keep "
            "the default gauge (not 'none'), give data that move more, or try another model kind"
        )
    if not rel_res <= POOR_FIT_REL_RES:
        more = "train longer (max_iter) or " if method != "exact" else ""
        return (
            f"verdict: poor: the data do not obey the learned equations (off by {rel_res:.0%} of their size); "
            f'next: {more}try higher orders, another model kind, or select = "auto" to compare candidates'
        )
    return (
        f"verdict: good: the data obey the learned equations to {rel_res:.1e} of their size; next: serve it "
        "(a served field that leaves the training range is flagged)"
    )


def fit_warnings(diag: dict[str, Any]) -> tuple[bool, list[str]]:
    """``(degenerate, warnings)`` of a fit from its :func:`diagnose` figures, by the documented thresholds."""
    warnings = []
    smin, smax = diag["hessian_min_sv"], diag.get("hessian_max_sv", math.nan)
    degenerate = not smax >= DEGENERATE_RTOL or not smin >= DEGENERATE_RTOL * smax
    if degenerate:
        warnings.append(
            "degenerate fit: the mixed time Hessian M is singular over the data "
            f"(singular values of h0^2 M from {smin:.2e} to {smax:.2e}"
            + (
                "; L_d collapsed to a constant or a null Lagrangian, as gauge 'none' does"
                if smax < DEGENERATE_RTOL
                else ""
            )
            + "): it cannot be served"
        )
    rel = diag["rel_res"]
    if not rel <= POOR_FIT_REL_RES:
        warnings.append(
            f"poor fit: rel_res = {rel:.3g} is above {POOR_FIT_REL_RES:g}: the learned L_d does not satisfy its "
            "DEL equations on the training data; served fields are unreliable"
        )
    return degenerate, warnings
