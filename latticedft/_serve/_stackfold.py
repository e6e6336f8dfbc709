"""Slice-Newton of a stacked ensemble of polynomials on the folded kernels: every member's cells evaluated by its
own :class:`._folded.FoldedSlices`, on its own components, as when it is served alone.

A stacked ensemble (``latticedft._models._ensemble._Stacked``) puts its ``n_members`` models side by side on the
components (member ``k`` sees components ``k w .. (k + 1) w - 1``) and their DEL equations never couple. Where
every member is a polynomial that the folded kernels serve (:func:`._folded.folded_slices`), the stacked slice is
evaluated member by member: each member's two slices cut from the stacked field (a contiguous copy of its own
columns), its gradients, residual and Hessian blocks computed by its own folded kernels on the member's slice
system (``_SliceSystem.member_system``), then put side by side. Each member's residual, gradients and blocks are
then what its own ``FoldedSlices`` computes alone, to the bit (the kernels read the same values; the copies and
the interleaving move values without arithmetic), and :func:`._members.newton_members` judges, factorises and
solves each member on those (its blocks are handed on per member: :class:`MemberBlocks`). A stack that cannot
fold (networks, feature models, ``compiled_kernels=False``) keeps the torch evaluation (``CellDerivatives``).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from .._models._ensemble import _block_diagonal
from ._folded import FoldedCells, FoldedSlices, folded_slices
from ._slices import Blocks, _SliceSystem

__all__ = ["MemberBlocks", "StackedCells", "StackedFolded", "stacked_folded"]


class MemberBlocks(Blocks):
    """The Hessian blocks of a stacked ensemble's slice held per member: ``members[k]`` is member ``k``'s own
    :class:`._slices.Blocks` (``(cells, w, w)`` per pair, its columns and its summed diagonal with it), as its
    folded kernels give them alone. A pair read as a whole (``blocks[pair]``) is the stacked block-diagonal
    ``(cells, members w, members w)`` tensor, built on first read; the member-wise readers
    (``_members._assess``, ``_SliceSystem.member_singular_values``, ``_solvers.factor_members``) take
    ``members`` instead."""

    def __init__(self, members: list[dict[tuple[int, int], torch.Tensor]]):
        super().__init__()
        self.members = members

    def __missing__(self, key: tuple[int, int]) -> torch.Tensor:
        full = _block_diagonal(torch.stack([b[key] for b in self.members]))
        self[key] = full
        return full


class StackedCells:
    """The cells anchored on one slice of a stacked ensemble: each member's :class:`._folded.FoldedCells`
    (``parts``) and the members' gradients side by side (``grad``: ``(cells, K members w)``, the stacked
    components' order)."""

    def __init__(self, parts: list[FoldedCells], k: int):
        self.parts = parts
        self.grad = _side_by_side([p.grad for p in parts], k)

    def blocks(self, pairs: list[tuple[int, int]]) -> MemberBlocks:
        """Each member's Hessian blocks of ``pairs`` (:meth:`._folded.FoldedCells.blocks`), held per member."""
        return MemberBlocks([p.blocks(pairs) for p in self.parts])


def _side_by_side(parts: list[np.ndarray], k: int) -> np.ndarray:
    """``(cells, K w)`` per member -> ``(cells, K members w)``: at each stencil point the members' components
    one after the other."""
    ncell = parts[0].shape[0]
    return np.stack([p.reshape(ncell, k, -1) for p in parts], axis=2).reshape(ncell, -1)


