"""Training a model by iterations: full-batch L-BFGS or Adam on the DEL loss plus a gauge penalty.

The objective is always the full batch. When the data come in several chunks (streamed training) or
several processes share them, it is evaluated chunk by chunk with the gradients accumulated (and summed
over processes): the same objective and gradient, with the memory of one chunk. The gauge penalty depends
on the mean mixed Hessian of all the data, so such an evaluation first sums the Hessians (no graph), then
adds each chunk's share of the penalty's gradient by the chain rule.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass

import torch

from .._action import del_residual, mixed_hessian
from .._lattice import LatticeField
from .._models import AbstractLagrangian
from .._progress import progress_bar
from . import _dist
from ._data import kinetic_scale, kinetic_sums, stacked
from ._gauge import Gauge
from ._stream import TrainingData

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
    device: torch.device | None = None  # where the model is evaluated (None: the CPU)


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


class _Chunked:
    """The objective of :func:`_objective` over all the data, evaluated chunk by chunk (and process by process).

    ``value(backward=True)`` leaves the gradient of the whole objective in the parameters' ``.grad``.
    """

    def __init__(self, model: AbstractLagrangian, data: TrainingData, gauge: Gauge, penalty: float, nsites: int):
        self.model, self.data, self.gauge, self.penalty, self.nsites = model, data, gauge, penalty, nsites
        self.params = [p for p in model.parameters() if p.requires_grad]
        self.with_penalty = gauge.fixes and not model.unit_mass_by_construction
        total = torch.zeros(2, dtype=torch.float64)
        for chunk in data.my_chunks():
            for piece in chunk:
                s, n = kinetic_sums(data.read(piece)[0], model, None)
                total += torch.tensor([s, n], dtype=torch.float64)
        total = _dist.all_sum(total)
        self.norm2 = (math.sqrt(float(total[0]) / max(float(total[1]), 1.0)) ** 2) or 1.0

    def _read_all(self) -> Iterator[tuple[LatticeField, int]]:
        """(field, skip) per chunk of this process: pieces whose cells are all their own stacked by shape (one
        pass each), slabs that begin with a neighbour's cells (``skip`` slices of them) one by one."""
        for chunk in self.data.my_chunks():
            read = [self.data.read(p) for p in chunk]
            yield from ((f, 0) for f in stacked([f for f, skip in read if skip == 0]))
            yield from ((f, skip) for f, skip in read if skip)

    def _hessians(self, f: LatticeField, skip: int, graph: bool) -> tuple[torch.Tensor, int]:
        """The sum of the mixed Hessians over the cells that are the piece's own, and their number."""
        mh = mixed_hessian(self.model, f, create_graph=graph)
        if skip:  # an unstacked slab: cells in time-major order
            mh = mh[skip * (mh.shape[0] // (f.shape[0] - int(self.model.stencil.width[0]))) :]
        return mh.sum(0), mh.shape[0]

    def value(self, backward: bool) -> torch.Tensor:
        model, h0 = self.model, self.model.spacing[0]
        gpen, pen, ncells = None, 0.0, 1.0
        if self.with_penalty:
            m = model.m
            msum = torch.zeros(m, m, dtype=torch.float64)
            count = torch.zeros((), dtype=torch.float64)
            with torch.enable_grad():
                for f, skip in self._read_all():
                    s, n = self._hessians(f, skip, graph=False)
                    msum += s.detach()
                    count += n
            mbar = (_dist.all_sum(msum) / _dist.all_sum(count)).requires_grad_(True)
            with torch.enable_grad():
                p = self.gauge.penalty(mbar, h0)
                assert p is not None
                (gpen,) = torch.autograd.grad(p, mbar)
            pen = float(p.detach())
            ncells = float(_dist.all_sum(count))
        sq = 0.0
        if backward:
            for q in self.params:
                q.grad = torch.zeros_like(q)
        with torch.enable_grad():
            for f, skip in self._read_all():
                el = del_residual(model, f, create_graph=backward)
                part_sq = (el**2).sum()
                sq += float(part_sq.detach())
                if not backward:
                    continue
                part = part_sq / self.nsites / self.norm2
                if gpen is not None:
                    s, _ = self._hessians(f, skip, graph=True)
                    part = part + self.penalty * (gpen * s).sum() / ncells
                part.backward()
        if backward and _dist.is_parallel():
            grads = [q.grad if q.grad is not None else torch.zeros_like(q) for q in self.params]
            flat = _dist.all_sum(torch.cat([g.reshape(-1) for g in grads]))
            i = 0
            for q in self.params:
                q.grad = flat[i : i + q.numel()].view_as(q).clone()
                i += q.numel()
        loss = float(_dist.all_sum(torch.tensor(sq, dtype=torch.float64))) / self.nsites
        return torch.tensor(loss / self.norm2 + self.penalty * pen, dtype=torch.float64)


class _Run:
    """One training run: the optimizer, the objective it minimises, and the best state seen."""

    def __init__(self, model: AbstractLagrangian, data: TrainingData, gauge: Gauge, nsites: int, settings: Training):
        self.model, self.settings = model, settings
        self.params = [p for p in model.parameters() if p.requires_grad]
        self.chunk = _LBFGS_CHUNK if settings.optimizer == "lbfgs" else 1
        self.opt = _optimizer(settings, self.params)
        self.chunked: _Chunked | None = None
        if data.in_memory or data.is_single_chunk():  # everything at once, exactly as in memory
            fields = data.fields if data.in_memory else [data.read(p)[0] for p in data.chunks[0]]
            norm2 = kinetic_scale(fields, model, None) ** 2 or 1.0
            self._terms = (stacked(fields), gauge, settings.penalty, nsites, norm2)
        else:
            self.chunked = _Chunked(model, data, gauge, settings.penalty, nsites)

    def objective(self) -> float:
        if self.chunked is not None:
            return float(self.chunked.value(backward=False))
        with torch.enable_grad():
            return float(_objective(self.model, *self._terms)[0].detach())

    def closure(self) -> torch.Tensor:
        self.opt.zero_grad()
        if self.chunked is not None:
            return self.chunked.value(backward=True)
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
    model: AbstractLagrangian, data: TrainingData, gauge: Gauge, nsites: int, settings: Training
) -> tuple[int, list[tuple[int, float, float]], float, str]:
    """Train ``model`` in place and leave it at the best objective seen.

    Returns (iterations, history of (iterations, objective, seconds), initial objective, stop reason).
    """
    run = _Run(model, data, gauge, nsites, settings)
    history: list[tuple[int, float, float]] = []
    t0 = time.perf_counter()
    initial = run.objective()
    best = (initial, run.snapshot())
    reason = "max_iter"
    done = 0
    bar = progress_bar(settings.max_iter, f"train ({settings.optimizer})", settings.progress)
    try:
        while done < settings.max_iter:
            left = settings.max_iter - done
            obj, step_its = run.step(left)
            done += step_its
            history.append((done, obj, time.perf_counter() - t0))
            bar.update(step_its)
            bar.set_postfix(objective=f"{obj:.3e}", refresh=False)  # drawn at the bar's own interval
            if math.isfinite(obj) and obj < best[0]:
                best = (obj, run.snapshot())
            elapsed = time.perf_counter() - t0
            if _dist.is_parallel():  # one clock for all processes, so that all stop at the same iteration
                elapsed = float(_dist.all_max(torch.tensor(elapsed, dtype=torch.float64)))
            stop = _stop_reason(settings, obj, initial, elapsed, history, step_its, left, run.chunk)
            if stop is not None:
                reason = stop
                break
    finally:
        bar.close()
    model.load_state_dict(best[1])
    return done, history, initial, reason
