"""Neural discrete Lagrangians: the paper's free MLP and a structured kinetic-plus-potential form.

``MLPLagrangian(...)`` (``kind = "mlp"`` in case.toml and model files) builds one of two classes, chosen
by its ``form`` option: :class:`FreeMLPLagrangian` (``form="free"``, ``L_d`` is the network) and
:class:`KineticPotentialMLPLagrangian` (``form="kinetic-potential"``, a kinetic term minus a network
potential). Both share the options, the network and its input and output scaling.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping, Sequence
from typing import Any, ClassVar, NamedTuple, Self, cast

import torch

from .._collective import merged_max, merged_min
from .._contract import AbstractLagrangian
from .._errors import InputError
from .._stencil import Stencil

__all__ = ["MLPLagrangian", "FreeMLPLagrangian", "KineticPotentialMLPLagrangian", "PRESETS", "mlp_lagrangian"]

_ACTIVATIONS = {
    "sigmoid": torch.nn.Sigmoid,
    "tanh": torch.nn.Tanh,
    "softplus": torch.nn.Softplus,
    "silu": torch.nn.SiLU,
    "gelu": torch.nn.GELU,
}

#: Named settings. ``paper``: Qin (2020) Sec. 4, a 2x40 sigmoid network on the
#: raw stencil values. ``kinetic-potential``: unit-mass kinetic term minus a
#: learned on-site potential of the values. ``radial``: the same with the
#: potential a function of ``1 / |psi|`` (central forces, e.g. Kepler orbits).
PRESETS: dict[str, dict[str, Any]] = {
    "paper": {"hidden": [40, 40], "activation": "sigmoid", "form": "free", "features": "values", "scale": False},
    "kinetic-potential": {
        "hidden": [32, 32],
        "activation": "tanh",
        "form": "kinetic-potential",
        "features": "values",
        "scale": True,
    },
    # central forces (Kepler): unit-mass kinetic term plus a learned potential of 1/|psi|
    "radial": {
        "hidden": [32, 32],
        "activation": "tanh",
        "form": "kinetic-potential",
        "features": "inverse-radius",
        "scale": True,
    },
}
_DEFAULTS: dict[str, Any] = {"hidden": [40, 40], "activation": "sigmoid", "features": None, "scale": True}


class _Inputs(NamedTuple):
    """One choice of network inputs (``features``): their number and how they come from the cells."""

    width: Callable[[int, int, int], int]  # (n, m, K) -> number of inputs
    of: Callable[[AbstractLagrangian, torch.Tensor], torch.Tensor]  # (model, cells (..., K, m)) -> inputs
    vector: bool = False  # needs a vector field (m >= 2)


def _flat_mean_and_differences(model: AbstractLagrangian, cells: torch.Tensor) -> torch.Tensor:
    z = model.mean_and_differences(cells)
    return z.reshape(*z.shape[:-2], -1)


def _gram(model: AbstractLagrangian, cells: torch.Tensor) -> torch.Tensor:
    gram = cells @ cells.transpose(-1, -2)
    iu = torch.triu_indices(cells.shape[-2], cells.shape[-2])
    return gram[..., iu[0], iu[1]]


def _settings(
    hidden: Any, activation: Any, form: Any, features: Any, scale: Any, preset: Any, default_form: str = "free"
) -> dict[str, Any]:
    """The defaults, then the preset's settings, then the arguments given (``None``: not given)."""
    out = dict(_DEFAULTS, form=default_form)
    if preset is not None:
        if preset not in PRESETS:
            raise InputError.at("preset", f"unknown preset {preset!r}; expected one of {sorted(PRESETS)}")
        out.update(PRESETS[preset])
    if scale is not None and not isinstance(scale, bool):
        raise InputError.at("scale", f"expected True, False or None, got {scale!r}")
    given = {"hidden": hidden, "activation": activation, "form": form, "features": features, "scale": scale}
    out.update({k: v for k, v in given.items() if v is not None})
    if out["form"] not in _FORM_CLASSES:
        raise InputError.at("form", f"expected one of {list(_FORM_CLASSES)}, got {out['form']!r}")
    return out


