"""Training in several processes reads each process's share of the data only, the input scaling included.

Two processes on the loopback (gloo) learn a polynomial and an MLP from fields read chunk by chunk: the
pieces each reads are disjoint and together those one process reads; the scaling and the training range
(minima and maxima, merged over the processes) equal the one-process ones bit for bit, and the model equals
it to round-off.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from helpers import GROUP_END, alone_and_in_two

_WORKER = (
    """
import os, sys, json, torch
torch.set_num_threads(1)
import torch.distributed as dist
import latticedft as ldft
from latticedft import systems
from latticedft._learn import _dist
from latticedft._learn._source import Piece
_dist.init_from_env()
seen = []
_read = Piece.read
def counted(self, *args):
    seen.append([self.source, self.t0, self.t1])
    return _read(self, *args)
Piece.read = counted
fields = [systems.wave_string([(k, 0.5 / k), (k + 1, 0.1, 0.3 * k)], nx=24, nt=40) for k in range(1, 5)]
out = {}
m = ldft.PolynomialLagrangian((2, 4))
ldft.learn(m, fields, chunk_sites=200, ridge=0.0)
out["poly"] = [m.coef.tolist(), m.center.tolist(), m.halfwidth.tolist(), m.trained_range().tolist()]
out["poly_read"] = sorted(seen)
seen.clear()
data = systems.klein_gordon_training_set(n=4, steps=10, seed=0)
m = ldft.MLPLagrangian(hidden=[6], activation="tanh", form="free", seed=0)
ldft.learn(m, data, optimizer="lbfgs", max_iter=4, chunk_sites=150, boundary="periodic")
params = torch.cat([p.detach().reshape(-1) for p in m.parameters()]).tolist()
out["mlp"] = [params, m.in_center.tolist(), m.in_scale.tolist(), float(m.out_scale), m.trained_range().tolist()]
out["mlp_read"] = sorted(set(map(tuple, seen)))
from latticedft._learn import _noise
estimated, _estimate = [], _noise._estimate
def spied(fields, nt, pooled=False):
    estimated.append(len(fields))
    return _estimate(fields, nt, pooled)
_noise._estimate = spied
_noise.ROUNDS = 0  # the estimate only: no correction rounds
noisy = [f + 2e-4 * torch.randn(f.shape, generator=torch.Generator().manual_seed(k)).numpy()
         for k, f in enumerate(systems.wave_string([(1, 0.5), (2, 0.1)], nx=24, nt=60) for _ in range(3))]
m = ldft.PolynomialLagrangian((2, 2))
report = ldft.learn(m, noisy, noise="auto")
out["noise"] = [report.noise["sigma"], report.noise["relative"], report.noise["method"], estimated]
with open(sys.argv[1], "w") as f:
    json.dump(out, f)
"""
    + GROUP_END
)


def _rel(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.max(np.abs(a - b)) / max(np.max(np.abs(b)), 1e-300))


@pytest.mark.slow
def test_each_process_reads_its_share_and_learns_what_one_learns(tmp_path: Path) -> None:
    ref, ranks = alone_and_in_two(tmp_path, _WORKER)
    for kind in ("poly", "mlp"):
        reads = [{tuple(p) for p in r[f"{kind}_read"]} for r in ranks]
        assert reads[0] and reads[1] and not reads[0] & reads[1]  # each its share, no piece read twice
        assert reads[0] | reads[1] == {tuple(p) for p in ref[f"{kind}_read"]}
        assert ranks[0][kind] == ranks[1][kind]  # every process ends with the same model, bit for bit
    coef, *scaling = ranks[0]["poly"]
    assert scaling == ref["poly"][1:]  # minima and maxima: merged exactly
    assert _rel(np.array(coef), np.array(ref["poly"][0])) < 1e-10
    params, *scaling = ranks[0]["mlp"]
    assert scaling == ref["mlp"][1:]
    assert _rel(np.array(params), np.array(ref["mlp"][0])) < 1e-8
    # the noise estimate: each process its share of the three fields, the sums reduced over the processes
    assert ref["noise"][3] == [3] and [r["noise"][3] for r in ranks] == [[2], [1]]
    assert ranks[0]["noise"][:3] == ranks[1]["noise"][:3] and ref["noise"][0] > 0
    assert _rel(np.array(ranks[0]["noise"][:2]), np.array(ref["noise"][:2])) < 1e-12
    assert ranks[0]["noise"][2] == ref["noise"][2]
