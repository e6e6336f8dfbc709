"""Learning ``L_d`` from observed fields with an explicit gauge fix (DESIGN.md §1).

The loss ``F = mean over interior sites of |EL_y|^2`` (Qin 2020, Eq. 7) is
ill-posed: ``L_d = const`` gives ``F = 0``. The gauge is fixed by the
unit-mass normalisation of the mixed time Hessian,
``mean over training cells of d^2 L_d / dpsi_x dpsi_{x+e_0} = -I / h_0^2``.
Models linear in their parameters are then an equality-constrained linear
least-squares problem, solved exactly; neural models are trained by L-BFGS or
Adam with the normalisation as a penalty (or by construction).
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field, replace
from typing import Any

import numpy as np
import scipy.linalg
import torch
import xarray as xr
from tqdm.auto import tqdm

from ._action import del_residual, mixed_hessian, second_time_difference
from ._errors import InputError
from ._lattice import BoundaryKinds, LatticeField, as_lattice_field, gather_cells, interior_slices
from ._models import AbstractLagrangian

__all__ = ["learn", "LearnReport", "diagnose", "GAUGES"]

#: Gauge fixes: ``unit-mass`` (mean mixed Hessian = -I/h0^2, every entry),
#: ``trace`` (only its trace, for unequal masses), ``none`` (no fix: collapses).
GAUGES = ("unit-mass", "trace", "none")
#: Optimizers: ``exact`` (linear models), ``lbfgs`` and ``adam`` (neural models).
OPTIMIZERS = ("exact", "lbfgs", "adam")
_RIDGE_GRID = (0.0, 1e-14, 1e-12, 1e-10, 1e-8, 1e-6, 1e-4)


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

    def summary_line(self) -> str:
        return (f"learned by {self.method}: F = {self.loss:.3e}, rel_res = {self.rel_res:.3e}, "
                f"gauge residual = {self.gauge_residual:.1e}, min sv(h0^2 M) = {self.hessian_min_sv:.3g}, "
                f"cond(M) = {self.hessian_cond:.3g}, {self.iterations} iterations, {self.wall_time:.2f} s")

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["history"] = [list(h) for h in self.history]
        return d


# -- data --------------------------------------------------------------------------------------------------
def _as_fields(data: Any, boundary: BoundaryKinds | None) -> list[LatticeField]:
    items = list(data) if isinstance(data, (list, tuple)) else [data]
    if not items:
        raise InputError("data: no training fields given")
    fields = []
    for i, d in enumerate(items):
        src = None if len(items) == 1 else f"data[{i}]"
        if isinstance(d, xr.DataArray) and "source_file" in d.attrs:
            src = str(d.attrs["source_file"])
        fields.append(as_lattice_field(d, source=src, boundary=boundary))
    ref = fields[0]
    for i, f in enumerate(fields[1:], 1):
        name = f"data[{i}]"
        if f.ndim != ref.ndim:
            raise InputError(f"{name}: has {f.ndim} lattice dims {f.dims}; data[0] has {ref.ndim} {ref.dims}")
        if f.components != ref.components:
            raise InputError(f"{name}: component labels {list(f.components or [])} differ from data[0]'s "
                             f"{list(ref.components or [])}")
        if f.ncomp != ref.ncomp:
            raise InputError(f"{name}: has {f.ncomp} components; data[0] has {ref.ncomp}")
        for k, (a, b) in enumerate(zip(f.spacing, ref.spacing)):
            if not math.isclose(a, b, rel_tol=1e-6):
                raise InputError(f"{name}: spacing along {f.dims[k]!r} is {a:.6g}; data[0] has {b:.6g} "
                                 "(a discrete theory belongs to one lattice spacing)")
    return fields


def _check_model_lattice(model: AbstractLagrangian, f: LatticeField, what: str) -> None:
    if model.stencil is not None and model.stencil.ndim != f.ndim:
        raise InputError(f"{what}: has {f.ndim} lattice dims but the model's stencil has {model.stencil.ndim}")
    if model.bound:
        if model.m != f.ncomp:
            raise InputError(f"{what}: has {f.ncomp} component(s) but the model was learned with {model.m}")
        if model.components and f.components and tuple(model.components) != tuple(f.components):
            raise InputError(f"{what}: component labels {list(f.components)} differ from the model's "
                             f"{list(model.components)}")
        for k, (a, b) in enumerate(zip(f.spacing, model.spacing)):
            if not math.isclose(a, b, rel_tol=1e-6):
                raise InputError(f"{what}: spacing along {f.dims[k]!r} is {a:.6g} but the model was learned at "
                                 f"{b:.6g} (a discrete theory belongs to its lattice)")


def _n_sites(f: LatticeField, model: AbstractLagrangian) -> int:
    inner = interior_slices(f.shape, model.stencil, f.periodic)
    return int(np.prod([len(range(*s.indices(n))) for s, n in zip(inner, f.shape)]))


def _kinetic_scale(fields: list[LatticeField], model: AbstractLagrangian, mbar: torch.Tensor | None) -> float:
    """rms over interior sites of the M-weighted second time difference, ``prod(h) M d2psi``."""
    h = model.spacing
    total, count = 0.0, 0
    for f in fields:
        d2 = second_time_difference(f, model.stencil)
        mat = -torch.eye(f.ncomp, dtype=d2.dtype) / h[0] ** 2 if mbar is None else mbar
        v = math.prod(h) * torch.einsum("ij,...j->...i", mat, d2)
        total += float((v ** 2).sum())
        count += d2[..., 0].numel()
    return math.sqrt(total / max(count, 1))


# -- diagnostics -------------------------------------------------------------------------------------------
def diagnose(model: AbstractLagrangian, data: Any, *, gauge: str = "unit-mass",
             boundary: BoundaryKinds | None = None) -> dict[str, float]:
    """Residual and gauge diagnostics of ``model`` on fields ``data``.

    Returns ``loss`` (mean squared DEL residual), ``rel_res`` (rms residual
    over rms of the M-weighted second time difference), ``gauge_residual``
    (``||h_0^2 mean M + I||_F / sqrt(m)``, or the trace version),
    ``hessian_min_sv`` (smallest singular value of ``h_0^2 M`` over the
    cells; 1 for a unit mass) and ``hessian_cond`` (largest condition number
    of ``M`` over the cells).
    """
    fields = data if isinstance(data, list) and all(isinstance(f, LatticeField) for f in data) \
        else _as_fields(data, boundary)
    model._require_bound()
    h0 = model.spacing[0]
    sq, nsites = 0.0, 0
    ms = []
    for f in fields:
        el = del_residual(model, f)
        sq += float((el ** 2).sum())
        nsites += el[..., 0].numel()
        ms.append(mixed_hessian(model, f))
    mcat = torch.cat(ms)
    mbar = mcat.mean(0)
    m = mbar.shape[0]
    eye = torch.eye(m, dtype=mbar.dtype)
    if gauge == "trace":
        gres = abs(float(h0 ** 2 * torch.trace(mbar) / m + 1))
    else:
        gres = float(torch.linalg.norm(h0 ** 2 * mbar + eye) / math.sqrt(m))
    sv = torch.linalg.svdvals(h0 ** 2 * mcat)
    smin = float(sv[:, -1].min())
    cond = float((sv[:, 0] / sv[:, -1]).max()) if smin > 0 else math.inf
    loss = sq / max(nsites, 1)
    scale = _kinetic_scale(fields, model, mbar)
    rel = math.sqrt(loss) / scale if scale > 0 else math.inf
    return {"loss": loss, "rel_res": rel, "gauge_residual": gres, "hessian_min_sv": smin, "hessian_cond": cond}


# -- the linear (exact) solve --------------------------------------------------------------------------------
def _unit(x: torch.Tensor, a: int, i: int) -> torch.Tensor:
    t = torch.zeros_like(x)
    t[..., a, i] = 1.0
    return t


def _residual_matrix(model: AbstractLagrangian, f: LatticeField) -> np.ndarray:
    """Rows: DEL residual components on interior sites; columns: basis functions. ``EL = R @ coef``.

    Per-cell derivatives of every basis function, in closed form when the
    model offers them (``feature_derivatives``), else by forward mode (one
    pass per stencil point and component); then the adjoint of the cell
    gather puts them on the sites.
    """
    st = model.stencil
    x = gather_cells(f.values, st, f.periodic)
    k, m = st.size, f.ncomp
    closed = getattr(model, "feature_derivatives", None)
    if closed is not None:
        d, _ = closed(x)  # (*cells, K, m, C)
    else:
        d = torch.stack([torch.stack([torch.func.jvp(model.features, (x,), (_unit(x, a, i),))[1]
                                      for i in range(m)], -2) for a in range(k)], -3)  # (*cells, K, m, C)
    c = d.shape[-1]
    z = torch.zeros(*f.values.shape, c, dtype=torch.float64, requires_grad=True)
    with torch.enable_grad():
        (sites,) = torch.autograd.grad((gather_cells(z, st, f.periodic) * d).sum(), z)
    sites = math.prod(model.spacing) * sites  # (*N, m, C)
    inner = interior_slices(f.shape, st, f.periodic)
    return sites[inner].reshape(-1, c).numpy()


def _gauge_matrix(model: AbstractLagrangian, fields: list[LatticeField], gauge: str) -> tuple[np.ndarray, np.ndarray]:
    """Constraint rows ``G coef = g`` of the gauge (mean mixed Hessian over all training cells)."""
    st = model.stencil
    a0, a1 = st.anchor, st.forward
    m = model.m
    c = model.n_terms
    total = torch.zeros(c, m, m, dtype=torch.float64)
    ncells = 0
    closed = getattr(model, "feature_derivatives", None)
    for f in fields:
        x = gather_cells(f.values, st, f.periodic)
        ncells += x[..., 0, 0].numel()
        if closed is not None:
            _, blocks = closed(x, [(a0, a1)], first=False)
            total += blocks[(a0, a1)].reshape(-1, m, m, c).sum(0).permute(2, 0, 1)
            continue
        for i in range(m):
            first = _unit(x, a0, i)

            def dphi(y: torch.Tensor, t: torch.Tensor = first) -> torch.Tensor:
                return torch.func.jvp(model.features, (y,), (t,))[1]

            for j in range(m):
                second = torch.func.jvp(dphi, (x,), (_unit(x, a1, j),))[1]
                total[:, i, j] += second.reshape(-1, c).sum(0)
    mean = (total / ncells).numpy()  # (C, m, m)
    h0 = model.spacing[0]
    if gauge == "trace":
        return np.trace(mean, axis1=1, axis2=2)[None, :] * h0 ** 2, np.array([-float(m)])
    return mean.reshape(c, m * m).T * h0 ** 2, -np.eye(m).reshape(-1)


def _constrained_lstsq(r: np.ndarray, g_mat: np.ndarray | None, g_vec: np.ndarray | None,
                       ridge: float) -> np.ndarray:
    c = r.shape[1]
    colsq = float((r ** 2).sum(0).mean()) or 1.0
    lam = ridge * colsq
    if g_mat is None:  # no gauge: the unit-norm minimiser (what an unconstrained trainer drifts to)
        a = np.vstack([r, math.sqrt(lam) * np.eye(c)]) if lam > 0 else r
        _, _, vt = np.linalg.svd(a, full_matrices=True)
        return vt[-1]
    u, s, vt = np.linalg.svd(g_mat, full_matrices=True)
    if s.size == 0 or s[0] == 0:
        raise InputError("model: no basis function gives a mixed time Hessian, so no L_d of this class can "
                         "describe dynamics (raise the orders)")
    rank = int((s > 1e-12 * s[0]).sum())
    theta_p = vt[:rank].T @ ((u[:, :rank].T @ g_vec) / s[:rank])
    null = vt[rank:].T
    if null.shape[1] == 0:
        return theta_p
    a = r @ null
    b = -(r @ theta_p)
    if lam > 0:
        a = np.vstack([a, math.sqrt(lam) * null])
        b = np.concatenate([b, -math.sqrt(lam) * theta_p])
    # Null Lagrangians (discrete divergences, e.g. a term linear in one difference) have zero columns in
    # exact arithmetic but round-off ones in practice: without a cutoff they get huge coefficients that
    # swamp L_d and break the gauge (seen on the 1+1D wave string). Drop directions below 1e-10 relative.
    z, *_ = scipy.linalg.lstsq(a, b, cond=1e-10, lapack_driver="gelsd")
    return theta_p + null @ z


def _time_split(f: LatticeField) -> tuple[LatticeField, LatticeField] | None:
    nt = f.shape[0]
    cut = int(round(0.7 * nt))
    if cut < 3 or nt - cut < 3:
        return None
    return f.with_values(f.values[:cut]), f.with_values(f.values[cut:])


def _learn_linear(model, fields, gauge, ridge, nsites):
    rs = [_residual_matrix(model, f) for f in fields]
    g_mat, g_vec = (None, None) if gauge == "none" else _gauge_matrix(model, fields, gauge)
    validation: dict[str, float] = {}
    if ridge == "auto":
        folds: list[tuple[list[np.ndarray], list[np.ndarray], list[LatticeField]]] = []
        if len(fields) >= 2:
            for i in range(min(len(fields), 6)):
                folds.append(([r for j, r in enumerate(rs) if j != i], [rs[i]], [fields[i]]))
        else:
            split = _time_split(fields[0])
            if split is None:
                raise InputError.at("ridge", "'auto' needs two or more fields, or one field of at least 9 time slices")
            folds.append(([_residual_matrix(model, split[0])], [_residual_matrix(model, split[1])], [split[1]]))
        best, best_score = 0.0, math.inf
        for lam in _RIDGE_GRID:
            scores = []
            for train, val, vfields in folds:
                rt = np.vstack(train) / math.sqrt(sum(r.shape[0] for r in train) / model.m)
                theta = _constrained_lstsq(rt, g_mat, g_vec, lam)
                rv = np.vstack(val)
                res = math.sqrt(float(((rv @ theta) ** 2).sum()) / (rv.shape[0] / model.m))
                scale = _kinetic_scale(vfields, model, None)
                scores.append(res / scale)
            score = float(np.mean(scores))
            validation[f"{lam:g}"] = score
            if score < best_score * (1 - 1e-9):
                best, best_score = lam, score
        ridge = best
    r = np.vstack(rs) / math.sqrt(nsites)
    theta = _constrained_lstsq(r, g_mat, g_vec, float(ridge))
    with torch.no_grad():
        model.coef.copy_(torch.from_numpy(theta))
    return float(ridge), validation


# -- the neural (iterative) solve -----------------------------------------------------------------------------
def _objective(model, fields, gauge, penalty, nsites, norm2):
    sq = 0
    ms = []
    for f in fields:
        el = del_residual(model, f, create_graph=True)
        sq = sq + (el ** 2).sum()
        if gauge != "none" and not model.unit_mass_by_construction:
            ms.append(mixed_hessian(model, f, create_graph=True))
    loss = sq / nsites
    obj = loss / norm2
    if ms:
        mbar = torch.cat(ms).mean(0)
        m = mbar.shape[0]
        h0 = model.spacing[0]
        if gauge == "trace":
            gterm = (h0 ** 2 * torch.trace(mbar) / m + 1) ** 2
        else:
            gterm = ((h0 ** 2 * mbar + torch.eye(m, dtype=mbar.dtype)) ** 2).sum() / m
        obj = obj + penalty * gterm
    return obj, loss


def _stacked(fields: list[LatticeField]) -> list[LatticeField]:
    """Fields of one shape and periodicity stacked along a batch axis: one pass instead of one per field."""
    groups: dict[tuple, list[LatticeField]] = {}
    for f in fields:
        groups.setdefault((f.shape, f.periodic), []).append(f)
    return [g[0] if len(g) == 1 else replace(g[0], values=torch.stack([f.values for f in g]), batch=1)
            for g in groups.values()]


def _learn_neural(model, fields, gauge, optimizer, nsites, *, max_iter, max_time, tol, rel_tol, lr, penalty,
                  progress):
    """Full-batch L-BFGS (strong Wolfe line search, in chunks of up to 20 iterations) or Adam."""
    norm2 = _kinetic_scale(fields, model, None) ** 2 or 1.0
    fields = _stacked(fields)
    params = [p for p in model.parameters() if p.requires_grad]
    chunk = 20 if optimizer == "lbfgs" else 1
    if optimizer == "lbfgs":
        opt = torch.optim.LBFGS(params, lr=1.0, max_iter=chunk, history_size=50, line_search_fn="strong_wolfe",
                                tolerance_grad=1e-14, tolerance_change=1e-16)
    else:
        opt = torch.optim.Adam(params, lr=lr)

    def objective() -> float:
        with torch.enable_grad():
            return float(_objective(model, fields, gauge, penalty, nsites, norm2)[0].detach())

    def closure():
        opt.zero_grad()
        obj, _ = _objective(model, fields, gauge, penalty, nsites, norm2)
        obj.backward()
        return obj

    def snapshot():
        return {k: v.detach().clone() for k, v in model.state_dict().items()}

    history: list[tuple[int, float, float]] = []
    t0 = time.perf_counter()
    initial = objective()
    best = (initial, snapshot())
    reason = "max_iter"
    done = 0
    bar = tqdm(total=max_iter, desc=f"train ({optimizer})", disable=None if progress is None else not progress,
               leave=False)
    try:
        while done < max_iter:
            if optimizer == "lbfgs":
                opt.param_groups[0]["max_iter"] = min(chunk, max_iter - done)
                before = opt.state[params[0]].get("n_iter", 0)
                opt.step(closure)
                step_its = max(opt.state[params[0]].get("n_iter", 0) - before, 1)
                obj = objective()
            else:
                obj = float(opt.step(closure).detach())  # Adam: the objective before this update
                step_its = 1
            done += step_its
            history.append((done, obj, time.perf_counter() - t0))
            bar.update(step_its)
            bar.set_postfix(objective=f"{obj:.3e}")
            if not math.isfinite(obj):
                reason = "non-finite objective"
                break
            if obj < best[0]:
                best = (obj, snapshot())
            if obj <= tol:
                reason = f"objective <= tol ({tol:g})"
                break
            if rel_tol is not None and obj <= rel_tol * initial:
                reason = f"objective reduced by {1 / rel_tol:g}x"
                break
            if max_time is not None and time.perf_counter() - t0 >= max_time:
                reason = f"max_time ({max_time:g} s)"
                break
            if optimizer == "lbfgs" and step_its < min(chunk, max_iter - done + step_its) and \
                    len(history) > 1 and history[-2][1] - obj <= 1e-14 * abs(obj):
                reason = "converged (no further decrease)"
                break
    finally:
        bar.close()
    model.load_state_dict(best[1])
    return done, history, initial, reason


# -- public -----------------------------------------------------------------------------------------------------
def learn(model: AbstractLagrangian, data: xr.DataArray | Sequence[xr.DataArray], *, gauge: str = "unit-mass",
          ridge: float | str = 0.0, optimizer: str | None = None, max_iter: int = 500,
          max_time: float | None = None, tol: float = 0.0, rel_tol: float | None = None, lr: float = 1e-3,
          penalty: float = 1.0, boundary: BoundaryKinds | None = None,
          progress: bool | None = None) -> LearnReport:
    """Learn ``L_d`` from one or more observed fields; the model is fitted in place.

    Parameters
    ----------
    model : AbstractLagrangian
        The model to fit (e.g. ``PolynomialLagrangian((4, 8))``).
    data : DataArray or list of DataArray
        Observed fields in the DESIGN.md layout, each on its own lattice of
        the same spacing.
    gauge : "unit-mass", "trace" or "none"
        How the gauge is fixed (see :data:`GAUGES`). ``none`` shows the
        collapse the loss alone leads to.
    ridge : float or "auto"
        Linear models: Tikhonov weight (relative to the mean squared column
        norm); ``"auto"`` picks it from a grid by the held-out relative
        residual (leave-one-field-out, or the last 30 % of a single field).
    optimizer : "exact", "lbfgs" or "adam"
        Default: ``exact`` for linear models, ``lbfgs`` otherwise.
    max_iter, max_time, tol, rel_tol, lr, penalty
        Iterative training: stop after ``max_iter`` iterations or
        ``max_time`` seconds, or when the objective is ``<= tol`` or has
        fallen by the factor ``rel_tol`` (the paper stops at ``1e-5``);
        Adam's learning rate; weight of the gauge penalty.
    boundary : str or dict, optional
        Boundary kinds per spatial axis (``periodic`` axes wrap, so every
        site carries an equation); default from the coordinates' ``periodic``
        attribute.
    progress : bool, optional
        Progress bar; ``None`` shows it only on a terminal.

    Returns
    -------
    LearnReport
        Also stored as ``model.report_``.

    Examples
    --------
    >>> import numpy as np, xarray as xr, latticedft as ldft
    >>> t = np.arange(60) * 0.1
    >>> data = [xr.DataArray(a * np.cos(t), dims="t", coords={"t": t}, name="psi") for a in (0.5, 1.0)]
    >>> model = ldft.PolynomialLagrangian(orders=(2, 2))
    >>> report = ldft.learn(model, data)
    >>> report.gauge_residual < 1e-10 and report.rel_res < 1e-3
    True
    """
    if gauge not in GAUGES:
        raise InputError.at("gauge", f"expected one of {list(GAUGES)}, got {gauge!r}")
    if not isinstance(model, AbstractLagrangian):
        raise InputError(f"model: expected a latticedft model, got {type(model).__name__}")
    fields = _as_fields(data, boundary)
    f0 = fields[0]
    for i, f in enumerate(fields):
        _check_model_lattice(model, f, f"data[{i}]")
    optimizer = optimizer or ("exact" if model.linear else "lbfgs")
    if optimizer not in OPTIMIZERS:
        raise InputError.at("optimizer", f"expected 'exact', 'lbfgs' or 'adam', got {optimizer!r}")
    if optimizer == "exact" and not model.linear:
        raise InputError.at("optimizer", f"'exact' needs a model linear in its parameters; {model.kind!r} is not")
    if not (ridge == "auto" or (isinstance(ridge, (int, float)) and not isinstance(ridge, bool) and ridge >= 0)):
        raise InputError.at("ridge", f"expected a number >= 0 or 'auto', got {ridge!r}")
    if not isinstance(max_iter, int) or max_iter < 1:
        raise InputError.at("max_iter", f"expected a positive integer, got {max_iter!r}")
    model.bind(f0.ndim, f0.ncomp, f0.spacing, f0.components)
    model.prepare([gather_cells(f.values, model.stencil, f.periodic) for f in fields])
    nsites = sum(_n_sites(f, model) for f in fields)
    if nsites == 0:
        raise InputError("data: no interior site carries a DEL equation (lattices too small for the stencil)")
    t0 = time.perf_counter()
    history: list[tuple[int, float, float]] = []
    initial = None
    validation: dict[str, float] = {}
    used_ridge = 0.0
    if optimizer == "exact":
        used_ridge, validation = _learn_linear(model, fields, gauge, ridge, nsites)
        iterations, reason = 1, "exact solve"
    else:
        iterations, history, initial, reason = _learn_neural(
            model, fields, gauge, optimizer, nsites, max_iter=max_iter, max_time=max_time, tol=tol,
            rel_tol=rel_tol, lr=lr, penalty=penalty, progress=progress)
    wall = time.perf_counter() - t0
    diag = diagnose(model, fields, gauge="trace" if gauge == "trace" else "unit-mass")
    report = LearnReport(method=optimizer, loss=diag["loss"], rel_res=diag["rel_res"], iterations=iterations,
                         wall_time=wall, gauge=gauge, gauge_residual=diag["gauge_residual"],
                         hessian_min_sv=diag["hessian_min_sv"], hessian_cond=diag["hessian_cond"],
                         ridge=used_ridge, initial_loss=initial, n_fields=len(fields), n_sites=nsites,
                         n_parameters=model.n_parameters(), stop_reason=reason, history=history,
                         validation=validation)
    model.report_ = report
    return report