class MLPLagrangian(AbstractLagrangian):
    """``L_d`` given by a multilayer perceptron.

    Calling ``MLPLagrangian(...)`` builds the class of the chosen ``form``: a
    :class:`FreeMLPLagrangian` or a :class:`KineticPotentialMLPLagrangian`
    (both are ``MLPLagrangian`` instances).

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
    features : str
        Network inputs. Free form: ``values`` (the stencil values),
        ``differences`` (default: stencil mean and per-axis differences) or
        ``invariant`` (rotation invariants: the Gram matrix of the stencil
        vectors). Kinetic-potential form: ``values`` (default: the site value),
        ``invariant`` (``|psi|``) or ``inverse-radius`` (``1 / |psi|``, so that
        ``V`` extrapolates gently to large ``|psi|``: ``1/|psi| -> 0`` there, a
        small step outside the training range, where ``|psi|`` would leave the
        range of the scaled inputs by far). ``invariant`` and
        ``inverse-radius`` need vector fields. An input the form does not take
        is refused.
    scale : bool
        Scale inputs to the training data's range and the output to the
        kinetic energy's scale.
    seed : int
        Seed of the initial weights.
    preset : str, optional
        A name in :data:`PRESETS` whose settings fill the defaults.

    >>> MLPLagrangian(preset="paper").options()["hidden"]
    [40, 40]
    >>> type(MLPLagrangian(form="kinetic-potential")).__name__
    'KineticPotentialMLPLagrangian'
    """

    prepare_merges_processes = True

    kind = "mlp"
    #: The ``form`` option this class implements (set by the two forms).
    form: ClassVar[str]
    #: ``features`` -> the network inputs it stands for, for this form.
    inputs: ClassVar[dict[str, _Inputs]]
    #: ``features`` when neither the arguments nor a preset give it.
    default_features: ClassVar[str]
    #: Buffers set by :meth:`_build`: the inputs' centre and scale, the output's scale.
    in_center: torch.Tensor
    in_scale: torch.Tensor
    out_scale: torch.Tensor

    def __new__(cls, *args: Any, **kwargs: Any) -> Self:
        target = _form_class(kwargs) if cls is MLPLagrangian else cls  # MLPLagrangian(...): as mlp_lagrangian
        return cast(Self, super().__new__(target))  # target is cls, or a form class when cls is MLPLagrangian

    def __init__(
        self,
        hidden: Sequence[int] | None = None,
        activation: str | None = None,
        *,
        form: str | None = None,
        features: str | None = None,
        scale: bool | None = None,
        seed: int = 0,
        preset: str | None = None,
        stencil: Stencil | None = None,
    ):
        super().__init__(stencil)
        opts = _settings(hidden, activation, form, features, scale, preset, default_form=self.form)
        hid = opts["hidden"]
        if (
            not isinstance(hid, (list, tuple))
            or not hid
            or not all(isinstance(h, int) and not isinstance(h, bool) and h > 0 for h in hid)
        ):
            raise InputError.at("hidden", f"expected a non-empty list of positive layer sizes, got {hid!r}")
        if opts["activation"] not in _ACTIVATIONS:
            raise InputError.at(
                "activation",
                f"expected one of {sorted(_ACTIVATIONS)} (smooth; serving needs second "
                f"derivatives), got {opts['activation']!r}",
            )
        if opts["form"] != self.form:
            raise InputError.at(
                "form",
                f"{type(self).__name__} has form {self.form!r}, got {opts['form']!r} "
                "(MLPLagrangian(form=...) picks the class)",
            )
        feats = opts["features"] or self.default_features
        every = list(dict.fromkeys(name for cls in _FORM_CLASSES.values() for name in cls.inputs))
        if feats not in every:
            raise InputError.at("features", f"expected one of {every}, got {feats!r}")
        if feats not in self.inputs:
            raise InputError.at(
                "features",
                f"{feats!r} does not go with form={self.form!r} (that form takes "
                f"{', '.join(repr(k) for k in self.inputs)})",
            )
        if not isinstance(seed, int) or isinstance(seed, bool):
            raise InputError.at("seed", f"expected an integer, got {seed!r}")
        self.hidden = [int(h) for h in hid]
        self.activation = opts["activation"]
        self.features = feats
        self.scale = bool(opts["scale"])
        self.seed = seed

    def reseed(self, seed: int) -> None:
        self.seed = seed

    @classmethod
    def parameter_lower_bound(cls, options: Mapping[str, Any], n: int, m: int) -> tuple[int, str] | None:
        """The weights and biases of the hidden layers and the output, with at least one input."""
        hidden = options.get("hidden")
        if not isinstance(hidden, list):  # from a preset or the defaults
            try:
                hidden = mlp_lagrangian(**options).hidden
            except Exception:  # noqa: BLE001 - bad options are the case reader's to report
                return None
        sizes = [int(h) for h in hidden]
        if not sizes:
            return None
        count, width = 0, 1  # at least one input
        for h in sizes:
            count += (width + 1) * h
            width = h
        return count + width + 1, "model.hidden"

    def options(self) -> dict[str, Any]:
        return {
            "hidden": list(self.hidden),
            "activation": self.activation,
            "form": self.form,
            "features": self.features,
            "scale": self.scale,
            "seed": self.seed,
        }

    # -- structure ---------------------------------------------------------------------------------------
    def _n_inputs(self) -> int:
        return self.inputs[self.features].width(self.n, self.m, self.stencil.size)

    def _build(self) -> None:
        if self.inputs[self.features].vector and self.m < 2:
            raise InputError.at(
                "features", f"{self.features!r} needs a vector field (m >= 2); use 'values' for scalars"
            )
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

    def _inputs(self, cells: torch.Tensor) -> torch.Tensor:
        """Raw (unscaled) network inputs: per cell (free form) or per stencil site (potential)."""
        return self.inputs[self.features].of(self, cells)

    def prepare(self, cells: Iterable[torch.Tensor]) -> None:
        if not self.scale:
            return
        lo = hi = g0max = None
        for c in cells:  # chunk by chunk: the cells may be read from files one slab at a time
            if c.numel() == 0:
                continue
            x = self._inputs(c).reshape(-1, self.in_center.numel())
            xlo, xhi = x.min(0).values, x.max(0).values
            g0 = self.mean_and_differences(c)[..., 1, :].abs().max()
            lo = xlo if lo is None else torch.minimum(lo, xlo)
            hi = xhi if hi is None else torch.maximum(hi, xhi)
            g0max = g0 if g0max is None else torch.maximum(g0max, g0)
        size = (self.in_center.numel(),)  # several processes: each read its share of the cells
        lo, hi, g0max = merged_min(lo, size), merged_max(hi, size), merged_max(g0max, ())
        if lo is None or hi is None or g0max is None:
            return
        half = (hi - lo) / 2
        self.in_center.copy_((hi + lo) / 2)
        self.in_scale.copy_(torch.where(half > 0, half, torch.ones_like(half)))
        kinetic = 0.5 * (g0max / self.spacing[0]) ** 2
        self.out_scale.fill_(float(kinetic) if kinetic > 0 else 1.0)

    def _net(self, x: torch.Tensor) -> torch.Tensor:
        y: torch.Tensor = self.net((x - self.in_center) / self.in_scale)
        return self.out_scale * y.squeeze(-1)

    def _formula(self) -> list[str]:
        """Lines of :meth:`describe` that write ``L_d`` out."""
        return []

    def describe(self, max_terms: int | None = 12) -> str:
        head = super().describe(max_terms)
        arch = " -> ".join(str(w) for w in [self._n_inputs() if self.bound else "?", *self.hidden, 1])
        lines = [
            head,
            f"  network: {arch}, {self.activation}, inputs: {self.features}"
            + (", scaled to the data" if self.scale else ""),
        ]
        return "\n".join(lines + self._formula())


