"""Symmetries and Noether charges of the learned theories of the cases (the figures of docs/symmetries.md).

    python -m benchmarks.noether [--quick] [--json PATH]

For each system it learns the case's model (in memory, from the case's data generators), tests the
built-in symmetries on the training data, fits the affine symmetry generator, serves the case's tasks
(and, for the field theories, a travelling solution on the periodic lattice) and measures the drift of
every Noether charge and of the discrete energy along the served fields. Drifts are
``(max - min) / scale`` (``latticedft.relative_drift``). About 2 minutes on one core. ``--quick``: small
networks, few iterations, three planets and two launches, short fields and no learned sine-Gordon model
(seconds; checks that everything runs). Also run by ``python -m benchmarks --only noether``.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from typing import Any

import numpy as np
import torch

import latticedft as ldft
from latticedft import lagrangians, systems

from ._common import Check, Config, Table, markdown

NAME = "noether"
TITLE = "Symmetries of learned theories and the conservation of their Noether charges along served fields"
ROTATION = np.array([[0.0, -1.0], [1.0, 0.0]])

# cases/kepler: dt, launches (r0, speeds), box and escape horizon (cases/kepler/make_data.py)
KEPLER_DT, KEPLER_BOX, KEPLER_T_ESCAPE = 0.05, 10.0, 30.0
KEPLER_LAUNCHES = {
    "earth": (1.0167, [0.98, 1.13, 1.26, 1.40, 1.50]),
    "mercury": (0.4667, [1.30, 1.56, 1.80, 2.07, 2.20]),
}


def _kepler_launch(r0: float, v0: float):
    energy = 0.5 * v0 * v0 - 1.0 / r0
    if energy < 0 and -1.0 / energy - r0 < KEPLER_BOX:
        return systems.kepler_orbit(r0, v0, dt=KEPLER_DT)
    return systems.kepler_orbit(r0, v0, dt=KEPLER_DT, t_end=KEPLER_T_ESCAPE)


def _rotated(orbit, angle: float):
    c, s = math.cos(angle), math.sin(angle)
    return orbit.copy(data=orbit.values @ np.array([[c, s], [-s, c]]))


def _sine_gordon() -> ldft.AnalyticLagrangian:
    """The explicit scheme of psi_tt = psi_xx - sin psi: forward differences, the potential at the anchor."""

    def fn(c, h):
        u = c[..., 0, 0]
        return 0.5 * ((c[..., 1, 0] - u) / h[0]) ** 2 - 0.5 * ((c[..., 2, 0] - u) / h[1]) ** 2 - (1.0 - torch.cos(u))

    return ldft.AnalyticLagrangian(fn, name="sine-Gordon, explicit scheme")


def _rep(reports, name):
    return next(r for r in reports if r.name == name)


def _discovery_error(model, data) -> tuple[float, float, float]:
    found = ldft.discover_symmetries(model, data)
    mat, off = np.array(found.best.generator["matrix"]), np.array(found.best.generator["offset"])
    return float(np.abs(mat - ROTATION).max()), float(np.abs(off).max()), found.best.residual


def _drifts(model, served: list, charge: str) -> tuple[float, float]:
    """Largest charge drift and largest energy oscillation over served fields."""
    jd = max(ldft.relative_drift(ldft.noether_charge(model, f, charge)) for f in served)
    ed = max(ldft.relative_drift(ldft.discrete_energy(model, f)) for f in served)
    return jd, ed


def kepler(cfg: Config, table: Table, discovery: Table) -> None:
    planets = ("Venus", "Earth", "Mars") if cfg.quick else systems.PLANETS
    train = [systems.planet_orbit(p, dt=KEPLER_DT) for p in planets]
    launches = [_kepler_launch(r0, v) for r0, speeds in KEPLER_LAUNCHES.values() for v in speeds]
    if cfg.quick:  # earth_0.98 (one period) and mercury_1.30
        launches = [launches[0], launches[5]]
    where = f"Kepler ({len(train)} planets)"

    def serve_all(model):
        """Served launches (the solved part where Newton failed, as a briefly trained model may) and failure flags."""
        out = []
        for f in launches:
            try:
                out.append((ldft.serve(model, f.isel(t=slice(0, 2)), slices=f.sizes["t"], box=KEPLER_BOX).field, False))
            except ldft.ServeError as err:
                out.append((err.result.field, True))
        return out

    hidden = [8] if cfg.quick else [32, 32]
    models = [
        ("analytic Verlet", lagrangians.kepler(), None),
        (
            "radial MLP (case)",
            ldft.MLPLagrangian(preset="radial", hidden=hidden),
            {"max_iter": 20 if cfg.quick else 500, "max_time": 150},
        ),
        (
            "free MLP",
            ldft.MLPLagrangian(hidden=hidden, activation="tanh", form="free", features="differences"),
            {"max_iter": 20 if cfg.quick else 300},
        ),
    ]
    for label, model, kw in models:
        if kw is not None:
            rep = ldft.learn(model, train, **kw)
            label += f", rel_res {rep.rel_res:.1e}"
        sym = _rep(ldft.symmetries(model, train, ["rotation-xy"]), "rotation-xy")
        served = serve_all(model)
        for task, part in (("earth_0.98, one period", served[:1]), (f"{len(served)} launches", served)):
            jd, ed = _drifts(model, [f for f, _ in part], "rotation-xy")
            failed = sum(bad for _, bad in part)
            if failed:
                task += f" ({failed} stopped by a Newton failure)"
            if label.startswith("radial MLP") and part is served:
                table.checks.append(
                    Check(
                        "angular momentum of the learned radial Kepler theory, every launch: drift <= 1e-10",
                        f"{jd:.1e}",
                        jd <= 1e-10,
                    )
                )
            table.rows.append(
                [
                    where,
                    label,
                    "rotation-xy",
                    sym.residual,
                    sym.residual_equations,
                    sym.verdict,
                    task,
                    jd,
                    ed,
                ]
            )
        merr, werr, res = _discovery_error(model, train)
        discovery.rows.append([where, label, merr, werr, res])
    # a potential of the position (not invariant by construction) learned from orbits in several orientations
    rotated = [
        _rotated(systems.planet_orbit(p), 2 * math.pi * k / 3 + i)
        for i, p in enumerate(("Earth",) if cfg.quick else ("Venus", "Earth", "Mars"))
        for k in range(3)
    ]
    kp = ldft.MLPLagrangian(hidden=hidden, activation="tanh", form="kinetic-potential", features="values")
    rep = ldft.learn(kp, rotated, max_iter=20 if cfg.quick else 300)
    label = f"kinetic-potential MLP of q, rel_res {rep.rel_res:.1e}"
    sym = _rep(ldft.symmetries(kp, rotated, ["rotation-xy"]), "rotation-xy")
    jd, ed = _drifts(
        kp, [ldft.serve(kp, launches[0].isel(t=slice(0, 2)), slices=launches[0].sizes["t"]).field], "rotation-xy"
    )
    orientations = f"Kepler ({len(rotated) // 3} planet(s) x 3 orientations)"
    table.rows.append(
        [
            orientations,
            label,
            "rotation-xy",
            sym.residual,
            sym.residual_equations,
            sym.verdict,
            "earth_0.98",
            jd,
            ed,
        ]
    )
    discovery.rows.append([orientations, label, *_discovery_error(kp, rotated)])


def quartic(cfg: Config, table: Table, discovery: Table) -> None:
    truth = lagrangians.verlet(lambda q: 0.5 * (q * q).sum(-1) + 0.25 * ((q * q).sum(-1)) ** 2)
    rng = np.random.default_rng(0)
    starts = []
    for _ in range(6):
        q0, v = rng.normal(size=2), rng.normal(size=2)
        starts.append(systems.make_field([q0, q0 + 0.1 * v], ["t"], spacing=0.1, components=["x", "y"]))
    orbits = [r.field for r in ldft.serve(truth, starts, slices=60)]
    model = ldft.PolynomialLagrangian(orders=(4, 4))
    rep = ldft.learn(model, orbits)
    label = f"polynomial (4, 4), rel_res {rep.rel_res:.1e}"
    sym = _rep(ldft.symmetries(model, orbits, ["rotation-xy"]), "rotation-xy")
    launch = systems.make_field([[1.0, 0.0], [1.0, 0.12]], ["t"], spacing=0.1, components=["x", "y"])
    steps = 300 if cfg.quick else 2000
    served = ldft.serve(model, launch, slices=steps).field
    jd, ed = _drifts(model, [served], "rotation-xy")
    table.rows.append(
        [
            "isotropic quartic oscillator",
            label,
            "rotation-xy",
            sym.residual,
            sym.residual_equations,
            sym.verdict,
            f"{steps} steps",
            jd,
            ed,
        ]
    )
    discovery.rows.append(["isotropic quartic oscillator", label, *_discovery_error(model, orbits)])


def klein_gordon(cfg: Config, table: Table) -> None:
    train = systems.klein_gordon_training_set(n=10 if cfg.quick else 80)
    steps = 100 if cfg.quick else 400
    test = systems.klein_gordon_test_field(steps=steps)
    x = 0.05 * np.arange(20)

    def wave(s):
        return np.sin(2 * np.pi * (x - s)) + 0.3 * np.cos(6 * np.pi * (x - s))

    travelling = systems.klein_gordon(wave(0.0), wave(0.03), steps=1)
    mlp = ldft.MLPLagrangian(hidden=[10, 10], activation="tanh", form="kinetic-potential", seed=0)
    models = [
        ("analytic", lagrangians.klein_gordon(), None),
        ("polynomial (2, 2) (case)", ldft.PolynomialLagrangian(orders=(2, 2)), {}),
        ("kinetic-potential MLP (case mlp/)", mlp, {"optimizer": "lbfgs", "max_iter": 10 if cfg.quick else 150}),
    ]
    for label, model, kw in models:
        if kw is not None:
            rep = ldft.learn(model, train, boundary="periodic", **kw)
            label += f", rel_res {rep.rel_res:.1e}"
        sym = _rep(ldft.symmetries(model, train, ["momentum-x"]), "momentum-x")
        for task, init in ((f"test{steps} (standing)", test), ("travelling, k = 1 + 3", travelling)):
            served = ldft.serve(model, init.isel(t=slice(0, 2)), slices=steps + 1, boundary="periodic").field
            jd, ed = _drifts(model, [served], "momentum-x")
            if label.startswith("polynomial"):
                table.checks.append(
                    Check(
                        f"pseudo-momentum of the periodic Klein-Gordon polynomial, {task}: drift <= 1e-10",
                        f"{jd:.1e}",
                        jd <= 1e-10,
                    )
                )
            table.rows.append(
                [
                    "Klein-Gordon, periodic",
                    label,
                    "momentum-x",
                    sym.residual,
                    sym.residual_equations,
                    sym.verdict,
                    task,
                    jd,
                    ed,
                ]
            )


def sine_gordon(cfg: Config, table: Table) -> None:
    nx, steps = (161, 100) if cfg.quick else (401, 400)  # dx = 0.25 (quick) or 0.1
    lattice = {"xlim": (-20.0, 20.0), "nx": nx, "dt": 0.05}
    moving = systems.sine_gordon_breather(0.7, velocity=0.3, x0=-3.0, nt=2, **lattice).isel(x=slice(0, nx - 1))
    moving["x"].attrs["periodic"] = "true"  # period 40: the breather's tails are ~1e-6 at the ends
    models: list[tuple[str, Any, Any]] = [("analytic (explicit scheme)", _sine_gordon(), None)]
    if not cfg.quick:
        models.append(
            (
                "polynomial (2, 12), time-symmetric (case)",
                ldft.PolynomialLagrangian(orders=(2, 12), time_symmetric=True),
                {"ridge": "auto"},
            )
        )
    for label, model, kw in models:
        if kw is not None:
            train = systems.sine_gordon_breather(0.3, nt=401, **lattice)
            rep = ldft.learn(model, train, **kw)
            label += f", rel_res {rep.rel_res:.1e}"
        per = ldft.serve(model, moving, slices=steps + 1, boundary="periodic").field
        sym = _rep(ldft.symmetries(model, per.isel(t=slice(0, 60)), ["momentum-x"]), "momentum-x")
        jd, ed = _drifts(model, [per], "momentum-x")
        table.rows.append(
            [
                "sine-Gordon, periodic x in [-20, 20)",
                label,
                "momentum-x",
                sym.residual,
                sym.residual_equations,
                sym.verdict,
                f"moving breather, {steps} steps",
                jd,
                ed,
            ]
        )


def run_all(cfg: Config) -> list[Table]:
    torch.set_num_threads(cfg.threads)
    t0 = time.perf_counter()
    table = Table(
        NAME,
        TITLE,
        [
            "system",
            "model",
            "symmetry",
            "residual",
            "equations residual",
            "verdict",
            "served",
            "charge drift",
            "energy oscillation",
        ],
    )
    discovery = Table(
        NAME + "-discovery",
        "Discovered affine generator M psi + w on the training data",
        ["system", "model", "max |M - [[0,-1],[1,0]]|", "max |w|", "residual"],
    )
    kepler(cfg, table, discovery)
    quartic(cfg, table, discovery)
    klein_gordon(cfg, table)
    sine_gordon(cfg, table)
    table.notes += [
        (
            "residual, equations residual: `ldft.symmetries` on the training data (for sine-Gordon: on the first 60 "
            "served slices); verdict at tol = 1e-9"
        ),
        (
            "charge drift, energy oscillation: (max - min) / scale of `ldft.noether_charge` and `ldft.discrete_energy` "
            "along the served fields (the largest over the launches for Kepler)"
        ),
    ]
    table.seconds = discovery.seconds = time.perf_counter() - t0
    return [table, discovery]


def run(cfg: Config) -> Table:
    """The runner's entry point: the charge table (``python -m benchmarks.noether`` also prints discovery)."""
    return run_all(cfg)[0]


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.noether", description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true", help="fewer training iterations; no learned sine-Gordon model")
    p.add_argument("--json", metavar="PATH", help="also write the tables as JSON")
    p.add_argument("--threads", type=int, default=1)
    args = p.parse_args(argv)
    tables = run_all(Config(quick=args.quick, threads=args.threads))
    for t in tables:
        print(markdown(t))
        print()
    print(f"({tables[0].seconds:.0f} s)")
    if args.json:
        with open(args.json, "w") as fh:
            json.dump([t.to_dict() for t in tables], fh, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
