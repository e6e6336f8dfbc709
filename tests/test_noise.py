"""Noisy data: the noise estimate, learning with noise correction, denoised serving starts, their options."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
import xarray as xr
from scipy.integrate import solve_ivp

import latticedft as ldft
from benchmarks.noise_hessian import autograd_products
from latticedft import ConfigError, InputError, systems
from latticedft._action import _action, action_hessian
from latticedft._case import load_case
from latticedft._lattice import as_lattice_field
from latticedft._learn import _noise
from latticedft._learn._noise import DENOISE_SLICES, SECOND_DIFFERENCE_WARN, denoised_start
from latticedft._run._task import _start
from latticedft.io import write_field

from case_helpers import run_cli, tiny_wave, write_toml

H = 0.25  # the double-well Duffing oscillator psi'' = psi - psi^3, sampled every H


def duffing(q0: float, n: int) -> xr.DataArray:
    t = np.arange(n) * H
    sol = solve_ivp(
        lambda _, y: [y[1], y[0] - y[0] ** 3], (0, t[-1]), [q0, 0.0], method="DOP853", rtol=1e-12, atol=1e-12, t_eval=t
    )
    return systems.make_field(sol.y[0], ("t",), spacing=H)


def noisy(f: xr.DataArray, sigma: float, rng: np.random.Generator) -> xr.DataArray:
    """``f`` plus Gaussian noise of standard deviation ``sigma`` times its amplitude."""
    return f + sigma * float(abs(f).max()) * rng.standard_normal(f.shape)


def served_error(model: ldft.AbstractLagrangian, start: xr.DataArray, ref: xr.DataArray) -> float:
    out = ldft.serve(model, start.isel(t=slice(0, 2)), slices=ref.sizes["t"], progress=False)
    return float(abs(out.field.values - ref.values).max() / abs(ref).max())


@pytest.mark.parametrize("seed", [0, 1])
def test_estimate_within_a_factor_two(seed: int) -> None:
    f = systems.oscillator_sin(1.2, n=400, dt=0.5)
    sigma = 1e-3 * float(abs(f).max())
    est = ldft.estimate_noise(noisy(f, 1e-3, np.random.default_rng(seed)))
    assert est.resolved and est.significant
    assert sigma / 2 < est.sigma < 2 * sigma
    assert est.relative == pytest.approx(est.sigma / float(abs(f).max()), rel=0.01)


def test_estimate_of_clean_and_of_pooled_fields() -> None:
    clean = [duffing(q, 201) for q in (1.3, 1.6)]
    est = ldft.estimate_noise(clean)
    assert not est.significant and est.sigma < 1e-6
    rng = np.random.default_rng(3)
    pooled = ldft.estimate_noise([noisy(f, 1e-2, rng) for f in clean])
    assert pooled.significant and 0.5 * 1e-2 < pooled.relative < 2 * 1e-2


def test_noise_correction_beats_plain_learning() -> None:
    """sigma = 1e-3 on a double-well Duffing oscillator: corrected training and a denoised start serve 50 steps
    well within 10 sigma and several times better than learning and starting from the noisy data."""
    rng = np.random.default_rng(0)
    train = [noisy(duffing(q, 161), 1e-3, rng) for q in (0.6, 1.0, 1.3, 1.45, 1.6, 1.75)]
    ref = duffing(1.55, 51)
    test = noisy(ref, 1e-3, rng)
    plain = ldft.PolynomialLagrangian(orders=(4, 8))
    rep_plain = ldft.learn(plain, train, progress=False)
    aware = ldft.PolynomialLagrangian(orders=(4, 8))
    rep = ldft.learn(aware, train, progress=False, noise="correct")
    assert rep_plain.noise is None and rep.noise is not None
    assert rep.noise["method"] == "errors in variables" and rep.noise["resolved"]
    assert 0.5e-3 < rep.noise["relative"] < 2e-3
    e_plain = served_error(plain, test, ref)
    e_aware = served_error(aware, denoised_start(aware, test), ref)
    assert e_aware < 1e-2
    assert e_aware < e_plain / 3


def test_auto_leaves_clean_data_alone() -> None:
    train = [duffing(q, 81) for q in (1.3, 1.6)]
    a, b = ldft.PolynomialLagrangian(orders=(2, 4)), ldft.PolynomialLagrangian(orders=(2, 4))
    ldft.learn(a, train, progress=False)
    rep = ldft.learn(b, train, progress=False, noise="auto")
    assert rep.noise is not None and rep.noise["method"] == "none" and not rep.warnings
    for k, v in a.state_dict().items():
        assert np.array_equal(v.numpy(), b.state_dict()[k].numpy())


def test_a_given_sigma_of_zero_leaves_noisy_data_alone() -> None:
    rng = np.random.default_rng(1)
    train = [noisy(duffing(q, 121), 1e-2, rng) for q in (1.3, 1.6)]
    rep = ldft.learn(ldft.PolynomialLagrangian(orders=(2, 4)), train, progress=False, noise="auto", noise_sigma=0.0)
    assert rep.noise is not None and rep.noise["given"] and rep.noise["method"] == "none"


def test_noise_that_swamps_the_second_differences_warns() -> None:
    """The share of the noise in the second time differences grows with sigma and as the sampling gets finer;
    above SECOND_DIFFERENCE_WARN learning says the equations may be unreliable, below it does not."""
    shares = {}
    for dt, sigma in ((0.25, 1e-3), (0.25, 1e-2), (0.05, 1e-2)):
        t = np.arange(int(40 / dt)) * dt
        sol = solve_ivp(lambda _, y: [y[1], y[0] - y[0] ** 3], (0, t[-1]), [1.3, 0.0], t_eval=t, rtol=1e-11, atol=1e-11)
        clean = systems.make_field(sol.y[0], ("t",), spacing=dt)
        data = noisy(clean, sigma, np.random.default_rng(6))
        rep = ldft.learn(ldft.PolynomialLagrangian(orders=(2, 4)), data, progress=False, noise="correct")
        assert rep.noise is not None
        shares[dt, sigma] = rep.noise["second_difference_ratio"]
        warned = any("second time differences" in w for w in rep.warnings)
        assert warned == (shares[dt, sigma] > SECOND_DIFFERENCE_WARN)
    assert shares[0.25, 1e-3] < shares[0.25, 1e-2] < shares[0.05, 1e-2]
    assert shares[0.25, 1e-3] < SECOND_DIFFERENCE_WARN < shares[0.05, 1e-2]


def test_selection_scores_a_noise_corrected_candidate_from_denoised_starts() -> None:
    """With ``noise="auto"``, each candidate serves its held-out fields from denoised initial slices (as a task
    with ``start = "auto"`` does): the hand-set score stays near the noise, where the noisy start of each field
    would put it tens of sigma off."""
    rng = np.random.default_rng(5)
    train = [noisy(duffing(q, 121), 1e-3, rng) for q in (1.0, 1.3, 1.6)]
    rep = ldft.select(ldft.PolynomialLagrangian(orders=(2, 4)), train, [{"orders": [2, 8]}], noise="auto")
    assert rep.rows[0]["status"] == "ok" and rep.rows[0]["score"] < 2e-2
    model = ldft.PolynomialLagrangian(orders=(2, 4))
    ldft.learn(model, [f.isel(t=slice(0, 85)) for f in train], progress=False, noise="auto")
    from_noisy = max(float(abs(ldft.serve(model, f, progress=False).field - f).max() / abs(f).max()) for f in train)
    assert from_noisy > 3 * rep.rows[0]["score"]


def test_gauge_auto_under_noise_compares_the_gauges_after_the_correction() -> None:
    """sigma = 1e-3 on two orbits of a charged particle: the noise floor of both gauges' dense fits (0.38 and 0.15)
    hides that unit-mass cannot hold the magnetic term, and the correction then pulls the data toward unit-mass's
    wrong equations. After the correction trace fits 70x better, so ``gauge="auto"`` takes it and recovers
    ``q x Dq``; on Kepler orbits (equal masses) the two fit alike after the correction and unit-mass is kept."""
    rng = np.random.default_rng(0)
    starts = (((0.0, 0.0), (1.0, 0.5)), ((1.0, -1.0), (-0.3, 0.8)))
    orbits = [systems.charged_particle(q0=q, v0=v, B=0.8, n=60, dt=0.1) for q, v in starts]
    data = [noisy(f, 1e-3, rng) for f in orbits]
    fixed = ldft.SparseLagrangian("kinetic + poly:2 + cross", threshold=0.1)
    rep_unit = ldft.learn(fixed, data, progress=False, noise="auto", gauge="unit-mass")
    assert "(q1*Dtq2-q2*Dtq1)" not in fixed.kept_terms()  # unit-mass: an isotropic oscillator in its place
    model = ldft.SparseLagrangian("kinetic + poly:2 + cross", threshold=0.1)
    rep = ldft.learn(model, data, progress=False, noise="auto")
    assert rep.noise is not None and rep.noise["method"] == "errors in variables"
    assert rep.gauge == "trace" and "after the noise correction" in rep.gauge_choice
    assert rep.gauge_scores["unit-mass"] == rep_unit.rel_res and rep.gauge_scores["trace"] == rep.rel_res
    assert model.kept_terms() == ["(Dtq1**2+Dtq2**2)", "(q1*Dtq2-q2*Dtq1)"]
    kin, mag = model.coef.detach().numpy()[model.coef.detach().numpy() != 0]
    assert mag / (2 * kin) == pytest.approx(0.4, rel=1e-2)  # B / 2
    kepler = [noisy(systems.kepler_orbit(1.0, v, dt=0.1, n=80), 1e-3, rng) for v in (0.9, 1.1)]
    rep_kepler = ldft.learn(ldft.SparseLagrangian("kinetic + norm:-1", threshold=0.1), kepler, noise="auto")
    assert rep_kepler.gauge == "unit-mass" and "after the noise correction" in rep_kepler.gauge_choice


def test_noise_correction_of_a_neural_model() -> None:
    """An iterative model is corrected too (refits from its previous weights): at sigma = 1e-3 a small
    kinetic-potential MLP serves 50 steps within 10 sigma and several times better than fitted plainly."""
    rng = np.random.default_rng(0)
    train = [noisy(duffing(q, 161), 1e-3, rng) for q in (0.6, 1.0, 1.3, 1.45, 1.6, 1.75)]
    ref = duffing(1.55, 51)
    test = noisy(ref, 1e-3, rng)
    errors = {}
    for mode in ("none", "correct"):
        model = ldft.MLPLagrangian(preset="kinetic-potential", hidden=[16, 16])
        rep = ldft.learn(model, train, progress=False, noise=mode, max_iter=200)
        start = test if mode == "none" else denoised_start(model, test)
        errors[mode] = served_error(model, start, ref)
    assert rep.noise is not None and rep.noise["method"] == "errors in variables" and rep.noise["rounds"] >= 1
    assert errors["correct"] < 1e-2
    assert errors["correct"] < errors["none"] / 5


def test_noise_correction_with_an_ensemble() -> None:
    """Member 0 is the noise-corrected model of a plain ``noise="correct"`` call; the other members learn on
    resamples of the corrected fields, so they fit them as well as member 0 fits (a noisy field fits worse)."""
    rng = np.random.default_rng(4)
    train = [noisy(duffing(q, 161), 1e-3, rng) for q in (0.6, 1.0, 1.3, 1.6, 1.75)]
    alone = ldft.PolynomialLagrangian(orders=(2, 6))
    rep_alone = ldft.learn(alone, train, progress=False, noise="correct")
    model = ldft.PolynomialLagrangian(orders=(2, 6))
    rep = ldft.learn(model, train, progress=False, noise="correct", ensemble=4)
    for k, v in alone.state_dict().items():
        assert np.array_equal(v.numpy(), model.state_dict()[k].numpy())
    assert rep.noise == rep_alone.noise and rep.ensemble is not None
    plain = ldft.learn(ldft.PolynomialLagrangian(orders=(2, 6)), train, progress=False)
    members = rep.ensemble["rel_res"]
    assert len(members) == 4 and members[0] == rep_alone.rel_res
    assert max(members) < plain.rel_res / 10
    std = ldft.serve(model.ensemble_, train[2].isel(t=slice(0, 2)), slices=40, progress=False).std
    assert std is not None and 0 < float(std.max()) < 1e-1


def test_denoise_moves_toward_the_del() -> None:
    model = ldft.PolynomialLagrangian(orders=(4, 8))
    ldft.learn(model, [duffing(q, 121) for q in (1.0, 1.45, 1.7)], progress=False)
    ref = duffing(1.55, 41)
    data = noisy(ref, 1e-3, np.random.default_rng(2))
    out = ldft.denoise(model, data)
    assert out.dims == data.dims and out.shape == data.shape
    assert float(abs(out - ref).max()) < 0.5 * float(abs(data - ref).max())
    start = denoised_start(model, data)
    assert np.array_equal(start.values[2:], data.values[2:])
    assert np.allclose(start.values[:2], ldft.denoise(model, data.isel(t=slice(0, DENOISE_SLICES))).values[:2])


def test_argument_errors_are_one_line() -> None:
    model = ldft.PolynomialLagrangian(orders=(2, 2))
    f = duffing(1.3, 41)
    cases = [
        (lambda: ldft.estimate_noise(42), "field: expected a field"),
        (lambda: ldft.estimate_noise([]), "field: expected a field"),
        (lambda: ldft.denoise(model, f), "model: PolynomialLagrangian is not bound"),
        (lambda: ldft.learn(model, f, noise="maybe"), "noise: expected 'auto', 'none' or 'correct'"),
        (lambda: ldft.learn(model, f, noise="auto", noise_sigma=-1.0), "noise_sigma: expected a number >= 0"),
    ]
    for call, msg in cases:
        with pytest.raises(InputError, match=msg) as info:
            call()
        assert "\n" not in str(info.value)
    ldft.learn(model, f, progress=False)
    for kw, msg in [({"strength": 0}, "strength: expected a number > 0"), ({"steps": 0}, "steps: expected")]:
        with pytest.raises(InputError, match=msg):
            ldft.denoise(model, f, **kw)
    with pytest.raises(InputError, match="field: expected a 1-D field of 1 component.*got 1-D with 2"):
        ldft.denoise(model, systems.kepler_orbit(1.0, 1.0, n=20))


def _edit(case: Path, old: str, new: str) -> None:
    text = (case / "case.toml").read_text()
    assert old in text
    (case / "case.toml").write_text(text.replace(old, new))


def test_case_keys(tmp_path: Path) -> None:
    case = tiny_wave(tmp_path)
    c = load_case(case)
    assert c.train.learn["noise"] == "none" and c.train.learn["noise_sigma"] is None and c.serve[0].start == "auto"
    c = load_case(case, ["train.noise=correct", "train.noise_sigma=0.001", "serve.test.start=denoised"])
    assert c.train.learn["noise"] == "correct" and c.train.learn["noise_sigma"] == 1e-3
    assert c.serve[0].start == "denoised"
    for override, msg in [
        ("train.noise=yes", "train.noise: expected 'none' or 'auto' or 'correct'"),
        ("train.noise_sigma=-1", "train.noise_sigma: expected a number >= 0"),
        ("serve.test.start=clean", "start: expected 'auto' or 'data' or 'denoised'"),
    ]:
        with pytest.raises(ConfigError, match=msg) as info:
            load_case(case, [override])
        assert "\n" not in str(info.value)


class _Task:
    def __init__(self, start: str):
        self.start, self.name = start, "t"


class _TaskData:
    def __init__(self, start: str, init: xr.DataArray):
        self.task, self.init = _Task(start), init


def test_serve_start_option() -> None:
    rng = np.random.default_rng(4)
    train = [noisy(duffing(q, 121), 1e-3, rng) for q in (1.0, 1.45, 1.7)]
    init = noisy(duffing(1.55, 41), 1e-3, rng)
    plain = ldft.PolynomialLagrangian(orders=(2, 4))
    ldft.learn(plain, train, progress=False)
    assert _start(plain, _TaskData("auto", init)) == (init, "data")  # no correction in training
    out, how = _start(plain, _TaskData("denoised", init))
    assert how == "denoised" and not np.array_equal(out.values[:2], init.values[:2])
    aware = ldft.PolynomialLagrangian(orders=(2, 4))
    ldft.learn(aware, train, progress=False, noise="auto")
    assert _start(aware, _TaskData("auto", init))[1] == "denoised"
    assert _start(aware, _TaskData("data", init)) == (init, "data")
    member0 = ldft.PolynomialLagrangian(orders=(2, 4))
    ldft.learn(member0, train, progress=False, noise="auto", ensemble=3)
    out_ens, how = _start(member0.ensemble_, _TaskData("auto", init))  # a case serves the ensemble
    assert how == "denoised" and np.allclose(out_ens.values, _start(aware, _TaskData("auto", init))[0].values)


def test_case_with_noise_correction_and_an_ensemble(tmp_path: Path, capsys) -> None:
    """A case learning noisy data with ``noise = "auto"`` and ``ensemble = 3``: the training corrects the
    fields, the members learn on them, the task starts from denoised slices and writes the spread."""
    import json

    rng = np.random.default_rng(5)
    case = tmp_path / "noisy"
    (case / "data").mkdir(parents=True)
    for i, q in enumerate((1.0, 1.3, 1.6)):
        write_field(case / "data" / f"train{i}.nc", {"psi": noisy(duffing(q, 121), 1e-3, rng)})
    write_field(case / "data" / "test.nc", {"psi": noisy(duffing(1.45, 41), 1e-3, rng)})
    write_toml(
        case,
        """
        [model]
        kind = "polynomial"
        orders = [2, 4]
        [train]
        data = ["data/train*.nc"]
        noise = "auto"
        ensemble = 3
        [[serve]]
        name = "test"
        from = "data/test.nc"
        [run]
        threads = 1
        [export]
        formats = []
        """,
    )
    code, out, err = run_cli(capsys, "run", case)
    assert code == 0, err
    summary = json.loads((case / "results" / "summary.json").read_text())
    train = summary["train"]
    assert train["noise"]["method"] == "errors in variables" and train["ensemble"]["members"] == 3
    task = summary["tasks"]["test"]
    assert task["complete"] and task["start"] == "denoised" and task["ensemble_members"] == 3
    with xr.open_dataset(case / "results" / "test.nc") as ds:
        assert {"psi", "psi_mean", "psi_std"} <= set(ds.data_vars)
        assert float(ds["psi_std"].isel(t=slice(2, None)).max()) > 0


# -- the sparse Hessian of the action behind the correction ------------------------------------------------


def _breather(nt: int, nx: int, sigma: float, seed: int) -> xr.DataArray:
    """A noisy sine-Gordon breather (|psi| up to 5), the field of the case's kind on a small lattice."""
    f = systems.sine_gordon_breather(0.3, xlim=(-4.0, 4.0), nx=nx, nt=nt, dt=0.05 * 8)
    return noisy(f, sigma, np.random.default_rng(seed))


