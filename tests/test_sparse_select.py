"""Selection with sparse candidates: tried first, a hand-set model beaten 100x is not kept, ``progress`` passes."""

from __future__ import annotations

import math

import numpy as np
import pytest
import xarray as xr
from test_sparse import _ode, kepler_one_orbit, pendulum

import latticedft as ldft
from latticedft._learn._noise import SPREAD_WARN
from latticedft._select import (
    BEATEN,
    BEYOND_CEILING,
    COUPLED_LIBRARY,
    EXACT_STEP_THRESHOLD,
    SQUARE_TRIG_LIBRARY,
    _choose,
    auto_candidates,
    exact_step_candidates,
    is_exact_step,
    largest_field,
    sparse_candidates,
)


def _rows(*scores: float) -> list[dict]:
    return [{"score": s, "n_parameters": 10 - i, "label": f"c{i}"} for i, s in enumerate(scores)]


def test_a_hand_set_model_beaten_100x_is_not_kept_below_keep_below():
    chosen, reason, _ = _choose(_rows(1e-7, 1e-7 / (2 * BEATEN)), factor=2.0, keep_below=1e-6)
    assert chosen == 1 and "c1 scored" in reason
    chosen, reason, _ = _choose(_rows(1e-7, 1e-8), factor=2.0, keep_below=1e-6)  # only 10x: kept
    assert chosen == 0 and "keep_below" in reason
    assert _choose(_rows(1e-3, math.inf), factor=2.0, keep_below=1e-6)[0] == 0


def test_a_sparse_candidate_near_the_lowest_score_comes_first():
    rows = [
        {"score": math.inf, "n_parameters": 45, "label": "hand-set", "kind": "polynomial"},
        {"score": 8e-7, "n_parameters": 36, "label": "orders", "kind": "polynomial"},
        {"score": 2e-5, "n_parameters": 7, "label": "sparse", "kind": "sparse"},
        {"score": 2e-2, "n_parameters": 2, "label": "sparser", "kind": "sparse"},
    ]
    assert _choose(rows, factor=2.0, keep_below=1e-6)[0] == 2
    rows[2]["score"] = 1e-2  # beyond SPARSE_FACTOR and SPARSE_FLOOR: the dense one
    assert _choose(rows, factor=2.0, keep_below=1e-6)[0] == 1
    rows[3]["score"] = 1.6e-3  # below SPARSE_FLOOR (Kepler from one orbit: the true two terms)
    assert _choose(rows, factor=2.0, keep_below=1e-6)[0] == 3
    rows[1]["score"], rows[2]["score"], rows[3]["score"] = 1.5e-2, 0.6, math.inf  # above SPARSE_CEILING
    assert _choose(rows, factor=2.0, keep_below=1e-6)[0] == 1
    rows[2]["score"] = 3.0e-2  # the double pendulum's true terms by the trapezoid rule: within the ceiling
    assert _choose(rows, factor=2.0, keep_below=1e-6)[0] == 2


def test_under_noise_the_sparse_candidates_whose_coefficients_hold_over_the_bags_come_first():
    """Sine-Gordon 1+1D with noise 1e-3: the threshold 0.1 keeps the wrong six terms, which vary over the bags
    (spread 1.1) and score lower than the true six (spread 5e-4); the stable one is chosen. Without a spread (clean
    data) or with every candidate unstable, the rule is as before."""
    rows = [
        {"score": 8e-3, "n_parameters": 40, "label": "hand-set", "kind": "polynomial"},
        {"score": 1e-3, "n_parameters": 6, "label": "wrong", "kind": "sparse", "spread": 1.1},
        {"score": 3e-3, "n_parameters": 6, "label": "true", "kind": "sparse", "spread": 5e-4},
    ]
    assert _choose(rows, factor=2.0, keep_below=1e-6)[0] == 2
    rows[2]["spread"] = 0.5  # both unstable: the lower score
    assert _choose(rows, factor=2.0, keep_below=1e-6)[0] == 1
    for row in rows:
        row.pop("spread", None)
    assert _choose(rows, factor=2.0, keep_below=1e-6)[0] == 1
    rows[1]["spread"], rows[2]["spread"] = 1.1, SPREAD_WARN  # at the bound: stable
    assert _choose(rows, factor=2.0, keep_below=1e-6)[0] == 2


