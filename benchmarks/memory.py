"""Peak resident memory of serving a 1024 x 1024 lattice and of training the largest cases."""

from __future__ import annotations

import sys

from ._common import Config, Table, in_subprocess

NAME = "memory"
TITLE = "Peak resident memory (each task in a fresh subprocess)"


def run(cfg: Config) -> Table:
    table = Table(
        NAME, TITLE, ["task", "size", "wall time (s)", "peak RSS (MiB)", "growth during task (MiB)", "peak reset"]
    )
    nx, nt = (64, 64) if cfg.quick else (1024, 1024)
    for boundary in ("periodic", "dirichlet"):
        r = in_subprocess("serve_string", cfg.threads, inline=cfg.quick, nx=nx, nt=nt, boundary=boundary)
        table.rows.append(
            [
                f"serve wave L_d, {boundary}",
                f"{nx} x {nt} sites",
                r["seconds"],
                r["rss_peak"],
                r["rss_peak"] - r["rss_before"],
                r["reset"],
            ]
        )
    n, its = (4, 2) if cfg.quick else (80, 20)
    r = in_subprocess("train_kg_mlp", cfg.threads, inline=cfg.quick, n=n, iterations=its)
    table.rows.append(
        [
            "train kinetic-potential MLP (L-BFGS), Klein-Gordon case",
            f"{n} fields, {r['sites']} sites, {r['iterations']} iterations",
            r["seconds"],
            r["rss_peak"],
            r["rss_peak"] - r["rss_before"],
            r["reset"],
        ]
    )
    planets = ["Mercury", "Venus"] if cfg.quick else ["Mercury", "Venus", "Earth", "Mars", "Ceres", "Jupiter"]
    r = in_subprocess("train_kepler_paper", cfg.threads, inline=cfg.quick, iterations=its, planets=planets)
    table.rows.append(
        [
            "train paper MLP 4-40-40-1 (L-BFGS), Kepler",
            f"{len(planets)} orbits, {r['sites']} sites, {r['iterations']} iterations",
            r["seconds"],
            r["rss_peak"],
            r["rss_peak"] - r["rss_before"],
            r["reset"],
        ]
    )
    table.notes += [
        "Each task runs in a fresh Python (with --quick: in the runner itself). Peak RSS: the kernel's "
        "resident-set high-water mark `VmHWM`, reset just before the task (`/proc/self/clear_refs`); it includes "
        "the interpreter and torch (~300-400 MiB before any work). Growth: that peak minus the resident memory "
        "just before the task, i.e. what the task itself added (torch, numpy and allocator slack alike).",
        "The 1024 x 1024 lattices are served for all 1024 time slices.",
        "Training memory is reached in the first iterations (full batch, same graph every iteration), so the "
        "training tasks run a capped number of L-BFGS iterations.",
    ]
    return table


if __name__ == "__main__":
    from ._common import run_alone

    sys.exit(run_alone(run, __doc__))
