"""One time slice as a system of equations: the index maps of its equations and unknowns, its residual and its
factorised Jacobian, shared by the slice solvers (affine recurrence, slice-Newton, site-by-site sweep)."""

from __future__ import annotations

import copy
import functools
import math
from typing import Any

import numpy as np
import scipy.linalg
import scipy.sparse
import scipy.sparse.linalg
import torch

from .._boundary import axis_kinds
from .._kernel_krylov import krylov_kernels
from .._lattice import LatticeField, interior_slices
from .._models import AbstractLagrangian
from ._band import band_factor

#: A slice whose mixed Hessian has a smallest singular value below ``SINGULAR_RTOL`` times its scale (the
#: largest singular value met on the served field so far) is singular: serving stops there with a
#: ``ServeError`` instead of accepting whatever Newton's method makes of it.
SINGULAR_RTOL = 1e-10

#: Whether a fresh Jacobian's diagonal sum, its site-wise extremes (one component), its CSR values from the
#: evaluated columns and the largest sizes slice-Newton reads (:func:`abs_max`: the step's scale, the largest
#: off-diagonal entry) run as compiled loops (``latticedft._kernel_krylov``: the same values to the bit;
#: ``False``: torch's ``index_add_`` and reductions, numpy's gather).
COMPILED_ASSEMBLY = True


class Blocks(dict):
    """Hessian blocks ``(cells, m, m)`` per pair that keep the slice Jacobian's diagonal once
    :meth:`_SliceSystem.diagonal` has summed it (with the slice system it is of): the singular values of a
    fresh Jacobian and its factorisation read the same sum."""

    diag: tuple[Any, torch.Tensor] | None = None
    #: ``(columns, first)``: the blocks are read from these ``(cells, ...)`` columns, pair ``q``'s ``m x m`` entries
    #: at ``first + q m m`` on (the folded kernels' evaluation), for :meth:`_SliceSystem.csr`; ``None``: not
    columns: tuple[np.ndarray, int] | None = None