def test_a_sparse_preference_never_keeps_a_hand_set_model_beaten_100x():
    rows = [  # the pendulum at 2.9 rad: the hand-set polynomial below keep_below, trig features 260x better
        {"score": 7.0e-8, "n_parameters": 45, "label": "hand-set", "kind": "polynomial"},
        {"score": 1.95e-3, "n_parameters": 3, "label": "sparse", "kind": "sparse"},
        {"score": 2.7e-10, "n_parameters": 134, "label": "trig", "kind": "features"},
    ]
    chosen, reason, _ = _choose(rows, factor=2.0, keep_below=1e-6)
    assert chosen == 2 and "100x below the hand-set" in reason
    rows[2]["score"] = 7.0e-9  # only 10x better: the hand-set model is kept
    assert _choose(rows, factor=2.0, keep_below=1e-6)[0] == 0


def test_below_keep_below_a_sparse_candidate_is_kept_over_a_dense_hand_set_model():
    rows = [  # paper Example 1: the hand-set polynomial and the sparse terms both below keep_below
        {"score": 2.6e-9, "n_parameters": 45, "label": "hand-set", "kind": "polynomial"},
        {"score": 9.0e-10, "n_parameters": 130, "label": "features", "kind": "features"},
        {"score": 4.0e-9, "n_parameters": 3, "label": "sparse", "kind": "sparse"},
        {"score": 3.0e-4, "n_parameters": 2, "label": "sparser", "kind": "sparse"},
    ]
    chosen, reason, _ = _choose(rows, factor=2.0, keep_below=1e-6)
    assert chosen == 2 and "do not rank models" in reason
    rows[2]["score"] = 2e-6  # above keep_below: the hand-set model is kept
    assert _choose(rows, factor=2.0, keep_below=1e-6)[0] == 0
    rows[2]["score"], rows[0]["kind"] = 4.0e-9, "sparse"  # a sparse hand-set model is kept
    assert _choose(rows, factor=2.0, keep_below=1e-6)[0] == 0


def test_a_preferred_sparse_candidate_replaces_a_dense_hand_set_model_it_does_not_beat_2x():
    rows = [  # sine-Gordon 1+1D: the default polynomial a little lower than the three true terms
        {"score": 8.6e-5, "n_parameters": 135, "label": "hand-set", "kind": "polynomial"},
        {"score": 1.1e-4, "n_parameters": 3, "label": "sparse", "kind": "sparse"},
        {"score": 4.3e-5, "n_parameters": 54, "label": "orders", "kind": "polynomial"},
    ]
    assert _choose(rows, factor=2.0, keep_below=1e-6)[0] == 1
    rows[0]["kind"] = "sparse"  # a sparse hand-set model stays unless beaten 2x
    assert _choose(rows, factor=2.0, keep_below=1e-6)[0] == 0
    rows[0].update(kind="polynomial", score=5e-7)  # below keep_below: kept
    assert _choose(rows, factor=2.0, keep_below=1e-6)[0] == 0


def test_auto_tries_the_sparse_libraries_first():
    cands = auto_candidates(ldft.PolynomialLagrangian((4, 8)), n=2, m=1)
    assert cands[: len(sparse_candidates(2, 1))] == sparse_candidates(2, 1)
    assert all(c["kind"] == "sparse" for c in sparse_candidates(1, 2))
    # data through q = 0 (a charged particle) refuse |q|^-1 and log|q|: a library without them is tried too
    assert sparse_candidates(1, 2)[-4]["library"] == "kinetic + poly:2 + cross"
    # coupled degrees of freedom of unequal masses, at both ends of the step; not on a lattice with space axes
    assert sparse_candidates(1, 2)[-3:] == [
        {"kind": "sparse", "library": COUPLED_LIBRARY, "at": "average", "threshold": t} for t in (0.1, 0.01, "auto")
    ]
    assert all(c.get("at") is None for c in sparse_candidates(2, 2) + sparse_candidates(2, 1))
    assert any(c.get("at") == "average" for c in sparse_candidates(1, 1))
    assert {c["threshold"] for c in ldft.SparseLagrangian().auto_candidates(1)} >= {0.1, 0.0}


