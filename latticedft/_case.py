"""Case directories: ``case.toml`` read into validated objects.

A case is a folder holding ``case.toml`` (the one file a user edits), its
observed fields in ``data/`` and, after a run, ``results/``. :func:`load_case`
reads the file, applies ``--set key=value`` overrides, checks every key and
type, resolves paths (relative to the case, globs allowed for training data)
and returns a frozen :class:`Case`. Every problem raises
:class:`latticedft.ConfigError` with a one-line message that names the key
(or file) and what was expected.

>>> import tempfile, pathlib
>>> d = pathlib.Path(tempfile.mkdtemp())
>>> _ = (d / "case.toml").write_text('[model]\\nkind = "polynomal"\\n[train]\\ndata = []\\n')
>>> try:
...     load_case(d)
... except ConfigError as exc:
...     print(exc)  # doctest: +NORMALIZE_WHITESPACE
case.toml: model.kind: unknown model kind 'polynomal'; did you mean 'polynomial'?
(expected one of ['mlp', 'polynomial'])
"""

from __future__ import annotations

import contextlib
import difflib
import glob
import importlib
import inspect
import math
import os
import re
import sys
import tomllib
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ._boundary import BOUNDARY_KINDS, kinds_text
from ._errors import ConfigError, LatticeDFTError
from ._learn import GAUGES, OPTIMIZERS
from ._models import MODELS, AbstractLagrangian
from ._models._options import OptionTypeError
from ._serve import MODES
from ._stencil import Stencil

__all__ = [
    "Case",
    "FieldConfig",
    "ModelConfig",
    "TrainConfig",
    "ServeTask",
    "RunConfig",
    "ExportConfig",
    "load_case",
    "parse_override",
    "CASE_FILE",
    "SCHEMA",
]

CASE_FILE = "case.toml"
_NAME_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]*$")


# -- type checks ---------------------------------------------------------------------------------------------
# Each check returns the normalised value or raises _Bad(expected).
class _Bad(Exception):
    def __init__(self, expected: str):
        super().__init__(expected)
        self.expected = expected


def _is_int(v: Any) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def t_str(v: Any) -> str:
    if not isinstance(v, str):
        raise _Bad("a string")
    return v


def t_bool(v: Any) -> bool:
    if not isinstance(v, bool):
        raise _Bad("true or false")
    return v


def t_pos_int(v: Any) -> int:
    if not _is_int(v) or v < 1:
        raise _Bad("a positive integer")
    return int(v)


def t_nonneg_int(v: Any) -> int:
    if not _is_int(v) or v < 0:
        raise _Bad("an integer >= 0")
    return int(v)


def t_float(v: Any) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise _Bad("a number")
    return float(v)


def t_pos_float(v: Any) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v <= 0:
        raise _Bad("a positive number")
    return float(v)


def t_nonneg_float(v: Any) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0:
        raise _Bad("a number >= 0")
    return float(v)


def t_unit_float(v: Any) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not 0 < v < 1:
        raise _Bad("a number between 0 and 1 (exclusive)")
    return float(v)


def t_ridge(v: Any) -> float | str:
    if v == "auto":
        return "auto"
    try:
        return t_nonneg_float(v)
    except _Bad:
        raise _Bad('a number >= 0 or "auto"') from None


def t_str_list(v: Any) -> list[str]:
    if isinstance(v, str):
        return [v]
    if not isinstance(v, list) or not all(isinstance(s, str) for s in v):
        raise _Bad("a string or a list of strings")
    return list(v)


def t_choice(*choices: str) -> Callable[[Any], str]:
    def check(v: Any) -> str:
        if v not in choices:
            raise _Bad(" or ".join(repr(c) for c in choices))
        return str(v)

    check.__name__ = f"t_choice{choices}"
    return check


def t_boundary(v: Any) -> str | dict[str, str]:
    """A boundary kind of :data:`latticedft._boundary.BOUNDARY_KINDS`, or a table axis -> kind (the axes are
    checked against the data when they are read)."""
    if isinstance(v, str):
        if v not in BOUNDARY_KINDS:
            raise _Bad(f"{kinds_text()}, or a table axis -> kind")
        return v
    if isinstance(v, dict):
        for axis, kind in v.items():
            if kind not in BOUNDARY_KINDS:
                raise _Bad(f"a table axis -> kind with kinds {list(BOUNDARY_KINDS)} (axis {axis!r} has {kind!r})")
        return {str(k): str(kind) for k, kind in v.items()}
    raise _Bad(f"{kinds_text()}, or a table axis -> kind")