class FreeMLPLagrangian(MLPLagrangian):
    """``L_d = net(inputs)`` (``form="free"``), the paper's: the gauge is held by a penalty in training."""

    form = "free"
    inputs: ClassVar[dict[str, _Inputs]] = {
        "values": _Inputs(lambda n, m, k: k * m, lambda model, c: c.reshape(*c.shape[:-2], -1)),
        "differences": _Inputs(lambda n, m, k: (n + 1) * m, _flat_mean_and_differences),
        "invariant": _Inputs(lambda n, m, k: k * (k + 1) // 2, _gram, vector=True),
    }
    default_features = "differences"

    def forward(self, cells: torch.Tensor) -> torch.Tensor:
        return self._net(self._inputs(cells))

    def _formula(self) -> list[str]:
        return ["  L_d = net(inputs) (free form; gauge fixed by the mixed-Hessian penalty)"]


class KineticPotentialMLPLagrangian(MLPLagrangian):
    """``L_d = |g_0|^2 / (2 h_0^2) - sum_k w_k |g_k|^2 / (2 h_k^2) - mean_a V(psi[x+s_a])``
    (``form="kinetic-potential"``), with learned stiffnesses ``w_k`` and a network potential ``V``."""

    form = "kinetic-potential"
    inputs: ClassVar[dict[str, _Inputs]] = {
        "values": _Inputs(lambda n, m, k: m, lambda model, c: c),
        "invariant": _Inputs(
            lambda n, m, k: 1, lambda model, c: torch.sqrt((c * c).sum(-1, keepdim=True)), vector=True
        ),
        "inverse-radius": _Inputs(
            lambda n, m, k: 1, lambda model, c: torch.rsqrt((c * c).sum(-1, keepdim=True)), vector=True
        ),
    }
    default_features = "values"
    #: The potential is a sum of one-site terms, so every block coupling two stencil sites comes from the
    #: quadratic kinetic and gradient terms and is constant.
    constant_mixed_hessian = True

    @property
    def unit_mass_by_construction(self) -> bool:  # type: ignore[override]
        """``M = -I / h_0^2`` exactly when every spatial edge ``e_k`` is in the stencil (its differences then
        never couple ``psi_x`` with ``psi_{x+e_0}``); otherwise the gauge penalty applies."""
        return not self.has_stencil or all(self._edge(k) is not None for k in range(1, self.stencil.ndim))

    def _edge(self, k: int) -> int | None:
        e = [0] * self.stencil.ndim
        e[k] = 1
        return self.stencil.offsets.index(tuple(e)) if tuple(e) in self.stencil.offsets else None

    def _build(self) -> None:
        super()._build()
        self.stiffness = torch.nn.Parameter(torch.ones(self.n - 1, dtype=torch.float64))

    def forward(self, cells: torch.Tensor) -> torch.Tensor:
        lag = self.kinetic(cells)
        potential = self._net(self._inputs(cells)).mean(-1)  # mean over the K stencil sites
        return lag - potential

    def kinetic(self, cells: torch.Tensor) -> torch.Tensor:
        """The kinetic and gradient terms of ``L_d`` on ``cells`` (``(..., K, m)``): quadratic in the values."""
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
            lag = lag - 0.5 * self.stiffness[k - 1] * (dk**2).sum(-1) / h[k] ** 2
        return lag

    def _formula(self) -> list[str]:
        lines = ["  L_d = |D_t psi|^2 / (2 h_t^2) - sum_k w_k |D_k psi|^2 / (2 h_k^2) - mean over stencil of V(psi)"]
        if self.bound and self.n > 1:
            lines.append("  learned w_k = " + ", ".join(f"{float(w):.6g}" for w in self.stiffness))
        return lines


#: ``form`` -> the class that implements it.
_FORM_CLASSES: dict[str, type[MLPLagrangian]] = {
    cls.form: cls for cls in (FreeMLPLagrangian, KineticPotentialMLPLagrangian)
}


def _form_class(options: Mapping[str, Any]) -> type[MLPLagrangian]:
    """The class of the form ``options`` ask for, directly or by a preset (an unknown form: the free form's
    constructor says so)."""
    form = options.get("form")
    if form is None and options.get("preset") is not None:
        form = _settings(None, None, None, None, None, options["preset"])["form"]
    return _FORM_CLASSES.get(form or "free", FreeMLPLagrangian)


def mlp_lagrangian(*args: Any, **options: Any) -> MLPLagrangian:
    """``kind = "mlp"``: the MLP of the form its options ask for (the options of :class:`MLPLagrangian`)."""
    return _form_class(options)(*args, **options)
