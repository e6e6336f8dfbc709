"""Suite-wide settings: double precision, fixed threads, seeded randomness."""

from __future__ import annotations

import signal

import numpy as np
import pytest
import torch

import latticedft

torch.set_default_dtype(torch.float64)
torch.set_num_threads(1)

# A suite started as a background job of a shell script inherits SIGINT ignored, and so would every command the
# tests start: the tests that interrupt a command (tests/test_faults.py) would then see it finish instead. The
# suite's own commands get Ctrl-C's usual behaviour back (an exec resets a handled signal to its default).
if signal.getsignal(signal.SIGINT) == signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)


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
