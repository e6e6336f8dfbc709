"""The discrete action, the DEL residual, the mixed time Hessian and the action's sparse Hessian.

``A_d = prod(h) * sum_cells L_d(psi[x+s_0], ..., psi[x+s_{K-1}])`` and
``EL_y = dA_d / dpsi_y``, evaluated on a whole field by one reverse-mode pass
(Qin 2020, Eqs. 3 and 6). The Hessian ``d^2 A_d / dpsi_x dpsi_y`` couples only the sites of a common cell:
:func:`action_hessian` assembles it as a sparse matrix from the per-cell blocks ``d^2 L_d / dx_a dx_b``.
"""

from __future__ import annotations

import math
import weakref
from collections.abc import Sequence
from typing import Any

import numpy as np
import scipy.sparse
import torch
import xarray as xr

from ._contract import AbstractLagrangian, NumpyForms
from ._errors import InputError
from ._kernel import CompiledForms, compile_forms
from ._lattice import AxisBoundaries, LatticeField, as_lattice_field, gather_cells, interior_slices
from ._options import option
from ._stencil import Stencil

__all__ = [
    "check_model_lattice",
    "action",
    "action_hessian",
    "del_residual",
    "mixed_hessian",
    "cell_derivatives",
    "CellDerivatives",
    "numpy_closed_forms",
    "compiled_closed_forms",
    "second_time_difference",
]


def _check_action_args(
    model: AbstractLagrangian, psi: object, spacing: object, periodic: object, batch: object
) -> None:
    """Refuse bad :func:`action` arguments with an InputError naming the argument."""
    _check_model(model)
    if not isinstance(psi, torch.Tensor):
        raise InputError.at("psi", f"expected a torch tensor of shape (*N, m), got {type(psi).__name__}")
    if not isinstance(batch, int) or isinstance(batch, bool) or batch < 0:
        raise InputError.at("batch", f"expected a non-negative integer, got {batch!r}")
    n = int(model.stencil.ndim)
    if psi.ndim != batch + n + 1:
        raise InputError.at(
            "psi", f"expected {batch + n + 1} dims ({batch} batch, {n} lattice, 1 component), got {tuple(psi.shape)}"
        )
    if not isinstance(periodic, (tuple, list)) or len(periodic) != n:
        raise InputError.at("periodic", f"expected one entry per lattice axis ({n}), got {periodic!r}")
    if (
        not isinstance(spacing, (tuple, list))
        or len(spacing) != n
        or not all(isinstance(h, (int, float)) and not isinstance(h, bool) and h > 0 for h in spacing)
    ):
        raise InputError.at("spacing", f"expected positive numbers, one per lattice axis ({n}), got {spacing!r}")


def action(
    model: AbstractLagrangian, psi: torch.Tensor, spacing: tuple[float, ...], periodic: AxisBoundaries, batch: int = 0
) -> torch.Tensor:
    """Total discrete action of one field ``psi`` with shape ``(*N, m)`` (summed over ``batch`` leading axes).

    ``spacing`` and ``periodic`` have one entry per lattice axis of ``psi``.
    """
    _check_action_args(model, psi, spacing, periodic, batch)
    return _action(model, psi, spacing, periodic, batch)


def _action(
    model: AbstractLagrangian, psi: torch.Tensor, spacing: tuple[float, ...], periodic: AxisBoundaries, batch: int
) -> torch.Tensor:
    """:func:`action` without the argument checks (the engine's own calls)."""
    cells = gather_cells(psi, model.stencil, periodic, batch)
    density: torch.Tensor = model(cells)
    return math.prod(spacing) * density.sum()


def action_hessian(
    model: AbstractLagrangian, psi: torch.Tensor, spacing: tuple[float, ...], periodic: AxisBoundaries
) -> tuple[torch.Tensor, scipy.sparse.csr_matrix]:
    """The gradient ``dA_d / dpsi`` (``psi``'s shape, on its device) and the Hessian ``d^2 A_d / dpsi dpsi`` of
    the action of one field ``psi`` (``(*N, m)``, no batch axes), the latter a CPU sparse matrix over the
    flattened values of ``psi`` (row-major: sites, then components).

    Both are sums over the cells of their per-cell derivatives (:func:`cell_derivatives`: the model's closed
    forms where it has them, else ``K m`` backward passes), scattered to the sites each cell's points land on;
    a Hessian-vector product is then one sparse product instead of a double backward pass through the model.
    """
    st = model.stencil
    k, m = st.size, int(psi.shape[-1])
    where = gather_cells(torch.arange(psi.numel()).reshape(psi.shape), st, periodic).reshape(-1, k, m)
    cells = gather_cells(psi.detach(), st, periodic)
    pairs = [(a, b) for a in range(k) for b in range(k)]
    grad, blocks = cell_derivatives(model, cells, pairs)
    scale = math.prod(spacing)
    flat = where.reshape(-1).to(psi.device)
    g = torch.zeros(psi.numel(), dtype=psi.dtype, device=psi.device).index_add_(0, flat, grad.reshape(-1))
    rows = [where[:, a, :, None].expand(-1, m, m).reshape(-1) for a, _ in pairs]
    cols = [where[:, b, None, :].expand(-1, m, m).reshape(-1) for _, b in pairs]
    vals = torch.cat([blocks[p].reshape(-1) for p in pairs]).detach().cpu().numpy() * scale
    size = psi.numel()
    hess = scipy.sparse.csr_matrix((vals, (torch.cat(rows).numpy(), torch.cat(cols).numpy())), shape=(size, size))
    return (g * scale).reshape(psi.shape), hess


