"""The process grid of a split serve: slabs along the outer spatial axis, or pencils along the two outer ones.

A grid ``p1 x p2`` (``p1 * p2`` processes) splits the first spatial axis into ``p1`` slabs and, when
``p2 > 1``, the second into ``p2``; each process holds one rectangular :class:`Block` of the lattice (the
other axes whole) and a halo of the stencil's reach along each split axis. Process ``r`` holds the block at
``(r // p2, r % p2)``, so that slabs (``p2 = 1``) are the blocks of :func:`plan_slabs`, one a process in
rank order, as before pencils.

The choice (:func:`plan_grid`, ``grid = None``): among the grids whose every block is at least the halo
wide along each split axis, the one whose largest per-process halo (the sites a process holds beyond its
own block, corners included) is smallest; on a tie the one with more slabs along the first axis, so slabs
``N x 1`` win every tie. Slabs are therefore kept wherever they hold no more halo than any pencil grid, and
pencils serve where slabs cannot (more processes than planes of the outer axis, or slabs thinner than the
halo).

The halo exchange (:func:`exchange`) goes axis by axis: first along the first axis (the blocks' full extent
along the second), then along the second, the first axis's halo included, so that the corner sites arrive
from the diagonal neighbour by way of the first exchange.
"""

from __future__ import annotations

import math
from collections.abc import Hashable
from dataclasses import dataclass

import numpy as np
import torch
import torch.distributed as dist

from .._collective import group_device
from .._errors import InputError

__all__ = ["Block", "Slab", "assemble", "exchange", "grid_text", "plan_grid", "plan_slabs"]


@dataclass(frozen=True)
class Slab:
    """Planes ``lo .. hi - 1`` of a split axis (of ``n``), held with ``halo`` planes each side."""

    lo: int
    hi: int
    n: int
    halo: int
    periodic: bool

    @property
    def start(self) -> int:
        """The global plane of the first plane held (before wrapping, when periodic)."""
        return self.lo - self.halo if self.periodic else max(self.lo - self.halo, 0)

    @property
    def local(self) -> np.ndarray:
        """The global planes this process holds, in order (its halo included; wrapped when periodic)."""
        if self.periodic:
            return np.arange(self.lo - self.halo, self.hi + self.halo) % self.n
        return np.arange(max(self.lo - self.halo, 0), min(self.hi + self.halo, self.n))

    @property
    def own(self) -> slice:
        """The slab's own planes among :attr:`local`."""
        return slice(self.lo - self.start, self.hi - self.start)