def test_the_coupled_pendulums_exact_step_is_a_candidate_on_a_time_only_lattice_of_two_components_only():
    """``coupledstep`` (28 distinct terms with closed forms) on top of the coupled library, in the trapezoid rule at the
    exact-step threshold: an exact-step candidate of two components, not of three nor on a field lattice."""
    from latticedft._models._library import Library

    coupled = {"kind": "sparse", "library": f"{COUPLED_LIBRARY} + coupledstep", "at": "average"}
    coupled["threshold"] = EXACT_STEP_THRESHOLD
    assert coupled in exact_step_candidates(1, 2) and coupled in sparse_candidates(1, 2)
    assert is_exact_step({"kind": "sparse", "options": {**coupled, "bags": 20}})
    assert not any("coupledstep" in c["library"] for n, m in ((1, 3), (2, 2), (1, 1)) for c in sparse_candidates(n, m))
    terms = Library.parse("coupledstep").expand(1, 2)
    assert len(terms) == 28 and len({t.name for t in terms}) == 28 and all(t.form for t in terms)


def test_the_trig_of_q_squared_is_a_candidate_on_a_time_only_scalar_lattice_only():
    square = {"kind": "sparse", "library": SQUARE_TRIG_LIBRARY, "threshold": "auto"}
    assert square in sparse_candidates(1, 1)
    assert not any(c["library"] == SQUARE_TRIG_LIBRARY for n, m in ((2, 1), (1, 2)) for c in sparse_candidates(n, m))


def test_select_finds_the_double_well_of_paper_example_2_by_the_trig_of_q_squared():
    """``L = q'^2/2 + 0.015 (cos(q^2 - 1) + 0.2 q)``, dt = 1, from 1.7: the polynomial with time symmetry scores
    lowest, and among the sparse candidates near it the four terms of ``kinetic + poly:4 + trig:1@2`` are preferred
    to the seven wrong ones of the corrections library, which score lower."""
    q = _ode(lambda y: [y[1], 0.015 * (0.2 - 2 * y[0] * np.sin(y[0] ** 2 - 1))], [1.7, 0.0], 51, 1.0)[0]
    data = xr.DataArray(q, dims="t", coords={"t": np.arange(51.0)}, name="q")
    corrections = next(c for c in sparse_candidates(1, 1) if "kinetic*kinetic" in c["library"] and "at" not in c)
    square = {"kind": "sparse", "library": SQUARE_TRIG_LIBRARY, "threshold": "auto"}
    cands = [corrections, square, {"time_symmetric": True}]
    sel = ldft.select(ldft.PolynomialLagrangian((4, 8)), data, cands, progress=False)
    assert sel.rows[3]["score"] < sel.rows[1]["score"] < sel.rows[2]["score"] and len(sel.rows[1]["terms"]) > 4
    assert sel.chosen == 2 and sel.rows[2]["terms"] == ["Dtq**2", "q", "sin(q**2)", "cos(q**2)"]


def test_select_takes_progress_and_chooses_the_sparse_pendulum():
    data = [pendulum(2.0, 40), pendulum(2.6, 40)]
    cands = sparse_candidates(1, 1)[:1]
    sel = ldft.select(ldft.PolynomialLagrangian((2, 2)), data, cands, progress=False)
    assert sel.chosen == 1 and isinstance(sel.model, ldft.SparseLagrangian)
    assert set(sel.model.report_.sparse["kept"]) == {"Dtq**2", "cos(q)"}


