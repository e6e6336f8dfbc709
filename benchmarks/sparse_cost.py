"""The cost and the terms of the sparse fit with ``threshold = "auto"`` (held-out serving), on clean data.

``python -m benchmarks.sparse_cost`` prints, for Kepler from one orbit, the pendulum and the nonlinear
Klein-Gordon string (the generators of ``tests/test_sparse.py``), the terms kept and the warm fit time (best of
3) against the dense exact solve of the same library (``threshold = 0``, no bags) and of the default polynomial.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import latticedft as ldft

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from test_sparse import kepler_one_orbit, kept, klein_gordon_string, pendulum  # noqa: E402

CASES: dict[str, tuple[str, Callable[[], Any]]] = {
    "kepler-one-orbit": ("auto", kepler_one_orbit),
    "pendulum": ("kinetic + trig:1", lambda: [pendulum(2.0), pendulum(2.6)]),
    "klein-gordon": ("kinetic + gradient + poly:4", lambda: [klein_gordon_string(a) for a in (0.6, 1.1)]),
}


def _best(make: Callable[[], ldft.AbstractLagrangian], data: Any, n: int = 3) -> tuple[Any, float]:
    """The last model learned and the shortest of ``n`` learning times (s)."""
    times = []
    for _ in range(n):
        model = make()
        t0 = time.perf_counter()
        ldft.learn(model, data, progress=False)
        times.append(time.perf_counter() - t0)
    return model, min(times)


def main() -> None:
    for name, (lib, data) in CASES.items():
        fields = data()
        model, t_auto = _best(lambda lib=lib: ldft.SparseLagrangian(lib), fields)
        _, t_dense = _best(lambda lib=lib: ldft.SparseLagrangian(lib, threshold=0.0, bags=0), fields)
        _, t_poly = _best(lambda: ldft.PolynomialLagrangian(), fields)
        print(
            f"{name}: kept {sorted(kept(model))}; auto {t_auto:.2f} s, dense same library {t_dense:.2f} s "
            f"({t_auto / t_dense:.1f}x), default polynomial {t_poly:.2f} s ({t_auto / t_poly:.1f}x)"
        )


if __name__ == "__main__":
    main()
