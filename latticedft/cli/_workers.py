"""Training and serving in several processes: ``--workers N`` on this machine, or the processes ``torchrun``
starts.

``latticedft train/serve/run CASE --workers N`` starts N copies of the same command (ranks 0 .. N-1) that
form a ``torch.distributed`` process group (gloo on the loopback ``127.0.0.1``), and waits for them. Under
``torchrun`` the command is already one of the group's processes (``RANK``, ``WORLD_SIZE`` ... in the
environment). Either way every rank reads the case and trains on its share of the chunks
(:func:`latticedft.learn` combines the shares), then serves its slab of each task that can be split
(``latticedft._run._split``); rank 0 alone serves the other tasks and writes the results folder, the other
ranks write nothing.
"""

from __future__ import annotations

import argparse
import atexit
import contextlib
import logging
import os
import socket
import subprocess
import sys
import tempfile
import time
import warnings
from pathlib import Path
from typing import IO, TYPE_CHECKING, Any

from .._errors import InputError
from .._procenv import env_rank, env_world
from ._common import BAD_INPUT, OK

if TYPE_CHECKING:  # the CLI's help and usage errors load no engine (torch, xarray)
    from .._case import Case

log = logging.getLogger("latticedft")

__all__ = [
    "add_argument",
    "end_process",
    "supervise",
    "starts_group",
    "is_helper",
    "join",
    "leave",
    "record_processes",
    "serve_only",
    "serve_share",
    "train_only",
]


def add_argument(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--workers",
        type=int,
        default=1,
        metavar="N",
        help="train and serve in N local processes (torch.distributed over 127.0.0.1): training data-parallel, "
        "each task that can be split served in slabs of its outer spatial axis, the others by rank 0 alone; "
        "rank 0 writes the results. Under torchrun, leave it out: torchrun's processes are used",
    )


def _rank_env() -> tuple[int, int]:
    """(RANK, WORLD_SIZE) from the environment (torchrun's, or this launcher's)."""
    return env_rank(), env_world()


def is_helper() -> bool:
    """True in a rank other than 0 of a process group: it trains and writes nothing."""
    rank, size = _rank_env()
    return size > 1 and rank > 0


def _without_workers(argv: list[str]) -> list[str]:
    out, skip = [], False
    for a in argv:
        if skip:
            skip = False
        elif a == "--workers":
            skip = True
        elif not a.startswith("--workers="):
            out.append(a)
    return out


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def starts_group(args: argparse.Namespace) -> bool:
    """True when :func:`supervise` starts the processes (``--workers N > 1`` outside a process group)."""
    return int(getattr(args, "workers", 1)) > 1 and _rank_env()[1] == 1


def supervise(args: argparse.Namespace, argv: list[str]) -> int | None:
    """With ``--workers N > 1`` (and no process group in the environment): run the N ranks and return the
    exit status (rank 0's; 1 when another rank failed). ``None``: this process does the work itself."""
    n = getattr(args, "workers", 1)
    if n < 1:
        raise InputError(f"--workers: expected a positive integer, got {n}")
    if n == 1 or _rank_env()[1] > 1:
        return None
    port = _free_port()
    base = dict(os.environ, MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port), WORLD_SIZE=str(n))
    base.update(LOCAL_WORLD_SIZE=str(n), OMP_NUM_THREADS=os.environ.get("OMP_NUM_THREADS", "1"))
    cmd = [sys.executable, "-m", "latticedft", *_without_workers(argv)]
    procs: list[subprocess.Popen[bytes]] = []
    logs: list[IO[bytes] | None] = []
    errors = tempfile.TemporaryDirectory(prefix="latticedft-ranks-")
    try:
        for rank in range(n):
            env = dict(base, RANK=str(rank), LOCAL_RANK=str(rank))
            env[ERROR_FILE] = os.path.join(errors.name, f"rank{rank}")
            out = None if rank == 0 else tempfile.TemporaryFile()  # noqa: SIM115 - closed in the finally below
            logs.append(out)
            procs.append(subprocess.Popen(cmd, env=env, stdout=out, stderr=out))
        return _wait(procs, logs, errors.name)
    finally:
        for p in procs:
            if p.poll() is None:
                p.terminate()
        for p in procs:
            try:
                p.wait(timeout=10)
            except subprocess.TimeoutExpired:
                p.kill()
        for f in logs:
            if f is not None:
                f.close()
        errors.cleanup()


#: The environment variable naming the file where a rank that ``--workers`` started writes its one-line error.
ERROR_FILE = "LATTICEDFT_ERROR_FILE"
#: Seconds rank 0 is given to end by itself once another rank failed, before that rank's error is reported.
RANK0_GRACE_S = 10.0


def _said_by_rank0(procs: list[subprocess.Popen[bytes]], folder: str, failed: int) -> bool:
    """True when rank 0 failed too, within :data:`RANK0_GRACE_S`, with the error line rank ``failed`` wrote
    (every rank checks the same inputs: a bad file is then said once, by rank 0, as in one process)."""
    with contextlib.suppress(subprocess.TimeoutExpired):
        procs[0].wait(timeout=RANK0_GRACE_S)
    if procs[0].poll() in (None, 0):
        return False
    lines = []
    for rank in (0, failed):
        try:
            lines.append(Path(folder, f"rank{rank}").read_text().strip())
        except OSError:
            return False
    return lines[0] == lines[1] != ""


