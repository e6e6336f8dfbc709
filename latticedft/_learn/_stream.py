"""The training data of one :func:`latticedft.learn` call, held in memory or streamed chunk by chunk.

Streamed (the default), the data are read one chunk of sites at a time (:mod:`._source`): the exact solve
accumulates its least-squares system, iterative training its objective and gradient, and the diagnostics
their sums chunk by chunk, so memory does not grow with the data. With ``chunk_sites=0`` every field is
held and processed at once, as before streaming existed (the in-memory reference). Under a process group
(:mod:`._dist`) every process reads its share of the chunks.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Sequence
from dataclasses import replace
from typing import Any, overload

import torch

from .._action import del_residual, mixed_hessian, second_time_difference
from .._collective import merged_max, merged_min
from .._errors import InputError
from .._lattice import BoundaryKinds, LatticeField, gather_cells
from .._models import AbstractLagrangian, LinearLagrangian
from .._options import option
from .._stencil import Stencil
from . import _dist
from ._data import check_model_lattice, n_sites, site_sums
from ._gauge import gauge_named
from ._report import diagnose, symmetry_reports
from ._source import FieldSource, Piece, as_sources, pieces

__all__ = ["TrainingData", "by_field", "default_chunk_sites", "share_of", "training_data"]


def default_chunk_sites(model: AbstractLagrangian) -> int:
    """Sites per chunk when ``chunk_sites`` is not given (``model`` bound)."""
    if isinstance(model, LinearLagrangian):
        return max(1024, option("learn_linear_budget") // (model.n_terms * model.m))
    return int(option("learn_neural_chunk"))


class _Cells(Sequence[torch.Tensor]):
    """The training cells, piece by piece: ``(*cells, K, m)`` of each piece's own cells, read when asked."""

    def __init__(self, data: TrainingData, items: list[Piece], stencil: Stencil):
        self.data, self.items, self.stencil = data, items, stencil

    def __len__(self) -> int:
        return len(self.items)

    @overload
    def __getitem__(self, i: int) -> torch.Tensor: ...
    @overload
    def __getitem__(self, i: slice) -> list[torch.Tensor]: ...
    def __getitem__(self, i: int | slice) -> torch.Tensor | list[torch.Tensor]:
        if isinstance(i, slice):
            return [self[j] for j in range(*i.indices(len(self)))]
        f, skip = self.data.read(self.items[i])
        return gather_cells(f.values, self.stencil, f.boundary)[skip:]

    def __iter__(self) -> Iterator[torch.Tensor]:
        return (self[i] for i in range(len(self)))


