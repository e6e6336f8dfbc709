"""Training a model by iterations: full-batch L-BFGS or Adam on the DEL loss plus a gauge penalty."""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass

import torch
from tqdm.auto import tqdm

from .._action import del_residual, mixed_hessian
from .._lattice import LatticeField
from .._models import AbstractLagrangian
from ._data import kinetic_scale, stacked
from ._gauge import Gauge

__all__ = ["Training", "learn_neural"]

#: L-BFGS runs in chunks of this many iterations (a strong Wolfe line search each), checked in between.
_LBFGS_CHUNK = 20


@dataclass(frozen=True)
class Training:
    """Settings of iterative training (the keywords of :func:`latticedft.learn`)."""

    optimizer: str  # "lbfgs" or "adam"
    max_iter: int
    max_time: float | None
    tol: float
    rel_tol: float | None
    lr: float
    penalty: float
    progress: bool | None


def _objective(
    model: AbstractLagrangian, fields: list[LatticeField], gauge: Gauge, penalty: float, nsites: int, norm2: float
) -> tuple[torch.Tensor, torch.Tensor]:
    """(objective, loss): the mean squared DEL residual over ``norm2``, plus the weighted gauge penalty
    unless the model has a unit mass by construction."""
    sq = torch.zeros((), dtype=torch.float64)
    ms = []
    for f in fields:
        el = del_residual(model, f, create_graph=True)
        sq = sq + (el**2).sum()
        if gauge.fixes and not model.unit_mass_by_construction:
            ms.append(mixed_hessian(model, f, create_graph=True))
    loss = sq / nsites
    obj = loss / norm2
    if ms and (pen := gauge.penalty(torch.cat(ms).mean(0), model.spacing[0])) is not None:  # None: no gauge
        obj = obj + penalty * pen
    return obj, loss


def _optimizer(settings: Training, params: list[torch.nn.Parameter]) -> torch.optim.Optimizer:
    if settings.optimizer == "lbfgs":
        return torch.optim.LBFGS(
            params,
            lr=1.0,
            max_iter=_LBFGS_CHUNK,
            history_size=50,
            line_search_fn="strong_wolfe",
            tolerance_grad=1e-14,
            tolerance_change=1e-16,
        )
    return torch.optim.Adam(params, lr=settings.lr)


def _step(opt: torch.optim.Optimizer, closure: Callable[[], torch.Tensor]) -> torch.Tensor:
    """``opt.step(closure)``, which returns the loss tensor the closure returned."""
    # torch annotates the closure and the result as float; LBFGS and Adam take and return the loss tensor
    return opt.step(closure)  # type: ignore[arg-type, return-value]


class _Run:
    """One training run: the optimizer, the objective it minimises, and the best state seen."""

    def __init__(
        self, model: AbstractLagrangian, fields: list[LatticeField], gauge: Gauge, nsites: int, settings: Training
    ):
        norm2 = kinetic_scale(fields, model, None) ** 2 or 1.0
        fields = stacked(fields)
        self.model, self.settings = model, settings
        self.params = [p for p in model.parameters() if p.requires_grad]
        self.chunk = _LBFGS_CHUNK if settings.optimizer == "lbfgs" else 1
        self.opt = _optimizer(settings, self.params)
        self._terms = (fields, gauge, settings.penalty, nsites, norm2)

    def objective(self) -> float:
        with torch.enable_grad():
            return float(_objective(self.model, *self._terms)[0].detach())

    def closure(self) -> torch.Tensor:
        self.opt.zero_grad()
        obj, _ = _objective(self.model, *self._terms)
        obj.backward()
        return obj

    def step(self, left: int) -> tuple[float, int]:
        """One optimizer step of at most ``left`` iterations: (objective after it, iterations taken)."""
        if self.settings.optimizer == "lbfgs":
            self.opt.param_groups[0]["max_iter"] = min(self.chunk, left)
            state = self.opt.state[self.params[0]]
            before = state.get("n_iter", 0)
            _step(self.opt, self.closure)
            return self.objective(), max(self.opt.state[self.params[0]].get("n_iter", 0) - before, 1)
        return float(_step(self.opt, self.closure).detach()), 1  # Adam: the objective before this update

    def snapshot(self) -> dict[str, torch.Tensor]:
        return {k: v.detach().clone() for k, v in self.model.state_dict().items()}


def _stop_reason(
    settings: Training, obj: float, initial: float, elapsed: float, history: list, step_its: int, left: int, chunk: int
) -> str | None:
    """Why training stops after a step with objective ``obj`` (``left``: iterations left before it)."""
    if not math.isfinite(obj):
        return "non-finite objective"
    if obj <= settings.tol:
        return f"objective <= tol ({settings.tol:g})"
    if settings.rel_tol is not None and obj <= settings.rel_tol * initial:
        return f"objective reduced by {1 / settings.rel_tol:g}x"
    if settings.max_time is not None and elapsed >= settings.max_time:
        return f"max_time ({settings.max_time:g} s)"
    if (
        settings.optimizer == "lbfgs"
        and step_its < min(chunk, left)
        and len(history) > 1
        and history[-2][1] - obj <= 1e-14 * abs(obj)
    ):
        return "converged (no further decrease)"
    return None


def learn_neural(
    model: AbstractLagrangian, fields: list[LatticeField], gauge: Gauge, nsites: int, settings: Training
) -> tuple[int, list[tuple[int, float, float]], float, str]:
    """Train ``model`` in place and leave it at the best objective seen.

    Returns (iterations, history of (iterations, objective, seconds), initial objective, stop reason).
    """
    run = _Run(model, fields, gauge, nsites, settings)
    history: list[tuple[int, float, float]] = []
    t0 = time.perf_counter()
    initial = run.objective()
    best = (initial, run.snapshot())
    reason = "max_iter"
    done = 0
    bar = tqdm(
        total=settings.max_iter,
        desc=f"train ({settings.optimizer})",
        leave=False,
        disable=None if settings.progress is None else not settings.progress,
    )
    try:
        while done < settings.max_iter:
            left = settings.max_iter - done
            obj, step_its = run.step(left)
            done += step_its
            history.append((done, obj, time.perf_counter() - t0))
            bar.update(step_its)
            bar.set_postfix(objective=f"{obj:.3e}")
            if math.isfinite(obj) and obj < best[0]:
                best = (obj, run.snapshot())
            stop = _stop_reason(settings, obj, initial, time.perf_counter() - t0, history, step_its, left, run.chunk)
            if stop is not None:
                reason = stop
                break
    finally:
        bar.close()
    model.load_state_dict(best[1])
    return done, history, initial, reason