def t_stencil(v: Any) -> str | list[list[int]]:
    if v in ("first-order", "full-cell"):
        return str(v)
    if isinstance(v, list) and v and all(isinstance(o, list) and o and all(_is_int(i) for i in o) for o in v):
        return [[int(i) for i in o] for o in v]
    raise _Bad('"first-order", "full-cell" or a list of integer offsets such as [[0, 0], [1, 0], [0, 1]]')


def t_invariant(v: Any) -> str:
    if not isinstance(v, str) or not re.fullmatch(r"[A-Za-z_][\w.]*:[A-Za-z_]\w*", v):
        raise _Bad('"module:function", e.g. "latticedft.systems:sine_gordon_energy"')
    return v


def t_name(v: Any) -> str:
    if not isinstance(v, str) or not _NAME_RE.match(v) or v in ("model", "summary", "run"):
        raise _Bad("a plain file-name stem (letters, digits, '_', '-', '.'; not 'model', 'summary' or 'run')")
    return v


def t_any(v: Any) -> Any:
    return v


# -- the schema --------------------------------------------------------------------------------------------
_REQUIRED = object()

#: table -> key -> (check, default). ``[[serve]]`` entries use ``SCHEMA["serve"]``.
SCHEMA: dict[str, dict[str, tuple[Callable[[Any], Any], Any]]] = {
    "field": {
        "variable": (t_str, "psi"),
        "components": (t_str_list, None),
    },
    "train": {
        "data": (t_str_list, _REQUIRED),
        "boundary": (t_boundary, None),
        "gauge": (t_choice(*GAUGES), "unit-mass"),
        "ridge": (t_ridge, 0.0),
        "optimizer": (t_choice(*OPTIMIZERS), None),
        "max_iter": (t_pos_int, 500),
        "max_time": (t_pos_float, None),
        "tol": (t_nonneg_float, 0.0),
        "rel_tol": (t_pos_float, None),
        "lr": (t_pos_float, 1e-3),
        "penalty": (t_nonneg_float, 1.0),
        "chunk_sites": (t_nonneg_int, None),
    },
    "serve": {
        "name": (t_name, _REQUIRED),
        "from": (t_str, _REQUIRED),
        "steps": (t_pos_int, None),
        "boundary": (t_boundary, None),
        "mode": (t_choice(*MODES), "newton"),
        "box": (t_pos_float, None),
        "rtol": (t_unit_float, 1e-10),
        "max_newton": (t_pos_int, 30),
        "reference": (t_str, None),
        "baseline": (t_str, None),
        "invariant": (t_invariant, None),
    },
    "run": {
        "threads": (t_pos_int, None),
    },
    "export": {
        "formats": (t_str_list, None),  # None: latticedft.io.exporters.DEFAULT_FORMATS
        "paraview": (t_bool, None),  # alias: true adds "paraview" to formats, false removes it
        "figures": (t_bool, None),  # alias: the same for "figures"
        "max_frames": (t_pos_int, 200),
    },
}
_TABLES = ("field", "model", "train", "serve", "run", "export")


def model_options(kind: str) -> dict[str, Any]:
    """The constructor options of ``MODELS[kind]`` with their defaults (``stencil`` excluded)."""
    sig = inspect.signature(MODELS[kind].__init__)
    return {
        name: (None if p.default is inspect.Parameter.empty else p.default)
        for name, p in sig.parameters.items()
        if name not in ("self", "stencil") and p.kind not in (p.VAR_POSITIONAL, p.VAR_KEYWORD)
    }


def model_option_check(kind: str, option: str) -> Callable[[Any], Any]:
    """The type check of a ``[model]`` option, from the annotation of the model class's constructor."""
    check = MODELS[kind].option_checks().get(option, t_any)

    def run(value: Any) -> Any:
        try:
            return check(value)
        except OptionTypeError as bad:
            raise _Bad(bad.expected) from None

    return run


# -- dataclasses -------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class FieldConfig:
    """``[field]``: name of the data variable and (optionally) the expected component labels."""

    variable: str = "psi"
    components: tuple[str, ...] | None = None


