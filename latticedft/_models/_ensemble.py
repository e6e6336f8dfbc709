"""An ensemble of one model kind learned on resamples of the data: an error bar on what it serves."""

from __future__ import annotations

import copy
import functools
from collections.abc import Callable, Mapping, Sequence
from typing import Any, cast

import numpy as np
import torch

from .._contract import AbstractLagrangian, NumpyForms
from .._errors import InputError
from .._stencil import Stencil
from . import _polynumpy
from ._polynomial import PolynomialLagrangian, stacked_fast_derivatives
from ._registry import MODELS

__all__ = ["EnsembleLagrangian", "stacked"]

#: Parameters or buffers by name, as ``torch.func`` takes and stacks them.
_State = dict[str, torch.Tensor]


class EnsembleLagrangian(AbstractLagrangian):
    """``members`` copies of one model: member 0 learned on all the data, the others on bootstrap resamples.

    :func:`latticedft.learn` fits member 0 on the full training data (it is the model a plain ``learn``
    gives) and every other member on a bootstrap resample of the data's time windows: each training field
    is cut into windows of consecutive time slices and a member learns from as many windows, drawn with
    replacement from all of them (a resample over fields and windows). Members of a model with a ``seed``
    option (MLPs) also start from different seeds. :func:`latticedft.serve` steps all members together as
    one stacked field (the members' DEL equations never couple), and its result carries the spread:
    ``psi`` is member 0's field, ``mean`` and ``std`` are over all members (docs/uncertainty.md).

    As a Lagrangian (``forward``, :func:`latticedft.diagnose`) the ensemble is member 0.

    Parameters
    ----------
    model : AbstractLagrangian
        The model to copy; it becomes member 0 (fitted in place by ``learn``). A dict ``{"kind": ...,
        "options": {...}}`` rebuilds one from :data:`latticedft.MODELS` (how model files store it).
    members : int
        Members in all, member 0 included (at least 2).
    seed : int
        Seed of the resampling (and of the members' initial weights).

    >>> import latticedft as ldft
    >>> ens = ldft.EnsembleLagrangian(ldft.PolynomialLagrangian((2, 2)), members=5, seed=1)
    >>> len(ens.members), ens.options()["model"]["kind"]
    (5, 'polynomial')
    """

    kind = "ensemble"

    def __init__(
        self,
        model: AbstractLagrangian | Mapping[str, Any],
        *,
        members: int = 9,
        seed: int = 0,
        stencil: Stencil | None = None,
    ):
        if isinstance(model, Mapping):
            model = _rebuilt(model, stencil)
        if not isinstance(model, AbstractLagrangian) or isinstance(model, EnsembleLagrangian):
            raise InputError.at("model", f"expected a latticedft model (not an ensemble), got {type(model).__name__}")
        if not isinstance(members, int) or isinstance(members, bool) or members < 2:
            raise InputError.at("members", f"expected an integer >= 2 (member 0 included), got {members!r}")
        if not isinstance(seed, int) or isinstance(seed, bool) or seed < 0:
            raise InputError.at("seed", f"expected an integer >= 0, got {seed!r}")
        super().__init__(stencil if stencil is not None else (model.stencil if model.has_stencil else None))
        self.seed = seed
        seeds = np.random.default_rng(seed).integers(0, 2**31 - 1, size=members)
        copies: list[AbstractLagrangian] = [model]
        for k in range(1, members):
            member = copy.deepcopy(model)
            member.report_ = None
            member.reseed(int(seeds[k]))  # e.g. an MLP: another initial network
            copies.append(member)
        self.members = torch.nn.ModuleList(copies)

    def __len__(self) -> int:
        return len(self.members)

    @property
    def n_members(self) -> int:
        return len(self)

    def member(self, k: int) -> AbstractLagrangian:
        """Member ``k`` (0: the model learned on all the data)."""
        out = self.members[k]
        assert isinstance(out, AbstractLagrangian)
        return out

    def _build(self) -> None:
        for k in range(len(self)):
            self.member(k).bind(self.n, self.m, self.spacing, self.components)

    def forward(self, cells: torch.Tensor) -> torch.Tensor:
        density: torch.Tensor = self.member(0)(cells)
        return density

    def fast_derivatives(
        self, cells: torch.Tensor, pairs: list[tuple[int, int]]
    ) -> tuple[torch.Tensor, dict[tuple[int, int], torch.Tensor]] | None:
        return self.member(0).fast_derivatives(cells, pairs)

    def trained_range(self) -> torch.Tensor | None:
        return self.member(0).trained_range()

    def options(self) -> dict[str, Any]:
        base = self.member(0)
        return {
            "model": {"kind": MODELS.name_of(base), "options": base.options()},
            "members": len(self),
            "seed": self.seed,
        }

    def load_state_dict(self, state_dict: Mapping[str, Any], strict: bool = True, assign: bool = False) -> Any:
        """As ``torch.nn.Module.load_state_dict``, the members' training ranges (buffers made when learned)
        registered first."""
        for k in range(len(self)):
            rng = state_dict.get(f"members.{k}.feature_range")
            if isinstance(rng, torch.Tensor):
                self.member(k).set_feature_range(rng)
        return super().load_state_dict(state_dict, strict=strict, assign=assign)

    def describe(self, max_terms: int | None = 12) -> str:
        lines = [f"EnsembleLagrangian: {len(self)} members (seed {self.seed}); member 0 learned on all the data:"]
        lines.append(self.member(0).describe(max_terms))
        rel = [self.member(k).report_.rel_res for k in range(1, len(self)) if self.member(k).report_ is not None]
        if rel:
            lines.append(f"  resampled members: rel_res {min(rel):.3e} .. {max(rel):.3e}")
        return "\n".join(lines)


