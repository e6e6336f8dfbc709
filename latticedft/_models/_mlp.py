"""Neural discrete Lagrangians: the paper's free MLP and a structured kinetic-plus-potential form."""

from __future__ import annotations

from typing import Any

import torch

from .._errors import InputError
from .._stencil import Stencil
from ._base import AbstractLagrangian

__all__ = ["MLPLagrangian", "PRESETS"]

_ACTIVATIONS = {
    "sigmoid": torch.nn.Sigmoid,
    "tanh": torch.nn.Tanh,
    "softplus": torch.nn.Softplus,
    "silu": torch.nn.SiLU,
    "gelu": torch.nn.GELU,
}
_FORMS = ("free", "kinetic-potential")
_FEATURES = ("values", "differences", "invariant", "inverse-radius")

#: Named settings. ``paper``: Qin (2020) Sec. 4, a 2x40 sigmoid network on the
#: raw stencil values. ``kinetic-potential``: unit-mass kinetic term minus a
#: learned on-site potential of the values. ``radial``: the same with the
#: potential a function of ``1 / |psi|`` (central forces; cases/kepler).
PRESETS: dict[str, dict[str, Any]] = {
    "paper": {"hidden": [40, 40], "activation": "sigmoid", "form": "free", "features": "values", "scale": False},
    "kinetic-potential": {"hidden": [32, 32], "activation": "tanh", "form": "kinetic-potential",
                          "features": "values", "scale": True},
    # central forces (Kepler): unit-mass kinetic term plus a learned potential of 1/|psi|
    "radial": {"hidden": [32, 32], "activation": "tanh", "form": "kinetic-potential",
               "features": "inverse-radius", "scale": True},
}


