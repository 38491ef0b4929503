"""The mathematics (jet, lie, sparse, numeric) on both engines: SymEngine's results are
SymPy's numbers.

Each test builds its input on SymPy (by hand, or an example spec's objective),
converts it with the border's ``from_sympy`` under ``sx.using("symengine")``, runs the
same function on each engine and compares the values at random points to 1e-12
relative, each engine's expressions evaluated by its own :class:`Evaluator`. Both
engines are named (``sx.using("sympy")`` for the reference): none of the tests relies
on which one is the process's default.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable, Iterator, Mapping, Sequence
from typing import Any

import numpy as np
import pytest
import sympy as sp

from tvopt_codegen import symbolic as sx
from tvopt_codegen.derivation import jet_symbol
from tvopt_codegen.maths.jet import (
    Program,
    atomize,
    fresh_symbols,
    jacobian,
    next_derivative,
    partial,
)
from tvopt_codegen.maths.lie import (
    Sampler,
    brunovsky,
    control_affine,
    extend,
    from_entries,
    generic_rank,
    nonzero_entries,
    relative_degree,
)
from tvopt_codegen.maths.numeric import Evaluator, Tape
from tvopt_codegen.maths.sparse import cholesky_program, ldl_program
from tvopt_codegen.spec.parse import FUNCTIONS
from tvopt_codegen.symbolic.border import from_sympy, to_sympy

from .conftest import derivation

RTOL = 1e-12
POINTS = 6


def _symengine(value: Any) -> Any:
    """A SymPy expression, matrix, or nested tuples and lists and dicts of them, on SymEngine."""
    memo: dict[Any, Any] = {}

    def convert(item: Any) -> Any:
        if isinstance(item, dict):
            return {convert(k): convert(v) for k, v in item.items()}
        if isinstance(item, list | tuple):
            return type(item)(convert(v) for v in item)
        if isinstance(item, sp.Basic | sp.MatrixBase):
            return from_sympy(item, memo)
        return item

    with sx.using("symengine"):
        return convert(value)


def _values(
    names: Sequence[str], rng: np.random.Generator, low: float = 0.3, high: float = 1.2
) -> dict[str, np.ndarray]:
    """Random points for each symbol name, away from 0 (one array of ``POINTS`` each)."""
    return {name: rng.uniform(low, high, size=POINTS) for name in sorted(set(names))}


def _evaluate(
    exprs: Sequence[Any],
    values: Mapping[str, np.ndarray],
    program: Sequence[tuple[Any, Any]] = (),
) -> list[np.ndarray]:
    """The values of ``exprs`` (over ``program``'s symbols) on the current engine."""
    evaluator = Evaluator({sx.symbol(name): value for name, value in values.items()})
    for symbol, expr in program:
        evaluator.define(symbol, expr)
    return [np.broadcast_to(np.asarray(evaluator(e), dtype=complex), (POINTS,)) for e in exprs]


def _close(sympy_values: Sequence[np.ndarray], symengine_values: Sequence[np.ndarray]) -> None:
    assert len(sympy_values) == len(symengine_values)
    for a, b in zip(sympy_values, symengine_values, strict=True):
        assert np.all(np.isfinite(a))
        np.testing.assert_allclose(b, a, rtol=RTOL, atol=RTOL * max(1.0, np.abs(a).max()))


def _names(*exprs: Any) -> list[str]:
    return [s.name for e in exprs for s in sp.sympify(e).free_symbols]


# --- jet ----------------------------------------------------------------------------------

T = sp.Symbol("t", real=True)
Y = sp.symbols("y0 y1", real=True)
A, B = sp.symbols("a b", real=True)


def _objective() -> sp.Expr:
    """A time-varying objective with every kind of node the jet differentiates."""
    return (
        (Y[0] - sp.sin(T / 3) * A) ** 2
        + sp.Rational(3, 2) * (Y[1] - sp.atan2(T, 2 + Y[0])) ** 2
        + sp.exp(Y[0] * Y[1] / 5) * sp.cos(T)
        + sp.log(2 + Y[1] ** 2) * sp.sqrt(1 + T**2)
        + sp.cosh(B * Y[0] - Y[1] * sp.tanh(T)) / 7
        + sp.Float(0.25) * Y[0] * Y[1] * T**3
    )


def _jet(
    gradient: Sequence[Any], k: int
) -> tuple[Program, list[tuple[Any, ...]], tuple[tuple[Any, ...], ...]]:
    """The gradient jet up to order ``k`` on the current engine, as the derivation takes it."""
    names: Iterator[Any] = fresh_symbols("_g")
    y = [sx.symbol(f"y{i}") for i in range(2)]
    chains = tuple(tuple(jet_symbol(v.name, j) for j in range(k + 1)) for v in y)
    rates: dict[Any, Any] = {sx.symbol("t"): sx.Integer(1)}
    for chain in chains:
        for j in range(k):
            rates[chain[j]] = chain[j + 1]
    program, current = atomize(list(gradient), names)
    jet = [tuple(current)]
    for _ in range(k):
        new, current, rates = next_derivative(program, current, rates, names)
        program = program + new
        jet.append(tuple(current))
    return program, jet, chains


def test_jet_symbols_are_engine_symbols() -> None:
    """jet_symbol and fresh_symbols build the current engine's symbols."""
    with sx.using("symengine"):
        assert isinstance(next(fresh_symbols("q")), sx.Symbol)
        assert isinstance(jet_symbol("y", 2), sx.Symbol)
    with sx.using("sympy"):
        assert next(fresh_symbols("q")) == sp.Symbol("q0", real=True)


def test_gradient_jet_agrees_on_both_engines() -> None:
    """grad^(j) f0, j <= 4, of a time-varying objective: the same values at random points."""
    f0 = _objective()
    gradient = [sp.diff(f0, v) for v in Y]
    k = 4
    with sx.using("sympy"):
        program, jet, chains = _jet(gradient, k)
        names = _names(f0) + [s.name for chain in chains for s in chain]
        values = _values(names, np.random.default_rng(0))
        expected = _evaluate([e for level in jet for e in level], values, program.assignments)
    gradient_se = _symengine(gradient)
    with sx.using("symengine"):
        program_se, jet_se, _ = _jet(gradient_se, k)
        got = _evaluate([e for level in jet_se for e in level], values, program_se.assignments)
    _close(expected, got)
    # The jet grows by a small factor per order on SymEngine too (no expansion).
    assert len(program_se.assignments) < 2 * len(program.assignments)


def test_hessian_by_forward_mode_agrees_on_both_engines() -> None:
    f0 = _objective()
    gradient = [sp.diff(f0, v) for v in Y]

    def hessian(grad: Sequence[Any]) -> tuple[Program, list[Any]]:
        names = fresh_symbols("_h")
        program, current = atomize(list(grad), names)
        variables = [sx.symbol(v.name) for v in Y]
        new, columns = jacobian(program, current, variables, names)
        entries = [columns[i].get(j, sx.Integer(0)) for i in range(2) for j in range(2)]
        return program + new, entries

    values = _values(_names(f0), np.random.default_rng(1))
    with sx.using("sympy"):
        program, entries = hessian(gradient)
        expected = _evaluate(entries, values, program.assignments)
        reference = _evaluate([sp.diff(f0, a, b) for a in Y for b in Y], values)
    _close(reference, expected)
    gradient_se = _symengine(gradient)
    with sx.using("symengine"):
        program_se, entries_se = hessian(gradient_se)
        got = _evaluate(entries_se, values, program_se.assignments)
    _close(expected, got)


def test_partial_of_abs_and_sign_on_symengine() -> None:
    """SymEngine leaves Abs underived: d|u|/dx = sign(u) du/dx, as SymPy's; sign' = 0."""
    x, y = sp.symbols("x y", real=True)
    u = x * y - sp.sin(x)
    exprs = [sp.Abs(u) * sp.exp(x), sp.sqrt(x**2 + y**2) * sp.Abs(x - 2 * y), sp.atan2(y, x)]
    values = {"x": np.linspace(0.3, 1.4, POINTS), "y": np.linspace(-0.9, 0.8, POINTS)}
    with sx.using("sympy"):
        expected = _evaluate([partial(e, x) for e in exprs], values)
    with sx.using("symengine"):
        x_se = sx.symbol("x")
        derived = [partial(e, x_se) for e in _symengine(exprs)]
        assert not any(d.atoms(sx.Derivative) for d in derived)
        got = _evaluate(derived, values)
        assert partial(sx.sign(x_se * 3) * x_se, x_se) == sx.sign(3 * x_se)
    _close(expected, got)


# --- lie ----------------------------------------------------------------------------------


def _unicycle() -> tuple[Any, ...]:
    x1, x2, theta, v, omega = sp.symbols("x1 x2 theta v omega", real=True)
    f = sp.ImmutableMatrix([0, 0, 0])
    G = sp.ImmutableMatrix([[sp.cos(theta), 0], [sp.sin(theta), 0], [0, 1]])
    h = sp.ImmutableMatrix([x1 + sp.Rational(1, 2) * sp.cos(theta), x2])
    return (x1, x2, theta), (v, omega), f, G, h, {"v": 1}


def _pvtol() -> tuple[Any, ...]:
    """The planar VTOL aircraft (Hauser, Sastry and Meyer), thrust prolonged twice."""
    x, z, theta, xd, zd, thetad = sp.symbols("x z theta xd zd thetad", real=True)
    u1, u2 = sp.symbols("u1 u2", real=True)
    eps, g = sp.Rational(1, 10), sp.Float(9.81)
    f = sp.ImmutableMatrix([xd, zd, thetad, 0, -g, 0])
    G = sp.ImmutableMatrix(
        [
            [0, 0],
            [0, 0],
            [0, 0],
            [-sp.sin(theta), eps * sp.cos(theta)],
            [sp.cos(theta), eps * sp.sin(theta)],
            [0, 1],
        ]
    )
    h = sp.ImmutableMatrix([x - eps * sp.sin(theta), z + eps * sp.cos(theta)])
    return (x, z, theta, xd, zd, thetad), (u1, u2), f, G, h, {"u1": 2}


def _linearize(system: tuple[Any, ...]) -> tuple[Any, Any, int, list[tuple[int, int, Any]]]:
    """Extension, relative degree, generic rank of R and R's entries on the current engine."""
    x, u, f, G, h, counts = system
    ext = extend(x, u, f, G, counts)
    sampler = Sampler(ext.x, {})
    rd = relative_degree(ext.f, ext.G, h, ext.x, sampler)
    assert rd.R is not None
    return ext, rd, generic_rank(rd.R, sampler), nonzero_entries(rd.R)


@pytest.mark.parametrize("make", [_unicycle, _pvtol], ids=["unicycle", "pvtol"])
def test_relative_degree_and_generic_rank_agree_on_both_engines(
    make: Callable[[], tuple[Any, ...]],
) -> None:
    system = make()
    with sx.using("sympy"):
        ext, rd, rank, entries = _linearize(system)
    converted = _symengine(system)
    with sx.using("symengine"):
        ext_se, rd_se, rank_se, entries_se = _linearize(converted)
        assert isinstance(ext_se.f, sx.MatrixBase) and isinstance(ext_se.x[0], sx.Symbol)
    assert ext_se.states == ext.states and ext_se.inputs == ext.inputs
    assert [s.name for s in ext_se.x] == [s.name for s in ext.x]
    assert rd_se.r == rd.r and rank_se == rank >= 1
    assert [(i, j) for i, j, _ in entries_se] == [(i, j) for i, j, _ in entries]
    values = _values([s.name for s in ext.x], np.random.default_rng(2), -1.2, 1.2)
    lie = [e for chain in rd.lie for e in chain]
    lie_se = [e for chain in rd_se.lie for e in chain]
    drift = list(ext.f) + list(ext.G)
    with sx.using("sympy"):
        expected = _evaluate([*lie, *(e for _, _, e in entries), *drift], values)
    with sx.using("symengine"):
        drift_se = list(ext_se.f) + list(ext_se.G)
        got = _evaluate([*lie_se, *(e for _, _, e in entries_se), *drift_se], values)
    _close(expected, got)


def test_a_singular_decoupling_matrix_has_the_same_generic_rank() -> None:
    """The raw unicycle's R = [[cos, 0], [sin, 0]] has rank 1 on both engines."""
    x, u, f, G, h, _ = _unicycle()
    system = (x, u, f, G, sp.ImmutableMatrix(list(x[:2])))
    ranks = []
    for engine, (xs, _us, fs, Gs, hs) in (("sympy", system), ("symengine", _symengine(system))):
        with sx.using(engine):
            sampler = Sampler(xs, {})
            rd = relative_degree(fs, Gs, hs, xs, sampler)
            assert rd.r == (1, 1) and rd.R is not None
            ranks.append(generic_rank(rd.R, sampler))
    assert ranks == [1, 1]


def test_matrices_of_entries_and_brunovsky_agree_on_both_engines() -> None:
    x1, x2, u1, u2 = sp.symbols("x1 x2 u1 u2", real=True)
    entries = {(0, 1): sp.sin(x1), (2, 0): x1 * x2, (1, 1): sp.Float(0.5)}
    f = [x2, -x1, sp.Integer(0)]
    with sx.using("sympy"):
        a, b = brunovsky([3, 1, 2])
        dense = from_entries(3, 2, entries)
        affine = control_affine(sp.ImmutableMatrix(f), dense, [u1, u2])
    converted = _symengine((entries, f, [u1, u2]))
    with sx.using("symengine"):
        a_se, b_se = brunovsky([3, 1, 2])
        dense_se = from_entries(3, 2, converted[0])
        found = nonzero_entries(dense_se)
        affine_se = control_affine(sx.ImmutableMatrix(converted[1]), dense_se, converted[2])
        assert nonzero_entries(sx.zeros(3, 4)) == []
        assert to_sympy(a_se) == a and to_sympy(b_se) == b
        assert [(i, j) for i, j, _ in found] == sorted(set(entries) - {(59, 39)})
    values = _values(["x1", "x2", "u1", "u2"], np.random.default_rng(3))
    with sx.using("sympy"):
        expected = _evaluate(affine, values)
    with sx.using("symengine"):
        got = _evaluate(affine_se, values)
    _close(expected, got)


def test_an_exact_constant_is_decided_by_simplification_on_both_engines() -> None:
    """A constant Lie derivative crosses the border to SymPy's simplify (a small one)."""
    zero = sp.sin(sp.pi / 7) ** 2 + sp.cos(sp.pi / 7) ** 2 - 1
    nonzero = sp.sqrt(2) - sp.Rational(7, 5)
    converted = _symengine([zero, nonzero])
    with sx.using("symengine"):
        sampler = Sampler([sx.symbol("x")], {})
        assert sampler.is_zero(converted[0]) and not sampler.is_zero(converted[1])
        assert sampler.is_zero(sx.Integer(0))
    with sx.using("sympy"):
        sampler = Sampler([sp.Symbol("x", real=True)], {})
        assert sampler.is_zero(zero) and not sampler.is_zero(nonzero)


SPECS = ["pvtol", "two_unicycles_barrier"]


def _spec_jet(gradient: Sequence[Any], jets: Sequence[Sequence[Any]], k: int) -> tuple[Any, ...]:
    """A spec's gradient jet to order ``k - 1`` on the current engine, along its jets."""
    names: Iterator[Any] = fresh_symbols("_e")
    rates: dict[Any, Any] = {sx.symbol("t"): sx.Integer(1)}
    for chain in jets:
        for j in range(k):
            rates[sx.symbol(chain[j].name)] = sx.symbol(chain[j + 1].name)
    program, current = atomize(list(gradient), names)
    jet = [tuple(current)]
    for _ in range(k - 1):
        new, current, rates = next_derivative(program, current, rates, names)
        program = program + new
        jet.append(tuple(current))
    return program, jet


@pytest.mark.parametrize("spec", SPECS)
def test_an_example_specs_jet_is_the_derivations_on_both_engines(spec: str) -> None:
    """The derivation's grad^(j) f0 (SymPy), and the jet of its gradient on each engine."""
    with sx.using("sympy"):
        d = derivation(spec)
    k = len(d.jet.grad_jet)
    jets = [*d.jet.y_jet, *d.jet.signal_jet]
    rng = np.random.default_rng(5)
    values = _values([s.name for chain in jets for s in chain] + ["t"], rng, -1.0, 1.0)
    values |= {
        p.name: np.full(POINTS, v) for p, v in zip(d.model.params, d.model.defaults, strict=True)
    }
    # Away from the barrier's singular set: the outputs where the spec starts, moved a little.
    for y, start in zip(d.model.y, d.model.h, strict=True):
        initial = dict(zip(d.model.x, d.closed_loop.initial_state, strict=False))
        values[y.name] = float(start.subs(initial)) + rng.uniform(-0.1, 0.1, POINTS)
    flat = [e for level in d.jet.grad_jet for e in level]
    gradient = list(d.objective.gradient)
    with sx.using("sympy"):
        reference = _evaluate(flat, values, d.jet.jet_program.assignments)
        program, jet = _spec_jet(gradient, jets, k)
        expected = _evaluate([e for level in jet for e in level], values, program.assignments)
    _close(reference, expected)
    converted = _symengine(gradient)
    with sx.using("symengine"):
        program_se, jet_se = _spec_jet(converted, jets, k)
        got = _evaluate([e for level in jet_se for e in level], values, program_se.assignments)
    _close(expected, got)


@pytest.mark.parametrize("spec", SPECS)
def test_an_example_specs_relative_degree_is_the_derivations_on_both_engines(spec: str) -> None:
    with sx.using("sympy"):
        d = derivation(spec)
    m = d.model
    counts = dict(d.linearization.extension.counts)
    fixed = dict(zip(m.params, m.defaults, strict=True))
    system = (m.x, m.u, m.f, m.G, m.h, fixed)
    results = []
    for engine, (x, u, f, G, h, params) in (("sympy", system), ("symengine", _symengine(system))):
        with sx.using(engine):
            ext = extend(x, u, f, G, counts)
            sampler = Sampler(ext.x, params)
            rd = relative_degree(ext.f, ext.G, h, ext.x, sampler)
            assert rd.R is not None
            rank = generic_rank(rd.R, sampler)
            names = [s.name for s in ext.x] + [p.name for p in params]
            values = _values(names, np.random.default_rng(6), -1.2, 1.2)
            values |= {p.name: np.full(POINTS, v) for p, v in params.items()}
            exprs = [e for chain in rd.lie for e in chain] + [
                e for _, _, e in nonzero_entries(rd.R)
            ]
            results.append((rd.r, rank, _evaluate(exprs, values)))
    (r, rank, expected), (r_se, rank_se, got) = results
    assert r == r_se == d.linearization.relative_degree
    assert rank == rank_se == len(r)
    _close(expected, got)


# --- sparse -------------------------------------------------------------------------------


def _ldl(pattern: list[tuple[int, int]], m: int, leading: int | None) -> tuple[Any, ...]:
    h = [sx.symbol(f"h{i}_{j}") for i, j in pattern]
    c = [[sx.symbol(f"c{r}_{i}") for i in range(m)] for r in range(2)]
    return ldl_program(pattern, m, h, c, leading), cholesky_program(pattern, m, h, c[0])


@pytest.mark.parametrize("leading", [None, 3])
def test_ldl_programs_solve_the_same_systems_on_both_engines(leading: int | None) -> None:
    """A sparse symmetric matrix (an arrow and a band): both engines' programs solve it."""
    m = 6
    rng = np.random.default_rng(4)
    lower = {(i, i) for i in range(m)} | {(i + 1, i) for i in range(m - 1)} | {(m - 1, 0)}
    pattern = sorted(lower)
    dense = np.zeros((POINTS, m, m))
    for i, j in pattern:
        # A positive definite matrix at every point (diagonally dominant); with leading,
        # the second block negative definite, as a KKT matrix's.
        value = rng.uniform(-1.0, 1.0, size=POINTS)
        if i == j:
            value = (4.0 + rng.uniform(size=POINTS)) * (-1 if leading and i >= leading else 1)
        dense[:, i, j] = dense[:, j, i] = value
    rhs = rng.uniform(-1.0, 1.0, size=(2, POINTS, m))
    values = {f"h{i}_{j}": dense[:, i, j] for i, j in pattern}
    values |= {f"c{r}_{i}": rhs[r, :, i] for r in range(2) for i in range(m)}
    results = []
    for engine in ("sympy", "symengine"):
        with sx.using(engine):
            (program, solutions, pivots), (chol, z, chol_pivots) = _ldl(pattern, m, leading)
            outputs = [*solutions[0], *solutions[1], *pivots]
            results.append(_evaluate(outputs, values, program))
            single = _evaluate([*z, *chol_pivots], values, chol)
            _close(results[-1][:m] + results[-1][2 * m :], single)
            assert len(program) == len(_ldl(pattern, m, leading)[0][0])
    _close(*results)
    solved = np.linalg.solve(dense, rhs[0][..., None])[..., 0]
    np.testing.assert_allclose(np.array(results[0][:m]).T.real, solved, rtol=1e-10)


# --- numeric ------------------------------------------------------------------------------


@pytest.mark.parametrize("name", sorted(FUNCTIONS))
def test_every_spec_function_evaluates_alike_on_both_engines(name: str) -> None:
    """Each function a spec may call, and its first derivatives, on both engines' trees."""
    x, y = sp.symbols("x y", real=True)
    values = {"x": np.linspace(0.15, 0.85, POINTS), "y": np.linspace(0.4, 0.1, POINTS)}
    with sx.using("sympy"):
        func, arity = FUNCTIONS[name]  # the engine's function, read on the engine
        args = [x + 1 if name == "acosh" else x, y][:arity]
        expr = func(*args) * (x - y**2) + sp.Rational(3, 7) * func(*args) ** 2 - sp.pi * x
        exprs = [expr, sp.diff(expr, x), sp.diff(expr, y)]
        assert all(isinstance(e, sp.Basic) for e in exprs)
        expected = _evaluate(exprs, values)
    converted = _symengine(exprs)
    with sx.using("symengine"):
        got = _evaluate(converted, values)
        xs, ys = sx.symbols(["x", "y"])
        tape = Tape([xs, ys], converted, {}, {})(values["x"], values["y"])
        # SymEngine's own compiled evaluation, independent of the Evaluator.
        lambdified = sx.lambdify([xs, ys], converted)(values["x"], values["y"])
    _close(expected, got)
    _close(expected, [np.asarray(v, dtype=complex) for v in tape])
    _close(expected, [np.asarray(v, dtype=complex) for v in np.moveaxis(lambdified, -1, 0)])


def test_special_numbers_and_definitions_on_symengine() -> None:
    with sx.using("symengine"):
        x, t = sx.symbols(["x", "t"])
        evaluate = Evaluator({x: 2.0, t: np.array([0.0, 1.0])})
        assert evaluate(sx.I * x) == 2j
        assert evaluate(sx.oo + x) == np.inf
        assert evaluate(-sx.oo * x) == -np.inf
        assert np.isnan(evaluate(sx.zoo * x))
        assert np.isnan(evaluate(sx.nan + x))
        assert evaluate(sx.Rational(1, 3) * x) == pytest.approx(2 / 3, rel=1e-15)
        assert evaluate(sx.real(0.1) * x) == 0.2
        assert evaluate(sx.exp(x)) == np.exp(2.0)
        assert evaluate(sx.E * x) == pytest.approx(2 * np.e, rel=1e-15)
        q = sx.symbol("q")
        evaluate.define(q, sx.cos(t) * x)
        np.testing.assert_allclose(evaluate(q + t), 2 * np.cos([0.0, 1.0]) + [0.0, 1.0])
        with pytest.raises(ValueError, match="cannot evaluate"):
            evaluate(sx.Function("g")(x))
        with pytest.raises(ValueError, match="no value for the symbol z"):
            evaluate(sx.symbol("z") + x)


def test_inline_and_atomize_round_trip_on_symengine() -> None:
    """Program.inline undoes atomize on SymEngine, shared subtrees assigned once."""
    f0 = _objective()
    converted = _symengine([sp.diff(f0, v) for v in Y])
    with sx.using("symengine"):
        program, outputs = atomize(converted, fresh_symbols("_a"))
        back = [program.inline(e) for e in outputs]
        assert [(b - c).expand() for b, c in zip(back, converted, strict=True)] == [0, 0]
        assert len({e for _, e in program.assignments}) == len(program.assignments)
        assert program.inlined_size(outputs[0]) > len(program.assignments) // 2
    with sx.using("sympy"):
        names = list(itertools.islice(fresh_symbols("w"), 2))
    assert names == list(sp.symbols("w0 w1", real=True))


def test_a_teams_sparse_matrices_read_alike_on_both_engines() -> None:
    """A block-diagonal 60 x 40 G with scattered entries (and a float 0.0, which SymPy's
    matrix of entries drops): the same nonzero entries, extension and Brunovsky pair."""
    rng = np.random.default_rng(7)
    x = sp.symbols("s0:60", real=True)
    entries = {(i, i // 3 * 2 + (i % 2)): sp.cos(x[i]) + i for i in range(0, 60, 2)}
    entries |= {(int(i), int(j)): x[int(j)] ** 2 for i, j in rng.integers(0, 40, size=(8, 2))}
    entries[(59, 39)] = sp.Float(0.0)
    u = sp.symbols("w0:40", real=True)
    counts = {f"w{j}": 1 + j % 2 for j in range(0, 40, 3)}
    with sx.using("sympy"):
        G = from_entries(60, 40, entries)
        found = nonzero_entries(G)
        ext = extend(x, u, sp.zeros(60, 1), G, counts)
        ext_entries = nonzero_entries(ext.G)
        pair = brunovsky([2, 3, 1] * 10)
    assert [(i, j) for i, j, _ in found] == sorted(set(entries) - {(59, 39)})
    converted = _symengine((G, x, u))
    with sx.using("symengine"):
        found_se = nonzero_entries(converted[0])
        ext_se = extend(converted[1], converted[2], sx.zeros(60, 1), converted[0], counts)
        assert isinstance(ext_se.G, sx.ImmutableMatrix) and ext_se.G.shape == ext.G.shape
        G_ext_se = nonzero_entries(ext_se.G)
        f_se = list(ext_se.f)
        a_se, b_se = (to_sympy(m) for m in brunovsky([2, 3, 1] * 10))
    assert [(i, j, to_sympy(e)) for i, j, e in found_se] == found
    assert [(i, j, to_sympy(e)) for i, j, e in G_ext_se] == ext_entries
    assert [to_sympy(e) for e in f_se] == list(ext.f)
    assert (a_se, b_se) == pair
