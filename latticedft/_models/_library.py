"""Term libraries of a sparse ``L_d``: composable objects, ``+`` for their union and ``*`` for their products.

A library is a list of term families (:class:`latticedft._models._terms.Family`); once the lattice is known
(``n`` axes, ``m`` components) each family expands into concrete terms. Strings are shorthands, usable in
case.toml (``library = "kinetic + gradient + poly:4 + trig:1"``; the names are listed in
:mod:`latticedft._models._terms`): ``A*B`` is the products of two families' terms, ``A + B`` their union
(``*`` binds tighter), so ``cosdiff*velocities`` holds ``cos(q1 - q2) Dtq1 Dtq2``.

>>> lib = Library.parse("kinetic + poly:2 * kinetic + trig:1")
>>> [t.name for t in lib.expand(1, 1)]
['Dtq**2', 'q*Dtq**2', 'q**2*Dtq**2', 'sin(q)', 'cos(q)']
"""

from __future__ import annotations

import re
from collections.abc import Callable, Sequence
from typing import Any

import torch

from .._errors import InputError
from .._symbolic import cell_symbols
from ._terms import Family, Term, axis_name, component_name, function, named

__all__ = ["Library", "cell_variables", "readable_variables"]


class Library:
    """A union of term families; ``+`` is the union, ``*`` the products of every pair of terms.

    >>> (Library.parse("kinetic") + "cos").labels
    ['kinetic', 'trig:1']
    """

    def __init__(self, families: Sequence[Family]):
        self.families: list[Family] = list(families)

    # -- building -----------------------------------------------------------------------------------------
    @classmethod
    def parse(cls, spec: Any) -> Library:
        """A library from a string (``"kinetic + poly:4"``), a :class:`Family`, a library, or a list of them
        (their union); an ``InputError`` about ``library`` for anything else or an empty library."""
        if isinstance(spec, Library):
            out = spec
        elif isinstance(spec, Family):
            out = cls([spec])
        elif isinstance(spec, str) and not spec.strip():
            out = cls([])
        elif isinstance(spec, str):
            out = cls([f for part in _split(spec, "+") for f in _parse_product(part).families])
        elif isinstance(spec, (list, tuple)):
            out = cls([f for item in spec for f in cls.parse(item).families])
        else:
            raise InputError.at("library", f"expected a string such as 'kinetic + poly:4' or a list, got {spec!r}")
        if not out.families:
            raise InputError.at("library", "is empty; name at least one term, e.g. 'kinetic + poly:4'")
        return out

    def __add__(self, other: Any) -> Library:
        return Library(self.families + Library.parse(other).families)

    def __radd__(self, other: Any) -> Library:
        return Library.parse(other) + self

    def __mul__(self, other: Any) -> Library:
        right = Library.parse(other)
        return Library([_product(a, b) for a in self.families for b in right.families])

    def __rmul__(self, other: Any) -> Library:
        return Library.parse(other) * self

    @classmethod
    def function(
        cls, fn: Callable[[torch.Tensor], torch.Tensor], name: str, form: Callable[..., Any] | None = None
    ) -> Library:
        """A library of one user term: ``fn`` maps the field ``(..., m)`` (torch) to ``(...)``; ``form``, if
        given, maps the components' sympy symbols to the same function (the model then has a closed form). A
        library holding one cannot be written to a model file."""
        return cls([function(fn, name, form)])

    # -- reading ------------------------------------------------------------------------------------------
    @property
    def labels(self) -> list[str]:
        """The families' labels (what a model file records)."""
        return [f.label for f in self.families]

    @property
    def saveable(self) -> bool:
        """False when a family holds a Python function (a model file cannot store it)."""
        return all(f.saveable for f in self.families)

    def expand(self, n: int, m: int) -> list[Term]:
        """The terms on a lattice of ``n`` axes and ``m`` components, once each (by name), in order."""
        out: dict[str, Term] = {}
        for family in self.families:
            for term in family.expand(n, m):
                out.setdefault(term.name, term)
        if not out:
            raise InputError.at("library", f"{' + '.join(self.labels)} holds no term on this lattice")
        return list(out.values())

    def __repr__(self) -> str:
        return f"Library({' + '.join(self.labels)!r})"


def _product(a: Family, b: Family) -> Family:
    def build(n: int, m: int) -> list[Term]:
        return [x * y for x in a.expand(n, m) for y in b.expand(n, m)]

    return Family(f"{a.label}*{b.label}", build, a.saveable and b.saveable)


def _split(spec: str, sep: str) -> list[str]:
    """``spec`` split at ``sep`` (not inside a number's exponent such as ``1e+3``), parts stripped."""
    parts = re.split(r"(?<![eE])" + re.escape(sep), spec) if sep == "+" else spec.split(sep)
    out = [p.strip() for p in parts]
    if any(not p for p in out):
        raise InputError.at("library", f"an empty term in {spec!r}")
    return out


def _parse_product(part: str) -> Library:
    factors = [Library([named(s)]) for s in _split(part, "*")]
    out = factors[0]
    for f in factors[1:]:
        out = out * f
    return out


def cell_variables(proj: torch.Tensor, spacing: Sequence[float], m: int) -> tuple[list[Any], list[list[Any]]]:
    """The stencil mean ``q[i]`` and the derivatives ``d[k][i]`` as sympy expressions in the cell symbols
    (:func:`latticedft._symbolic.cell_symbols`): the projection's entries as exact rationals where they are
    (the first-order stencil's ``1/K``, ``+-1``), the spacings as floats."""
    import sympy

    u = cell_symbols(int(proj.shape[1]), m)
    weights = [[_rational(float(w)) for w in row] for row in proj.tolist()]
    q = [sum((w * u[p][i] for p, w in enumerate(weights[0])), sympy.Integer(0)) for i in range(m)]
    d = [
        [sum((w * u[p][i] for p, w in enumerate(weights[1 + k])), sympy.Integer(0)) / sympy.Float(h) for i in range(m)]
        for k, h in enumerate(spacing)
    ]
    return q, d


def _rational(w: float) -> Any:
    """``w`` as a sympy rational when it is one of small denominator to round-off, else as a float."""
    import sympy

    r = sympy.Rational(w).limit_denominator(64)
    return r if abs(float(r) - w) <= 1e-12 * max(1.0, abs(w)) else sympy.Float(w)


def readable_variables(n: int, m: int) -> tuple[list[Any], list[list[Any]], dict[Any, str]]:
    """Sympy symbols ``q`` (or ``q1 ...``) and ``Dtq``, ``Dxq`` ... for printing, and their LaTeX names."""
    import sympy

    q = [sympy.Symbol(component_name(m, i), real=True) for i in range(m)]
    d = [[sympy.Symbol(f"D{axis_name(k)}{component_name(m, i)}", real=True) for i in range(m)] for k in range(n)]
    sub = ["" if m == 1 else f"_{i + 1}" for i in range(m)]
    latex = {s: f"q{sub[i]}" for i, s in enumerate(q)}
    latex.update({s: f"D_{axis_name(k)} q{sub[i]}" for k, row in enumerate(d) for i, s in enumerate(row)})
    return q, d, latex