class TrainingData:
    """The training fields of one call: sources, and after :meth:`bind` the chunks this process reads."""

    def __init__(self, sources: list[FieldSource], chunk_sites: int | None):
        self.sources = sources
        self.chunk_sites = chunk_sites
        self.chunks: list[list[Piece]] = []
        self.stencil: Stencil | None = None
        self.budget = 0
        self._fields: list[LatticeField] | None = None
        #: under a process group, only each source's home holds its values (the others' are stale): the
        #: fields in memory are then taken from the homes (a noise correction's refits)
        self.held_at_home = False

    # -- the two modes ------------------------------------------------------------------------------------
    @property
    def in_memory(self) -> bool:
        """All data at once (``chunk_sites=0`` in a single process): the reference path."""
        return self.chunk_sites == 0 and not _dist.is_parallel()

    @property
    def fields(self) -> list[LatticeField]:
        """Every field in memory (the in-memory mode's data; lazy ones are read once and kept)."""
        if self._fields is None:
            self._fields = [self._from_home(s) if self.held_at_home else s.load() for s in self.sources]
        return self._fields

    def _from_home(self, s: FieldSource) -> LatticeField:
        """Source ``s`` whole, its values broadcast by its home (every process calls it, in the same order)."""
        assert s.home is not None
        values = s.load().values if s.home == _dist.world()[0] else torch.empty((s.nt, *s.lattice.values.shape[1:]))
        return replace(s.lattice, values=_dist.broadcast(values.to(torch.float64), s.home))

    def __len__(self) -> int:
        return len(self.sources)

    # -- binding ------------------------------------------------------------------------------------------
    def bind(self, model: AbstractLagrangian) -> int:
        """Bind and prepare ``model`` on the data; returns the number of DEL equations (sites)."""
        for i, s in enumerate(self.sources):
            check_model_lattice(model, s.lattice, f"data[{i}]")
        f0 = self.sources[0].lattice
        model.bind(f0.ndim, f0.ncomp, f0.spacing, f0.components)
        self.stencil = model.stencil
        if self.in_memory:
            fields = self.fields
            cells = [gather_cells(f.values, model.stencil, f.boundary) for f in fields]
            model.prepare(cells)
            model.record_feature_range(cells)
            nsites = sum(n_sites(f, model) for f in fields)
        else:
            chunk = default_chunk_sites(model) if self.chunk_sites is None else self.chunk_sites
            self.budget = chunk
            if chunk == 0:  # several processes, whole fields: one field per chunk
                self.chunks = [[p] for c in pieces(self.sources, model.stencil, 0) for p in c]
            else:
                self.chunks = pieces(self.sources, model.stencil, chunk)
            # the input scaling and the training range of each stencil feature (min/max, merged chunk by chunk):
            # each process reads its share of the cells and the extremes are merged over the processes (a
            # model whose ``prepare`` does not merge them gets every cell in every process)
            w = int(model.stencil.width[0])
            share = self.my_chunks() if model.prepare_merges_processes else self.chunks
            own = [p for c in share for p in c if min(p.t1, self.sources[p.source].nt - w) > p.t0]
            model.prepare(_Cells(self, own, model.stencil))
            model.record_feature_range(_Cells(self, own, model.stencil))
            if model.prepare_merges_processes:
                _merge_range(model, bool(own))
            nsites = sum(s.n_sites(model.stencil) for s in self.sources)
        if nsites == 0:
            raise InputError("data: no interior site carries a DEL equation (lattices too small for the stencil)")
        return nsites

    # -- reading ------------------------------------------------------------------------------------------
    def my_chunks(self) -> list[list[Piece]]:
        """The chunks this process reads (every one in a single process)."""
        return share_of(self.chunks, self.sources)

    def read(self, piece: Piece) -> tuple[LatticeField, int]:
        """A piece's slab of values and how many of its leading cell slices belong to the piece before it."""
        assert self.stencil is not None, "bind first"
        return piece.read(self.sources, self.stencil)

    def is_single_chunk(self) -> bool:
        """One chunk holding whole fields, in one process: iterative training runs exactly as in memory."""
        return (
            not _dist.is_parallel()
            and len(self.chunks) == 1
            and all(p.t0 == 0 and p.t1 == self.sources[p.source].nt for p in self.chunks[0])
        )

    # -- diagnostics --------------------------------------------------------------------------------------
    def diagnose(self, model: AbstractLagrangian, gauge: str, symmetries: bool = False) -> dict[str, Any]:
        """:func:`latticedft.diagnose` of ``model`` on the training data: in memory, or summed chunk by chunk
        (and process by process) with the same definitions. ``symmetries`` tests the built-in symmetries over
        the training fields, which that test holds in memory."""
        if self.in_memory:
            return diagnose(model, self.fields, gauge=gauge, symmetries=symmetries)
        out: dict[str, Any] = dict(_diagnose_streamed(model, self, gauge))
        if symmetries:
            out["symmetries"] = symmetry_reports(model, self.fields, None)
        return out


def _merge_range(model: AbstractLagrangian, saw: bool) -> None:
    """The training range of ``model`` merged over the processes (``saw``: this process read cells)."""
    rng = model.trained_range() if saw else None
    shape = (model.n + 1, model.m)
    lo = merged_min(None if rng is None else rng[0], shape)
    hi = merged_max(None if rng is None else rng[1], shape)
    if lo is not None and hi is not None:
        model.set_feature_range(torch.stack([lo, hi]))


def share_of(chunks: list[list[Piece]], sources: list[FieldSource]) -> list[list[Piece]]:
    """The chunks of ``chunks`` this process reads: under a process group of ``N``, chunk ``i`` goes to rank
    ``i mod N``, or, when the sources have a ``home``, each chunk to its sources' home; every chunk in a
    single process."""
    rank, size = _dist.world()
    if size == 1:
        return chunks
    if any(s.home is not None for s in sources):
        return [c for c in chunks if sources[c[0].source].home == rank]
    return chunks[rank::size]


def by_field(sources: list[FieldSource]) -> list[FieldSource]:
    """``sources`` with source ``i`` at home in rank ``i mod N`` of a process group of ``N``."""
    size = _dist.world()[1]
    return [replace(s, home=i % size) for i, s in enumerate(sources)]