class _SliceSystem:
    """Index maps of one slice's equations and unknowns, built once per lattice."""

    def __init__(self, model: AbstractLagrangian, f: LatticeField):
        st = model.stencil
        self.st = st
        self.m = f.ncomp
        #: Models side by side on the components (a stacked ensemble's members, ``m // members`` components each):
        #: their conditioning is judged one by one (:meth:`member_singular_values`).
        self.members = model.n_members
        spatial = f.shape[1:]
        self.spatial = spatial
        self.kinds = axis_kinds(f.boundary)[1:]  # the boundary kind of each spatial axis
        wraps = any(k.wraps for k in self.kinds)
        self.nsite = int(np.prod(spatial))
        inner = interior_slices(f.shape, st, f.boundary)[1:]
        mask = np.zeros(spatial, dtype=bool)
        mask[inner] = True
        self.interior = mask.reshape(-1)
        self.index = -np.ones(self.nsite, dtype=np.int64)  # site -> equation row / unknown column
        self.index[self.interior] = np.arange(int(self.interior.sum()))
        self.n = int(self.interior.sum())
        # cells anchored on one slice: shape of the cell grid along the spatial axes
        lo, width = st.lo, st.width
        cshape = [kind.cells(nk, int(width[k + 1])) for k, (nk, kind) in enumerate(zip(spatial, self.kinds))]
        self.cshape = tuple(cshape)
        self.site_of: list[np.ndarray] = []  # per stencil point: flat site index of that point for every cell
        for off in st.offsets:  # row-major, the sites of each axis found along that axis alone, then broadcast
            site = np.zeros((1,) * len(cshape), dtype=np.int64)
            for k, (ck, kind) in enumerate(zip(cshape, self.kinds)):
                v = np.asarray(kind.sites(np.arange(ck) + off[k + 1] - lo[k + 1], spatial[k]), dtype=np.int64)
                site = site * spatial[k] + v.reshape([-1 if j == k else 1 for j in range(len(cshape))])
            self.site_of.append(site.reshape(-1) if cshape else np.zeros(1, dtype=np.int64))
        self.now = [a for a, o in enumerate(st.offsets) if o[0] == 0]
        self.nxt = [a for a, o in enumerate(st.offsets) if o[0] == 1]
        self.pairs = [(a, b) for a in self.now for b in self.nxt]
        self.wraps = wraps
        self.banded = len(spatial) == 1 and not wraps
        self.kept: dict[str, Any] = {}  # what a solve derives from these maps and keeps with them (per lattice)
        # the Jacobian's structure (jac, lower, upper, triangular, diag_pairs, diag_entries) is built on first use:
        # the compiled slice Newton of a block-diagonal L_d never needs it

    @functools.cached_property
    def jac(self) -> dict[tuple[int, int], tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """Jacobian structure: per pair, the cells, equation rows (sites on slice i) and unknown columns (sites
        on slice i+1) of its entries."""
        jac = {}
        for a, b in self.pairs:
            r = self.index[self.site_of[a]]
            c = self.index[self.site_of[b]]
            keep = (r >= 0) & (c >= 0)
            jac[(a, b)] = (np.nonzero(keep)[0], r[keep], c[keep])
        return jac

    @functools.cached_property
    def _rows_cols(self) -> tuple[np.ndarray, np.ndarray]:
        rows = np.concatenate([r for _, r, _ in self.jac.values()]) if self.jac else np.zeros(0, np.int64)
        cols = np.concatenate([c for _, _, c in self.jac.values()]) if self.jac else np.zeros(0, np.int64)
        return rows, cols

    @property
    def lower(self) -> int:
        """The Jacobian's lower bandwidth."""
        rows, cols = self._rows_cols
        return int(max(0, (rows - cols).max() if rows.size else 0)) * self.m + self.m - 1

    @property
    def upper(self) -> int:
        """The Jacobian's upper bandwidth."""
        rows, cols = self._rows_cols
        return int(max(0, (cols - rows).max() if rows.size else 0)) * self.m + self.m - 1

    @functools.cached_property
    def triangular(self) -> bool:
        """Whether the Jacobian is block lower-triangular (no wrap)."""
        rows, cols = self._rows_cols
        return bool(rows.size == 0 or (cols <= rows).all()) and not self.wraps

    @functools.cached_property
    def diag_pairs(self) -> list[tuple[int, int]]:
        """The pairs with an entry on the Jacobian's diagonal blocks."""
        return [(a, b) for (a, b), (_, r, c) in self.jac.items() if np.any(r == c)]

    @functools.cached_property
    def offdiag_cells(self) -> list[tuple[tuple[int, int], torch.Tensor | None]]:
        """Per pair with entries off the Jacobian's diagonal blocks, the cells that hold them (``None``: every cell
        of the pair's blocks, in order: no gather)."""
        out: list[tuple[tuple[int, int], torch.Tensor | None]] = []
        for key, (at, r, c) in self.jac.items():
            cells = at[r != c]
            if cells.size:
                every = cells.size == self.site_of[0].size and bool(np.array_equal(cells, np.arange(cells.size)))
                out.append((key, None if every else torch.from_numpy(cells)))
        return out

    @functools.cached_property
    def diag_entries(self) -> list[tuple[tuple[int, int], torch.Tensor, torch.Tensor]]:
        """The entries of the Jacobian's diagonal m x m blocks (an equation's own site on the next slice): per
        unknown site the mixed Hessian summed over the cells that hold it."""
        return [
            (key, torch.from_numpy(cells[r == c]), torch.from_numpy(r[r == c]))
            for key, (cells, r, c) in self.jac.items()
            if np.any(r == c)
        ]

    @functools.cached_property
    def member_system(self) -> _SliceSystem:
        """The slice system of one of the :attr:`members` models side by side (``m // members`` components, the
        same lattice; itself for one model): each stacked member's own Jacobian is factorised and solved on it,
        as when the member is served alone (``_solvers.factor_members``)."""
        if self.members == 1:
            return self
        one = copy.copy(self)
        for name in ("_entry_places", "_csr_pattern", "member_system"):  # what depends on the components
            one.__dict__.pop(name, None)
        one.m, one.members, one.kept = self.m // self.members, 1, {}
        return one

    # EL on slice i (equation rows) from the per-cell gradients of the cells anchored at i-1 and i
    def residual(self, g_prev: torch.Tensor, g_cur: torch.Tensor, vol: float) -> np.ndarray:
        m = self.m
        el = torch.zeros(self.nsite, m, dtype=torch.float64)
        gp = g_prev.reshape(-1, self.st.size, m)
        gc = g_cur.reshape(-1, self.st.size, m)
        for a in self.nxt:
            el.index_add_(0, torch.from_numpy(self.site_of[a]), gp[:, a])
        for a in self.now:
            el.index_add_(0, torch.from_numpy(self.site_of[a]), gc[:, a])
        return (vol * el).numpy()[self.interior].reshape(-1)

    @functools.cached_property
    def _entry_places(self) -> tuple[np.ndarray, np.ndarray]:
        """``(rows, cols)`` of the slice Jacobian's entries, pair by pair (the order of :meth:`matrix_entries`)."""
        m = self.m
        rs, cs = [], []
        ii, jj = np.meshgrid(np.arange(m), np.arange(m), indexing="ij")
        for _, r, c in self.jac.values():
            rs.append((r[:, None, None] * m + ii).reshape(-1))
            cs.append((c[:, None, None] * m + jj).reshape(-1))
        return np.concatenate(rs), np.concatenate(cs)

    def _entry_values(self, blocks: dict[tuple[int, int], torch.Tensor], vol: float) -> np.ndarray:
        m = self.m
        vs = [
            (blocks[key].reshape(-1, m, m).numpy()[cells] * vol).reshape(-1) for key, (cells, _, _) in self.jac.items()
        ]
        return np.concatenate(vs)

    def matrix_entries(self, blocks: dict[tuple[int, int], torch.Tensor], vol: float):
        """``(rows, cols, values)`` of the slice Jacobian's entries, pair by pair."""
        rows, cols = self._entry_places
        return rows, cols, self._entry_values(blocks, vol)

    @functools.cached_property
    def _csr_pattern(self) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """``(order, indices, indptr)``: the slice Jacobian's entries (in :meth:`matrix_entries`'s order) sorted
        by row, then column, and the CSR structure they fill; ``None`` where two entries share a place (a
        lattice narrower than the stencil: their sum is left to scipy)."""
        rows, cols = self._entry_places
        order = np.lexsort((cols, rows))
        r, c = rows[order], cols[order]
        if r.size > 1 and bool(np.any((r[1:] == r[:-1]) & (c[1:] == c[:-1]))):
            return None
        indptr = np.zeros(self.n * self.m + 1, dtype=np.int64)
        np.cumsum(np.bincount(r, minlength=self.n * self.m), out=indptr[1:])
        return order, c.astype(np.int32 if c.size < 2**31 else np.int64), indptr.astype(c.dtype)

    def csr(self, blocks: dict[tuple[int, int], torch.Tensor], vol: float) -> scipy.sparse.csr_matrix:
        """The slice Jacobian of ``blocks`` as scipy builds it from :meth:`matrix_entries` (columns sorted within
        each row, the same values), its structure sorted once per lattice."""
        size = self.n * self.m
        data, indices, indptr = self.csr_arrays(blocks, vol)
        return scipy.sparse.csr_matrix((data, indices, indptr), shape=(size, size), copy=False)

    def csr_arrays(
        self, blocks: dict[tuple[int, int], torch.Tensor], vol: float
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(data, indices, indptr)`` of :meth:`csr`."""
        size = self.n * self.m
        pattern = self._csr_pattern
        if pattern is None:
            rows, cols, vals = self.matrix_entries(blocks, vol)
            mat = scipy.sparse.csr_matrix((vals, (rows, cols)), shape=(size, size))
            return mat.data, mat.indices, mat.indptr
        order, indices, indptr = pattern
        columns = getattr(blocks, "columns", None)
        if columns is not None:  # the entries read from the columns in CSR order at once: the same products
            held, first = columns
            if held.flags.c_contiguous:
                src, places = held.reshape(-1), self._column_places(held.shape[1], first)
            else:  # one contiguous row per column (its transpose)
                src, places = held.T.reshape(-1), self._column_places(held.shape[1], first, held.shape[0])
            mod = krylov_kernels() if COMPILED_ASSEMBLY else None
            if mod is not None:
                vals = np.empty(places.size)
                mod.take_scaled(src, places, vol, vals)
            else:
                vals = src[places] * vol
        else:
            vals = self._entry_values(blocks, vol)[order]
        return vals, indices, indptr

    def _column_places(self, width: int, first: int, ncell: int | None = None) -> np.ndarray:
        """Where each entry of the Jacobian, in CSR order, lies in the flat ``(cells, width)`` columns of
        :attr:`Blocks.columns` (pair ``q`` of :attr:`pairs` from ``first + q m m``), kept per layout; with
        ``ncell``, in their flat transpose ``(width, ncell)``."""
        key = f"column_places {width} {first} {ncell}"
        if key not in self.kept:
            mm = self.m * self.m
            q_of = {p: q for q, p in enumerate(self.pairs)}
            within = np.arange(mm, dtype=np.int64)
            cell_step, col_step = (width, 1) if ncell is None else (1, ncell)
            places = [
                ((cells.astype(np.int64) * cell_step)[:, None] + (first + q_of[key2] * mm + within) * col_step).reshape(
                    -1
                )
                for key2, (cells, _, _) in self.jac.items()
            ]
            pattern = self._csr_pattern
            assert pattern is not None
            self.kept[key] = np.concatenate(places)[pattern[0]]
        places_kept: np.ndarray = self.kept[key]
        return places_kept

    def site_singular_values(self, blocks: dict[tuple[int, int], torch.Tensor]) -> tuple[float, float, int]:
        """``(smallest, largest, row)``: the extreme singular values of the Jacobian's diagonal blocks (the mixed
        Hessian at each unknown site, without the cell volume) and the equation row of the smallest."""
        m = self.m
        diag = self.diagonal(blocks)
        if self.n == 0:
            return math.inf, 0.0, 0
        mod = krylov_kernels() if COMPILED_ASSEMBLY and m == 1 else None
        if mod is not None:  # the same extremes by one compiled pass
            low1, worst1, high1 = mod.abs_extremes(diag.reshape(-1).numpy())
            return float(low1), float(high1), int(worst1) * m
        sv = diag.abs().reshape(-1, 1) if m == 1 else torch.linalg.svdvals(diag)
        sv = torch.nan_to_num(sv, nan=0.0)
        low = sv[:, -1]
        worst = int(torch.argmin(low))
        return float(low[worst]), float(sv[:, 0].max()), worst * m

    def member_singular_values(
        self, blocks: dict[tuple[int, int], torch.Tensor]
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`site_singular_values` per model side by side on the components (:attr:`members`; one for a
        single model): ``(smallest, largest, row)`` each of shape ``(members,)``, of each member's own diagonal
        blocks (the Jacobian of a stacked ensemble is block diagonal in its members: each is judged on its own
        scale, as when served alone)."""
        if self.members == 1:
            low, high, row = self.site_singular_values(blocks)
            return np.array([low]), np.array([high]), np.array([row])
        nm, m = self.members, self.m
        w = m // nm
        if self.n == 0:
            return np.full(nm, math.inf), np.zeros(nm), np.zeros(nm, dtype=np.int64)
        own = getattr(blocks, "members", None)
        if own is not None:  # held per member (the folded kernels' of a stack): each member's own, as alone
            found = [self.member_system.site_singular_values(b) for b in own]
            rows = np.array([(row // w) * m + k * w for k, (_, _, row) in enumerate(found)], dtype=np.int64)
            return np.array([f[0] for f in found]), np.array([f[1] for f in found]), rows
        per = member_blocks(self.diagonal(blocks), nm)  # (members, n, w, w)
        sv = per.abs().reshape(nm, -1, 1) if w == 1 else torch.linalg.svdvals(per)
        sv = torch.nan_to_num(sv, nan=0.0)
        lowest = sv[..., -1]  # (members, n)
        worst = torch.argmin(lowest, dim=1)
        rows = worst.numpy() * m + np.arange(nm) * w
        smallest = lowest.gather(1, worst[:, None])[:, 0]
        return smallest.numpy().astype(np.float64), sv[..., 0].amax(dim=1).numpy().astype(np.float64), rows

    def diagonal(self, blocks: dict[tuple[int, int], torch.Tensor]) -> torch.Tensor:
        """The Jacobian's diagonal ``m x m`` blocks ``(n, m, m)`` without the cell volume: per unknown site the mixed
        Hessian summed over the cells that hold it; kept on ``blocks`` where they are :class:`Blocks`."""
        kept = getattr(blocks, "diag", None)
        if kept is not None and kept[0] is self:
            diag_kept: torch.Tensor = kept[1]
            return diag_kept
        m = self.m
        diag = torch.zeros(self.n, m, m, dtype=torch.float64)
        mod = krylov_kernels() if COMPILED_ASSEMBLY else None
        for key, cells, rows in self.diag_entries:
            held = blocks[key].detach().reshape(-1, m, m)
            if mod is not None and held.dtype == torch.float64 and held.device.type == "cpu":
                mod.diag_add(diag.numpy(), rows.numpy(), cells.numpy(), np.ascontiguousarray(held.numpy()))
            else:
                diag.index_add_(0, rows, held[cells])
        if isinstance(blocks, Blocks):
            blocks.diag = (self, diag)
        return diag

    def factor(self, blocks, vol: float):
        """Assemble and factorise the slice Jacobian; returns ``solve(rhs)``. On one spatial axis, a block-tridiagonal
        Jacobian is solved by the compiled kernels of ``._band`` where they serve it, else by the LU below."""
        solve = band_factor(self, blocks, vol)
        if solve is not None:
            return solve
        rows, cols, vals = self.matrix_entries(blocks, vol)
        size = self.n * self.m
        if self.banded:
            lo, up = self.lower, self.upper
            ab = np.zeros((lo + up + 1, size))
            np.add.at(ab, (up + rows - cols, cols), vals)
            if not np.all(ab[up] != 0):
                raise np.linalg.LinAlgError("zero on the diagonal")
            return lambda rhs: scipy.linalg.solve_banded((lo, up), ab, rhs, check_finite=False)
        mat = scipy.sparse.csc_matrix((vals, (rows, cols)), shape=(size, size))
        try:
            return scipy.sparse.linalg.splu(mat).solve
        except RuntimeError as exc:  # "Factor is exactly singular"
            raise np.linalg.LinAlgError(str(exc)) from None


def singular_message(smin: float, scale: float) -> str:
    """The reason a slice is refused: its mixed Hessian is singular relative to ``scale``."""
    if scale <= 0:
        return "mixed Hessian singular: it is zero (a degenerate L_d, e.g. learned with gauge 'none')"
    return (
        f"mixed Hessian singular: smallest singular value {smin:.3e}, {smin / scale:.1e} relative to its "
        f"scale {scale:.3e} (below {SINGULAR_RTOL:g})"
    )


def is_singular(smin: float, scale: float) -> bool:
    """Whether a smallest singular value ``smin`` is singular relative to ``scale`` (a zero scale is)."""
    return not (scale > 0 and smin > SINGULAR_RTOL * scale)


def member_abs_max(a: np.ndarray | torch.Tensor, nm: int, w: int) -> np.ndarray:
    """The largest ``|a|`` of each of ``nm`` models side by side on the components (``a``: ``(..., nm * w)``
    flattened or not; NaN where a member's entries hold one)."""
    if isinstance(a, torch.Tensor):
        a = a.numpy()
    if a.size == 0:
        return np.zeros(nm)
    cols = np.ascontiguousarray(a.reshape(-1, nm * w).T)  # each component's entries contiguous: a fast reduce
    np.abs(cols, out=cols)
    out: np.ndarray = cols.max(axis=1).reshape(nm, w).max(axis=1)
    return out


def member_block_sizes(blocks: dict[tuple[int, int], torch.Tensor], pair: tuple[int, int], nm: int) -> np.ndarray:
    """The largest ``|entry|`` of each of ``nm`` stacked members' own blocks of ``pair`` (NaN where one holds
    one): from the blocks held per member where they are (``blocks.members``), else from the stacked ones."""
    own = getattr(blocks, "members", None)
    if own is not None:
        return np.array([abs_max(b[pair]) for b in own])
    out: np.ndarray = member_blocks(blocks[pair], nm).abs().amax(dim=(1, 2, 3)).numpy()
    return out


def member_blocks(block: torch.Tensor, nm: int) -> torch.Tensor:
    """Each of ``nm`` stacked members' own ``w x w`` blocks of ``(cells, m, m)`` Hessian blocks (``m = nm * w``):
    ``(members, cells, w, w)``."""
    w = block.shape[-1] // nm
    own = torch.arange(nm)
    return block.reshape(-1, nm, w, nm, w)[:, own, :, own, :]


def first_singular(smin: np.ndarray, scale: np.ndarray) -> int | None:
    """The first member whose smallest singular value ``smin[k]`` is singular relative to its own ``scale[k]``
    (:func:`is_singular`), or None."""
    for k in range(len(smin)):
        if is_singular(float(smin[k]), float(scale[k])):
            return k
    return None


def _site_label(f: LatticeField, sys: _SliceSystem, tslice: int, row: int) -> tuple[int, ...]:
    """The lattice index ``(slice, site...)`` of equation row ``row`` of slice ``tslice``."""
    site = int(np.nonzero(sys.interior)[0][row // sys.m])
    return (tslice, *[int(v) for v in np.unravel_index(site, sys.spatial)])


def slice_message(f: LatticeField, i: int, msg: str, site: str | None = None, res: float = math.nan) -> str:
    """``slice 12 (t = 0.12): msg``: why the equations of slice ``i`` of ``f`` gave no slice ``i + 1``, then
    `` in the DEL equation of site ...`` where the text of the ``site`` is given (:func:`site_text`) and
    ``, residual ...`` where ``res`` is finite: the one line of a whole field, a window, a slab of a split
    field and a 1D trajectory."""
    tval = float(f.coords[f.dims[0]][0] + (i + 1) * f.spacing[0])
    return (
        f"slice {i + 1} (t = {tval:.6g}): {msg}"
        + (f" in the DEL equation of site {site}" if site else "")
        + (f", residual {res:.3e}" if math.isfinite(res) else "")
    )


def site_text(dims: tuple[str, ...], site: tuple[int, ...], coords: Any) -> str:
    """``index t=12, x=5 (x = 0.3125)``: a lattice index along ``dims``, and apart the spatial coordinates it
    stands for (``coords[d][i]``, for the axes ``d`` that ``coords`` holds)."""
    idx = ", ".join(f"{d}={i}" for d, i in zip(dims, site))
    where = ", ".join(f"{d} = {float(coords[d][i]):.6g}" for d, i in zip(dims[1:], site[1:]) if d in coords)
    return f"index {idx}" + (f" ({where})" if where else "")


def _scale(flat: torch.Tensor, i: int, unk: torch.Tensor, known: tuple[float, float] | None = None) -> float:
    """Size of the values on slices ``i - 1``, ``i`` and the unknowns of ``i + 1``: the scale of a Newton step
    (``unk``, distinct sites, holding every site: the whole slice, not gathered). ``known``: the sizes of slices
    ``i - 1`` and ``i`` (:func:`_known_sizes`), which a slice's Newton iterations do not move."""
    nxt = flat[i + 1] if unk.numel() == flat.shape[1] else flat[i + 1, unk]
    older, last = _known_sizes(flat, i) if known is None else known
    return max(older, last, abs_max(nxt), 1e-300)


def _known_sizes(flat: torch.Tensor, i: int) -> tuple[float, float]:
    """The sizes of slices ``i - 1`` and ``i`` in :func:`_scale`."""
    return abs_max(flat[i - 1]), abs_max(flat[i])


def values_abs_max(a: np.ndarray) -> float:
    """``float(np.abs(a).max())`` of a non-empty array (a not-a-number wherever one is), by one compiled pass where
    ``a`` is a contiguous double array."""
    mod = krylov_kernels() if COMPILED_ASSEMBLY else None
    if mod is None or a.dtype != np.float64 or not a.flags.c_contiguous:
        return float(np.abs(a).max())
    return float(mod.abs_max(a.reshape(-1)))


def finite_step(a: np.ndarray) -> tuple[bool, float]:
    """``(finite, size)``: whether every value of ``a`` is finite and, where so, its largest size (``0.0`` when
    empty; numpy's ``isfinite().all()`` and ``abs().max()``), by one compiled pass where ``a`` is a contiguous
    double array."""
    mod = krylov_kernels() if COMPILED_ASSEMBLY else None
    if mod is None or a.dtype != np.float64 or not a.flags.c_contiguous or not a.size:
        finite = bool(np.all(np.isfinite(a)))
        return finite, float(np.abs(a).max()) if finite and a.size else 0.0
    finite, top = mod.finite_abs_max(a.reshape(-1))
    return bool(finite), float(top) if finite else 0.0


def abs_max(t: torch.Tensor) -> float:
    """``float(t.abs().max())`` (a not-a-number wherever one is), by one compiled pass where ``t`` is a non-empty
    contiguous CPU tensor in double precision (no array of the sizes)."""
    if not t.numel() or t.dtype != torch.float64 or t.device.type != "cpu":
        return float(t.abs().max())
    return values_abs_max(t.detach().numpy())
