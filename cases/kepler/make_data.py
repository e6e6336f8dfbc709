"""Regenerate data/ for the Kepler case (Qin 2020, Sec. 4).

    python make_data.py

Units 1 au and 58.14 days, so GM = 1; time step dt = 0.05. Newton's equations
r'' = -r / |r|^3 solved by latticedft.systems (DOP853, rtol = atol = 1e-12).
Exact solutions, no noise: the script is deterministic.

data/train_<planet>.nc   one period of Mercury, Venus, Earth, Mars, Ceres and Jupiter, each
                         launched from its aphelion (systems.planet_orbit)
data/earth_<v>.nc        launches from Earth's aphelion point (1.0167, 0) with velocity (0, v),
                         v = 0.98, 1.13, 1.26, 1.40, 1.50 (escape speed there: 1.4026)
data/mercury_<v>.nc      launches from Mercury's aphelion point (0.4667, 0),
                         v = 1.30, 1.56, 1.80, 2.07, 2.20 (escape speed there: 2.0702)

A launch whose orbit stays within r < 10 is recorded for one period of the true orbit; the
others (the hyperbolic v = 1.50 and 2.20, and the nearly parabolic v = 1.40 and 2.07 whose
true periods are 1e4 and 5e5 time units) for t <= 30, by which time the truth is beyond
r = 10. `latticedft run` serves each from its first two slices (box = 10 stops an escaping
orbit) and scores the prediction against the rest.
"""

from __future__ import annotations

from pathlib import Path

from latticedft import systems
from latticedft.io import write_field

HERE = Path(__file__).resolve().parent
DT = 0.05
LAUNCHES = {"earth": (1.0167, [0.98, 1.13, 1.26, 1.40, 1.50]), "mercury": (0.4667, [1.30, 1.56, 1.80, 2.07, 2.20])}
BOX = 10.0
T_ESCAPE = 30.0


def launch(r0: float, v0: float):
    energy = 0.5 * v0 * v0 - 1.0 / r0
    if energy < 0 and -1.0 / energy - r0 < BOX:  # bound, apocentre 2a - r0 inside the box
        return systems.kepler_orbit(r0, v0, dt=DT)  # one period
    return systems.kepler_orbit(r0, v0, dt=DT, t_end=T_ESCAPE)


def main() -> None:
    data = HERE / "data"
    data.mkdir(exist_ok=True)
    history = "cases/kepler/make_data.py"
    files = {f"train_{p.lower()}": systems.planet_orbit(p, dt=DT) for p in systems.PLANETS}
    for body, (r0, speeds) in LAUNCHES.items():
        files |= {f"{body}_{v:.2f}": launch(r0, v) for v in speeds}
    for stem, orbit in files.items():
        path = write_field(data / f"{stem}.nc", {"psi": orbit}, history=history)
        print(f"wrote data/{path.name} ({orbit.sizes['t']} slices, {path.stat().st_size // 1024} kB)")


if __name__ == "__main__":
    main()
