"""case.toml: validation, suggestions, types, paths, globs, overrides."""

from __future__ import annotations

from pathlib import Path

import pytest

from latticedft import ConfigError
from latticedft._case import SCHEMA, load_case, model_options, parse_override

from case_helpers import tiny_wave, write_toml


@pytest.fixture()
def case(tmp_path: Path) -> Path:
    return tiny_wave(tmp_path)


def _edit(case: Path, old: str, new: str) -> None:
    text = (case / "case.toml").read_text()
    assert old in text
    (case / "case.toml").write_text(text.replace(old, new))


def _error(case: Path, overrides=()) -> str:
    with pytest.raises(ConfigError) as info:
        load_case(case, list(overrides))
    msg = str(info.value)
    assert "\n" not in msg
    return msg


def test_defaults_and_paths(case: Path) -> None:
    c = load_case(case)
    assert c.field.variable == "psi" and c.model.kind == "polynomial" and c.model.options == {"orders": [2, 0]}
    assert c.train.data == (case / "data" / "train.nc",)
    assert c.serve[0].source == case / "data" / "test.nc" and c.serve[0].options.mode == "newton"
    assert c.serve[0].options.rtol == 1e-10 and c.serve[0].slices is None
    assert c.export.paraview and c.export.figures and c.export.max_frames == 4
    assert c.run.threads == 1 and c.results == case / "results"


def test_default_threads(case: Path) -> None:
    _edit(case, "threads = 1\n", "")
    assert load_case(case).run.threads == 1  # the default: one thread (docs/performance.md)


def test_minimal_case_runs_with_defaults(tmp_path: Path) -> None:
    case = write_toml(tmp_path / "m", '[train]\ndata = "d.nc"\n')
    (case / "d.nc").write_text("")
    c = load_case(case)
    assert c.model.kind == "polynomial" and c.serve == () and c.train.learn["gauge"] == "auto"


@pytest.mark.parametrize(
    "old,new,needles",
    [
        ("[export]", "[exprt]", ("exprt", "did you mean 'export'")),
        ("max_frames = 4", "maxframes = 4", ("export.maxframes", "did you mean 'max_frames'")),
        ("orders = [2, 0]", "oders = [2, 0]", ("model.oders", "did you mean 'orders'")),
        ("orders = [2, 0]", "hidden = [4]", ("model.hidden", "option of kind 'mlp'")),
        ('kind = "polynomial"', 'kind = "mpl"', ("model.kind", "did you mean 'mlp'")),
        ('from = "data/test.nc"', 'form = "data/test.nc"', ("serve[0].form", "did you mean 'from'")),
    ],
)
def test_unknown_keys_suggest(case: Path, old: str, new: str, needles: tuple[str, ...]) -> None:
    _edit(case, old, new)
    msg = _error(case)
    assert msg.startswith("case.toml: ")
    for n in needles:
        assert n in msg


@pytest.mark.parametrize(
    "old,new,needles",
    [
        (
            'name = "test"',
            'name = "test"\nslices = "ten"',
            ("serve[0].slices: expected a positive integer, got 'ten'",),
        ),
        ("max_frames = 4", "max_frames = 0", ("export.max_frames: expected a positive integer, got 0",)),
        ("threads = 1", "threads = true", ("run.threads", "got true")),
        ("orders = [2, 0]", "orders = [2]", ("model.orders: expected two non-negative integers",)),
        ("orders = [2, 0]", 'basis = "fourier"', ("model.basis", "'legendre' or 'monomial'")),
        ('name = "test"', 'name = "test"\nboundary = "open"', ("serve[0].boundary", "'dirichlet' or 'periodic'")),
        ('name = "test"', 'name = "test"\nboundary = {x = "wrap"}', ("serve[0].boundary", "'wrap'")),
        ('name = "test"', 'name = "a/b"', ("serve[0].name", "file-name stem")),
        ("[model]", '[model]\nstencil = "second"', ("model.stencil", "first-order")),
        ('data = ["data/train.nc"]', 'data = ["data/train.nc"]\nridge = "big"', ("train.ridge", '"auto"')),
    ],
)
def test_wrong_types_named(case: Path, old: str, new: str, needles: tuple[str, ...]) -> None:
    _edit(case, old, new)
    msg = _error(case)
    for n in needles:
        assert n in msg, msg


def test_missing_files_and_globs(case: Path) -> None:
    _edit(case, '"data/train.nc"', '"data/nope*.nc"')
    assert "train.data: no file matches 'data/nope*.nc'" in _error(case)
    _edit(case, '"data/nope*.nc"', '"data/*.nc"')
    assert [p.name for p in load_case(case).train.data] == ["test.nc", "train.nc"]
    _edit(case, '"data/*.nc"', '"data/missing.nc"')
    assert "train.data: file not found: data/missing.nc" in _error(case)


def test_missing_required_and_duplicates(case: Path) -> None:
    text = (case / "case.toml").read_text()
    (case / "case.toml").write_text(text.replace('[train]\ndata = ["data/train.nc"]\n', ""))
    assert "train: missing table [train]" in _error(case)
    (case / "case.toml").write_text(text + '[[serve]]\nname = "test"\nfrom = "data/test.nc"\n')
    assert "serve[1].name: duplicate task name 'test'" in _error(case)


def test_bad_toml_and_missing_case(tmp_path: Path) -> None:
    assert "file not found" in _error(tmp_path)
    write_toml(tmp_path, "[model\n")
    assert "not valid TOML" in _error(tmp_path)


