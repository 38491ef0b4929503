"""The one symbolic API over SymEngine and SymPy, its engine choice and its border."""

from __future__ import annotations

import math
import os
import random
import subprocess
import sys
from typing import Any

import pytest

from tvopt_codegen import __main__ as entry_module
from tvopt_codegen import symbolic as sx
from tvopt_codegen.symbolic import engine
from tvopt_codegen.symbolic.border import from_sympy, to_sympy


def _sample(name: str) -> tuple[sx.Expr, dict[str, float]]:
    """One expression with every kind of node, built on engine ``name``, and a point."""
    with sx.using(name):
        x, y, t = sx.symbols(["x", "y", "t"])
        expr = (
            sx.sin(x) * y**2
            + sx.atan2(x, y) / 3
            + sx.real(0.1) * sx.Piecewise((x, x > 0), (y, True))
            + sx.sqrt(x**2 + 1) * sx.exp(-t)
            + sx.pi * sx.E
            + sx.Rational(2, 7) * sx.cosh(t) ** -1
            + sx.Max(x, y)
            + sx.Abs(y - x)
            + sx.log(1 + t**2)
            + sx.tanh(x * y)
        )
    return expr, {"x": 0.7, "y": -1.3, "t": 0.4}


def _value(expr: sx.Expr, point: dict[str, float]) -> float:
    sp_expr = to_sympy(expr) if not _is_sympy(expr) else expr
    subs = {s: point[s.name] for s in sp_expr.free_symbols}
    return float(sp_expr.xreplace(subs).evalf(30))


def _is_sympy(expr: object) -> bool:
    return type(expr).__module__.startswith("sympy")


def test_both_engines_build_the_same_expression() -> None:
    sympy_expr, point = _sample("sympy")
    symengine_expr, _ = _sample("symengine")
    assert _is_sympy(sympy_expr)
    assert type(symengine_expr).__module__.startswith("symengine")
    with sx.using("symengine"):
        theirs = _value(symengine_expr, point)
    ours = _value(sympy_expr, point)
    assert theirs == pytest.approx(ours, rel=1e-14)
    # By hand, as a third opinion.
    x, y, t = point["x"], point["y"], point["t"]
    hand = (
        math.sin(x) * y**2
        + math.atan2(x, y) / 3
        + 0.1 * x
        + math.sqrt(x**2 + 1) * math.exp(-t)
        + math.pi * math.e
        + 2 / 7 / math.cosh(t)
        + max(x, y)
        + abs(y - x)
        + math.log(1 + t**2)
        + math.tanh(x * y)
    )
    assert ours == pytest.approx(hand, rel=1e-14)


def test_the_border_round_trips_and_keeps_symbols_real() -> None:
    symengine_expr, point = _sample("symengine")
    with sx.using("symengine"):
        crossed = to_sympy(symengine_expr)
        assert all(s.is_real for s in crossed.free_symbols)
        back = from_sympy(crossed)
        assert back == symengine_expr
        # An engine expression passes through, and a matrix crosses entry by entry.
        assert from_sympy(symengine_expr) is symengine_expr
        m = sx.matrix([[sx.symbol("x"), sx.cos(sx.symbol("y"))]])
        assert from_sympy(to_sympy(m)) == m
    assert _value(crossed, point) == pytest.approx(_value(_sample("sympy")[0], point), rel=1e-14)


def test_a_symengine_double_crosses_exactly() -> None:
    with sx.using("symengine"):
        value = 0.1 + 0.2  # not a short decimal
        assert float(to_sympy(sx.real(value))) == value
        assert float(from_sympy(to_sympy(sx.real(value)))) == value


def test_using_returns_to_the_process_engine() -> None:
    before = sx.ENGINE
    # Each engine in turn, whichever is the default: one of them is a real switch.
    for name in engine.ENGINES:
        with sx.using(name):
            assert sx.SYMENGINE == (name == "symengine") and sx.ENGINE == name
            assert type(sx.ZERO).__module__.startswith(name)
            assert type(sx.FUNCTIONS["sin"](sx.symbol("x"))).__module__.startswith(name)
            assert set(sx.FUNCTIONS) >= {"sin", "atan2", "Max"}
        assert sx.ENGINE == before
        assert sx.SYMENGINE == (before == "symengine")
        assert type(sx.ZERO).__module__.startswith(before)
    with pytest.raises(engine.EngineError, match="unknown engine 'maple'"):
        with sx.using("maple"):
            pass
    assert sx.ENGINE == before


def test_piecewise_pairs_and_function_names_agree() -> None:
    for name in engine.ENGINES:
        with sx.using(name):
            x = sx.symbol("x")
            pairs = sx.piecewise_pairs(sx.Piecewise((x, x > 0), (-x, True)))
            assert [str(v) for v, _ in pairs] == ["x", "-x"]
            assert sx.function_name(sx.atan2(x, sx.symbol("y"))) == "atan2"
            assert sx.function_name(sx.Function("f")(x)) == "f"
            assert sx.sort_key(x) == sx.sort_key(sx.symbol("x"))


def test_the_command_line_offers_the_engines_without_loading_one() -> None:
    assert entry_module.ENGINES == engine.ENGINES  # type: ignore[attr-defined]
    done = subprocess.run(
        [sys.executable, "-c", "import sys, tvopt_codegen.cli; print(sorted("
         "m for m in ('sympy', 'symengine', 'tvopt_codegen.symbolic') if m in sys.modules))"],
        capture_output=True, text=True, check=True, timeout=120,
    )  # fmt: skip
    assert done.stdout.strip() == "[]"


