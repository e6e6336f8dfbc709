"""Boundary kinds have one owner (latticedft._boundary): vocabulary, parsing, index rules, strips check."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
import torch
import xarray as xr

import latticedft as ldft
from latticedft import _boundary, _case, systems
from latticedft._boundary import (
    KINDS,
    BoundaryKind,
    axis_kinds,
    boundary_kinds,
    kind,
    missing_edges,
    parse_boundary,
)
from latticedft._errors import InputError
from latticedft._lattice import gather_cells, interior_slices

from helpers import wave_field


def test_vocabulary() -> None:
    assert boundary_kinds() == ("dirichlet", "periodic")
    assert _case.boundary_kinds is boundary_kinds
    assert {k.name for k in KINDS.values()} == {"dirichlet", "periodic", "open"} and not KINDS["open"].selectable
    assert kind(True) is KINDS["periodic"] and kind(False) is KINDS["dirichlet"] and kind(KINDS["open"]).name == "open"
    assert [k.name for k in axis_kinds(("open", True, "dirichlet"))] == ["open", "periodic", "dirichlet"]


# -- parsing the boundary argument ---------------------------------------------------------------------------
def test_parse() -> None:
    dims = ("t", "y", "x")
    assert parse_boundary("periodic", dims, "f") == ("open", "periodic", "periodic")
    assert parse_boundary({"x": "periodic"}, dims, "f") == ("open", "dirichlet", "periodic")
    assert parse_boundary({}, dims, "f") == ("open", "dirichlet", "dirichlet")


@pytest.mark.parametrize(
    "arg,problem",
    [
        ({"z": "periodic"}, "unknown axis 'z'; the spatial axes of init are ['y', 'x']"),
        ("wrap", "axis 'y' has kind 'wrap'; expected one of ['dirichlet', 'periodic']"),
        ({"x": "open"}, "axis 'x' has kind 'open'; expected one of ['dirichlet', 'periodic']"),
        (3, "expected 'dirichlet', 'periodic' or a table axis -> kind, got 3"),
    ],
)
def test_parse_errors_are_one_line_and_keyed(arg, problem: str) -> None:
    with pytest.raises(InputError) as err:
        parse_boundary(arg, ("t", "y", "x"), "init")
    assert str(err.value) == f"boundary: {problem}"
    assert err.value.key == "boundary" and err.value.problem == problem


def test_serve_and_learn_errors_carry_the_key() -> None:
    with pytest.raises(InputError) as err:
        ldft.serve(ldft.lagrangians.wave(), wave_field(nt=5), boundary={"y": "periodic"})
    assert err.value.key == "boundary" and str(err.value).startswith("boundary: unknown axis 'y'")
    with pytest.raises(InputError) as err:
        systems.leapfrog(np.zeros(5), np.zeros(5), 3, 0.1, 0.1, boundary="wrap")
    assert str(err.value) == "boundary: expected 'dirichlet' or 'periodic', got 'wrap'" and err.value.key == "boundary"
    with pytest.raises(InputError, match="boundary_values: only used with boundary='dirichlet'"):
        systems.leapfrog(np.zeros(5), np.zeros(5), 3, 0.1, 0.1, boundary="periodic", boundary_values=np.zeros((4, 5)))


# -- the index rules per kind --------------------------------------------------------------------------------
def test_rules_per_kind() -> None:
    d, p, o = KINDS["dirichlet"], KINDS["periodic"], KINDS["open"]
    assert (d.cells(7, 1), p.cells(7, 1), o.cells(7, 2)) == (6, 7, 5)
    assert (d.interior(7, 1), p.interior(7, 1), o.interior(7, 2)) == (slice(1, 6), slice(None), slice(2, 5))
    assert p.sites(np.array([-1, 0, 7, 8]), 7).tolist() == [6, 0, 0, 1]
    assert d.sites(np.array([0, 3, 6]), 7).tolist() == [0, 3, 6]
    assert d.given_edges and not p.given_edges and not o.given_edges and p.wraps and not d.wraps


@pytest.mark.parametrize("name", ["dirichlet", "periodic", "open"])
def test_fast_paths_equal_the_generic_rules(name: str) -> None:
    """What a new kind gets from cells/sites/interior alone equals the dirichlet/periodic fast paths."""
    k = KINDS[name]
    v = torch.arange(2 * 7 * 3, dtype=torch.float64).reshape(2, 7, 3)
    u = v.numpy()
    for start, width in [(0, 1), (1, 1), (0, 2), (2, 2)]:
        assert torch.equal(k.take(v, 1, start, 7, width), BoundaryKind.take(k, v, 1, start, 7, width))
    for shift in (-1, 1):
        assert np.array_equal(k.shifted(u, 1, shift, 1), BoundaryKind.shifted(k, u, 1, shift, 1))


def _naive_cells(psi: np.ndarray, stencil: ldft.Stencil, periodic: tuple[bool, ...]) -> np.ndarray:
    n = stencil.ndim
    lo, width = stencil.lo, stencil.width
    cshape = [psi.shape[k] if periodic[k] else psi.shape[k] - width[k] for k in range(n)]
    out = np.empty((*cshape, stencil.size, *psi.shape[n:]))
    for cell in itertools.product(*[range(c) for c in cshape]):
        for a, off in enumerate(stencil.offsets):
            site = [cell[k] + off[k] - lo[k] for k in range(n)]
            site = [s % psi.shape[k] if periodic[k] else s for k, s in enumerate(site)]
            out[(*cell, a)] = psi[tuple(site)]
    return out


@pytest.mark.parametrize(
    "periodic", [(False, False, False), (False, True, False), (False, False, True), (False, True, True)]
)
def test_gather_cells_and_interior(periodic: tuple[bool, ...]) -> None:
    rng = np.random.default_rng(0)
    psi = rng.standard_normal((4, 5, 6, 2))
    stencil = ldft.Stencil.full_cell(3)
    names = tuple(["open"] + ["periodic" if p else "dirichlet" for p in periodic[1:]])
    cells = gather_cells(torch.from_numpy(psi), stencil, names)
    assert np.array_equal(cells.numpy(), _naive_cells(psi, stencil, periodic))
    assert torch.equal(gather_cells(torch.from_numpy(psi), stencil, periodic), cells)  # flags: the same kinds
    batched = gather_cells(torch.from_numpy(np.stack([psi, 2 * psi])), stencil, names, batch=1)
    assert torch.equal(batched[1], 2 * cells)
    inner = interior_slices(psi.shape[:3], stencil, names)
    assert inner == tuple(slice(None) if p else slice(1, n - 1) for p, n in zip(periodic, psi.shape))
    assert interior_slices(psi.shape[:3], stencil, periodic) == inner


# -- the Dirichlet strips ------------------------------------------------------------------------------------
def test_missing_edges() -> None:
    dims = ("t", "y", "x")
    assert missing_edges(("open", "periodic", "dirichlet"), dims, 2, 10) == ("x", KINDS["dirichlet"])
    assert missing_edges(("open", "periodic", "periodic"), dims, 2, 10) is None
    assert missing_edges(("open", "dirichlet", "dirichlet"), dims, 10, 10) is None
    assert missing_edges((False, False, True), dims, 3, 4)[0] == "y"


def test_strips_checked_by_serve() -> None:
    field = wave_field(nt=8)
    with pytest.raises(InputError, match="the Dirichlet boundary along 'x' needs its strips on all 30 slices"):
        ldft.serve(ldft.lagrangians.wave(), field.isel(t=slice(0, 2)), slices=30)
    out = ldft.serve(ldft.lagrangians.wave(), field.isel(t=slice(0, 2)), slices=30, boundary="periodic")
    assert out.complete and out.field.sizes["t"] == 30


# -- the reference leapfrog scheme follows the kinds ---------------------------------------------------------
def _by_hand(u0, u1, steps, dt, h, periodic):
    out = [u0, u1]
    for _ in range(1, steps):
        u, up = out[-1], out[-2]
        if periodic:
            lap = (np.roll(u, -1) - 2.0 * u + np.roll(u, 1)) / (h * h)
            new = 2.0 * u - up + dt * dt * lap
        else:
            new = u1.copy()
            new[1:-1] = 2.0 * u[1:-1] - up[1:-1] + dt * dt * ((u[2:] - 2.0 * u[1:-1] + u[:-2]) / (h * h))
        out.append(new)
    return np.array(out)


@pytest.mark.parametrize("boundary", ["dirichlet", "periodic"])
def test_leapfrog_is_the_scheme_bit_for_bit(boundary: str) -> None:
    x = np.linspace(0.0, 1.0, 17)
    u0, u1 = np.sin(np.pi * x), 0.99 * np.sin(np.pi * x)
    out = systems.leapfrog(u0, u1, 20, 0.03, 1 / 16, boundary=boundary)
    assert np.array_equal(out, _by_hand(u0, u1, 20, 0.03, 1 / 16, boundary == "periodic"))


class _Reflecting(BoundaryKind):
    """A toy kind: the axis mirrors at its end sites (index -1 is index 1); every site is stepped."""

    name, title = "reflecting", "reflecting"

    def cells(self, n: int, width: int) -> int:
        return n

    def sites(self, index: np.ndarray, n: int) -> np.ndarray:
        index = np.abs(index)
        return np.where(index > n - 1, 2 * (n - 1) - index, index)

    def interior(self, n: int, width: int) -> slice:
        return slice(None)


def test_a_new_kind_is_one_registry_entry(monkeypatch: pytest.MonkeyPatch) -> None:
    """Registering a kind in the boundary module is enough for parsing, cells, interior and the leapfrog."""
    monkeypatch.setitem(_boundary.KINDS, "reflecting", _Reflecting())
    assert parse_boundary("reflecting", ("t", "x"), "f") == ("open", "reflecting")
    psi = torch.arange(12, dtype=torch.float64).reshape(3, 4, 1)
    cells = gather_cells(psi, ldft.Stencil.first_order(2), ("open", "reflecting"))
    assert cells.shape == (2, 4, 3, 1) and cells[0, 3, 2, 0] == psi[0, 2, 0]  # the right neighbour of site 3 is 2
    assert interior_slices((3, 4), ldft.Stencil.first_order(2), ("open", "reflecting")) == (slice(1, 2), slice(None))
    x = np.linspace(0.0, 1.0, 9)
    u0 = np.cos(np.pi * x)
    out = systems.leapfrog(u0, u0, 6, 0.05, 1 / 8, boundary="reflecting")
    ghost = np.pad(u0, 1, mode="reflect")  # Neumann by mirror ghosts, by hand
    step = 2.0 * u0 - u0 + 0.05**2 * (ghost[2:] - 2.0 * u0 + ghost[:-2]) / (1 / 8) ** 2
    assert np.array_equal(out[2], step)


def test_strips_checked_by_the_case_run(tmp_path) -> None:
    from latticedft._case import load_case
    from latticedft._run import check_case

    from case_helpers import tiny_wave

    case = tiny_wave(tmp_path)
    with pytest.raises(ldft.ConfigError) as err:
        check_case(load_case(case, ["serve.test.slices=50"]))
    assert str(err.value) == (
        "case.toml: serve[0].slices: 50 slices need the Dirichlet strips along 'x' on every "
        "slice, but test.nc holds 30; give the whole field, fewer slices or serve[0].boundary_value"
    )
    assert err.value.key == "serve[0].slices"
    check_case(load_case(case, ["serve.test.slices=50", "serve.test.boundary=periodic"]))


def test_boundary_value_serves_past_the_end_of_the_data() -> None:
    """A number or a function of (t, *coords) gives the Dirichlet strips beyond the data: the served field
    equals the one served from the whole field (whose strips hold those values), on the whole-field and the
    windowed (``every``) paths; without it the strips are missing."""
    train = systems.wave_string([(1, 1.0), (2, 0.5, 0.3)], nx=13, nt=41)
    whole = systems.wave_string([(1, 0.6, 0.5), (3, 0.2)], nx=13, nt=61)
    whole = whole.copy(data=whole.values.copy())
    whole.values[:, [0, -1]] = 0.0
    model = ldft.PolynomialLagrangian(orders=(2, 2))
    ldft.learn(model, train)
    expected = ldft.serve(model, whole).field.values
    head = whole.isel(t=slice(0, 2))
    served = ldft.serve(model, head, slices=61, boundary_value=0.0).field
    np.testing.assert_array_equal(served.values, expected)
    by_function = ldft.serve(model, whole.isel(t=slice(0, 20)), slices=61, boundary_value=lambda t, x: 0.0 * x)
    np.testing.assert_array_equal(by_function.field.values, expected)
    windowed = ldft.serve(model, head, slices=61, boundary_value=0.0, every=7).field
    np.testing.assert_array_equal(windowed.values, expected[windowed["slice"].values])
    with pytest.raises(ldft.InputError, match="boundary_value"):
        ldft.serve(model, head, slices=61)
    with pytest.raises(ldft.InputError, match="boundary_value: the function returned shape"):
        ldft.serve(model, head, slices=61, boundary_value=lambda t, x: np.zeros(3))


def test_boundary_value_in_a_case(tmp_path, capsys) -> None:
    from case_helpers import run_cli, tiny_wave

    case = tiny_wave(tmp_path)
    (case / "edges.py").write_text("def zero(t, x):\n    return 0.0 * x\n")
    code, _, err = run_cli(capsys, "check", case, "--set", "serve.test.slices=50")
    assert code == 1 and "boundary_value" in err
    for value in ("0.0", '"edges:zero"'):
        code, _, err = run_cli(
            capsys,
            "run",
            case,
            "-q",
            "--overwrite",
            "--set",
            "serve.test.slices=50",
            "--set",
            f"serve.test.boundary_value={value}",
        )
        assert code == 0, err
        with xr.open_dataset(case / "results" / "test.nc") as ds:
            assert ds.sizes["t"] == 50 and np.isfinite(ds["psi"].values).all()
    code, _, err = run_cli(capsys, "check", case, "--set", "serve.test.boundary_value=[1]")
    assert code == 1 and "serve[0].boundary_value" in err and len(err.strip().splitlines()) == 1
    code, _, err = run_cli(
        capsys,
        "run",
        case,
        "-q",
        "--overwrite",
        "--set",
        "serve.test.slices=50",
        "--set",
        'serve.test.boundary_value="edges:none"',
    )
    assert code == 1 and "serve[0].boundary_value 'edges:none': module 'edges' has no function 'none'" in err, err