def check_model_lattice(model: AbstractLagrangian, f: LatticeField, what: str) -> None:
    """Refuse a field whose lattice (dims, components, spacing) is not the one the model is bound to."""
    if model.has_stencil and model.stencil.ndim != f.ndim:
        raise InputError(f"{what}: has {f.ndim} lattice dims but the model's stencil has {model.stencil.ndim}")
    if model.bound:
        if model.m != f.ncomp:
            raise InputError(f"{what}: has {f.ncomp} component(s) but the model was learned with {model.m}")
        if model.components and f.components and tuple(model.components) != tuple(f.components):
            raise InputError(
                f"{what}: component labels {list(f.components)} differ from the model's {list(model.components)}"
            )
        for k, (a, b) in enumerate(zip(f.spacing, model.spacing)):
            if not math.isclose(a, b, rel_tol=1e-6):
                raise InputError(
                    f"{what}: spacing along {f.dims[k]!r} is {a:.6g} but the model was learned at "
                    f"{b:.6g} (a discrete theory belongs to its lattice)"
                )


def _check_model(model: AbstractLagrangian) -> None:
    """Refuse anything but a model bound to a lattice (an InputError naming ``model``)."""
    if not isinstance(model, AbstractLagrangian):
        raise InputError.at("model", f"expected a latticedft model, got {type(model).__name__}")
    if not model.bound:
        raise InputError.at(
            "model", f"{type(model).__name__} is not bound to a lattice; learn it first (or model.bind(n, m, h))"
        )


def del_residual(
    model: AbstractLagrangian, f: LatticeField | xr.DataArray, *, create_graph: bool = False
) -> torch.Tensor:
    """DEL residual ``EL_y`` on the interior sites of ``f``: shape ``(*interior, m)``.

    ``f`` is a :class:`LatticeField` or a DataArray in the field layout
    (converted by :func:`as_lattice_field`). With ``create_graph=True`` the
    result is differentiable in the model's parameters (for training).
    """
    if not isinstance(f, LatticeField):
        f = as_lattice_field(f, source="field")
    _check_model(model)
    psi = f.values.detach().clone().requires_grad_(True)
    with torch.enable_grad():
        a = _action(model, psi, f.spacing, f.boundary, f.batch)
        (g,) = torch.autograd.grad(a, psi, create_graph=create_graph)
    return g[(slice(None),) * f.batch + interior_slices(f.shape, model.stencil, f.boundary)]


def cell_derivatives(
    model: AbstractLagrangian, cells: torch.Tensor, pairs: list[tuple[int, int]], *, create_graph: bool = False
) -> tuple[torch.Tensor, dict[tuple[int, int], torch.Tensor]]:
    """Per-cell gradient ``dL/dx_a`` (``(*cells, K, m)``) and Hessian blocks.

    ``pairs`` lists the ``(a, b)`` stencil positions whose ``m x m`` blocks
    ``d^2 L / dx_a dx_b`` (shape ``(*cells, m, m)``, row = component of
    ``x_a``) are wanted. Costs one backward pass per distinct ``b`` and
    component, unless the model has closed forms (:meth:`AbstractLagrangian.fast_derivatives`) and no graph
    is asked for.
    """
    if not create_graph:
        closed = model.fast_derivatives(cells.detach(), pairs)
        if closed is not None:
            return closed
    x = cells.detach().requires_grad_(True) if not cells.requires_grad else cells
    m = x.shape[-1]
    with torch.enable_grad():
        lval = model(x)
        (g,) = torch.autograd.grad(lval.sum(), x, create_graph=True)
        blocks: dict[tuple[int, int], torch.Tensor] = {}
        bs = sorted({b for _, b in pairs})
        cols: dict[int, list[torch.Tensor]] = {}
        for b in bs:
            cols[b] = []
            for j in range(m):
                (hj,) = torch.autograd.grad(
                    g[..., b, j].sum(), x, retain_graph=True, create_graph=create_graph, allow_unused=True
                )
                if hj is None:
                    hj = torch.zeros_like(x)
                cols[b].append(hj)  # d/dx_b,j of dL/dx  -> (*cells, K, m)
        for a, b in pairs:
            # H[a, i; b, j] = d^2L/dx_{a,i} dx_{b,j}
            blocks[(a, b)] = torch.stack([c[..., a, :] for c in cols[b]], dim=-1)
    if not create_graph:
        g = g.detach()
        blocks = {k: v.detach() for k, v in blocks.items()}
    return g, blocks


