"""Case directories: ``case.toml`` read into validated objects.

A case is a folder holding ``case.toml`` (the one file a user edits), its
observed fields in ``data/`` and, after a run, ``results/``. :func:`load_case`
reads the file, applies ``--set key=value`` overrides, checks every key and
type, resolves paths (relative to the case, globs allowed for training data)
and returns a frozen :class:`Case`. Every problem raises
:class:`latticedft.ConfigError` with a one-line message that names the key
(or file) and what was expected.

>>> import tempfile, pathlib
>>> from latticedft import ConfigError
>>> d = pathlib.Path(tempfile.mkdtemp())
>>> _ = (d / "case.toml").write_text('[model]\\nkind = "polynomal"\\n[train]\\ndata = []\\n')
>>> try:
...     load_case(d)
... except ConfigError as exc:
...     print(exc)  # doctest: +NORMALIZE_WHITESPACE
case.toml: model.kind: unknown model kind 'polynomal'; did you mean 'polynomial'?
(expected one of ['features', 'mlp', 'polynomial', 'sparse'])
"""

from __future__ import annotations

from .._boundary import boundary_kinds as boundary_kinds
from ._read import load_case as load_case
from ._read import load_invariant as load_invariant
from ._read import parse_override as parse_override
from ._schema import CASE_FILE as CASE_FILE
from ._schema import DEFAULT_THREADS as DEFAULT_THREADS
from ._schema import SCHEMA as SCHEMA
from ._schema import Case as Case
from ._schema import ExportConfig as ExportConfig
from ._schema import FieldConfig as FieldConfig
from ._schema import ModelConfig as ModelConfig
from ._schema import RunConfig as RunConfig
from ._schema import ServeTask as ServeTask
from ._schema import TrainConfig as TrainConfig
from ._schema import model_option_check as model_option_check
from ._schema import model_options as model_options

__all__ = [
    "CASE_FILE",
    "Case",
    "DEFAULT_THREADS",
    "ExportConfig",
    "FieldConfig",
    "ModelConfig",
    "RunConfig",
    "SCHEMA",
    "ServeTask",
    "TrainConfig",
    "load_case",
    "load_invariant",
    "model_option_check",
    "model_options",
    "parse_override",
]
