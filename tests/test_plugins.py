"""Model kinds and export formats from other packages: by entry point or by import path, loaded lazily.

``tests/plugins`` holds such a package, ``latticedft_demo``, with the ``dist-info`` folder an installed
package would have (its ``entry_points.txt`` declares one model kind, one export format and two broken
entries); the fixture puts that folder on ``sys.path`` and forgets what was loaded afterwards.
"""

from __future__ import annotations

import json
import sys
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

import latticedft as ldft
from latticedft import _plugins, systems
from latticedft._case import load_case
from latticedft._models import MODELS
from latticedft.io import exporters, write_field

from case_helpers import run_cli, write_toml

PLUGINS = Path(__file__).resolve().parent / "plugins"
QUIET = ["--set", "run.threads=1", "-q"]


def _forget_demo() -> None:
    """Drop what the registries and the import system kept of the demo package."""
    for name in [k for k in MODELS if k.startswith(("demo-", "latticedft_demo"))]:
        del MODELS[name]
    for name in [k for k in exporters._PLUGINS if k.startswith(("demo-", "latticedft_demo"))]:
        del exporters._PLUGINS[name]
    for module in [m for m in sys.modules if m == "latticedft_demo" or m.startswith("latticedft_demo.")]:
        del sys.modules[module]


@pytest.fixture()
def demo(monkeypatch: pytest.MonkeyPatch) -> Iterator[Path]:
    """The demo package importable and its entry points visible, as if it were installed."""
    monkeypatch.syspath_prepend(str(PLUGINS))
    yield PLUGINS
    _forget_demo()


def _case(tmp: Path, kind: str, fmt: str) -> Path:
    """A nonlinear oscillator sampled at two amplitudes, and a task inside their range."""
    case = tmp / "oscillator"
    (case / "data").mkdir(parents=True)
    for i, a in enumerate((1.2, 0.6)):
        write_field(case / "data" / f"train{i}.nc", {"psi": systems.oscillator_sin(a, n=51)})
    write_field(case / "data" / "inside.nc", {"psi": systems.oscillator_sin(-0.9, n=51)})
    return write_toml(
        case,
        f"""
        [model]
        kind = "{kind}"
        quartic = true
        [train]
        data = ["data/train*.nc"]
        [[serve]]
        name = "inside"
        from = "data/inside.nc"
        [export]
        formats = ["{fmt}"]
        """,
    )


def test_a_case_runs_with_a_plugin_model_kind_and_export_format(demo, tmp_path, capsys):
    case = _case(tmp_path, "demo-well", "demo-table")
    out = tmp_path / "out"
    code, _, err = run_cli(capsys, "run", case, "--out", out, *QUIET)
    assert code == 0, err
    record = json.loads((out / "model.json").read_text())
    assert record["kind"] == "demo-well" and record["options"] == {"quartic": True}
    table = np.loadtxt(out / "inside.demo.txt")
    served = ldft.io.read_field(out / "inside.nc")
    assert table.shape == (served.sizes["t"], 2) and np.array_equal(table[:, 1], served.values)
    assert json.loads((out / "summary.json").read_text())["tasks"]["inside"]["exports"] == ["inside.demo.txt"]

    model = ldft.load_model(out / "model.pt")
    assert type(model).__module__ == "latticedft_demo.models" and model.options() == {"quartic": True}
    assert model.gauge == "unit-mass" and model.coef.shape == (3,)


def test_import_paths_name_a_kind_and_a_format_and_the_model_file_records_the_path(demo, tmp_path, capsys):
    kind, fmt = "latticedft_demo.models:DemoWell", "latticedft_demo.export:TableExporter"
    case = _case(tmp_path, kind, fmt)
    out = tmp_path / "out"
    code, _, err = run_cli(capsys, "run", case, "--out", out, *QUIET)
    assert code == 0, err
    assert json.loads((out / "model.json").read_text())["kind"] == kind  # what load_model finds it by
    assert (out / "inside.demo.txt").is_file()
    assert ldft.load_model(out / "model.pt").options() == {"quartic": True}

    _forget_demo()
    sys.path.remove(str(PLUGINS))  # the plugin uninstalled
    with pytest.raises(ldft.ModelFileError) as refused:
        ldft.load_model(out / "model.pt")
    assert str(refused.value).startswith(f"{out / 'model.pt'}: model kind '{kind}': cannot import '{kind}'")
    assert "\n" not in str(refused.value)


