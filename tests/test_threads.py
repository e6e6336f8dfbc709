"""The thread policy: ``latticedft.limit_threads`` bounds torch and the BLAS/OpenMP pools together, for good
or for a block; the command line applies ``[run] threads`` through it."""

from __future__ import annotations

import pytest
import torch
from threadpoolctl import threadpool_info

import latticedft as ldft


def _pools() -> list[int]:
    return [pool["num_threads"] for pool in threadpool_info()]


def test_block_bounds_torch_and_blas_and_puts_them_back():
    torch_before, pools_before = torch.get_num_threads(), _pools()
    with ldft.limit_threads(1) as limits:
        assert limits.threads == 1
        assert torch.get_num_threads() == 1
        assert pools_before and all(n == 1 for n in _pools())
    assert torch.get_num_threads() == torch_before and _pools() == pools_before


def test_call_holds_until_undone():
    torch_before, pools_before = torch.get_num_threads(), _pools()
    limits = ldft.limit_threads(1)
    try:
        assert torch.get_num_threads() == 1 and all(n == 1 for n in _pools())
    finally:
        limits.__exit__(None, None, None)
    assert torch.get_num_threads() == torch_before and _pools() == pools_before


@pytest.mark.parametrize("bad", [0, -1, 1.5, True, "2"])
def test_bad_thread_count_is_refused(bad):
    with pytest.raises(ldft.InputError, match="threads: expected a positive integer"):
        ldft.limit_threads(bad)


def test_run_threads_of_a_case_bound_every_pool():
    from types import SimpleNamespace

    from latticedft.cli import _common

    torch_before, pools_before = torch.get_num_threads(), _pools()
    with ldft.limit_threads(2):  # puts back what was there before, after the command line's limit for good
        _common.set_threads(SimpleNamespace(run=SimpleNamespace(threads=1)))  # type: ignore[arg-type]
        assert torch.get_num_threads() == 1 and all(n == 1 for n in _pools())
    assert torch.get_num_threads() == torch_before and _pools() == pools_before
