"""The model contract: what the engine asks of a model of the discrete Lagrangian density ``L_d``.

:class:`AbstractLagrangian` is the base class of every model. It binds a model to a lattice and holds the
features the models share; its methods and class attributes with defaults are the *capabilities* the
action, the learner, the server and the case pipeline read. A model kind overrides the ones it has
(closed-form derivatives, a lower bound on its parameters, the candidates ``select = "auto"`` tries) and
inherits the defaults of the others, so nothing above this module looks a capability up by name.

The gauge a model was learned with is a :class:`GaugeName`: reports and model files write its value (a
plain string), and :func:`parse_gauge` reads one back.
"""

from __future__ import annotations

import abc
import enum
import inspect
import math
from collections.abc import Callable, Iterable, Mapping, Sequence
from typing import Any, ClassVar

import numpy as np
import torch

from ._errors import InputError
from ._modeloptions import option_checks_of
from ._stencil import Stencil
from ._symbolic import SymbolicLd

__all__ = ["AbstractLagrangian", "DEFAULT_GAUGE", "GaugeName", "NumpyForms", "parse_gauge"]

#: ``LinearLagrangian`` once its module has defined it (it checks that ``linear = True`` comes with its contract).
_LINEAR_BASE: list[type] = []

#: Numpy closed forms of a model for given stencil pairs: ``fn(cells (B, K, m)) -> (dL/dx, [blocks per pair])``.
NumpyForms = Callable[[np.ndarray], tuple[np.ndarray, list[np.ndarray]]]


class GaugeName(enum.StrEnum):
    """The gauges :func:`latticedft.learn` fixes, by the names that case files, reports and model files use."""

    UNIT_MASS = "unit-mass"
    TRACE = "trace"
    NONE = "none"


#: The gauge of a model file that names none (and of a model saved before it was learned).
DEFAULT_GAUGE = GaugeName.UNIT_MASS


def parse_gauge(value: object, *, key: str = "gauge") -> GaugeName:
    """The :class:`GaugeName` of ``value`` (a name such as ``"unit-mass"``); an InputError naming ``key``
    for anything else."""
    if isinstance(value, str) and value in GaugeName.__members__.values():
        return GaugeName(value)
    raise InputError.at(key, f"expected one of {[g.value for g in GaugeName]}, got {value!r}")