def _learned(kind: str) -> tuple[ldft.AbstractLagrangian, xr.DataArray]:
    """A model learned on a small noisy field, and that field: a polynomial and a sparse library on a breather
    (closed-form second derivatives), a 2+1D polynomial on a membrane, an MLP on a two-component orbit (second
    derivatives by autograd)."""
    if kind in ("breather", "terms"):
        f = _breather(24, 17, 1e-3, 0)
        model: ldft.AbstractLagrangian = (
            ldft.PolynomialLagrangian(orders=(2, 6), time_symmetric=True)
            if kind == "breather"
            else ldft.SparseLagrangian("kinetic + gradient + trig:1")
        )
    elif kind == "membrane":
        f = noisy(systems.wave_membrane([(1, 1, 1.0), (2, 1, 0.3)], nx=7, ny=6, nt=9), 1e-3, np.random.default_rng(1))
        model = ldft.PolynomialLagrangian(orders=(2, 2))
    else:
        f = noisy(systems.kepler_orbit(1.0, 1.1, dt=0.1, n=30), 1e-3, np.random.default_rng(2))
        model = ldft.MLPLagrangian(hidden=[8])
    ldft.learn(model, f, progress=False, max_iter=20)
    return model, f


@pytest.mark.parametrize("kind", ["breather", "terms", "membrane", "orbit"])
@pytest.mark.parametrize("wrap", [False, True])
def test_sparse_action_hessian_equals_the_dense_one(kind: str, wrap: bool) -> None:
    """The Hessian assembled from per-cell blocks equals autograd's dense Hessian of the action, and its
    gradient autograd's gradient, on tiny lattices (with the spatial axes Dirichlet or periodic)."""
    model, data = _learned(kind)
    lf = as_lattice_field(data, source="field")
    psi = lf.values[:7].detach().clone()  # a few slices: a dense Hessian of some hundred values
    boundary = ("open",) + ("periodic" if wrap else "dirichlet",) * (lf.ndim - 1)

    def action(p: torch.Tensor) -> torch.Tensor:
        return _action(model, p, lf.spacing, boundary, 0)

    dense = torch.autograd.functional.hessian(action, psi).reshape(psi.numel(), psi.numel())
    x = psi.clone().requires_grad_(True)
    (grad,) = torch.autograd.grad(action(x), x)
    g, hess = action_hessian(model, psi, lf.spacing, boundary)
    scale = float(dense.abs().max())
    assert np.abs(hess.toarray() - dense.numpy()).max() <= 1e-13 * scale
    assert float((g - grad).abs().max()) <= 1e-13 * float(grad.abs().max())


