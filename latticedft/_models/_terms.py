"""The terms of a sparse ``L_d``'s libraries: :class:`Term` (one function of a cell), :class:`Family` (terms
expanded once the lattice is known) and the families the shorthand strings name.

A term is one function of the field ``q`` on a cell (per component: its value at the cell's anchor site, or
the stencil mean) and of the discrete derivatives ``D_k q = g_k / h_k`` (the per-axis differences of
:meth:`AbstractLagrangian.mean_and_differences` over the spacing). It is written once against a small math
namespace, so the same code gives its torch values on cells and its sympy form (for its name, for
``symbolic()`` and for the DEL it implies).

The shorthands (usable in case.toml, joined into libraries by :mod:`latticedft._models._library`):

- on-site functions of the field: ``poly:K`` (the monomials of the components of total degree ``1 .. K``),
  ``trig:K`` / ``trig:K:w`` (``sin(j w q_i)``, ``cos(j w q_i)``, ``j = 1 .. K``), ``trig:K@P`` / ``trig:K:w@P``
  (the same of the power ``q_i^P``: ``trig:1@2`` holds ``sin(q**2)``, ``cos(q**2)``), ``trig:K(F)`` (the same of
  every term of one family ``F``: ``trig:1(poly:2)`` holds ``sin(q)`` and ``sin(q**2)``), ``exp`` / ``exp:w``
  (``exp(w q_i)``), ``exp@P`` / ``exp:w@P`` (``exp(w q_i^P)``);
- squared derivatives: ``kinetic`` (``|D_t q|^2``), ``gradient`` (``|D_x q|^2`` per space axis),
  ``velocities`` (every product ``D_t q_i D_t q_j``, for unequal masses);
- vector fields: ``norm:k1,k2,...`` (``|q|^k``, negative ``k`` too), ``log`` (``log|q|``), ``cross``
  (``q_1 D_t q_2 - q_2 D_t q_1``, a magnetic term), ``radial`` (``(q . D_t q)^2``), ``cosdiff`` / ``sindiff``
  (``cos(q_i - q_j)``, ``sin(q_i - q_j)``, ``i < j``), ``coupledstep`` (two components: the exact step's
  corrections of two pendulums coupled through ``cos(q1 - q2)``, 28 terms, with ``velocities + trig:1 +
  cosdiff*velocities``).

>>> [t.name for t in named("trig:2").expand(1, 1)]
['sin(q)', 'cos(q)', 'sin(2*q)', 'cos(2*q)']
>>> [t.name for t in named("trig:1@2").expand(1, 2)]
['sin(q1**2)', 'cos(q1**2)', 'sin(q2**2)', 'cos(q2**2)']
"""

from __future__ import annotations

import functools
import itertools
import operator
import re
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import partial
from typing import Any

import torch

from .._errors import InputError

__all__ = [
    "Term",
    "Family",
    "Vars",
    "AXES",
    "axis_name",
    "component_name",
    "function",
    "named",
    "term_values",
    "term_forms",
]

#: Axis names of the lattice, time first: D_t, D_x, D_y, D_z (then x4, x5 ...).
AXES = ("t", "x", "y", "z")

#: What a term's function takes: ``q[i]`` the mean of component ``i``, ``d[k][i]`` its derivative along axis
#: ``k``, and the math namespace (torch or sympy).
Evaluator = Callable[["Vars"], Any]


def axis_name(k: int) -> str:
    """``t``, ``x``, ``y``, ``z``, then ``x4`` ...: the name of lattice axis ``k`` (time first)."""
    return AXES[k] if k < len(AXES) else f"x{k}"


class _TorchMath:
    """The math of a term's torch values."""

    sympy = False
    sin, cos, exp, log, sqrt = torch.sin, torch.cos, torch.exp, torch.log, torch.sqrt

    @staticmethod
    def power(x: Any, num: int, den: int = 1) -> Any:
        return x**num if den == 1 else x ** (num / den)


class _SympyMath:
    """The math of a term's sympy form."""

    sympy = True

    def __init__(self) -> None:
        import sympy

        self.sin, self.cos, self.exp, self.log, self.sqrt = sympy.sin, sympy.cos, sympy.exp, sympy.log, sympy.sqrt
        self._rational = sympy.Rational

    def power(self, x: Any, num: int, den: int = 1) -> Any:
        return x**num if den == 1 else x ** self._rational(num, den)


