"""``device=`` for learning and serving, ``[run] device`` and ``--device``, on the CPU.

The machine running the suite may have no GPU: "cuda" is then the fallback path (one DeviceWarning, the CPU
used, results identical). The bridge that carries a model's evaluations to another device is exercised on
the CPU itself (``_device._moved``), so what it changes around the model (patched methods, autograd through
them, double backward included) is tested even where no GPU exists.
"""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest
import torch

import latticedft as ldft
from latticedft import _device, systems
from latticedft._learn import _dist

from case_helpers import run_cli, tiny_wave, write_toml
from helpers import oscillator_data, wave_field

NO_CUDA = not torch.cuda.is_available()
needs_no_cuda = pytest.mark.skipif(not NO_CUDA, reason="the fallback needs a machine without CUDA")


def _kg():
    return systems.klein_gordon_training_set(n=3, steps=10, seed=0)


def _mlp_learned(device, **kw):
    model = ldft.MLPLagrangian(hidden=[6], activation="tanh", form="free", seed=0)
    report = ldft.learn(model, _kg(), optimizer="lbfgs", max_iter=6, boundary="periodic", device=device, **kw)
    return model, report


def _params(model) -> np.ndarray:
    return torch.cat([p.detach().reshape(-1) for p in model.parameters()]).numpy()


# -- resolving the device string ----------------------------------------------------------------------------
def test_resolve_cpu_and_auto():
    assert _device.resolve_device(None) == torch.device("cpu")
    assert _device.resolve_device("cpu") == torch.device("cpu")
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # "auto" never warns
        auto = _device.resolve_device("auto")
    assert auto.type == ("cpu" if NO_CUDA else "cuda")


@needs_no_cuda
@pytest.mark.parametrize("text", ["cuda", "cuda:0", "cuda:3"])
def test_cuda_without_a_gpu_falls_back_with_one_warning(text):
    with pytest.warns(ldft.DeviceWarning) as caught:
        assert _device.resolve_device(text) == torch.device("cpu")
    assert len(caught) == 1
    msg = str(caught[0].message)
    assert "\n" not in msg and text in msg and "CPU" in msg


@pytest.mark.parametrize("bad", ["gpu", "CUDA", "cuda:", "cuda:x", "cpu:0", "", 3, True, ["cpu"]])
def test_bad_device_refused_with_one_line(bad):
    with pytest.raises(ldft.InputError) as err:
        _device.resolve_device(bad)
    assert err.value.key == "device"
    assert str(err.value).startswith("device: expected 'cpu', 'cuda', 'cuda:N'") and "\n" not in str(err.value)
    with pytest.raises(ldft.InputError, match=r"^run\.device: expected"):
        _device.resolve_device(bad, key="run.device")


def test_learn_and_serve_refuse_a_bad_device():
    model = ldft.PolynomialLagrangian(orders=(2, 2))
    with pytest.raises(ldft.InputError, match="^device: expected"):
        ldft.learn(model, oscillator_data()[1], device="gpu")
    ldft.learn(model, oscillator_data()[1])
    with pytest.raises(ldft.InputError, match="^device: expected"):
        ldft.serve(model, oscillator_data()[1][0], device="tpu")


# -- learn and serve: identical results on every spelling of the CPU --------------------------------------
def test_learn_mlp_same_on_every_cpu_device():
    ref_model, ref = _mlp_learned(None)
    assert ref.device == "cpu" and ref.iterations > 1
    for device in ("cpu", "auto") if NO_CUDA else ("cpu",):
        model, rep = _mlp_learned(device)
        np.testing.assert_array_equal(_params(model), _params(ref_model))
        assert rep.loss == ref.loss and rep.device == "cpu"


@needs_no_cuda
def test_learn_cuda_falls_back_once_and_matches():
    ref_model, ref = _mlp_learned(None)
    with pytest.warns(ldft.DeviceWarning) as caught:
        model, rep = _mlp_learned("cuda")
    assert len([w for w in caught if issubclass(w.category, ldft.DeviceWarning)]) == 1
    np.testing.assert_array_equal(_params(model), _params(ref_model))
    assert rep.loss == ref.loss and rep.device == "cpu"


def test_serve_same_on_every_device_spelling():
    field = wave_field()
    model = ldft.PolynomialLagrangian(orders=(2, 0))
    ldft.learn(model, field)
    ref = ldft.serve(model, field, affine=False)
    assert ref.device == "cpu"
    devices = ["cpu", "auto"] + (["cuda"] if NO_CUDA else [])
    for device in devices:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            out = ldft.serve(model, field, affine=False, device=device)
        dw = [w for w in caught if issubclass(w.category, ldft.DeviceWarning)]
        assert len(dw) == (1 if device == "cuda" else 0)
        if device == "cpu" or NO_CUDA:  # the same arithmetic: the same field to the bit
            np.testing.assert_array_equal(out.field.values, ref.field.values)
            assert out.device == "cpu" and out.to_dict()["device"] == "cpu"
        else:  # "auto" on a GPU: the slices solved there, by its arithmetic (round-off apart)
            np.testing.assert_allclose(out.field.values, ref.field.values, rtol=0, atol=1e-12)
            assert out.device.startswith("cuda")


def test_serve_batch_1d_with_device():
    data = oscillator_data()[1]
    model = ldft.PolynomialLagrangian(orders=(4, 8))
    ldft.learn(model, data)
    ref = ldft.serve(model, data, slices=50)
    out = ldft.serve(model, data, slices=50, device="auto" if NO_CUDA else "cpu")
    for a, b in zip(out, ref):
        np.testing.assert_array_equal(a.field.values, b.field.values)
        assert a.device == "cpu"