def test_a_sparse_case_prints_its_equation(tmp_path, capsys):
    import json

    import xarray as xr

    import latticedft.cli

    (tmp_path / "data").mkdir()
    for a in (2.0, 2.6):
        pendulum(a, 40).to_netcdf(tmp_path / "data" / f"train_{a}.nc")
    pendulum(2.9, 20).to_netcdf(tmp_path / "data" / "test.nc")
    (tmp_path / "case.toml").write_text(
        '[field]\nvariable = "psi"\n\n[model]\nkind = "sparse"\nlibrary = "kinetic + poly:2 + trig:1"\nbags = 4\n\n'
        '[train]\ndata = ["data/train_*.nc"]\n\n[[serve]]\nname = "test"\nfrom = "data/test.nc"\n'
    )
    assert latticedft.cli.main(["run", str(tmp_path), "-q"]) == 0
    record = json.loads((tmp_path / "results" / "model.json").read_text())
    assert record["training"]["sparse"]["kept"] == ["Dtq**2", "cos(q)"]
    assert "cos" in record["training"]["sparse"]["equation"]["latex"]
    with xr.open_dataset(tmp_path / "results" / "test.nc") as ds:
        assert ds.attrs["latticedft_L_d"].startswith("L_d = ") and "*cos(q)" in ds.attrs["latticedft_L_d"]
    capsys.readouterr()
    assert latticedft.cli.main(["info", str(tmp_path)]) == 0
    assert "DEL: " in capsys.readouterr().out


@pytest.mark.parametrize(
    ("vector", "library", "words"),
    [
        (False, "kinetic + norm:-1", "'norm:-1' needs a vector field"),
        (False, "kinetic + cross", "'cross' needs a field of 2 components"),
        (False, "kinetic + coupledstep", "'coupledstep' needs a field of 2 components"),
        (False, "kinetic + gradient", "'gradient' needs a space axis"),
        (True, "kinetic + gradient + norm:-1", "'gradient' needs a space axis"),
    ],
)
def test_check_refuses_a_library_that_does_not_fit_the_lattice(tmp_path, capsys, vector, library, words):
    import latticedft.cli

    (tmp_path / "data").mkdir()
    field = kepler_one_orbit(n=12) if vector else pendulum(2.0, 12)
    field.to_netcdf(tmp_path / "data" / "train.nc")
    name = "q" if vector else "psi"
    (tmp_path / "case.toml").write_text(
        f'[field]\nvariable = "{name}"\n\n[model]\nkind = "sparse"\nlibrary = "{library}"\n\n'
        '[train]\ndata = ["data/train.nc"]\n\n[[serve]]\nname = "train"\nfrom = "data/train.nc"\n'
    )
    capsys.readouterr()
    assert latticedft.cli.main(["check", str(tmp_path)]) != 0
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "model.library: " in err and words in err
    assert not (tmp_path / "results").exists()


def test_backward_elimination_finds_an_exact_support_among_collinear_terms():
    import numpy as np

    from latticedft._learn._sparse import backward

    rng = np.random.default_rng(0)
    a, b = rng.normal(size=(2, 40))
    t = np.stack([a, b, a + 2 * b + 1e-3 * rng.normal(size=40), rng.normal(size=40)], axis=1)
    t[:, 1] = a / 2  # the exact support {0, 1}: a - 2 (a / 2) = 0
    gauge = (np.array([[1.0, 0.0, 0.0, 0.0]]), np.array([1.0]))
    path = backward(t, gauge, 0.0)
    assert [int(np.count_nonzero(x)) for x in path] == [4, 3, 2, 1]
    assert np.allclose(path[2], [1.0, -2.0, 0.0, 0.0])


def test_the_held_in_rows_are_the_head_of_the_whole_fields_rows():
    import numpy as np

    from latticedft._learn._data import as_fields
    from latticedft._learn._exact import residual_matrix
    from latticedft._learn._sparse import _head

    data = pendulum(2.0, 20)
    model = ldft.SparseLagrangian("kinetic + trig:1", threshold=0.1, bags=0)
    ldft.learn(model, data, progress=False)
    (field,) = as_fields([data], None)
    whole = residual_matrix(model, field)
    part = residual_matrix(model, field.with_values(field.values[:14]))
    assert np.array_equal(_head(model, field, whole, 14), part)