@dataclass
class Vars:
    """A term's inputs: ``q[i]`` the stencil mean of component ``i``, ``d[k][i]`` the derivative of component
    ``i`` along axis ``k`` (time first), ``xp`` the math (``sin``, ``cos``, ``exp``, ``log``, ``sqrt``,
    ``power(x, num, den)``) and ``raw`` the mean as one tensor ``(..., m)`` (torch only: user functions)."""

    q: Sequence[Any]
    d: Sequence[Sequence[Any]]
    xp: Any
    raw: torch.Tensor | None = None


@dataclass(frozen=True)
class Term:
    """One concrete term: its plain-text name and its function of :class:`Vars` (torch and sympy alike);
    ``form`` is False for a user function without a sympy form (the model then has no closed form)."""

    name: str
    fn: Evaluator
    form: bool = True

    def __mul__(self, other: Term) -> Term:
        a, b = self.fn, other.fn
        return Term(_product_name(self.name, other.name), lambda v: a(v) * b(v), self.form and other.form)


def _product_name(a: str, b: str) -> str:
    return "*".join(f"({s})" if _has_sum(s) else s for s in (a, b))


def _has_sum(name: str) -> bool:
    """True when ``name`` holds a ``+`` or ``-`` outside parentheses (it needs them in a product)."""
    depth = 0
    for i, ch in enumerate(name):
        depth += (ch == "(") - (ch == ")")
        if depth == 0 and ch in "+-" and i > 0 and name[i - 1] not in "*e":
            return True
    return False


@dataclass(frozen=True)
class Family:
    """A family of terms, expanded once the lattice is known: ``expand(n, m)`` -> the terms, or an
    ``InputError`` about ``library`` when the family does not fit that lattice. ``label`` is what a model
    file records (the shorthand string; a user function's label cannot be saved)."""

    label: str
    builder: Callable[[int, int], list[Term]]
    saveable: bool = True

    def expand(self, n: int, m: int) -> list[Term]:
        return self.builder(n, m)


# -- the named families ------------------------------------------------------------------------------------
def function(fn: Callable[[torch.Tensor], torch.Tensor], name: str, form: Callable[..., Any] | None = None) -> Family:
    """A family of one user term: ``fn`` maps the stencil mean ``(..., m)`` (torch) to ``(...)``; ``form``, if
    given, maps the mean's sympy components ``q_0, ..., q_{m-1}`` to the same function in sympy (the model
    then has a closed form). A library holding one cannot be written to a model file."""
    if not callable(fn):
        raise InputError.at("library", f"expected a function of the stencil mean, got {fn!r}")

    def value(v: Vars) -> Any:
        if v.xp.sympy:
            return form(*v.q) if form is not None else None
        assert v.raw is not None
        return fn(v.raw)

    return Family(f"function:{name}", lambda n, m: [Term(name, value, form is not None)], saveable=False)


def _need(label: str, n: int, m: int, *, vector: bool = False, space: bool = False, pair: bool = False) -> None:
    """Refuse a family on a lattice it does not fit (one line naming ``library``)."""
    if vector and m < 2:
        raise InputError.at("library", f"'{label}' needs a vector field (2 or more components); the field has 1")
    if pair and m != 2:
        raise InputError.at("library", f"'{label}' needs a field of 2 components; the field has {m}")
    if space and n < 2:
        raise InputError.at("library", f"'{label}' needs a space axis; the lattice has time only")


def component_name(m: int, i: int) -> str:
    """``q`` for a scalar field, ``q1``, ``q2`` ... for the components of a vector field."""
    return "q" if m == 1 else f"q{i + 1}"


_NUMBER = r"([0-9]*\.?[0-9]+(?:[eE][+-]?[0-9]+)?)"
_FAMILIES: list[tuple[re.Pattern[str], Callable[[re.Match[str], str], Family]]] = []


def _family(pattern: str) -> Callable[[Callable[[re.Match[str], str], Family]], Callable[[re.Match[str], str], Family]]:
    def register(make: Callable[[re.Match[str], str], Family]) -> Callable[[re.Match[str], str], Family]:
        _FAMILIES.append((re.compile(f"^{pattern}$"), make))
        return make

    return register


