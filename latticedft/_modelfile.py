"""Model files: a plain dict that loads with ``torch.load(..., weights_only=True)``."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path
from typing import Any

import torch

from ._contract import DEFAULT_GAUGE, parse_gauge
from ._errors import InputError, LatticeDFTError, ModelFileError, not_a_regular_file
from ._models import MODELS, AbstractLagrangian, EnsembleLagrangian, ModelKind
from ._plugins import MODEL_GROUP
from ._stencil import Stencil

__all__ = ["save_model", "load_model", "FORMAT_VERSION", "model_record"]

FORMAT_VERSION = 1


def model_record(model: AbstractLagrangian, gauge: str | None = None) -> dict[str, Any]:
    """Everything of a model file except ``state_dict`` (JSON-compatible); ``gauge`` default: the model's."""
    if not isinstance(model, AbstractLagrangian):
        raise InputError.at("model", f"expected a latticedft model, got {type(model).__name__}")
    if not model.saveable:
        raise ModelFileError(f"model: a {type(model).__name__} cannot be written to a model file")
    if model.has_functions:
        raise ModelFileError(
            "model: its feature library holds Python functions, which a model file cannot store; "
            "use the named features ('poly:K', 'trig:K', 'trig:K:w') to save it"
        )
    model._require_bound()
    return {
        "format": "latticedft-model",
        "format_version": FORMAT_VERSION,
        "kind": MODELS.name_of(model),
        "options": model.options(),
        "stencil": model.stencil.to_list(),
        "gauge": (parse_gauge(gauge) if gauge is not None else model.gauge or DEFAULT_GAUGE).value,
        "n": model.n,
        "m": model.m,
        "spacing": list(model.spacing),
        "components": list(model.components) if model.components else None,
    }


def save_model(model: AbstractLagrangian, path: str | os.PathLike[str], *, gauge: str | None = None) -> Path:
    """Write ``model`` to ``path`` (atomically: a temporary file, then a rename); the folder must exist."""
    if not isinstance(path, (str, os.PathLike)):
        raise InputError.at("path", f"expected a file path, got {type(path).__name__}")
    if gauge is not None and not isinstance(gauge, str):
        raise InputError.at("gauge", f"expected the name of the gauge the model was learned with, got {gauge!r}")
    record = model_record(model, gauge or None)
    record["state_dict"] = {k: v.detach().cpu().clone() for k, v in model.state_dict().items()}
    path = Path(path)
    folder = path.parent if str(path.parent) else Path(".")
    if not folder.is_dir():
        raise InputError(f"{path}: folder {folder} does not exist; expected an existing folder")
    if path.is_dir():
        raise InputError(f"{path}: is a folder; expected a model file path")
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.close(fd)
    try:
        torch.save(record, tmp)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def not_a_file(path: Path) -> str:
    """Why ``path`` (not a regular file) cannot be read as a file: missing, or what it is instead."""
    if not os.path.lexists(path):
        return "model file not found"
    if os.path.islink(path) and not path.exists():
        return f"a link to {os.readlink(path)}, which does not exist"
    return f"is {not_a_regular_file(path)}; expected a model file"


def _head(path: Path) -> bytes:
    with open(path, "rb") as f:
        return f.read(64)


def _kind(path: Path, kind: Any) -> ModelKind | type[EnsembleLagrangian]:
    """What builds a model of ``kind`` (a name a model file records); a one-line ModelFileError when no
    kind of that name is registered, given by an import path or by an installed package's entry point."""
    if kind == EnsembleLagrangian.kind:
        return EnsembleLagrangian
    try:
        if isinstance(kind, str):
            return MODELS[kind]
    except KeyError:
        pass
    except LatticeDFTError as exc:
        raise ModelFileError(f"{path}: model kind {kind!r}: {exc.problem}") from None
    raise ModelFileError(
        f"{path}: unknown model kind {kind!r}; expected one of {sorted([*MODELS, EnsembleLagrangian.kind])}, "
        f"an import path 'module:Class' or an entry point of group {MODEL_GROUP!r} (is its package installed?)"
    )


def load_model(path: str | os.PathLike[str]) -> AbstractLagrangian:
    """Read a model file written by :func:`save_model`; never unpickles arbitrary objects.

    >>> load_model("no-such-file.pt")
    Traceback (most recent call last):
    ...
    latticedft._errors.ModelFileError: no-such-file.pt: model file not found
    """
    if not isinstance(path, (str, os.PathLike)):
        raise InputError.at("path", f"expected a file path, got {type(path).__name__}")
    path = Path(path)
    if not path.is_file():
        raise ModelFileError(f"{path}: {not_a_file(path)}")
    head = _head(path)
    if head[:2] != b"PK" and head[:1] != b"\x80":  # neither torch's zip format nor a pickle
        raise ModelFileError(
            f"{path}: not a model file: expected a file written by latticedft (torch's zip format), "
            f"found one starting with {head[:16]!r}"
        )
    try:
        rec = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # corrupt zip, truncated file, or a pickled object refused by weights_only
        text = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        if "weights_only" in str(exc) or "Unsupported global" in str(exc) or "GLOBAL" in str(exc):
            raise ModelFileError(
                f"{path}: refused to load: it holds pickled Python objects, not a plain "
                "latticedft model dict (loaded with weights_only=True)"
            ) from None
        raise ModelFileError(f"{path}: not a readable model file ({type(exc).__name__}: {text[:120]})") from None
    if not isinstance(rec, dict) or rec.get("format") != "latticedft-model":
        raise ModelFileError(f"{path}: not a latticedft model file (expected a dict with format 'latticedft-model')")
    if rec.get("format_version") != FORMAT_VERSION:
        raise ModelFileError(
            f"{path}: format version {rec.get('format_version')!r}; this latticedft reads version {FORMAT_VERSION}"
        )
    build = _kind(path, rec.get("kind"))
    options = rec.get("options")
    if build is EnsembleLagrangian and isinstance(options, dict) and isinstance(options.get("model"), dict):
        _kind(path, options["model"].get("kind"))  # the members' kind
    try:
        model = build(**rec["options"], stencil=Stencil(rec["stencil"]))
        comps = tuple(rec["components"]) if rec.get("components") else None
        model.bind(int(rec["n"]), int(rec["m"]), tuple(rec["spacing"]), comps)
        state = rec["state_dict"]
        if isinstance(state, dict) and isinstance(state.get("feature_range"), torch.Tensor):
            model.set_feature_range(state["feature_range"])  # files written before ranges were kept have none
        model.load_state_dict(state)
        model.gauge = rec.get("gauge", DEFAULT_GAUGE)
    except ModelFileError:
        raise
    except Exception as exc:
        raise ModelFileError(
            f"{path}: inconsistent model file ({type(exc).__name__}: "
            f"{str(exc).strip().splitlines()[0][:160] if str(exc).strip() else ''})"
        ) from None
    return model
