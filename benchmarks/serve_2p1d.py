"""2+1D serving: the wave L_d on a membrane, sites per second and peak memory."""

from __future__ import annotations

import sys

from ._common import Config, Table, in_subprocess

NAME = "serve-2+1d"
TITLE = "2+1D serving (wave L_d, Dirichlet frame): sites per second and peak memory"


def run(cfg: Config) -> Table:
    n, nt = (24, 8) if cfg.quick else (256, 100)
    r = in_subprocess("serve_membrane", cfg.threads, inline=cfg.quick, n=n, nt=nt)
    table = Table(
        NAME,
        TITLE,
        [
            "lattice (y * x * t)",
            "solver",
            "sites/s",
            "leapfrog sites/s",
            "serve / leapfrog time",
            "iters/slice",
            "max |served - leapfrog|",
            "peak RSS (MiB)",
            "RSS growth while serving (MiB)",
            "field size (MiB)",
        ],
    )
    lattice = f"{n} x {n} x {nt}"
    table.rows.append(
        [
            lattice,
            r["solver"],
            r["sites"] / r["t_newton"],
            r["sites"] / r["t_leapfrog"],
            r["t_newton"] / r["t_leapfrog"],
            r["iterations"] / (nt - 2),
            r["error"],
            r["rss_peak"],
            r["rss_peak"] - r["rss_before"],
            r["field_mib"],
        ]
    )
    table.rows.append(
        [
            lattice,
            "newton (affine=False)",
            r["sites"] / r["t_forced"],
            r["sites"] / r["t_leapfrog"],
            r["t_forced"] / r["t_leapfrog"],
            r["forced_iterations"] / (nt - 2),
            r["forced_error"],
            r["forced_rss_peak"],
            r["forced_rss_peak"] - r["forced_rss_before"],
            r["field_mib"],
        ]
    )
    table.notes += [
        "Served in a fresh subprocess (with --quick: in the runner); peak RSS is the kernel's high-water mark "
        "`VmHWM` reset just before serving (interpreter, torch and the inputs included); the growth is that "
        "peak minus the resident memory just before serving.",
        "solver: 'affine' is what `ldft.serve` chooses for the (quadratic) wave L_d: one sparse solve per slice "
        "and a vectorised check of the DEL residual of the whole field afterwards; the second row forces "
        "slice-Newton (`affine=False`) in the same process, measured after the first.",
        "Membrane 1 x 1 with a fixed frame, dt = h / 2, two by one half waves; leapfrog: "
        "`latticedft.systems.leapfrog` (numpy), one run.",
    ]
    return table


if __name__ == "__main__":
    from ._common import run_alone

    sys.exit(run_alone(run, __doc__))