@dataclass(frozen=True)
class ModelConfig:
    """``[model]``: the model kind, its constructor options and the stencil."""

    kind: str = "polynomial"
    options: dict[str, Any] = field(default_factory=dict)
    stencil: str | list[list[int]] | None = None

    def build(self, n: int) -> AbstractLagrangian:
        """A fresh model for an ``n``-dimensional lattice (raises ConfigError on bad options)."""
        if self.stencil is None or self.stencil == "first-order":
            st = Stencil.first_order(n)
        elif self.stencil == "full-cell":
            st = Stencil.full_cell(n)
        elif isinstance(self.stencil, str):  # t_stencil lets no other name through
            raise ConfigError(f"case.toml: model.stencil: unknown stencil {self.stencil!r}")
        else:
            if any(len(o) != n for o in self.stencil):
                raise ConfigError(
                    f"case.toml: model.stencil: expected offsets with {n} entries each "
                    f"(the data have {n} lattice dims), got {self.stencil!r}"
                )
            try:
                st = Stencil(self.stencil)
            except LatticeDFTError as exc:
                raise ConfigError(f"case.toml: model.stencil: {exc}") from None
        try:
            return MODELS[self.kind](**self.options, stencil=st)
        except LatticeDFTError as exc:
            raise ConfigError(f"case.toml: model.{exc}") from None


@dataclass(frozen=True)
class TrainConfig:
    """``[train]``: training files (globs resolved, sorted) and :func:`latticedft.learn` keywords."""

    data: tuple[Path, ...]
    patterns: tuple[str, ...]
    boundary: str | dict[str, str] | None = None
    learn: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class ServeTask:
    """One ``[[serve]]`` entry with its paths resolved."""

    name: str
    source: Path
    steps: int | None = None
    boundary: str | dict[str, str] | None = None
    mode: str = "newton"
    box: float | None = None
    rtol: float = 1e-10
    max_newton: int = 30
    reference: Path | None = None
    baseline: Path | None = None
    invariant: str | None = None
    label: str = "serve[0]"

    def serve_kwargs(self) -> dict[str, Any]:
        return {
            "steps": self.steps,
            "boundary": self.boundary,
            "mode": self.mode,
            "box": self.box,
            "rtol": self.rtol,
            "max_newton": self.max_newton,
        }


@dataclass(frozen=True)
class RunConfig:
    """``[run]``: torch threads (default ``min(2, os.cpu_count())``)."""

    threads: int


@dataclass(frozen=True)
class ExportConfig:
    """``[export]``: the export formats of every task (names of ``latticedft.io.exporters.EXPORTERS``, written
    in this order) and the most frames per task of the time-series formats."""

    formats: tuple[str, ...] = ("paraview", "figures")
    max_frames: int | None = 200

    @property
    def paraview(self) -> bool:
        return "paraview" in self.formats

    @property
    def figures(self) -> bool:
        return "figures" in self.formats


@dataclass(frozen=True)
class Case:
    """A validated case directory."""

    root: Path
    field: FieldConfig
    model: ModelConfig
    train: TrainConfig
    serve: tuple[ServeTask, ...]
    run: RunConfig
    export: ExportConfig
    raw: dict[str, Any]
    overrides: tuple[str, ...] = ()

    @property
    def results(self) -> Path:
        return self.root / "results"

    @property
    def name(self) -> str:
        return self.root.resolve().name


# -- reading -----------------------------------------------------------------------------------------------
def _closest(word: str, options: list[str]) -> str:
    match = difflib.get_close_matches(word, options, n=1, cutoff=0.5)
    return f"; did you mean {match[0]!r}?" if match else ""


def _describe(v: Any) -> str:
    if isinstance(v, str):
        return repr(v)
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, dict):
        return "a table"
    text = repr(v)
    return text if len(text) <= 60 else text[:57] + "..."


class _Ctx:
    """Error messages: ``<where>: <key>: <problem>`` where ``where`` is the file or ``--set``."""

    def __init__(self, file: str, overridden: set[str]):
        self.file = file
        self.overridden = overridden

    def error(self, key: str, problem: str) -> ConfigError:
        where = "--set" if key in self.overridden else self.file
        return ConfigError(f"{where}: {key}: {problem}", key=key, problem=problem)

    def check(self, key: str, check: Callable[[Any], Any], value: Any) -> Any:
        try:
            return check(value)
        except _Bad as bad:
            raise self.error(key, f"expected {bad.expected}, got {_describe(value)}") from None


