"""The numeric evaluator agrees with lambdify on every function a spec may call."""

from __future__ import annotations

import numpy as np
import pytest
import sympy as sp

from tvopt_codegen.maths.numeric import Evaluator
from tvopt_codegen.spec.parse import FUNCTIONS

x, y, t = sp.symbols("x y t", real=True)
POINTS = np.linspace(0.15, 0.85, 7)


@pytest.mark.parametrize("name", sorted(FUNCTIONS))
def test_every_spec_function_and_its_derivative(name: str) -> None:
    func, arity = FUNCTIONS[name]
    # acosh lives on [1, oo): shift its argument there.
    args = [x + 1 if name == "acosh" else x, y][:arity]
    expr = func(*args) * (x - y**2) + sp.Rational(3, 7) * func(*args) ** 2
    values = {x: POINTS, y: POINTS[::-1] * 0.5}
    for candidate in (expr, sp.diff(expr, x), sp.diff(expr, x, y)):
        reference = sp.lambdify((x, y), candidate, modules="numpy")(*values.values())
        np.testing.assert_allclose(Evaluator(values)(candidate), reference, rtol=1e-13)


def test_numbers_constants_powers_and_shared_subtrees() -> None:
    shared = sp.tan(x * y + sp.pi / 4)
    exprs = [shared**2 + 1, 1 / shared, sp.sqrt(x) * sp.E, sp.Abs(x - 0.5) * sp.sign(x - 0.5)]
    evaluate = Evaluator({x: POINTS, y: 2.0})
    got = [evaluate(e) for e in exprs]
    reference = sp.lambdify((x, y), exprs, modules="numpy")(POINTS, 2.0)
    for a, b in zip(got, reference, strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-13)


def test_out_of_domain_is_nan_not_an_error() -> None:
    value = Evaluator({x: np.array([-1.0, 4.0])})(sp.sqrt(x) + sp.log(x))
    assert np.isnan(value[0]) and value[1] == pytest.approx(2.0 + np.log(4.0))


def test_program_bindings_and_deep_sums() -> None:
    evaluate = Evaluator({t: np.array([0.0, 1.0])})
    evaluate.define(x, sp.cos(t))
    # 5000 nested levels would overflow a recursive walk.
    deep = x
    for i in range(5000):
        deep = sp.Mul(deep, 1 + t / (i + 1), evaluate=False) if i % 2 else sp.Add(deep, t)
    assert np.all(np.isfinite(evaluate(deep)))
    np.testing.assert_allclose(evaluate(x * 2), 2 * np.cos([0.0, 1.0]))


def test_unknown_symbol_and_function_are_errors() -> None:
    with pytest.raises(ValueError, match="no value for the symbol y"):
        Evaluator({x: 1.0})(x + y)
    with pytest.raises(ValueError, match="cannot evaluate"):
        Evaluator({x: 1.0})(sp.gamma(x))


def test_special_numbers() -> None:
    evaluate = Evaluator({x: 2.0})
    assert evaluate(sp.I * x) == 2j
    assert evaluate(sp.oo + x) == np.inf
    assert np.isnan(evaluate(sp.zoo * x))
    assert evaluate(sp.Rational(1, 3) * x) == pytest.approx(2 / 3)


def test_definitions_are_lazy() -> None:
    evaluate = Evaluator({t: np.array([0.5])})
    evaluate.define(x, sp.cos(t))
    evaluate.define(y, sp.sqrt(z_undefined := sp.Symbol("z", real=True)))  # never needed
    np.testing.assert_allclose(evaluate(x + t), np.cos(0.5) + 0.5)
    with pytest.raises(ValueError, match="no value for the symbol z"):
        evaluate(y + z_undefined)


def test_a_tape_computes_the_evaluators_bits() -> None:
    """Tape (compiled once, run per call) runs Evaluator's operations in its order: the
    same bits, out-of-domain NaN included, for programs, constants and every function."""
    from tvopt_codegen.maths.numeric import Tape

    a, b = sp.symbols("_a _b", real=True)
    p = sp.Symbol("p", real=True)
    definitions = {a: sp.tan(x * y + sp.pi / 4) * p, b: sp.sqrt(x) - a**2 / 3}
    exprs = [
        *(
            func(x + 1 if name == "acosh" else x, y) if arity == 2 else func(x - 0.4 * y + a)
            for name, (func, arity) in sorted(FUNCTIONS.items())
        ),
        b * a + sp.Rational(2, 7) * t**3 - sp.E,
        sp.log(x - 0.5) + 1 / (x - y),
        sp.Abs(b) * sp.sign(x - 0.5) + p,
        sp.Integer(3),
    ]
    tape = Tape([x, y, t], exprs, definitions, {p: 1.5})
    rng = np.random.default_rng(2)
    for _ in range(3):
        xs, ys, ts = rng.uniform(0.1, 0.9, (3, 9))
        evaluate = Evaluator({x: xs, y: ys, t: ts, p: 1.5})
        for symbol, value in definitions.items():
            evaluate.define(symbol, value)
        for expr, got in zip(exprs, tape(xs, ys, ts), strict=True):
            want = evaluate(expr)
            assert np.array_equal(np.asarray(got), np.asarray(want), equal_nan=True), expr
    with pytest.raises(ValueError, match="no value for the symbol q"):
        Tape([x], [x + sp.Symbol("q")], {}, {})
