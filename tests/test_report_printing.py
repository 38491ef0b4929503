"""The report's own printers (LaTeX, MathML, text) and operation count, against SymPy's.

The report prints either engine's expressions without SymPy
(:mod:`tvopt_codegen.report.printing`). Its LaTeX must be SymPy's ``latex(expr,
order="none", mul_symbol=r"\\,")`` and its text SymPy's ``sstr(expr, order="none")``
character for character, its operation count SymPy's ``count_ops``, on every expression
a real derivation shows; its MathML SymPy's markup (as the report customizes it) where
SymPy keeps the factors in the same order, and the same names and numbers where it
arranges them its own way.
"""

from __future__ import annotations

import functools
import re
from collections.abc import Callable, Iterator
from typing import Any
from xml.etree import ElementTree

import pytest
import sympy as sp

from tvopt_codegen import symbolic as sx
from tvopt_codegen.derivation import Derivation
from tvopt_codegen.report import entries, printing
from tvopt_codegen.report.sections import _shown

from .conftest import derivation, remembered

#: A plain law, signals (tanh, polynomials), a barrier (tan, pi, alpha), a mass-matrix
#: plant (sines and cosines, a_i and W_i,j), an equality, a robot (341 definitions).
SPECS = (
    "integrator",
    "unicycle_switch",
    "two_unicycles_barrier",
    "pvtol",
    "flexible_joint",
    "planar_arm3",
    "arm_on_line",
    "two_unicycles_corridor",
    "ur5_tip",
)
ENGINES = ("symengine", "sympy")


#: Each expression's SymPy form, once per expression and its engine (the four printers'
#: tests read the same expressions, and a SymEngine one crosses the border once, not once
#: per printer: the conversion was a fifth of this file's time).
_as_sympy = remembered(
    entries.as_sympy, key=lambda expr: (type(expr).__module__.split(".")[0], expr)
)


def _remembered(read: Callable[[Any], Any]) -> Callable[[Any], Any]:
    """``read`` of SymPy's form of an expression, worked out once per SymPy expression.

    SymPy's printers are the reference and the dearest part of these tests (a robot's
    590 expressions); both engines' derivations of a spec show the same SymPy
    expressions, so each is printed by SymPy once, not once per engine and test.
    """
    once = remembered(read)
    return lambda expr: once(_as_sympy(expr))


@_remembered
def _sympy_latex(value: Any) -> str:
    return str(sp.latex(value, order="none", mul_symbol=r"\,"))


@_remembered
def _sympy_mathml(value: Any) -> str:
    printer = entries._printer_class()({"order": "none"})
    return str(printer.doprint(value))


@_remembered
def _sympy_text(value: Any) -> str:
    return str(sp.sstr(value, order="none"))


@_remembered
def _sympy_count_ops(value: Any) -> Any:
    return sp.count_ops(value)


def _shown_expressions(d: Derivation) -> Iterator[Any]:
    """Every expression and matrix the report shows of ``d``, and their entries."""
    names = _shown(d)
    matrices = [
        d.model.f.xreplace(names),
        d.model.G.xreplace(names),
        d.model.h,
        d.linearization.R.xreplace(names),
        d.decoupling.p.xreplace(names),
        d.decoupling.phi,
        d.objective.gradient,
        d.hessian,
    ]
    mech = d.model.mechanics
    if mech is not None:
        matrices.append(sx.matrix(mech.mass_matrix).xreplace(names))
        yield from (e.xreplace(names) for _, e in mech.definitions)
    for matrix in matrices:
        yield matrix
        yield from (matrix[i, j] for i in range(matrix.shape[0]) for j in range(matrix.shape[1]))
    yield d.model.f0
    yield from (e for _, e in d.model.signals)
    yield from (c.g for c in (*d.model.constraints, *d.model.equalities))
    if d.decoupling.det_R is not None:
        yield d.decoupling.det_R
    program = d.jet.jet_program + d.jet.rest_program
    for exprs in (*d.jet.grad_jet[1:], d.jet.rest):
        for e in exprs:
            if program.inlined_size(e) < 3000:
                yield program.inline(e)


@functools.cache
def _on(engine: str, name: str) -> tuple[Any, ...]:
    """What the report shows of ``name``'s derivation on ``engine``, listed once for all
    four printers' tests (the robot's inlined jets take a while)."""
    with sx.using(engine):
        return tuple(_shown_expressions(derivation(name)))


@pytest.mark.parametrize("engine", ENGINES)
@pytest.mark.parametrize("name", SPECS)
def test_latex_is_sympys_character_for_character(name: str, engine: str) -> None:
    with sx.using(engine):
        shown = _on(engine, name)
        assert len(shown) > 20
        for expr in shown:
            assert printing.latex(expr) == _sympy_latex(expr), expr


@pytest.mark.parametrize("engine", ENGINES)
@pytest.mark.parametrize("name", SPECS)
def test_text_is_sympys_character_for_character(name: str, engine: str) -> None:
    """The one-line text (a barrier's weight mu(t) and slack s(t)) is SymPy's ``sstr``."""
    with sx.using(engine):
        d = derivation(name)
        exprs = [e for e in _on(engine, name) if not isinstance(e, sx.MatrixBase)]
        if d.model.constraints:
            exprs += [d.model.mu, d.model.slack]
        for expr in exprs:
            assert printing.text(expr) == _sympy_text(expr), expr