def _table(
    ctx: _Ctx,
    raw: dict[str, Any],
    name: str,
    schema: dict[str, tuple[Callable[[Any], Any], Any]],
    label: str | None = None,
) -> dict[str, Any]:
    """Check the keys of ``raw[name]`` (or of ``raw`` itself when ``label`` is given)."""
    tab = raw if label is not None else raw.get(name, {})
    label = label or name
    if not isinstance(tab, dict):
        raise ctx.error(label, f"expected a table [{label}], got {_describe(tab)}")
    out: dict[str, Any] = {}
    for key in tab:
        if key not in schema:
            raise ctx.error(
                f"{label}.{key}", f"unknown key{_closest(key, list(schema))} (valid keys: {', '.join(schema)})"
            )
    for key, (check, default) in schema.items():
        if key in tab:
            out[key] = ctx.check(f"{label}.{key}", check, tab[key])
        elif default is _REQUIRED:
            raise ctx.error(f"{label}.{key}", "missing required key")
        else:
            out[key] = default
    return out


def _resolve(ctx: _Ctx, root: Path, key: str, rel: str) -> Path:
    p = Path(rel)
    p = p if p.is_absolute() else root / p
    if not p.is_file():
        raise ctx.error(key, f"file not found: {rel}" + (" (a folder)" if p.is_dir() else ""))
    return p


def parse_override(text: str) -> tuple[list[str], Any]:
    """Split ``key.path=value``; the value is read as TOML (bare words become strings).

    >>> parse_override("model.orders=[2, 2]")
    (['model', 'orders'], [2, 2])
    >>> parse_override("serve.test1.mode=sweep")
    (['serve', 'test1', 'mode'], 'sweep')
    """
    if "=" not in text:
        raise ConfigError(f"--set {text}: expected key=value, e.g. model.orders=[2,2]")
    key, value = text.split("=", 1)
    key = key.strip()
    parts = key.split(".")
    if not key or not all(parts):
        raise ConfigError(f"--set {text}: expected a dotted key such as train.max_time, got {key!r}")
    try:
        parsed = tomllib.loads(f"v = {value.strip()}")["v"]
    except tomllib.TOMLDecodeError:
        if not re.fullmatch(r"[\w.:/*+-]+", value.strip()):
            raise ConfigError(f"--set {key}: {value!r} is not a TOML value (quote strings)") from None
        parsed = value.strip()
    return parts, parsed


def _apply_override(raw: dict[str, Any], text: str, overridden: set[str]) -> None:
    parts, value = parse_override(text)
    table = parts[0]
    if table not in _TABLES:
        raise ConfigError(
            f"--set {'.'.join(parts)}: unknown table {table!r}{_closest(table, list(_TABLES))} "
            f"(tables: {', '.join(_TABLES)})"
        )
    if table == "serve":
        if len(parts) != 3:
            raise ConfigError(f"--set {'.'.join(parts)}: expected serve.<task name>.<key>")
        tasks = raw.get("serve", [])
        names = [t.get("name") for t in tasks if isinstance(t, dict)]
        if parts[1] not in names:
            raise ConfigError(
                f"--set {'.'.join(parts)}: no serving task named {parts[1]!r}"
                f"{_closest(parts[1], [str(n) for n in names])} (tasks: {names})"
            )
        i = names.index(parts[1])
        tasks[i][parts[2]] = value
        overridden.add(f"serve[{i}].{parts[2]}")
        return
    if len(parts) != 2:
        raise ConfigError(f"--set {'.'.join(parts)}: expected <table>.<key>, e.g. train.max_time=10")
    tab = raw.setdefault(table, {})
    if not isinstance(tab, dict):
        raise ConfigError(f"--set {'.'.join(parts)}: [{table}] is not a table")
    tab[parts[1]] = value
    overridden.add(f"{table}.{parts[1]}")


