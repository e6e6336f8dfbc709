"""Regenerate data/ for the wave case: a string with fixed ends, psi_tt = c^2 psi_xx (c = 1, L = 1).

    python make_data.py

data/train.nc         one observed solution (three standing modes), 81 slices (t in [0, 1])
data/test.nc          another solution (other amplitudes and phases, and mode 4 which the training
                      data lack) over 401 slices (t in [0, 5], five times the training duration):
                      `latticedft run` serves it from its first two slices and its fixed ends and
                      scores the prediction against the rest
data/test_leapfrog.nc the explicit leapfrog scheme of the TRUE equation from the same two slices at
                      the same dt, dx: the baseline a hand-written integrator reaches

Exact solutions, no noise: the script is deterministic.
"""

from __future__ import annotations

from pathlib import Path

from latticedft import systems
from latticedft.io import write_field

HERE = Path(__file__).resolve().parent
NX = 41  # dx = 1/40; dt = dx/2 (Courant number 1/2, the wave_string default)
TRAIN_MODES = [(1, 1.0), (2, 0.5, 0.3), (3, 0.25, 1.0)]
TEST_MODES = [(1, 0.6, 0.5), (2, -0.4), (4, 0.15, 0.7)]


def main() -> None:
    data = HERE / "data"
    data.mkdir(exist_ok=True)
    train = systems.wave_string(TRAIN_MODES, nx=NX, nt=81)
    test = systems.wave_string(TEST_MODES, nx=NX, nt=401)
    dt = float(test.t[1] - test.t[0])
    leap = systems.leapfrog(
        test.isel(t=0, drop=True),
        test.isel(t=1, drop=True),
        steps=test.sizes["t"] - 1,
        dt=dt,
        c=1.0,
        boundary="dirichlet",
    )
    leap = leap.assign_coords(t=test.t.values).rename("psi")
    leap.attrs["long_name"] = "leapfrog of psi_tt = psi_xx (baseline)"
    history = "cases/wave/make_data.py"
    write_field(data / "train.nc", {"psi": train}, history=history)
    write_field(data / "test.nc", {"psi": test}, history=history)
    write_field(data / "test_leapfrog.nc", {"psi": leap}, history=history)
    for p in ("train.nc", "test.nc", "test_leapfrog.nc"):
        print(f"wrote data/{p} ({(data / p).stat().st_size // 1024} kB)")


if __name__ == "__main__":
    main()