def test_per_axis_boundary_and_stencil(case: Path) -> None:
    _edit(case, 'name = "test"', 'name = "test"\nboundary = {x = "periodic"}')
    _edit(case, "[model]", "[model]\nstencil = [[0, 0], [1, 0], [0, 1], [1, 1]]")
    c = load_case(case)
    assert c.serve[0].boundary == {"x": "periodic"}
    assert c.model.build(2).stencil.to_list() == [[0, 0], [1, 0], [0, 1], [1, 1]]
    with pytest.raises(ConfigError, match="model.stencil: expected offsets with 3 entries"):
        c.model.build(3)


def test_model_options_follow_the_class(case: Path) -> None:
    assert set(model_options("mlp")) >= {"hidden", "activation", "form", "features", "seed", "preset"}
    _edit(case, 'kind = "polynomial"\norders = [2, 0]', 'kind = "mlp"\nactivation = "relu"')
    assert "model.activation" in _error(case) and "smooth" in _error(case)


def test_overrides(case: Path) -> None:
    c = load_case(case, ["model.orders=[3, 1]", "train.max_time=10", "serve.test.mode=sweep", "export.figures=false"])
    assert c.model.options["orders"] == [3, 1] and c.train.learn["max_time"] == 10.0
    assert c.serve[0].options.mode == "sweep" and not c.export.figures
    assert c.overrides == ("model.orders=[3, 1]", "train.max_time=10", "serve.test.mode=sweep", "export.figures=false")
    assert _error(case, ["serve.tset.slices=3"]).startswith(
        "--set serve.tset.slices: no serving task named 'tset'; did you mean 'test'?"
    )
    assert _error(case, ["serve.test.slices=ten"]) == ("--set: serve[0].slices: expected a positive integer, got 'ten'")
    assert "expected key=value" in _error(case, ["model.orders"])
    assert "did you mean 'train'" in _error(case, ["trian.gauge=none"])
    assert parse_override("train.ridge=auto") == (["train", "ridge"], "auto")


def test_schema_is_documented() -> None:
    doc = (Path(__file__).resolve().parents[1] / "docs" / "case-toml.md").read_text()
    for table, keys in SCHEMA.items():
        for key in keys:
            assert f"`{key}`" in doc, f"{table}.{key} missing from docs/case-toml.md"
    for kind in ("polynomial", "mlp"):
        for key in model_options(kind):
            assert f"`{key}`" in doc, f"model.{key} missing from docs/case-toml.md"


# -- [export] formats and its aliases --------------------------------------------------------------------------
@pytest.mark.parametrize(
    "lines,overrides,formats",
    [
        ("", [], ("paraview", "figures")),
        ('formats = ["xdmf"]', [], ("xdmf",)),
        ('formats = "xdmf"', [], ("xdmf",)),
        ("formats = []", [], ()),
        ("paraview = false", [], ("figures",)),
        ("figures = false\nparaview = false", [], ()),
        ('formats = ["xdmf", "paraview"]\nparaview = true', [], ("xdmf", "paraview")),  # agrees: fine
        ('formats = ["figures", "xdmf"]', ["export.figures=false"], ("xdmf",)),  # --set wins over the file
        ('formats = ["xdmf"]', ["export.paraview=true"], ("xdmf", "paraview")),
        ("figures = false", ['export.formats=["figures"]'], ("figures",)),
        ("", ['export.formats=["xdmf", "figures"]', "export.max_frames=9"], ("xdmf", "figures")),
    ],
)
def test_export_formats_and_aliases(case: Path, lines: str, overrides: list[str], formats: tuple[str, ...]) -> None:
    _edit(case, "[export]\n", f"[export]\n{lines}\n")
    c = load_case(case, overrides)
    assert c.export.formats == formats and c.export.max_frames == (9 if "export.max_frames=9" in overrides else 4)
    assert c.export.paraview == ("paraview" in formats) and c.export.figures == ("figures" in formats)


@pytest.mark.parametrize(
    "lines,overrides,message",
    [
        (
            'formats = ["paraveiw"]',
            [],
            (
                "case.toml: export.formats: unknown format 'paraveiw'; did you mean 'paraview'? "
                "(formats: paraview, figures, xdmf)"
            ),
        ),
        ('formats = ["figures", "figures"]', [], "case.toml: export.formats: format 'figures' listed twice"),
        ("formats = [1]", [], "case.toml: export.formats: expected a string or a list of strings, got [1]"),
        (
            'formats = ["paraview"]\nparaview = false',
            [],
            "case.toml: export.paraview: false contradicts export.formats = ['paraview']; set one of them",
        ),
        (
            'formats = ["xdmf"]\nfigures = true',
            [],
            "case.toml: export.figures: true contradicts export.formats = ['xdmf']; set one of them",
        ),
        (
            "",
            ['export.formats=["figures"]', "export.figures=false"],
            "--set: export.figures: false contradicts export.formats = ['figures']; set one of them",
        ),
        ("", ['export.formats=["xdmf5"]'], "--set: export.formats: unknown format 'xdmf5'; did you mean 'xdmf'?"),
        ("paraview = 1", [], "case.toml: export.paraview: expected true or false, got 1"),
    ],
)
def test_export_formats_errors(case: Path, lines: str, overrides: list[str], message: str) -> None:
    _edit(case, "[export]\n", f"[export]\n{lines}\n")
    assert _error(case, overrides).startswith(message)