def plan_slabs(n: int, processes: int, halo: int, periodic: bool, axis: str = "x") -> list[Slab]:
    """``processes`` slabs of the ``n`` planes of ``axis`` (as equal as can be); one-line InputErrors naming
    ``--workers`` when there are more processes than planes or a slab is thinner than the halo."""
    if processes > n:
        raise InputError.at(
            "--workers",
            f"{processes} processes for the {n} planes of the outer axis {axis!r}: at most {n} (one plane each)",
        )
    bounds = [n * r // processes for r in range(processes + 1)]
    thinnest = min(b - a for a, b in zip(bounds[:-1], bounds[1:]))
    if processes > 1 and thinnest < halo:
        raise InputError.at(
            "--workers",
            f"the halo of {halo} planes is wider than a slab of {thinnest} planes of {axis!r}; "
            f"use at most {n // halo} processes",
        )
    return [Slab(a, b, n, halo, periodic) for a, b in zip(bounds[:-1], bounds[1:])]


@dataclass(frozen=True)
class Block:
    """One process's block: its :class:`Slab` of each split axis (``axes``), at ``at`` in the ``grid``."""

    parts: tuple[Slab, ...]
    axes: tuple[str, ...]
    grid: tuple[int, ...]
    at: tuple[int, ...]

    @property
    def own(self) -> tuple[slice, ...]:
        """The block's own sites among those held, along the split axes (an index of the held array)."""
        return tuple(p.own for p in self.parts)

    @property
    def held(self) -> tuple[int, ...]:
        """The number of planes held along each split axis."""
        return tuple(len(p.local) for p in self.parts)

    def owned(self, dims: tuple[Hashable, ...]) -> dict[Hashable, slice]:
        """The block's own planes as an ``isel`` of an array whose spatial axes are ``dims[1:]``."""
        return {dims[1 + k]: slice(p.lo, p.hi) for k, p in enumerate(self.parts)}

    def take(self, a: np.ndarray, axis: int) -> np.ndarray:
        """The planes held of ``a``, whose split axes start at ``axis`` (global planes there)."""
        for k, p in enumerate(self.parts):
            a = np.take(a, p.local, axis=axis + k)
        return a

    def bounds(self) -> list[list[int]]:
        """``[lo, hi]`` of each split axis."""
        return [[p.lo, p.hi] for p in self.parts]


def _blocks(
    sizes: tuple[int, ...],
    grid: tuple[int, int],
    halos: tuple[int, ...],
    periodic: tuple[bool, ...],
    axes: tuple[str, ...],
) -> list[Block]:
    """The blocks of ``grid`` in rank order (one-line InputErrors naming ``--workers`` as :func:`plan_slabs`)."""
    split = 1 if grid[1] == 1 else 2
    per = [plan_slabs(sizes[k], grid[k], halos[k], periodic[k], axes[k]) for k in range(split)]
    if split == 1:
        return [Block((s,), axes[:1], grid[:1], (r,)) for r, s in enumerate(per[0])]
    return [Block((per[0][a], per[1][b]), axes[:2], grid, (a, b)) for a in range(grid[0]) for b in range(grid[1])]


def _halo_sites(blocks: list[Block], sizes: tuple[int, ...]) -> int:
    """The largest number of sites a process holds beyond its own block, on the plane of the (at most two)
    axes a grid may split (``sizes``: the axes' sizes; the other axes multiply every grid's alike)."""
    rest = math.prod(sizes[len(blocks[0].parts) : 2])
    return rest * max(math.prod(b.held) - math.prod(p.hi - p.lo for p in b.parts) for b in blocks)


def plan_grid(
    sizes: tuple[int, ...],
    processes: int,
    halos: tuple[int, ...],
    periodic: tuple[bool, ...],
    axes: tuple[str, ...],
    grid: tuple[int, int] | None = None,
) -> list[Block]:
    """The blocks of ``processes`` over the spatial axes ``axes`` (``sizes``, the stencil's reach ``halos``,
    ``periodic``): of ``grid`` when given, else of the grid chosen by the rule of the module's docstring.
    None fits: the slabs' one-line refusal naming ``--workers`` (with the pencils' when there are two axes)."""
    if grid is not None:
        if grid[0] * grid[1] != processes or (grid[1] > 1 and len(sizes) < 2):
            raise InputError.at("--workers", f"a grid {grid[0]} x {grid[1]} for {processes} processes over {axes}")
        return _blocks(sizes, grid, halos, periodic, axes)
    try:
        slabs = _blocks(sizes, (processes, 1), halos, periodic, axes)
    except InputError as exc:
        slabs, refusal = [], exc
    best, most = slabs, _halo_sites(slabs, sizes) if slabs else math.inf
    for p1 in range(processes - 1, 0, -1) if len(sizes) >= 2 else ():
        if processes % p1:
            continue
        try:
            blocks = _blocks(sizes, (p1, processes // p1), halos, periodic, axes)
        except InputError:
            continue
        if _halo_sites(blocks, sizes) < most:
            best, most = blocks, _halo_sites(blocks, sizes)
    if not best:
        two = f", nor into pencils over {axes[:2]}" if len(sizes) >= 2 else ""
        raise InputError.at("--workers", f"{refusal.problem}{two}")
    return best


def grid_text(blocks: list[Block]) -> str:
    """``slabs 4 over x`` or ``pencils 2 x 2 over (x, y)``."""
    grid = blocks[0].grid
    if len(grid) == 1:
        return f"slabs {grid[0]} over {blocks[0].axes[0]}"
    return f"pencils {grid[0]} x {grid[1]} over ({', '.join(blocks[0].axes)})"


def assemble(parts: list[np.ndarray], grid: tuple[int, ...], axis: int) -> np.ndarray:
    """The blocks ``parts`` (in rank order, their split axes from ``axis`` on) as one array."""
    if len(grid) == 1:
        return np.concatenate(parts, axis=axis)
    rows = [np.concatenate(parts[a * grid[1] : (a + 1) * grid[1]], axis=axis + 1) for a in range(grid[0])]
    return np.concatenate(rows, axis=axis)


def exchange(v: np.ndarray, block: Block, rank: int, size: int) -> None:
    """Send the block's edge planes of the slice ``v`` (``(nsite * m,)``) to its neighbours along each split
    axis in turn; receive theirs into its halo planes (corners by way of the first axis's exchange)."""
    planes = v.reshape(*block.held, -1)
    for k, part in enumerate(block.parts):
        if part.halo == 0:
            continue
        step = math.prod(block.grid[k + 1 :])
        n, at = block.grid[k], block.at[k]
        _exchange_axis(planes, k, part, n, at, rank, step)


def _exchange_axis(planes: np.ndarray, k: int, part: Slab, n: int, at: int, rank: int, step: int) -> None:
    """The halo exchange along split axis ``k`` (``n`` blocks along it, this one at ``at``; the neighbours'
    ranks ``step`` apart)."""
    w, own = part.halo, part.own

    def cut(s: slice) -> tuple[slice, ...]:
        return (slice(None),) * k + (s,)

    if n == 1:  # periodic in one process: its own edge planes
        if not part.periodic:
            return
        planes[cut(slice(own.start - w, own.start))] = planes[cut(slice(own.stop - w, own.stop))]
        planes[cut(slice(own.stop, own.stop + w))] = planes[cut(slice(own.start, own.start + w))]
        return
    left = rank + step * ((at - 1) % n - at) if (part.periodic or at > 0) else None
    right = rank + step * ((at + 1) % n - at) if (part.periodic or at < n - 1) else None
    dev = group_device()
    ops, got = [], []
    # tag 0: planes going left, tag 1: going right (two blocks, periodic: both neighbours are the same rank)
    for peer, send, recv, out_tag in (
        (left, slice(own.start, own.start + w), slice(own.start - w, own.start), 0),
        (right, slice(own.stop - w, own.stop), slice(own.stop, own.stop + w), 1),
    ):
        if peer is None:
            continue
        ops.append(dist.P2POp(dist.isend, torch.from_numpy(planes[cut(send)].copy()).to(dev), peer, tag=out_tag))
        buf = torch.empty(planes[cut(recv)].shape, dtype=torch.float64, device=dev)
        ops.append(dist.P2POp(dist.irecv, buf, peer, tag=1 - out_tag))
        got.append((recv, buf))
    for req in dist.batch_isend_irecv(ops):
        req.wait()
    for where, buf in got:
        planes[cut(where)] = buf.cpu().numpy()
