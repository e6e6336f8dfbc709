"""Noisy data: estimate the measurement noise of a field, and correct fields toward a learned DEL.

The noise estimate is difference-based. The ``k``-th time difference of a field sampled finely enough
shrinks with ``k`` by the factor ``sin(h omega / 2)`` per order, while that of white noise of standard
deviation ``sigma`` has the standard deviation ``sigma sqrt(C(2k, k))``. Normalised by that factor, the
differences of order ``k`` give ``s_k``: it falls with ``k`` while the signal dominates and levels off at
``sigma`` once the noise does. The estimate is resolved when four consecutive orders agree to 6 %
(:data:`AGREE`); else it is unresolved (the data too short or too coarse to tell noise from signal).

The correction (errors in variables) moves the fields ``psi`` from the data ``d`` toward the DEL of a
learned model, minimising ``strength * sum_y |EL_y(psi)|^2 / rbar^2 + |psi - d|^2`` by Gauss-Newton
steps, where ``rbar^2`` is the mean squared row norm of the Jacobian ``J = dEL/dpsi`` (so the weight is
free of units: ``strength = 1`` moves a site half-way to its equation). ``J`` is the Hessian of the
action restricted to the interior rows; it is assembled once per step as a sparse matrix from the per-cell
second derivatives of ``L_d``, and the normal equations ``(strength J^T J / rbar^2 + I) delta = ...`` are
solved by conjugate gradients with sparse products. Learning with ``noise="correct"`` alternates a fit of the
model with a correction of the training fields.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
import torch
import xarray as xr

from .._action import _check_model, action_hessian
from .._errors import InputError
from .._lattice import LatticeField, as_lattice_field, interior_slices
from .._models import AbstractLagrangian
from . import _dist
from ._report import LearnReport
from ._source import FieldSource
from ._stream import TrainingData, by_field

__all__ = [
    "NOISE_MODES",
    "NoiseEstimate",
    "estimate_noise",
    "denoise",
    "correct_fields",
    "SIGNIFICANT",
    "STRENGTH",
    "ROUNDS",
    "learn_noisy",
    "denoised_start",
]

#: ``learn(..., noise=...)``: ``auto`` corrects when the estimated noise is significant, ``correct`` always,
#: ``none`` never.
NOISE_MODES = ("auto", "none", "correct")
#: The estimate is resolved where :data:`SPAN` consecutive orders agree: their largest estimate is at most
#: ``1 + AGREE`` times their smallest (a signal still falling by a few percent per order is not noise).
AGREE = 0.06
SPAN = 4
#: Highest difference order tried.
MAX_ORDER = 20
#: The estimated noise is significant (``noise="auto"`` corrects) above this fraction of the amplitude.
SIGNIFICANT = 1e-6
#: Weight of the DEL residual against the displacement of the fields (see the module docstring) in the first
#: round of ``learn(..., noise="correct")``; every further round multiplies it by :data:`STRENGTH_GROWTH`
#: (the first rounds remove the noise no smooth DEL explains, later ones the slower noise as the model improves).
STRENGTH = 30.0
STRENGTH_GROWTH = 4.0
#: Rounds of fit-then-correct in ``learn(..., noise="correct")``.
ROUNDS = 4
#: :func:`denoise`'s default strength: close to the exact solution of the DEL nearest to the field.
DENOISE_STRENGTH = 1e5
#: ``[[serve]] start = "denoised"``: the initial slices come from :func:`denoise` of this many first slices.
DENOISE_SLICES = 20
#: A correction that moves the training fields by more than this many sigma (rms) is reported as a warning.
SHIFT_WARN = 3.0
#: Noisy data whose noise is more than this share of their second time differences are reported as a warning
#: (on the systems of ``benchmarks.noise``, every row the noise-aware fit failed lay above it: docs/noise.md).
SECOND_DIFFERENCE_WARN = 0.7
#: A sparse model learned from noisy data whose kept coefficients vary over its bagged fits (resampled time
#: blocks) by more than this share of their value is reported as a warning (``benchmarks.discovery_noise``: the
#: rows whose terms were wrong without another warning varied by 140 % to 390 %, those recovered by 0.5 % or less).
SPREAD_WARN = 0.05


@dataclass
class NoiseEstimate:
    """The measurement noise of one or more fields, estimated from their time differences."""

    #: Standard deviation of the noise (field units); ``0.0`` when unresolved.
    sigma: float
    #: ``sigma`` relative to the amplitude (the largest ``|psi|``).
    relative: float
    #: Whether :data:`SPAN` consecutive difference orders agreed.
    resolved: bool
    #: The first of the agreeing orders (``None`` when unresolved).
    order: int | None
    #: ``s_k`` of every order tried.
    by_order: dict[int, float] = field(default_factory=dict)

    @property
    def significant(self) -> bool:
        """Resolved and above :data:`SIGNIFICANT` of the amplitude."""
        return self.resolved and self.relative > SIGNIFICANT

    @property
    def second_difference_ratio(self) -> float | None:
        """The noise's share of the data's second time differences (which the DEL equations must explain):
        ``sqrt(6) sigma`` over their RMS, that is ``sigma / s_2``; near 1 the noise dominates them. ``None``
        when unresolved or not computed."""
        s2 = self.by_order.get(2)
        if not self.resolved or not s2:
            return None
        return min(1.0, self.sigma / s2)

    def summary(self) -> str:
        if not self.resolved:
            return f"noise unresolved (no {SPAN} consecutive difference orders agree)"
        return f"noise sigma = {self.sigma:.2e} ({self.relative:.1e} of the amplitude, orders {self.order}-)"


def _fields(data: object, name: str) -> list[LatticeField]:
    items = list(data) if isinstance(data, (list, tuple)) else [data]
    out: list[LatticeField] = []
    for d in items:
        if not isinstance(d, (xr.DataArray, LatticeField)):
            got = type(d).__name__
            raise InputError.at(name, f"expected a field (DataArray or LatticeField) or a list of them, got {got}")
        out.append(d if isinstance(d, LatticeField) else as_lattice_field(d, source=name))
    if not out:
        raise InputError.at(name, "expected a field (DataArray or LatticeField) or a list of them, got an empty list")
    return out


def estimate_noise(field: xr.DataArray | LatticeField | Sequence[xr.DataArray | LatticeField]) -> NoiseEstimate:
    """Estimate the measurement noise of one or more fields from high-order time differences.

    Parameters
    ----------
    field : DataArray, LatticeField or a list of them
        Observed fields (time first); a list is pooled (one noise level for all).

    Returns
    -------
    NoiseEstimate
        ``sigma`` (0 when unresolved), ``relative`` to the amplitude, ``resolved``, the estimate of every
        difference order.

    Examples
    --------
    >>> import numpy as np, latticedft as ldft
    >>> from latticedft import systems
    >>> f = systems.oscillator_sin(1.2, n=400, dt=0.5)
    >>> noisy = f + 1e-3 * np.random.default_rng(0).standard_normal(f.shape)
    >>> est = ldft.estimate_noise(noisy)
    >>> bool(0.5e-3 < est.sigma < 2e-3)
    True
    """
    fields = _fields(field, "field")
    return _estimate(fields, min(f.shape[0] for f in fields))


def _estimate(fields: list[LatticeField], nt: int, pooled: bool = False) -> NoiseEstimate:
    """:func:`estimate_noise` of ``fields``, the shortest of which (of all pooled) holds ``nt`` slices;
    ``pooled``: ``fields`` are this process's share, the sums and the amplitude taken over the processes."""
    top = min(MAX_ORDER, nt - 8)
    amp = max((float(f.values.abs().max()) for f in fields), default=0.0)
    if pooled:
        amp = float(_dist.all_max(torch.tensor([amp], dtype=torch.float64))[0])
    if top < 2 or amp == 0.0:
        return NoiseEstimate(0.0, 0.0, False, None)
    sums = torch.zeros((2, top + 1), dtype=torch.float64)  # per order: squared differences, their count
    diffs = [f.values for f in fields]
    for k in range(1, top + 1):
        diffs = [d[1:] - d[:-1] for d in diffs]
        sums[0, k] = sum(float((d**2).sum()) for d in diffs)
        sums[1, k] = sum(d.numel() for d in diffs)
    if pooled:
        sums = _dist.all_sum(sums)
    s = {k: math.sqrt(float(sums[0, k]) / float(sums[1, k]) / math.comb(2 * k, k)) for k in range(1, top + 1)}
    for k in range(2, top - SPAN + 2):
        run = [s[j] for j in range(k, k + SPAN)]
        if min(run) > 0 and max(run) <= (1 + AGREE) * min(run):
            sigma = sorted(run)[SPAN // 2]
            return NoiseEstimate(sigma, sigma / amp, True, k, s)
    return NoiseEstimate(0.0, 0.0, False, None, s)


# -- the correction ---------------------------------------------------------------------------------------


def _cg(
    apply: Callable[[torch.Tensor], torch.Tensor], rhs: torch.Tensor, tol: float = 1e-10, max_iter: int = 2000
) -> torch.Tensor:
    """Conjugate gradients for the symmetric positive definite operator ``apply``."""
    x = torch.zeros_like(rhs)
    r = rhs.clone()
    p = r.clone()
    rr = float((r * r).sum())
    stop = tol**2 * rr
    for _ in range(max_iter):
        if rr <= stop or rr == 0.0:
            break
        ap = apply(p)
        alpha = rr / float((p * ap).sum())
        x += alpha * p
        r -= alpha * ap
        rr_new = float((r * r).sum())
        p = r + (rr_new / rr) * p
        rr = rr_new
    return x


def _products(
    model: AbstractLagrangian, f: LatticeField, psi: torch.Tensor
) -> tuple[torch.Tensor, Callable[[torch.Tensor], torch.Tensor]]:
    """The action's gradient at ``psi`` and the product of its Hessian with a vector, on the CPU (where the
    solve runs). The Hessian is assembled once as a sparse matrix (:func:`action_hessian`): each product is one
    sparse product instead of a double backward pass through the model."""
    g, hess = action_hessian(model, psi, f.spacing, f.boundary)
    shape = psi.shape

    def hv(v: torch.Tensor) -> torch.Tensor:
        return torch.from_numpy(hess @ v.reshape(-1).numpy()).reshape(shape)

    return g.cpu(), hv


def _step(
    model: AbstractLagrangian,
    f: LatticeField,
    psi: torch.Tensor,
    data: torch.Tensor,
    mask: torch.Tensor,
    strength: float,
    gen: torch.Generator,
) -> torch.Tensor | None:
    """One Gauss-Newton step: the move ``delta`` of ``psi`` (None when the Jacobian vanishes), on the CPU."""
    g, hv = _products(model, f, psi)
    mask, psi, data = mask.cpu(), psi.cpu(), data.cpu()
    # mean squared row norm of J = mask * H, by Hutchinson's estimate with four Rademacher probes
    probes = [torch.randint(0, 2, psi.shape, generator=gen, dtype=torch.float64) * 2 - 1 for _ in range(4)]
    fro = sum(float(((mask * hv(z)) ** 2).sum()) for z in probes) / len(probes)
    if fro == 0.0:
        return None
    w = strength * float(mask.sum()) / fro
    rhs = -w * hv(mask * g) - (psi - data)
    return _cg(lambda v: w * hv(mask * hv(v)) + v, rhs)


def _correct_one(
    model: AbstractLagrangian, f: LatticeField, data: torch.Tensor, strength: float, steps: int
) -> torch.Tensor:
    """Gauss-Newton steps from ``f``'s values toward the DEL of ``model``, anchored to ``data``."""
    psi = f.values.detach().clone()
    mask = torch.zeros_like(psi)
    mask[interior_slices(f.shape, model.stencil, f.boundary)] = 1.0
    gen = torch.Generator().manual_seed(0)
    for _ in range(steps):
        delta = _step(model, f, psi, data, mask, strength, gen)
        if delta is None:
            break
        psi = psi + delta.to(psi.device)
        if float(delta.abs().max()) <= 1e-14 * max(float(psi.abs().max()), 1.0):
            break
    return psi


def denoise(
    model: AbstractLagrangian,
    field: xr.DataArray | LatticeField,
    *,
    strength: float = DENOISE_STRENGTH,
    steps: int = 2,
) -> xr.DataArray:
    """Move an observed field toward the DEL equations of a learned model (errors in variables).

    Minimises ``strength * sum_y |EL_y(psi)|^2 / rbar^2 + |psi - field|^2`` over ``psi`` by Gauss-Newton
    steps (``rbar^2``: the mean squared row norm of ``dEL/dpsi``). Used to start serving from noisy
    initial slices: denoise the first slices of a noisy field, then serve from them.

    Parameters
    ----------
    model : AbstractLagrangian
        A learned model, bound to the field's lattice.
    field : DataArray or LatticeField
        The observed (noisy) field, at least three time slices.
    strength : float
        Weight of the DEL residual (> 0); larger moves the field closer to an exact solution.
    steps : int
        Gauss-Newton steps (>= 1).

    Returns
    -------
    DataArray
        The corrected field, in the input's layout.
    """
    _check_model(model)
    if not isinstance(strength, (int, float)) or isinstance(strength, bool) or not strength > 0:
        raise InputError.at("strength", f"expected a number > 0, got {strength!r}")
    if not isinstance(steps, int) or isinstance(steps, bool) or steps < 1:
        raise InputError.at("steps", f"expected a positive integer, got {steps!r}")
    (f,) = _fields(field, "field")
    if f.ndim != model.stencil.ndim or f.ncomp != model.m:
        raise InputError.at(
            "field",
            f"expected a {model.stencil.ndim}-D field of {model.m} component(s) (the model's lattice), "
            f"got {f.ndim}-D with {f.ncomp}",
        )
    psi = _correct_one(model, f, f.values, float(strength), steps)
    return f.to_dataarray(psi)


def correct_fields(
    model: AbstractLagrangian,
    fields: list[LatticeField],
    current: list[LatticeField],
    strength: float = STRENGTH,
    steps: int = 1,
) -> list[LatticeField]:
    """One correction round of the training fields: ``current`` moved toward the DEL, anchored to ``fields``."""
    return [
        c.with_values(_correct_one(model, c, d.values, strength, steps)) for c, d in zip(current, fields, strict=True)
    ]


def learn_noisy(
    model: AbstractLagrangian,
    data: TrainingData,
    fit: Callable[[TrainingData], LearnReport],
    mode: str,
    sigma: float | None,
    make: Callable[[list[LatticeField]], TrainingData],
) -> tuple[LearnReport, TrainingData]:
    """``learn(..., noise="auto" | "correct")``: estimate the noise, fit, and when correcting alternate
    :data:`ROUNDS` corrections of the training fields with refits (an exact solve for a linear model; an
    iterative model's refits start from its previous weights). Returns the report (its ``noise`` records the
    estimate and what was done) and the training data of the last fit (the corrected fields when corrected),
    on which an ensemble's resampled members learn."""
    share = _share(data)
    if sigma is None:
        est = _estimate(share, min(src.shape[0] for src in data.sources), pooled=True)
    else:
        amp = max((float(f.values.abs().max()) for f in share), default=0.0)
        amp = float(_dist.all_max(torch.tensor([amp], dtype=torch.float64))[0]) or 1.0
        est = NoiseEstimate(float(sigma), float(sigma) / amp, True, None)
    report = fit(data)
    wanted = mode == "correct" or (mode == "auto" and est.significant)
    info: dict[str, Any] = {
        "mode": mode,
        "sigma": est.sigma,
        "relative": est.relative,
        "resolved": est.resolved,
        "given": sigma is not None,
        "method": "none",
    }
    ratio = est.second_difference_ratio  # None for a given sigma: no orders were estimated
    if ratio is not None:
        info["second_difference_ratio"] = ratio
    warnings = list(report.warnings)
    used = data
    if wanted:
        report, used, shift = _correct(model, data, share, fit, make, report)
        info.update(method="errors in variables", rounds=ROUNDS, shift=shift)
        warnings = list(report.warnings)
        if est.resolved and est.sigma > 0 and shift > SHIFT_WARN * est.sigma:
            warnings.append(
                f"noise correction moved the training fields by {shift:.2e} (rms), over {SHIFT_WARN:g} times the "
                f"noise sigma {est.sigma:.2e}: the model may not describe the data"
            )
    if est.significant and ratio is not None and ratio > SECOND_DIFFERENCE_WARN:
        warnings.append(
            f"the noise makes up {100 * ratio:.0f} % of the data's second time differences ({est.summary()}), "
            "which the learned equations must explain: they may be unreliable; data sampled coarser in time are "
            "less affected (a stride of k divides the share by about k^2 while it is small)"
        )
    spread = largest_spread(model)
    if est.significant and spread is not None and spread[0] > SPREAD_WARN:
        warnings.append(
            f"the kept terms' coefficients vary by up to {100 * spread[0]:.0f} % ({spread[1]}) over the fits on "
            "resampled time blocks of the noisy data: the terms and their coefficients may be the noise's"
        )
    return replace(report, noise=info, warnings=warnings), used


def largest_spread(model: AbstractLagrangian) -> tuple[float, str] | None:
    """A sparse model's largest relative spread of a kept coefficient over its bagged fits, and that term's
    name (None for another model, or without bags)."""
    spread = getattr(model, "bag_spread", None)
    if spread is None or not np.isfinite(spread).any():
        return None
    i = int(np.nanargmax(spread))
    terms = getattr(model, "terms", None) or []
    return float(spread[i]), (str(terms[i].name) if i < len(terms) else f"term {i}")


def _correct(
    model: AbstractLagrangian,
    data: TrainingData,
    share: list[LatticeField],
    fit: Callable[[TrainingData], LearnReport],
    make: Callable[[list[LatticeField]], TrainingData],
    report: LearnReport,
) -> tuple[LearnReport, TrainingData, float]:
    """:data:`ROUNDS` corrections of this process's share of the training fields (every field in a single
    process), each followed by a refit; under a process group each process reads only its corrected fields in
    the refits. Returns the last report (``report``, that of the first fit, without rounds), the data of the
    last fit and the rms shift of the fields."""
    used, current = data, share
    for k in range(ROUNDS):
        current = correct_fields(model, share, current, STRENGTH * STRENGTH_GROWTH**k)
        used = _corrected(data, current) if _dist.is_parallel() else make(current)
        report = fit(used)
    sq: float = sum(float(((c.values - d.values) ** 2).sum()) for c, d in zip(current, share, strict=True))
    count: float = sum(d.values.numel() for d in share)
    if _dist.is_parallel():
        sq, count = _dist.all_sum(torch.tensor([sq, count], dtype=torch.float64)).tolist()
    return report, used, math.sqrt(sq / count)


def _corrected(data: TrainingData, current: list[LatticeField]) -> TrainingData:
    """The training data of a refit under a process group: field ``i`` at home in rank ``i mod N``, this
    process's own fields replaced by their corrections ``current`` (the others are never read here)."""
    rank, size = _dist.world()
    sources = by_field(data.sources)
    for j, f in enumerate(current):
        i = rank + j * size
        sources[i] = FieldSource(f, f.shape[0], sources[i].label, home=rank)
    out = TrainingData(sources, data.chunk_sites)
    out.held_at_home = True  # a training that holds every field (a sparse model's, the symmetry tests) gathers them
    return out


def _share(data: TrainingData) -> list[LatticeField]:
    """This process's share of the training fields (field ``i`` goes to rank ``i mod N``), read for the
    noise estimate (every field without a process group)."""
    rank, size = _dist.world()
    if size == 1 or data._fields is not None:  # one process, or every field already in memory
        return data.fields[rank::size]
    return [src.load() for src in data.sources[rank::size]]


def denoised_start(model: AbstractLagrangian, init: xr.DataArray, slices: int = DENOISE_SLICES) -> xr.DataArray:
    """``init`` with its first two time slices replaced by those of :func:`denoise` applied to its first
    ``slices`` slices (all of them when fewer; unchanged when fewer than three)."""
    tdim = init.dims[0]
    n = min(int(init.sizes[tdim]), slices)
    if n < 3:
        return init
    window = denoise(model, init.isel({tdim: slice(0, n)}))
    out = init.copy(deep=True)
    out[{tdim: slice(0, 2)}] = window.isel({tdim: slice(0, 2)}).values
    return out
