"""Where the model's arithmetic runs: ``device = "cpu"``, ``"cuda"``, ``"cuda:N"`` or ``"auto"``.

The field data, the bookkeeping of a slice and the sparse linear algebra (scipy) stay on the CPU; what moves
to the device is the model: its parameters and buffers, and every evaluation of ``L_d`` and its closed-form
derivatives (:func:`on_device`). Cells travel to the device and the results come back to the device of the
caller's tensors, so the code around a model call (and autograd through it, double backward included) is
the same on every device. Results, and models after :func:`latticedft.learn`, are on the CPU.

>>> resolve_device("cpu"), resolve_device(None)
(device(type='cpu'), device(type='cpu'))
>>> resolve_device("tpu")
Traceback (most recent call last):
...
latticedft._errors.InputError: device: expected 'cpu', 'cuda', 'cuda:N' (N a GPU index) or 'auto', got 'tpu'
"""

from __future__ import annotations

import functools
import re
import warnings
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import TYPE_CHECKING, Any

import torch

from ._errors import InputError

if TYPE_CHECKING:  # the device layer moves any model; the contract sits layers above
    from ._contract import AbstractLagrangian

__all__ = ["DEVICES", "DeviceWarning", "resolve_device", "device_label", "on_device", "backend_for_device"]

#: The device strings accepted (``cuda:N``: GPU number ``N``).
DEVICES = ("cpu", "cuda", "cuda:N", "auto")

_CUDA_RE = re.compile(r"^cuda(?::(\d+))?$")


class DeviceWarning(UserWarning):
    """A requested device is not available here: the work runs on the CPU instead (one line says so)."""


def _expected(key: str, value: object) -> InputError:
    return InputError.at(key, f"expected 'cpu', 'cuda', 'cuda:N' (N a GPU index) or 'auto', got {value!r}")


def resolve_device(device: str | torch.device | None, *, key: str = "device") -> torch.device:
    """The torch device of ``device``: ``None`` and ``"cpu"`` are the CPU; ``"auto"`` is CUDA when available,
    else the CPU; ``"cuda"`` is the current GPU (each process of a ``torch.distributed`` run sets its own),
    ``"cuda:N"`` GPU ``N``.

    CUDA requested where it is not available (no GPU, a CPU-only torch, or no GPU ``N``) falls back to the CPU
    with one :class:`DeviceWarning`. Any other string is refused with an InputError naming ``key``.
    """
    if device is None:
        return torch.device("cpu")
    text = str(device) if isinstance(device, torch.device) else device
    if not isinstance(text, str):
        raise _expected(key, device)
    if text == "cpu":
        return torch.device("cpu")
    if text == "auto":
        return _current_cuda() if torch.cuda.is_available() else torch.device("cpu")
    match = _CUDA_RE.match(text)
    if match is None:
        raise _expected(key, text)
    if not torch.cuda.is_available():
        warnings.warn(
            f"{key} {text!r}: CUDA is not available here (no GPU, or a CPU-only torch); running on the CPU",
            DeviceWarning,
            stacklevel=3,
        )
        return torch.device("cpu")
    if match.group(1) is None:
        return _current_cuda()
    index = int(match.group(1))
    count = torch.cuda.device_count()
    if index >= count:
        warnings.warn(
            f"{key} {text!r}: this machine has {count} GPU(s) (cuda:0 to cuda:{count - 1}); running on the CPU",
            DeviceWarning,
            stacklevel=3,
        )
        return torch.device("cpu")
    return torch.device("cuda", index)


def _current_cuda() -> torch.device:
    return torch.device("cuda", torch.cuda.current_device())


def device_label(device: torch.device) -> str:
    """``"cpu"`` or ``"cuda:N (GPU name)"``: the device as outputs record it."""
    if device.type == "cuda":
        index = device.index if device.index is not None else torch.cuda.current_device()
        return f"cuda:{index} ({torch.cuda.get_device_name(index)})"
    return str(device)


def backend_for_device(device: torch.device) -> str:
    """The ``torch.distributed`` backend of processes that compute on ``device``: NCCL for CUDA, gloo else."""
    return "nccl" if device.type == "cuda" else "gloo"


def _to(value: Any, device: torch.device) -> Any:
    """``value`` with its tensors (also inside tuples, lists and dict values) moved to ``device``."""
    if isinstance(value, torch.Tensor):
        return value if value.device == device else value.to(device)
    if isinstance(value, tuple):
        return tuple(_to(v, device) for v in value)
    if isinstance(value, list):
        return [_to(v, device) for v in value]
    if isinstance(value, dict):
        return {k: _to(v, device) for k, v in value.items()}
    return value


def _first_device(args: tuple[Any, ...]) -> torch.device | None:
    return next((a.device for a in args if isinstance(a, torch.Tensor)), None)


def _bridged(method: Callable[..., Any], device: torch.device) -> Callable[..., Any]:
    """``method`` run on ``device``: its tensor arguments move there, its results back to the device of the
    first tensor argument, or to the CPU without one (so a call from inside the model, already on the device,
    moves nothing)."""

    @functools.wraps(method)
    def run(*args: Any, **kwargs: Any) -> Any:
        home = _first_device(args) or torch.device("cpu")
        return _to(method(*_to(args, device), **_to(kwargs, device)), home)

    return run


@contextmanager
def on_device(model: AbstractLagrangian, device: torch.device) -> Iterator[AbstractLagrangian]:
    """Inside the block, ``model``'s parameters and buffers are on ``device`` and its evaluations (the methods
    its class lists in ``bridged``) take and return tensors on the caller's device; on leaving, the model is
    back on the CPU. On the CPU the block changes nothing."""
    if device.type == "cpu":
        yield model
        return
    with _moved(model, device):
        yield model


@contextmanager
def _moved(model: AbstractLagrangian, device: torch.device) -> Iterator[None]:
    """The work of :func:`on_device` for any device (the CPU too: the tests exercise the bridge there)."""
    patched = list(model.bridged)
    model.to(device)
    for name in patched:
        object.__setattr__(model, name, _bridged(getattr(model, name), device))
    try:
        yield
    finally:
        for name in patched:
            model.__dict__.pop(name, None)
        model.to("cpu")
