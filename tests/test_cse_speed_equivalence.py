"""The DAG's faster passes compute what the plain walks compute (issue 49, lowering's speed).

Each shortcut taken to lower faster has a plain counterpart here, written the obvious
way, and the two are held equal on random programs, in ids and in numbers: a child
looked up in place when a program is read, a substitution's walk, the bytearray walk of
what the outputs need, the leaves a value reads, a program marked as pruned already,
the factored rewrite kept across kernels, and the cost of constant outputs counted once
per number.
"""

from __future__ import annotations

import random

import pytest

from tvopt_codegen import cse
from tvopt_codegen import symbolic as sx
from tvopt_codegen.cse import assembly, numbering, programs
from tvopt_codegen.cse.coefficients import factored
from tvopt_codegen.cse.dag import Dag, Program

from .engine_cases import float_value

NAMES = ["a", "b", "c", "d", "x", "y"]
POINT = {"a": 0.31, "b": -0.77, "c": 1.3, "d": 0.45, "x": -1.1, "y": 0.6}


def _value(expr: sx.Expr, env: dict[str, float]) -> float:
    value: float = float_value(expr, env, {}, str)
    return value


def _random_expr(rng: random.Random, leaves: list[sx.Expr], depth: int) -> sx.Expr:
    """A small random expression: sums, products with rational coefficients, sines."""
    if depth == 0 or rng.random() < 0.25:
        return rng.choice(leaves)
    pick = rng.random()
    left = _random_expr(rng, leaves, depth - 1)
    right = _random_expr(rng, leaves, depth - 1)
    if pick < 0.35:
        return left + right
    if pick < 0.55:
        return left - rng.choice([1, 2, 3]) * right
    if pick < 0.8:
        return sx.Rational(rng.choice([-2, -1, 1, 3]), rng.choice([1, 2])) * left * right
    return sx.sin(left) + right


def _random_program(
    seed: int, size: int = 40
) -> tuple[list[tuple[sx.Expr, sx.Expr]], list[sx.Expr]]:
    """A straight-line program over NAMES: each value reads inputs and earlier symbols;
    some assignments are aliases (a symbol, a negated one), some are read by nothing."""
    rng = random.Random(seed)
    inputs = sx.symbols(NAMES)
    known = list(inputs)
    program: list[tuple[sx.Expr, sx.Expr]] = []
    for i in range(size):
        sym = sx.symbol(f"_v{i}")
        if rng.random() < 0.15:
            value = rng.choice(known) * rng.choice([1, -1])
        else:
            value = _random_expr(rng, known[-8:] + list(inputs), 3)
            # Bounded values: a chain of products would reach 1e17, where the rounding
            # of one evaluation order is not another's.
            value = sx.sin(value) if rng.random() < 0.6 else value
        program.append((sym, value))
        known.append(sym)
    outputs = [_random_expr(rng, known[-12:], 2) for _ in range(5)]
    # One that nothing reads, at the end.
    program.append((sx.symbol(f"_v{size}"), known[-1] * inputs[0] + 1))
    return program, outputs


def _evaluate(program: list[tuple[sx.Expr, sx.Expr]], outputs: list[sx.Expr]) -> list[float]:
    env = dict(POINT)
    for sym, value in program:
        env[str(sym)] = _value(value, env)
    return [_value(o, env) for o in outputs]


def _on_ids(
    dag: Dag, program: list[tuple[sx.Expr, sx.Expr]], outputs: list[sx.Expr]
) -> tuple[Program, list[int]]:
    return [(dag.intern(s), dag.intern(v)) for s, v in program], [dag.intern(o) for o in outputs]


def _plain_needed(dag: Dag, program: Program, outputs: list[int]) -> Program:
    """programs.needed written the obvious way: reachable symbols, a set."""
    reached: set[int] = set()
    stack = list(outputs)
    values = dict(program)
    while stack:
        node = stack.pop()
        if node in reached:
            continue
        reached.add(node)
        stack.extend(dag.args[node])
        if node in values:
            stack.append(values[node])
    return [(s, v) for s, v in program if s in reached]


def _plain_leaves(dag: Dag, root: int) -> set[int]:
    found: set[int] = set()
    stack = [root]
    while stack:
        node = stack.pop()
        if dag.args[node]:
            stack.extend(dag.args[node])
        else:
            found.add(node)
    return found


@pytest.mark.parametrize("seed", range(6))
def test_reading_a_program_keeps_one_id_per_value(seed: int) -> None:
    """Children looked up in place (in Dag.intern) give the ids a call per child gives:
    equal subtrees one id, each id's expression the subtree, whatever the reading order."""
    with sx.using("symengine"):
        program, outputs = _random_program(seed)
        forward, backward = Dag(), Dag()
        ids = [forward.intern(v) for _, v in program] + [forward.intern(o) for o in outputs]
        exprs = [v for _, v in program] + outputs
        back = [backward.intern(e) for e in reversed(exprs)][::-1]
        for i, j, e in zip(ids, back, exprs, strict=True):
            assert forward.expression(i) == e
            assert backward.expression(j) == e
        # Equal expressions, one id; different ones, different ids (in both tables).
        for a, ea in zip(ids, exprs, strict=True):
            for b, eb in zip(ids, exprs, strict=True):
                assert (a == b) == (ea == eb)


