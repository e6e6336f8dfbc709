"""Bad input raises one clear, one-line error."""

from __future__ import annotations

import numpy as np
import pytest

import latticedft as ldft
from latticedft import lagrangians

from helpers import oscillator_data, series, wave_field


def _one_line(exc):
    text = str(exc.value)
    assert "\n" not in text and text
    return text


def test_nan_in_data():
    _, data = oscillator_data(steps=20)
    bad = data[0].copy()
    bad[5] = np.nan
    with pytest.raises(ldft.InputError) as err:
        ldft.learn(ldft.PolynomialLagrangian((2, 2)), [data[1], bad])
    assert "NaN" in _one_line(err)


def test_shape_mismatch_between_fields():
    _, data = oscillator_data(steps=20)
    with pytest.raises(ldft.InputError) as err:
        ldft.learn(ldft.PolynomialLagrangian((2, 2)), [data[0], wave_field(nt=20)])
    assert "data[1]" in _one_line(err) and "lattice dims" in str(err.value)


def test_component_mismatch():
    dt = 0.1
    a = series(np.random.rand(10, 2), dt, components=["x", "y"])
    b = series(np.random.rand(10, 2), dt, components=["x", "z"])
    with pytest.raises(ldft.InputError) as err:
        ldft.learn(ldft.PolynomialLagrangian((2, 2)), [a, b])
    assert "component" in _one_line(err) and "'z'" in str(err.value)


def test_component_mismatch_at_serve():
    dt = 0.05
    model = ldft.PolynomialLagrangian((2, 1))
    data = [
        ldft.serve(
            lagrangians.kepler(), series([[1.0, 0.0], [1.0, v * dt]], dt, components=["x", "y"]), slices=60
        ).field
        for v in (0.9, 1.0, 1.1)
    ]
    ldft.learn(model, data)
    other = series([[1.0, 0.0], [1.0, 0.05]], dt, components=["q", "p"])
    with pytest.raises(ldft.InputError) as err:
        ldft.serve(model, other, slices=10)
    assert "component labels" in _one_line(err)


def test_fewer_than_three_time_slices():
    with pytest.raises(ldft.InputError) as err:
        ldft.learn(ldft.PolynomialLagrangian((2, 2)), series([0.1, 0.2], 0.1))
    assert "at least 3" in _one_line(err)


def test_spacing_mismatch_at_serve():
    _, data = oscillator_data(steps=20)
    model = ldft.PolynomialLagrangian((2, 2))
    ldft.learn(model, data)
    with pytest.raises(ldft.InputError) as err:
        ldft.serve(model, series([0.1, 0.2], 0.2), slices=5)
    assert "spacing" in _one_line(err) and "0.1" in str(err.value)


def test_unlearned_model_cannot_serve():
    with pytest.raises(ldft.InputError) as err:
        ldft.serve(ldft.PolynomialLagrangian((2, 2)), series([0.1, 0.2], 0.1), slices=5)
    assert "not been learned" in _one_line(err)


def test_bad_options():
    with pytest.raises(ldft.InputError, match="orders"):
        ldft.PolynomialLagrangian(orders=(2,))
    with pytest.raises(ldft.InputError, match="activation"):
        ldft.MLPLagrangian(activation="relu")
    with pytest.raises(ldft.InputError, match="gauge"):
        ldft.learn(ldft.PolynomialLagrangian((2, 2)), oscillator_data(steps=20)[1], gauge="wrong")
    with pytest.raises(ldft.InputError, match="mode"):
        ldft.serve(lagrangians.wave(), wave_field(nt=5), mode="fast")
    with pytest.raises(ldft.InputError, match="slices"):
        ldft.serve(lagrangians.wave(), wave_field(nt=5), slices=2)
    with pytest.raises(ldft.InputError, match="boundary"):
        ldft.serve(lagrangians.wave(), wave_field(nt=5), boundary={"y": "periodic"})


def test_not_a_dataarray():
    with pytest.raises(ldft.InputError, match="DataArray"):
        ldft.learn(ldft.PolynomialLagrangian((2, 2)), np.zeros(10))


