"""One thread policy: torch's threads and the BLAS/OpenMP pools of numpy and scipy, bounded together.

``torch.set_num_threads`` bounds only torch's own pool; numpy's and scipy's BLAS (OpenBLAS, MKL) and the
OpenMP runtimes loaded in the process keep a thread per core. ``latticedft.limit_threads(n)`` bounds all of
them (through threadpoolctl): called, for the rest of the session; used in a ``with`` statement, for the
block only, after which the limits they had are put back. ``[run] threads`` of a case goes through it for
the whole run. Measured by ``python -m benchmarks.threads`` (docs/performance.md, *Threads under load*).
"""

from __future__ import annotations

from types import TracebackType
from typing import Any

from threadpoolctl import threadpool_limits

from ._errors import InputError

__all__ = ["limit_threads"]


class limit_threads:  # noqa: N801  (a function to its users, as set_options)
    """Bound torch's threads and every BLAS/OpenMP pool of the process to ``threads``.

    >>> import latticedft as ldft, torch
    >>> with ldft.limit_threads(1):
    ...     torch.get_num_threads()
    1
    """

    def __init__(self, threads: int) -> None:
        if not isinstance(threads, int) or isinstance(threads, bool) or threads < 1:
            raise InputError.at("threads", f"expected a positive integer, got {threads!r}")
        import torch

        self.threads = threads
        self._torch_before = torch.get_num_threads()
        torch.set_num_threads(threads)
        self._pools: Any = threadpool_limits(limits=threads)

    def __enter__(self) -> limit_threads:
        return self

    def __exit__(self, kind: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None) -> None:
        import torch

        self._pools.restore_original_limits()
        torch.set_num_threads(self._torch_before)