def test_sparse_products_correct_as_the_double_backward_did(monkeypatch: pytest.MonkeyPatch) -> None:
    """The noise-aware fit and the denoised field with the assembled sparse Hessian equal those with a double
    backward pass per product (the conjugate gradients converged, to 1e-10 of their residual): the corrected
    coefficients to 1e-9 relative, the denoised field to 1e-9 of its move."""
    f = _breather(40, 25, 1e-3, 3)
    fits, moved = {}, {}
    for name in ("sparse", "autograd"):
        if name == "autograd":
            monkeypatch.setattr(_noise, "_products", autograd_products)  # the path replaced
        model = ldft.PolynomialLagrangian(orders=(2, 6), time_symmetric=True)
        rep = ldft.learn(model, f, progress=False, noise="correct")
        assert rep.noise is not None and rep.noise["rounds"] == _noise.ROUNDS
        fits[name] = (model.coef.detach().numpy().copy(), rep.noise["shift"])
        moved[name] = ldft.denoise(model, f.isel(t=slice(0, 12)), strength=1e3).values
    coef, ref = fits["sparse"][0], fits["autograd"][0]
    assert np.abs(coef - ref).max() <= 1e-9 * np.abs(ref).max()
    assert fits["sparse"][1] == pytest.approx(fits["autograd"][1], rel=1e-9)
    move = np.abs(moved["autograd"] - f.values[:12]).max()
    assert move > 1e-4 and np.abs(moved["sparse"] - moved["autograd"]).max() <= 1e-9 * move
