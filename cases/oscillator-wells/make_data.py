"""Regenerate data/ for the oscillator-wells case (Qin 2020, Example 2).

    python make_data.py

    psi'' - 0.03 [sin(1 - psi^2) psi + 0.1] = 0,   psi'(0) = 0,

i.e. psi'' = -V'(psi), V = -0.015 [cos(psi^2 - 1) + 0.2 psi] (latticedft.systems.wells_potential):
a large well |psi| < 1.6 holding two small wells, (-1.3, -0.1) and (-0.1, 1.5), split by a
barrier at psi = -0.12. 51 samples at dt = 1, solved by latticedft.systems.oscillator_wells
(DOP853, rtol = atol = 1e-12). Exact solutions, no noise: the script is deterministic.

data/train_1.70.nc   the paper's training sequence, psi(0) = 1.7 (the large well)
data/train_1.65.nc   three more large-well sequences of slightly smaller amplitude
data/train_1.60.nc   (our default training set; the paper trains on train_1.70.nc alone)
data/train_1.55.nc
data/test_right.nc   psi(0) = 0.3: an oscillation in the right small well (0.3 ... 1.48)
data/test_left.nc    psi(0) = -0.4: an oscillation in the left small well (-1.25 ... -0.4)
"""

from __future__ import annotations

from pathlib import Path

from latticedft import systems
from latticedft.io import write_field

HERE = Path(__file__).resolve().parent
TRAIN = [1.7, 1.65, 1.6, 1.55]
TEST = {"test_right": 0.3, "test_left": -0.4}


def main() -> None:
    data = HERE / "data"
    data.mkdir(exist_ok=True)
    files = {f"train_{a:.2f}": a for a in TRAIN} | TEST
    for stem, psi0 in files.items():
        path = write_field(
            data / f"{stem}.nc",
            {"psi": systems.oscillator_wells(psi0, 0.0, n=51, dt=1.0)},
            history="cases/oscillator-wells/make_data.py",
        )
        print(f"wrote data/{path.name} ({path.stat().st_size // 1024} kB)")


if __name__ == "__main__":
    main()
