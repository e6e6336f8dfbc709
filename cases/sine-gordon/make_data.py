"""Regenerate data/ for the sine-Gordon case: psi_tt - psi_xx + sin psi = 0 on x in [-20, 20], dx = 0.1, dt = 0.05.

    python make_data.py

data/train.nc                  ONE observed breather at rest, omega = 0.3 (|psi| <= 5.06), t in [0, 20]
data/breather.nc               another breather: omega = 0.7, moving at v = 0.3 from x0 = -3, t in [0, 20]
data/kink_antikink.nc          a kink-antikink collision, v = 0.5, t in [-2, 2] (|psi| <= 4.94, inside the
                               training range; later the field tends to 2 pi, outside it)
data/*_leapfrog.nc             the explicit leapfrog of the TRUE equation from the same first two slices and
                               the same boundary strips at the same dt, dx (the baseline)

All exact solutions (latticedft.systems), sampled; deterministic. `latticedft run` serves the test fields from
their first two slices and their end strips (Dirichlet) and scores them against the exact solutions.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from latticedft import systems
from latticedft.io import write_field

HERE = Path(__file__).resolve().parent
LATTICE = {"xlim": (-20.0, 20.0), "nx": 401, "dt": 0.05}


def _leapfrog(ref):
    dt = float(ref.t[1] - ref.t[0])
    lf = systems.leapfrog(
        ref.isel(t=0, drop=True),
        ref.isel(t=1, drop=True),
        steps=ref.sizes["t"] - 1,
        dt=dt,
        force=lambda u: -np.sin(u),
        boundary="dirichlet",
        boundary_values=ref.values,
    )
    lf = lf.assign_coords(t=ref.t.values).rename("psi")
    lf.attrs["long_name"] = "leapfrog of psi_tt = psi_xx - sin psi (baseline)"
    return lf


def main() -> None:
    data = HERE / "data"
    data.mkdir(exist_ok=True)
    history = "cases/sine-gordon/make_data.py"
    fields = {
        "train": systems.sine_gordon_breather(0.3, nt=401, **LATTICE),
        "breather": systems.sine_gordon_breather(0.7, velocity=0.3, x0=-3.0, nt=401, **LATTICE),
        "kink_antikink": systems.kink_antikink(0.5, nt=81, t0=-2.0, **LATTICE),
    }
    for name, f in fields.items():
        write_field(data / f"{name}.nc", {"psi": f}, history=history)
        if name != "train":
            write_field(data / f"{name}_leapfrog.nc", {"psi": _leapfrog(f)}, history=history)
    total = sum(p.stat().st_size for p in data.glob("*.nc"))
    print(f"wrote {len(list(data.glob('*.nc')))} files to data/ ({total // 1024} kB)")


if __name__ == "__main__":
    main()
