"""Small fields and theories shared by the core tests."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
from pathlib import Path

import numpy as np
import torch
import xarray as xr

import latticedft as ldft
from latticedft import lagrangians, systems


def series(values, dt: float, name: str = "psi", components=None) -> xr.DataArray:
    values = np.asarray(values, dtype=float)
    t = np.arange(values.shape[0]) * dt
    if components is None:
        return xr.DataArray(values, dims="t", coords={"t": t}, name=name)
    return xr.DataArray(values, dims=("t", "component"), coords={"t": t, "component": list(components)}, name=name)


def sine_gordon(closed: bool = True):
    """The sine-Gordon ``L_d`` on the first-order stencil (any dimension); with its ``closed`` form (sympy: the
    compiled kernels and the generated derivatives take it) or without (autograd serves it everywhere)."""
    import sympy

    def fn(c: torch.Tensor, h: tuple[float, ...]) -> torch.Tensor:
        u = c[..., 0, 0]
        out = 0.5 * ((c[..., 1, 0] - u) / h[0]) ** 2 - (1 - torch.cos(u))
        for k in range(1, len(h)):
            out = out - 0.5 * ((c[..., k + 1, 0] - u) / h[k]) ** 2
        return out

    def closed_form(c: np.ndarray, h: tuple[float, ...]) -> object:
        u = c[0, 0]
        out = 0.5 * ((c[1, 0] - u) / h[0]) ** 2 - (1 - sympy.cos(u))
        for k in range(1, len(h)):
            out = out - 0.5 * ((c[k + 1, 0] - u) / h[k]) ** 2
        return out

    return ldft.AnalyticLagrangian(fn, name="sine-Gordon", closed_form=closed_form if closed else None)


def smooth_start(ndim: int, n: int, periodic: bool = True) -> xr.DataArray:
    """Two slices at rest of a smooth field on ``n^ndim`` sites (spacing 0.1, dt 0.04), periodic or with
    fixed ends (no periodic attribute)."""
    x = np.arange(n) / n
    u = np.ones([n] * ndim)
    for k in range(ndim):
        shape = [1] * ndim
        shape[k] = n
        u = u * np.sin(2 * np.pi * x + k).reshape(shape)
    dims = ("t", *"zyx"[3 - ndim :])
    attrs = {d: {"periodic": "true", "period": n * 0.1} for d in dims[1:]} if periodic else None
    return systems.make_field(np.stack([0.8 * u, 0.8 * u]), dims, spacing=(0.04, *[0.1] * ndim), coord_attrs=attrs)


def quartic(q: torch.Tensor) -> torch.Tensor:
    """An anharmonic potential ``V = q^2/2 + q^4/4``."""
    return 0.5 * q**2 + 0.25 * q**4


def oscillator_data(amplitudes=(0.4, 0.8, 1.2), dt: float = 0.1, steps: int = 120):
    """Trajectories served from the Störmer–Verlet ``L_d`` of the quartic oscillator (zero initial velocity)."""
    truth = lagrangians.verlet(quartic)
    out = []
    for a in amplitudes:
        q1 = a - 0.5 * dt**2 * (a + a**3)  # a Taylor step; any second slice defines a discrete solution
        out.append(ldft.serve(truth, series([a, q1], dt), slices=steps).field)
    return truth, out


def wave_field(nx: int = 33, nt: int = 40, modes=((1, 1.0), (3, 0.3)), courant: float = 0.5):
    dx = 1.0 / (nx - 1)
    return systems.wave_string(list(modes), nx=nx, nt=nt, dt=courant * dx)


def membrane_field(n: int = 12, nt: int = 16):
    return systems.wave_membrane([(1, 1, 1.0), (2, 1, 0.4)], nx=n, ny=n + 2, nt=nt)


def leapfrog_of(field: xr.DataArray, c: float = 1.0, boundary: str = "dirichlet") -> np.ndarray:
    """The explicit leapfrog of ``psi_tt = c^2 Laplacian psi`` from the first two slices (and strips) of ``field``."""
    v = field.values
    spacing = tuple(float(field[d][1] - field[d][0]) for d in field.dims[1:])
    dt = float(field[field.dims[0]][1] - field[field.dims[0]][0])
    kw = {"boundary_values": v} if boundary == "dirichlet" else {}
    return np.asarray(systems.leapfrog(v[0], v[1], v.shape[0] - 1, dt, spacing, c=c, boundary=boundary, **kw))


def on_a_terminal(argv: list[str], env: dict[str, str], columns: int = 100) -> tuple[int, str]:
    """Run ``argv`` with its stderr on a pseudo-terminal ``columns`` wide (a new one is 0 wide: progress bars
    would draw nothing); its exit status and what it wrote there. Unix only."""
    import fcntl
    import os
    import struct
    import subprocess
    import termios

    master, slave = os.openpty()
    fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", 24, columns, 0, 0))
    proc = subprocess.Popen(argv, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=slave, env=env)
    os.close(slave)
    chunks = []
    while True:
        try:
            data = os.read(master, 4096)
        except OSError:  # the child closed the terminal
            break
        if not data:
            break
        chunks.append(data)
    proc.wait(timeout=300)
    os.close(master)
    return proc.returncode, b"".join(chunks).decode()


def free_port() -> int:
    """A TCP port free on the loopback now (for a process group's rendezvous)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


#: The end of a process-group worker script (which imports os, sys and torch.distributed as dist): wait for all,
#: leave the group, and end without the interpreter's teardown, as the command line does
#: (``latticedft.cli._workers.end_process``: gloo's threads can abort a process there after its work is done).
GROUP_END = """
if dist.is_initialized():
    dist.barrier()
    dist.destroy_process_group()
    sys.stdout.flush(); sys.stderr.flush()
    os._exit(0)
"""

#: The end of a worker script run by :func:`two_ranks`: its results ``out`` written as JSON to its first
#: argument plus ``.<rank>``, then :data:`GROUP_END`.
RANK_RESULTS_END = (
    """
with open(sys.argv[1] + f".{rank}", "w") as f:
    json.dump(out, f)
"""
    + GROUP_END
)

RANK_VARIABLES = ("RANK", "WORLD_SIZE", "LOCAL_RANK", "LOCAL_WORLD_SIZE", "MASTER_ADDR", "MASTER_PORT")
REPO = Path(__file__).resolve().parents[1]


def group_env(repo=REPO) -> dict[str, str]:
    """This environment for a worker: one thread, the repository importable, no process group of its own."""
    env = dict(os.environ, OMP_NUM_THREADS="1", PYTHONPATH=str(repo))
    for k in RANK_VARIABLES:
        env.pop(k, None)
    return env


def start_group(argv, n: int, env: dict[str, str], timeout: float = 600.0) -> list[tuple[int, str, str]]:
    """Run ``argv(rank)`` as the ``n`` ranks of a process group on the loopback (``RANK``, ``LOCAL_RANK``,
    ``WORLD_SIZE``, ``MASTER_ADDR`` and ``MASTER_PORT``, a free port, added to ``env``); each rank's ``(exit
    status, stdout, stderr)``. Ranks still running after ``timeout`` seconds (a guard against a hang, not a
    measurement) are killed and the test fails with their output."""
    import pytest

    base = dict(env, MASTER_ADDR="127.0.0.1", MASTER_PORT=str(free_port()), WORLD_SIZE=str(n))
    procs = [
        subprocess.Popen(
            argv(r),
            env=dict(base, RANK=str(r), LOCAL_RANK=str(r)),
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        for r in range(n)
    ]
    try:
        outs = [p.communicate(timeout=timeout) for p in procs]
    except subprocess.TimeoutExpired:
        for p in procs:
            p.kill()
        tails = [f"rank {r}: {p.communicate()[1][-2000:]}" for r, p in enumerate(procs)]
        pytest.fail(f"the group of {n} did not finish in {timeout} s\n" + "\n".join(tails))
    return [(p.returncode, out, err) for p, (out, err) in zip(procs, outs)]


def run_ranks(script, n: int, *args: str, timeout: float = 600.0, env=None) -> list[tuple[int, str, str]]:
    """The Python file ``script`` (``args`` after it) as the ``n`` ranks of a group (:func:`start_group`), in
    :func:`group_env` with ``env`` added; each rank's ``(exit status, stdout, stderr)``."""
    return start_group(lambda r: [sys.executable, str(script), *args], n, dict(group_env(), **(env or {})), timeout)


def run_group(argv, n: int, env: dict[str, str], timeout: float = 600.0) -> list[str]:
    """:func:`start_group`, asserting that every rank exits 0 (the ranks' stderr in the message); their stderr."""
    ranks = start_group(argv, n, env, timeout)
    assert [rc for rc, _, _ in ranks] == [0] * n, "\n".join(err[-3000:] for _, _, err in ranks)
    return [err for _, _, err in ranks]


def two_ranks(tmp_path, worker: str) -> list[dict]:
    """The worker script ``worker`` (writing JSON to its first argument plus ``.<rank>``) run as the two ranks
    of a group, asserting that both exit 0 (their stderr in the message): each rank's JSON."""
    import json

    script = tmp_path / "worker.py"
    script.write_text(worker)
    ranks = run_ranks(script, 2, str(tmp_path / "out"))
    assert [rc for rc, _, _ in ranks] == [0, 0], "\n".join(err[-3000:] for _, _, err in ranks)
    return [json.loads((tmp_path / f"out.{r}").read_text()) for r in range(2)]


def alone_and_in_two(tmp_path, worker: str) -> tuple[dict, list[dict]]:
    """The worker script ``worker`` (writing JSON to its first argument) run in one process, then as the two
    ranks of a group: the one process's JSON and each rank's."""
    import json

    script = tmp_path / "worker.py"
    script.write_text(worker)
    env = group_env()
    one = subprocess.run([sys.executable, str(script), str(tmp_path / "one.json")], env=env, timeout=600)
    assert one.returncode == 0
    run_group(lambda r: [sys.executable, str(script), str(tmp_path / f"two_{r}.json")], 2, env)
    ranks = [json.loads((tmp_path / f"two_{r}.json").read_text()) for r in range(2)]
    return json.loads((tmp_path / "one.json").read_text()), ranks
