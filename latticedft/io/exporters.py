"""The export formats of a run, by name: ``[export] formats = ["paraview", "figures"]`` in case.toml.

Each format is one :class:`Exporter` subclass living in its own module, and one
line of :data:`EXPORTERS` (``name -> "module:Class"``, imported only when the
format is written, so reading a case imports neither pyvista nor matplotlib
nor meshio). An exporter writes the files of one serving task and returns the
exact list of files it wrote; the command line records that list in
``summary.json`` (``tasks.<name>.exports``) and, before the next export of the
same task, deletes exactly those files (:func:`remove_exports`), never files
found by a name pattern.

A new format is a module with its exporter, e.g. ``latticedft/io/xdmf.py``::

    class XdmfExporter(Exporter):
        name = "xdmf"
        summary = "..."

        def write(self, task: ExportTask) -> list[Path]:
            return write_xdmf(task.folder, task.name, task.field, task.extra, max_frames=task.max_frames)

plus its line in :data:`EXPORTERS` and the names of its files in :data:`EXPORT_FILES`
(``latticedft check`` checks with them that every file of a task fits the file system's limit on
file names, whichever format a later ``export`` picks).

A format from another package needs no line here: ``formats = ["mypkg.export:MyExporter"]`` (an import
path) or the name of an entry point of group ``latticedft.exporters`` (:mod:`latticedft._plugins`) names
its :class:`Exporter` subclass, which lists the names of its files in :attr:`Exporter.files`. It is
loaded when a case names it, and kept under that name.

>>> sorted(EXPORTERS)
['figures', 'paraview', 'xdmf']
>>> get_exporter("xdmf").name
'xdmf'
"""

from __future__ import annotations

import importlib
import logging
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from dataclasses import field as _field
from pathlib import Path
from typing import Any, ClassVar

import xarray as xr

from latticedft._errors import InputError
from latticedft._plugins import EXPORTER_GROUP, describe, entry_point_names, load

__all__ = [
    "EXPORTERS",
    "EXPORT_FILES",
    "DEFAULT_FORMATS",
    "Exporter",
    "ExportTask",
    "get_exporter",
    "export_formats",
    "remove_exports",
    "export_file_names",
    "known_format",
    "format_names",
    "TEMPORARY_NAME_EXTRA",
]

log = logging.getLogger("latticedft")

#: Every export format: name -> ``"module:Class"`` of its :class:`Exporter`.
EXPORTERS: dict[str, str] = {
    "paraview": "latticedft.io.vtk:ParaViewExporter",
    "figures": "latticedft.io.figures:FigureExporter",
    "xdmf": "latticedft.io.xdmf:XdmfExporter",
}

#: The files each format may write for a task ``{name}``; ``{frame}`` is a slice number zero-padded to
#: ``max(4, digits of the last slice)`` (:func:`export_file_names`). Every format of :data:`EXPORTERS` has
#: its line; the test suite checks the exporters against it.
EXPORT_FILES: dict[str, tuple[str, ...]] = {
    "paraview": (
        "{name}.pvd",
        "{name}_{frame}.vtr",
        "{name}_{frame}.vtp",
        "{name}_spacetime.vtr",
        "{name}.vtp",
        "{name}_view.py",
    ),
    "figures": ("{name}.png",),
    "xdmf": ("{name}.xdmf", "{name}.h5"),
}

#: The most characters a writer adds to a file's name for its temporary file (``.<file>.<12 hex>.tmp``),
#: which is renamed to the file once written.
TEMPORARY_NAME_EXTRA = 18

#: The formats written when case.toml names none.
DEFAULT_FORMATS: tuple[str, ...] = ("paraview", "figures")

# Files of a results folder that no export owns, whatever a summary says.
_NOT_EXPORTS = frozenset({"model.pt", "model.json", "summary.json", "run.log", ".latticedft-results"})


@dataclass(frozen=True)
class ExportTask:
    """What an exporter gets: one served task and the export options.

    ``field`` is the served field, named after the case's variable (``psi``);
    ``reference`` and ``error`` (``field - reference``) lie on the same slices
    when a reference covers them, else they are None. ``series`` are the task
    file's other variables over time only (``invariant``, ``energy``,
    ``charge_<name>``, ``baseline_err_max`` ...) and ``attrs`` its global
    attributes (``latticedft_complete``, ``latticedft_steps``,
    ``latticedft_stopped_at_slice``, ``latticedft_stop_reason``,
    ``latticedft_warnings`` ...); both are empty when the task has no file.
    Every file an exporter writes goes into ``folder`` and starts with ``name``.
    """

    folder: Path
    name: str
    field: xr.DataArray
    reference: xr.DataArray | None = None
    error: xr.DataArray | None = None
    max_frames: int | None = None
    train: tuple[xr.DataArray, ...] | None = None
    title: str | None = None
    attrs: Mapping[str, Any] = _field(default_factory=dict)
    series: Mapping[str, xr.DataArray] = _field(default_factory=dict)
    #: An ensemble served: the standard deviation over its members (``<var>_std``), in the field's layout.
    spread: xr.DataArray | None = None

    @property
    def variable(self) -> str:
        return str(self.field.name) if self.field.name is not None else "psi"

    @property
    def extra(self) -> dict[str, xr.DataArray]:
        """``{"<var>_ref": reference, "<var>_err": error}`` when both are known, and ``"<var>_std"`` for an
        ensemble (else ``{}``): the arrays written beside the field."""
        out = {}
        if self.reference is not None and self.error is not None:
            out = {f"{self.variable}_ref": self.reference, f"{self.variable}_err": self.error}
        if self.spread is not None:
            out[f"{self.variable}_std"] = self.spread
        return out


