"""A model kind from outside latticedft: an oscillator in a quartic well, linear in its parameters."""

from __future__ import annotations

from typing import Any

import torch

import latticedft as ldft


class DemoWell(ldft.LinearLagrangian):
    """``L_d = a (q1 - q0)^2 / (2 h^2) - b (q0^2 + q1^2) / 2 - c (q0^4 + q1^4) / 2`` (``c`` only when
    ``quartic``)."""

    kind = "demo-well"

    def __init__(self, quartic: bool = True, *, stencil: ldft.Stencil | None = None):
        super().__init__(stencil)
        self.quartic = quartic

    def options(self) -> dict[str, Any]:
        return {"quartic": self.quartic}

    @property
    def n_terms(self) -> int:
        return 3 if self.quartic else 2

    def features(self, cells: torch.Tensor) -> torch.Tensor:
        q0, q1 = cells[..., 0, 0], cells[..., 1, 0]
        terms = [0.5 * ((q1 - q0) / self.spacing[0]) ** 2, -(q0**2 + q1**2) / 2]
        if self.quartic:
            terms.append(-(q0**4 + q1**4) / 2)
        return torch.stack(terms, -1)


def not_a_model() -> None:
    """Named by an entry point that gives the wrong type."""