def named(spec: str) -> Family:
    """The family a shorthand names (``"poly:4"``, ``"kinetic"`` ...); an ``InputError`` about ``library`` else."""
    for pattern, make in _FAMILIES:
        match = pattern.match(spec)
        if match:
            return make(match, spec)
    raise InputError.at(
        "library",
        f"unknown term {spec!r}; expected poly:K, trig:K[:w][@P], trig:K(F), exp[:w][@P], kinetic, gradient, "
        "velocities, norm:k1,k2,..., log, cross, radial, cosdiff, sindiff, coupledstep, joined by '+' and '*'",
    )


@_family(r"poly:(\d+)")
def _poly(match: re.Match[str], label: str) -> Family:
    k = int(match.group(1))
    if k < 1:
        raise InputError.at("library", f"expected K >= 1 in {label!r}")

    def build(n: int, m: int) -> list[Term]:
        exps = [e for d in range(1, k + 1) for e in _exponents(m, d)]
        return [_monomial(e, m) for e in exps]

    return Family(label, build)


def _exponents(m: int, d: int) -> list[tuple[int, ...]]:
    """The exponent tuples of the monomials of total degree ``d`` in ``m`` variables, the first variable's
    powers highest first."""
    return sorted((e for e in itertools.product(range(d + 1), repeat=m) if sum(e) == d), reverse=True)


def _monomial(e: tuple[int, ...], m: int) -> Term:
    def value(v: Vars) -> Any:
        return _product([v.q[i] ** p for i, p in enumerate(e) if p])

    name = "*".join(component_name(m, i) + (f"**{p}" if p > 1 else "") for i, p in enumerate(e) if p)
    return Term(name, value)


def _frequency(text: str | None, label: str) -> float:
    w = float(text) if text else 1.0
    if not w > 0:
        raise InputError.at("library", f"expected a positive frequency in {label!r}")
    return w


def _number(x: float) -> int | float:
    """``x`` as an int when it is one (sympy then prints ``cos(2*q)``, not ``cos(2.0*q)``)."""
    return int(x) if float(x).is_integer() else x


def _scaled(w: float, j: int, name: str) -> str:
    c = w * j
    return name if c == 1 else f"{c:g}*{name}"


_POWER = r"(?:@(\d+))?"


def _power(text: str | None, label: str) -> int:
    """The ``P`` of ``...@P`` (1 without it); an ``InputError`` about ``library`` for ``P < 1``."""
    p = int(text) if text else 1
    if p < 1:
        raise InputError.at("library", f"expected a power P >= 1 after '@' in {label!r}")
    return p


def _argument(m: int, i: int, p: int) -> str:
    """The name of ``q_i^p``: ``q``, ``q**2``, ``q1**3`` ..."""
    return component_name(m, i) + (f"**{p}" if p > 1 else "")


@_family(rf"trig:(\d+)(?::{_NUMBER})?{_POWER}")
def _trig(match: re.Match[str], label: str) -> Family:
    """``trig:K[:w][@P]``: ``sin(j w q_i^P)``, ``cos(j w q_i^P)``, ``j = 1 .. K``, of each component."""
    k, w, p = int(match.group(1)), _frequency(match.group(2), label), _power(match.group(3), label)
    if k < 1:
        raise InputError.at("library", f"expected K >= 1 in {label!r}")

    def build(n: int, m: int) -> list[Term]:
        out = []
        for i in range(m):
            for j in range(1, k + 1):
                arg = _scaled(w, j, _argument(m, i, p))
                c = _number(j * w)
                out += [
                    Term(f"sin({arg})", partial(_onsite, "sin", i, c, p)),
                    Term(f"cos({arg})", partial(_onsite, "cos", i, c, p)),
                ]
        return out

    return Family(label, build)


