"""Group actions on lattice fields: the symmetries whose invariance and charges latticedft measures.

A :class:`Symmetry` acts on a whole field ``psi`` of shape ``(N_0, ..., N_{n-1}, m)``.

* **Continuous** symmetries are given by their generator ``xi``, a vector field on one time slice's
  configuration space: ``Xi = xi(Q)`` for every slice ``Q`` (never mixing time slices). Built in: affine
  internal generators ``xi(psi_y) = M psi_y + w`` at every site (field shifts, rotations of the
  components, or any ``M``, ``w``), and the lattice pseudo-momentum generator along a periodic axis
  ``k``, ``xi(Q)_y = -(psi_{y+e_k} - psi_{y-e_k}) / (2 h_k)`` (a central difference: the generator of a
  translation ``x -> x + eps`` of the field's profile).
* **Discrete** symmetries map a field to a field: an internal affine map ``psi -> A psi + b`` (the point
  reflection ``psi -> -psi``), the lattice translation by one site along a periodic axis, and time
  reversal ``psi_{i} -> psi_{N_0 - 1 - i}``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from .._errors import InputError

__all__ = ["Symmetry", "resolve_symmetries", "standard_symmetries"]

_CONTINUOUS = ("affine", "momentum")
_DISCRETE = ("linear-map", "translation", "time-reversal")


def _matrix(a: Any, shape: tuple[int, ...], arg: str) -> np.ndarray:
    try:
        out = np.asarray(a, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(f"{arg}: expected an array of numbers, got {a!r}") from None
    if out.shape != shape:
        raise InputError(f"{arg}: expected shape {shape}, got {out.shape}")
    if not np.all(np.isfinite(out)):
        raise InputError(f"{arg}: must be finite, got {a!r}")
    return out


@dataclass(frozen=True, eq=False)
class Symmetry:
    """A symmetry candidate of a discrete Lagrangian: a one-parameter group (``continuous``) or a map.

    Build one with the class methods :meth:`affine`, :meth:`shift`, :meth:`rotation`, :meth:`momentum`
    (continuous) or :meth:`reflection`, :meth:`linear_map`, :meth:`translation`,
    :meth:`time_reversal` (discrete); ``latticedft.builtin_symmetries(field)`` lists the standard ones
    for a field, by name.

    >>> Symmetry.rotation(0, 1, 2).matrix.tolist()
    [[0.0, -1.0], [1.0, 0.0]]
    >>> Symmetry.reflection().continuous
    False
    """

    name: str
    action: str
    #: ``M`` (affine generator) or ``A`` (linear map), ``(m, m)``.
    matrix: np.ndarray | None = None
    #: ``w`` (affine generator) or ``b`` (linear map), ``(m,)``.
    offset: np.ndarray | None = None
    #: Lattice axis of a translation or momentum generator.
    axis: int | None = None
    description: str = ""
    meta: dict[str, Any] = field(default_factory=dict)

    # -- constructors ---------------------------------------------------------------------------------------
    @classmethod
    def affine(cls, matrix: Any, offset: Any = None, *, name: str = "affine") -> Symmetry:
        """The continuous internal symmetry with generator ``xi(psi) = M psi + w`` at every site."""
        mat = np.atleast_2d(np.asarray(matrix, dtype=np.float64)) if matrix is not None else None
        if mat is None or mat.ndim != 2 or mat.shape[0] != mat.shape[1]:
            raise InputError(f"matrix: expected a square (m, m) array, got {matrix!r}")
        m = mat.shape[0]
        mat = _matrix(mat, (m, m), "matrix")
        off = np.zeros(m) if offset is None else _matrix(np.atleast_1d(offset), (m,), "offset")
        if not (np.any(mat) or np.any(off)):
            raise InputError("matrix, offset: the generator M = 0, w = 0 moves nothing")
        return cls(
            name=name,
            action="affine",
            matrix=mat,
            offset=off,
            description=f"xi(psi) = M psi + w, M = {mat.tolist()}, w = {off.tolist()}",
        )

    @classmethod
    def shift(cls, m: int = 1, component: int | None = None, *, name: str | None = None) -> Symmetry:
        """Field shift ``psi -> psi + eps e_component`` (all components together when ``component`` is None)."""
        w = np.ones(m) if component is None else np.eye(m)[_component(component, m)]
        sym = cls.affine(np.zeros((m, m)), w, name=name or ("shift" if component is None else f"shift-{component}"))
        what = "every component" if component is None else f"component {component}"
        return _renamed(sym, sym.name, f"field shift psi -> psi + eps ({what})")

    @classmethod
    def rotation(cls, i: int, j: int, m: int, *, name: str | None = None) -> Symmetry:
        """Rotation of components ``i`` and ``j``: generator ``M = E_ji - E_ij`` (``M[j, i] = 1``, ``M[i, j] = -1``)."""
        i, j = _component(i, m), _component(j, m)
        if i == j:
            raise InputError(f"i, j: a rotation needs two different components, got {i} and {j}")
        mat = np.zeros((m, m))
        mat[j, i], mat[i, j] = 1.0, -1.0
        sym = cls.affine(mat, None, name=name or f"rotation-{i}{j}")
        return _renamed(
            sym, sym.name, f"rotation of components {i}, {j}: xi(psi) = M psi, M[{j},{i}] = 1 = -M[{i},{j}]"
        )

    @classmethod
    def momentum(cls, axis: int = 1, *, name: str | None = None) -> Symmetry:
        """Pseudo-momentum generator along periodic axis ``axis``: ``xi_y = -(psi_{y+e_k} - psi_{y-e_k}) / (2 h_k)``.

        An exact symmetry of quadratic translation-invariant ``L_d`` only (see docs/symmetries.md).
        """
        if not isinstance(axis, int) or isinstance(axis, bool) or axis < 1:
            raise InputError(f"axis: expected a spatial lattice axis >= 1, got {axis!r}")
        return cls(
            name=name or f"momentum-{axis}",
            action="momentum",
            axis=axis,
            description=f"xi(Q)_y = -(psi[y + e_{axis}] - psi[y - e_{axis}]) / (2 h_{axis}) (periodic axis)",
        )

    @classmethod
    def linear_map(cls, matrix: Any, offset: Any = None, *, name: str = "linear-map") -> Symmetry:
        """The discrete internal map ``psi -> A psi + b`` at every site."""
        mat = np.atleast_2d(np.asarray(matrix, dtype=np.float64))
        m = mat.shape[0] if mat.ndim == 2 else 0
        mat = _matrix(mat, (m, m), "matrix")
        off = np.zeros(m) if offset is None else _matrix(np.atleast_1d(offset), (m,), "offset")
        return cls(
            name=name,
            action="linear-map",
            matrix=mat,
            offset=off,
            description=f"psi -> A psi + b, A = {mat.tolist()}, b = {off.tolist()}",
        )

    @classmethod
    def reflection(cls, m: int = 1, *, name: str = "reflection") -> Symmetry:
        """The point reflection ``psi -> -psi`` (a discrete symmetry)."""
        sym = cls.linear_map(-np.eye(m), None, name=name)
        return _renamed(sym, name, "point reflection psi -> -psi")

    @classmethod
    def translation(cls, axis: int = 1, *, name: str | None = None) -> Symmetry:
        """Lattice translation by one site along periodic axis ``axis`` (a discrete symmetry)."""
        if not isinstance(axis, int) or isinstance(axis, bool) or axis < 1:
            raise InputError(f"axis: expected a spatial lattice axis >= 1, got {axis!r}")
        return cls(
            name=name or f"translation-{axis}",
            action="translation",
            axis=axis,
            description=f"psi[y] -> psi[y + e_{axis}] (periodic axis)",
        )

    @classmethod
    def time_reversal(cls, *, name: str = "time-reversal") -> Symmetry:
        """Time reversal ``psi_i -> psi_{N-1-i}``: each cell's two time slices swap (a discrete symmetry)."""
        return cls(
            name=name,
            action="time-reversal",
            description="psi[i] -> psi[N - 1 - i] (the two time slices "
            "of every slab swap: L_s(Q_{i+1}, Q_i) against L_s(Q_i, Q_{i+1}))",
        )

    # -- properties -----------------------------------------------------------------------------------------
    @property
    def continuous(self) -> bool:
        """True for a one-parameter group (it has a generator and a Noether charge)."""
        return self.action in _CONTINUOUS

    @property
    def kind(self) -> str:
        return "continuous" if self.continuous else "discrete"

    def generator(self) -> dict[str, Any] | str:
        """JSON-compatible description: ``{"matrix": M, "offset": w}`` for affine generators and maps."""
        if self.matrix is not None and self.offset is not None:
            return {"matrix": self.matrix.tolist(), "offset": self.offset.tolist()}
        return self.description

    def check(self, n: int, m: int, periodic: tuple[bool, ...]) -> None:
        """Raise ``InputError`` unless the symmetry acts on fields with ``n`` lattice dims and ``m`` components."""
        if self.matrix is not None and self.matrix.shape[0] != m:
            raise InputError(f"symmetry {self.name!r}: acts on {self.matrix.shape[0]} components; the field has {m}")
        if self.axis is not None:
            if self.axis >= n:
                raise InputError(f"symmetry {self.name!r}: axis {self.axis} is not a spatial axis of an {n}-D lattice")
            if not periodic[self.axis]:
                raise InputError(
                    f"symmetry {self.name!r}: axis {self.axis} is not periodic; lattice translations "
                    "and momenta need a periodic axis"
                )

    # -- action on values -------------------------------------------------------------------------------------
    def xi(self, psi: torch.Tensor, spacing: tuple[float, ...]) -> torch.Tensor:
        """The generator on every slice of ``psi`` ``(N_0, ..., m)``; differentiable in ``psi``."""
        if self.action == "affine":
            mat = torch.as_tensor(self.matrix, dtype=psi.dtype)
            return psi @ mat.T + torch.as_tensor(self.offset, dtype=psi.dtype)
        if self.action == "momentum":
            k = int(self.axis)  # type: ignore[arg-type]
            return -(torch.roll(psi, -1, dims=k) - torch.roll(psi, 1, dims=k)) / (2.0 * spacing[k])
        raise InputError(f"symmetry {self.name!r}: a discrete symmetry has no generator")

    def apply(self, psi: torch.Tensor) -> torch.Tensor:
        """The discrete map on a whole field ``psi`` ``(N_0, ..., m)``; differentiable in ``psi``."""
        if self.action == "linear-map":
            mat = torch.as_tensor(self.matrix, dtype=psi.dtype)
            return psi @ mat.T + torch.as_tensor(self.offset, dtype=psi.dtype)
        if self.action == "translation":
            return torch.roll(psi, -1, dims=int(self.axis))  # type: ignore[arg-type]
        if self.action == "time-reversal":
            return torch.flip(psi, dims=(0,))
        raise InputError(f"symmetry {self.name!r}: a continuous symmetry acts through its generator; use xi()")

    def __repr__(self) -> str:
        return f"Symmetry({self.name!r}, {self.kind}: {self.description})"


