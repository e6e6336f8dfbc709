"""Boundary kinds of the lattice axes: the one owner of every rule that depends on how an axis ends.

Each lattice axis has a kind. The time axis is ``"open"`` (served slice by
slice, nothing wraps); a spatial axis is one of :func:`boundary_kinds`:

``"dirichlet"`` (the default)
    The axis has edges. A cell lies wholly inside the lattice, so axis ``k``
    holds ``N_k - w_k`` cells (``w_k`` the stencil's width along it) and the
    sites within ``w_k`` of an edge carry no DEL equation; their values are
    data, given on every slice served (the Dirichlet strips).
``"periodic"``
    The axis wraps (index ``N_k`` is index 0): it holds ``N_k`` cells and
    every site carries an equation. A field file marks such an axis with the
    coordinate attribute ``periodic = "true"``.

A kind is a :class:`BoundaryKind`: its index rules along one axis (how many
cells, which stored site a lattice index lands on, which sites are interior)
and the operations built on them (the stencil points of every cell for
:func:`latticedft._lattice.gather_cells`, a shifted view for the reference
leapfrog scheme). Everything else -- the engine's cells and interior sites,
the serving index maps, the Dirichlet-strips check, the ``boundary``
argument and ``case.toml`` key, the leapfrog scheme -- asks this module.

A new kind is one subclass of :class:`BoundaryKind` registered in
:data:`KINDS`: the generic :meth:`BoundaryKind.take` and
:meth:`BoundaryKind.shifted` follow from its :meth:`~BoundaryKind.cells`,
:meth:`~BoundaryKind.sites` and :meth:`~BoundaryKind.interior`, and every
vocabulary (the ``boundary`` argument, ``case.toml``, the messages) is read
from :data:`KINDS` when it is used, never copied.

>>> parse_boundary({"x": "periodic"}, ("t", "y", "x"), "init")
('open', 'dirichlet', 'periodic')
>>> parse_boundary("wrap", ("t", "x"), "init")
Traceback (most recent call last):
...
latticedft._errors.InputError: boundary: axis 'x' has kind 'wrap'; expected one of ['dirichlet', 'periodic']
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from ._errors import InputError

__all__ = [
    "BoundaryKind",
    "KINDS",
    "boundary_kinds",
    "DEFAULT_KIND",
    "TIME_KIND",
    "BoundaryKinds",
    "kind",
    "spatial_kind",
    "axis_kinds",
    "kinds_text",
    "parse_boundary",
    "lattice_boundary",
    "missing_edges",
]

#: The ``boundary`` argument: one kind for every spatial axis, or a dict axis -> kind (others Dirichlet).
BoundaryKinds = str | dict[str, str]


class BoundaryKind:
    """How one lattice axis ends: its index rules and what follows from them.

    Attributes
    ----------
    name
        The kind's name (``"dirichlet"``, ``"periodic"``, ``"open"``).
    title
        Its name in messages (``"Dirichlet"``).
    wraps
        The axis closes on itself (its coordinate is marked ``periodic``).
    given_edges
        The sites that carry no equation hold data on every slice (the
        Dirichlet strips): a served field needs them on all its slices.
    selectable
        A user may choose it for a spatial axis (``boundary=``, ``case.toml``).
    """

    name: str = ""
    title: str = ""
    wraps: bool = False
    given_edges: bool = False
    selectable: bool = True

    def __repr__(self) -> str:
        return f"<boundary kind {self.name!r}>"

    # -- the index rules (what a new kind defines) --------------------------------------------------------
    def cells(self, n: int, width: int) -> int:
        """Number of cells along an axis of ``n`` sites for a stencil ``width`` wide along it."""
        raise NotImplementedError

    def sites(self, index: np.ndarray, n: int) -> np.ndarray:
        """The stored site (``0 .. n-1``) that each lattice ``index`` of a cell's point lands on."""
        raise NotImplementedError

    def interior(self, n: int, width: int) -> slice:
        """The sites that carry a DEL equation (every cell ``y - s_a`` exists)."""
        raise NotImplementedError

    # -- generic operations built on the rules (kinds may give faster equivalents) ---------------------------
    def take(self, v: Any, dim: int, start: int, n: int, width: int) -> Any:
        """Along tensor dim ``dim`` of ``v`` (``n`` sites): the point at offset ``start`` of every cell."""
        import torch

        idx = self.sites(np.arange(self.cells(n, width)) + start, n)
        return v.index_select(dim, torch.from_numpy(np.ascontiguousarray(idx, dtype=np.int64)))

    def shifted(self, u: np.ndarray, axis: int, shift: int, width: int) -> np.ndarray:
        """``u`` at index ``i + shift`` along ``axis`` for every interior site ``i`` along it (other axes whole)."""
        n = u.shape[axis]
        idx = self.sites(np.arange(n)[self.interior(n, width)] + shift, n)
        return np.take(u, idx, axis=axis)


class _Edged(BoundaryKind):
    """An axis with two edges: cells inside the lattice, the ``width`` sites at each edge carry no equation."""

    def __init__(self, name: str, title: str, *, given_edges: bool, selectable: bool):
        self.name, self.title, self.given_edges, self.selectable = name, title, given_edges, selectable

    def cells(self, n: int, width: int) -> int:
        return n - width

    def sites(self, index: np.ndarray, n: int) -> np.ndarray:
        return index

    def interior(self, n: int, width: int) -> slice:
        return slice(width, n - width)

    def take(self, v: Any, dim: int, start: int, n: int, width: int) -> Any:
        return v[(slice(None),) * dim + (slice(int(start), int(start + n - width)),)]

    def shifted(self, u: np.ndarray, axis: int, shift: int, width: int) -> np.ndarray:
        n = u.shape[axis]
        index = [slice(None)] * u.ndim
        index[axis] = slice(width + shift, n - width + shift)
        return u[tuple(index)]


