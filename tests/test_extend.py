"""What an extension costs, counted by adding a throwaway one.

Each section adds one kind of extension the way docs/design.md ("Extending latticedft") says to, inside a
test, and checks that it works end to end:

- a model kind is one file plus one registry line: the class below (in a package it would be its own module)
  and ``MODELS[kind] = TheClass``. Nothing else in the package names it, yet a case selects it, validates its
  options, checks its size against the memory, tries its ``select = "auto"`` candidates, trains it, and writes
  and reads its model file;
- a boundary kind is one class and its line in ``KINDS``, both in ``latticedft/_boundary.py``;
- an export format is one module and its lines in ``latticedft/io/exporters.py``;
- a ``[[serve]]`` key is one field of the serving options.

:class:`_Recipe` records the package's files a recipe touches, so each count is asserted, not just claimed.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np
import pytest
import torch

import latticedft as ldft
from latticedft import _boundary, systems
from latticedft._boundary import BoundaryKind
from latticedft._case import load_case
from latticedft.io import exporters, write_field
from latticedft.io.exporters import Exporter, ExportTask

from case_helpers import REPO, run_cli, tiny_wave, write_toml

NO_EXPORT = ["--set", "export.figures=false", "--set", "export.paraview=false", "--set", "run.threads=1", "-q"]


# -- the one file -----------------------------------------------------------------------------------------------
class EvenWell(ldft.LinearLagrangian):
    """``L_d = a (q1 - q0)^2 / (2 h^2) - sum_k b_k (q0^2k + q1^2k) / 2`` for ``k = 1 .. degree``."""

    kind = "test-even-well"

    def __init__(self, degree: int = 1, *, stencil: ldft.Stencil | None = None):
        super().__init__(stencil)
        if degree < 1:
            raise ldft.InputError.at("degree", f"expected an integer >= 1, got {degree!r}")
        self.degree = degree

    def options(self) -> dict[str, Any]:
        return {"degree": self.degree}

    @property
    def n_terms(self) -> int:
        return 1 + self.degree

    def features(self, cells: torch.Tensor) -> torch.Tensor:
        q0, q1 = cells[..., 0, 0], cells[..., 1, 0]
        kinetic = 0.5 * ((q1 - q0) / self.spacing[0]) ** 2
        wells = [-(q0 ** (2 * k) + q1 ** (2 * k)) / 2 for k in range(1, self.degree + 1)]
        return torch.stack([kinetic, *wells], -1)

    @classmethod
    def parameter_lower_bound(cls, options: Mapping[str, Any], n: int, m: int) -> tuple[int, str] | None:
        return 1 + int(options.get("degree", 1)), "model.degree"

    def auto_candidates(self, n: int, ridge: Any = 0.0) -> list[dict[str, Any]]:
        return [{"degree": self.degree + 1}, {"degree": self.degree + 2}]


@pytest.fixture()
def even_well(monkeypatch: pytest.MonkeyPatch) -> type[EvenWell]:
    monkeypatch.setitem(ldft.MODELS, EvenWell.kind, EvenWell)  # -- the one registry line
    return EvenWell


def _case(tmp: Path) -> Path:
    """A pendulum (``V = 1 - cos q``) sampled at two amplitudes, and a task inside their range."""
    case = tmp / "pendulum"
    (case / "data").mkdir(parents=True)
    for i, a in enumerate((1.2, 0.6)):
        write_field(case / "data" / f"train{i}.nc", {"psi": systems.oscillator_sin(a, n=51)})
    write_field(case / "data" / "inside.nc", {"psi": systems.oscillator_sin(-0.9, n=51)})
    return write_toml(
        case,
        f"""
        [model]
        kind = "{EvenWell.kind}"
        degree = 1
        select = "auto"
        [train]
        data = ["data/train*.nc"]
        [[serve]]
        name = "inside"
        from = "data/inside.nc"
        """,
    )


def test_a_model_kind_is_one_class_and_one_registry_line(even_well, tmp_path, capsys):
    case = _case(tmp_path)
    model = load_case(case).model.build(1)  # case.toml names it and its options are checked
    assert type(model) is even_well and model.degree == 1

    text = (case / "case.toml").read_text()
    (case / "case.toml").write_text(text.replace("degree = 1", 'degree = "two"'))
    code, _, err = run_cli(capsys, "check", case, "-q")
    assert code == 1 and "model.degree: expected an integer, got 'two'" in err

    (case / "case.toml").write_text(text.replace("degree = 1", "degree = 1000000000000"))
    code, _, err = run_cli(capsys, "check", case, "-q")  # the memory check reads its parameter bound
    assert code == 1 and "model.degree" in err and "parameters" in err and "memory" in err

    (case / "case.toml").write_text(text)
    out = tmp_path / "out"
    code, _, err = run_cli(capsys, "run", case, "--out", out, *NO_EXPORT)
    assert code == 0, err
    record = json.loads((out / "model.json").read_text())
    labels = [row["label"] for row in record["training"]["selection"]["candidates"]]
    assert labels[0] == "hand-set" and labels[-2:] == ["degree=2", "degree=3"]  # its own "auto" candidates too
    assert all("kind='sparse'" in label for label in labels[1:-2])  # after the sparse libraries

    (case / "case.toml").write_text(text.replace('select = "auto"', ""))  # the hand-set kind alone
    code, _, err = run_cli(capsys, "run", case, "--out", out, "--overwrite", *NO_EXPORT)
    assert code == 0, err
    record = json.loads((out / "model.json").read_text())
    assert record["kind"] == even_well.kind and record["gauge"] == "unit-mass"

    back = ldft.load_model(out / "model.pt")  # the model file round-trips
    assert type(back) is even_well and back.options() == {"degree": record["options"]["degree"]}
    assert back.gauge == "unit-mass" and back.n_terms == 1 + back.degree
    again = ldft.load_model(ldft.save_model(back, tmp_path / "again.pt"))
    assert all(torch.equal(a, b) for a, b in zip(again.state_dict().values(), back.state_dict().values()))


# -- what a recipe changes --------------------------------------------------------------------------------------
class _Recipe:
    """The package's files an extension changes, as a test adds it: the files its code goes into, and the module
    of each registry it adds a line to (the line added for the test's duration)."""

    def __init__(self, monkeypatch: pytest.MonkeyPatch) -> None:
        self._monkeypatch = monkeypatch
        self.files: set[str] = set()

    def code_in(self, path: str) -> None:
        """The extension's code goes into ``path`` (relative to the repository; here it sits in the test)."""
        self.files.add(path)

    def registry_line(self, module: ModuleType, registry: str, key: str, value: object) -> None:
        """``module.registry[key] = value``: one line in the module that owns the registry."""
        self._monkeypatch.setitem(getattr(module, registry), key, value)
        self.files.add(Path(str(module.__file__)).resolve().relative_to(REPO).as_posix())


# -- a boundary kind: its class and its line in KINDS, both in latticedft/_boundary.py ---------------------------
class Clamped(BoundaryKind):
    """An axis whose edge sites hold data, by the generic index rules alone (the Dirichlet kind's twin)."""

    name, title, given_edges = "clamped", "clamped", True

    def cells(self, n: int, width: int) -> int:
        return n - width

    def sites(self, index: np.ndarray, n: int) -> np.ndarray:
        return index

    def interior(self, n: int, width: int) -> slice:
        return slice(width, n - width)


def test_a_boundary_kind_is_one_class_and_one_registry_line(tmp_path, capsys, monkeypatch):
    case = tiny_wave(tmp_path)
    with pytest.raises(ldft.ConfigError, match="serve\\[0\\].boundary: expected 'dirichlet' or 'periodic'"):
        load_case(case, ["serve.test.boundary=clamped"])  # not a kind before it is registered

    recipe = _Recipe(monkeypatch)
    recipe.code_in("latticedft/_boundary.py")  # the class
    recipe.registry_line(_boundary, "KINDS", "clamped", Clamped())
    assert recipe.files == {"latticedft/_boundary.py"}  # one file of code (target: 2), plus its docs row

    with pytest.raises(ldft.ConfigError, match="expected 'dirichlet' or 'periodic' or 'clamped'"):
        load_case(case, ["serve.test.boundary=clamp"])  # every vocabulary is read from the registry
    code, _, err = run_cli(
        capsys, "check", case, "--set", "serve.test.boundary=clamped", "--set", "serve.test.slices=50"
    )
    assert code == 1 and "50 slices need the clamped strips along 'x'" in err  # its edges are data

    fields = {}
    for kind in ("clamped", "dirichlet"):
        out = tmp_path / kind
        code, _, err = run_cli(capsys, "run", case, "--out", out, "--set", f"serve.test.boundary={kind}", *NO_EXPORT)
        assert code == 0, err
        fields[kind] = ldft.io.read_field(out / "test.nc")
    assert np.array_equal(fields["clamped"].values, fields["dirichlet"].values)  # the generic rules serve it

    u0 = np.sin(np.pi * np.linspace(0.0, 1.0, 9))
    clamped = systems.leapfrog(u0, u0, 6, 0.05, 1 / 8, boundary="clamped")
    assert np.array_equal(clamped, systems.leapfrog(u0, u0, 6, 0.05, 1 / 8, boundary="dirichlet"))


# -- an export format: its module (latticedft/io/<format>.py) and its lines in latticedft/io/exporters.py --------
class CsvExporter(Exporter):
    """``<task>.csv``: the served field, one row per time slice."""

    name = "csv"
    summary = "the served field as comma-separated values, one row per slice"

    def write(self, task: ExportTask) -> list[Path]:
        path = task.folder / f"{task.name}.csv"
        values = np.asarray(task.field.values, dtype=float)
        np.savetxt(path, values.reshape(values.shape[0], -1), delimiter=",")
        return [path]


def test_an_export_format_is_one_module_and_its_registry_lines(tmp_path, capsys, monkeypatch):
    case = tiny_wave(tmp_path)
    recipe = _Recipe(monkeypatch)
    recipe.code_in("latticedft/io/csv.py")  # the exporter
    recipe.registry_line(exporters, "EXPORTERS", "csv", f"{__name__}:{CsvExporter.__qualname__}")
    recipe.registry_line(exporters, "EXPORT_FILES", "csv", ("{name}.csv",))
    assert recipe.files == {"latticedft/io/csv.py", "latticedft/io/exporters.py"}  # two files (target: 2)

    code, _, err = run_cli(capsys, "check", case, "--set", 'export.formats=["cvs"]')
    assert code == 1 and "export.formats: unknown format 'cvs'; did you mean 'csv'?" in err
    out = tmp_path / "out"
    code, _, err = run_cli(capsys, "run", case, "--out", out, "--set", 'export.formats=["csv"]', "-q")
    assert code == 0, err
    served = ldft.io.read_field(out / "test.nc")
    assert np.array_equal(np.loadtxt(out / "test.csv", delimiter=",", ndmin=2), served.values.reshape(30, -1))
    summary = json.loads((out / "summary.json").read_text())
    assert summary["tasks"]["test"]["exports"] == ["test.csv"]  # recorded, so a later export replaces exactly it

    code, _, err = run_cli(capsys, "export", case, "--out", out, "--set", 'export.formats=["figures"]')
    assert code == 0, err
    assert not (out / "test.csv").exists() and (out / "test.png").is_file()
    assert "test.csv" in exporters.export_file_names("test", 30)  # the file-name checks know its files


# ---------------------------------------------------------------------------------------------------------
# A [[serve]] key: one field of the serving options (plus its row in docs/case-toml.md's table).
# ---------------------------------------------------------------------------------------------------------


def test_a_serve_key_is_one_field_of_the_serving_options(tmp_path, monkeypatch):
    from dataclasses import dataclass

    import pytest

    import latticedft._run._task
    from latticedft import ConfigError
    from latticedft._case import _schema, load_case
    from latticedft._run import check_case, serve_task, train_model
    from latticedft._serve._options import ServeOptions, choice, option

    from case_helpers import tiny_wave

    @dataclass(frozen=True)
    class FlavouredOptions(ServeOptions):
        """The serving options with one more ``[[serve]]`` key: all that a new key needs in the code."""

        flavour: str = option("plain", choice("plain", "spicy"))

    case = tiny_wave(tmp_path)
    with pytest.raises(ConfigError, match=r"serve\[0\]\.flavour: unknown key"):
        load_case(case, ["serve.test.flavour=spicy"])  # not a key before it is a field

    monkeypatch.setattr(_schema, "SERVE_OPTIONS", FlavouredOptions)
    assert load_case(case).serve[0].options.flavour == "plain"  # the field's default
    c = load_case(case, ["serve.test.flavour=spicy"])
    assert c.serve[0].options.flavour == "spicy" and c.serve[0].options.rtol == 1e-10
    with pytest.raises(ConfigError) as bad:
        load_case(case, ["serve.test.flavour=mild"])
    assert str(bad.value) == "--set: serve[0].flavour: expected 'plain' or 'spicy', got 'mild'"
    with pytest.raises(ConfigError, match=r"serve\[0\]\.flavor: unknown key; did you mean 'flavour'\?"):
        load_case(case, ["serve.test.flavor=spicy"])

    seen: list[ServeOptions] = []
    real = latticedft._run._task.serve

    def spy(*args, **kwargs):
        seen.append(kwargs["options"])
        return real(*args, **kwargs)

    monkeypatch.setattr(latticedft._run._task, "serve", spy)  # the pipeline's serving call
    data = check_case(c)
    model, _ = train_model(c, data)
    out = serve_task(model, data.tasks[0])
    assert out.complete and [type(o) for o in seen] == [FlavouredOptions] and seen[0].flavour == "spicy"
