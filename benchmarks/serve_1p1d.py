"""1+1D serving: slice-Newton vs the paper's site-by-site sweep vs a hand-written numpy leapfrog."""

from __future__ import annotations

import sys
import time

import numpy as np

import latticedft as ldft
from latticedft import systems

from ._common import Check, Config, Table, best_time
from ._fixtures import DT, DX, kg_force, kg_mlp, string_field

NAME = "serve-1+1d"
TITLE = "1+1D serving: sites per second, slice-Newton vs site-by-site sweep vs numpy leapfrog"


def _sizes(quick: bool) -> list[tuple[int, int, int]]:
    """(nx, time slices served by Newton, slices solved by the sweep)."""
    return [(24, 8, 1)] if quick else [(256, 256, 2), (1024, 1024, 1)]


def run(cfg: Config) -> Table:
    table = Table(
        NAME,
        TITLE,
        [
            "lattice (x * t)",
            "boundary",
            "L_d",
            "solver",
            "serve sites/s",
            "Newton sites/s (affine=False)",
            "sweep sites/s",
            "leapfrog sites/s",
            "serve / sweep speed",
            "serve / leapfrog time",
            "iters/slice",
            "max |served - leapfrog|",
        ],
    )
    wave = ldft.lagrangians.wave()
    mlp = kg_mlp(cfg.quick)
    worst = {"wave_sps": np.inf, "wave_vs_leapfrog": 0.0, "vs_sweep": np.inf}
    for nx, nt, nsweep in _sizes(cfg.quick):
        for boundary in ("dirichlet", "periodic"):
            for label, model, force in (("wave", wave, None), ("MLP (Klein-Gordon)", mlp, kg_force)):
                ref, da = string_field(nx, nt, boundary, force)
                inner = nx - 2 if boundary == "dirichlet" else nx
                sites = (nt - 2) * inner
                bvals = ref if boundary == "dirichlet" else None
                t_lf, lf = best_time(
                    lambda ref=ref, nt=nt, force=force, boundary=boundary, bvals=bvals: systems.leapfrog(
                        ref[0], ref[1], nt - 1, DT, DX, force=force, boundary=boundary, boundary_values=bvals
                    )
                )
                t0 = time.perf_counter()
                res = ldft.serve(model, da, boundary=boundary, progress=False)
                t_newton = time.perf_counter() - t0
                t_forced = t_newton
                if res.solver != "newton":  # the same lattice by slice-Newton alone, for comparison
                    t0 = time.perf_counter()
                    forced = ldft.serve(model, da, boundary=boundary, affine=False, progress=False)
                    t_forced = time.perf_counter() - t0
                    assert float(abs(forced.field.values - res.field.values).max()) < 1e-10
                init = da.isel(t=slice(0, 2 + nsweep))
                t0 = time.perf_counter()
                ldft.serve(model, init, slices=2 + nsweep, boundary=boundary, mode="sweep", progress=False)
                t_sweep = time.perf_counter() - t0
                sps_newton = sites / t_newton
                sps_sweep = nsweep * inner / t_sweep
                err = float(np.abs(res.field.values - lf).max())
                table.rows.append(
                    [
                        f"{nx} x {nt}",
                        boundary,
                        label,
                        res.solver,
                        sps_newton,
                        sites / t_forced,
                        sps_sweep,
                        sites / t_lf,
                        sps_newton / sps_sweep,
                        t_newton / t_lf,
                        res.newton_iterations / (nt - 2),
                        err,
                    ]
                )
                worst["vs_sweep"] = min(worst["vs_sweep"], sps_newton / sps_sweep)
                if label == "wave":
                    worst["wave_sps"] = min(worst["wave_sps"], sps_newton)
                    worst["wave_vs_leapfrog"] = max(worst["wave_vs_leapfrog"], t_newton / t_lf)
    sweep_slices = ", ".join(f"{ns} slice{'s' * (ns > 1)} at nx = {nx}" for nx, _, ns in _sizes(cfg.quick))
    table.notes += [
        "Sites = interior sites solved (time slices served minus the two given, times the sites each slice "
        "determines); serve, Newton and sweep times are wall times of the whole `ldft.serve` call.",
        "solver: what `ldft.serve` (mode='newton', the default) chose. The wave L_d is quadratic, so its DEL is "
        "an affine recurrence: 'affine' = one sparse solve per slice with the slice matrix factorised once, then "
        "one vectorised check of the model's DEL residual on the whole served field (included in the time). "
        "'Newton sites/s (affine=False)' serves the same lattice by slice-Newton (autograd per slice) for "
        "comparison; iters/slice counts linear solves for 'affine'.",
        f"The sweep is timed on a few slices only ({sweep_slices}) and its rate is per site; its cost per site "
        "does not depend on how many slices follow.",
        "Leapfrog: `latticedft.systems.leapfrog` (numpy, whole-slice stencil) of the true equation "
        "(wave; Klein-Gordon `psi_tt = psi_xx - psi` for the MLP rows), best of 3; for the wave L_d the last "
        "column is round-off (the wave L_d serves exactly the leapfrog), for the MLP it is the learned "
        "model's error.",
        "MLP: `MLPLagrangian(form='kinetic-potential', hidden=[10, 10], activation='tanh')` learned with "
        "L-BFGS on 8 periodic Klein-Gordon fields (20 x 20 sites); dt = 0.025, dx = 0.05 on every lattice.",
    ]
    table.checks += [
        Check("wave L_d: >= 1e6 sites/s (slowest row)", f"{worst['wave_sps']:.3g} sites/s", worst["wave_sps"] >= 1e6),
        Check(
            "wave L_d: <= 10x the leapfrog's time (worst row)",
            f"{worst['wave_vs_leapfrog']:.3g}x",
            worst["wave_vs_leapfrog"] <= 10,
        ),
        Check(
            ">= 100x faster than the site-by-site sweep (worst row)",
            f"{worst['vs_sweep']:.3g}x",
            worst["vs_sweep"] >= 100,
        ),
    ]
    return table


if __name__ == "__main__":
    from ._common import run_alone

    sys.exit(run_alone(run, __doc__))
