"""Resumable serving (``[[serve]] checkpoint = K``): a task's checkpoints and the journal of the stage.

A task with ``checkpoint = K`` is served through the rolling window (as with ``every > 1``) and appends its
kept slices to its part file; every ``K`` slices :class:`TaskCheckpoint` writes ``.<task>.ckpt`` beside it,
atomically (a temporary file synced, then renamed): the window's state (``_serve._checkpoint``), the meter's
figures and how many slices the part file holds. The stage's :class:`Journal`
(``.latticedft-resume.json``) records what the command was run on (the command, the case as read, the
model's and the input files' identities) and the tasks done, with their ``summary.json`` records.

A killed run leaves its staging folder; ``--resume`` takes it up again (the command line finds it), checks
the journal against the case, skips the tasks done, continues the task that was being served from its
checkpoint and serves the others. The checkpoint files are removed before the results are published.
"""

from __future__ import annotations

import hashlib
import io
import json
import pickle
from pathlib import Path
from typing import Any

import numpy as np
import torch
import xarray as xr

from .._atomic import fault, write_bytes_atomic, write_text_atomic
from .._case import Case
from .._errors import InputError
from .._part_file import PartFile, part_path
from ._guards import case_inputs
from ._meter import TaskMeter

__all__ = ["RESUME_FILE", "Journal", "TaskCheckpoint", "open_part", "read_state", "state_bytes", "state_from_bytes"]

#: The journal of a stage that holds resumable tasks: a staging folder holding it is kept for ``--resume``.
RESUME_FILE = ".latticedft-resume.json"
_VERSION = 1


def checkpoint_path(folder: Path, name: str) -> Path:
    """``folder/.<name>.ckpt``."""
    return Path(folder) / f".{name}.ckpt"


class TaskCheckpoint:
    """``.<task>.ckpt``: the ``checkpointer`` of a task's meter (see ``_serve._checkpoint.Checkpointer``).

    ``state`` is the checkpoint a resumed task goes on from, as :func:`open_part` read it (None for a task
    served from its start): the file is read once."""

    def __init__(self, part: PartFile, meter: TaskMeter, name: str, state: dict[str, Any] | None):
        self.path = checkpoint_path(part.path.parent, name)
        self.part, self.meter, self.state = part, meter, state

    def save(self, state: dict[str, Any]) -> None:
        """Write the window's ``state`` with the meter's figures, atomically."""
        state = {**state, "meter": self.meter.state()}
        write_bytes_atomic(self.path, state_bytes(state))
        fault("checkpoint", self.path)

    def load(self) -> dict[str, Any] | None:
        """The state to go on from (the meter's figures put back, the kept slices read from the part file), or
        None for a task served from its start."""
        if self.state is None:
            return None
        state = dict(self.state)
        self.meter.restore(state.pop("meter"))
        self.part.n = int(state["nkept"])
        state["kept_values"] = self.part.rows()
        return state


def open_part(
    stage: Path, name: str, variable: str, template: xr.DataArray, every: int, resume: bool
) -> tuple[PartFile, dict[str, Any] | None]:
    """The task's part file, and the checkpoint it goes on from: with ``resume`` and a checkpoint of the
    task, the part file it left and the checkpoint read (refused in one line when unreadable); otherwise a
    new one and None."""
    ckpt = checkpoint_path(stage, name)
    if resume and ckpt.is_file() and part_path(stage, name).is_file():
        try:
            state = read_state(ckpt)
            return PartFile.reopen(stage, name, variable, template, int(state["nkept"])), state
        except (OSError, ValueError, KeyError, RuntimeError, pickle.UnpicklingError, EOFError) as exc:
            raise InputError.at(
                "checkpoint",
                f"task {name}: the checkpointed run's part file or checkpoint cannot be read ({exc}); "
                "run again without --resume",
            ) from None
    ckpt.unlink(missing_ok=True)  # the task was done when the run stopped: served again whole
    return PartFile(stage, name, variable, template, every), None


def state_bytes(state: dict[str, Any]) -> bytes:
    """``state`` (dicts, lists, tuples, numbers, strings, tensors, numpy arrays, DataArrays) as the bytes of a file that
    :func:`read_state` reads back without unpickling any object: torch's format, numpy arrays as tensors."""
    buf = io.BytesIO()
    torch.save(_encoded(state), buf)
    return buf.getvalue()


def read_state(path: Path) -> dict[str, Any]:
    """The state written by :func:`state_bytes` into ``path`` (:func:`state_from_bytes`)."""
    return state_from_bytes(Path(path).read_bytes())


def state_from_bytes(data: bytes) -> dict[str, Any]:
    """The state of :func:`state_bytes`, read with ``weights_only``: a file holding any other pickled object
    is refused (a checkpoint in a case folder may come from anyone)."""
    try:
        raw = torch.load(io.BytesIO(data), weights_only=True)
    except (pickle.UnpicklingError, RuntimeError, EOFError, ValueError):
        raise ValueError("it is damaged, or holds objects a checkpoint does not (refused unread)") from None
    state = _decoded(raw)
    if not isinstance(state, dict):
        raise ValueError("it is not a checkpoint")
    return state


_ARRAY, _DATAARRAY = "__ndarray__", "__dataarray__"