class Exporter:
    """One export format: :attr:`name` (its key in :data:`EXPORTERS`), a one-line :attr:`summary`
    and :meth:`write`."""

    name: ClassVar[str] = ""
    summary: ClassVar[str] = ""
    #: The names of the files it may write, as in :data:`EXPORT_FILES` (which holds those of latticedft's own
    #: formats, so that checking names imports none of them): read for a format from another package.
    files: ClassVar[tuple[str, ...]] = ()

    def write(self, task: ExportTask) -> list[Path]:
        """Write the files of ``task`` into ``task.folder``; return exactly the files written."""
        raise NotImplementedError

    def __repr__(self) -> str:
        return f"<exporter {self.name!r}>"


#: The formats from other packages loaded so far: name (as a case names it) -> :class:`Exporter` subclass.
_PLUGINS: dict[str, type[Exporter]] = {}


def _plugin(name: str) -> type[Exporter] | None:
    """The exporter class another package gives for ``name`` (loaded now, then kept), or None when none does;
    a one-line InputError about ``export.formats`` when it fails to load or is no Exporter subclass."""
    if name not in _PLUGINS:
        found = load(name, EXPORTER_GROUP, "export.formats")
        if found is None:
            return None
        if not (isinstance(found, type) and issubclass(found, Exporter)):
            raise InputError.at(
                "export.formats",
                f"{name!r} gives {describe(found)}; expected a subclass of latticedft.io.exporters.Exporter",
            )
        _PLUGINS[name] = found
    return _PLUGINS[name]


def known_format(name: str) -> bool:
    """True when ``name`` is an export format: one of :data:`EXPORTERS`, or one another package gives (loaded
    now; a one-line InputError when it fails to load)."""
    return name in EXPORTERS or _plugin(name) is not None


def format_names() -> list[str]:
    """The formats a case may name without an import path: :data:`EXPORTERS`, then those of other packages
    (loaded, or entry points not loaded yet); for messages about an unknown format."""
    return list(dict.fromkeys([*EXPORTERS, *_PLUGINS, *entry_point_names(EXPORTER_GROUP)]))


def get_exporter(name: str) -> Exporter:
    """The exporter of format ``name`` (its module is imported now)."""
    if name not in EXPORTERS:
        plugin = _plugin(name)
        if plugin is None:
            raise InputError(f"unknown export format {name!r} (formats: {', '.join(EXPORTERS)})")
        return plugin()
    module, _, cls = EXPORTERS[name].partition(":")
    exporter = getattr(importlib.import_module(module), cls)()
    if exporter.name != name:  # pragma: no cover - a registry line that names the wrong class
        raise RuntimeError(f"EXPORTERS[{name!r}] names an exporter called {exporter.name!r}")
    return exporter


def export_formats(task: ExportTask, formats: Sequence[str]) -> list[Path]:
    """Write ``task`` in every format of ``formats`` (in that order); the files written, each once."""
    written: list[Path] = []
    for fmt in formats:
        files = get_exporter(fmt).write(task)
        for p in files:
            log.debug("wrote %s (%s)", p.name, fmt)
        written += [p for p in files if p not in written]
    return written


def _patterns(fmt: str) -> tuple[str, ...]:
    """The file names format ``fmt`` may write (see :data:`EXPORT_FILES`)."""
    if fmt in EXPORT_FILES:
        return EXPORT_FILES[fmt]
    cls = _plugin(fmt)
    return cls.files if cls is not None else ()


def export_file_names(name: str, slices: int, formats: Iterable[str] | None = None) -> list[str]:
    """The names of every file the formats (default: every registered one, and those loaded from other
    packages) may write for task ``name`` of ``slices`` time slices.

    >>> export_file_names("test", 401, ["paraview"])[:2]
    ['test.pvd', 'test_0400.vtr']
    """
    last = max(int(slices), 1) - 1
    frame = f"{last:0{max(4, len(str(last)))}d}"  # the longest frame name: the last slice's
    names: list[str] = []
    for fmt in [*EXPORTERS, *_PLUGINS] if formats is None else formats:
        names += [
            p.format(name=name, frame=frame) for p in _patterns(fmt) if p.format(name=name, frame=frame) not in names
        ]
    return names


def remove_exports(folder: Path, names: Iterable[str]) -> list[str]:
    """Delete the files ``names`` (plain file names recorded by an earlier export) from ``folder``.

    Names that are not plain file names, that a task or the model owns
    (``*.nc``, ``model.pt``, ``summary.json`` ...) or that no longer exist are
    skipped. Returns the names deleted.
    """
    removed = []
    for name in names:
        if (
            not isinstance(name, str)
            or not name
            or Path(name).name != name
            or name in (".", "..")
            or name in _NOT_EXPORTS
            or name.endswith(".nc")
        ):
            log.debug("not removing %r: not an export file", name)
            continue
        path = Path(folder) / name
        if path.is_file() and not path.is_symlink():
            path.unlink()
            removed.append(name)
    return removed
