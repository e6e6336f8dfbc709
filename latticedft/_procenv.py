"""The process group the environment describes, read without torch.

``torchrun`` and ``latticedft ... --workers N`` start each process with ``RANK``, ``WORLD_SIZE``,
``LOCAL_RANK`` and ``LOCAL_WORLD_SIZE`` set. The command line reads them before torch is imported (whether
this process is a helper rank), the pipeline before the processes join their group (which share of the data
each reads), and training when it joins. One reader, so that every part agrees on an absent or empty
variable (rank 0 of one process).
"""

from __future__ import annotations

import os

__all__ = ["env_rank", "env_world", "local_rank", "local_world"]


def _int(name: str, default: int) -> int:
    return int(os.environ.get(name, "") or default)


def env_rank() -> int:
    """``RANK``: this process's rank in the group the environment describes (0 without one)."""
    return _int("RANK", 0)


def env_world() -> int:
    """``WORLD_SIZE``: the number of processes the environment describes (1 without a group)."""
    return _int("WORLD_SIZE", 1)


def local_rank() -> int:
    """``LOCAL_RANK``: this process's rank on its machine (0 without one)."""
    return _int("LOCAL_RANK", 0)


def local_world() -> int:
    """``LOCAL_WORLD_SIZE``: the number of the group's processes on this machine (``WORLD_SIZE`` without it)."""
    return _int("LOCAL_WORLD_SIZE", env_world())
