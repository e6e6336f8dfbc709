"""Reading case.toml: tables checked against the schema, --set overrides, paths resolved, one-line errors."""

from __future__ import annotations

import contextlib
import difflib
import glob
import importlib
import os
import re
import sys
import tomllib
from collections.abc import Callable
from pathlib import Path
from typing import Any

from .._errors import ConfigError, LatticeDFTError
from .._models import MODELS
from .._serve import ServeOptions
from ..io.exporters import DEFAULT_FORMATS, format_names, known_format
from . import _schema
from ._checks import _Bad, t_ridge, t_stencil, t_str
from ._schema import (
    _REQUIRED,
    _SLICES_ALIASES,
    _TABLES,
    CASE_FILE,
    DEFAULT_THREADS,
    SCHEMA,
    Case,
    ExportConfig,
    FieldConfig,
    ModelConfig,
    RunConfig,
    ServeTask,
    TrainConfig,
    model_option_check,
    model_options,
)


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
        if parts[2] in _SLICES_ALIASES:  # an override of either name replaces the file's count
            for alias in _SLICES_ALIASES:
                tasks[i].pop(alias, None)
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
    """The case of ``raw`` (parsed case.toml), table by table in the order of its errors' precedence."""
    ctx = _Ctx(CASE_FILE if file.name == CASE_FILE else file.name, overridden)
    for key in raw:
        if key not in _TABLES:
            raise ctx.error(key, f"unknown table{_closest(key, list(_TABLES))} (tables: {', '.join(_TABLES)})")
    fld = _table(ctx, raw, "field", SCHEMA["field"])
    field_cfg = FieldConfig(
        variable=fld["variable"], components=tuple(fld["components"]) if fld["components"] is not None else None
    )
    model_cfg = _model_config(ctx, raw)
    train_cfg = _train_config(ctx, raw, root)
    tasks = _serve_tasks(ctx, raw, root)
    rn = _table(ctx, raw, "run", SCHEMA["run"])
    run_cfg = RunConfig(threads=rn["threads"] or DEFAULT_THREADS, device=rn["device"], strict=rn["strict"])
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


def _known_kind(ctx: _Ctx, key: str, kind: str) -> bool:
    """True when ``kind`` is a registered model kind, or one another package gives (an import path or an entry
    point, loaded now); a kind that fails to load is an error about ``key``."""
    try:
        return kind in MODELS
    except LatticeDFTError as exc:
        raise ctx.error(key, exc.problem) from None


def _select_config(ctx: _Ctx, value: Any, kind: str) -> str | tuple[dict[str, Any], ...]:
    """``[model] select``: ``"auto"`` or a list of candidate tables (a ``kind``, ``ridge`` and model options)."""
    if value == "auto":
        return "auto"
    if not isinstance(value, list) or not value or not all(isinstance(c, dict) for c in value):
        raise ctx.error(
            "model.select",
            f'expected "auto" or a list of candidate tables, e.g. [{{orders = [2, 2]}}], got {_describe(value)}',
        )
    out = []
    for i, cand in enumerate(value):
        where = f"model.select[{i}]"
        ckind = ctx.check(f"{where}.kind", t_str, cand.get("kind", kind))
        if not _known_kind(ctx, f"{where}.kind", ckind):
            raise ctx.error(f"{where}.kind", f"unknown model kind {ckind!r}{_closest(ckind, MODELS.names())}")
        valid = model_options(ckind)
        checked: dict[str, Any] = {"kind": ckind} if "kind" in cand else {}
        for key, v in cand.items():
            if key == "kind":
                continue
            if key == "ridge":
                checked[key] = ctx.check(f"{where}.ridge", t_ridge, v)
            elif key in valid:
                checked[key] = ctx.check(f"{where}.{key}", model_option_check(ckind, key), v)
            else:
                keys = ["kind", "ridge", *valid]
                raise ctx.error(
                    f"{where}.{key}",
                    f"unknown key of a {ckind!r} candidate{_closest(key, keys)} (valid: {', '.join(keys)})",
                )
        try:
            MODELS[ckind](**{k: v for k, v in checked.items() if k not in ("kind", "ridge")})
        except LatticeDFTError as exc:
            raise ctx.error(f"{where}.{exc.key}" if exc.key else where, exc.problem) from None
        out.append(checked)
    return tuple(out)


def _model_config(ctx: _Ctx, raw: dict[str, Any]) -> ModelConfig:
    """``[model]``: the kind, its options (types from the constructor) and the stencil."""
    mraw = raw.get("model", {})
    if not isinstance(mraw, dict):
        raise ctx.error("model", f"expected a table [model], got {_describe(mraw)}")
    kind = ctx.check("model.kind", t_str, mraw.get("kind", "polynomial"))
    if not _known_kind(ctx, "model.kind", kind):
        raise ctx.error(
            "model.kind",
            f"unknown model kind {kind!r}{_closest(kind, MODELS.names())} (expected one of {MODELS.names()})",
        )
    valid = model_options(kind)
    options: dict[str, Any] = {}
    for key, value in mraw.items():
        if key in ("kind", "stencil", "select"):
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
    select = _select_config(ctx, mraw["select"], kind) if "select" in mraw else None
    model_cfg = ModelConfig(kind=kind, options=options, stencil=stencil, select=select)
    try:  # the class's own checks of its options (e.g. an unknown activation), before any data are read
        MODELS[kind](**options)
    except LatticeDFTError as exc:
        raise ctx.error(f"model.{exc.key}" if exc.key else "model", exc.problem) from None
    except TypeError as exc:
        raise ctx.error("model", f"bad options for kind {kind!r} ({exc})") from None
    return model_cfg