def training_data(data: Any, boundary: BoundaryKinds | None, chunk_sites: int | None) -> TrainingData:
    """The training data of :func:`latticedft.learn`: fields (in memory or lazy) or paths of field files;
    under a process group with ``learn_share="fields"`` (:func:`latticedft.set_options`), field ``i`` is read
    by rank ``i mod N`` alone."""
    if chunk_sites is not None and (
        isinstance(chunk_sites, bool) or not isinstance(chunk_sites, int) or chunk_sites < 0
    ):
        raise InputError.at("chunk_sites", f"expected an integer >= 0 or None, got {chunk_sites!r}")
    sources = as_sources(data, boundary)
    if _dist.is_parallel() and option("learn_share") == "fields":
        sources = by_field(sources)
    return TrainingData(sources, chunk_sites)


def _owned_cells(values: torch.Tensor, f: LatticeField, stencil: Stencil, skip: int) -> torch.Tensor:
    """Per-cell values ``(ncells, ...)`` flattened in cell order, without the first ``skip`` time slices."""
    if skip == 0:
        return values
    per_slice = values.shape[0] // (f.shape[0] - int(stencil.width[0]))
    return values[skip * per_slice :]


def _diagnose_streamed(model: AbstractLagrangian, data: TrainingData, gauge: str) -> dict[str, float]:
    """The figures of :func:`latticedft.diagnose` from sums over chunks (see there for their meaning).

    The kinetic scale ``rms(prod(h) mbar d2psi)`` needs the mean Hessian of all the data; it is summed as the
    second moments ``S = sum d2psi d2psi^T``, with ``sum |P mbar d2psi|^2 = P^2 tr(mbar^T mbar S)``.
    """
    fix = gauge_named(gauge)
    model._require_bound()
    st = model.stencil
    h0, m = model.spacing[0], model.m
    pair = (st.anchor, st.forward)
    sq = torch.zeros((), dtype=torch.float64)
    msum = torch.zeros(m, m, dtype=torch.float64)
    moment = torch.zeros(m, m, dtype=torch.float64)
    counts = torch.zeros(2, dtype=torch.float64)  # sites, cells
    smin = torch.full((), math.inf, dtype=torch.float64)
    cmax = torch.zeros((), dtype=torch.float64)
    smax = torch.zeros((), dtype=torch.float64)
    for chunk in data.my_chunks():
        for piece in chunk:
            f, skip = data.read(piece)
            closed = model.fast_derivatives(gather_cells(f.values, st, f.boundary), [pair])
            if closed is not None:  # closed forms (as serving uses them): the gradient and M in one call
                el = site_sums(model, f, closed[0])
                mh = closed[1][pair].reshape(-1, m, m)
            else:
                el = del_residual(model, f)
                mh = mixed_hessian(model, f)
            sq += (el**2).sum()
            counts[0] += el[..., 0].numel()
            mh = _owned_cells(mh, f, st, skip)
            msum += mh.sum(0)
            counts[1] += mh.shape[0]
            if mh.shape[0]:
                sv = torch.linalg.svdvals(h0**2 * mh)
                smin = torch.minimum(smin, sv[:, -1].min())
                smax = torch.maximum(smax, sv[:, 0].max())
                ok = sv[:, -1] > 0
                if ok.any():
                    cmax = torch.maximum(cmax, (sv[ok, 0] / sv[ok, -1]).max())
            d2 = second_time_difference(f, st).reshape(-1, m)
            moment += d2.T @ d2
    sq, msum, moment, counts = (_dist.all_sum(t) for t in (sq, msum, moment, counts))
    smin, cmax, smax = _dist.all_min(smin), _dist.all_max(cmax), _dist.all_max(smax)
    mbar = msum / counts[1]
    gres = fix.residual(mbar, h0)
    smin_f = float(smin)
    cond = float(cmax) if smin_f > 0 else math.inf
    nsites = max(int(counts[0]), 1)
    loss = float(sq) / nsites
    p = math.prod(model.spacing)
    scale = math.sqrt(max(float(p**2 * torch.trace(mbar.T @ mbar @ moment)), 0.0) / nsites)
    rel = math.sqrt(loss) / scale if scale > 0 else math.inf
    return {
        "loss": loss,
        "rel_res": rel,
        "gauge_residual": gres,
        "hessian_min_sv": smin_f,
        "hessian_cond": cond,
        "hessian_max_sv": float(smax),
    }
