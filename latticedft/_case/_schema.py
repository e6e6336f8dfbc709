"""The case.toml schema (tables, keys, checks, defaults) and the validated objects a case becomes."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from .._errors import ConfigError, LatticeDFTError
from .._learn import GAUGES, OPTIMIZERS
from .._modeloptions import OptionTypeError
from .._models import MODELS, AbstractLagrangian
from .._serve import Cadence, ServeOptions
from .._stencil import Stencil
from ._checks import (
    _Bad,
    t_any,
    t_bool,
    t_boundary,
    t_calibrate,
    t_choice,
    t_device,
    t_ensemble,
    t_invariant,
    t_name,
    t_nonneg_float,
    t_nonneg_int,
    t_pos_float,
    t_pos_int,
    t_ridge,
    t_str,
    t_str_list,
    t_threads,
)

CASE_FILE = "case.toml"


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
        "gauge": (t_choice(*GAUGES), "auto"),
        "ridge": (t_ridge, 0.0),
        "optimizer": (t_choice(*OPTIMIZERS), None),
        "max_iter": (t_pos_int, 500),
        "max_time": (t_pos_float, None),
        "tol": (t_nonneg_float, 0.0),
        "rel_tol": (t_pos_float, None),
        "lr": (t_pos_float, 1e-3),
        "penalty": (t_nonneg_float, 1.0),
        "symmetries": (t_bool, False),
        "chunk_sites": (t_nonneg_int, None),
        "ensemble": (t_ensemble, None),
        "ensemble_seed": (t_nonneg_int, 0),
        "noise": (t_choice("none", "auto", "correct"), "none"),
        "noise_sigma": (t_nonneg_float, None),
        "calibrate": (t_calibrate, "auto"),
    },
    "serve": {
        "name": (t_name, _REQUIRED),
        "from": (t_str, _REQUIRED),
        "slices": (t_pos_int, None),
        "steps": (t_pos_int, None),  # deprecated alias of slices (the same count)
        "boundary": (t_boundary, None),
        "reference": (t_str, None),
        "baseline": (t_str, None),
        "invariant": (t_invariant, None),
        "charges": (t_str_list, None),
        "start": (t_choice("auto", "data", "denoised"), "auto"),
        # then the serving options: the fields of ServeOptions that are case keys (serve_schema)
    },
    "run": {
        "threads": (t_threads, None),
        "device": (t_device, "cpu"),
        "strict": (t_bool, False),
    },
    "export": {
        "formats": (t_str_list, None),  # None: latticedft.io.exporters.DEFAULT_FORMATS
        "paraview": (t_bool, None),  # alias: true adds "paraview" to formats, false removes it
        "figures": (t_bool, None),  # alias: the same for "figures"
        "max_frames": (t_pos_int, 200),
    },
}


_TABLES = ("field", "model", "train", "serve", "run", "export")


#: ``[run] threads`` when the case does not set it: one torch thread. Measured (``python -m benchmarks.threads``,
#: docs/performance.md): a second thread beside another busy process made cases/wave 17x slower, and on an
#: idle machine only slice-Newton gained (1.9x).
DEFAULT_THREADS = 1


#: ``[[serve]] slices`` and its deprecated alias ``steps``.
_SLICES_ALIASES = ("slices", "steps")


def _toml_check(check: Callable[[Any], Any]) -> Callable[[Any], Any]:
    """A check that raises :class:`OptionTypeError` as one that raises ``_Bad`` (the case reader's)."""

    def run(value: Any) -> Any:
        try:
            return check(value)
        except OptionTypeError as bad:
            raise _Bad(bad.expected) from None

    return run


#: The options class of ``[[serve]]`` tasks: its fields with a TOML check are keys of ``[[serve]]``.
SERVE_OPTIONS: type[ServeOptions] = ServeOptions

#: The keys of a ``[[serve]]`` table that describe the task rather than how it is served.
_TASK_KEYS = dict(SCHEMA["serve"])


def serve_schema() -> dict[str, tuple[Callable[[Any], Any], Any]]:
    """The keys of a ``[[serve]]`` table: the task's, then the serving options (key -> (check, default)) from
    the fields of :data:`SERVE_OPTIONS` (:meth:`ServeOptions.case_keys`)."""
    options = {key: (_toml_check(check), default) for key, (check, default) in SERVE_OPTIONS.case_keys().items()}
    return {**_TASK_KEYS, **options}


SCHEMA["serve"] = serve_schema()


def model_options(kind: str) -> dict[str, Any]:
    """The constructor options of ``MODELS[kind]`` with their defaults (``stencil`` excluded)."""
    return MODELS[kind].option_defaults()


def model_option_check(kind: str, option: str) -> Callable[[Any], Any]:
    """The type check of a ``[model]`` option, from the annotation of the model class's constructor."""
    return _toml_check(MODELS[kind].option_checks().get(option, t_any))


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
    #: ``select``: ``"auto"`` or candidate tables (option changes, ``kind``, ``ridge``); None: no selection.
    select: str | tuple[dict[str, Any], ...] | None = None

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
    #: ``calibrate``: error bars by held-out serving; ``"auto"``: with ``select``, ``ensemble`` or ``noise``.
    calibrate: bool | str = "auto"


@dataclass(frozen=True)
class ServeTask:
    """One ``[[serve]]`` entry with its paths resolved."""

    name: str
    source: Path
    slices: int | None = None
    boundary: str | dict[str, str] | None = None
    #: the serving options (``serve(..., options=...)``): the case's keys, the others their defaults
    options: ServeOptions = field(default_factory=ServeOptions)
    reference: Path | None = None
    baseline: Path | None = None
    invariant: str | None = None
    #: Noether charges (names of built-in continuous symmetries, "energy", "auto") measured along the served field.
    charges: tuple[str, ...] = ()
    label: str = "serve[0]"
    #: True when the file (or ``--set``) gave the deprecated key ``steps`` instead of ``slices``.
    deprecated_steps: bool = False
    #: Initial slices: ``data`` as read, ``denoised`` by the learned DEL, ``auto`` denoised when training
    #: corrected noisy data.
    start: str = "auto"

    @property
    def cadence(self) -> Cadence:
        """The output cadence: the task's file keeps the slices it keeps (``[[serve]] every``)."""
        return self.options.cadence


@dataclass(frozen=True)
class RunConfig:
    """``[run]``: threads of torch and the BLAS/OpenMP pools (default 1: measured fastest for the cases and far
    safer on a shared machine; ``python -m benchmarks.threads``, docs/performance.md)."""

    threads: int
    #: where training and serving evaluate the model (``learn``/``serve``'s ``device``); the command line
    #: replaces a CUDA request it cannot honour by ``"cpu"`` (one warning)
    device: str = "cpu"
    #: warnings (a poor or degenerate fit, extrapolation, an inaccurate task ...) make the exit status 4
    strict: bool = False


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