def test_a_missing_plugin_kind_is_refused_in_one_line(tmp_path, capsys, monkeypatch):
    """A model file whose kind came from an entry point, read where that package is not installed."""
    monkeypatch.syspath_prepend(str(PLUGINS))
    model = MODELS["demo-well"](quartic=False)
    ldft.learn(model, systems.oscillator_sin(0.6, n=41), optimizer="exact")
    path = ldft.save_model(model, tmp_path / "model.pt")
    _forget_demo()
    monkeypatch.undo()
    with pytest.raises(ldft.ModelFileError) as refused:
        ldft.load_model(path)
    assert str(refused.value) == (
        f"{path}: unknown model kind 'demo-well'; expected one of "
        "['ensemble', 'features', 'mlp', 'polynomial', 'sparse'], "
        "an import path 'module:Class' or an entry point of group 'latticedft.models' (is its package installed?)"
    )


@pytest.mark.parametrize(
    ("key", "value", "message"),
    [
        (
            "model.kind",
            "demo-broken",
            "case.toml: model.kind: the entry point 'demo-broken' of group 'latticedft.models' "
            "(latticedft_demo.missing:Nothing) failed to load (ModuleNotFoundError: No module named "
            "'latticedft_demo.missing')",
        ),
        (
            "model.kind",
            "demo-wrong",
            "case.toml: model.kind: 'demo-wrong' gives the function latticedft_demo.models.not_a_model; expected a "
            "subclass of latticedft.AbstractLagrangian or a latticedft.ModelKind",
        ),
        (
            "model.kind",
            "latticedft_demo.models:NoSuchModel",
            "case.toml: model.kind: cannot import 'latticedft_demo.models:NoSuchModel' (AttributeError: ",
        ),
        (
            "export.formats",
            "latticedft_demo.models:DemoWell",
            "case.toml: export.formats: 'latticedft_demo.models:DemoWell' gives the class "
            "latticedft_demo.models.DemoWell; expected a subclass of latticedft.io.exporters.Exporter",
        ),
    ],
)
def test_a_broken_plugin_is_a_one_line_error_naming_the_key(demo, tmp_path, key, value, message):
    kind, fmt = (value, "demo-table") if key == "model.kind" else ("demo-well", value)
    with pytest.raises(ldft.ConfigError) as bad:
        load_case(_case(tmp_path, kind, fmt))
    assert str(bad.value).startswith(message) and "\n" not in str(bad.value) and bad.value.key == key


def test_an_unknown_name_is_matched_against_the_installed_plugins_too(demo, tmp_path):
    with pytest.raises(ldft.ConfigError) as bad:
        load_case(_case(tmp_path, "demo-wel", "demo-table"))
    assert "unknown model kind 'demo-wel'; did you mean 'demo-well'?" in str(bad.value)
    assert "'demo-broken', 'demo-well', 'demo-wrong', 'features', 'mlp', 'polynomial'" in str(bad.value)
    assert "demo-well" not in MODELS._kinds  # named in the message, not loaded
    with pytest.raises(ldft.ConfigError, match="unknown format 'demo-tabel'; did you mean 'demo-table'"):
        load_case(_case(tmp_path / "2", "demo-well", "demo-tabel"))


def test_plugins_are_looked_up_only_for_names_latticedft_does_not_hold(demo, tmp_path, monkeypatch):
    def refuse(**_: object) -> None:
        raise AssertionError("entry points scanned")

    monkeypatch.setattr(_plugins, "entry_points", refuse)
    case = _case(tmp_path, "polynomial", "figures")
    (case / "case.toml").write_text((case / "case.toml").read_text().replace("quartic = true", ""))
    assert load_case(case).model.kind == "polynomial"
    with pytest.raises(AssertionError, match="entry points scanned"):
        MODELS["demo-well"]


def test_a_model_file_records_the_name_its_kind_was_found_by(demo):
    class Unregistered(ldft.PolynomialLagrangian):
        kind = "unregistered-polynomial"

    assert MODELS.name_of(ldft.PolynomialLagrangian()) == "polynomial"
    assert MODELS.name_of(Unregistered()) == "unregistered-polynomial"  # never recorded as its base's kind
    by_path = MODELS["latticedft_demo.models:DemoWell"]()
    assert by_path.kind == "demo-well" and MODELS.name_of(by_path) == "latticedft_demo.models:DemoWell"
