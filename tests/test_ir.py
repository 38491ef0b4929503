"""The IR: kernel optimisation (cse.py) and generated sparse linear algebra (sparse.py).

Expressions are built through ``sx`` when a test runs, on the engine in use (the default,
SymEngine, unless a test is marked for SymPy): nothing is built at import, so the
hypothesis strategies draw the engine's leaves as they draw.
"""

from __future__ import annotations

import random
from collections import Counter
from collections.abc import Iterator, Sequence
from typing import Any

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from tvopt_codegen import cse
from tvopt_codegen import symbolic as sx
from tvopt_codegen.cse import (
    assembly,
    canonical_odd,
    make_kernel,
    make_kernels,
    numbering,
    operation_count,
    ordered_cse,
    rewrite,
    split_invariant,
)
from tvopt_codegen.cse.rewrite import _substitute
from tvopt_codegen.lowering.kernel import Arg, Kernel, Output
from tvopt_codegen.maths.sparse import cholesky_program, elimination_order, reverse_cuthill_mckee
from tvopt_codegen.symbolic.border import from_sympy, to_sympy

from .conftest import derivation, kernels


def _txya() -> list[Any]:
    """The symbols t, x, y, a of the engine in use."""
    return sx.symbols(["t", "x", "y", "a"])


def _nodes(expr: sx.Expr) -> Iterator[sx.Expr]:
    """Every node of ``expr``'s tree, a subtree as often as it occurs (either engine)."""
    stack = [sx.as_expr(expr)]
    while stack:
        node = stack.pop()
        yield node
        stack.extend(node.args)


def _value(expr: sx.Expr, env: dict[Any, float]) -> float:
    """``expr`` at the point ``env`` (symbol -> float), as a float."""
    return float(sx.as_expr(expr).xreplace({k: sx.real(v) for k, v in env.items()}))


def test_substitute_keeps_functions_unevaluated_but_folds_numbers() -> None:
    _, x, y, a = _txya()
    expr = sx.tan(sx.pi * x / (2 * a)) ** 2 + sx.sin(y)
    s0, p0 = sx.symbols(["_s0", "_p0"])
    out = _substitute(expr, {x: s0, a: p0, y: sx.Integer(0)})
    assert out == sx.tan(sx.pi * s0 / (2 * p0)) ** 2
    assert sx.expand(out - expr.xreplace({x: s0, a: p0, y: sx.ZERO})) == 0


def test_canonical_odd_merges_mirrored_arguments_once() -> None:
    t, x, y, a = _txya()
    memo: dict[sx.Expr, sx.Expr] = {}
    first = canonical_odd(sx.tanh((a - t) / x), memo)
    second = canonical_odd(sx.tanh((t - a) / x), memo)
    # Which of the two arguments is canonical is the engine's order (SymPy keeps t - a);
    # either way both spellings become one tanh and its negation.
    mirrored = (
        {sx.tanh((t - a) / x), -sx.tanh((t - a) / x)},
        {sx.tanh((a - t) / x), -sx.tanh((a - t) / x)},
    )
    assert {first, second} in mirrored
    if not sx.SYMENGINE:
        assert {first, second} == mirrored[0]
    assert first == -second
    # Shared memo: a second pass over the same node is a lookup.
    assert canonical_odd(sx.tanh((a - t) / x) + y, memo) == first + y


