"""Inputs shared by several benchmarks: lattices, reference fields and learned models (built on demand)."""

from __future__ import annotations

import functools
import math

import numpy as np
import torch
import xarray as xr

import latticedft as ldft
from latticedft import systems

DT, DX = 0.025, 0.05  # the Klein-Gordon benchmark's lattice (Courant number 1/2); used for every 1+1D field


def string_field(nx: int, nt: int, boundary: str, force=None) -> tuple[np.ndarray, xr.DataArray]:
    """A smooth 1+1D field of ``nt`` slices on ``nx`` sites from the numpy leapfrog of the true equation.

    Dirichlet: three half waves with fixed (zero) ends; periodic: three wavelengths. The field starts at
    rest (``psi_1 = psi_0``). Returns the array and its DataArray (periodic ``x`` marked as such).
    """
    x = DX * np.arange(nx)
    if boundary == "periodic":
        u0 = 0.5 * np.sin(2 * np.pi * 3 * x / (nx * DX))
    else:
        u0 = 0.5 * np.sin(np.pi * 3 * x / x[-1])
        u0[[0, -1]] = 0.0
    u = systems.leapfrog(u0, u0.copy(), nt - 1, DT, DX, force=force, boundary=boundary)
    attrs = {"x": {"periodic": "true", "period": nx * DX}} if boundary == "periodic" else None
    return u, systems.make_field(u, ("t", "x"), spacing=(DT, DX), coord_attrs=attrs)


def membrane_field(n: int, nt: int) -> tuple[np.ndarray, xr.DataArray]:
    """A 2+1D wave on an ``n x n`` membrane with a fixed frame, ``nt`` slices (numpy leapfrog, Courant 1/2)."""
    h = 1.0 / (n - 1)
    dt = 0.5 * h  # c dt sqrt(2) / h = 0.71 <= 1: stable
    y = h * np.arange(n)
    u0 = 0.5 * np.outer(np.sin(2 * np.pi * y), np.sin(np.pi * y))
    u0[[0, -1], :] = 0.0
    u0[:, [0, -1]] = 0.0
    u = systems.leapfrog(u0, u0.copy(), nt - 1, dt, h)
    return u, systems.make_field(u, ("t", "y", "x"), spacing=(dt, h, h))


def kg_force(u: np.ndarray) -> np.ndarray:
    return -u


@functools.lru_cache(maxsize=2)
def kg_mlp(quick: bool) -> ldft.MLPLagrangian:
    """A kinetic-potential MLP ``L_d`` (1 -> 10 -> 10 -> 1 tanh potential) learned on periodic Klein-Gordon data."""
    torch.manual_seed(0)
    data = systems.klein_gordon_training_set(n=4 if quick else 8, steps=20, seed=0)
    model = ldft.MLPLagrangian(hidden=[10, 10], activation="tanh", form="kinetic-potential", seed=0)
    ldft.learn(model, data, max_iter=3 if quick else 40, max_time=10.0, progress=False)
    return model


def kepler_training(quick: bool) -> list[xr.DataArray]:
    """The paper's training orbits (Sec. 4): six bodies, dt = 0.05, one period each (fewer when quick)."""
    names = ["Mercury", "Venus", "Earth"] if quick else list(systems.PLANETS)
    return [systems.planet_orbit(p, dt=0.05) for p in names]


@functools.lru_cache(maxsize=2)
def kepler_mlp(quick: bool) -> ldft.MLPLagrangian:
    """The Kepler-sized MLP of the serving benchmark: kinetic-potential form, V = net(1/|q|), 1 -> 40 -> 40 -> 1,
    bound to dt = 0.05, m = 2 and learned for a few seconds with L-BFGS (the serving cost does not depend on
    how well it is learned, only on the network's size and the Newton iterations)."""
    model = ldft.MLPLagrangian(
        hidden=[40, 40], activation="tanh", form="kinetic-potential", features="inverse-radius", seed=0
    )
    ldft.learn(
        model, kepler_training(quick), max_iter=2 if quick else 60, max_time=2.0 if quick else 15.0, progress=False
    )
    return model


def kepler_inits(count: int, n: int = 3) -> list[xr.DataArray]:
    """``count`` bound orbits (first ``n`` slices each), radii 0.6 .. 2.5 au, speeds 0.9 .. 1.05 circular."""
    out = []
    for k in range(count):
        r0 = 0.6 + 1.9 * k / max(count - 1, 1)
        v0 = (0.9 + 0.15 * ((k * 7) % count) / max(count - 1, 1)) / math.sqrt(r0)
        out.append(systems.kepler_orbit(r0, v0, dt=0.05, n=n))
    return out