def _encoded(value: Any) -> Any:
    if isinstance(value, np.ndarray):
        return {_ARRAY: torch.from_numpy(np.array(value, copy=True))}
    if isinstance(value, xr.DataArray):
        return {_DATAARRAY: _encoded(value.to_dict(data="array"))}
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, dict):
        return {k: _encoded(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return type(value)(_encoded(v) for v in value)
    return value


def _decoded(value: Any) -> Any:
    if isinstance(value, dict):
        if set(value) == {_ARRAY} and isinstance(value[_ARRAY], torch.Tensor):
            return value[_ARRAY].numpy()
        if set(value) == {_DATAARRAY}:
            return xr.DataArray.from_dict(_decoded(value[_DATAARRAY]))
        return {k: _decoded(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return type(value)(_decoded(v) for v in value)
    return value


def _flat(value: Any, key: str = "") -> dict[str, Any]:
    """``value`` (the case as read) as dotted keys: ``serve[0].slices`` -> 200."""
    if isinstance(value, dict):
        out: dict[str, Any] = {}
        for k, v in value.items():
            out.update(_flat(v, f"{key}.{k}" if key else str(k)))
        return out or {key: {}}
    if isinstance(value, list) and any(isinstance(v, dict) for v in value):
        return {k: v for i, item in enumerate(value) for k, v in _flat(item, f"{key}[{i}]").items()}
    return {key: value}


_UNSET = object()


def _shown(value: Any) -> str:
    return "unset" if value is _UNSET else json.dumps(value)


def _identity(case: Case, model: Path) -> dict[str, Any]:
    """What a resumed run must share with the run it continues: the case as read (with ``--set``), the
    model file's hash, and the size and modification time of every input file."""
    files = {}
    for p in case_inputs(case):
        if p.is_file() and p.name != "case.toml":
            st = p.stat()
            files[str(p)] = [st.st_size, st.st_mtime_ns]
    digest = hashlib.sha256(model.read_bytes()).hexdigest() if model.is_file() else None
    return {"case": json.loads(json.dumps(_flat(case.raw), default=str)), "model": digest, "files": files}


class Journal:
    """``.latticedft-resume.json`` of a stage: the command, what it was run on, and the tasks done."""

    def __init__(self, folder: Path, data: dict[str, Any]):
        self.folder, self.data = Path(folder), data

    @classmethod
    def begin(cls, folder: Path, command: str, case: Case, model: Path, train: Any = None) -> Journal:
        """A new journal for ``command`` serving ``case`` with the model file ``model`` (``train``: the
        summary's train section of a ``run``)."""
        data = {"version": _VERSION, "command": command, **_identity(case, model), "train": train, "tasks": {}}
        journal = cls(folder, data)
        journal.write()
        return journal

    @classmethod
    def read(cls, folder: Path) -> Journal:
        data = json.loads((Path(folder) / RESUME_FILE).read_text(encoding="utf-8"))
        if not isinstance(data, dict) or data.get("version") != _VERSION:
            raise InputError.at("--resume", f"{folder.name}/{RESUME_FILE}: not a journal of this version")
        return cls(folder, data)

    def write(self) -> None:
        write_text_atomic(self.folder / RESUME_FILE, json.dumps(self.data, indent=1, default=str))

    def check(self, command: str, case: Case, model: Path) -> None:
        """Refuse, in one line naming the key, to resume a run of another command, case, model or input."""
        if self.data["command"] != command:
            raise InputError.at(
                "--resume",
                f"the checkpointed run is a `latticedft {self.data['command']}`: resume it with "
                f"`latticedft {self.data['command']} --resume`",
            )
        now = _identity(case, model)
        then, later = self.data["case"], now["case"]
        for key in sorted({*then, *later}):
            if then.get(key, _UNSET) != later.get(key, _UNSET):
                raise InputError.at(
                    key,
                    f"is {_shown(later.get(key, _UNSET))} now but the checkpointed run had "
                    f"{_shown(then.get(key, _UNSET))}; --resume continues the same case: undo the edit, "
                    "or run without --resume",
                )
        if now["model"] != self.data["model"]:
            raise InputError.at("--resume", "model.pt changed since the checkpointed run; run without --resume")
        for path in sorted({*self.data["files"], *now["files"]}):
            if self.data["files"].get(path) != now["files"].get(path):
                raise InputError.at(
                    "--resume", f"the input file {path} changed since the checkpointed run; run without --resume"
                )

    @property
    def done(self) -> dict[str, dict[str, Any]]:
        """The tasks done: name -> their ``summary.json`` record."""
        tasks: dict[str, dict[str, Any]] = self.data["tasks"]
        return tasks

    def task_done(self, name: str, record: dict[str, Any]) -> None:
        """Record task ``name`` as done (its file written and exported); its checkpoint is removed."""
        self.data["tasks"][name] = record
        self.write()
        checkpoint_path(self.folder, name).unlink(missing_ok=True)

    def close(self) -> None:
        """Every task done: remove the journal and any checkpoint left, before the results are published."""
        for p in self.folder.glob(".*.ckpt"):
            p.unlink(missing_ok=True)
        (self.folder / RESUME_FILE).unlink(missing_ok=True)
