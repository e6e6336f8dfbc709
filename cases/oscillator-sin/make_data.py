"""Regenerate data/ for the oscillator-sin case (Qin 2020, Example 1).

    python make_data.py

    2 (sin psi + 1) psi'' + psi'^2 cos psi + pi^2/200 psi = 0,   psi'(0) = 0,

51 samples at dt = 1 (t = 0 ... 50), solved by latticedft.systems.oscillator_sin
(DOP853, rtol = atol = 1e-12). Exact solutions, no noise: the script is deterministic.

data/train_1.20.nc   the paper's training sequence, psi(0) = 1.2
data/train_0.80.nc   two more sequences of smaller amplitude (our default training set;
data/train_0.40.nc   the paper trains on train_1.20.nc alone, see README.md)
data/test_m0.60.nc   the paper's test from psi(0) = -0.6 (Fig. 3)
data/test_0.10.nc    the paper's test from psi(0) = 0.1 (Fig. 4)
"""

from __future__ import annotations

from pathlib import Path

from latticedft import systems
from latticedft.io import write_field

HERE = Path(__file__).resolve().parent
TRAIN = [1.2, 0.8, 0.4]
TEST = {"test_m0.60": -0.6, "test_0.10": 0.1}


def main() -> None:
    data = HERE / "data"
    data.mkdir(exist_ok=True)
    files = {f"train_{a:.2f}": a for a in TRAIN} | TEST
    for stem, psi0 in files.items():
        path = write_field(
            data / f"{stem}.nc",
            {"psi": systems.oscillator_sin(psi0, 0.0, n=51, dt=1.0)},
            history="cases/oscillator-sin/make_data.py",
        )
        print(f"wrote data/{path.name} ({path.stat().st_size // 1024} kB)")


if __name__ == "__main__":
    main()
