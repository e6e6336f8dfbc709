"""Training in several processes reads each process's share of the data only, the input scaling included.

Two processes on the loopback (gloo) learn a polynomial and an MLP from fields read chunk by chunk: the
pieces each reads are disjoint and together those one process reads; the scaling and the training range
(minima and maxima, merged over the processes) equal the one-process ones bit for bit, and the model equals
it to round-off. A case (``check_case``, ``train_model``) of four tiny noisy training files, told apart by
their number of time slices, learned with ``[train] noise = "correct"``: each rank holds in memory the files
``i mod 2`` (the others left in their files), reads and corrects only those, and the model equals the one
process's to round-off; so does a sparse model, which fits every corrected field at once (each process
gets the others' corrections from them).
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
out["noise"] = [report.noise["sigma"], report.noise["relative"], report.noise["method"], list(estimated)]

from latticedft._case import load_case
from latticedft._layout import is_lazy
from latticedft._run import check_case, train_model
case = load_case(CASE)
data = check_case(case)
held = sorted(int(da.sizes["t"]) for da in data.train if not is_lazy(da))
read, corrected = set(), []
_read2, _one = Piece.read, _noise._correct_one
_noise.ROUNDS = 1  # one correction and its refit
def counted2(self, sources, *args):
    read.add(sources[self.source].nt)
    return _read2(self, sources, *args)
def spied2(model, f, *args):
    corrected.append(f.shape[0])
    return _one(model, f, *args)
Piece.read, _noise._correct_one = counted2, spied2
model, report = train_model(case, data)
out["case"] = dict(held=held, read=sorted(read), corrected=sorted(set(corrected)), coef=model.coef.tolist(),
                   shift=report.noise["shift"], sigma=report.noise["sigma"])
m = ldft.SparseLagrangian("kinetic + poly:2", threshold=0.0, bags=0)  # fits every field at once: they are
ldft.learn(m, noisy, noise="correct")  # gathered from the processes that corrected them
out["sparse"] = m.coef.tolist()
with open(sys.argv[1], "w") as f:
    json.dump(out, f)
"""
    + GROUP_END
)


_CASE = """
[model]
kind = "polynomial"
orders = [2, 2]

[train]
data = ["data/train_*.nc"]
noise = "correct"
calibrate = false
"""


def _write_case(root: Path) -> None:
    import latticedft.io
    from latticedft import systems

    (root / "data").mkdir(parents=True)
    (root / "case.toml").write_text(_CASE)
    rng = np.random.default_rng(0)
    for k, nt in enumerate((20, 21, 22, 23)):
        f = systems.wave_string([(1, 0.5), (k + 2, 0.1)], nx=8, nt=nt)
        noisy = f + 1e-4 * rng.standard_normal(f.shape)
        latticedft.io.write_field(root / "data" / f"train_{k}.nc", {"psi": noisy})


def _rel(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.max(np.abs(a - b)) / max(np.max(np.abs(b)), 1e-300))


@pytest.mark.slow
def test_each_process_reads_its_share_and_learns_what_one_learns(tmp_path: Path) -> None:
    _write_case(tmp_path / "case")
    ref, ranks = alone_and_in_two(tmp_path, _WORKER.replace("CASE", repr(str(tmp_path / "case")), 1))
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
    # the case: each rank holds, reads and corrects the training files i mod 2 only
    one, two = ref["case"], [r["case"] for r in ranks]
    assert one["held"] == one["read"] == one["corrected"] == [20, 21, 22, 23]
    assert [r["held"] for r in two] == [[20, 22], [21, 23]]
    assert all(r["read"] == r["corrected"] == r["held"] for r in two)
    assert two[0]["coef"] == two[1]["coef"] and two[0]["shift"] == two[1]["shift"]
    assert _rel(np.array(two[0]["coef"]), np.array(one["coef"])) < 1e-10
    assert two[0]["shift"] == pytest.approx(one["shift"], rel=1e-12)
    assert two[0]["sigma"] == pytest.approx(one["sigma"], rel=1e-12)
    assert ranks[0]["sparse"] == ranks[1]["sparse"]
    assert _rel(np.array(ranks[0]["sparse"]), np.array(ref["sparse"])) < 1e-10
