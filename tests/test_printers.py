"""Printers and the IR's rewriting helpers, on hand-made expressions."""

from __future__ import annotations

import sympy as sp

from tvopt_codegen.ir import _substitute, canonical_odd
from tvopt_codegen.printers import CPrinter, PythonPrinter

t, x, y, a = sp.symbols("t x y a", real=True)


def test_sums_start_positive_and_end_with_their_constant() -> None:
    py, c = PythonPrinter(), CPrinter()
    assert py.doprint(1 - x) == "1 - x"
    assert py.doprint(t - 25) == "t - 25"
    assert py.doprint(sp.Rational(1, 2) - sp.tanh((t - a) / x) / 2) == (
        "1/2 - 1/2*numpy.tanh((t - a)/x)"
    )
    assert py.doprint(-x - y - 3) == "-x - y - 3"
    assert c.doprint(x * y - 2 * t + 10) == "x*y - 2*t + 10"
    # Equal expressions print equally however they were built.
    assert py.doprint(sp.Add(y, -x, 4)) == py.doprint(sp.Add(4, -x, y)) == "y - x + 4"


def test_substitute_keeps_functions_unevaluated_but_folds_numbers() -> None:
    expr = sp.tan(sp.pi * x / (2 * a)) ** 2 + sp.sin(y)
    s0, p0 = sp.symbols("_s0 _p0", real=True)
    out = _substitute(expr, {x: s0, a: p0, y: sp.Integer(0)})
    assert out == sp.tan(sp.pi * s0 / (2 * p0)) ** 2
    assert out.equals(expr.xreplace({x: s0, a: p0, y: 0}))


def test_canonical_odd_merges_mirrored_arguments_once() -> None:
    memo: dict[sp.Basic, sp.Expr] = {}
    first = canonical_odd(sp.tanh((a - t) / x), memo)
    second = canonical_odd(sp.tanh((t - a) / x), memo)
    assert {first, second} == {sp.tanh((t - a) / x), -sp.tanh((t - a) / x)}
    assert first == -second
    # Shared memo: a second pass over the same node is a lookup.
    assert canonical_odd(sp.tanh((a - t) / x) + y, memo) == first + y
