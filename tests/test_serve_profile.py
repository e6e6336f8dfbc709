"""``benchmarks.serve_profile`` (the profiles docs/performance.md quotes) runs every part on tiny lattices and
returns its tables: every part, a row per lattice, finite figures, positive costs, the switches it turns put
back. No timing is asserted."""

from __future__ import annotations

import math

import pytest

from benchmarks import serve_profile
from latticedft._serve import _field, _folded, _fused, _newton, _solvers

#: Per part, the columns whose every figure is a cost or a count measured directly (so positive).
POSITIVE = {
    "slice-work": [
        "leapfrog step (ms)",
        "evaluations / slice",
        "GMRES solves / slice",
        "fresh Jacobians / slice",
        "evaluation",
        "evaluation with blocks",
        "GMRES solve",
        "fresh Jacobian's own work",
        "whole slice",
    ],
    "chord": ["leapfrog step (ms)", "field's largest value"],
    "lattice-new": ["leapfrog step (ms)", "serve / leapfrog", "fixed per serve", "fixed, lattice new"],
    "fixed-part": [
        "leapfrog (ns / site and step)",
        "slice_steps (ns / site and slice)",
        "serve (ms)",
        "slice_steps' share of the serve",
    ],
    "faults": ["field (pages)", "serve, held -> dropped: least / median (ms)"],
    "linalg": ["leapfrog step (ms)"],
    "fit3d": ["leapfrog (ns / site and step)"],
    "affine": [],
}


def _numbers(text: str) -> list[float]:
    """The figures of a text cell such as ``"3.00 -> 2.50"``, ``"0.41 / 0.49"`` or ``"0 (2112) -> 0 (2080)"`` (a
    percent sign and parentheses dropped)."""
    for mark in ("->", "/", "(", ")"):
        text = text.replace(mark, " ")
    return [float(w.rstrip("%")) for w in text.split()]


def _switches() -> tuple[object, ...]:
    """Every module switch and timed function the profile replaces while it runs."""
    return (
        _newton.CHORD_PREDICT,
        _newton.FRESH_FIRST_ON,
        _solvers.COMPILED_GMRES,
        serve_profile._slices.COMPILED_ASSEMBLY,
        _folded.FoldedSlices.evaluate,
        _newton._factorise,
        _newton._fresh_blocks,
        _fused.FusedSlices.solve_many,
        _field._affine_prefix,
    )


@pytest.fixture(scope="module")
def tables() -> dict[str, serve_profile.Table]:
    before = _switches()
    out = serve_profile.run(quick=True)
    after = _switches()
    assert after == before  # every switch and timed function put back
    return out


def test_every_part_has_a_row_per_lattice_with_finite_figures(tables):
    assert list(tables) == list(serve_profile.PARTS)
    for name, table in tables.items():
        assert table.rows, name
        for row in table.rows:
            assert len(row) == len(table.columns), name
            assert isinstance(row[0], str) and "D " in row[0], (name, row[0])  # "3+1D 32^3 x 10"
            for column, value in zip(table.columns[1:], row[1:]):
                if isinstance(value, bool) or column == "orders":
                    continue
                figures = [float(value)] if isinstance(value, (int, float)) else _numbers(str(value))
                assert figures and all(math.isfinite(v) for v in figures), (name, column, value)
                if column in POSITIVE[name]:
                    assert all(v > 0 for v in figures), (name, column, value)
        assert any("Load average before" in n for n in table.notes), name


def test_the_switched_ways_serve_the_same_iterations_and_fields_within_round_off(tables):
    # the largest difference of the two ways' fields over their size: the compiled linear algebra's steps differ
    # by round-off, the chord's rate test stops Newton elsewhere within its tolerance (rtol 1e-10)
    for row in tables["linalg"].rows:
        assert 0 <= row[-1] < 1e-12, row
    for row in tables["chord"].rows:
        assert all(0 <= v < 1e-9 for v in _numbers(row[-2])), row
    for row in tables["affine"].rows:
        assert row[-1] is True  # the kept answer serves the same field to the bit
        assert len(_numbers(row[1])) == len(_numbers(row[2])) == 2  # a figure per round, each way
    for row in tables["faults"].rows:  # held -> dropped: the median and the most faults a serve each way
        held, most_held, dropped, most_dropped = _numbers(row[2])
        assert 0 <= held <= most_held and 0 <= dropped <= most_dropped, row
        assert all(v == int(v) for v in (held, most_held, dropped, most_dropped)), row  # whole counts
    evals = [_numbers(r[3]) for r in tables["chord"].rows]  # per way of the chord, evaluations a slice
    assert all(len(e) == len(serve_profile.CHORD_WAYS) and all(v >= 1 for v in e) for e in evals)


def test_an_unknown_part_is_refused(capsys):
    with pytest.raises(SystemExit):
        serve_profile.main(["--part", "nope"])
    assert "invalid choice: 'nope'" in capsys.readouterr().err
