"""Tuning knobs: ``latticedft.set_options`` as a call and as a context manager, ``get_options``, the checks,
and the table of docs/api.md, which lists every knob with its default."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

import latticedft as ldft

API_PAGE = Path(__file__).resolve().parents[1] / "docs" / "api.md"
DEFAULTS = ldft.get_options()  # as the package sets them (the suite puts back what a test sets)


def test_defaults_and_a_call_that_sets_for_good() -> None:
    assert ldft.get_options() == DEFAULTS and DEFAULTS["serve_window_bytes"] == 32 * 2**20
    out = ldft.set_options(scan_bytes=1024)
    assert ldft.get_options()["scan_bytes"] == 1024 and out is not None
    ldft.get_options()["scan_bytes"] = 5  # a copy: changing it changes nothing
    assert ldft.get_options()["scan_bytes"] == 1024


def test_a_block_sets_and_puts_back_even_on_an_error() -> None:
    before = ldft.get_options()
    with ldft.set_options(serve_window_bytes=7, folded_max_powers=0):
        assert ldft.get_options()["serve_window_bytes"] == 7 and ldft.get_options()["folded_max_powers"] == 0
        with ldft.set_options(serve_window_bytes=9):
            assert ldft.get_options()["serve_window_bytes"] == 9
        assert ldft.get_options()["serve_window_bytes"] == 7
    assert ldft.get_options() == before
    with pytest.raises(RuntimeError), ldft.set_options(task_block_bytes=3):
        raise RuntimeError("inside")
    assert ldft.get_options() == before


@pytest.mark.parametrize(
    ("knobs", "message"),
    [
        ({"scan_bytes": 0}, "scan_bytes: expected a positive integer, got 0"),
        ({"serve_window_bytes": 2.5}, "serve_window_bytes: expected a positive integer, got 2.5"),
        ({"folded_chunk": True}, "folded_chunk: expected a positive integer, got True"),
        ({"folded_max_powers": -1}, "folded_max_powers: expected a non-negative integer, got -1"),
        ({"window": 3}, "window: no such tuning knob; set_options knows scan_bytes, "),
    ],
)
def test_bad_knobs_are_refused_by_name_and_nothing_is_set(knobs: dict[str, object], message: str) -> None:
    before = ldft.get_options()
    with pytest.raises(ldft.InputError) as err:
        ldft.set_options(learn_neural_chunk=5, **knobs)
    assert str(err.value).startswith(message) and "\n" not in str(err.value)
    assert err.value.key == next(iter(knobs))
    assert ldft.get_options() == before


def test_the_api_page_lists_every_knob_with_its_default() -> None:
    section = API_PAGE.read_text().split("## Tuning knobs", 1)[1].split("\n## ", 1)[0]
    rows = dict(re.findall(r"^\| `(\w+)` \| `([^`]+)` \|", section, flags=re.M))
    assert set(rows) == set(DEFAULTS)
    for name, default in rows.items():
        assert eval(default) == DEFAULTS[name], name  # noqa: S307  (a literal of the docs)