def load_case(case: str | os.PathLike[str], overrides: list[str] | tuple[str, ...] = ()) -> Case:
    """Read and validate ``CASE/case.toml`` (``case`` may also name the file itself).

    ``overrides`` are ``--set`` strings such as ``"model.orders=[2,2]"``; they
    are checked like keys of the file and kept in :attr:`Case.overrides`.
    """
    path = Path(case)
    if path.is_dir():
        root, file = path, path / CASE_FILE
    elif path.name.endswith(".toml"):
        root, file = path.parent, path
    else:
        root, file = path, path / CASE_FILE
    if not root.is_dir():
        raise ConfigError(f"{root}: case folder not found")
    if not file.is_file():
        raise ConfigError(f"{file}: file not found; a case folder holds a {CASE_FILE}")
    try:
        raw = tomllib.loads(file.read_text(encoding="utf-8"))
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{file}: not valid TOML ({' '.join(str(exc).split())})") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"{file}: cannot read ({type(exc).__name__}: {exc})") from None
    overridden: set[str] = set()
    for text in overrides:
        _apply_override(raw, text, overridden)
    return _validate(raw, root, file, tuple(overrides), overridden)


def _validate(raw: dict[str, Any], root: Path, file: Path, overrides: tuple[str, ...], overridden: set[str]) -> Case:
    ctx = _Ctx(CASE_FILE if file.name == CASE_FILE else file.name, overridden)
    for key in raw:
        if key not in _TABLES:
            raise ctx.error(key, f"unknown table{_closest(key, list(_TABLES))} (tables: {', '.join(_TABLES)})")
    # [field]
    fld = _table(ctx, raw, "field", SCHEMA["field"])
    field_cfg = FieldConfig(
        variable=fld["variable"], components=tuple(fld["components"]) if fld["components"] is not None else None
    )
    # [model]
    mraw = raw.get("model", {})
    if not isinstance(mraw, dict):
        raise ctx.error("model", f"expected a table [model], got {_describe(mraw)}")
    kind = ctx.check("model.kind", t_str, mraw.get("kind", "polynomial"))
    if kind not in MODELS:
        raise ctx.error(
            "model.kind",
            f"unknown model kind {kind!r}{_closest(kind, sorted(MODELS))} (expected one of {sorted(MODELS)})",
        )
    valid = model_options(kind)
    options: dict[str, Any] = {}
    for key, value in mraw.items():
        if key in ("kind", "stencil"):
            continue
        if key not in valid:
            keys = ["kind", "stencil", *valid]
            others = [k for k in MODELS if k != kind and key in model_options(k)]
            hint = f" (it is an option of kind {others[0]!r})" if others else ""
            raise ctx.error(
                f"model.{key}",
                f"unknown option of model kind {kind!r}{_closest(key, keys)}{hint} (valid keys: {', '.join(keys)})",
            )
        options[key] = ctx.check(f"model.{key}", model_option_check(kind, key), value)
    stencil = ctx.check("model.stencil", t_stencil, mraw["stencil"]) if "stencil" in mraw else None
    model_cfg = ModelConfig(kind=kind, options=options, stencil=stencil)
    try:  # the class's own checks of its options (e.g. an unknown activation), before any data are read
        MODELS[kind](**options)
    except LatticeDFTError as exc:
        raise ctx.error(f"model.{exc.key}" if exc.key else "model", exc.problem) from None
    except TypeError as exc:
        raise ctx.error("model", f"bad options for kind {kind!r} ({exc})") from None
    # [train]
    if "train" not in raw:
        raise ctx.error("train", 'missing table [train] (with data = ["data/train.nc"])')
    tr = _table(ctx, raw, "train", SCHEMA["train"])
    files: list[Path] = []
    for pat in tr["data"]:
        full = pat if Path(pat).is_absolute() else str(root / pat)
        if glob.has_magic(pat):
            found = sorted(Path(p) for p in glob.glob(full) if Path(p).is_file())
            if not found:
                raise ctx.error("train.data", f"no file matches {pat!r}")
            files.extend(found)
        else:
            files.append(_resolve(ctx, root, "train.data", pat))
    if not files:
        raise ctx.error("train.data", "expected at least one training file")
    learn_kw = {k: v for k, v in tr.items() if k not in ("data", "boundary")}
    train_cfg = TrainConfig(
        data=tuple(dict.fromkeys(files)), patterns=tuple(tr["data"]), boundary=tr["boundary"], learn=learn_kw
    )
    # [[serve]]
    sraw = raw.get("serve", [])
    if isinstance(sraw, dict):
        raise ctx.error("serve", "expected [[serve]] entries (an array of tables), got a single [serve] table")
    if not isinstance(sraw, list):
        raise ctx.error("serve", f"expected [[serve]] entries, got {_describe(sraw)}")
    tasks: list[ServeTask] = []
    names: set[str] = set()
    for i, entry in enumerate(sraw):
        label = f"serve[{i}]"
        if not isinstance(entry, dict):
            raise ctx.error(label, f"expected a table, got {_describe(entry)}")
        s = _table(ctx, entry, label, SCHEMA["serve"], label=label)
        if s["name"] in names:
            raise ctx.error(f"{label}.name", f"duplicate task name {s['name']!r}")
        names.add(s["name"])
        tasks.append(
            ServeTask(
                name=s["name"],
                source=_resolve(ctx, root, f"{label}.from", s["from"]),
                steps=s["steps"],
                boundary=s["boundary"],
                mode=s["mode"],
                box=s["box"],
                rtol=s["rtol"],
                max_newton=s["max_newton"],
                reference=_resolve(ctx, root, f"{label}.reference", s["reference"]) if s["reference"] else None,
                baseline=_resolve(ctx, root, f"{label}.baseline", s["baseline"]) if s["baseline"] else None,
                invariant=s["invariant"],
                label=label,
            )
        )
        if s["steps"] is not None and s["steps"] < 3:
            raise ctx.error(
                f"{label}.steps", f"expected at least 3 (the two initial slices and one served), got {s['steps']}"
            )
    # [run], [export]
    rn = _table(ctx, raw, "run", SCHEMA["run"])
    run_cfg = RunConfig(threads=rn["threads"] or max(1, min(2, os.cpu_count() or 1)))
    export_cfg = _export_config(ctx, _table(ctx, raw, "export", SCHEMA["export"]))
    return Case(
        root=root,
        field=field_cfg,
        model=model_cfg,
        train=train_cfg,
        serve=tuple(tasks),
        run=run_cfg,
        export=export_cfg,
        raw=raw,
        overrides=overrides,
    )