@_family(rf"trig:(\d+)(?::{_NUMBER})?\(([^()]+)\)")
def _trig_of(match: re.Match[str], label: str) -> Family:
    """``trig:K(F)``: ``sin(j w T)``, ``cos(j w T)`` of every term ``T`` of the on-site family ``F`` (``poly:2``:
    the trig functions of ``q`` and ``q^2``, a potential such as ``cos(q^2 - 1)``)."""
    k, w = int(match.group(1)), _frequency(match.group(2), label)
    inner = named(match.group(3).strip())
    if k < 1:
        raise InputError.at("library", f"expected K >= 1 in {label!r}")

    def build(n: int, m: int) -> list[Term]:
        out = []
        for term in inner.expand(n, m):
            for j in range(1, k + 1):
                arg = _scaled(w, j, f"({term.name})" if _has_sum(term.name) else term.name)
                c = _number(j * w)
                out += [Term(f"{f}({arg})", partial(_of_term, f, c, term.fn), term.form) for f in ("sin", "cos")]
        return out

    return Family(label, build, inner.saveable)


def _of_term(name: str, c: float, fn: Evaluator, v: Vars) -> Any:
    """``name(c T)``: ``sin`` or ``cos`` of a scaled term."""
    return getattr(v.xp, name)(_times(c, fn(v)))


@_family(r"(?:cos|sin)")
def _trig_short(match: re.Match[str], label: str) -> Family:
    return named("trig:1")


@_family(rf"exp(?::{_NUMBER})?{_POWER}")
def _exp(match: re.Match[str], label: str) -> Family:
    """``exp[:w][@P]``: ``exp(w q_i^P)`` of each component."""
    w, p = _frequency(match.group(1), label), _power(match.group(2), label)

    def build(n: int, m: int) -> list[Term]:
        c = _number(w)
        return [Term(f"exp({_scaled(w, 1, _argument(m, i, p))})", partial(_onsite, "exp", i, c, p)) for i in range(m)]

    return Family(label, build)


@_family(r"(?:trig|exp)[^@]*@.*")
def _bad_power(match: re.Match[str], label: str) -> Family:
    """A ``@`` that none of the forms above read (``trig:1@x``, ``trig:1(poly:2)@2``): one line naming the form."""
    raise InputError.at(
        "library", f"expected trig:K[:w]@P or exp[:w]@P with a power P >= 1 (an integer), got {label!r}"
    )


def _squared(axis: int, m: int) -> Term:
    """``|D_axis q|^2``: the sum over components (rotation invariant)."""
    name = "+".join(f"D{axis_name(axis)}{component_name(m, i)}**2" for i in range(m))
    return Term(name if m == 1 else f"({name})", lambda v: _total([v.d[axis][i] ** 2 for i in range(m)]))


@_family(r"kinetic")
def _kinetic(match: re.Match[str], label: str) -> Family:
    return Family(label, lambda n, m: [_squared(0, m)])


@_family(r"gradient")
def _gradient(match: re.Match[str], label: str) -> Family:
    def build(n: int, m: int) -> list[Term]:
        _need(label, n, m, space=True)
        return [_squared(k, m) for k in range(1, n)]

    return Family(label, build)


@_family(r"velocities")
def _velocities(match: re.Match[str], label: str) -> Family:
    def build(n: int, m: int) -> list[Term]:
        out = []
        for i, j in itertools.combinations_with_replacement(range(m), 2):
            a, b = f"Dt{component_name(m, i)}", f"Dt{component_name(m, j)}"
            out.append(Term(f"{a}**2" if i == j else f"{a}*{b}", partial(_velocity_product, i, j)))
        return out

    return Family(label, build)


# Sums and products of a term's parts start from the first part, and a factor of 1 is left out: the values are the
# same to the bit (0 + a = a, 1 * a = a), and under ``torch.func.jvp`` (the exact solve's derivatives) an
# operation with a Python number costs several times one between tensors.
def _total(parts: Sequence[Any]) -> Any:
    """``parts[0] + parts[1] + ...``, left to right."""
    return functools.reduce(operator.add, parts)


def _product(parts: Sequence[Any]) -> Any:
    """``parts[0] * parts[1] * ...``, left to right."""
    return functools.reduce(operator.mul, parts)


def _times(c: float, x: Any) -> Any:
    """``c x``, or ``x`` itself for ``c = 1``."""
    return x if c == 1 else c * x


def _onsite(name: str, i: int, c: float, p: int, v: Vars) -> Any:
    """``name(c q_i^p)``: ``sin``, ``cos`` or ``exp`` of a scaled power of a component."""
    return getattr(v.xp, name)(_times(c, v.q[i] if p == 1 else v.q[i] ** p))


