"""Selection with sparse candidates: tried first, a hand-set model beaten 100x is not kept, ``progress`` passes."""

from __future__ import annotations

import math

from test_sparse import pendulum

import latticedft as ldft
from latticedft._select import BEATEN, _choose, auto_candidates, sparse_candidates


def _rows(*scores: float) -> list[dict]:
    return [{"score": s, "n_parameters": 10 - i, "label": f"c{i}"} for i, s in enumerate(scores)]


def test_a_hand_set_model_beaten_100x_is_not_kept_below_keep_below():
    chosen, reason, _ = _choose(_rows(1e-7, 1e-7 / (2 * BEATEN)), factor=2.0, keep_below=1e-6)
    assert chosen == 1 and "c1 scored" in reason
    chosen, reason, _ = _choose(_rows(1e-7, 1e-8), factor=2.0, keep_below=1e-6)  # only 10x: kept
    assert chosen == 0 and "keep_below" in reason
    assert _choose(_rows(1e-3, math.inf), factor=2.0, keep_below=1e-6)[0] == 0


def test_auto_tries_the_sparse_libraries_first():
    cands = auto_candidates(ldft.PolynomialLagrangian((4, 8)), n=2, m=1)
    assert cands[: len(sparse_candidates(2, 1))] == sparse_candidates(2, 1)
    assert all(c["kind"] == "sparse" for c in sparse_candidates(1, 2))
    assert {c["threshold"] for c in ldft.SparseLagrangian().auto_candidates(1)} >= {0.1, 0.0}


def test_select_takes_progress_and_chooses_the_sparse_pendulum():
    data = [pendulum(2.0, 40), pendulum(2.6, 40)]
    cands = sparse_candidates(1, 1)[:1]
    sel = ldft.select(ldft.PolynomialLagrangian((2, 2)), data, cands, progress=False)
    assert sel.chosen == 1 and isinstance(sel.model, ldft.SparseLagrangian)
    assert set(sel.model.report_.sparse["kept"]) == {"Dtq**2", "cos(q)"}