def _export_config(ctx: _Ctx, ex: dict[str, Any]) -> ExportConfig:
    """``formats`` checked against the registry; the aliases ``paraview``/``figures`` add or remove their format.

    An alias that contradicts an explicit ``formats`` is an error, unless one of the two comes from
    ``--set`` (the override wins).
    """
    from .io.exporters import DEFAULT_FORMATS, EXPORTERS

    given = ex["formats"] is not None
    formats = list(ex["formats"]) if given else list(DEFAULT_FORMATS)
    for i, fmt in enumerate(formats):
        if fmt not in EXPORTERS:
            raise ctx.error(
                "export.formats",
                f"unknown format {fmt!r}{_closest(fmt, list(EXPORTERS))} (formats: {', '.join(EXPORTERS)})",
            )
        if fmt in formats[:i]:
            raise ctx.error("export.formats", f"format {fmt!r} listed twice")
    for alias in ("paraview", "figures"):
        on = ex[alias]
        if on is None or on == (alias in formats):
            continue
        if given:
            alias_set, formats_set = f"export.{alias}" in ctx.overridden, "export.formats" in ctx.overridden
            if alias_set == formats_set:
                raise ctx.error(
                    f"export.{alias}",
                    f"{'true' if on else 'false'} contradicts export.formats = {ex['formats']!r}; set one of them",
                )
            if formats_set:
                continue
        if on:
            formats.append(alias)
        else:
            formats.remove(alias)
    return ExportConfig(formats=tuple(formats), max_frames=ex["max_frames"])


def load_invariant(spec: str, root: Path) -> Callable[[Any], Any]:
    """Import ``module:function`` (modules in the case folder are found too)."""
    module, _, name = spec.partition(":")
    added = str(root.resolve())
    sys.path.insert(0, added)
    try:
        mod = importlib.import_module(module)
    except Exception as exc:
        raise ConfigError(
            f"invariant {spec!r}: cannot import module {module!r} ({type(exc).__name__}: "
            f"{' '.join(str(exc).split())[:120]})"
        ) from None
    finally:
        with contextlib.suppress(ValueError):
            sys.path.remove(added)
    fn = getattr(mod, name, None)
    if not callable(fn):
        raise ConfigError(f"invariant {spec!r}: module {module!r} has no function {name!r}")
    return fn