def _wait(procs: list[subprocess.Popen[bytes]], logs: list[Any], folder: str) -> int:
    """Wait for every rank; stop the others as soon as one fails. Rank 0's status, or 1 when another failed
    (its error said as ``worker N failed: ...``, unless rank 0 said the same error itself)."""
    while True:
        first = procs[0].poll()
        failed = next((i for i, p in enumerate(procs[1:], 1) if p.poll() not in (None, 0)), None)
        if first is not None and first != 0:
            return int(first)  # rank 0 reported its own error (or an incomplete serving task)
        if first is None and failed is None:
            time.sleep(0.05)
            continue
        if first is not None:  # rank 0 is done: the others finished training before it could
            for p in procs[1:]:
                with contextlib.suppress(subprocess.TimeoutExpired):
                    p.wait(timeout=60)
            failed = next((i for i, p in enumerate(procs[1:], 1) if p.poll() != 0), None)
            if failed is None:
                return int(first)
        assert failed is not None
        if first is None and _said_by_rank0(procs, folder, failed):
            return int(procs[0].poll() or BAD_INPUT)
        logs[failed].seek(0)
        tail = [ln for ln in logs[failed].read().decode(errors="replace").splitlines() if ln.strip()][-3:]
        msg = " | ".join(ln.strip() for ln in tail) or f"exit status {procs[failed].poll()}"
        print(f"latticedft: error: worker {failed} failed: {msg}", file=sys.stderr)
        return BAD_INPUT


#: True once this process joined a process group (it then ends with :func:`end_process`)
_joined = False


def join(device: str = "cpu", what: str = "training") -> None:
    """Join the process group described by the environment (a no-op in a single process); ``device`` is the
    training device (CUDA: NCCL, each rank on its own GPU)."""
    from .._device import DeviceWarning
    from .._learn import _dist

    with warnings.catch_warnings():  # the backend's choice only: run_device warns of a fallback, once
        warnings.simplefilter("ignore", DeviceWarning)
        joined = _dist.init_from_env(device=device)
    if joined:
        global _joined
        _joined = True
        rank, size = _dist.world()
        log.info("%s in %d processes (this is rank %d, backend %s)", what, size, rank, _dist_backend())
        atexit.register(_leave)


def record_processes(summary: dict[str, Any]) -> None:
    """``processes`` in ``summary.json``: the number of processes of the command (left out for one)."""
    if _rank_env()[1] > 1:
        summary["processes"] = _rank_env()[1]


def _dist_backend() -> str:
    import torch.distributed as dist

    return str(dist.get_backend())


def _leave() -> None:
    """Leave the process group without waiting for the others (the fallback at exit after an error)."""
    import torch.distributed as dist

    if dist.is_available() and dist.is_initialized():
        dist.destroy_process_group()


def leave() -> None:
    """After training, in every rank: wait for all, then leave the group together (a rank that leaves while
    another still holds its connections can make that one abort at exit)."""
    import torch.distributed as dist

    if dist.is_available() and dist.is_initialized():
        dist.barrier()
        dist.destroy_process_group()


def end_process(status: int) -> int:
    """The exit status of a command; a process that was in a process group ends here at once.

    Its work is written and its outcome said; what is left is the interpreter's own teardown, in which the
    gloo backend's threads can still abort the process ("terminate called without an active exception",
    SIGABRT) although its group was destroyed: a helper rank would then read as failed. So such a process
    flushes its output and logs and leaves with ``os._exit`` (the group is left first, if it was not)."""
    if not _joined:
        return status
    with contextlib.suppress(Exception):
        _leave()
    logging.shutdown()
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):
            stream.flush()
    os._exit(status)


def train_only(case: Case, serve: bool = True) -> int:
    """A helper rank's work in ``train`` and (``serve``) ``run``: read the case, take part in training, then
    serve its slab of each task that is split; write nothing."""
    from .._run import check_case, train_model
    from ._common import run_device, set_threads

    set_threads(case)
    case = run_device(case)
    data = check_case(case)
    join(case.run.device)
    model, _ = train_model(case, data)
    splits = _splits(data, model) if serve else False
    if splits is None:
        return OK  # rank 0 says why
    if splits:
        serve_share(model, data)
    leave()
    return OK


def _splits(data: Any, model: Any) -> bool | None:
    """Whether some task may be split; None when split serving is bad input (rank 0 says why in one line)."""
    from .._run._split import check_split

    try:
        return check_split(data.tasks, model)
    except InputError:
        return None


def serve_share(model: Any, data: Any, resume: bool = False) -> None:
    """A helper rank's part of serving: its slab of every task that is split (rank 0 serves the others; under
    ``resume`` it says which tasks were done before the run stopped)."""
    from .._run._split import serve_split

    for td in data.tasks:
        serve_split(model, td, td.init, resume=resume)


def serve_only(case: Case, dest: Any, resume: bool = False) -> int:
    """A helper rank's whole work in ``serve`` (and ``run --resume``): read the case and the model of the
    folder ``dest``, serve its slab of every task that is split (``resume``: of the run ``--resume``
    continues), write nothing."""
    from .._results import load_verified_model
    from .._run import check_case
    from ._common import set_threads

    set_threads(case)
    model = load_verified_model(dest)
    data = check_case(case)
    if not _splits(data, model):
        return OK  # no task is split (rank 0 serves them), or bad input (rank 0 says why)
    join("cpu", "serving")
    serve_share(model, data, resume)
    leave()
    return OK
