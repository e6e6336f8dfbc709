"""Orbit figures like Qin (2020) Figs. 9-12 and the table of README.md, from a finished run.

    python plot.py [RESULTS]        (default: results/)

Writes RESULTS/orbits_training.png, RESULTS/orbits_earth.png, RESULTS/orbits_mercury.png and prints
per launch: escaped (r > 10) in the prediction and in the truth, slices served, max error over the
first 100 steps and over the whole served orbit.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import xarray as xr  # noqa: E402

HERE = Path(__file__).resolve().parent


def main() -> None:
    res = Path(sys.argv[1]) if len(sys.argv) > 1 else HERE / "results"
    summary = json.loads((res / "summary.json").read_text())
    t = summary["train"]
    print(
        f"train: rel_res = {t['rel_res']:.2e}, F = {t['loss']:.2e}, {t['iterations']} iterations, "
        f"{t['wall_time']:.1f} s"
    )
    print("| launch | escaped (model) | escaped (Newton) | slices | max error, 100 steps | max error | status |")
    print("|---|---|---|---|---|---|---|")
    for name, task in summary["tasks"].items():
        with xr.open_dataset(res / f"{name}.nc") as ds:
            p, r = ds["psi"].values, ds["psi_ref"].values
        full = xr.open_dataarray(HERE / "data" / f"{name}.nc").values
        n = min(len(p), len(r), 101)
        e100 = float(np.abs(p[:n] - r[:n]).max())
        esc = "yes" if (np.hypot(*p.T) > 10).any() else "no"
        truth = "yes" if (np.hypot(*full.T) > 10).any() else "no"
        print(
            f"| {name} | {esc} | {truth} | {task['slices']} | {e100:.1e} | {task['max_error']:.1e} | "
            f"{'complete' if task['complete'] else 'incomplete: ' + task['reason']} |"
        )
    fig, ax = plt.subplots(figsize=(6, 6))
    for f in sorted((HERE / "data").glob("train_*.nc")):
        o = xr.open_dataarray(f).values
        ax.plot(o[:, 0], o[:, 1], ".", ms=2, label=f.stem[6:].capitalize())
    ax.set_aspect("equal")
    ax.legend(fontsize=7)
    ax.set_xlabel("x [au]")
    ax.set_ylabel("y [au]")
    ax.set_title("training orbits (one period each, dt = 0.05)")
    fig.savefig(res / "orbits_training.png", dpi=120)
    plt.close(fig)
    for body, lim in (("earth", 6), ("mercury", 3)):
        fig, ax = plt.subplots(figsize=(6, 6))
        for name in summary["tasks"]:
            if not name.startswith(body):
                continue
            with xr.open_dataset(res / f"{name}.nc") as ds:
                p, r = ds["psi"].values, ds["psi_ref"].values
            ax.plot(r[:, 0], r[:, 1], "o", mfc="none", ms=3, color="tab:blue")
            ax.plot(p[:, 0], p[:, 1], ".", ms=2, color="tab:red")
            ax.annotate(f"v={name.split('_')[1]}", p[min(len(p) - 1, len(p) // 3)], fontsize=7)
        ax.plot([], [], "o", mfc="none", color="tab:blue", label="Newton")
        ax.plot([], [], ".", color="tab:red", label="learned L_d")
        ax.set_xlim(-lim, lim)
        ax.set_ylim(-lim, lim)
        ax.set_aspect("equal")
        ax.legend()
        ax.set_title(f"launches from {body.capitalize()}'s aphelion point")
        ax.set_xlabel("x [au]")
        ax.set_ylabel("y [au]")
        fig.savefig(res / f"orbits_{body}.png", dpi=120)
        plt.close(fig)


if __name__ == "__main__":
    main()