# -- the bridge to another device, exercised on the CPU ---------------------------------------------------
def test_bridge_patches_the_evaluations_and_removes_them():
    model, _ = _mlp_learned(None)
    cells = torch.randn(5, model.stencil.size, model.m, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    before = model(cells)
    with _device._moved(model, torch.device("cpu")):
        assert "forward" in model.__dict__ and "trained_range" in model.__dict__
        np.testing.assert_array_equal(model(cells).detach().numpy(), before.detach().numpy())
        assert model.trained_range().device.type == "cpu"
    assert not any(callable(model.__dict__.get(name)) for name in type(model).bridged)


def test_training_and_serving_through_the_bridge_match(monkeypatch):
    """Iterative training (double backward through the bridged forward) and serving through the bridge give
    exactly what the plain model gives."""
    ref_model, ref = _mlp_learned(None, symmetries=True)
    field = wave_field(nx=17, nt=12)
    lin = ldft.PolynomialLagrangian(orders=(2, 0))
    ldft.learn(lin, field)
    served = ldft.serve(lin, field, affine=False)
    import latticedft._learn._api as api
    import latticedft._serve as srv

    monkeypatch.setattr(api, "on_device", _device._moved)
    monkeypatch.setattr(srv, "on_device", _device._moved)
    model, rep = _mlp_learned(None, symmetries=True)
    np.testing.assert_array_equal(_params(model), _params(ref_model))
    assert rep.loss == ref.loss and rep.rel_res == ref.rel_res and rep.hessian_min_sv == ref.hessian_min_sv
    assert rep.symmetries == ref.symmetries and rep.symmetries
    out = ldft.serve(lin, field, affine=False)
    np.testing.assert_array_equal(out.field.values, served.field.values)
    assert not any(callable(lin.__dict__.get(name)) for name in type(lin).bridged)


def test_device_label_of_cpu():
    assert _device.device_label(torch.device("cpu")) == "cpu"


# -- the process-group backend ----------------------------------------------------------------------------
def test_backend_nccl_for_cuda_gloo_otherwise():
    assert _device.backend_for_device(torch.device("cpu")) == "gloo"
    assert _device.backend_for_device(torch.device("cuda", 0)) == "nccl"
    assert _device.backend_for_device(torch.device("cuda")) == "nccl"
    assert _dist.backend_for(1) == "gloo"
    assert _dist.backend_for(2, "cpu") == "gloo"


@needs_no_cuda
def test_backend_for_cuda_without_a_gpu_is_gloo():
    with pytest.warns(ldft.DeviceWarning):
        assert _dist.backend_for(1, "cuda") == "gloo"


# -- case.toml and the command line -----------------------------------------------------------------------
def test_case_toml_device_checked(tmp_path, capsys):
    case = tiny_wave(tmp_path)
    text = (case / "case.toml").read_text().replace("threads = 1", 'threads = 1\ndevice = "gpu"')
    write_toml(case, text)
    code, _, err = run_cli(capsys, "check", case)
    assert code == 1
    line = err.strip()
    assert "\n" not in line and "run.device" in line and "'cuda:N'" in line


def test_cli_device_refused(tmp_path, capsys):
    case = tiny_wave(tmp_path)
    code, _, err = run_cli(capsys, "run", case, "--device", "tpu")
    assert code == 1
    assert "run.device" in err and "\n" not in err.strip()
    assert not (case / "results").exists()


def test_cli_run_records_the_device(tmp_path, capsys):
    case = tiny_wave(tmp_path)
    args = ("run", case, "--device", "cuda") if NO_CUDA else ("run", case, "--device", "cpu")
    code, _, err = run_cli(capsys, *args)
    assert code == 0
    if NO_CUDA:
        lines = [ln for ln in err.splitlines() if "CUDA is not available" in ln]
        assert len(lines) == 1 and lines[0].startswith("latticedft: warning: run.device 'cuda'")
    res = case / "results"
    summary = json.loads((res / "summary.json").read_text())
    assert summary["device"] == "cpu"
    assert summary["train"]["device"] == "cpu"
    assert summary["tasks"]["test"]["device"] == "cpu"
    assert json.loads((res / "model.json").read_text())["training"]["device"] == "cpu"
    log = (res / "run.log").read_text()
    assert "device: cpu" in log and "task test served on cpu" in log
    if NO_CUDA:
        assert "CUDA is not available" in log
    # the saved model is on the CPU and loads there
    state = torch.load(res / "model.pt", weights_only=True, map_location="cpu")
    assert all(t.device.type == "cpu" for t in state["state_dict"].values())
    # serve takes --device too and records it
    code, _, err = run_cli(capsys, "serve", case, "--device", "auto")
    assert code == 0
    assert json.loads((res / "summary.json").read_text())["tasks"]["test"]["device"] == ("cpu" if NO_CUDA else "cuda")


def test_device_warning_is_public():
    assert issubclass(ldft.DeviceWarning, UserWarning)
    assert "DeviceWarning" in ldft.__all__


@pytest.mark.slow
def test_device_benchmark_runs(capsys):
    """``python -m benchmarks.device`` on a machine without CUDA: says so and measures the CPU at small sizes
    (no timing asserted; the two runs of each workload agree exactly)."""
    from benchmarks import device as bench

    assert bench.main(["--quick", "--device", "cpu"]) == 0
    out = capsys.readouterr().out
    rows = [ln for ln in out.splitlines() if ln.startswith(("serve 2+1D", "serve 3+1D", "train MLP"))]
    assert len(rows) == 3
    assert all(" 0.0e+00 " in ln and ln.rstrip().endswith("cpu") for ln in rows)
    if NO_CUDA:
        assert "CUDA is unavailable here" in out
