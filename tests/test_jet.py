"""The gradient jet (jet.py): total derivatives on straight-line programs, the Hessian
by forward mode, and rest, against the paper's formulas and sympy's differentiation."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
import sympy as sp

from tvopt_codegen import symbolic as sx
from tvopt_codegen.derivation import jet_symbol
from tvopt_codegen.maths.jet import (
    Program,
    atomize,
    fresh_symbols,
    next_derivative,
    partial,
    total_derivative,
    without_atoms,
)
from tvopt_codegen.maths.numeric import Evaluator
from tvopt_codegen.symbolic.border import to_sympy

from .conftest import EXAMPLES, derivation
from .oracle import naive_total_derivative


@pytest.mark.parametrize("k", [1, 2, 3, 4])
@pytest.mark.parametrize("seed", [0, 1])
def test_jet_program_matches_the_papers_binomial_formula(k: int, seed: int) -> None:
    """grad^(k) f0 = sum_m C(k-1, m) Hess^(m) y^(k-m) + grad_yt^(k-1) (paper's lemma)."""
    rng = np.random.default_rng(seed)
    t = sx.symbol("t")
    y = [sx.symbol(f"y{i}") for i in range(2)]
    jets = [[jet_symbol(str(yi), j) for j in range(k + 1)] for yi in y]
    c = [sx.Rational(int(v), 10) for v in rng.integers(1, 9, size=6)]
    # A random strongly convex, genuinely time-varying objective.
    f0 = (
        c[0] * (y[0] - sx.sin(c[1] * t)) ** 2
        + c[2] * (y[1] - t**2 / 10) ** 2
        + c[3] * y[0] * y[1] / 10
        + sx.cosh(c[4] * y[0] - c[5] * y[1] * sx.cos(t)) / 5
    )
    grad = [sx.diff(f0, yi) for yi in y]
    rates = {t: sx.Integer(1)} | {ch[j]: ch[j + 1] for ch in jets for j in range(k)}
    names = fresh_symbols("q")
    program, current = atomize(grad, names)
    for _ in range(k):
        new, current, rates = total_derivative(program, current, rates, names)
        program = program + new
    ours = [program.inline(e) for e in current]

    hess = sx.Matrix([[sx.diff(g, yj) for yj in y] for g in grad])
    hess_derivs = [hess]
    grad_t = sx.Matrix([sx.diff(g, t) for g in grad])
    grad_t_derivs = [grad_t]
    for _ in range(k - 1):
        hess_derivs.append(hess_derivs[-1].applyfunc(lambda e: naive_total_derivative(e, t, jets)))
        grad_t_derivs.append(
            grad_t_derivs[-1].applyfunc(lambda e: naive_total_derivative(e, t, jets))
        )
    paper = grad_t_derivs[k - 1]
    for m in range(k):
        paper += math.comb(k - 1, m) * hess_derivs[m] * sx.Matrix([ch[k - m] for ch in jets])

    symbols = [t, *itertools.chain.from_iterable(jets)]
    for _ in range(5):
        point = {s: sx.real(rng.uniform(-1, 1)) for s in symbols}
        a = np.array([float(e.xreplace(point)) for e in ours])
        b = np.array([float(e.xreplace(point)) for e in paper])
        assert np.allclose(a, b, rtol=1e-10, atol=1e-10)


def test_rest_is_grad_k_without_the_hessian_term() -> None:
    """grad^(k) f0 = Hess y^(k) + rest, with rest free of y^(k)."""
    d = derivation("two_unicycles_barrier")
    k = d.dynamics.k
    program = d.jet.jet_program + d.jet.rest_program
    for e in d.jet.rest:
        assert not (program.inline(e).free_symbols & {ch[k] for ch in d.jet.y_jet})


@pytest.mark.parametrize("k", [1, 2, 3])
def test_next_derivative_assigns_no_atom_and_keeps_the_values(k: int) -> None:
    """A rate that atomizes to an atom (a subtree met before, a number) is no assignment.

    ``(y - t)**2 * (y - t)``'s derivative meets ``y - t`` again, and ``t**2 + y``'s
    second derivative is a number: each was an assignment of one atom, walked by every
    pass of lowering. The values are total_derivative's all the same, at random points.
    """
    t, y = sx.symbol("t"), sx.symbol("y")
    jet = [jet_symbol("y", j) for j in range(k + 1)]
    exprs = [(y - t) ** 2 * (y - t) + sx.sin(y - t), t**2 + y * t]
    rates = {t: sx.Integer(1)} | {jet[j]: jet[j + 1] for j in range(k)}
    names = fresh_symbols("q")
    program, current = atomize(exprs, names)
    plain_program, plain, plain_rates = program, current, dict(rates)
    for _ in range(k):
        new, current, rates = next_derivative(program, current, rates, names)
        assert not any(value.is_Atom for _, value in new.assignments)
        program = program + new
        more, plain, plain_rates = total_derivative(plain_program, plain, plain_rates, names)
        plain_program = plain_program + more
    rng = np.random.default_rng(3)
    for _ in range(4):
        point = {s: sx.real(rng.uniform(-1, 1)) for s in [t, *jet]}
        ours = [float(program.inline(e).xreplace(point)) for e in current]
        theirs = [float(plain_program.inline(e).xreplace(point)) for e in plain]
        assert np.allclose(ours, theirs, rtol=1e-12, atol=1e-12)


def test_without_atoms_substitutes_what_an_assignment_of_an_atom_stood_for() -> None:
    a, b, c, d, x = (sx.symbol(n) for n in "abcdx")
    program, outputs = without_atoms(
        [(a, sx.Integer(0)), (b, a), (c, x * b + x), (d, c * c)], [d + b, c]
    )
    assert program.assignments == ((d, x * x),)
    assert outputs == (d, x)


@pytest.mark.parametrize("name", EXAMPLES)
def test_hessian_program_is_the_symbolic_hessian(name: str) -> None:
    """The generated code's Hessian (forward mode over the gradient program) against
    sympy's differentiation of the gradient, at random points."""
    d = derivation(name)
    model = d.model
    m = len(model.y)
    rng = np.random.default_rng(3)
    values: dict[sx.Expr, object] = {y: rng.uniform(-2, 2, size=5) for y in model.y}
    values |= {q: float(v) for q, v in zip(model.params, model.defaults, strict=True)}
    values[model.t] = rng.uniform(0, 10, size=5)
    evaluate = Evaluator(values)
    for symbol, expr in model.signals:
        evaluate.define(symbol, expr)
    for symbol, expr in (d.jet.jet_program + d.objective.hessian_program).assignments:
        evaluate.define(symbol, expr)
    entries = dict(d.objective.hessian_entries)
    assert all(i >= j for i, j in entries)
    for i in range(m):
        for j in range(m):
            ours = entries.get((max(i, j), min(i, j)), 0)
            reference = evaluate(d.hessian[i, j])
            np.testing.assert_allclose(evaluate(ours), reference, rtol=1e-11, atol=1e-12)
            if d.hessian[i, j] == 0:
                assert (max(i, j), min(i, j)) not in entries


def _random_expression(rng: np.random.Generator, symbols: list[sp.Symbol], depth: int) -> sp.Expr:
    if depth == 0 or rng.random() < 0.2:
        choice = rng.integers(0, len(symbols) + 1)
        return symbols[choice] if choice < len(symbols) else sp.Rational(int(rng.integers(1, 7)), 3)
    kind = rng.integers(0, 6)
    a = _random_expression(rng, symbols, depth - 1)
    b = _random_expression(rng, symbols, depth - 1)
    if kind == 0:
        return a + b
    if kind == 1:
        return a * b
    if kind == 2:
        return a ** int(rng.integers(-3, 4))
    if kind == 3:
        return a - 2 * b
    functions = (sp.sin, sp.cos, sp.tan, sp.exp, sp.tanh, sp.atan, sp.cosh, sp.log, sp.sqrt)
    return functions[int(rng.integers(0, len(functions)))](a)


# SymPy's own forms: on SymPy, partial's fast rules must build what sympy's diff builds
# (the goldens depend on it); on SymEngine partial is SymEngine's diff, with its own forms.
@pytest.mark.engine("sympy")
@pytest.mark.parametrize("seed", range(200))
def test_partial_builds_what_sympys_diff_builds(seed: int) -> None:
    """The fast rules give sympy's own expression, not just an equal value: the generated
    code (and its goldens) depend on the form."""
    rng = np.random.default_rng(seed)
    symbols = list(sp.symbols("x y z", real=True))
    expr = _random_expression(rng, symbols, 4)
    for var in symbols:
        assert partial(expr, var) == sp.diff(expr, var), (expr, var)
    x, y = symbols[:2]
    assert partial(x**y, x) == sp.diff(x**y, x)  # a symbolic exponent: sympy's rule


def _signal_shapes(t: sx.Expr, a: sx.Expr, b: sx.Expr) -> list[sx.Expr]:
    """The usual shapes of a signal's argument, on the engine in use."""
    return [(t - a) / b, 2 * sx.pi * t / 7 + a, sx.real(0.3) * t**2 - 1]


def _signals(t: sx.Expr, a: sx.Expr, b: sx.Expr) -> list[tuple[str, sx.Expr]]:
    """Every function a spec may call, applied to every shape, as a signal of t."""
    from tvopt_codegen.spec.parse import FUNCTIONS

    return [
        (name, b * func(shape, t + 1) if arity == 2 else b * func(shape) + sx.real(0.2) * t)
        for name, (func, arity) in FUNCTIONS.items()
        for shape in _signal_shapes(t, a, b)
    ]


@pytest.mark.engine("sympy")
def test_signal_chains_are_sympys_derivatives() -> None:
    """The derivation differentiates signals with partial: for every function a spec may
    call, four orders of the usual signal shapes are sympy's diff, expression for expression."""
    t, a, b = sx.symbols(["t", "a", "b"])
    for name, signal in _signals(t, a, b):
        ours = theirs = signal
        for _ in range(4):
            ours, theirs = partial(ours, t), sp.diff(theirs, t)
            assert ours == theirs, (name, signal)


def test_signal_chains_have_sympys_values_on_the_default_engine() -> None:
    """The same four orders on the default engine: equal in value to sympy's diff of the
    same signal (the forms may differ), at a point inside every function's domain."""
    t, a, b = sx.symbols(["t", "a", "b"])
    point = {to_sympy(t): 0.4, to_sympy(a): 0.35, to_sympy(b): 1.3}
    for name, signal in _signals(t, a, b):
        ours, theirs = signal, to_sympy(signal)
        for order in range(1, 5):
            ours, theirs = partial(ours, t), sp.diff(theirs, to_sympy(t))
            got = complex(to_sympy(ours).xreplace(point).evalf())
            want = complex(theirs.xreplace(point).evalf())
            assert np.isclose(got, want, rtol=1e-9, atol=1e-12), (name, signal, order)


@pytest.mark.engine("sympy")
def test_partial_leaves_functions_with_their_own_rule_to_sympy() -> None:
    x, y = sp.symbols("x y", real=True)
    for expr in (sp.Abs(x * y), sp.sign(x - y), sp.sign(x) * sp.Abs(x) ** 2):
        assert partial(expr, x) == sp.diff(expr, x), expr
    assert not partial(sp.sign(x), x).has(sp.Derivative)


def test_partial_differentiates_abs_and_sign_where_they_are_defined() -> None:
    """SymEngine leaves Abs and sign underived: partial's own rules give Abs(u)' =
    sign(u) u' and sign(u)' = 0, sympy's diff wherever u != 0 (its DiracDelta is 0
    there), and no Derivative for a later stage to choke on."""
    x, y = sx.symbols(["x", "y"])
    exprs = (sx.Abs(x * y), sx.sign(x - y), sx.sign(x) * sx.Abs(x) ** 2, sx.Abs(sx.sin(x) - y))
    if sx.SYMENGINE:
        # SymEngine's own rules (SymPy's diff writes sign' as 2*DiracDelta, zero here too).
        assert partial(exprs[0], x) == sx.sign(x * y) * y
        assert partial(exprs[1], x) == 0
    rng = np.random.default_rng(5)
    for expr in exprs:
        ours = partial(expr, x)
        assert "Derivative" not in sx.text(ours), expr
        theirs = sp.diff(to_sympy(expr), to_sympy(x))
        for _ in range(5):
            values = {x: sx.real(rng.uniform(-2, 2)), y: sx.real(rng.uniform(-2, 2))}
            crossed = {to_sympy(s): to_sympy(v) for s, v in values.items()}
            got = float(ours.xreplace(values))
            want = float(theirs.xreplace(crossed).evalf())
            assert np.isclose(got, want, rtol=1e-12, atol=1e-12), (expr, values)


@pytest.mark.parametrize("name", ["unicycle_switch", "pvtol", "two_unicycles_barrier"])
def test_inlining_once_per_assignment_gives_the_expressions_of_inlining_one_by_one(
    name: str,
) -> None:
    d = derivation(name)
    program = d.jet.jet_program + d.jet.rest_program

    def one_by_one(expr: sp.Expr) -> sp.Expr:
        for sym, value in reversed(program.assignments):
            expr = expr.xreplace({sym: value})
        return expr

    for expr in [*d.jet.grad_jet[1], *d.jet.rest]:
        assert program.inline(expr) == one_by_one(expr)


def test_the_inlined_size_counts_every_read_without_building() -> None:
    x, y, a, b = sx.symbols(["x", "y", "a", "b"])
    program = Program(((a, x + y), (b, a * sx.sin(a))))
    # a: Add(x, y) is 3 nodes; b: Mul(a, sin(a)) is 1 + 3 + (1 + 3); b + x: 1 + 8 + 1.
    assert program.inlined_size(b + x) == 10
    assert program.inlined_size(x) == 1
    assert program.inline(b + x) == (x + y) * sx.sin(x + y) + x
