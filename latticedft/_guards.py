"""Checks made before anything is written: what a case reads, file-name limits, memory.

Each check raises a one-line :class:`latticedft.ConfigError` naming the key at
fault; ``latticedft check`` runs them all, ``run``, ``train`` and ``serve``
run those of their stages before training or serving.

- :func:`case_inputs`: the files and folders a case reads (the results folder
  must not be, contain or lie inside any of them).
- :func:`check_file_names`: every file a task may get (its ``.nc`` and the files
  of every registered export format, with their temporary names) fits the file
  system's limit on the length of a file name (``NAME_MAX``, 255 bytes on
  most file systems).
- :func:`check_model_size`: a lower bound of the model's parameters (with their
  gradients) fits the memory available.
- :func:`check_task_memory`: each task's served field, its aligned reference,
  its error and the copy made to write it fit the memory available.
"""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Any

from ._case import CASE_FILE, Case
from ._errors import ConfigError
from ._models import MODELS
from .io.exporters import TEMPORARY_NAME_EXTRA, export_file_names

__all__ = [
    "available_memory",
    "case_inputs",
    "check_before_writing",
    "check_file_names",
    "check_model_size",
    "check_task_memory",
    "name_max",
]

_STAGING_EXTRA = len(".tmp-old-") + 10  # the results folder's staging siblings: DEST.tmp-old-<10 hex>


def case_inputs(case: Case) -> list[Path]:
    """The files and folders case ``case`` reads: ``data/``, ``case.toml``, the training files, each task's
    initial field, reference and baseline, and the invariant modules found in the case folder."""
    paths = [case.root / "data", case.root / CASE_FILE, *case.train.data]
    for t in case.serve:
        paths += [p for p in (t.source, t.reference, t.baseline) if p is not None]
        if t.invariant:
            top = t.invariant.partition(":")[0].split(".")[0]
            paths += [p for p in (case.root / f"{top}.py", case.root / top) if p.exists()]
    return list(dict.fromkeys(paths))


def _where(case: Case, override: str) -> str:
    """``--set`` when an override set the key ``override`` (``serve.*.KEY``: any task's KEY), else
    ``case.toml``."""
    for o in case.overrides:
        key = o.split("=", 1)[0].strip()
        parts, want = key.split("."), override.split(".")
        if len(parts) == len(want) and all(w in ("*", k) for w, k in zip(want, parts)):
            return "--set"
    return "case.toml"


def _bytes(n: float) -> str:
    for unit, size in (("TB", 1e12), ("GB", 1e9), ("MB", 1e6), ("kB", 1e3)):
        if n >= size:
            return f"{n / size:.1f} {unit}"
    return f"{int(n)} bytes"


def _existing(folder: Path) -> Path:
    p = Path(os.path.abspath(folder))
    while not p.exists() and p != p.parent:
        p = p.parent
    return p


def name_max(folder: str | os.PathLike[str]) -> int:
    """The longest file name (bytes) the file system of ``folder`` (or its nearest existing parent) allows."""
    try:
        return int(os.pathconf(_existing(Path(folder)), "PC_NAME_MAX"))
    except (OSError, ValueError, AttributeError):  # no pathconf (Windows) or no answer: the common limit
        return 255


def check_file_names(case: Case, data: Any, dest: Path) -> None:
    """Refuse a task name whose longest file (export formats of every kind, temporary names included) or a
    results folder whose staging folder would not fit the file system's limit on file names."""
    limit = name_max(dest.parent)
    if len(dest.name.encode()) + _STAGING_EXTRA > limit:
        raise ConfigError(
            f"results folder {dest.name[:24]}...: its name of {len(dest.name.encode())} bytes leaves "
            f"no room for its staging folder's suffix ({_STAGING_EXTRA} bytes) within the "
            f"{limit}-byte limit on file names; choose a shorter --out"
        )
    for td in data.tasks:
        t = td.task
        names = [f"{t.name}.nc", *export_file_names(t.name, td.slices)]
        longest = max(names, key=lambda n: len(n.encode()))
        need = len(longest.encode()) + TEMPORARY_NAME_EXTRA
        if need > limit:
            room = limit - (need - len(t.name.encode()))
            shown = t.name if len(t.name) <= 24 else t.name[:21] + "..."
            raise ConfigError(
                f"{_where(case, 'serve.*.name')}: {t.label}.name: {shown!r} ({len(t.name.encode())} "
                f"bytes) is too long for its files: {longest[:12]}...{longest[-16:]} with its "
                f"temporary name needs {need} bytes, file names here hold at most {limit}; use a "
                f"name of at most {max(room, 0)} characters"
            )