def _velocity_product(i: int, j: int, v: Vars) -> Any:
    return v.d[0][i] * v.d[0][j]


def _norm_power(k: int, v: Vars) -> Any:
    return v.xp.power(_norm_squared(v), k, 2)


def _component_difference(name: str, i: int, j: int, v: Vars) -> Any:
    return getattr(v.xp, name)(v.q[i] - v.q[j])


def _norm_squared(v: Vars) -> Any:
    return _total([qi**2 for qi in v.q])


@_family(r"norm:(-?\d+(?:,-?\d+)*)")
def _norm(match: re.Match[str], label: str) -> Family:
    powers = [int(s) for s in match.group(1).split(",")]
    if 0 in powers:
        raise InputError.at("library", f"a power 0 in {label!r} is a constant, which no DEL sees")

    def build(n: int, m: int) -> list[Term]:
        _need(label, n, m, vector=True)
        return [Term(f"|q|**{k}", partial(_norm_power, k)) for k in powers]

    return Family(label, build)


@_family(r"log")
def _log(match: re.Match[str], label: str) -> Family:
    def build(n: int, m: int) -> list[Term]:
        _need(label, n, m, vector=True)
        return [Term("log|q|", lambda v: v.xp.log(_norm_squared(v)) / 2)]

    return Family(label, build)


@_family(r"radial")
def _radial(match: re.Match[str], label: str) -> Family:
    """``(q . D_t q)^2``: the squared radial velocity times ``|q|^2``; with ``norm:-5`` the part of Kepler's
    exact-step correction that the Hessian of ``1/|q|`` gives along ``q``."""

    def build(n: int, m: int) -> list[Term]:
        _need(label, n, m, vector=True)
        name = "+".join(f"{component_name(m, i)}*Dt{component_name(m, i)}" for i in range(m))
        return [Term(f"({name})**2", _radial_value)]

    return Family(label, build)


def _radial_value(v: Vars) -> Any:
    return _total([qi * di for qi, di in zip(v.q, v.d[0])]) ** 2


@_family(r"coupledstep")
def _coupledstep(match: re.Match[str], label: str) -> Family:
    """The exact step's ``O(h^2)`` corrections of two pendulums coupled through ``cos(q1 - q2)`` (28 terms): for
    ``L = a Dtq1^2 + b Dtq2^2 + c cos(q1 - q2) Dtq1 Dtq2 - V1(q1) - V2(q2)`` with ``V_i`` in ``trig:1``, the terms
    of ``v.L_qq.v`` and of ``E.adj(M).E`` (``E = L_q - (d L_v/dq) v``), ``1/det M`` taken as a constant
    (docs/discovery.md: the double pendulum)."""

    def build(n: int, m: int) -> list[Term]:
        _need(label, n, m, pair=True)
        return _coupled_step_terms()

    return Family(label, build)


def _cd(v: Vars) -> Any:
    return v.xp.cos(v.q[0] - v.q[1])


def _sd(v: Vars) -> Any:
    return v.xp.sin(v.q[0] - v.q[1])


def _sd2(v: Vars) -> Any:
    return _sd(v) ** 2


def _site_trig(f: str, i: int, v: Vars) -> Any:
    return v.xp.sin(v.q[i]) if f == "sin" else v.xp.cos(v.q[i])


def _dt(i: int, k: int, v: Vars) -> Any:
    return v.d[0][i] ** k if k > 1 else v.d[0][i]


def _mul(*factors: Callable[[Vars], Any]) -> Callable[[Vars], Any]:
    """The product of ``factors`` (left to right)."""

    def value(v: Vars) -> Any:
        out = factors[0](v)
        for f in factors[1:]:
            out = out * f(v)
        return out

    return value