def test_bad_stencils():
    with pytest.raises(ldft.InputError, match="anchor"):
        ldft.Stencil([[1, 0], [1, 1]])
    with pytest.raises(ldft.InputError, match="time offsets"):
        ldft.Stencil([[0, 0], [1, 0], [2, 0]])
    with pytest.raises(ldft.InputError, match="distinct"):
        ldft.Stencil([[0], [1], [1]])
    model = ldft.PolynomialLagrangian((2, 2), stencil=ldft.Stencil.first_order(3))
    with pytest.raises(ldft.InputError, match="stencil"):
        ldft.learn(model, wave_field(nt=10))


def test_non_uniform_coordinate():
    field = wave_field(nt=10)
    t = field.t.values.copy()
    t[3] += 1e-3
    with pytest.raises(ldft.InputError, match="uniform"):
        ldft.learn(ldft.PolynomialLagrangian((2, 2)), field.assign_coords(t=t))


# -- errors carry the key they concern -------------------------------------------------------------------------
def test_errors_carry_their_key():
    err = ldft.InputError.at("optimizer", "expected 'exact', 'lbfgs' or 'adam', got 'sgd'")
    assert str(err) == "optimizer: expected 'exact', 'lbfgs' or 'adam', got 'sgd'"
    assert err.key == "optimizer" and err.problem == "expected 'exact', 'lbfgs' or 'adam', got 'sgd'"
    plain = ldft.InputError("data: no training fields given")
    assert plain.key is None and plain.problem == str(plain)
    with pytest.raises(ldft.InputError) as info:
        ldft.learn(ldft.PolynomialLagrangian((2, 2)), oscillator_data(steps=20)[1], gauge="wrong")
    assert info.value.key == "gauge" and str(info.value).startswith("gauge: expected one of")
    with pytest.raises(ldft.InputError) as info:
        ldft.learn(ldft.MLPLagrangian(hidden=[4]), oscillator_data(steps=20)[1], optimizer="exact")
    assert info.value.key == "optimizer" and "needs a model linear" in info.value.problem


@pytest.mark.parametrize(
    "edit,key,text",
    [
        (
            ("[train]\n", '[train]\nboundary = {y = "periodic"}\n'),
            "train.boundary",
            "case.toml: train.boundary: unknown axis 'y'; the spatial axes of ",
        ),
        (
            ('name = "test"\n', 'name = "test"\nboundary = {z = "periodic"}\n'),
            "serve[0].boundary",
            "case.toml: serve[0].boundary: unknown axis 'z'; the spatial axes of ",
        ),
    ],
)
def test_case_errors_readdress_the_boundary_key(tmp_path, edit, key, text):
    from latticedft._case import load_case
    from latticedft._run import check_case

    from case_helpers import tiny_wave

    case = tiny_wave(tmp_path)
    toml = (case / "case.toml").read_text()
    (case / "case.toml").write_text(toml.replace(*edit))
    with pytest.raises(ldft.ConfigError) as info:
        check_case(load_case(case))
    assert str(info.value).startswith(text) and _one_line(info).endswith("are ['x']")
    assert info.value.key == key


@pytest.mark.parametrize(
    "option,key,text",
    [
        (
            'optimizer = "exact"',
            "train.optimizer",
            "case.toml: train.optimizer: 'exact' needs a model linear in its parameters; 'mlp' is not",
        ),
        (
            'ridge = "auto"',
            "train.ridge",
            "case.toml: train.ridge: 'auto' needs two or more fields, or one field of at least 9 time slices",
        ),
    ],
)
def test_case_errors_readdress_learn_keys(tmp_path, option, key, text):
    from latticedft._case import load_case
    from latticedft._run import check_case, train_model

    from case_helpers import tiny_wave

    case = tiny_wave(tmp_path)
    toml = (case / "case.toml").read_text()
    if key == "train.optimizer":
        toml = toml.replace('kind = "polynomial"\norders = [2, 0]', 'kind = "mlp"\nhidden = [4]')
    else:  # one field of 4 slices
        from latticedft import systems
        from latticedft.io import write_field

        write_field(case / "data" / "train.nc", {"psi": systems.wave_string([(1, 1.0)], nx=13, nt=4)})
    (case / "case.toml").write_text(toml.replace("[train]\n", f"[train]\n{option}\n"))
    c = load_case(case)
    with pytest.raises(ldft.ConfigError) as info:
        train_model(c, check_case(c))
    assert _one_line(info) == text and info.value.key == key