class StackedFolded:
    """The folded kernels of a stacked ensemble's served field: one :class:`._folded.FoldedSlices` per member
    (``parts``, on the member's slice system), each evaluating its own member's columns of the stacked slices.
    Offers what slice-Newton reads of ``FoldedSlices``: :meth:`predict`, :meth:`grad`, :meth:`evaluate`,
    :meth:`excess`."""

    def __init__(self, parts: list[FoldedSlices], sys: _SliceSystem):
        self.parts, self.sys = parts, sys
        self.nm, self.w, self.k = len(parts), sys.m // len(parts), len(sys.st.offsets)

    def _own(self, flat: torch.Tensor, i: int) -> list[torch.Tensor]:
        """Each member's slices ``i`` and ``i + 1`` of the stacked ``flat``, ``(2, sites, w)`` contiguous."""
        two = flat[i : i + 2].numpy().reshape(2, -1, self.nm, self.w)
        return [torch.from_numpy(np.ascontiguousarray(two[:, :, q])) for q in range(self.nm)]

    def _split(self, g: Any) -> list[np.ndarray]:
        """Stacked gradients ``(cells, K members w)`` (this class's, or ``CellDerivatives``') per member,
        ``(cells, K w)`` contiguous."""
        arr = g.numpy() if isinstance(g, torch.Tensor) else np.asarray(g)
        per = arr.reshape(-1, self.k, self.nm, self.w)
        return [np.ascontiguousarray(per[:, :, q]).reshape(per.shape[0], -1) for q in range(self.nm)]

    def predict(self, flat: torch.Tensor, i: int, older: torch.Tensor | None) -> tuple[float, float, float]:
        """Slice-Newton's predictor on the unknown sites of slice ``i + 1`` (elementwise: each member's
        components as alone), by the compiled pass of :meth:`._folded.FoldedSlices.predict` over the stacked
        slices; the sizes it returns are the whole stack's (a stacked run measures each member's own)."""
        return self.parts[0].predict(flat, i, older)

    def grad(self, flat: torch.Tensor, i: int) -> np.ndarray:
        """The members' :meth:`._folded.FoldedSlices.grad` of the cells anchored on slice ``i``, side by side."""
        own = self._own(flat, i)
        return _side_by_side([p.grad(o, 0) for p, o in zip(self.parts, own, strict=True)], self.k)

    def evaluate(
        self, flat: torch.Tensor, vol: float, i: int, g_prev: Any, blocks: bool = False
    ) -> tuple[StackedCells, np.ndarray]:
        """Each member's :meth:`._folded.FoldedSlices.evaluate` on its own slices and gradients: the cells
        anchored on slice ``i`` (:class:`StackedCells`) and the stacked residual on the equation rows (the
        members' residuals side by side at each row's site)."""
        own = self._own(flat, i)
        prev = self._split(g_prev)
        found = [p.evaluate(o, vol, 0, g, blocks) for p, o, g in zip(self.parts, own, prev, strict=True)]
        r = np.stack([res.reshape(-1, self.w) for _, res in found], axis=1).reshape(-1)
        return StackedCells([ev for ev, _ in found], self.k), r

    def excess(self, model: Any, values: torch.Tensor) -> np.ndarray | None:
        """No compiled training-range pass for the stack (its result's range is member 0's, assessed apart)."""
        return None


def stacked_folded(model: Any, sys: _SliceSystem, flat: torch.Tensor) -> StackedFolded | None:
    """The folded kernels of a stacked ensemble on ``sys`` (:class:`StackedFolded`), or ``None``: where
    ``model`` stacks several members and :func:`._folded.folded_slices` serves every one of them on the
    member's slice system (polynomials whose coefficients fold, on the CPU, the ``compiled_kernels`` option
    on), with the stacked values on the CPU in double precision."""
    nm = model.n_members
    if nm < 2 or sys.members != nm or sys.m % nm:
        return None
    if flat.dtype != torch.float64 or flat.device.type != "cpu" or not flat.is_contiguous():
        return None
    one = sys.member_system
    probe = torch.empty((0, sys.nsite, one.m), dtype=torch.float64)  # folded_slices reads its dtype and place
    parts = []
    for q in range(nm):
        part = folded_slices(model.member(q), one, probe)
        if part is None:
            return None
        parts.append(part)
    return StackedFolded(parts, sys)