def _coupled_step_terms() -> list[Term]:
    def vel(i: int, k: int) -> str:
        return f"Dtq{i + 1}" + (f"**{k}" if k > 1 else "")

    def trig(f: str, i: int) -> Callable[[Vars], Any]:
        return partial(_site_trig, f, i)

    def dt(i: int, k: int) -> Callable[[Vars], Any]:
        return partial(_dt, i, k)

    trigs = ("sin", "cos")
    out = []
    # v.L_qq.v: the mass's cos(q1 - q2) v1 v2 (v1 - v2)^2 and the potentials' V_i'' v_i^2
    for p, r in ((3, 1), (2, 2), (1, 3)):
        out.append(Term(f"cos(q1-q2)*{vel(0, p)}*{vel(1, r)}", _mul(_cd, dt(0, p), dt(1, r))))
    out += [Term(f"{f}(q{i + 1})*{vel(i, 2)}", _mul(trig(f, i), dt(i, 2))) for i in range(2) for f in trigs]
    # E.adj(M).E: E_1 = -c v2^2 sin(q1 - q2) - V1'(q1), E_2 = c v1^2 sin(q1 - q2) - V2'(q2); the squares ...
    for i, j in ((0, 1), (1, 0)):
        out.append(Term(f"sin(q1-q2)**2*{vel(j, 4)}", _mul(_sd2, dt(j, 4))))
        out += [Term(f"sin(q1-q2)*{f}(q{i + 1})*{vel(j, 2)}", _mul(_sd, trig(f, i), dt(j, 2))) for f in trigs]
        pairs = (("sin", "sin"), ("sin", "cos"), ("cos", "cos"))
        out += [Term(f"{f}(q{i + 1})*{g}(q{i + 1})", _mul(trig(f, i), trig(g, i))) for f, g in pairs]
    # ... and the cross product E_1 E_2 cos(q1 - q2)
    out.append(Term(f"cos(q1-q2)*sin(q1-q2)**2*{vel(0, 2)}*{vel(1, 2)}", _mul(_cd, _sd2, dt(0, 2), dt(1, 2))))
    for i in (1, 0):
        name = "cos(q1-q2)*sin(q1-q2)*{}(q{})*{}"
        out += [Term(name.format(f, i + 1, vel(i, 2)), _mul(_cd, _sd, trig(f, i), dt(i, 2))) for f in trigs]
    out += [Term(f"cos(q1-q2)*{f}(q1)*{g}(q2)", _mul(_cd, trig(f, 0), trig(g, 1))) for f in trigs for g in trigs]
    return out


@_family(r"cross")
def _cross(match: re.Match[str], label: str) -> Family:
    def build(n: int, m: int) -> list[Term]:
        _need(label, n, m, pair=True)
        return [Term("(q1*Dtq2-q2*Dtq1)", lambda v: v.q[0] * v.d[0][1] - v.q[1] * v.d[0][0])]

    return Family(label, build)


@_family(r"(cos|sin)diff")
def _diffs(match: re.Match[str], label: str) -> Family:
    trig = match.group(1)

    def build(n: int, m: int) -> list[Term]:
        _need(label, n, m, vector=True)
        return [
            Term(f"{trig}(q{i + 1}-q{j + 1})", partial(_component_difference, trig, i, j))
            for i, j in itertools.combinations(range(m), 2)
        ]

    return Family(label, build)


# -- evaluation ---------------------------------------------------------------------------------------------
def term_values(terms: Sequence[Term], z: torch.Tensor, spacing: Sequence[float]) -> torch.Tensor:
    """Every term on cells: ``z`` is :meth:`AbstractLagrangian.mean_and_differences` ``(..., n + 1, m)``;
    returns ``(..., len(terms))``."""
    m = z.shape[-1]
    q = [z[..., 0, i] for i in range(m)]
    d = [[z[..., 1 + k, i] / h for i in range(m)] for k, h in enumerate(spacing)]
    v = Vars(q, d, _TorchMath, raw=z[..., 0, :])
    cols = []
    for t in terms:
        value = t.fn(v)
        cols.append(value if isinstance(value, torch.Tensor) else torch.full_like(q[0], float(value)))
    return torch.stack(cols, -1)


def term_forms(terms: Sequence[Term], q: Sequence[Any], d: Sequence[Sequence[Any]]) -> list[Any] | None:
    """Every term's sympy form in the given sympy ``q[i]`` and ``d[k][i]``; None when a term has none."""
    if not all(t.form for t in terms):
        return None
    v = Vars(q, d, _SympyMath())
    return [t.fn(v) for t in terms]