def test_cse_merges_equal_and_opposite_values() -> None:
    x, y, z = sx.symbols(["x", "y", "z"])
    a, b1, b2, c, d = sx.symbols(["a", "b1", "b2", "c", "d"])
    # b1 and b2 only become equal once a is named; c is -(x - y) spelled the other way.
    program = [
        (a, sx.tan(x * z)),
        (b1, a**2 + 1),
        (b2, sx.tan(x * z) ** 2 + 1),
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
        env[sym] = _value(value, env)
    for got, want in zip(outs, reference, strict=True):
        assert _value(got, env) == pytest.approx(_value(want, point), rel=1e-15)
    # tan once, its square plus one once, and x - y once (y - x is its negation).
    assert len(body) == 3


def _evaluate(
    body: Sequence[tuple[sx.Expr, sx.Expr]], outs: Sequence[sx.Expr], env: dict[Any, float]
) -> list[float]:
    env = dict(env)
    for sym, value in body:
        env[sym] = _value(value, env)
    return [_value(e, env) for e in outs]


def _uses(body: Sequence[tuple[sx.Expr, sx.Expr]], outs: Sequence[sx.Expr]) -> Counter[sx.Expr]:
    return Counter(
        node for e in [v for _, v in body] + list(outs) for node in _nodes(e) if node.is_Symbol
    )


def test_inlining_follows_the_uses_that_collecting_terms_removes() -> None:
    # Each level is s_j = s_{j-1} + b_j, read by u_j = s_j + 2*u_{j+1}-like sums: inlining
    # the single-use u collects 3*s_j, after which s_j is used once too. One pass over
    # the program found one level; the result must have no temporary used once.
    xs = sx.symbols([f"x{j}" for j in range(8)])
    s = sx.symbols([f"_s{j}" for j in range(8)])
    u = sx.symbols([f"_u{j}" for j in range(8)])
    program = [(s[0], xs[0] * xs[1])]
    for j in range(1, 8):
        program.append((s[j], s[j - 1] + sx.sin(xs[j])))
    # u_j = s_j + s_{j-1}, and the output sums s_j + 2*u_j: s_j twice, u_j once.
    for j in range(1, 8):
        program.append((u[j], s[j] + xs[j] * s[j - 1]))
    out = sx.Add(*(s[j] + 2 * u[j] for j in range(1, 8)))
    # One call reaches the fixed point (it used to take a pass per level).
    once, once_outs = numbering._inline_single_use(program, [out])
    uses = _uses(once, once_outs)
    assert all(uses[sym] > 1 for sym, _ in once), [(sym, uses[sym]) for sym, _ in once]
    # _reduce stops at the first round whose inlining removes nothing: another round
    # of merging and inlining must then change nothing.
    order, order_outs = numbering._reduce(program, [out], search=False)
    assert numbering._inline_single_use(*numbering._merge_equal(order, order_outs)) == (
        order,
        order_outs,
    )
    body, outs = ordered_cse(program, [out], search=False)
    point = {x: 0.1 * (i + 1) for i, x in enumerate(xs)}
    full = sx.Add(*(s[j] + 2 * u[j] for j in range(1, 8)))
    for sym, value in reversed(program):
        full = full.xreplace({sym: value})
    assert _evaluate(body, outs, point) == pytest.approx([_value(full, point)], rel=1e-14)


@pytest.mark.parametrize("small_program_ops", [5, 10**6])
def test_number_outputs_pass_through_lowering_in_place(
    monkeypatch: pytest.MonkeyPatch, small_program_ops: int
) -> None:
    # A Hessian-like output, mostly numbers, lowered together with another kernel and
    # alone: the numbers come out where they were, and no pass ever sees them.
    monkeypatch.setattr(assembly, "SMALL_PROGRAM_OPS", small_program_ops)
    monkeypatch.setattr(numbering, "SMALL_PROGRAM_OPS", small_program_ops)
    t, x, _, a = _txya()
    s0, p0 = sx.symbols(["_s0", "_p0"])
    g = sx.symbols([f"_g{i}" for i in range(3)])
    program = [(g[0], sx.sin(x * a)), (g[1], g[0] ** 2 + x), (g[2], g[1] * g[0] + a)]
    subs = {x: s0, a: p0}
    inputs = [Arg("t", (), (), "time"), Arg("s", (s0,), ("x",), ""), Arg("p", (p0,), ("a",), "")]
    numbers = [sx.Integer(0), sx.Rational(1, 2), sx.real(-1.5), sx.Integer(0)]
    hessian = [numbers[0], g[2] * g[1], numbers[1], numbers[2], g[1] - g[0], numbers[3]]
    specs: list[tuple[str, str, Sequence[Arg], assembly.Outputs]] = [
        ("hess", "mostly numbers", inputs, [("h", (2, 3), hessian, "")]),
        ("grad", "no numbers", inputs, [("d", (2,), [g[2], g[1] * a], "")]),
    ]
    seen: list[sx.Expr] = []
    prepare = assembly._prepare

    def spy(assignments: Any, exprs: Any, *rest: Any, **named: Any) -> Any:
        seen.extend(exprs)
        return prepare(assignments, exprs, *rest, **named)

    monkeypatch.setattr(assembly, "_prepare", spy)
    env = {t: 0.3, s0: 0.8, p0: 1.7}
    together = make_kernels(specs, program, subs, odd={})
    alone = make_kernel("hess", "", inputs, program, specs[0][3], subs, odd={})
    assert seen and not any(e.is_Number for e in seen)
    for kernel in (together[0], alone):
        out = kernel.outputs[0].exprs
        assert [out[i] for i in (0, 2, 3, 5)] == numbers
        assert all(out[i] is n for i, n in zip((0, 2, 3, 5), numbers, strict=True))
        value = x * a
        direct = {g[0]: sx.sin(value)}
        direct[g[1]] = direct[g[0]] ** 2 + x
        direct[g[2]] = direct[g[1]] * direct[g[0]] + a
        point = {x: 0.8, a: 1.7}
        want = [_value(e.xreplace(direct), point) for e in hessian]
        assert _evaluate(kernel.body, out, env) == pytest.approx(want, rel=1e-14)


def test_kernels_lowered_together_compute_what_they_compute_apart(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # A jet-like program read by two kernels (one needs a prefix of it), lowered
    # together once both are "large" (the limit lowered to make them so).
    monkeypatch.setattr(assembly, "SMALL_PROGRAM_OPS", 5)
    monkeypatch.setattr(numbering, "SMALL_PROGRAM_OPS", 5)
    t, x, y, a = _txya()
    s0, s1, p0 = sx.symbols(["_s0", "_s1", "_p0"])
    g = sx.symbols([f"_g{i}" for i in range(6)])
    program = [
        (g[0], sx.tanh((x - t) / a)),
        (g[1], g[0] ** 2 + y),
        (g[2], g[1] * x + g[0] * y),
        (g[3], g[2] + g[1] * a),
        (g[4], g[3] * g[0] + sx.cos(y - x)),
        (g[5], g[4] + 2 * g[3] + g[2] * g[1]),
    ]
    subs = {x: s0, y: s1, a: p0}
    inputs = [
        Arg("t", (), (), "time"),
        Arg("s", (s0, s1), ("x", "y"), ""),
        Arg("p", (p0,), ("a",), ""),
    ]
    first = ("first", "all of it", inputs, [("o", (2,), [g[5], g[4] * g[1]], "")])
    second = ("second", "a prefix", inputs, [("e", (2,), [g[2], g[3] - g[0]], "")])
    reduced = []
    # The reduction of the whole program: SymEngine's runs on the program's DAG.
    step = "_reduce_dag" if sx.SYMENGINE else "_reduce"
    reduce = getattr(assembly, step)

    def spy(*args: Any, **named: Any) -> Any:
        reduced.append(1)
        return reduce(*args, **named)

    monkeypatch.setattr(assembly, step, spy)
    together = make_kernels([first, second], program, subs, odd={})
    assert len(reduced) == 1  # one lowering for both
    apart = [
        make_kernel(name, doc, args, program, outs, subs, odd={})
        for name, doc, args, outs in (first, second)
    ]
    env = {t: 0.3, s0: 0.8, s1: -0.4, p0: 1.7}
    for joint, alone in zip(together, apart, strict=True):
        assert joint.name == alone.name
        assert joint.ops <= alone.ops
        assert joint.ops_before_cse == alone.ops_before_cse
        got = _evaluate(joint.body, joint.outputs[0].exprs, env)
        want = _evaluate(alone.body, alone.outputs[0].exprs, env)
        assert got == pytest.approx(want, rel=1e-14)
        uses = _uses(joint.body, joint.outputs[0].exprs)
        assert all(uses[sym] > 1 for sym, _ in joint.body), joint.name
        # Each keeps what its outputs need: the prefix kernel never reads g4's cosine.
    assert not any(isinstance(node, sx.cos) for _, v in together[1].body for node in _nodes(v))


@pytest.mark.parametrize("spec", ["two_unicycles_barrier", "unicycle_ring", "flexible_joint"])
def test_no_kernel_computes_a_value_twice(spec: str) -> None:
    for kernel in kernels(spec).kernels:
        values = [value for _, value in kernel.body]
        assert len(values) == len(set(values)), kernel.name
        assert not set(values) & {-v for v in values}, kernel.name


def test_split_invariant_hoists_time_terms_out_of_the_state_part() -> None:
    t = sx.symbol("t")
    s0, p0, t0, t1 = sx.symbols(["_s0", "_p0", "_t0", "_t1"])
    kernel = Kernel(
        "k",
        "test",
        (Arg("t", (), (), "time"), Arg("s", (s0,), ("x",), "state"), Arg("p", (p0,), ("c",), "")),
        ((t0, sx.tanh(p0 * t)), (t1, s0 * t0)),
        (Output("out", (3,), (s0 + t + 1 + t0 * t, sx.sin(s0 + 2 * t) * t0 * p0, t1 * t), ""),),
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
        for node in _nodes(expr):
            if not node.is_Atom and node.free_symbols:
                assert not node.free_symbols <= given | set(state_part.inputs[-1].symbols), node
    # Composed, the two parts are the kernel.
    env = {t: 0.7, s0: -1.3, p0: 0.4}
    for sym, value in time_part.body:
        env[sym] = _value(value, env)
    for sym, value in zip(state_part.inputs[-1].symbols, time_part.outputs[0].exprs, strict=True):
        env[sym] = _value(value, env)
    for sym, value in state_part.body:
        env[sym] = _value(value, env)
    want = dict(env)
    for sym, value in kernel.body:
        want[sym] = _value(value, want)
    for got, ref in zip(state_part.outputs[0].exprs, kernel.outputs[0].exprs, strict=True):
        assert _value(got, env) == pytest.approx(_value(ref, want), rel=1e-14)


def test_the_state_part_of_the_switching_jet_is_small() -> None:
    # unicycle_switch: the tanh switch and the target paths are shared by a batch; per
    # state remain the heading's cos and sin and a few products.
    jet = kernels("unicycle_switch")["jet"]
    assert jet.ops <= 25
    assert kernels("unicycle_switch")["jet_time"].ops >= 100


def _run(program: list[tuple[sx.Expr, sx.Expr]], env: dict[sx.Expr, float]) -> None:
    for symbol, value in program:
        env[symbol] = _value(value, env)


@pytest.mark.parametrize("seed", range(4))
def test_cholesky_program_solves_a_sparse_system(seed: int) -> None:
    """An arrow-plus-ring pattern: the LDL^T program's z solves Hess z = c to rounding."""
    m = 7
    rng = np.random.default_rng(seed)
    pattern = {(i, i) for i in range(m)} | {(i, i - 1) for i in range(1, m)} | {(m - 1, 0)}
    entries = sorted(pattern)
    dense = np.zeros((m, m))
    for i, j in entries:
        dense[i, j] = dense[j, i] = rng.uniform(-1, 1)
    dense += np.diag(np.abs(dense).sum(axis=1) + 1.0)  # diagonally dominant: positive definite
    rhs = rng.standard_normal(m)
    h = sx.symbols([f"_h{e}" for e in range(len(entries))])
    c = sx.symbols([f"_c{i}" for i in range(m)])
    program, z, pivots = cholesky_program(entries, m, h, c)
    env: dict[sx.Expr, float] = {s: dense[i, j] for s, (i, j) in zip(h, entries, strict=True)}
    env |= {s: rhs[i] for i, s in enumerate(c)}
    _run(program, env)
    solution = np.array([_value(e, env) for e in z])
    np.testing.assert_allclose(dense @ solution, rhs, rtol=0, atol=1e-13)
    # The pivots are D of L D L^T: their product is det(Hess).
    product = np.prod([_value(e, env) for e in pivots])
    assert product == pytest.approx(np.linalg.det(dense), rel=1e-12)


def test_cholesky_program_subtracts_each_product_on_its_own() -> None:
    """``a - l*s - l'*s'``, never ``a - (l*s + l'*s')``: SymEngine keeps the second a
    negated sum, which lowering would distribute again at every elimination step."""
    m = 7
    pattern = {(i, i) for i in range(m)} | {(i, i - 1) for i in range(1, m)} | {(m - 1, 0)}
    entries = sorted(pattern)
    h = sx.symbols([f"_h{e}" for e in range(len(entries))])
    c = sx.symbols([f"_c{i}" for i in range(m)])
    program, _, _ = cholesky_program(entries, m, h, c)
    negated_sums = [
        value
        for _, value in program
        for node in [value, *value.args]
        if node.is_Mul and any(arg.is_Add for arg in node.args)
    ]
    assert negated_sums == []
    # The dots are there: a fill-in's elimination subtracts two products at once.
    assert max(len(value.args) for _, value in program if value.is_Add) >= 3


def test_cholesky_pivots_turn_negative_for_an_indefinite_matrix() -> None:
    h = sx.symbols([f"_h{i}" for i in range(3)])
    c = sx.symbols([f"_c{i}" for i in range(2)])
    program, _, pivots = cholesky_program([(0, 0), (1, 0), (1, 1)], 2, h, c)
    env: dict[sx.Expr, float] = {h[0]: 1.0, h[1]: 2.0, h[2]: 1.0, c[0]: 0.0, c[1]: 0.0}
    _run(program, env)
    values = [_value(e, env) for e in pivots]
    assert values[0] == 1.0 and values[1] == -3.0  # 1 - 2 * 2 / 1


def test_elimination_order_avoids_the_arrow_fill() -> None:
    """An arrow whose hub is row 0: natural order fills the whole matrix, RCM does not."""
    m = 6
    pattern = {(i, i) for i in range(m)} | {(0, i) for i in range(m)} | {(i, 0) for i in range(m)}
    order = elimination_order(pattern, m)
    assert sorted(order) == list(range(m))
    assert order != tuple(range(m))
    h = sx.symbols([f"_h{i}" for i in range(len([e for e in pattern if e[0] >= e[1]]))])
    c = sx.symbols([f"_c{i}" for i in range(m)])
    entries = sorted(e for e in pattern if e[0] >= e[1])
    program, _, _ = cholesky_program(entries, m, h, c)
    # No fill: per column below the diagonal one L entry and one scaled entry at most.
    assert operation_count([v for _, v in program]) < 6 * m * 3


def test_reverse_cuthill_mckee_is_scipys_order() -> None:
    """The order is scipy's to the tie, so the generated code did not change with it."""
    from scipy.sparse import csr_matrix  # noqa: PLC0415
    from scipy.sparse.csgraph import reverse_cuthill_mckee as scipys  # noqa: PLC0415

    rng = random.Random(3)
    for _ in range(300):
        m = rng.choice([2, 3, 5, 8, 13, 30, 64, 130, 600])
        density = rng.choice([0.005, 0.02] if m > 100 else [0.02, 0.1, 0.3, 0.7])
        pattern = {(i, i) for i in range(m) if rng.random() < 0.8}
        for i in range(m):
            for j in range(i):
                if rng.random() < density:
                    pattern |= {(i, j), (j, i)}
        if not pattern:
            continue
        rows, cols = zip(*sorted(pattern), strict=True)
        graph = csr_matrix(([1] * len(rows), (rows, cols)), shape=(m, m))
        expected = tuple(int(i) for i in scipys(graph, symmetric_mode=True))
        assert reverse_cuthill_mckee(pattern, m) == expected, (m, density)


def _leaves() -> list[Any]:
    """The leaves the property tests draw: four symbols, exact numbers, floats and pi."""
    return [
        *sx.symbols(["a", "b", "c", "d"]),
        sx.Integer(2),
        sx.Integer(-1),
        sx.Rational(1, 3),
        sx.real(0.1),
        sx.real(-2.5),
        sx.pi,
    ]


def _leaf(kinds: int = 10) -> st.SearchStrategy[sx.Expr]:
    """One of the first ``kinds`` leaves (4: a symbol), built on the engine in use."""
    return st.integers(0, kinds - 1).map(lambda i: _leaves()[i])


def _sine(expr: sx.Expr) -> sx.Expr:
    """``sin(expr)``, NaN where ``expr`` is infinite (``1/0``): SymPy's sin is NaN there,
    SymEngine's constructor raises."""
    try:
        return sx.sin(expr)
    except RuntimeError:
        return sx.nan


def _expressions() -> st.SearchStrategy[sx.Expr]:
    leaves = _leaf()

    def extend(children: st.SearchStrategy[sx.Expr]) -> st.SearchStrategy[sx.Expr]:
        return st.one_of(
            st.lists(children, min_size=2, max_size=4).map(lambda xs: sx.Add(*xs)),
            st.lists(children, min_size=2, max_size=4).map(lambda xs: sx.Mul(*xs)),
            st.tuples(children, st.sampled_from([(2, 1), (-1, 1), (1, 2)])).map(
                lambda p: sx.Pow(p[0], sx.Rational(*p[1]))
            ),
            children.map(_sine),
            # exp of a leaf only: exp(exp(...)) of a number overflows mpmath in both.
            leaves.map(lambda e: sx.exp(e)),  # noqa: PLW0108 - sx.exp is read at draw time
        )

    return st.recursive(leaves, extend, max_leaves=12)


@pytest.mark.engine("sympy")
@given(_expressions(), st.dictionaries(_leaf(4), _expressions(), max_size=3))
@settings(max_examples=400, deadline=None)
def test_substitution_builds_what_sympy_builds(expr: sx.Expr, mapping: dict[Any, Any]) -> None:
    """Sums and products rebuilt without flatten (rewrite._sorted_args) are sympy's own:
    the same tree, argument for argument, whatever the substitution splices or folds.

    SymPy only: on SymEngine the engine's constructors rebuild every node (the twin
    below checks the values there)."""
    import sympy as sp  # noqa: PLC0415 - the subject is SymPy's own constructors

    from tvopt_codegen.cse.rewrite import _negate, _substitute

    def reference(node: sp.Basic) -> sp.Basic:
        # rewrite._rebuild's rule for functions (not re-evaluated on symbolic arguments),
        # sympy's full constructor for everything else.
        if node in mapping:
            return mapping[node]
        if not node.args:
            return node
        args = [reference(arg) for arg in node.args]
        if args == list(node.args):
            # Nothing substituted below: the tree as it was, not rebuilt (as _substitute
            # leaves it). SymPy's constructors are not idempotent: a product hypothesis
            # drew, 0.18*(0.01 - 2.3*I), is one complex number once rebuilt from its own
            # two arguments.
            return node
        if isinstance(node, sp.Function) and not all(a.is_Number for a in args):
            return node.func(*args, evaluate=False)
        return node.func(*args)

    assert sp.srepr(_substitute(expr, mapping)) == sp.srepr(reference(expr))
    assert sp.srepr(_negate(expr)) == sp.srepr(-expr)


#: Where the values of substituted trees are compared (no two leaves cancel there).
_POINT = (0.3137, 0.7261, 1.1893, 1.9411)


def _agree(got: sx.Expr, want: sx.Expr) -> bool:
    """Whether two expressions in the leaves' symbols have the same value at _POINT.

    A draw whose value is not a finite number of moderate size (a pole, an overflow:
    the two trees may round into different infinities) is rejected, not compared.
    """
    from tvopt_codegen.maths.numeric import Evaluator  # noqa: PLC0415

    point = dict(zip(_leaves()[:4], _POINT, strict=True))
    values = np.array([Evaluator(point)(e) for e in (got, want)], dtype=complex)
    with np.errstate(all="ignore"):
        assume(bool(np.all(np.isfinite(values)) and np.all(np.abs(values) < 1e100)))
        return bool(np.isclose(values[0], values[1], rtol=1e-9, atol=1e-12))


@given(_expressions(), st.dictionaries(_leaf(4), _expressions(), max_size=3))
@settings(max_examples=300, deadline=None)
def test_substitution_computes_what_xreplace_computes(
    expr: sx.Expr, mapping: dict[Any, Any]
) -> None:
    """The substitution is ``xreplace`` (on SymEngine with a rational coefficient of a sum
    distributed, as SymPy's Mul does): the same values, and negating negates them. Where
    ``xreplace`` itself is refused (SymEngine's ``sin`` of the infinity ``1/0``), the
    substitution is refused alike."""
    from tvopt_codegen.cse.rewrite import _negate, _substitute

    try:
        want = expr.xreplace(mapping)
    except RuntimeError as refused:
        with pytest.raises(RuntimeError) as raised:
            _substitute(expr, mapping)
        assert str(raised.value) == str(refused)
        return
    assert _agree(_substitute(expr, mapping), want)
    assert _agree(_negate(expr), -expr)


@pytest.mark.engine("sympy")
def test_a_sum_rebuilt_around_sympys_nested_product() -> None:
    """sympy builds ``2*exp(a + 0.1)`` as a product holding a product,
    ``2*(1.105...*exp(a))``, and ``Add.flatten`` rebuilds such a term from its coefficient
    and the rest: a sum rebuilt around it is flatten's, not a re-sorted copy (a case the
    substitution property test above found). SymPy's own nesting: SymPy only."""
    import sympy as sp  # noqa: PLC0415 - the subject is SymPy's own constructors

    from tvopt_codegen.cse.rewrite import _substitute

    a = sp.Symbol("a", real=True)
    nested = sp.Mul(2, sp.exp(a + sp.Float(0.1), evaluate=False))
    assert nested.args[1].is_Mul  # the premise: sympy nests it
    expected = sp.Add(a + sp.Float(0.1), nested)
    got = _substitute(a + 2 * sp.exp(a), {a: a + sp.Float(0.1)})
    assert sp.srepr(got) == sp.srepr(expected)


@given(_expressions())
@settings(max_examples=200, deadline=None)
def test_an_exact_expansion_negated_is_the_negations_expansion(expr: sx.Expr) -> None:
    """canonical_odd expands an odd function's argument once and negates the terms for
    the mirrored argument: the same tree as expanding the negation, without floats
    (the engine's ``==`` compares trees, SymPy's argument for argument)."""
    from tvopt_codegen.cse.rewrite import _negate

    assume(not expr.atoms(sx.Float))
    assert _negate(sx.expand(expr)) == sx.expand(-expr)


@given(st.lists(_expressions(), min_size=1, max_size=6))
@settings(max_examples=200, deadline=None)
def test_symbols_in_is_the_union_of_free_symbols(exprs: list[sx.Expr]) -> None:
    assert rewrite.symbols_in(exprs) == set().union(*(e.free_symbols for e in exprs))


@st.composite
def _programs_with_aliases(draw: st.DrawFn) -> tuple[list[tuple[sx.Expr, sx.Expr]], list[Any]]:
    """Three-address-like programs: temporaries that alias an earlier one (or its
    negation, or a leaf), repeat an earlier value (or its negation), or combine."""
    order: list[tuple[sx.Expr, sx.Expr]] = []
    for k in range(draw(st.integers(1, 12))):
        known = [sym for sym, _ in order] + _leaves()[:4]
        kind = draw(st.sampled_from(["alias", "negated", "repeat", "combine", "combine"]))
        if kind in ("alias", "negated"):
            value = draw(st.sampled_from(known)) * (-1 if kind == "negated" else 1)
        elif kind == "repeat" and order:
            value = draw(st.sampled_from([v for _, v in order])) * draw(st.sampled_from([1, -1]))
        else:
            pick = st.sampled_from(known)
            value = draw(st.sampled_from([sx.Add, sx.Mul]))(draw(pick), draw(pick))
            value = draw(st.sampled_from([value, sx.sin(value), value - draw(pick)]))
        order.append((sx.symbol(f"_cse{k}"), value))
    syms = [sym for sym, _ in order]
    outs = draw(st.lists(st.sampled_from(syms), min_size=1, max_size=4))
    return order, [o + 1 for o in outs]


@given(_programs_with_aliases())
@settings(max_examples=300, deadline=None)
def test_merging_also_drops_aliases_and_computes_the_same(program: tuple[Any, Any]) -> None:
    """_merge_equal substitutes aliases (a temporary that is a symbol, a constant or a
    negation of one) in the same walk as it merges equal values: the outputs are the
    same numbers, no alias and no value twice (or negated) is left, and nothing is
    kept that dropping aliases first, then merging, would have removed."""
    order, outs = program
    merged, merged_outs = numbering._merge_equal(order, outs)
    apart, apart_outs = numbering._merge_equal(*numbering._drop_aliases(order, outs))
    assert len(merged) <= len(apart)
    values = [value for _, value in merged]
    assert not any(v.is_Atom or rewrite._negated_atom(v) for v in values)
    assert len(set(values)) == len(values) and not set(values) & {-v for v in values}
    point = {leaf: 0.1 * (k + 2) for k, leaf in enumerate(_leaves()[:4])}
    want = _evaluate(order, outs, point)
    assert _evaluate(merged, merged_outs, point) == pytest.approx(want, rel=1e-12)
    assert _evaluate(apart, apart_outs, point) == pytest.approx(want, rel=1e-12)


def test_a_kernel_reading_a_symbol_it_is_not_given_is_refused() -> None:
    s0, stray = sx.symbols(["_s0", "_stray"])
    inputs = [Arg("s", (s0,), ("x",), "state")]
    with pytest.raises(AssertionError, match=r"kernel k: unbound symbols \['_stray'\]"):
        make_kernel("k", "", inputs, [], [("out", (1,), [s0 * stray + 1], "")], {})


@given(_expressions(), st.dictionaries(_leaf(4), _leaf()))
@settings(max_examples=300, deadline=None)
def test_substituting_and_signing_odd_functions_in_one_pass(
    expr: sx.Expr, mapping: dict[Any, Any]
) -> None:
    """_prepare substitutes slots and gives odd functions their canonical sign in one
    walk: the same tree as substituting, then canonical_odd."""
    from tvopt_codegen.cse.rewrite import _substitute

    try:
        two_passes = canonical_odd(_substitute(expr, mapping), {})
    except RuntimeError:
        # A pole under a function, sin(a + 1/(2 + 2a)) at a = -1: SymEngine's constructor
        # refuses sin(zoo) (SymPy's is nan). The one pass refuses it alike.
        with pytest.raises(RuntimeError, match="infinite"):
            _substitute(expr, mapping, {}, {})
        return
    assert _substitute(expr, mapping, {}, {}) == two_passes


@pytest.mark.parametrize("engine_name", ["symengine", "sympy"])
def test_an_odd_function_whose_new_argument_gives_up_its_sign_is_signed_once(
    engine_name: str,
) -> None:
    """The constructor pulls a minus out of the substituted argument (sin(-2.5 (a + c))
    is built as -sin(2.5 (a + c))): the one-pass walk signs the sine under that minus as
    canonical_odd does in a second walk (hypothesis found the float case; a symbol
    gives it too). Before, the one pass left -sin(2.5 (a + c)) where canonical_odd
    writes sin(2.5 (-a - c)), and CSE saw two sines."""
    with sx.using(engine_name):
        a, b, c = sx.symbols(["a", "b", "c"])
        expr = sx.sin(b * (a + c))
        for value in (sx.real(-2.5), -a):
            mapping = {b: value}
            one = _substitute(expr, mapping, {}, {})
            assert one == canonical_odd(_substitute(expr, mapping), {}), value
            assert canonical_odd(one, {}) == one, value


def test_a_number_beside_a_sum_is_distributed_exactly_where_sympy_does() -> None:
    """Substitution distributes a number over a sum where flatten does (a product of two
    arguments, or of the number and the sum alone), and nowhere else: on either engine
    the tree SymPy's constructors build (SymEngine's keep every product, and
    rewrite._distributed distributes as SymPy does)."""
    from tvopt_codegen.cse.rewrite import _substitute

    t, x, y, a = _txya()
    g, h = sx.symbols(["_g", "_h"])
    values = {g: a + y, h: 2 * x}
    on_sympy = {to_sympy(k): to_sympy(v) for k, v in values.items()}
    for expr in (2 * g, 2 * x * g, -3 * g * x * t, h * g, h * g * t, g * h / 3, -g, 2 * g**2):
        expected = from_sympy(to_sympy(expr).xreplace(on_sympy))
        built = _substitute(expr, values)
        assert built == expected, (expr, built, expected)


def test_lowering_leaves_no_reference_cycles_of_its_own() -> None:
    """The command line runs the derivation and lowering without the cyclic collector:
    every recursive walk of ours releases itself (jet.release), so what it built is
    freed by reference counting. Cycles left by sympy's own helpers are few and small."""
    import gc

    from tests.conftest import derivation
    from tvopt_codegen.lowering.ir import lower

    d = derivation("two_unicycles_barrier")
    gc.collect()
    gc.disable()
    gc.set_debug(gc.DEBUG_SAVEALL)
    try:
        lower(d)
        gc.collect()
        ours = [
            o.__qualname__
            for o in gc.garbage
            if callable(o) and getattr(o, "__module__", "").startswith("tvopt_codegen")
        ]
    finally:
        gc.set_debug(0)
        gc.garbage.clear()
        gc.enable()
    assert ours == []


def _kernel_values(kernel: Kernel, inputs: dict[Any, float]) -> list[float]:
    """A kernel's outputs, flat, at ``inputs`` (symbol -> float), each value evaluated once."""
    env: dict[Any, float] = {}

    def value(expr: sx.Expr) -> float:
        expr = sx.as_expr(expr)
        point = {s: sx.real(env[s] if s in env else inputs[s]) for s in expr.free_symbols}
        return float(expr.xreplace(point))

    for sym, expr in kernel.body:
        env[sym] = value(expr)
    return [value(e) for out in kernel.outputs for e in out.exprs]


def _kernel_groups(monkeypatch: pytest.MonkeyPatch) -> list[list[str]]:
    """The names of the kernels each of ``lower``'s calls of make_kernels makes, as it goes."""
    from tvopt_codegen.lowering import ir  # noqa: PLC0415

    calls: list[list[str]] = []

    def counted(kernels: Any, *args: Any, **options: Any) -> list[Kernel]:
        made = cse.make_kernels(kernels, *args, **options)
        calls.append([k.name for k in made])
        return made

    monkeypatch.setattr(ir, "make_kernels", counted)
    return calls


def test_f0s_gradient_and_hessian_cut_from_the_jet_program_are_the_objectives_own(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Outputs that are states: the gradient and Hessian kernels at outputs are cut from
    the jet's program (lowered once, in one union with the jet), their state slots read
    as the outputs'. They compute what the objective's own program lowered apart
    computes, at no more operations; a spec whose outputs are functions of the state,
    or whose gradient is the KKT map's, lowers them apart."""
    from tvopt_codegen.derivation.pipeline import derive  # noqa: PLC0415
    from tvopt_codegen.lowering import ir  # noqa: PLC0415
    from tvopt_codegen.spec import parse_spec  # noqa: PLC0415

    from .conftest import ROOT  # noqa: PLC0415

    raw = (ROOT / "tvopt_codegen" / "examples" / "unicycle_ring.toml").read_bytes()
    # 32 agents: the jet and E are large enough to be lowered as one union, and f0, its
    # gradient and its Hessian would be one too, lowered apart.
    ring = derive(parse_spec("ring32.toml", raw.replace(b"\ni = 4 ", b"\ni = 32 ", 1)))
    assert ir._outputs_as_states(ring, ir._arguments(ring)) is not None
    calls = _kernel_groups(monkeypatch)
    cut = {k.name: k for k in ir.lower(ring).kernels}
    # The riders came with the jet; f0 alone was lowered apart.
    assert calls == [["jet", "optimality", "gradient", "hessian"], ["objective"]]
    monkeypatch.setattr(ir, "_outputs_as_states", lambda d, args: None)
    apart = {k.name: k for k in ir.lower(ring).kernels}
    monkeypatch.undo()
    assert [k for k in cut] == [k for k in apart]
    assert all(cut[name].ops == apart[name].ops for name in ("jet", "optimality"))
    rng = np.random.default_rng(11)
    for name in ("objective", "gradient", "hessian"):
        ours, theirs = cut[name], apart[name]
        assert ours.inputs == theirs.inputs
        assert ours.ops <= theirs.ops
        for _ in range(2):
            point = {s: rng.uniform(-2.0, 2.0) for arg in ours.inputs for s in arg.symbols}
            point[sx.symbol("t")] = rng.uniform(0.0, 5.0)
            np.testing.assert_allclose(
                _kernel_values(ours, point), _kernel_values(theirs, point), rtol=1e-12, atol=1e-12
            )
    # At 16 agents f0's kernel is small enough for the engine's search: the three are
    # lowered apart, as they would be without riders, and searched.
    calls = _kernel_groups(monkeypatch)
    small = derive(parse_spec("ring16.toml", raw.replace(b"\ni = 4 ", b"\ni = 16 ", 1)))
    ir.lower(small)
    monkeypatch.undo()
    assert calls == [["jet", "optimality"], ["objective", "gradient", "hessian"]]
    # y = h(x) a function of the state (the arm's tip), and equalities (the KKT map).
    for spec in ("planar_arm3", "arm_on_line"):
        d = derivation(spec)
        assert ir._outputs_as_states(d, ir._arguments(d)) is None


_RING_FEATURES = {
    "integral": "[robust]\nintegral = true\n",
    "observer": "[robust.observer]\nbandwidth = 20.0\n",
    "eso": "[robust.eso]\nbandwidth = 20.0\n",
    "limits": "[limits]\nomega_0 = 2.0\nomega_3 = 2.0\n",
}


@pytest.mark.parametrize(
    "spec",
    [
        "unicycle_ring",
        "unicycle_ring_refs",
        "two_unicycles_barrier",
        "two_unicycles_corridor",
        "flexible_joint",
        "figure8_wall.toml",
        "nonuniform.toml",
        *(f"unicycle_ring+{feature}" for feature in _RING_FEATURES),
    ],
)
def test_riders_beside_every_feature_compute_the_objectives_own_kernels(
    spec: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """With every kernel taken for large (the union's threshold at 0), the riders ride on
    small specs too: beside references, constraints, padding chains, integral action, the
    disturbance observer, the extended-state observer and limits, f0 and its derivatives
    at outputs equal those lowered apart, at random inputs."""
    from tvopt_codegen.cse import assembly  # noqa: PLC0415
    from tvopt_codegen.derivation.pipeline import derive  # noqa: PLC0415
    from tvopt_codegen.lowering import ir  # noqa: PLC0415
    from tvopt_codegen.spec import parse_spec  # noqa: PLC0415

    from .conftest import ROOT, SPECS  # noqa: PLC0415

    if "+" in spec:
        base, feature = spec.split("+")
        raw = (ROOT / "tvopt_codegen" / "examples" / f"{base}.toml").read_text(encoding="utf-8")
        raw = raw.replace("[simulation]", _RING_FEATURES[feature] + "\n[simulation]", 1)
        if feature == "integral":  # one more pole per output
            raw = raw.replace("poles = [-1.0, -1.5]", "poles = [-1.0, -1.5, -2.0]", 1)
        d = derive(parse_spec(f"{spec}.toml", raw.encode()))
    else:
        d = derivation(str(SPECS / spec) if spec.endswith(".toml") else spec)
    args = ir._arguments(d)
    as_states = ir._outputs_as_states(d, args)
    assert as_states is not None
    monkeypatch.setattr(assembly, "SMALL_PROGRAM_OPS", 0)
    calls = _kernel_groups(monkeypatch)
    cut = {k.name: k for k in ir.lower(d).kernels}
    assert calls[0][2:] == ["gradient", "hessian"]
    monkeypatch.setattr(ir, "_outputs_as_states", lambda d, args: None)
    apart = {k.name: k for k in ir.lower(d).kernels}
    # Near the start, where the spec's barriers are defined: each output at its state's
    # initial value, the parameters at their defaults, plus a little noise.
    start = dict(zip(args.s.symbols, d.closed_loop.initial_state, strict=True))
    given = {y: start[s] for s, y in as_states.items()}
    given |= {p: float(v) for p, v in zip(args.p.symbols, d.model.defaults, strict=True)}
    rng = np.random.default_rng(5)
    for name in ("objective", "gradient", "hessian"):
        point = {
            s: given.get(s, 0.5) + rng.uniform(-0.01, 0.01)
            for arg in cut[name].inputs
            for s in arg.symbols
        }
        point[sx.symbol("t")] = 0.0
        theirs = _kernel_values(apart[name], point)
        ours = _kernel_values(cut[name], point)
        np.testing.assert_allclose(ours, theirs, rtol=1e-12, atol=1e-12)
