"""The numeric evaluator agrees with lambdify on every function a spec may call.

The expressions are the default engine's (built through ``sx``); the reference values
are SymPy's ``lambdify`` of the same expressions converted at the border, so the
evaluator is checked against an implementation it shares nothing with.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from tvopt_codegen import symbolic as sx
from tvopt_codegen.maths.numeric import Evaluator
from tvopt_codegen.spec.parse import FUNCTIONS
from tvopt_codegen.symbolic.border import sympy, to_sympy

POINTS = np.linspace(0.15, 0.85, 7)


def xyt() -> list[Any]:
    """The symbols x, y, t of the engine in use (built when a test runs, never at import)."""
    return sx.symbols(["x", "y", "t"])


def reference(args: list[Any], exprs: Any, *values: Any) -> Any:
    """SymPy's NumPy ``lambdify`` of ``exprs`` (the engine's) at ``values``."""
    converted = [to_sympy(e) for e in exprs] if isinstance(exprs, list) else to_sympy(exprs)
    return sympy().lambdify([to_sympy(a) for a in args], converted, modules="numpy")(*values)


@pytest.mark.parametrize("name", sorted(FUNCTIONS))
def test_every_spec_function_and_its_derivative(name: str) -> None:
    x, y, _ = xyt()
    func, arity = FUNCTIONS[name]
    # acosh lives on [1, oo): shift its argument there.
    args = [x + 1 if name == "acosh" else x, y][:arity]
    expr = func(*args) * (x - y**2) + sx.Rational(3, 7) * func(*args) ** 2
    values = {x: POINTS, y: POINTS[::-1] * 0.5}
    for candidate in (expr, sx.diff(expr, x), sx.diff(sx.diff(expr, x), y)):
        want = reference([x, y], candidate, *values.values())
        np.testing.assert_allclose(Evaluator(values)(candidate), want, rtol=1e-13)


def test_numbers_constants_powers_and_shared_subtrees() -> None:
    x, y, _ = xyt()
    shared = sx.tan(x * y + sx.pi / 4)
    exprs = [shared**2 + 1, 1 / shared, sx.sqrt(x) * sx.E, sx.Abs(x - 0.5) * sx.sign(x - 0.5)]
    evaluate = Evaluator({x: POINTS, y: 2.0})
    got = [evaluate(e) for e in exprs]
    for a, b in zip(got, reference([x, y], exprs, POINTS, 2.0), strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-13)


def test_out_of_domain_is_nan_not_an_error() -> None:
    x, _, _ = xyt()
    value = Evaluator({x: np.array([-1.0, 4.0])})(sx.sqrt(x) + sx.log(x))
    assert np.isnan(value[0]) and value[1] == pytest.approx(2.0 + np.log(4.0))


def test_program_bindings_and_deep_sums() -> None:
    x, _, t = xyt()
    evaluate = Evaluator({t: np.array([0.0, 1.0])})
    evaluate.define(x, sx.cos(t))
    # 5000 nested levels would overflow a recursive walk. A product of two sums and a
    # sum of a product and a symbol stay nested on either engine as built.
    chain = [x]
    for i in range(5000):
        chain.append(chain[-1] * (1 + t / (i + 1)) if i % 2 else chain[-1] + t)
    assert all(inner in outer.args for inner, outer in zip(chain, chain[1:], strict=False))
    deep = chain[-1]
    assert np.all(np.isfinite(evaluate(deep)))
    np.testing.assert_allclose(evaluate(x * 2), 2 * np.cos([0.0, 1.0]))


def test_unknown_symbol_and_function_are_errors() -> None:
    x, y, _ = xyt()
    with pytest.raises(ValueError, match="no value for the symbol y"):
        Evaluator({x: 1.0})(x + y)
    with pytest.raises(ValueError, match="cannot evaluate"):
        Evaluator({x: 1.0})(sx.Function("f")(x))


def test_special_numbers() -> None:
    x, _, _ = xyt()
    evaluate = Evaluator({x: 2.0})
    assert evaluate(sx.I * x) == 2j
    assert evaluate(sx.oo + x) == np.inf
    assert np.isnan(evaluate(sx.zoo * x))
    assert evaluate(sx.Rational(1, 3) * x) == pytest.approx(2 / 3)


def test_definitions_are_lazy() -> None:
    x, y, t = xyt()
    evaluate = Evaluator({t: np.array([0.5])})
    evaluate.define(x, sx.cos(t))
    evaluate.define(y, sx.sqrt(z_undefined := sx.symbol("z")))  # never needed
    np.testing.assert_allclose(evaluate(x + t), np.cos(0.5) + 0.5)
    with pytest.raises(ValueError, match="no value for the symbol z"):
        evaluate(y + z_undefined)


def test_a_tape_computes_the_evaluators_bits() -> None:
    """Tape (compiled once, run per call) runs Evaluator's operations in its order: the
    same bits, out-of-domain NaN included, for programs, constants and every function."""
    from tvopt_codegen.maths.numeric import Tape

    x, y, t = xyt()
    a, b, p = sx.symbols(["_a", "_b", "p"])
    definitions = {a: sx.tan(x * y + sx.pi / 4) * p, b: sx.sqrt(x) - a**2 / 3}
    exprs = [
        *(
            func(x + 1 if name == "acosh" else x, y) if arity == 2 else func(x - 0.4 * y + a)
            for name, (func, arity) in sorted(FUNCTIONS.items())
        ),
        b * a + sx.Rational(2, 7) * t**3 - sx.E,
        sx.log(x - 0.5) + 1 / (x - y),
        sx.Abs(b) * sx.sign(x - 0.5) + p,
        sx.Integer(3),
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
        Tape([x], [x + sx.symbol("q")], {}, {})
