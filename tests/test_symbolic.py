"""The closed-form contract: symbols, the default of models with no closed form, and a hand-made form."""

import pytest
import sympy

from latticedft import InputError, MLPLagrangian
from latticedft._symbolic import SymbolicLd, cell_symbols, symbol_name


def test_symbols_are_named_by_point_and_component() -> None:
    syms = cell_symbols(3, 2)
    assert [[str(s) for s in row] for row in syms] == [["u0_0", "u0_1"], ["u1_0", "u1_1"], ["u2_0", "u2_1"]]
    assert symbol_name(1, 1) == "u1_1"
    assert all(s.is_real for row in syms for s in row)


def test_a_form_evaluates_and_prints() -> None:
    (u0,), (u1,), (u2,) = cell_symbols(3, 1)
    expr = (u1 - u0) ** 2 / 2 - (u2 - u0) ** 2 / 2 - sympy.cos(u0)
    form = SymbolicLd(expr=expr, offsets=((0, 0), (1, 0), (0, 1)), m=1, spacing=(0.1, 0.2))
    assert form.flat_symbols() == [u0, u1, u2]
    assert form.evaluate([[0.0], [1.0], [3.0]]) == pytest.approx(0.5 - 4.5 - 1.0)
    assert "\\cos" in form.latex()


def test_a_model_with_no_closed_form_says_so() -> None:
    model = MLPLagrangian()
    assert model.symbolic() is None
    with pytest.raises(InputError, match="no closed form"):
        model.to_sympy()