class _Periodic(BoundaryKind):
    """An axis that wraps: index ``n`` is index 0; ``n`` cells, every site interior."""

    name, title, wraps = "periodic", "periodic", True

    def cells(self, n: int, width: int) -> int:
        return n

    def sites(self, index: np.ndarray, n: int) -> np.ndarray:
        return index % n

    def interior(self, n: int, width: int) -> slice:
        return slice(None)

    def take(self, v: Any, dim: int, start: int, n: int, width: int) -> Any:
        return v.roll(shifts=-int(start), dims=dim) if start else v

    def shifted(self, u: np.ndarray, axis: int, shift: int, width: int) -> np.ndarray:
        return np.roll(u, -shift, axis=axis)


#: Every kind by name: the spatial kinds a user may choose, and ``open`` for the time axis.
KINDS: dict[str, BoundaryKind] = {
    "dirichlet": _Edged("dirichlet", "Dirichlet", given_edges=True, selectable=True),
    "periodic": _Periodic(),
    "open": _Edged("open", "open", given_edges=False, selectable=False),
}


def boundary_kinds() -> tuple[str, ...]:
    """The kinds a spatial axis may have (the vocabulary of ``boundary=`` and of ``case.toml``), read from
    :data:`KINDS` now.

    >>> boundary_kinds()
    ('dirichlet', 'periodic')
    """
    return tuple(name for name, k in KINDS.items() if k.selectable)


#: The kind of a spatial axis that neither the ``boundary`` argument nor the file makes periodic.
DEFAULT_KIND = "dirichlet"
#: The kind of the time axis.
TIME_KIND = "open"


def kinds_text(sep: str = " or ") -> str:
    """The selectable kinds for a message: ``'dirichlet' or 'periodic'``."""
    return sep.join(repr(k) for k in boundary_kinds())


def kind(entry: str | bool | BoundaryKind) -> BoundaryKind:
    """The kind of one axis from its name, a :class:`BoundaryKind`, or a periodic flag (True: periodic,
    False: the default kind)."""
    if isinstance(entry, BoundaryKind):
        return entry
    if isinstance(entry, (bool, np.bool_)):
        return KINDS["periodic" if entry else DEFAULT_KIND]
    try:
        return KINDS[entry]
    except (KeyError, TypeError):
        raise InputError.at("boundary", f"expected {kinds_text()}, got {entry!r}") from None


def spatial_kind(name: Any, key: str = "boundary") -> BoundaryKind:
    """The selectable kind named ``name`` (one-line :class:`InputError` about ``key`` otherwise)."""
    if not isinstance(name, str) or name not in boundary_kinds():
        raise InputError.at(key, f"expected {kinds_text()}, got {name!r}")
    return KINDS[name]


def axis_kinds(entries: Sequence[str | bool | BoundaryKind]) -> tuple[BoundaryKind, ...]:
    """:func:`kind` of every axis."""
    return tuple(kind(e) for e in entries)


# -- the boundary argument -----------------------------------------------------------------------------------
def parse_boundary(boundary: BoundaryKinds, dims: Sequence[str], source: str) -> tuple[str, ...]:
    """Kind names of every lattice axis (time first, ``open``) from a ``boundary`` argument.

    ``boundary`` is one kind for every spatial axis or a dict axis -> kind
    (unnamed axes take :data:`DEFAULT_KIND`). Errors are one-line
    :class:`InputError` about the key ``boundary``.
    """
    spatial = tuple(dims[1:])
    if isinstance(boundary, str):
        names = {d: boundary for d in spatial}
    elif isinstance(boundary, dict):
        unknown = [k for k in boundary if k not in spatial]
        if unknown:
            raise InputError.at(
                "boundary", f"unknown axis {unknown[0]!r}; the spatial axes of {source} are {list(spatial)}"
            )
        names = {d: boundary.get(d, DEFAULT_KIND) for d in spatial}
    else:
        raise InputError.at("boundary", f"expected {kinds_text(', ')} or a table axis -> kind, got {boundary!r}")
    for d, k in names.items():
        if k not in boundary_kinds():
            raise InputError.at("boundary", f"axis {d!r} has kind {k!r}; expected one of {list(boundary_kinds())}")
    return (TIME_KIND, *(names[d] for d in spatial))


def lattice_boundary(
    periodic_attrs: Sequence[bool | None], boundary: BoundaryKinds | None, dims: Sequence[str], source: str
) -> tuple[str, ...]:
    """Kind names of every lattice axis of a field: from ``boundary`` when given, else from the coordinates'
    ``periodic`` attributes (``periodic_attrs``, None where absent; periodic or :data:`DEFAULT_KIND`)."""
    if boundary is not None:
        return parse_boundary(boundary, dims, source)
    if periodic_attrs and periodic_attrs[0]:
        raise InputError(f"{source}: the time axis {dims[0]!r} cannot be periodic")
    return (TIME_KIND, *("periodic" if p else DEFAULT_KIND for p in periodic_attrs[1:]))


# -- serving -------------------------------------------------------------------------------------------------
def missing_edges(
    boundary: Sequence[str | bool | BoundaryKind], dims: Sequence[str], given: int, steps: int
) -> tuple[str, BoundaryKind] | None:
    """The first spatial axis (and its kind) whose edge values are data that a field of ``given`` slices lacks
    for ``steps`` served slices (the Dirichlet strips), or None when nothing is missing."""
    if given >= steps:
        return None
    for d, k in zip(dims[1:], axis_kinds(boundary)[1:]):
        if k.given_edges:
            return d, k
    return None
