"""Suite-wide settings: double precision, fixed threads, seeded randomness."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import latticedft

torch.set_default_dtype(torch.float64)
torch.set_num_threads(1)


@pytest.fixture(autouse=True)
def _options():
    """Tuning knobs a test sets with ``latticedft.set_options(...)`` are put back after it."""
    saved = latticedft.get_options()
    yield
    latticedft.set_options(**saved)


@pytest.fixture(autouse=True)
def _seed():
    torch.manual_seed(0)
    np.random.seed(0)
    yield


#: A package that extends latticedft through entry points, put on sys.path by the tests that use it only.
collect_ignore = ["plugins"]