#: Per model, its numpy closed forms (:meth:`AbstractLagrangian.numpy_derivatives`) per tuple of pairs, with the
#: parameters and buffers they were built from (rebuilt when one is replaced or changed in place).
_NumpyFormsCache = dict[tuple[tuple[int, int], ...], NumpyForms | None]
_NUMPY_FORMS: weakref.WeakKeyDictionary[AbstractLagrangian, tuple[list[tuple[torch.Tensor, int]], _NumpyFormsCache]] = (
    weakref.WeakKeyDictionary()
)


def numpy_closed_forms(
    model: AbstractLagrangian, cells: torch.Tensor, pairs: Sequence[tuple[int, int]]
) -> NumpyForms | None:
    """The model's numpy ``fn(cells (B, K, m)) -> (dL/dx, [blocks per pair])`` for ``pairs``, or ``None``: for
    a linear model that offers them, with its parameters and ``cells`` on the CPU in double precision (a model
    on an accelerator keeps its torch closed forms). Built once per model state."""
    if not model.numpy_ready or cells.device.type != "cpu":
        return None
    if cells.dtype != torch.float64:
        return None
    state = [*model.parameters(), *model.buffers()]
    if any(t.device.type != "cpu" for t in state):
        return None
    forms = _NUMPY_FORMS.get(model)
    key = [(t, t._version) for t in state]
    if forms is None or len(forms[0]) != len(key) or any(a is not b or u != v for (a, u), (b, v) in zip(forms[0], key)):
        built: _NumpyFormsCache = {}
        forms = (key, built)
        _NUMPY_FORMS[model] = forms
    pairs = tuple(pairs)
    if pairs not in forms[1]:
        forms[1][pairs] = model.numpy_derivatives(pairs)
    return forms[1][pairs]


def serving_pairs(stencil: Stencil) -> list[tuple[int, int]]:
    """The stencil pairs whose blocks serving needs: every point on a cell's first slice with every point on
    its second (the mixed Hessian blocks of a slice's Jacobian)."""
    now = [a for a, o in enumerate(stencil.offsets) if o[0] == 0]
    nxt = [a for a, o in enumerate(stencil.offsets) if o[0] == 1]
    return [(a, b) for a in now for b in nxt]


#: Per model, its compiled kernels (:func:`compiled_closed_forms`) with the state they were built from.
_COMPILED: weakref.WeakKeyDictionary[AbstractLagrangian, tuple[list[Any], CompiledForms | None]] = (
    weakref.WeakKeyDictionary()
)


def compiled_closed_forms(
    model: AbstractLagrangian, cells: torch.Tensor, numpy_too: bool = False
) -> CompiledForms | None:
    """The model's compiled gradient and :func:`serving_pairs` blocks (:mod:`latticedft._kernel`), or ``None``:
    for a model without numpy closed forms (with them too where ``numpy_too``) whose ``symbolic()`` compiles,
    with ``cells`` on the CPU in double precision, while the ``compiled_kernels`` option is on. Built once per
    model state and lattice."""
    if not option("compiled_kernels") or (model.numpy_ready and not numpy_too) or cells.device.type != "cpu":
        return None
    if cells.dtype != torch.float64 or not model.bound:
        return None
    state = [*model.parameters(), *model.buffers()]
    key: list[Any] = [tuple(model.spacing), model.stencil.offsets, model.m] + [(t, t._version) for t in state]
    known = _COMPILED.get(model)
    if known is not None and len(known[0]) == len(key) and all(_same(a, b) for a, b in zip(known[0], key)):
        return known[1]
    form = model.symbolic()
    built = None if form is None else compile_forms(form, serving_pairs(model.stencil), type(model).__name__)
    _COMPILED[model] = (key, built)
    return built