def _rebuilt(spec: Mapping[str, Any], stencil: Stencil | None) -> AbstractLagrangian:
    """The member model a model file describes: ``{"kind": ..., "options": {...}}``."""
    kind = spec.get("kind")
    if not isinstance(kind, str) or kind not in MODELS or not isinstance(spec.get("options"), Mapping):
        raise InputError.at("model", f"expected {{'kind': one of {sorted(MODELS)}, 'options': {{...}}}}, got {spec!r}")
    return MODELS[kind](**spec["options"], stencil=stencil)


class _Stacked(AbstractLagrangian):
    """The members of an ensemble as one ``L_d`` of ``members x m`` components: the sum of the members' ``L_d``,
    member ``k`` seeing components ``k m .. (k + 1) m - 1``. Its DEL equations are the members' own, side by
    side (never coupled), so one serving run steps every member."""

    kind = "ensemble-stack"
    saveable = False

    def __init__(self, members: list[AbstractLagrangian]):
        super().__init__(members[0].stencil)
        self.parts = torch.nn.ModuleList(members)
        self.mm = members[0].m

    def _members(self) -> list[AbstractLagrangian]:
        """The stacked members, in order."""
        return [p for p in self.parts if isinstance(p, AbstractLagrangian)]

    @property
    def n_members(self) -> int:
        """The members stacked side by side: their components follow one another (member 0's first)."""
        return len(self.parts)

    def member(self, k: int) -> AbstractLagrangian:
        return self._members()[k]

    def forward(self, cells: torch.Tensor) -> torch.Tensor:
        m = self.mm
        batched = self._batched
        if batched is not None:  # one vectorised call for every member
            params, buffers, call = batched
            per = cells.unflatten(-1, (len(self.parts), m)).movedim(-2, 0)  # (members, ..., K, m)
            per_member: torch.Tensor = torch.func.vmap(call)(params, buffers, per)
            return per_member.sum(0)
        total = torch.zeros(cells.shape[:-2], dtype=cells.dtype, device=cells.device)
        for k, part in enumerate(self.parts):
            total = total + part(cells[..., k * m : (k + 1) * m])
        return total

    @functools.cached_property
    def _batched(self) -> tuple[_State, _State, Callable[[_State, _State, torch.Tensor], torch.Tensor]] | None:
        """The members' parameters and buffers stacked along a leading axis and a function of one member's
        slice, when the members are neural networks of one structure (their ``L_d`` is then evaluated by one
        ``torch.func.vmap`` call instead of one call per member); ``None`` otherwise. Built once: the stacked
        model is made for one serving run, after learning."""
        parts = self._members()

        def shape(p: AbstractLagrangian) -> tuple[Any, ...]:  # the structure; the initial seed does not change it
            opts = p.options()
            return (type(p), sorted((k, repr(v)) for k, v in opts.items() if k != "seed"), sorted(p.state_dict()))

        neural = not parts[0].linear and any(True for _ in parts[0].parameters())
        if not neural or any(shape(p) != shape(parts[0]) for p in parts):
            return None
        params, buffers = torch.func.stack_module_state(parts)
        params = {k: v.detach() for k, v in params.items()}
        base = copy.deepcopy(parts[0]).to("meta")

        def call(p: _State, b: _State, x: torch.Tensor) -> torch.Tensor:
            density: torch.Tensor = torch.func.functional_call(base, (p, b), (x,))
            return density

        return params, buffers, call

    def fast_derivatives(
        self, cells: torch.Tensor, pairs: list[tuple[int, int]]
    ) -> tuple[torch.Tensor, dict[tuple[int, int], torch.Tensor]] | None:
        """The members' closed forms side by side (block-diagonal second derivatives); high-degree polynomials'
        basis tables evaluated for all members together (:func:`._polynomial.stacked_fast_derivatives`, the same
        values); by autograd on all members at once when a member has none (:meth:`_autograd_derivatives`)."""
        m = self.mm
        parts = self._members()
        own = [cells[..., k * m : (k + 1) * m] for k in range(len(parts))]
        polys = [p for p in parts if isinstance(p, PolynomialLagrangian)]
        found = stacked_fast_derivatives(polys, own, pairs) if len(polys) == len(parts) else None
        if found is None:
            found = []
            for part, c in zip(parts, own, strict=True):
                out = part.fast_derivatives(c, pairs)
                if out is None:
                    return self._autograd_derivatives(cells, pairs)
                found.append(out)
        grad = torch.cat([g for g, _ in found], dim=-1)
        return grad, {pair: _block_diagonal(torch.stack([b[pair] for _, b in found])) for pair in pairs}

    @property
    def numpy_ready(self) -> bool:  # type: ignore[override]
        """Whether :meth:`numpy_derivatives` may give closed forms: every member may (the serving loops ask
        this before building them)."""
        return all(p.numpy_ready for p in self._members())

    def _autograd_derivatives(
        self, cells: torch.Tensor, pairs: list[tuple[int, int]]
    ) -> tuple[torch.Tensor, dict[tuple[int, int], torch.Tensor]]:
        """Gradient and block-diagonal Hessian blocks by autograd, one backward pass per member component for
        all members together: the members never couple, so differentiating the sum over members of their
        ``j``-th gradient component gives every member's ``j``-th Hessian column at once (``1 + m`` passes per
        stencil position instead of ``1 + members * m``, each of which would traverse every member)."""
        n, m = len(self.parts), self.mm
        x = cells.detach().requires_grad_(True)
        with torch.enable_grad():
            (g,) = torch.autograd.grad(self(x).sum(), x, create_graph=True)
            per = g.unflatten(-1, (n, m))  # (..., K, members, m)
            cols: dict[int, list[torch.Tensor]] = {}
            for b in sorted({b for _, b in pairs}):
                cols[b] = []
                for j in range(m):
                    (h,) = torch.autograd.grad(per[..., b, :, j].sum(), x, retain_graph=True, allow_unused=True)
                    cols[b].append((torch.zeros_like(x) if h is None else h).unflatten(-1, (n, m)))
        blocks = {}
        for a, b in pairs:
            col = torch.stack([c[..., a, :, :] for c in cols[b]], dim=-1)  # (..., members, m (row), m (column))
            blocks[(a, b)] = _block_diagonal(col.movedim(-3, 0)).detach()
        return g.detach(), blocks

    def numpy_derivatives(self, pairs: Sequence[tuple[int, int]]) -> NumpyForms | None:
        """The members' numpy closed forms side by side (as :meth:`fast_derivatives`), or None when a member
        offers none: an ensemble of polynomials is then served by the numpy loops as one model is."""
        parts = [p for p in self.parts if isinstance(p, PolynomialLagrangian)]
        if len(parts) == len(self.parts):  # polynomials of one shape: evaluated together
            together = _polynumpy.stacked_numpy_derivatives(parts, pairs)
            if together is not None:
                return together
        forms = []
        for part in self._members():
            form = part.numpy_derivatives(pairs)
            if form is None:
                return None
            forms.append(form)
        return _polynumpy.side_by_side(forms, self.mm, len(pairs))


def _block_diagonal(blocks: torch.Tensor) -> torch.Tensor:
    """``(members, ..., m, m)`` -> ``(..., members m, members m)``, member ``k``'s block on the diagonal."""
    n, m = blocks.shape[0], blocks.shape[-1]
    eye = torch.eye(n, dtype=blocks.dtype, device=blocks.device)
    return torch.einsum("k...ij,kl->...kilj", blocks, eye).reshape(*blocks.shape[1:-2], n * m, n * m)


def stacked(ens: EnsembleLagrangian, components: tuple[str, ...]) -> AbstractLagrangian:
    """The learned members of ``ens`` as one model on ``len(ens) * m`` components labelled ``components``."""
    parts = [ens.member(k) for k in range(len(ens))]
    flag = all(p.constant_mixed_hessian for p in parts)
    cls = cast(type[_Stacked], type("_Stacked", (_Stacked,), {"constant_mixed_hessian": flag}))
    model = cls(parts)
    model.bind(ens.n, len(ens) * ens.m, ens.spacing, components)
    return model