def available_memory() -> int | None:
    """Bytes of memory available to this process: ``MemAvailable`` of /proc/meminfo, capped by a cgroup limit;
    else the free physical pages (``os.sysconf``); None when nothing says."""
    avail: int | None = None
    try:
        with open("/proc/meminfo", encoding="ascii") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    avail = int(line.split()[1]) * 1024
                    break
    except (OSError, ValueError, IndexError):
        pass
    if avail is None:
        try:
            avail = int(os.sysconf("SC_AVPHYS_PAGES")) * int(os.sysconf("SC_PAGE_SIZE"))
        except (OSError, ValueError, AttributeError):
            return None
    for limit_file, used_file in (
        ("/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory.current"),
        ("/sys/fs/cgroup/memory/memory.limit_in_bytes", "/sys/fs/cgroup/memory/memory.usage_in_bytes"),
    ):
        try:
            limit = Path(limit_file).read_text().strip()
            used = Path(used_file).read_text().strip()
            if limit.isdigit() and used.isdigit() and int(limit) < 1 << 60:
                avail = min(avail, max(int(limit) - int(used), 0))
                break
        except OSError:
            continue
    return avail


def _parameter_lower_bound(case: Case, data: Any) -> tuple[int, str] | None:
    """(a lower bound of the parameter count, the key that sets it) of the case's model, or None: its kind's
    :meth:`~latticedft.AbstractLagrangian.parameter_lower_bound`."""
    kind = MODELS.get(case.model.kind)
    if kind is None:  # the case reader reports it
        return None
    m = len(data.components) if data.components else 1
    return kind.parameter_lower_bound(case.model.options, len(data.dims), m)


def check_model_size(case: Case, data: Any, available: int | None = None) -> None:
    """Refuse a model whose parameters alone (8 bytes each, twice: values and gradients) exceed the memory."""
    found = _parameter_lower_bound(case, data)
    available = available_memory() if available is None else available
    if found is None or available is None:
        return
    count, key = found
    need = count * 8 * 2
    if need > available:
        value = case.model.options.get(key.split(".")[1])
        raise ConfigError(
            f"{_where(case, key)}: {key}: {value!r} means at least {count:.3g} parameters, "
            f"{_bytes(need)} with their gradients, but {_bytes(available)} of memory is available; "
            "choose a smaller model"
        )


def check_task_memory(case: Case, data: Any, available: int | None = None) -> None:
    """Refuse a task whose served field, with its reference, error and write copy, exceeds the memory."""
    available = available_memory() if available is None else available
    if available is None:
        return
    for td in data.tasks:
        t = td.task
        held = t.cadence.kept_count(td.slices)  # with an output cadence: the kept slices
        values = held * math.prod(int(s) for s in td.init.shape[1:])
        covered = td.reference is not None and td.reference.shape[0] >= td.slices  # then _ref and _err are written
        copies = 4 if covered else 2
        members = int(case.train.learn.get("ensemble") or 1)
        copies += 2 * members + 2 if members > 1 else 0  # the stacked members, their split copy, mean and std
        need = values * 8 * copies
        if need > available:
            name = "steps" if t.deprecated_steps else "slices"
            key = f"{t.label}.{name}" if t.slices is not None else f"{t.label}.from"
            raise ConfigError(
                f"{_where(case, f'serve.{t.name}.{name}')}: {key}: task {t.name!r} needs about "
                f"{_bytes(need)} of memory ({held} {'kept ' if t.cadence.thins else ''}slices of {values // held} "
                "values, 8 bytes "
                f"each, {copies} copies: the served field"
                + (", its reference, its error" if covered else "")
                + (f", {members} ensemble members (twice), their mean and std" if members > 1 else "")
                + f" and the copy written to disk) but {_bytes(available)} is available; "
                "serve fewer slices"
            )


def check_before_writing(case: Case, data: Any, dest: Path, *, train: bool = True, serve: bool = True) -> None:
    """The checks of the stages a command runs: file names always, the model's size before training, each
    task's memory before serving."""
    check_file_names(case, data, dest)
    available = available_memory()
    if train:
        check_model_size(case, data, available)
    if serve:
        check_task_memory(case, data, available)
