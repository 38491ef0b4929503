"""Printers and the IR's rewriting helpers, on hand-made expressions."""

from __future__ import annotations

import numpy as np
import pytest
import sympy as sp

from tvopt_codegen.ir import (
    Arg,
    Kernel,
    Output,
    _substitute,
    canonical_odd,
    ordered_cse,
    split_invariant,
)
from tvopt_codegen.printers import CPrinter, PythonPrinter, PythonScalarPrinter

from .conftest import kernels

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


def test_cse_merges_equal_and_opposite_values() -> None:
    x, y, z = sp.symbols("x y z", real=True)
    a, b1, b2, c, d = (sp.Symbol(n, real=True) for n in ("a", "b1", "b2", "c", "d"))
    # b1 and b2 only become equal once a is named; c is -(x - y) spelled the other way.
    program = [
        (a, sp.tan(x * z)),
        (b1, a**2 + 1),
        (b2, sp.tan(x * z) ** 2 + 1),
        (c, y - x),
        (d, (x - y) * z),
    ]
    body, outs = ordered_cse(program, [b1 * x + b2 * y, c * b2 + d * b1, c * z + d])
    values = [value for _, value in body]
    assert len(values) == len(set(values))
    assert not any(-v in values for v in values)
    point = {x: 0.3, y: -1.2, z: 0.7}
    reference = [b1 * x + b2 * y, c * b2 + d * b1, c * z + d]
    full = dict(program)
    for _ in range(3):
        reference = [e.xreplace(full) for e in reference]
    env = dict(point)
    for sym, value in body:
        env[sym] = float(value.xreplace(env))
    for got, want in zip(outs, reference, strict=True):
        assert float(got.xreplace(env)) == pytest.approx(float(want.xreplace(point)), rel=1e-15)
    # tan once, its square plus one once, and x - y once (y - x is its negation).
    assert len(body) == 3


@pytest.mark.parametrize("spec", ["two_unicycles_barrier", "unicycle_ring", "flexible_joint"])
def test_no_kernel_computes_a_value_twice(spec: str) -> None:
    for kernel in kernels(spec).kernels:
        values = [value for _, value in kernel.body]
        assert len(values) == len(set(values)), kernel.name
        assert not set(values) & {-v for v in values}, kernel.name


def test_split_invariant_hoists_time_terms_out_of_the_state_part() -> None:
    s0, p0 = sp.Symbol("_s0", real=True), sp.Symbol("_p0", real=True)
    t0, t1 = sp.Symbol("_t0", real=True), sp.Symbol("_t1", real=True)
    kernel = Kernel(
        "k",
        "test",
        (Arg("t", (), (), "time"), Arg("s", (s0,), ("x",), "state"), Arg("p", (p0,), ("c",), "")),
        ((t0, sp.tanh(p0 * t)), (t1, s0 * t0)),
        (Output("out", (3,), (s0 + t + 1 + t0 * t, sp.sin(s0 + 2 * t) * t0 * p0, t1 * t), ""),),
        20,
        20,
    )
    split = split_invariant(kernel, "k_time", "time part")
    assert split is not None
    time_part, state_part = split
    assert [a.name for a in time_part.inputs] == ["t", "p"]
    assert state_part.inputs[-1].name == "tau"
    # The state part keeps nothing that depends on time and parameters alone.
    given = {t, p0}
    for expr in [v for _, v in state_part.body] + list(state_part.outputs[0].exprs):
        for node in sp.preorder_traversal(expr):
            if not node.is_Atom and node.free_symbols:
                assert not node.free_symbols <= given | set(state_part.inputs[-1].symbols), node
    # Composed, the two parts are the kernel.
    env = {t: 0.7, s0: -1.3, p0: 0.4}
    for sym, value in time_part.body:
        env[sym] = float(value.xreplace(env))
    for sym, value in zip(state_part.inputs[-1].symbols, time_part.outputs[0].exprs, strict=True):
        env[sym] = float(sp.sympify(value).xreplace(env))
    for sym, value in state_part.body:
        env[sym] = float(value.xreplace(env))
    want = dict(env)
    for sym, value in kernel.body:
        want[sym] = float(value.xreplace(want))
    for got, ref in zip(state_part.outputs[0].exprs, kernel.outputs[0].exprs, strict=True):
        assert float(got.xreplace(env)) == pytest.approx(float(ref.xreplace(want)), rel=1e-14)


def test_the_state_part_of_the_switching_jet_is_small() -> None:
    # unicycle_switch: the tanh switch and the target paths are shared by a batch; per
    # state remain the heading's cos and sin and a few products.
    jet = kernels("unicycle_switch")["jet"]
    assert jet.ops <= 25
    assert kernels("unicycle_switch")["jet_time"].ops >= 100


def test_python_powers_print_alike_for_arrays_and_floats() -> None:

    x, y = sp.symbols("x y")
    array, scalar = PythonPrinter(), PythonScalarPrinter()
    cases = {
        x**2: ("(x*x)", "(x*x)"),
        x**-3: ("1/(x*x*x)", "1.0/(x*x*x)"),
        x**7: ("numpy.power(x, 7)", "float(numpy.power(x, 7.0))"),
        2 * x + 1: ("2*x + 1", "2.0*x + 1.0"),
        sp.sqrt(x): ("numpy.sqrt(x)", "float(numpy.sqrt(x))"),
        x**y: ("numpy.power(x, y)", "float(numpy.power(x, y))"),
        sp.tanh(x) + 1: ("numpy.tanh(x) + 1", "float(numpy.tanh(x)) + 1.0"),
    }
    for expr, (want_array, want_scalar) in cases.items():
        assert array.doprint(expr) == want_array
        assert scalar.doprint(expr) == want_scalar
    # Same bits on both paths: NumPy's own routine, whatever the argument's type.
    values = np.linspace(-3, 3, 101)
    for expr in (x**7, x**3, sp.tanh(x), 2 * x - 3):
        batch = eval(array.doprint(expr), {"numpy": np, "x": values})  # noqa: S307
        single = [
            eval(scalar.doprint(expr), {"numpy": np, "x": float(v)})  # noqa: S307
            for v in values
        ]
        assert np.array_equal(batch, single)
