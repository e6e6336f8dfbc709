"""Names that say what they count: ``slices`` (and its deprecated alias ``steps``), the served field's
``source``, indices against coordinates in messages, plain help text, the usage exit status."""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import numpy as np
import pytest

import latticedft as ldft
from latticedft import lagrangians, systems
from latticedft.cli import build_parser

from case_helpers import run_cli, tiny_wave


# -- serve(slices=...), serve(steps=...) -------------------------------------------------------------------
def test_serve_slices_counts_the_two_initial_slices() -> None:
    init = systems.make_field([1.0, 0.99], ["t"], spacing=0.1)
    out = ldft.serve(lagrangians.verlet(lambda q: q**2 / 2), init, slices=11)
    assert out.field.sizes["t"] == 11 and out.slices == 11  # 10 steps


def test_serve_steps_is_a_deprecated_alias() -> None:
    init = systems.make_field([1.0, 0.99], ["t"], spacing=0.1)
    osc = lagrangians.verlet(lambda q: q**2 / 2)
    with pytest.warns(FutureWarning, match="slices"):
        old = ldft.serve(osc, init, steps=11)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        new = ldft.serve(osc, init, slices=11)
    assert old.field.sizes["t"] == 11 and np.array_equal(old.field.values, new.field.values)
    with pytest.raises(ldft.InputError, match="slices only"):
        ldft.serve(osc, init, slices=11, steps=11)


def test_the_served_field_does_not_claim_the_source_of_its_initial_data() -> None:
    ref = systems.wave_string([(1, 1.0)], nx=9, nt=12)
    assert "latticedft.systems.wave_string" in ref.attrs["source"]
    served = ldft.serve(lagrangians.wave(), ref).field
    assert served.attrs["latticedft_initial_from"] == ref.attrs["source"]
    assert served.attrs["source"].startswith("latticedft.serve") and "wave_string" not in served.attrs["source"]
    assert ref.attrs["source"].startswith("latticedft.systems")  # the input is untouched
    orbit = ldft.serve(lagrangians.kepler(), systems.kepler_orbit(1.0, 1.0, n=2), slices=5).field
    assert "kepler_orbit" in orbit.attrs["latticedft_initial_from"] and "serve" in orbit.attrs["source"]


# -- case.toml slices / steps --------------------------------------------------------------------------------
def test_case_slices_and_the_deprecated_steps(tmp_path: Path, capsys) -> None:
    case = tiny_wave(tmp_path)
    text = (case / "case.toml").read_text().replace('from = "data/test.nc"', 'from = "data/test.nc"\nsteps = 25')
    (case / "case.toml").write_text(text)
    code, _, err = run_cli(capsys, "run", case, "--set", "export.formats=[]")
    assert code == 0, err
    warning = [ln for ln in err.splitlines() if "deprecated" in ln]
    assert warning == [
        "latticedft: warning: case.toml: serve[0].steps is deprecated: write serve[0].slices (the same count: "
        "time slices served, the two initial ones included)"
    ]
    assert "serve[0].steps is deprecated" in (case / "results" / "run.log").read_text()
    task = json.loads((case / "results" / "summary.json").read_text())["tasks"]["test"]
    assert task["slices"] == 25 and task["requested_slices"] == 25
    # `check` reports it too
    code, out, _ = run_cli(capsys, "check", case)
    assert code == 0 and "serve[0].steps is deprecated" in out
    # --set of either name replaces the file's count
    code, _, err = run_cli(capsys, "run", case, "--overwrite", "--set", "serve.test.slices=20", "-q")
    assert code == 0 and "deprecated" not in err
    assert json.loads((case / "results" / "summary.json").read_text())["tasks"]["test"]["slices"] == 20
    # both in the file: one line naming the key
    (case / "case.toml").write_text(text.replace("steps = 25", "steps = 25\nslices = 25"))
    code, _, err = run_cli(capsys, "check", case)
    assert code == 1 and err.strip() == (
        "latticedft: error: case.toml: serve[0].steps: give slices only (steps is its deprecated alias, the same count)"
    )


# -- messages ------------------------------------------------------------------------------------------------
def test_nan_message_gives_index_and_coordinates() -> None:
    da = systems.wave_string([(1, 1.0)], nx=9, nt=10)
    da[2, 3] = np.nan
    with pytest.raises(ldft.InputError) as err:
        ldft.io.validate_field(da, "f.nc")
    t, x = float(da.t[2]), float(da.x[3])
    assert f"the first at index t=2, x=3 (t = {t:.6g}, x = {x:.6g})" in str(err.value)


def test_serve_error_gives_index_and_coordinates() -> None:
    singular = ldft.AnalyticLagrangian(lambda c, h: c[..., 0, 0] ** 2 + c[..., 1, 0] ** 2 + 0 * c[..., 2, 0])
    field = systems.wave_string([(1, 1.0)], nx=9, nt=6)
    with pytest.raises(ldft.ServeError) as err:
        ldft.serve(singular, field)
    msg = str(err.value)
    assert "site index t=" in msg and ", x=" in msg and "(x = " in msg


# -- the command line ----------------------------------------------------------------------------------------
def test_help_has_no_markup_and_lists_the_exit_statuses() -> None:
    parser = build_parser()
    texts = [parser.format_help()]
    sub = next(a for a in parser._actions if a.dest == "command")
    texts += [p.format_help() for p in sub.choices.values()]
    for text in texts:
        assert "``" not in text
    assert "exit status" in texts[0] and "2 a usage error" in " ".join(texts[0].split())


def test_usage_errors_exit_2(capsys) -> None:
    assert run_cli(capsys, "nonsense")[0] == 2
    assert run_cli(capsys, "run")[0] == 2  # missing CASE
    assert run_cli(capsys, "run", "x", "--no-such-option")[0] == 2
    assert run_cli(capsys, "--help")[0] == 0