def _same(a: Any, b: Any) -> bool:
    """Whether two entries of a compiled-kernel key agree: a tensor by identity and version, or, where the
    model holds a new tensor (an analytic model binding its projection afresh on every call), one left
    unchanged since with the same values."""
    if isinstance(a, tuple) and len(a) == 2 and isinstance(a[0], torch.Tensor):
        if not isinstance(b, tuple) or not isinstance(b[0], torch.Tensor):
            return False
        if a[0] is b[0]:
            return bool(a[1] == b[1])
        old, new = a[0], b[0]
        if old._version != a[1] or old.dtype != new.dtype or old.shape != new.shape or old.device != new.device:
            return False
        return bool(torch.equal(old, new))
    return bool(a == b)


class CellDerivatives:
    """Per-cell gradient now, Hessian blocks on demand (serving skips them while a cached Jacobian serves).

    The gradient is taken without a graph; only when blocks are asked for is
    it taken again with one (one extra pass, saved on every slice that needs
    no fresh Jacobian). A model's numpy closed forms serve when it has them
    (:func:`numpy_closed_forms`), then its compiled kernel (:func:`compiled_closed_forms`), then its torch
    closed forms, then autograd.
    """

    def __init__(self, model: AbstractLagrangian, cells: torch.Tensor):
        self.model = model
        self.cells = cells.detach()
        fn = numpy_closed_forms(model, self.cells, ())
        self._numpy = fn is not None
        self._closed = False
        self._compiled = None if fn is not None else compiled_closed_forms(model, self.cells)
        if fn is not None:
            self.grad = torch.from_numpy(self._numpy_forms(fn)[0].reshape(self.cells.shape))
            return
        if self._compiled is not None:
            self.grad = torch.from_numpy(self._compiled.grad(self._flat()).reshape(self.cells.shape))
            return
        closed = model.fast_derivatives(self.cells, [])
        self._closed = closed is not None  # the model's closed forms serve the blocks too
        if closed is not None:
            self.grad = closed[0]
            return
        x = self.cells.requires_grad_(True)
        with torch.enable_grad():
            (g,) = torch.autograd.grad(model(x).sum(), x)
        self.grad = g.detach()

    def _flat(self) -> np.ndarray:
        """The cells as one contiguous ``(B, K, m)`` array."""
        c = self.cells
        return np.ascontiguousarray(c.numpy()).reshape(-1, c.shape[-2], c.shape[-1])

    def _numpy_forms(self, fn: NumpyForms) -> tuple[np.ndarray, list[np.ndarray]]:
        """``fn`` (numpy closed forms) on the cells. A diverging serve overflows there: its values turn non-finite,
        which serving tests for (as it does for the torch forms, which are silent), with no numpy warning."""
        with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
            return fn(self._flat())

    def blocks(self, pairs: list[tuple[int, int]]) -> dict[tuple[int, int], torch.Tensor]:
        if self._numpy and (fn := numpy_closed_forms(self.model, self.cells, pairs)) is not None:
            lead, m = self.cells.shape[:-2], self.cells.shape[-1]
            out = self._numpy_forms(fn)[1]
            return {p: torch.from_numpy(b.reshape(*lead, m, m)) for p, b in zip(pairs, out)}
        if self._compiled is not None and list(pairs) == serving_pairs(self.model.stencil):
            lead, m = self.cells.shape[:-2], self.cells.shape[-1]
            out = self._compiled.both(self._flat())[1]
            return {p: torch.from_numpy(b.reshape(*lead, m, m)) for p, b in zip(pairs, out)}
        if self._closed and (closed := self.model.fast_derivatives(self.cells, pairs)) is not None:
            return closed[1]
        return cell_derivatives(self.model, self.cells.detach(), pairs)[1]


def mixed_hessian(model: AbstractLagrangian, f: LatticeField, *, create_graph: bool = False) -> torch.Tensor:
    """The mixed time Hessian ``M = d^2 L_d / dpsi_x dpsi_{x+e_0}`` on every cell of ``f``: ``(ncells, m, m)``."""
    st = model.stencil
    cells = gather_cells(f.values, st, f.boundary, f.batch)
    pair = (st.anchor, st.forward)
    _, blocks = cell_derivatives(model, cells, [pair], create_graph=create_graph)
    m = f.ncomp
    return blocks[pair].reshape(-1, m, m)


def second_time_difference(f: LatticeField, stencil: Stencil) -> torch.Tensor:
    """``psi_{y+e0} - 2 psi_y + psi_{y-e0}`` on the interior sites of ``f``."""
    v = f.values
    d2 = v[2:] - 2 * v[1:-1] + v[:-2]
    inner = interior_slices(f.shape, stencil, f.boundary)
    pad = torch.nn.functional.pad(d2, [0, 0] * (v.ndim - 1) + [1, 1])  # back to full time length
    return pad[inner]