class AbstractLagrangian(torch.nn.Module, abc.ABC):
    """A discrete Lagrangian density ``L_d(psi[x+s_0], ..., psi[x+s_{K-1}])``.

    Subclasses implement :meth:`forward` on a batch of cells ``(..., K, m)``
    returning ``(...)``. A model is *bound* to a lattice (dimension ``n``,
    components ``m``, spacings ``h``) when it is first learned; a discrete
    theory belongs to its lattice spacing, so serving checks the spacing.

    What a subclass implements (the contract; :class:`LinearLagrangian` adds the linear one):

    - ``kind``: the name used in ``case.toml`` and model files (and the key of its
      :data:`latticedft.MODELS` entry);
    - ``__init__(..., *, stencil=None)``: keyword options with type annotations (``case.toml``
      checks ``[model]`` values against them, see :meth:`option_checks`), returned by :meth:`options`;
    - :meth:`_build`: parameters and buffers, once the lattice is known;
    - :meth:`forward`: ``L_d`` on a batch of cells, smooth (serving differentiates twice);
    - optionally :meth:`prepare` (input scaling from the training data), :meth:`describe`, and the
      capabilities below, each with a default: the class flags, :meth:`fast_derivatives` and
      :meth:`numpy_derivatives` (closed-form derivatives for serving; ``None``: autograd),
      :attr:`has_functions`, :attr:`bridged`, :meth:`parameter_lower_bound` (the memory check),
      :meth:`auto_candidates` (``select = "auto"``), :meth:`reseed` (ensemble members), and
      :attr:`n_members` with :meth:`member` (an ensemble's members; a model is its own only member).
    """

    kind: ClassVar[str] = "abstract"
    #: True when ``L_d`` is linear in its parameters (``coef``): learned exactly.
    linear: ClassVar[bool] = False
    #: True when the model may offer numpy closed forms (:meth:`numpy_derivatives`; linear models, and stacked
    #: ensembles of them): the serving loops ask this before building them.
    numpy_ready: ClassVar[bool] = False
    #: True when the mixed time Hessian is ``-I / h_0^2`` by construction.
    unit_mass_by_construction: ClassVar[bool] = False
    #: True when every block coupling two different stencil sites is constant (1D serving then assembles
    #: the Newton Jacobian once).
    constant_mixed_hessian: ClassVar[bool] = False
    #: False for models that cannot be written to a model file.
    saveable: ClassVar[bool] = True
    #: True for models without learned parameters (a formula in the spacings): serving binds them to the
    #: lattice it is given instead of checking that lattice against the one they were learned on.
    rebinds_to_any_lattice: ClassVar[bool] = False
    #: True when :meth:`prepare` merges what every process of a process group saw (``latticedft._collective``):
    #: training in several processes then reads each process's share of the cells for it; otherwise every
    #: process reads every cell. A subclass that overrides ``prepare`` states it again.
    prepare_merges_processes: ClassVar[bool] = False
    #: The methods that evaluate ``L_d`` or its features on cells, or return one of its buffers: on a device
    #: other than the CPU they run on the model's device and answer on the caller's (``latticedft._device``).
    bridged: ClassVar[tuple[str, ...]] = ("forward", "fast_derivatives", "mean_and_differences", "trained_range")
    #: ``learn(model, data, ensemble=N)``: the :class:`latticedft.EnsembleLagrangian` whose member 0 is this model.
    ensemble_: Any = None
    #: What :attr:`report_` and :attr:`gauge` return.
    _report: Any = None
    _gauge: GaugeName | None = None

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        if cls.linear and _LINEAR_BASE and not issubclass(cls, _LINEAR_BASE[0]):
            raise TypeError(
                f"{cls.__name__}: a model linear in its parameters subclasses "
                "latticedft.LinearLagrangian (setting linear = True is not enough)"
            )

    #: Projection ``(n + 1, K)`` of the stencil values onto (mean, per-axis differences); a buffer set by
    #: :meth:`bind`.
    proj: torch.Tensor

    def __init__(self, stencil: Stencil | None = None):
        if stencil is not None and not isinstance(stencil, Stencil):
            raise InputError.at("stencil", f"expected a latticedft.Stencil or None, got {type(stencil).__name__}")
        super().__init__()
        self._stencil: Stencil | None = stencil
        self._n: int | None = None
        self._m: int | None = None
        self._spacing: tuple[float, ...] | None = None
        self.components: tuple[str, ...] | None = None

    # -- binding to a lattice -----------------------------------------------------------------------------
    @property
    def bound(self) -> bool:
        return self._spacing is not None

    @property
    def has_stencil(self) -> bool:
        """True once the stencil is known: given to the constructor, else chosen by :meth:`bind`."""
        return self._stencil is not None

    @property
    def stencil(self) -> Stencil:
        """The stencil (given, or the first-order one chosen by :meth:`bind`); ``InputError`` before either."""
        if self._stencil is None:  # bind() always sets one
            raise self._unbound_error()
        return self._stencil

    @property
    def n(self) -> int:
        """Lattice dimensions (time first); ``InputError`` until the model is bound."""
        return self._lattice()[0]

    @property
    def m(self) -> int:
        """Field components; ``InputError`` until the model is bound."""
        return self._lattice()[1]

    @property
    def spacing(self) -> tuple[float, ...]:
        """Lattice spacings ``h`` (time first); ``InputError`` until the model is bound."""
        return self._lattice()[2]

    def bind(self, n: int, m: int, spacing: tuple[float, ...], components: tuple[str, ...] | None = None) -> None:
        """Fix the lattice dimension, number of components and spacings; build parameters."""
        if self._stencil is None:
            self._stencil = Stencil.first_order(n)
        if self._stencil.ndim != n:
            raise InputError.at(
                "stencil", f"has offsets in {self._stencil.ndim} dimensions but the data have {n} lattice dims"
            )
        if self.bound and (self.n, self.m) != (n, m):
            raise InputError(f"model: bound to n={self.n}, m={self.m}; data have n={n}, m={m}")
        first = not self.bound
        self._n, self._m = n, m
        self._spacing = tuple(float(h) for h in spacing)
        self.components = components
        if first:
            self.register_buffer("proj", self._projection(), persistent=False)
            self._build()
        self.double()

    def _build(self) -> None:
        """Create parameters and buffers once ``n``, ``m`` and the stencil are known."""

    def prepare(self, cells: Iterable[torch.Tensor]) -> None:
        """Data-dependent set-up before training (input scaling), from the training cells: a sequence of
        ``(*cells, K, m)`` tensors that streamed training reads one chunk at a time (reduce chunk by chunk)."""

    def _require_bound(self) -> None:
        if not self.bound:
            raise self._unbound_error()

    def _unbound_error(self) -> InputError:
        return InputError(f"{type(self).__name__}: not bound to a lattice yet; learn it first (latticedft.learn)")

    def _lattice(self) -> tuple[int, int, tuple[float, ...]]:
        """``(n, m, spacing)`` of the bound lattice; ``InputError`` before :meth:`bind`."""
        if self._n is None or self._m is None or self._spacing is None:
            raise self._unbound_error()
        return self._n, self._m, self._spacing

    # -- what learning left: the report and the gauge -----------------------------------------------------
    @property
    def report_(self) -> Any:
        """The ``LearnReport`` of the last :func:`latticedft.learn` (``None`` before); setting a report sets
        :attr:`gauge` to the report's gauge."""
        return self._report

    @report_.setter
    def report_(self, report: Any) -> None:
        object.__setattr__(self, "_report", report)
        if report is not None:
            self.gauge = report.gauge

    @property
    def gauge(self) -> GaugeName | None:
        """The gauge ``L_d`` was learned with: set by :func:`latticedft.learn` (with :attr:`report_`) and by
        :func:`latticedft.load_model`; ``None`` before either."""
        return self._gauge

    @gauge.setter
    def gauge(self, value: GaugeName | str | None) -> None:
        object.__setattr__(self, "_gauge", None if value is None else parse_gauge(value))

    # -- evaluation ---------------------------------------------------------------------------------------
    @abc.abstractmethod
    def forward(self, cells: torch.Tensor) -> torch.Tensor:
        """``L_d`` on cells ``(..., K, m)``, returning ``(...)``."""

    def fast_derivatives(
        self, cells: torch.Tensor, pairs: list[tuple[int, int]]
    ) -> tuple[torch.Tensor, dict[tuple[int, int], torch.Tensor]] | None:
        """Closed-form per-cell derivatives, or ``None`` (the default) where the model has none.

        A model that overrides this returns ``(grad, blocks)`` without autograd: ``grad`` is ``dL/dx_a``
        with shape ``(*cells, K, m)``, and ``blocks[(a, b)]`` is ``d^2 L / dx_a dx_b`` with shape
        ``(*cells, m, m)`` (row: component of ``x_a``) for each ``(a, b)`` in ``pairs``. With ``None``
        the action module differentiates :meth:`forward` by autograd.
        """
        return None

    def numpy_derivatives(self, pairs: Sequence[tuple[int, int]]) -> NumpyForms | None:
        """Numpy closed forms ``fn(cells (B, K, m)) -> (dL/dx, [blocks per pair])`` for ``pairs``, or ``None``
        (the default): asked only when :attr:`numpy_ready` is true, and served on the CPU in double precision."""
        return None

    def symbolic(self) -> SymbolicLd | None:
        """This ``L_d`` in closed form (:class:`latticedft._symbolic.SymbolicLd`), or ``None`` (the default):
        models known in closed form override it; printing, ``to_sympy`` and the compiled kernels read it."""
        return None

    def to_sympy(self) -> Any:
        """``L_d`` of one cell as a sympy expression in the stencil values ``u{point}_{component}``.

        Raises ``InputError`` for a model with no closed form (an MLP)."""
        form = self.symbolic()
        if form is None:
            raise InputError.at("model", f"{type(self).__name__} (kind {self.kind!r}) has no closed form")
        return form.expr

    def equation_text(self) -> dict[str, Any]:
        """``L_d`` and the DEL it implies as readable text (keys ``L_d``, ``latex``, ``del``, ``where``) for
        models that print themselves as an equation (the sparse kind); ``{}`` (the default) for the others."""
        return {}

    # -- capabilities read by learning, serving and the case pipeline -------------------------------------
    @property
    def has_functions(self) -> bool:
        """True when the model holds Python functions (a model file cannot store it); False by default."""
        return False

    @property
    def n_members(self) -> int:
        """Models in this one: an ensemble's members; 1 for any other model."""
        return 1

    def member(self, k: int) -> AbstractLagrangian:
        """Member ``k`` (0: the model learned on all the data); a model that is no ensemble is its member 0."""
        if k != 0:
            raise IndexError(f"{type(self).__name__} has one member; asked for member {k}")
        return self

    def reseed(self, seed: int) -> None:
        """Start from another initial state (the members of an ensemble): models with a ``seed`` option take
        ``seed``; the others (the default) have nothing to change."""

    @classmethod
    def parameter_lower_bound(cls, options: Mapping[str, Any], n: int, m: int) -> tuple[int, str] | None:
        """``(a lower bound of the parameter count, the option key that sets it)`` of this kind with
        ``options`` on a lattice of ``n`` dimensions and ``m`` components, without building any tensor; or
        ``None`` (the default: no bound known). The memory check before a case runs refuses a model whose
        parameters alone exceed the memory. Bad options give ``None``: they are the case reader's to report."""
        return None

    def auto_candidates(self, n: int, ridge: Any = 0.0) -> list[dict[str, Any]]:
        """The candidates of ``select = "auto"`` for this hand-set model on an ``n``-dimensional lattice, as
        option changes (a change may name another ``kind``, and ``ridge``). The default: input scaling
        flipped when the model has a ``scale`` option, else none."""
        opts = self.options()
        return [{"scale": not opts["scale"]}] if "scale" in opts else []

    # -- features shared by models ------------------------------------------------------------------------
    def _projection(self) -> torch.Tensor:
        """Matrix ``(n + 1, K)`` mapping stencil values to (mean, per-axis differences).

        Least-squares fit of ``c + sum_k g_k (s_k - centroid_k)`` over the
        stencil; exact for the first-order stencil, where ``g_k`` is
        ``psi[x + e_k] - psi[x]`` and ``c`` the mean of the ``K`` values.
        """
        s = self.stencil.array.astype(np.float64)
        s = s - s.mean(axis=0)
        a = np.hstack([np.ones((s.shape[0], 1)), s])
        return torch.from_numpy(np.linalg.pinv(a))

    def mean_and_differences(self, cells: torch.Tensor) -> torch.Tensor:
        """``(..., n + 1, m)``: the stencil mean then ``g_0 ... g_{n-1}``."""
        return torch.einsum("pk,...km->...pm", self.proj, cells)

    # -- the training range -------------------------------------------------------------------------------
    def record_feature_range(self, cells: Iterable[torch.Tensor]) -> None:
        """Store the range of the stencil's inputs over the training cells (a buffer: saved in model files).

        Per feature of :meth:`mean_and_differences` (the stencil mean, then the difference along each axis,
        per component), the minimum and maximum over every cell in ``cells`` (merged chunk by chunk); serving
        measures how far its cells leave this range (``ServeResult.extrapolation``).
        """
        lo: torch.Tensor | None = None
        hi: torch.Tensor | None = None
        for c in cells:
            feats = self.mean_and_differences(c.detach().to(torch.float64))
            feats = feats.reshape(-1, *feats.shape[-2:])
            if feats.shape[0] == 0:
                continue
            clo, chi = feats.amin(0), feats.amax(0)
            lo = clo if lo is None else torch.minimum(lo, clo)
            hi = chi if hi is None else torch.maximum(hi, chi)
        if lo is not None and hi is not None:
            self.set_feature_range(torch.stack([lo, hi]))

    def set_feature_range(self, value: torch.Tensor) -> None:
        """Set the training range ``(2, n + 1, m)`` (minima, maxima), e.g. from a model file's state."""
        self.register_buffer("feature_range", value.detach().to(torch.float64).clone())

    def trained_range(self) -> torch.Tensor | None:
        """``(2, n + 1, m)``: the minima and maxima of :meth:`mean_and_differences` over the training cells,
        or None (a model not learned from data, or read from a model file written before ranges were kept)."""
        return self._buffers.get("feature_range")

    # -- description -------------------------------------------------------------------------------------
    def options(self) -> dict[str, Any]:
        """Constructor keywords that rebuild this model (JSON-compatible)."""
        return {}

    @classmethod
    def option_checks(cls) -> dict[str, Callable[[Any], Any]]:
        """Option name -> type check of a ``case.toml`` value, read from the constructor's annotations.

        Each check returns the (normalised) value or raises ``OptionTypeError`` saying what was expected;
        the constructor then checks the values themselves. ``stencil`` is not an option.

        >>> from latticedft import PolynomialLagrangian
        >>> sorted(PolynomialLagrangian.option_checks())
        ['basis', 'orders', 'parity', 'scale', 'time_symmetric']
        """
        return option_checks_of(cls.__init__)

    @classmethod
    def option_defaults(cls) -> dict[str, Any]:
        """Option name -> its default in the constructor (``None`` for an option without one); ``stencil`` is
        not an option."""
        sig = inspect.signature(cls.__init__)
        return {
            name: (None if p.default is inspect.Parameter.empty else p.default)
            for name, p in sig.parameters.items()
            if name not in ("self", "stencil") and p.kind not in (p.VAR_POSITIONAL, p.VAR_KEYWORD)
        }

    def n_parameters(self) -> int:
        return sum(p.numel() for p in self.parameters())

    def describe(self, max_terms: int | None = 12) -> str:
        """The learned ``L_d`` in words; subclasses add their terms (at most ``max_terms`` of them, the
        largest first; ``None``: all)."""
        lines = [f"{type(self).__name__} (kind {self.kind!r}), {self.n_parameters()} parameters"]
        if self.bound:
            lines.append(
                f"  lattice: n = {self.n} (time first), m = {self.m} component(s), "
                f"spacing = {tuple(float(f'{h:.6g}') for h in self.spacing)}"
            )
            lines.append(f"  stencil: {self.stencil.to_list()}")
        else:
            lines.append("  not bound to a lattice yet")
        if self.report_ is not None:
            lines.append("  " + self.report_.summary_line())
        return "\n".join(lines)

    def __str__(self) -> str:  # print(model) shows the learned theory
        return self.describe()

    def extra_repr(self) -> str:
        return ", ".join(f"{k}={v!r}" for k, v in self.options().items())

    @property
    def cell_volume(self) -> float:
        self._require_bound()
        return math.prod(self.spacing)