@pytest.mark.parametrize("engine", ENGINES)
@pytest.mark.parametrize("name", SPECS)
def test_operation_counts_are_sympys(name: str, engine: str) -> None:
    with sx.using(engine):
        for expr in _on(engine, name):
            if not isinstance(expr, sx.MatrixBase):
                assert printing.count_ops(expr) == _sympy_count_ops(expr), expr


def _leaves(markup: str) -> set[tuple[str, str]]:
    """The names and numbers of MathML markup: (tag, text) of each mi and mn."""
    return set(re.findall(r"<(mi|mn)(?:\s[^>]*)?>([^<]*)<", markup))


@pytest.mark.parametrize("engine", ENGINES)
@pytest.mark.parametrize("name", SPECS)
def test_mathml_has_sympys_names_and_numbers_and_is_well_formed(name: str, engine: str) -> None:
    """SymPy sorts a product's factors by its own key, and its MathML (not its LaTeX)
    distributes a number over a sum in a numerator: the structure may differ, the names
    and numbers may not."""
    with sx.using(engine):
        for expr in _on(engine, name):
            markup = printing.mathml(expr)
            assert _leaves(markup) == _leaves(_sympy_mathml(expr)), expr
            ElementTree.fromstring(f"<math>{re.sub(r'&[A-Za-z]+;', '', markup)}</math>")


def _simple() -> list[Any]:
    """Expressions whose factors SymPy's MathML keeps in their order: identical markup."""
    x, y, theta, q1 = sx.symbols(["x", "y", "theta", "q1"])
    w = sx.symbol("W_2,3")
    return [
        x,
        theta,
        q1,
        w,
        sx.Integer(-3),
        sx.Rational(-3, 4),
        sx.real(0.1),
        sx.real(2.5e-7),
        x + y,
        x - y,
        -x,
        2 * x,
        x / 2,
        -3 * x / 4,
        x / y,
        1 / (x + y),
        x**2,
        x**-2,
        sx.sqrt(x),
        1 / sx.sqrt(x),
        x ** sx.Rational(3, 2),
        (x + y) ** 2,
        sx.sin(theta),
        sx.cos(x) ** 2,
        sx.atan2(y, x),
        sx.Abs(x),
        sx.log(x),
        sx.exp(x),
        sx.tanh((x - y) / 3),
        sx.pi * x,
        sx.matrix([[x, 0], [sx.sin(y), x + y]]),
    ]


@pytest.mark.parametrize("engine", ENGINES)
def test_simple_expressions_print_as_sympy_does_and_the_same_on_both_engines(engine: str) -> None:
    with sx.using(engine):
        printed = [(printing.latex(e), printing.mathml(e)) for e in _simple()]
        expected = [(_sympy_latex(e), _sympy_mathml(e)) for e in _simple()]
        texts = [printing.text(e) for e in _simple()[:-1]]
        assert texts == [sp.sstr(entries.as_sympy(e), order="none") for e in _simple()[:-1]]
    assert printed == expected
    with sx.using("sympy"):
        reference = [(printing.latex(e), printing.mathml(e)) for e in _simple()]
        assert [printing.text(e) for e in _simple()[:-1]] == texts
    assert printed == reference
    assert "0.100000000000000" in texts and "-3*x/4" in texts and "1/sqrt(x)" in texts
    # Some of them, spelled out.
    latex = dict(zip([str(e) for e in _simple()], [t for t, _ in printed], strict=True))
    assert latex[str(sx.real(2.5e-7))] == r"2.5 \cdot 10^{-7}"
    assert r"\operatorname{atan}_{2}{\left(y,x \right)}" in [t for t, _ in printed]
    assert r"\theta" in [t for t, _ in printed]
    assert "W_{2,3}" in [t for t, _ in printed]


def test_a_thin_space_keeps_names_apart_in_mathml() -> None:
    wheelbase, v = sx.symbols(["wheelbase", "v"])
    markup = printing.mathml(wheelbase * sx.cos(v))
    assert '<mo lspace="0.1667em" rspace="0.1667em">&InvisibleTimes;</mo>' in markup
    assert "<mo>&InvisibleTimes;</mo>" in printing.mathml(v * sx.symbol("x"))


def test_a_node_it_does_not_print_falls_back_to_sympy() -> None:
    """Max sorts its arguments by SymPy's key: SymPy prints the whole formula."""
    x, y = sx.symbols(["x", "y"])
    expr = sx.Max(x, y) + x
    with pytest.raises(printing.Unprintable):
        printing.latex(expr)
    math = entries.formula(expr)
    assert math.latex == _sympy_latex(expr)
    assert r"\max\left(x, y\right)" in math.latex


def test_the_report_of_a_robot_imports_no_sympy() -> None:
    """ur5_tip's report (341 definitions, six matrices) prints everything itself.

    ``report ur5_tip`` in a fresh SymEngine process, SymPy's import allowed, and the SymPy
    modules loaded after it: that process is shared with test_det_native's and
    test_engine_det's checks (``engine_cases.sympy_free_run``), whose parts before it
    could not import SymPy.
    """
    from .engine_cases import sympy_free_run

    found, _ = sympy_free_run()
    assert "report failed" not in found, found["report failed"][-2000:]
    assert found["report's sympy modules"] == []