class MLPLagrangian(AbstractLagrangian):
    """``L_d`` given by a multilayer perceptron.

    Parameters
    ----------
    hidden : list of int
        Hidden layer sizes (default ``[40, 40]``, the paper's).
    activation : str
        One of ``sigmoid``, ``tanh``, ``softplus``, ``silu``, ``gelu``
        (smooth: serving needs second derivatives).
    form : "free" or "kinetic-potential"
        ``free``: ``L_d = net(inputs)``, the gauge is fixed during training by
        a penalty on the mixed Hessian. ``kinetic-potential``:
        ``L_d = |g_0|^2 / (2 h_0^2) - sum_k w_k |g_k|^2 / (2 h_k^2) - mean_a V(psi[x+s_a])``
        with learned ``w_k`` and potential ``V = net(site features)``; its
        mixed time Hessian is ``-I / h_0^2`` by construction.
    features : "values", "differences" or "invariant"
        Network inputs. ``values``: the stencil values (free form) or the site
        value (potential). ``differences``: stencil mean and per-axis
        differences (free form only). ``invariant``: rotation invariants — the
        Gram matrix of the stencil vectors (free form) or ``|psi|`` (potential).
        ``inverse-radius`` (kinetic-potential form, vector fields): ``1 / |psi|``,
        so that ``V`` extrapolates gently to large ``|psi|`` (``1/|psi| -> 0``
        there, a small step outside the training range) where ``|psi|`` would
        leave the range of the scaled inputs by far.
    scale : bool
        Scale inputs to the training data's range and the output to the
        kinetic energy's scale.
    seed : int
        Seed of the initial weights.
    preset : str, optional
        A name in :data:`PRESETS` whose settings fill the defaults.

    >>> MLPLagrangian(preset="paper").options()["hidden"]
    [40, 40]
    """

    kind = "mlp"

    def __init__(self, hidden: list[int] | tuple[int, ...] | None = None, activation: str | None = None, *,
                 form: str | None = None, features: str | None = None, scale: bool | None = None,
                 seed: int = 0, preset: str | None = None, stencil: Stencil | None = None):
        super().__init__(stencil)
        base: dict[str, Any] = {"hidden": [40, 40], "activation": "sigmoid", "form": "free",
                                "features": "differences", "scale": True}
        if preset is not None:
            if preset not in PRESETS:
                raise InputError(f"preset: unknown preset {preset!r}; expected one of {sorted(PRESETS)}")
            base.update(PRESETS[preset])
        given = {"hidden": hidden, "activation": activation, "form": form, "features": features, "scale": scale}
        base.update({k: v for k, v in given.items() if v is not None})
        hid = base["hidden"]
        if (not isinstance(hid, (list, tuple)) or not hid
                or not all(isinstance(h, int) and not isinstance(h, bool) and h > 0 for h in hid)):
            raise InputError(f"hidden: expected a non-empty list of positive layer sizes, got {hid!r}")
        if base["activation"] not in _ACTIVATIONS:
            raise InputError(f"activation: expected one of {sorted(_ACTIVATIONS)} (smooth; serving needs second "
                             f"derivatives), got {base['activation']!r}")
        if base["form"] not in _FORMS:
            raise InputError(f"form: expected one of {list(_FORMS)}, got {base['form']!r}")
        if base["features"] not in _FEATURES:
            raise InputError(f"features: expected one of {list(_FEATURES)}, got {base['features']!r}")
        if base["form"] == "kinetic-potential" and base["features"] == "differences":
            base["features"] = "values"
        if base["features"] == "inverse-radius" and base["form"] != "kinetic-potential":
            raise InputError("features: 'inverse-radius' is a feature of the potential; use it with "
                             "form='kinetic-potential'")
        if not isinstance(seed, int) or isinstance(seed, bool):
            raise InputError(f"seed: expected an integer, got {seed!r}")
        self.hidden = [int(h) for h in hid]
        self.activation = base["activation"]
        self.form = base["form"]
        self.features = base["features"]
        self.scale = bool(base["scale"])
        self.seed = seed

    @property
    def unit_mass_by_construction(self) -> bool:  # type: ignore[override]
        """The kinetic-potential form has ``M = -I / h_0^2`` exactly when every spatial edge ``e_k`` is in the
        stencil (its differences then never couple ``psi_x`` with ``psi_{x+e_0}``); otherwise the gauge
        penalty applies."""
        if self.form != "kinetic-potential":
            return False
        return self.stencil is None or all(self._edge(k) is not None for k in range(1, self.stencil.ndim))

    @property
    def constant_mixed_hessian(self) -> bool:
        """Kinetic-potential form: the potential is a sum of one-site terms, so every block coupling two
        stencil sites comes from the quadratic kinetic and gradient terms and is constant."""
        return self.form == "kinetic-potential"

    def _edge(self, k: int) -> int | None:
        e = [0] * self.stencil.ndim
        e[k] = 1
        return self.stencil.offsets.index(tuple(e)) if tuple(e) in self.stencil.offsets else None

    def options(self) -> dict[str, Any]:
        return {"hidden": list(self.hidden), "activation": self.activation, "form": self.form,
                "features": self.features, "scale": self.scale, "seed": self.seed}

    # -- structure ---------------------------------------------------------------------------------------
    def _n_inputs(self) -> int:
        n, m, k = self.n, self.m, self.stencil.size
        if self.form == "free":
            if self.features == "values":
                return k * m
            if self.features == "differences":
                return (n + 1) * m
            return k * (k + 1) // 2
        return 1 if self.features in ("invariant", "inverse-radius") else m

    def _build(self) -> None:
        if self.features in ("invariant", "inverse-radius") and self.m < 2:
            raise InputError(f"features: {self.features!r} needs a vector field (m >= 2); use 'values' for scalars")
        gen_state = torch.random.get_rng_state()
        torch.manual_seed(self.seed)
        try:
            layers: list[torch.nn.Module] = []
            width = self._n_inputs()
            for h in self.hidden:
                layers += [torch.nn.Linear(width, h, dtype=torch.float64), _ACTIVATIONS[self.activation]()]
                width = h
            layers.append(torch.nn.Linear(width, 1, dtype=torch.float64))
            self.net = torch.nn.Sequential(*layers)
        finally:
            torch.random.set_rng_state(gen_state)
        nin = self._n_inputs()
        self.register_buffer("in_center", torch.zeros(nin, dtype=torch.float64))
        self.register_buffer("in_scale", torch.ones(nin, dtype=torch.float64))
        self.register_buffer("out_scale", torch.ones((), dtype=torch.float64))
        if self.form == "kinetic-potential":
            self.stiffness = torch.nn.Parameter(torch.ones(self.n - 1, dtype=torch.float64))

    def _inputs(self, cells: torch.Tensor) -> torch.Tensor:
        """Raw (unscaled) network inputs: per cell (free) or per stencil site (potential)."""
        if self.form == "free":
            if self.features == "values":
                return cells.reshape(*cells.shape[:-2], -1)
            if self.features == "differences":
                z = self.mean_and_differences(cells)
                return z.reshape(*z.shape[:-2], -1)
            gram = cells @ cells.transpose(-1, -2)
            iu = torch.triu_indices(cells.shape[-2], cells.shape[-2])
            return gram[..., iu[0], iu[1]]
        if self.features == "invariant":
            return torch.sqrt((cells * cells).sum(-1, keepdim=True))
        if self.features == "inverse-radius":
            return torch.rsqrt((cells * cells).sum(-1, keepdim=True))
        return cells

    def prepare(self, cells: list[torch.Tensor]) -> None:
        if not self.scale:
            return
        x = torch.cat([self._inputs(c).reshape(-1, self.in_center.numel()) for c in cells])
        lo, hi = x.min(0).values, x.max(0).values
        half = (hi - lo) / 2
        self.in_center.copy_((hi + lo) / 2)
        self.in_scale.copy_(torch.where(half > 0, half, torch.ones_like(half)))
        g0 = torch.cat([self.mean_and_differences(c)[..., 1, :].reshape(-1) for c in cells])
        kinetic = 0.5 * (g0.abs().max() / self.spacing[0]) ** 2
        self.out_scale.fill_(float(kinetic) if kinetic > 0 else 1.0)

    def _net(self, x: torch.Tensor) -> torch.Tensor:
        return self.out_scale * self.net((x - self.in_center) / self.in_scale).squeeze(-1)

    def forward(self, cells: torch.Tensor) -> torch.Tensor:
        if self.form == "free":
            return self._net(self._inputs(cells))
        # kinetic term from the time edge psi[x+e0] - psi[x]: its mixed Hessian is -I/h0^2 on every stencil;
        # spatial terms from the edges psi[x+e_k] - psi[x] when present, else the stencil's least-squares slope
        z = self.mean_and_differences(cells)  # (..., n+1, m)
        h = self.spacing
        st = self.stencil
        x0 = cells[..., st.anchor, :]
        lag = 0.5 * ((cells[..., st.forward, :] - x0) ** 2).sum(-1) / h[0] ** 2
        for k in range(1, self.n):
            edge = self._edge(k)
            dk = cells[..., edge, :] - x0 if edge is not None else z[..., k + 1, :]
            lag = lag - 0.5 * self.stiffness[k - 1] * (dk ** 2).sum(-1) / h[k] ** 2
        potential = self._net(self._inputs(cells)).mean(-1)  # mean over the K stencil sites
        return lag - potential

    def describe(self) -> str:
        head = super().describe()
        arch = " -> ".join(str(w) for w in [self._n_inputs() if self.bound else "?", *self.hidden, 1])
        lines = [head, f"  network: {arch}, {self.activation}, inputs: {self.features}"
                 + (", scaled to the data" if self.scale else "")]
        if self.form == "kinetic-potential":
            lines.append("  L_d = |D_t psi|^2 / (2 h_t^2) - sum_k w_k |D_k psi|^2 / (2 h_k^2) - mean over stencil of V(psi)")
            if self.bound and self.n > 1:
                lines.append("  learned w_k = " + ", ".join(f"{float(w):.6g}" for w in self.stiffness))
        else:
            lines.append("  L_d = net(inputs) (free form; gauge fixed by the mixed-Hessian penalty)")
        return "\n".join(lines)