@pytest.mark.parametrize(
    ("argv", "env", "message"),
    [
        (["--engine", "maple", "examples"], {}, "argument --engine: invalid choice: 'maple'"),
        (["examples"], {"TVOPT_CODEGEN_ENGINE": "maple"}, "TVOPT_CODEGEN_ENGINE: unknown engine"),
    ],
)
def test_an_unknown_engine_is_one_line_and_exit_2(
    argv: list[str], env: dict[str, str], message: str
) -> None:
    done = subprocess.run(
        [sys.executable, "-m", "tvopt_codegen", *argv],
        capture_output=True,
        text=True,
        env={**os.environ, **env},
        check=False,
        timeout=120,
    )
    assert done.returncode == 2
    assert done.stderr.count("\n") == 1
    assert message in done.stderr


def test_a_user_function_named_like_a_builtin_stays_the_user_s() -> None:
    import sympy as sp

    with sx.using("symengine"):
        x = sp.Symbol("x", real=True)
        crossed = from_sympy(sp.Function("gamma")(x))
        assert sx.function_name(crossed) == "gamma"
        assert crossed != from_sympy(sp.gamma(x))


def test_is_polynomial_cse_and_lambdify_agree_on_both_engines() -> None:
    import itertools

    results = []
    for name in engine.ENGINES:
        with sx.using(name):
            x, y = sx.symbols(["x", "y"])
            polynomial = [
                sx.is_polynomial(e, [x, y])
                for e in (x**2 * y + 3, x / y, sx.sin(x) * y, x ** sx.Rational(1, 2), 2**x)
            ]
            exprs = [sx.sin(x + y) * sx.cos(x + y), (x + y) ** 2 + sx.sin(x + y)]
            names = (sx.symbol(f"_c{i}") for i in itertools.count())
            replacements, reduced = sx.cse(exprs, names)
            # The reduced expressions, with the replacements substituted back in order,
            # are the expressions.
            values = dict(replacements)
            for _ in replacements:
                reduced = [e.xreplace(values) for e in reduced]
            assert [sx.expand(a - b) for a, b in zip(reduced, exprs, strict=True)] == [0, 0]
            assert replacements  # x + y is common
            f = sx.lambdify([x, y], exprs)
            scalar = sx.lambdify([x, y], exprs[0], "math")
            results.append((polynomial, [float(v) for v in f(0.3, -1.1)], float(scalar(0.3, -1.1))))
    assert results[0][0] == results[1][0] == [True, False, False, False, False]
    np = pytest.importorskip("numpy")
    np.testing.assert_allclose(results[0][1], results[1][1], rtol=1e-14)
    assert results[0][2] == pytest.approx(math.sin(-0.8) * math.cos(-0.8), rel=1e-14)
    assert results[1][2] == pytest.approx(results[0][2], rel=1e-14)


def test_symengines_arguments_sort_into_sympys_order_with_exp_and_user_functions() -> None:
    """canonical_key ranks SymEngine's E**x as SymPy's function exp, and a user's
    applied function by its name, as SymPy orders the arguments of sums and products."""
    from tvopt_codegen.symbolic.order import sympy_ordered

    names = ["t", "x", "y", "z"]
    rng = random.Random(7)

    def build() -> list[Any]:
        t, x, y, z = sx.symbols(names)
        f = sx.Function("f")
        leaves = [t, x, y + z, sx.exp(t), sx.exp(x + y), f(x), sx.sin(y), x**2, sx.Integer(3)]
        return [sx.Mul(*rng.sample(leaves, 4)) for _ in range(3)] + [
            sx.Add(*rng.sample(leaves, 4)) for _ in range(3)
        ]

    state = rng.getstate()
    with sx.using("symengine"):
        ours = [[sx.text(a) for a in sympy_ordered(e.args)] for e in build()]
    rng.setstate(state)
    with sx.using("sympy"):
        theirs = [[sx.text(a) for a in e.args] for e in build()]
    assert [sorted(o) for o in ours] == [sorted(t) for t in theirs]  # the same terms
    assert ours == theirs


def test_lambdify_takes_a_batch_of_points_in_a_list_argument_on_both_engines() -> None:
    """A list argument whose entries are arrays (or an array of shape (size, batch)) is a
    batch of points, as SymPy's lambdify takes it; the values are the same on both engines
    (the result's batch axes first, the expressions' shape last)."""
    import numpy as np

    rows = np.array([[1.0, 3.0, -2.0], [2.0, 4.0, 0.5]])
    for engine_name in ("symengine", "sympy"):
        with sx.using(engine_name):
            x, y, t = sx.symbols(["x", "y", "t"])
            f = sx.lambdify([[x, y], t], [x * y + t, sx.sin(x) - y])
            batched = np.asarray(f(rows, 0.5), dtype=float)
            listed = np.asarray(f([rows[0], rows[1]], 0.5), dtype=float)
            single = np.asarray(f([rows[0, 1], rows[1, 1]], 0.5), dtype=float)
        if engine_name == "sympy":  # SymPy's list of per-expression arrays
            batched, listed = batched.T, listed.T
        expected = np.stack([rows[0] * rows[1] + 0.5, np.sin(rows[0]) - rows[1]], -1)
        np.testing.assert_allclose(batched, expected, rtol=1e-15)
        np.testing.assert_allclose(listed, expected, rtol=1e-15)
        np.testing.assert_allclose(single, expected[1], rtol=1e-15)
