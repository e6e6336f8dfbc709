"""Regenerate data/ for the periodic Klein-Gordon benchmark (Offen & Ober-Blöbaum's setup).

    python make_data.py

L = u_t^2/2 - u_x^2/2 - u^2/2 on x in [0, 1) periodic, 20 sites (dx = 0.05), dt = 0.025. The data are the
peers' explicit scheme (u_{i+1} - 2u_i + u_{i-1})/dt^2 = D_xx u_i - u_i, i.e. the field served by
L_d = L(u_ij, (u_{i+1,j} - u_ij)/dt, (u_{i,j+1} - u_ij)/dx):

data/train_00.nc .. train_79.nc  80 solutions of 20 steps (21 slices, T = 0.5) from random smooth initial data
                                 and velocities (latticedft.systems.klein_gordon_training_set, seed 0: Fourier
                                 amplitudes N(0,1) exp(-2 k^4), so only the modes k = 0, 1 carry weight)
data/test.nc                     the unseen u0 = sin(4 pi x), u1 = u0 (mode k = 2) over 400 steps (401 slices)
data/travelling.nc               a wave of modes k = 1 and 3 travelling to the right, u(x) = sin(2 pi x) +
                                 0.3 cos(6 pi x) and u1 = u(x - 0.03), over 400 steps (its pseudo-momentum is
                                 not zero, unlike a standing wave's)

Deterministic (seeded); a few seconds.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from latticedft import systems
from latticedft.io import write_field

HERE = Path(__file__).resolve().parent
N_TRAIN, STEPS, SEED = 80, 20, 0
TEST_STEPS = 400
NX, DX = 20, 0.05


def travelling(shift: float) -> np.ndarray:
    x = DX * np.arange(NX)
    return np.sin(2 * np.pi * (x - shift)) + 0.3 * np.cos(6 * np.pi * (x - shift))


def main() -> None:
    data = HERE / "data"
    data.mkdir(exist_ok=True)
    history = "cases/klein-gordon-periodic/make_data.py"
    for m, f in enumerate(systems.klein_gordon_training_set(n=N_TRAIN, steps=STEPS, seed=SEED)):
        write_field(data / f"train_{m:02d}.nc", {"psi": f}, history=history)
    write_field(data / "test.nc", {"psi": systems.klein_gordon_test_field(steps=TEST_STEPS)}, history=history)
    wave = systems.klein_gordon(travelling(0.0), travelling(0.03), steps=TEST_STEPS)
    write_field(data / "travelling.nc", {"psi": wave}, history=history)
    total = sum(p.stat().st_size for p in data.glob("*.nc"))
    print(f"wrote {N_TRAIN} training fields, data/test.nc and data/travelling.nc ({total // 1024} kB in all)")


if __name__ == "__main__":
    main()
