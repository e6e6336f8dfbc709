"""Model files round-trip and load with weights_only=True."""

from __future__ import annotations

import pickle

import numpy as np
import pytest
import torch

import latticedft as ldft

from helpers import oscillator_data


@pytest.mark.parametrize(
    "make",
    [
        lambda: ldft.PolynomialLagrangian((2, 4), time_symmetric=True),
        lambda: ldft.MLPLagrangian(hidden=[6], activation="tanh", form="kinetic-potential"),
    ],
)
def test_round_trip(tmp_path, make):
    _, data = oscillator_data(steps=40)
    model = make()
    ldft.learn(model, data, max_iter=20)
    path = ldft.save_model(model, tmp_path / "model.pt")
    rec = torch.load(path, weights_only=True)
    assert rec["kind"] == model.kind and rec["format_version"] == 1 and rec["stencil"] == [[0], [1]]
    back = ldft.load_model(path)
    a = ldft.serve(model, data[0]).field.values
    b = ldft.serve(back, data[0]).field.values
    np.testing.assert_array_equal(a, b)


def test_pickled_object_is_refused(tmp_path):
    class Evil:
        def __reduce__(self):
            return (print, ("owned",))

    path = tmp_path / "model.pt"
    torch.save({"format": "latticedft-model", "payload": Evil()}, path)
    with pytest.raises(ldft.ModelFileError, match="refused"):
        ldft.load_model(path)


def test_corrupt_file(tmp_path):
    path = tmp_path / "model.pt"
    path.write_bytes(b"PK\x03\x04 this is not a model")
    with pytest.raises(ldft.ModelFileError) as err:
        ldft.load_model(path)
    assert "\n" not in str(err.value) and "model.pt" in str(err.value)
    path.write_bytes(pickle.dumps({"a": 1}))
    with pytest.raises(ldft.ModelFileError):
        ldft.load_model(path)


@pytest.mark.parametrize(
    "make, needle",
    [
        (lambda p: p.write_text("cats are nice\n"), "not a model file: expected a file written by latticedft"),
        (lambda p: p.write_text("model = 3\n"), "found one starting with b'model = 3"),
        (
            lambda p: p.symlink_to("/dev/zero"),
            "is not a regular file (a device, a pipe or a socket) (a link to /dev/zero)",
        ),
        (lambda p: p.mkdir(), "is a folder"),
        (lambda p: p.symlink_to(p.parent / "gone.pt"), "which does not exist"),
    ],
    ids=["text", "text-m", "dev-zero", "folder", "dangling"],
)
def test_what_a_model_path_is_instead_is_said(tmp_path, make, needle):
    """A text file is not "pickled Python objects", a link to /dev/zero is not "not found"."""
    path = tmp_path / "model.pt"
    make(path)
    with pytest.raises(ldft.ModelFileError) as err:
        ldft.load_model(path)
    assert needle in str(err.value) and "pickled" not in str(err.value) and "\n" not in str(err.value)


def test_analytic_models_are_not_saveable(tmp_path):
    model = ldft.lagrangians.wave()
    model.bind(2, 1, (0.1, 0.1))
    with pytest.raises(ldft.ModelFileError, match="cannot be written"):
        ldft.save_model(model, tmp_path / "m.pt")