def _component(c: Any, m: int) -> int:
    if not isinstance(c, (int, np.integer)) or isinstance(c, bool) or not 0 <= int(c) < m:
        raise InputError(f"component: expected an index in 0..{m - 1}, got {c!r}")
    return int(c)


def _renamed(sym: Symmetry, name: str, description: str) -> Symmetry:
    return Symmetry(
        name=name, action=sym.action, matrix=sym.matrix, offset=sym.offset, axis=sym.axis, description=description
    )


def standard_symmetries(
    n: int,
    m: int,
    periodic: tuple[bool, ...],
    dims: tuple[str, ...] | None = None,
    components: tuple[str, ...] | None = None,
) -> list[Symmetry]:
    """The standard candidates for a lattice: shifts, reflection, rotations, time reversal, translations, momenta.

    Names use the field's labels: ``shift`` (scalar) or ``shift-<component>``, ``reflection``,
    ``rotation-<a><b>`` for each pair of components, ``time-reversal``, and for each periodic spatial
    axis ``translation-<dim>`` (discrete) and ``momentum-<dim>`` (its pseudo-momentum generator).
    """
    labels = list(components) if components is not None else [str(c) for c in range(m)]
    dims = tuple(dims) if dims is not None else tuple(f"axis{k}" for k in range(n))
    out: list[Symmetry] = []
    if m == 1:
        out.append(Symmetry.shift(1))
    else:
        out += [
            _renamed(
                Symmetry.shift(m, c), f"shift-{labels[c]}", f"field shift psi_{labels[c]} -> psi_{labels[c]} + eps"
            )
            for c in range(m)
        ]
    out.append(Symmetry.reflection(m))
    for i in range(m):
        for j in range(i + 1, m):
            r = Symmetry.rotation(i, j, m)
            out.append(
                _renamed(
                    r,
                    f"rotation-{labels[i]}{labels[j]}",
                    f"rotation in the ({labels[i]}, {labels[j]}) plane: xi = M psi, M[{j},{i}] = 1 = -M[{i},{j}]",
                )
            )
    out.append(Symmetry.time_reversal())
    for k in range(1, n):
        if periodic[k]:
            t = Symmetry.translation(k)
            out.append(_renamed(t, f"translation-{dims[k]}", f"psi[y] -> psi[y + e_{dims[k]}] (one site, periodic)"))
            p = Symmetry.momentum(k)
            out.append(
                _renamed(
                    p,
                    f"momentum-{dims[k]}",
                    f"pseudo-momentum generator xi_y = -(psi[y + e_{dims[k]}] - psi[y - e_{dims[k]}]) "
                    f"/ (2 h_{dims[k]})",
                )
            )
    return out


def resolve_symmetries(
    items: Any, n: int, m: int, periodic: tuple[bool, ...], dims: tuple[str, ...], components: tuple[str, ...] | None
) -> list[Symmetry]:
    """Symmetries from names of :func:`standard_symmetries` or :class:`Symmetry` objects (one or a list)."""
    if items is None:
        return standard_symmetries(n, m, periodic, dims, components)
    if isinstance(items, (str, Symmetry)):
        items = [items]
    known = {s.name: s for s in standard_symmetries(n, m, periodic, dims, components)}
    out = []
    for it in items:
        if isinstance(it, Symmetry):
            out.append(it)
        elif isinstance(it, str) and it in known:
            out.append(known[it])
        else:
            raise InputError(f"symmetry: unknown {it!r}; for this field expected a Symmetry or one of {sorted(known)}")
    for s in out:
        s.check(n, m, periodic)
    return out
