"""The files of a results folder: the model and its hash, task files, their exports, summary.json."""

from __future__ import annotations

import hashlib
import json
import math
import os
import platform
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import xarray as xr

from .. import __version__
from .._atomic import write_text_atomic
from .._errors import InputError, ModelFileError
from .._part_file import complete_part
from ..io.exporters import ExportTask, export_formats
from ..io.fields import prepared_dataset, read_field
from ..io.fields import write_field as _write_field
from ._safety import _show, _signals_deferred, _writing, log

if TYPE_CHECKING:
    from .._contract import AbstractLagrangian


def versions() -> dict[str, str]:
    import torch

    return {
        "latticedft": __version__,
        "torch": torch.__version__,
        "numpy": np.__version__,
        "xarray": xr.__version__,
        "python": platform.python_version(),
    }


def json_safe(obj: Any) -> Any:
    """Recursively turn numpy scalars/arrays, paths and non-finite floats into JSON values (nan/inf -> None)."""
    if isinstance(obj, Mapping):
        return {str(k): json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_safe(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return json_safe(obj.tolist())
    if isinstance(obj, (bool, np.bool_)):
        return bool(obj)
    if isinstance(obj, (int, np.integer)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        return float(obj) if math.isfinite(obj) else None
    if isinstance(obj, Path):
        return str(obj)
    if obj is None or isinstance(obj, str):
        return obj
    return str(obj)


def _write_json(path: Path, data: Any) -> None:
    text = json.dumps(json_safe(data), indent=2, allow_nan=False) + "\n"
    with _writing(path):
        write_text_atomic(path, text)


def sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def write_model(folder: Path, model: AbstractLagrangian, report: Any, meta: Mapping[str, Any]) -> dict[str, Any]:
    """``model.pt`` (:func:`latticedft.save_model`) and ``model.json`` (same record, no tensors)."""
    from .._modelfile import model_record, save_model

    with _writing(folder / "model.pt"):
        pt = save_model(model, folder / "model.pt", gauge=report.gauge if report is not None else None)
    record = model_record(model, report.gauge if report is not None else None)
    record["n_parameters"] = model.n_parameters()
    record["training"] = report.to_dict() if report is not None else None
    record["sha256"] = sha256(pt)
    record["file"] = pt.name
    record.update(meta)
    _write_json(folder / "model.json", record)
    log.debug("wrote %s (sha256 %s) and model.json", pt.name, record["sha256"])
    return record


def load_verified_model(folder: str | os.PathLike[str]) -> Any:
    """Load ``folder/model.pt`` after checking it against ``folder/model.json``; refuse non-finite weights.

    The sha256 that ``model.json`` records must match the file (a mismatch is a
    :class:`latticedft.ModelFileError`: the file was changed or damaged after
    training); without a recorded sha256 a warning says the file is unverified.
    A model whose parameters or buffers hold NaN or inf is refused.
    """
    from .._modelfile import load_model

    folder = Path(folder)
    pt, meta = folder / "model.pt", folder / "model.json"
    if not pt.is_file():
        raise ModelFileError(f"{_show(pt)}: model file not found; run `latticedft run` (or `train`) first")
    model = load_model(pt)  # a file that is not a model file at all says so first
    expected = None
    if meta.is_file():
        try:
            record = json.loads(meta.read_text(encoding="utf-8"))
        except (OSError, ValueError) as exc:
            raise ModelFileError(f"{_show(meta)}: not a readable model record ({type(exc).__name__})") from None
        expected = record.get("sha256") if isinstance(record, dict) else None
    if isinstance(expected, str) and expected:
        actual = sha256(pt)
        if actual != expected:
            raise ModelFileError(
                f"{_show(pt)}: sha256 {actual[:16]}... differs from the {expected[:16]}... "
                f"recorded in model.json: the file was changed or damaged after training; "
                "run `latticedft train` again"
            )
    else:
        log.warning("%s: no sha256 recorded in model.json; the model file is not verified", _show(pt))
    for name, tensor in model.state_dict().items():
        if tensor.is_floating_point() and not bool(tensor.isfinite().all()):
            bad = int((~tensor.isfinite()).sum())
            raise ModelFileError(
                f"{_show(pt)}: {bad} non-finite weight(s) (NaN or inf) in {name!r}; run `latticedft train` again"
            )
    return model


def _config_attr(config: Mapping[str, Any]) -> str:
    return json.dumps(json_safe(config), sort_keys=True)


def align_reference(pred: xr.DataArray, ref: xr.DataArray | None) -> xr.DataArray | None:
    """``ref`` on ``pred``'s slices (truncated to them), or None when it is shorter or on another lattice."""
    if ref is None:
        return None
    tdim = pred.dims[0]
    n = pred.sizes[tdim]
    idx = _slices_of(pred)
    if ref.sizes.get(tdim, 0) < (int(idx[-1]) + 1 if len(idx) else n) or ref.shape[1:] != pred.shape[1:]:
        return None
    return pred.copy(data=_at_slices(ref, idx))


def _at_slices(da: xr.DataArray, idx: np.ndarray) -> np.ndarray:
    """Slices ``idx`` of ``da`` as float64 (of a field opened lazily, only those slices are read)."""
    if da.chunks is None and getattr(da.variable, "_in_memory", True):
        return np.asarray(da.values[idx], dtype=np.float64)
    tdim = da.dims[0]
    out = np.empty((len(idx), *da.shape[1:]))
    for k, i in enumerate(idx):  # one slice at a time: the file's library may read a whole range for a list
        out[k] = da.isel({tdim: int(i)}).values
    return out


def _slices_of(pred: xr.DataArray) -> np.ndarray:
    """The slice index of each of ``pred``'s slices: its ``slice`` coordinate (a field served with an output
    cadence keeps some slices), else ``0 .. n - 1``."""
    if "slice" in pred.coords:
        return np.asarray(pred["slice"].values, dtype=np.int64)
    return np.arange(pred.sizes[pred.dims[0]])


def _invariant_named(invariant: xr.DataArray, pred: xr.DataArray) -> xr.DataArray:
    """The task's invariant as ``invariant``; a function computed from the field often hands on the field's
    attributes: its ``long_name`` (and the field's provenance) would then call the invariant "position"."""
    out = invariant.rename("invariant")
    inherited = {k for k, v in out.attrs.items() if k in pred.attrs and pred.attrs[k] == v}
    if "long_name" in inherited or not out.attrs.get("long_name"):
        out.attrs = {k: v for k, v in out.attrs.items() if k not in inherited and k != "units"}
        out.attrs["long_name"] = "invariant"
    return out


def write_task(
    folder: Path,
    name: str,
    variable: str,
    pred: xr.DataArray,
    ref: xr.DataArray | None,
    invariant: xr.DataArray | None,
    *,
    attrs: Mapping[str, Any],
    history: str,
    baseline: xr.DataArray | None = None,
    steps: int | None = None,
    charges: xr.Dataset | None = None,
    extra: Mapping[str, xr.DataArray] | None = None,
    part: Path | None = None,
) -> Path:
    """``<name>.nc``: the served field, ``<var>_ref`` and ``<var>_err`` when a reference covers it, the
    ``invariant`` and the task's ``charges`` (``charge_<name>(t)``, ``energy(t)``) when given, and the
    variables of ``extra`` (e.g. ``extrapolation(t, feature)``).

    With a ``baseline`` (another scheme's field, scored against the same
    reference) the file also holds ``baseline_err_max(t)`` and
    ``baseline_err_rms(t)``: the baseline's max and RMS error per served slice
    (NaN where the baseline holds no slice), so that the figures of a later
    ``export`` need the file alone. ``steps`` (the slices the task asked for)
    is written as the global attribute ``latticedft_steps``.

    ``part``: the part file that holds the served field's kept slices already (a task with an output
    cadence, :mod:`latticedft._part_file`); it is completed into ``<name>.nc`` (the same variables and
    attributes), so that the field is not written twice.
    """
    pred = pred.rename(variable).copy(deep=False)  # its own attributes: the caller's field is not changed
    quantity = str(pred.attrs.get("long_name") or variable)
    units = pred.attrs.get("units")
    unit_attrs = {"units": units} if units is not None else {}
    pred.attrs = {**pred.attrs, "long_name": quantity, "comment": "served by the learned discrete Lagrangian"}
    fields: dict[str, xr.DataArray] = {variable: pred}
    ref_al = align_reference(pred, ref)
    if ref_al is not None and ref is not None:
        # the reference's own description (not the served field's "predicted by ..."), under the quantity's name
        ref_al.attrs = {
            **{k: v for k, v in ref.attrs.items() if k not in ("comment", "latticedft_initial_from")},
            "long_name": quantity,
            **unit_attrs,
            "comment": "reference",
        }
        fields[f"{variable}_ref"] = ref_al
        err = pred - ref_al
        err.attrs = {"long_name": f"{variable} - {variable}_ref", **unit_attrs}  # nothing of either operand
        fields[f"{variable}_err"] = err
        if baseline is not None:
            fields.update(_baseline_errors(pred, ref_al, baseline, unit_attrs))
    if invariant is not None:
        fields["invariant"] = _invariant_named(invariant, pred)
    if charges is not None:
        fields.update({str(k): v.rename(str(k)) for k, v in charges.data_vars.items()})
    fields.update({k: v.rename(k) for k, v in (extra or {}).items()})
    all_attrs = dict(attrs)
    if steps is not None:
        all_attrs["latticedft_steps"] = int(steps)
    target = folder / f"{name}.nc"
    with _writing(target):
        if part is not None:
            return _complete_part(part, target, variable, fields, all_attrs, history)
        return write_field(target, fields, attrs=all_attrs, history=history)


def _complete_part(
    part: Path,
    target: Path,
    variable: str,
    fields: Mapping[str, xr.DataArray],
    attrs: Mapping[str, Any],
    history: str,
) -> Path:
    """``target`` made from ``part`` (holding ``variable``'s kept slices) and the other ``fields``."""
    ds, encoding = prepared_dataset(fields, attrs, history, where=str(target))
    return complete_part(part, target, ds, encoding, variable)


def _baseline_errors(
    pred: xr.DataArray, ref: xr.DataArray, baseline: xr.DataArray, unit_attrs: Mapping[str, Any]
) -> dict[str, xr.DataArray]:
    """The baseline's max and RMS error against ``ref`` per slice of ``pred`` (position by position)."""
    tdim = pred.dims[0]
    nt = pred.sizes[tdim]
    base = baseline.transpose(*pred.dims) if set(baseline.dims) == set(pred.dims) else baseline
    if base.shape[1:] != pred.shape[1:]:
        return {}
    idx = _slices_of(pred)
    n = int(np.count_nonzero(idx < base.sizes[tdim]))  # the kept slices the baseline holds
    diff = np.full(pred.shape, np.nan)
    diff[:n] = _at_slices(base, idx[:n]) - np.asarray(ref.values[:n], dtype=np.float64)
    flat = diff.reshape(nt, -1)
    with np.errstate(invalid="ignore"):
        worst = np.abs(flat).max(axis=1) if flat.shape[1] else np.full(nt, np.nan)
        rms = np.sqrt(np.mean(flat**2, axis=1)) if flat.shape[1] else np.full(nt, np.nan)
    label = str(baseline.attrs.get("long_name") or "baseline")
    coords = {tdim: pred.coords[tdim]} if tdim in pred.coords else None
    common = {"baseline": label, **unit_attrs}
    return {
        "baseline_err_max": xr.DataArray(
            worst, dims=(tdim,), coords=coords, attrs={"long_name": "max |baseline - reference| per slice", **common}
        ),
        "baseline_err_rms": xr.DataArray(
            rms, dims=(tdim,), coords=coords, attrs={"long_name": "rms of (baseline - reference) per slice", **common}
        ),
    }


def write_field(path: Path, fields: Mapping[str, xr.DataArray], *, attrs: Mapping[str, Any], history: str) -> Path:
    return _write_field(path, fields, attrs=dict(attrs), history=history)


def read_task(path: Path, variable: str) -> tuple[xr.DataArray, xr.DataArray | None, xr.DataArray | None]:
    """Reload ``<name>.nc``: (served field, reference or None, error or None)."""
    if not path.is_file():
        raise InputError(f"{path}: file not found; run `latticedft serve` first")
    with xr.open_dataset(path, engine="netcdf4", decode_times=False) as ds:
        names = {str(v) for v in ds.data_vars}
    pred = read_field(path, variable, allow_nan=True)
    ref = read_field(path, f"{variable}_ref") if f"{variable}_ref" in names else None
    err = read_field(path, f"{variable}_err", allow_nan=True) if f"{variable}_err" in names else None
    return pred, ref, err


def export_task(
    folder: Path,
    name: str,
    variable: str,
    pred: xr.DataArray,
    ref: xr.DataArray | None,
    err: xr.DataArray | None,
    *,
    formats: Sequence[str],
    max_frames: int | None,
    train: Sequence[xr.DataArray] | None = None,
    title: str | None = None,
) -> list[Path]:
    """Write task ``name`` in each export format of ``formats``; the files written.

    Formats are the names of :data:`latticedft.io.exporters.EXPORTERS`
    (``"paraview"``, ``"figures"``, ``"xdmf"``). When ``folder/<name>.nc``
    exists, its global attributes and its series over time (``invariant``,
    ``energy``, ``charge_*``, ``baseline_err_*`` ...) go to the exporters too
    (:func:`read_task_series`).
    """
    attrs, series = read_task_series(Path(folder) / f"{name}.nc", variable)
    spread = read_spread(Path(folder) / f"{name}.nc", variable)
    task = ExportTask(
        folder=Path(folder),
        name=name,
        field=pred.rename(variable),
        reference=ref,
        error=err,
        max_frames=max_frames,
        train=tuple(train) if train is not None else None,
        title=title or name,
        attrs=attrs,
        series=series,
        spread=spread if spread is not None and spread.shape == pred.shape else None,
    )
    # the exporters run native libraries (VTK, HDF5): a signal is delivered once they return, never inside them
    with _writing(Path(folder) / f"{name}.*"), _signals_deferred():
        return export_formats(task, formats)


def read_spread(path: Path, variable: str) -> xr.DataArray | None:
    """``<var>_std`` of a task file (an ensemble served), or None."""
    if not Path(path).is_file():
        return None
    with xr.open_dataset(path, engine="netcdf4", decode_times=False) as ds:
        found = f"{variable}_std" in ds.data_vars
    return read_field(path, f"{variable}_std", allow_nan=True) if found else None


def read_task_series(path: Path, variable: str) -> tuple[dict[str, Any], dict[str, xr.DataArray]]:
    """Global attributes and the series over time of a task file (both empty when there is no file).

    A series is a data variable whose only dim is the field's time dim, other
    than the field itself, ``<var>_ref`` and ``<var>_err`` (1D fields).
    """
    if not Path(path).is_file():
        return {}, {}
    with xr.open_dataset(path, engine="netcdf4", decode_times=False) as ds:
        attrs = dict(ds.attrs)
        if variable not in ds.data_vars:
            return attrs, {}
        tdim = ds[variable].dims[0]
        skip = {variable, f"{variable}_ref", f"{variable}_err", f"{variable}_mean", f"{variable}_std"}
        series = {str(k): v.load() for k, v in ds.data_vars.items() if v.dims == (tdim,) and str(k) not in skip}
    return attrs, series


def write_summary(folder: Path, summary: Mapping[str, Any]) -> Path:
    path = folder / "summary.json"
    _write_json(path, summary)
    return path


def read_summary(folder: Path) -> dict[str, Any] | None:
    path = folder / "summary.json"
    if not path.is_file():
        return None
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise InputError(f"{path}: not a readable summary ({type(exc).__name__})") from None
    return data if isinstance(data, dict) else None


def config_attrs(config: Mapping[str, Any], overrides: tuple[str, ...], command: str) -> dict[str, Any]:
    """Global attributes of a task file."""
    return {
        "source": f"latticedft {__version__}",
        "latticedft_config": _config_attr(config),
        "latticedft_overrides": json.dumps(list(overrides)),
        "latticedft_command": command,
    }
