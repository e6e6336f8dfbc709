"""The all-reduces of a serve split over processes, each carrying an error flag, so that no process is left
waiting for one that failed.

Every collective of the split serve that is not an all-reduce (the halo exchange, the final gather) comes
right after one (:meth:`Flag.maxima`, called without values where the serve has no test to make there: a
gate). A process that fails, by an exception of its own (reading its slab, evaluating the model, a singular
block of its part of the slice) or by a failed global test, calls :meth:`Flag.fail`: it meets the others at
their next all-reduce with the flag raised, the processes exchange their failures, and every one raises the
same error: the failure of the process that reported the largest residual (a failure without one counts as
infinite; ties go to the lowest rank). An :class:`InputError` or a plain :class:`ServeError` that was
reported (a refusal the processes reach together, after a global test) is raised again as such; any other
failure as a :class:`SlabError`, to which the caller adds what was served before it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, NoReturn

import torch
import torch.distributed as dist

from .._collective import group_device, world
from .._errors import InputError, ServeError

__all__ = ["WIDTH", "Failure", "Flag", "SlabError"]

#: The most values one all-reduce of the split serve carries beside its flag (slice-Newton's widest test).
WIDTH = 3


class SlabError(ServeError):
    """A split serve stopped, with the same message in every process; ``result`` is set by the caller (rank
    0: the kept slices served before the failure; the other processes: None)."""


@dataclass(frozen=True)
class Failure:
    """What one process reports of its failure (it travels between processes, so plain data)."""

    text: str
    #: which failure is told when several processes fail: the largest (NaN counts as infinite)
    weight: float = math.inf
    #: ``"stop"`` (a :class:`SlabError`), ``"input"`` (an :class:`InputError`) or ``"serve"`` (a ServeError)
    kind: str = "stop"
    key: str | None = None
    problem: str | None = None
    slice: int | None = None
    site: tuple[int, ...] | None = None
    residual: float | None = None

    @classmethod
    def of(cls, exc: Exception, text: str, at: int | None = None) -> Failure:
        """The failure an exception stands for (``text``: its one line, ``at`` the slice being served, for
        any exception but ours)."""
        if isinstance(exc, InputError):
            return cls(str(exc), kind="input", key=exc.key, problem=exc.problem)
        if isinstance(exc, ServeError) and not isinstance(exc, SlabError):
            return cls(str(exc), kind="serve", slice=exc.slice, site=exc.site, residual=exc.residual)
        return cls(text, slice=at)

    def error(self) -> Exception:
        """The exception every process raises for it."""
        if self.kind == "input":
            return InputError(self.text, key=self.key, problem=self.problem)
        cls = ServeError if self.kind == "serve" else SlabError
        return cls(self.text, slice=self.slice, site=self.site, residual=self.residual)


class Flag:
    """The flagged all-reduces of one split serve (every process makes the same calls)."""

    def __init__(self) -> None:
        self.failure: Failure | None = None

    def maxima(self, *values: float) -> tuple[float, ...]:
        """Each value's largest over the processes (at most :data:`WIDTH`); raises the failure when some
        process reports one, in every process."""
        n = len(values)
        flagged = self.failure is not None
        if world()[1] > 1:
            t = torch.full((1 + WIDTH,), -math.inf, dtype=torch.float64)
            t[0] = float(flagged)
            t[1 : 1 + n] = torch.tensor(values, dtype=torch.float64)
            t = t.to(group_device())
            dist.all_reduce(t, op=dist.ReduceOp.MAX)
            got = t.cpu().tolist()
            flagged, values = got[0] > 0, tuple(got[1 : 1 + n])
        if flagged:
            self._stop()
        return values

    def fail(self, failure: Failure) -> NoReturn:
        """Report ``failure`` to the others at their next all-reduce; raises the error every process raises."""
        self.failure = failure
        self.maxima()
        raise AssertionError("unreachable: a flagged all-reduce raises")  # pragma: no cover

    def _stop(self) -> NoReturn:
        """Every process's failure (None where it had none) to every process; the one told raised."""
        size = world()[1]
        every: list[Any] = [self.failure]
        if size > 1:
            every = [None] * size
            dist.all_gather_object(every, self.failure)
        failed = [(rank, f) for rank, f in enumerate(every) if f is not None]
        _, told = max(failed, key=lambda p: (p[1].weight if p[1].weight == p[1].weight else math.inf, -p[0]))
        raise told.error()
