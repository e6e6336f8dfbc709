"""Stencils: which lattice sites one cell of ``L_d`` sees (docs/mathematics.md, section 1)."""

from __future__ import annotations

import itertools
from collections.abc import Sequence

import numpy as np
import numpy.typing as npt

from ._errors import InputError

__all__ = ["Stencil"]


class Stencil:
    """Integer offsets ``s_0 ... s_{K-1}`` in ``Z^n`` of the sites one cell sees.

    The cell anchored at lattice site ``x`` evaluates
    ``L_d(psi[x + s_0], ..., psi[x + s_{K-1}])``. The stencil must contain the
    anchor ``0`` and the time step ``e_0`` (the gauge and the slice solver
    need the mixed Hessian between them) and span exactly two time slices
    (offsets along axis 0 are 0 or 1), so that serving fills one slice at a
    time.

    >>> Stencil.first_order(2).offsets
    ((0, 0), (1, 0), (0, 1))
    >>> Stencil.full_cell(2).size
    4
    """

    def __init__(self, offsets: Sequence[Sequence[int]]):
        arr = np.asarray(offsets)
        if arr.ndim != 2 or arr.shape[0] < 2 or arr.shape[1] < 1:
            raise InputError(
                f"stencil: expected a list of at least two offsets of equal length n >= 1, got {offsets!r}"
            )
        if not np.issubdtype(arr.dtype, np.integer):
            raise InputError(f"stencil: offsets must be integers, got {offsets!r}")
        tuples = [tuple(int(v) for v in row) for row in arr]
        if len(set(tuples)) != len(tuples):
            raise InputError(f"stencil: offsets must be distinct, got {tuples}")
        n = arr.shape[1]
        zero = (0,) * n
        e0 = (1,) + (0,) * (n - 1)
        if zero not in tuples or e0 not in tuples:
            raise InputError(f"stencil: must contain the anchor {zero} and the time step {e0}, got {tuples}")
        if arr[:, 0].min() != 0 or arr[:, 0].max() != 1:
            raise InputError(f"stencil: time offsets (first entries) must be 0 or 1, got {tuples}")
        self.offsets: tuple[tuple[int, ...], ...] = tuple(tuples)
        self._arr: npt.NDArray[np.int64] = arr.astype(np.int64)

    # -- constructors -----------------------------------------------------------------
    @classmethod
    def first_order(cls, n: int) -> Stencil:
        """The default stencil ``s_0 = 0, s_{k+1} = e_k`` (``K = n + 1``)."""
        eye = np.eye(n, dtype=int)
        return cls([[0] * n] + eye.tolist())

    @classmethod
    def full_cell(cls, n: int) -> Stencil:
        """All ``2^n`` corners of the unit cell."""
        return cls(list(itertools.product((0, 1), repeat=n)))

    # -- properties -------------------------------------------------------------------
    @property
    def array(self) -> npt.NDArray[np.int64]:
        return self._arr.copy()

    @property
    def size(self) -> int:
        """Number of points ``K``."""
        return len(self.offsets)

    @property
    def ndim(self) -> int:
        """Lattice dimension ``n``."""
        return int(self._arr.shape[1])

    @property
    def lo(self) -> npt.NDArray[np.int64]:
        lo: npt.NDArray[np.int64] = self._arr.min(axis=0)
        return lo

    @property
    def hi(self) -> npt.NDArray[np.int64]:
        hi: npt.NDArray[np.int64] = self._arr.max(axis=0)
        return hi

    @property
    def width(self) -> npt.NDArray[np.int64]:
        """Extent ``max - min`` of the offsets along each axis."""
        return self.hi - self.lo

    def index(self, offset: Sequence[int]) -> int:
        """Position of ``offset`` in the stencil."""
        return self.offsets.index(tuple(int(v) for v in offset))

    @property
    def anchor(self) -> int:
        return self.index((0,) * self.ndim)

    @property
    def forward(self) -> int:
        """Position of the time step ``e_0``."""
        return self.index((1,) + (0,) * (self.ndim - 1))

    def is_first_order(self) -> bool:
        return self == Stencil.first_order(self.ndim)

    def to_list(self) -> list[list[int]]:
        return [list(o) for o in self.offsets]

    def __eq__(self, other: object) -> bool:
        return isinstance(other, Stencil) and self.offsets == other.offsets

    def __hash__(self) -> int:
        return hash(self.offsets)

    def __repr__(self) -> str:
        return f"Stencil({[list(o) for o in self.offsets]})"