@pytest.mark.parametrize("seed", range(6))
def test_substitution_on_ids_is_the_engines_substitution(seed: int) -> None:
    """Dag.substitute (a method walk, one memo over many calls) gives, for each value,
    the expression xreplace gives, in numbers, and with a fresh memo the same ids."""
    with sx.using("symengine"):
        program, outputs = _random_program(seed)
        rng = random.Random(100 + seed)
        inputs = sx.symbols(NAMES)
        mapping = {s: _random_expr(rng, inputs, 2) for s in rng.sample(inputs, 3)}
        dag = Dag()
        ids, outs = _on_ids(dag, program, outputs)
        on_ids = {dag.intern(k): dag.intern(v) for k, v in mapping.items()}
        shared: dict[int, int] = {}
        # The program's symbols read as inputs here: each value is substituted alone.
        env = dict(POINT) | {str(s): 0.1 * i - 1.3 for i, (s, _) in enumerate(program)}
        for (_, value_id), (_, value) in zip(ids, program, strict=True):
            made = dag.substitute(value_id, on_ids, shared)
            assert made == dag.substitute(value_id, on_ids, {})
            want = value.xreplace(mapping)
            assert _value(dag.expression(made), env) == pytest.approx(
                _value(want, env), rel=1e-12, abs=1e-12
            )


@pytest.mark.parametrize("seed", range(6))
def test_what_the_outputs_need_and_the_leaves_they_read(seed: int) -> None:
    """programs.needed (a bytearray of marks) keeps what a plain reachability keeps, in
    order; programs.leaves finds the wanted leaves a plain walk finds, each once."""
    with sx.using("symengine"):
        program, outputs = _random_program(seed)
        dag = Dag()
        ids, outs = _on_ids(dag, program, outputs)
        for part in (outs, outs[:1], outs[2:4], []):
            assert programs.needed(dag, ids, part) == _plain_needed(dag, ids, part)
        assert len(programs.needed(dag, ids, outs)) < len(ids)  # something is dead
        wanted = {sym: value for sym, value in ids[::2]}
        for _, value in ids:
            found = programs.leaves(dag, value, wanted)
            assert len(found) == len(set(found))
            assert set(found) == {leaf for leaf in _plain_leaves(dag, value) if leaf in wanted}
            assert programs.leaves(dag, value, {}) == []


@pytest.mark.parametrize("seed", range(4))
def test_a_program_marked_pruned_reduces_as_the_whole_one(seed: int) -> None:
    """_reduce_dag of the needed part, marked pruned, gives the kernel the whole program
    gives (same text), and both compute the program's outputs."""
    with sx.using("symengine"):
        program, outputs = _random_program(seed, size=60)
        want = _evaluate(program, outputs)
        made = []
        for pruned in (False, True):
            dag = Dag()
            ids, outs = _on_ids(dag, program, outputs)
            if pruned:
                ids = programs.needed(dag, ids, outs)
            order, reduced = numbering._reduce_dag(dag, ids, outs, False, pruned=pruned)
            body, final = numbering._number_dag(dag, order, reduced)
            made.append(([(str(s), sx.text(v)) for s, v in body], [sx.text(e) for e in final]))
            assert _evaluate(list(body), list(final)) == pytest.approx(want, rel=1e-10, abs=1e-12)
        assert made[0] == made[1]


@pytest.mark.parametrize("seed", range(4))
def test_factored_kept_across_kernels_is_factored_afresh(seed: int) -> None:
    """coefficients.factored keeps its rewrite of a node for the next kernel of the table: the
    second kernel's program comes out as in a table of its own, in ids' expressions and
    in numbers, with no more operations than before."""
    with sx.using("symengine"):
        program, outputs = _random_program(seed)
        doubled = [(s, 2 * v) for s, v in program]
        shared = Dag()
        first_ids, first_outs = _on_ids(shared, doubled, outputs)
        factored(shared, first_ids, first_outs)
        second_ids, second_outs = _on_ids(shared, doubled, outputs[::-1])
        kept, kept_outs = factored(shared, second_ids, second_outs)
        fresh = Dag()
        ids, outs = _on_ids(fresh, doubled, outputs[::-1])
        alone, alone_outs = factored(fresh, ids, outs)
        for (_, a), (_, b) in zip(kept, alone, strict=True):
            assert shared.expression(a) == fresh.expression(b)
        for a, b in zip(kept_outs, alone_outs, strict=True):
            assert shared.expression(a) == fresh.expression(b)
        values = [shared.expression(v) for _, v in kept]
        assert cse.operation_count(values) <= cse.operation_count([v for _, v in doubled])
        env = dict(POINT)
        for (sym, _), value in zip(doubled, values, strict=True):
            env[str(sym)] = _value(value, env)
        assert [_value(shared.expression(o), env) for o in kept_outs] == pytest.approx(
            _evaluate(doubled, outputs[::-1]), rel=1e-10, abs=1e-12
        )


@pytest.mark.parametrize("engine", ["symengine", "sympy"])
def test_constant_outputs_cost_what_each_entry_costs(engine: str) -> None:
    """_constant_ops counts each distinct number once and multiplies: a Hessian of
    zeros costs nothing, a negative or a fraction one each, a float 0.5 nothing beside
    a rational 1/2 that costs one (they may compare equal, they do not cost alike)."""
    with sx.using(engine):
        x = sx.symbol("x")
        entries = [sx.ZERO] * 500 + [sx.Rational(1, 2)] * 3 + [sx.Float(0.5)] * 4
        entries += [sx.Integer(-3)] * 5 + [sx.Integer(7), x + 1]
        outputs = [("h", (len(entries),), entries, "entries")]
        want = sum(cse.operation_count([e]) for e in entries if isinstance(e, sx.Number))
        assert want == 3 + 5
        assert assembly._constant_ops(outputs) == want
