"""Layers 0-4 are type-checked as ``mypy --strict`` checks them, but for a ratchet that only shrinks.

pyproject.toml holds two ``[[tool.mypy.overrides]]`` blocks read here: the strict one sets, for the
modules of layers 0-4 of docs/design.md's table, every per-module flag ``--strict`` sets; the ratchet
names the modules of those layers not yet clean under them and sets the same flags back to mypy's
defaults. The ratchet only shrinks: its length is recorded in ``RATCHET_LENGTH``, a module added to it
fails the test, and so does a listed module that has become clean (remove it, and lower the length).
"""

from __future__ import annotations

import json
import subprocess
import sys
import tomllib
from pathlib import Path
from typing import Any

import pytest
from test_layers import MODULES, _layer_of, _layers, _module_name

REPO = Path(__file__).resolve().parents[1]
TOP_LAYER = 4  # layers 0 (foundation) to 4 (models) are checked strictly

#: How many modules the ratchet lists: it may only go down, and is lowered whenever a module leaves it.
RATCHET_LENGTH = 0


def _mypy_config() -> dict[str, Any]:
    config: dict[str, Any] = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["mypy"]
    return config


def _blocks(config: dict[str, Any] | None = None) -> tuple[dict[str, Any], dict[str, Any]]:
    """The strict block and the ratchet of ``config`` (pyproject.toml's): the overrides that set
    disallow_untyped_defs."""
    blocks = [b for b in (config or _mypy_config())["overrides"] if "disallow_untyped_defs" in b]
    assert len(blocks) == 2, "expected one strict block and one ratchet in pyproject.toml's [tool.mypy]"
    strict, ratchet = blocks
    assert strict["disallow_untyped_defs"] is True and ratchet["disallow_untyped_defs"] is False
    return strict, ratchet


def _flags(block: dict[str, Any]) -> dict[str, Any]:
    return {k: v for k, v in block.items() if k != "module"}


def _strict_assignments() -> list[tuple[str, bool]]:
    """The (option, value) pairs ``mypy --strict`` sets, as the installed mypy defines them."""
    from mypy.main import define_options

    return list(define_options()[2])


def _matches(name: str, pattern: str) -> bool:
    """Whether a module pattern of mypy's config (``pkg.*`` holds pkg and its submodules) names ``name``."""
    if pattern.endswith(".*"):
        stem = pattern[:-2]
        return name == stem or name.startswith(stem + ".")
    return name == pattern


def _strict_modules() -> list[str]:
    """Every module of layers 0 to 4, from the files of the package and the table of docs/design.md."""
    layers = _layers()
    names = (_module_name(path) for path in MODULES)
    return sorted(n for n in names if (layer := _layer_of(n, layers)) is not None and layer <= TOP_LAYER)


def test_the_strict_block_sets_what_mypy_strict_sets() -> None:
    from mypy.options import PER_MODULE_OPTIONS

    strict, _ = _blocks()
    config = _mypy_config()
    for option, value in _strict_assignments():
        # a per-module flag may be set for the whole package; a global one only can be
        effective = strict.get(option, config.get(option)) if option in PER_MODULE_OPTIONS else config.get(option)
        assert effective == value, f"{option} = {str(value).lower()} is missing from mypy's config"


def test_the_ratchet_sets_back_mypys_defaults() -> None:
    from mypy.options import Options

    strict, ratchet = _blocks()
    assert set(_flags(ratchet)) == set(_flags(strict))
    defaults = Options()
    for option, value in _flags(ratchet).items():
        assert value == getattr(defaults, option), f"the ratchet's {option} is not mypy's default"


def test_every_module_of_layers_0_to_4_is_in_one_block() -> None:
    strict, ratchet = _blocks()
    modules = _strict_modules()
    assert "latticedft._errors" in modules and "latticedft._models._polynomial" in modules
    assert not [m for m in ratchet["module"] if m not in modules], "the ratchet lists a module of layer 5 or above"
    assert not set(strict["module"]) & set(ratchet["module"]), "a module is in both blocks: leave the strict one"
    loose = [m for m in modules if m not in ratchet["module"] and not any(_matches(m, p) for p in strict["module"])]
    assert not loose, f"modules of layers 0-4 in neither block (add them to the strict one): {loose}"


def test_the_ratchet_only_shrinks() -> None:
    _, ratchet = _blocks()
    n = len(ratchet["module"])
    assert n <= RATCHET_LENGTH, f"the ratchet grew to {n} modules: type the new ones instead"
    assert n == RATCHET_LENGTH, f"the ratchet is down to {n} modules: lower RATCHET_LENGTH to {n}"


def _toml(value: object) -> str:
    """A boolean, string or list of strings as TOML (JSON writes the latter two the same way)."""
    return str(value).lower() if isinstance(value, bool) else json.dumps(value)


def _config_without_ratchet(config: dict[str, Any]) -> str:
    """A mypy config (pyproject.toml's [tool.mypy]) as TOML, with the ratchet's modules moved into the strict
    block and the ratchet left out."""
    strict, ratchet = _blocks(config)
    lines = ["[tool.mypy]"]
    lines += [f"{k} = {_toml(v)}" for k, v in config.items() if k not in ("overrides", "files")]
    lines.append(f"files = {_toml([str(REPO / 'latticedft')])}")
    for block in config["overrides"]:
        if block is ratchet:
            continue
        lines.append("[[tool.mypy.overrides]]")
        for k, v in block.items():
            lines.append(f"{k} = {_toml(v + ratchet['module'] if block is strict and k == 'module' else v)}")
    return "\n".join(lines) + "\n"


def _modules_with_errors(output: str) -> set[str]:
    files = {line.split(":", 1)[0] for line in output.splitlines() if ": error:" in line}
    return {_module_name(REPO / f) for f in files}


def test_the_config_without_the_ratchet_checks_its_modules_strictly() -> None:
    config = _mypy_config()
    _, ratchet = _blocks(config)
    ratchet["module"] = [*ratchet["module"], "latticedft._models._mlp"]
    written = tomllib.loads(_config_without_ratchet(config))["tool"]["mypy"]
    strict = [b for b in written["overrides"] if "disallow_untyped_defs" in b]
    assert len(strict) == 1 and strict[0]["disallow_untyped_defs"] is True
    assert set(ratchet["module"]) <= set(strict[0]["module"])
    assert written["files"] == [str(REPO / "latticedft")]
    assert {k: v for k, v in written.items() if k not in ("files", "overrides")} == {
        k: v for k, v in config.items() if k not in ("files", "overrides")
    }
    output = f"{REPO / 'latticedft' / '_models' / '_mlp.py'}:3: error: Missing type arguments  [type-arg]\n"
    assert _modules_with_errors(output + "Found 1 error in 1 file\n") == {"latticedft._models._mlp"}


@pytest.mark.slow
def test_the_ratchets_modules_are_not_clean(tmp_path: Path) -> None:
    _, ratchet = _blocks()
    if not ratchet["module"]:
        return
    config = tmp_path / "pyproject.toml"
    config.write_text(_config_without_ratchet(_mypy_config()))
    cmd = [sys.executable, "-m", "mypy", "--config-file", str(config), "--cache-dir", str(tmp_path / "cache")]
    run = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True)
    assert run.returncode in (0, 1), run.stderr
    clean = sorted(set(ratchet["module"]) - _modules_with_errors(run.stdout))
    assert not clean, f"modules of the ratchet clean under the strict flags (remove them from it): {clean}"