# -- beyond the training amplitudes ------------------------------------------------------------------------------
def _kept_by_keep_below() -> list[dict]:
    return [  # the hand-set polynomial below keep_below, an exact-step candidate 500x above it
        {"score": 3.5e-9, "n_parameters": 45, "label": "hand-set", "kind": "polynomial"},
        {"score": 2.8e-2, "n_parameters": 3, "label": "true terms", "kind": "sparse", "terms": ["a", "b", "c"]},
        {"score": 6.4e-6, "n_parameters": 5, "label": "exact step", "kind": "sparse", "terms": ["a", "b", "c", "d"]},
    ]


def test_a_hand_set_model_kept_by_keep_below_is_replaced_when_a_candidate_serves_the_largest_field_better():
    rows = _kept_by_keep_below()
    asked: list[int] = []

    def beyond(scores):
        def score(i):  # as select's: the score goes into the row
            asked.append(i)
            rows[i]["beyond"] = scores[i]
            return scores[i]

        return score

    assert _choose(rows, factor=2.0, keep_below=1e-6)[0] == 0  # not measured (one training field): kept
    chosen, reason, _ = _choose(rows, 2.0, 1e-6, beyond({0: math.inf, 2: 5.8e-2}))
    assert chosen == 2 and "largest amplitude" in reason and "inf" in reason
    chosen, reason, _ = _choose(rows, 2.0, 1e-6, beyond({0: 1e-1, 2: 5.8e-2}))
    assert chosen == 0 and "keep_below" in reason  # not 2x better: kept
    assert "beyond the training amplitudes 5.800e-02 against the hand-set model's 1.000e-01" in reason
    asked.clear()
    assert _choose(rows, 2.0, 1e-6, beyond({0: math.inf, 2: 2 * BEYOND_CEILING}))[0] == 0  # misses the ceiling
    assert asked == [2]  # ... and the hand-set model is not scored
    rows[0]["score"] = 1e-5  # above keep_below: the rules on the held-out slices alone
    asked.clear()
    assert _choose(rows, 2.0, 1e-6, beyond({0: math.inf, 2: 5.8e-2}))[0] == 2 and asked == []


def test_the_largest_field_is_the_one_of_largest_range_in_one_component():
    t = np.arange(5)
    small = xr.DataArray(np.outer(np.sin(t), [1.0, 0.1]) + 10.0, dims=("t", "component"))
    wide = xr.DataArray(np.outer(np.sin(t), [0.2, 1.5]), dims=("t", "component"))
    assert largest_field([small, wide]) == 1 and largest_field([wide, small, wide]) == 0
    assert largest_field([xr.DataArray(np.sin(t) * a, dims="t") for a in (0.5, 2.0, 1.0)]) == 1


def _quartic(a: float, n: int = 101, dt: float = 0.2) -> xr.DataArray:
    q = _ode(lambda y: [y[1], -y[0] - 0.5 * y[0] ** 3], [a, 0.0], n, dt)[0]
    return xr.DataArray(q, dims="t", coords={"t": np.arange(n) * dt}, name="psi")


def test_select_scores_candidates_beyond_the_training_amplitudes_only_when_the_hand_set_model_is_kept():
    exact_step = [c for c in exact_step_candidates(1, 1) if "poly:6" in c["library"]]
    data = [_quartic(0.5), _quartic(1.0)]
    sel = ldft.select(ldft.PolynomialLagrangian(), data, exact_step, progress=False)
    assert sel.rows[0]["score"] <= sel.keep_below < sel.rows[1]["score"]  # kept by keep_below on the slices alone
    assert sel.rows[0]["beyond"] == math.inf and sel.rows[1]["beyond"] < BEYOND_CEILING  # learned on 0.5, serve 1.0
    assert sel.chosen == 1 and isinstance(sel.model, ldft.SparseLagrangian)
    assert sel.to_dict()["candidates"][0]["beyond"] is None and "largest field left out" in sel.table_lines()[1]
    one = ldft.select(ldft.PolynomialLagrangian(), data[1:], exact_step, progress=False)
    assert all("beyond" not in r for r in one.rows)  # one field: nothing to leave out