def _train_config(ctx: _Ctx, raw: dict[str, Any], root: Path) -> TrainConfig:
    """``[train]``: the training files (globs resolved) and the keywords of ``learn``."""
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
    learn_kw = {k: v for k, v in tr.items() if k not in ("data", "boundary", "calibrate")}
    return TrainConfig(
        data=tuple(dict.fromkeys(files)),
        patterns=tuple(tr["data"]),
        boundary=tr["boundary"],
        learn=learn_kw,
        calibrate=tr["calibrate"],
    )


def _serve_tasks(ctx: _Ctx, raw: dict[str, Any], root: Path) -> list[ServeTask]:
    """``[[serve]]``: the tasks, names unique."""
    sraw = raw.get("serve", [])
    if isinstance(sraw, dict):
        raise ctx.error("serve", "expected [[serve]] entries (an array of tables), got a single [serve] table")
    if not isinstance(sraw, list):
        raise ctx.error("serve", f"expected [[serve]] entries, got {_describe(sraw)}")
    tasks: list[ServeTask] = []
    names: set[str] = set()
    for i, entry in enumerate(sraw):
        tasks.append(_serve_task(ctx, entry, i, root, names))
    return tasks


def _serve_task(ctx: _Ctx, entry: Any, i: int, root: Path, names: set[str]) -> ServeTask:
    """One ``[[serve]]`` entry (its name is added to ``names``)."""
    label = f"serve[{i}]"
    if not isinstance(entry, dict):
        raise ctx.error(label, f"expected a table, got {_describe(entry)}")
    s = _table(ctx, entry, label, _schema.serve_schema(), label=label)
    if s["name"] in names:
        raise ctx.error(f"{label}.name", f"duplicate task name {s['name']!r}")
    names.add(s["name"])
    if s["steps"] is not None and s["slices"] is not None:
        raise ctx.error(f"{label}.steps", "give slices only (steps is its deprecated alias, the same count)")
    slices_key = "steps" if s["steps"] is not None else "slices"
    slices = s[slices_key]
    if slices is not None and slices < 3:
        raise ctx.error(
            f"{label}.{slices_key}",
            f"expected at least 3 (time slices: the two initial ones and one served), got {slices}",
        )
    return ServeTask(
        name=s["name"],
        source=_resolve(ctx, root, f"{label}.from", s["from"]),
        slices=slices,
        boundary=s["boundary"],
        options=_serve_options(ctx, s, label),
        reference=_resolve(ctx, root, f"{label}.reference", s["reference"]) if s["reference"] else None,
        baseline=_resolve(ctx, root, f"{label}.baseline", s["baseline"]) if s["baseline"] else None,
        invariant=s["invariant"],
        charges=tuple(s["charges"] or ()),
        start=s["start"],
        label=label,
        deprecated_steps=slices_key == "steps",
    )


def _serve_options(ctx: _Ctx, s: dict[str, Any], label: str) -> ServeOptions:
    """The serving options of a checked ``[[serve]]`` entry ``s`` (its keys that are fields of ServeOptions)."""
    options = _schema.SERVE_OPTIONS
    try:
        return options(**{key: s[key] for key in options.case_keys()})
    except LatticeDFTError as exc:  # the options' own checks, beyond the types
        raise ctx.error(f"{label}.{exc.key}" if exc.key else label, exc.problem) from None


def _known_format(ctx: _Ctx, fmt: str) -> bool:
    """True when ``fmt`` is an export format (see :func:`latticedft.io.exporters.known_format`)."""
    try:
        return known_format(fmt)
    except LatticeDFTError as exc:
        raise ctx.error("export.formats", exc.problem) from None


def _export_config(ctx: _Ctx, ex: dict[str, Any]) -> ExportConfig:
    """``formats`` checked against the registry; the aliases ``paraview``/``figures`` add or remove their format.

    An alias that contradicts an explicit ``formats`` is an error, unless one of the two comes from
    ``--set`` (the override wins).
    """
    given = ex["formats"] is not None
    formats = list(ex["formats"]) if given else list(DEFAULT_FORMATS)
    for i, fmt in enumerate(formats):
        if not _known_format(ctx, fmt):
            raise ctx.error(
                "export.formats",
                f"unknown format {fmt!r}{_closest(fmt, format_names())} (formats: {', '.join(format_names())})",
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


def load_invariant(spec: str, root: Path, what: str = "invariant") -> Callable[..., Any]:
    """Import ``module:function`` (modules in the case folder are found too); errors name the key ``what``."""
    module, _, name = spec.partition(":")
    added = str(root.resolve())
    sys.path.insert(0, added)
    try:
        mod = importlib.import_module(module)
    except Exception as exc:
        raise ConfigError(
            f"{what} {spec!r}: cannot import module {module!r} ({type(exc).__name__}: "
            f"{' '.join(str(exc).split())[:120]})"
        ) from None
    finally:
        with contextlib.suppress(ValueError):
            sys.path.remove(added)
    fn = getattr(mod, name, None)
    if not callable(fn):
        raise ConfigError(f"{what} {spec!r}: module {module!r} has no function {name!r}")
    return fn
