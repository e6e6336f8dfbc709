"""The potential V with the training and test ranges, like Qin (2020) Fig. 6.

python plot.py [RESULTS]        (default: results/; writes RESULTS/potential.png)
"""

from __future__ import annotations

import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import xarray as xr  # noqa: E402

from latticedft import systems  # noqa: E402

HERE = Path(__file__).resolve().parent


def main() -> None:
    res = Path(sys.argv[1]) if len(sys.argv) > 1 else HERE / "results"
    x = np.linspace(-1.8, 1.8, 721)
    fig, ax = plt.subplots(figsize=(7, 4))
    ax.plot(x, systems.wells_potential(x), "k-", label="V(psi) = -0.015 [cos(psi^2 - 1) + 0.2 psi]")
    files = sorted((HERE / "data").glob("*.nc"))
    for k, f in enumerate(files):
        v = xr.open_dataarray(f).values
        lo, hi = float(v.min()), float(v.max())
        y = -0.0195 - 0.0006 * k
        ax.plot([lo, hi], [y, y], "-", lw=3, color="tab:gray" if f.stem.startswith("train") else "tab:red")
        ax.annotate(f.stem, (hi, y), fontsize=6, va="center")
    ax.set_xlabel("psi")
    ax.set_ylabel("V")
    ax.legend(fontsize=7, loc="upper center")
    ax.set_title("potential; bars: range of each training (grey) and test (red) sequence")
    fig.tight_layout()
    fig.savefig(res / "potential.png", dpi=120)
    plt.close(fig)


if __name__ == "__main__":
    main()
