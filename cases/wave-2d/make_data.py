"""Regenerate data/ for the 2+1D membrane case: psi_tt = psi_xx + psi_yy on the unit square, fixed frame.

    python make_data.py [--size N] [--steps S]

data/train.nc          one observed solution (exact standing modes), 41 slices
data/test.nc           another solution (other modes, amplitudes, phases, incl. modes the training lacks)
                       over S + 1 slices (default 240 steps, t in [0, 1.875]): `latticedft run` serves it from
                       its first two slices and its frame and scores the prediction against the rest
data/test_leapfrog.nc  the explicit leapfrog of the TRUE equation from the same two slices at the same dt, dx
                       (the baseline)

Lattice: N x N sites (default 65: 64 x 64 cells, dx = dy = 1/64), dt = dx/2. Exact solutions, no noise:
deterministic. The files are large (about 8 MB) and are not committed; run this script first.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from latticedft import systems
from latticedft.io import write_field

HERE = Path(__file__).resolve().parent
TRAIN_MODES = [(1, 1, 1.0), (2, 1, 0.4, 0.3), (1, 3, 0.25, 1.0), (3, 2, 0.15, 2.0)]
TEST_MODES = [(1, 2, 0.7, 0.5), (2, 2, -0.3), (3, 1, 0.25, 0.7), (4, 3, 0.1, 1.3)]


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=65, help="sites per side (default 65)")
    ap.add_argument("--steps", type=int, default=240, help="time steps of the test field (default 240)")
    ap.add_argument("--out", type=Path, default=HERE / "data", help="output folder (default data/)")
    args = ap.parse_args(argv)
    out = args.out
    out.mkdir(parents=True, exist_ok=True)
    n = args.size
    train = systems.wave_membrane(TRAIN_MODES, nx=n, ny=n, nt=41)
    test = systems.wave_membrane(TEST_MODES, nx=n, ny=n, nt=args.steps + 1)
    dt = float(test.t[1] - test.t[0])
    leap = systems.leapfrog(
        test.isel(t=0, drop=True),
        test.isel(t=1, drop=True),
        steps=args.steps,
        dt=dt,
        c=1.0,
        boundary="dirichlet",
        boundary_values=test.values,
    )
    leap = leap.assign_coords(t=test.t.values).rename("psi")
    leap.attrs["long_name"] = "leapfrog of psi_tt = psi_xx + psi_yy (baseline)"
    history = "cases/wave-2d/make_data.py"
    for name, f in (("train.nc", train), ("test.nc", test), ("test_leapfrog.nc", leap)):
        write_field(out / name, {"psi": f}, history=history)
        print(f"wrote {out.name}/{name} {dict(f.sizes)} ({(out / name).stat().st_size // 1024} kB)")


if __name__ == "__main__":
    main()
