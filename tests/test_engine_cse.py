"""The CSE (tvopt_codegen.cse) on SymEngine: the kernels of SymPy's, in value and size.

Each example is derived and lowered on SymPy (the reference) while the calls lowering
makes to the CSE are recorded; the same calls, their expressions converted at the border,
are then made on SymEngine. The kernels must compute the same numbers at random inputs
(1e-12 relative), cost at most 5 % more operations (issue 49) and come out the same on
every run.
"""

from __future__ import annotations

import os
import random
import subprocess
import sys
from collections.abc import Callable, Iterator
from typing import Any

import pytest

from tvopt_codegen import cse
from tvopt_codegen import symbolic as sx
from tvopt_codegen.cse import numbering
from tvopt_codegen.cse.dag import Dag
from tvopt_codegen.lowering import ir
from tvopt_codegen.lowering.kernel import Arg, Kernel
from tvopt_codegen.symbolic.border import from_sympy

from .conftest import ROOT, derivation
from .engine_cases import float_value

#: A recorded call: its kind (``kernel``, ``kernels``, ``split``), arguments, result.
Call = tuple[str, tuple[Any, ...], Any]


def _record(spec: str, monkeypatch: pytest.MonkeyPatch) -> list[Call]:
    """The calls ``lower`` makes to the CSE for ``spec`` on SymPy, with their kernels.

    A kernel's call is recorded with its ``search`` flag last (True unless given).
    """
    calls: list[Call] = []

    def recording(kind: str, function: Callable[..., Any]) -> Callable[..., Any]:
        def call(*args: Any, **options: Any) -> Any:
            result = function(*args, **options)
            search = (options.get("search", True),) if kind == "kernel" else ()
            # A group's riders and companions (make_kernels' options) are replayed too.
            riding = (options,) if kind == "kernels" else ()
            calls.append((kind, (*args, *search, *riding), result))
            return result

        return call

    for kind, name in (
        ("kernel", "make_kernel"),
        ("kernels", "make_kernels"),
        ("split", "split_invariant"),
    ):
        monkeypatch.setattr(ir, name, recording(kind, getattr(ir, name)))
    with sx.using("sympy"):  # the reference, whichever engine is the default
        ir.lower(derivation(spec))
    monkeypatch.undo()
    return calls


def _arg(arg: Arg, convert: Callable[[Any], Any]) -> Arg:
    return Arg(arg.name, tuple(convert(s) for s in arg.symbols), arg.labels, arg.doc)


def _outputs(outputs: Any, convert: Callable[[Any], Any]) -> list[Any]:
    return [(name, shape, [convert(e) for e in exprs], doc) for name, shape, exprs, doc in outputs]


def _replay(calls: list[Call]) -> list[Kernel]:
    """The recorded calls made again on the current engine; the kernels ``lower`` keeps."""
    memo: dict[Any, Any] = {}

    def convert(expr: Any) -> Any:
        return from_sympy(expr, memo)

    odd: dict[Any, Any] = {}
    symbols: dict[Any, Any] = {}
    made: dict[int, Kernel] = {}
    kernels: list[Kernel] = []
    for kind, args, result in calls:
        if kind == "kernel":
            name, doc, inputs, program, outputs, subs, search = args
            kernel = cse.make_kernel(
                name,
                doc,
                [_arg(a, convert) for a in inputs],
                [(convert(s), convert(v)) for s, v in program],
                _outputs(outputs, convert),
                {convert(s): convert(v) for s, v in subs.items()},
                odd,
                search,
                symbols,
            )
            made[id(result)] = kernel
            kernels.append(kernel)
        elif kind == "kernels":
            specs, program, subs = args[:3]
            options = args[-1]

            def spec(name: str, doc: str, inputs: Any, outputs: Any) -> Any:
                return (name, doc, [_arg(a, convert) for a in inputs], _outputs(outputs, convert))

            group = cse.make_kernels(
                [spec(*entry) for entry in specs],
                [(convert(s), convert(v)) for s, v in program],
                {convert(s): convert(v) for s, v in subs.items()},
                odd,
                symbols,
                riders=[
                    (*spec(*rider[:4]), {convert(a): convert(b) for a, b in rider[4].items()})
                    for rider in options.get("riders", ())
                ],
                companions=[spec(*entry) for entry in options.get("companions", ())],
            )
            made.update((id(old), new) for old, new in zip(result, group, strict=True))
            kernels.extend(group)
        else:
            jet = made[id(args[0])]
            split = cse.split_invariant(jet, *args[1:])
            if split is not None:
                kernels.remove(jet)
                kernels.extend(split)
    return kernels


def _recorded(calls: list[Call]) -> list[Kernel]:
    """The kernels the recorded calls made on SymPy, as :func:`_replay` lists them."""
    kernels: list[Kernel] = []
    for kind, args, result in calls:
        if kind == "split":
            if result is not None:
                kernels.remove(args[0])
                kernels.extend(result)
        else:
            kernels.extend(result if kind == "kernels" else [result])
    return kernels


def _run(kernel: Kernel, seed: int, given: dict[str, list[float]] | None = None) -> list[float]:
    """The kernel's outputs, flat, at random inputs (``given`` arrays by argument name).

    Each input is drawn by its name: the jet and its ``jet_time`` (which reads a subset
    of the jet's inputs, in another order) see the same parameters and time.
    """
    env = {"t": 0.37}
    for arg in kernel.inputs:
        drawn = [random.Random(f"{seed} {sym}").uniform(0.2, 1.2) for sym in arg.symbols]
        env.update(zip(map(str, arg.symbols), (given or {}).get(arg.name, drawn), strict=True))
    for sym, value in kernel.body:
        env[str(sym)] = float_value(value, env, {}, str)
    memo: dict[Any, Any] = {}
    return [float_value(e, env, memo, str) for out in kernel.outputs for e in out.exprs]


def _values(kernels: list[Kernel], seed: int) -> Iterator[tuple[str, list[float]]]:
    """Each kernel's outputs; the jet reads the ``tau`` its own ``jet_time`` computed."""
    by_name = {k.name: k for k in kernels}
    tau = {"tau": _run(by_name["jet_time"], seed)} if "jet_time" in by_name else None
    for kernel in kernels:
        # tau holds the terms of time and parameters as each engine's sums and products
        # split them (split_invariant): other terms, checked through the jet that adds
        # them up, at the jet's own time and parameters (_run).
        if kernel.name != "jet_time":
            yield kernel.name, _run(kernel, seed, tau)


def _text(kernels: list[Kernel]) -> list[str]:
    return [
        f"{k.name} {k.ops} {k.body} {[out.exprs for out in k.outputs]} {k.inputs}" for k in kernels
    ]


@pytest.mark.parametrize("spec", ["pvtol", "unicycle_ring", "planar_arm3", "unicycle_switch"])
def test_symengine_kernels_compute_sympys_values_in_as_many_operations(
    spec: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    calls = _record(spec, monkeypatch)
    reference = _recorded(calls)
    assert all(type(v).__module__.startswith("sympy") for k in reference for _, v in k.body)
    with sx.using("sympy"):
        want = {seed: dict(_values(reference, seed)) for seed in range(2)}
    with sx.using("symengine"):
        kernels = _replay(calls)
        again = _replay(calls)
        assert all(isinstance(v, sx.Basic) for k in kernels for _, v in k.body)
        got = {seed: dict(_values(kernels, seed)) for seed in range(2)}
        for kernel in kernels:
            # Counted on the DAG's ids, as operation_count counts the kernel's expressions
            # (on SymEngine, whose trees these are: the count reads the engine's nodes).
            exprs = [v for _, v in kernel.body] + [e for out in kernel.outputs for e in out.exprs]
            assert kernel.ops == cse.operation_count(exprs), kernel.name
    assert _text(kernels) == _text(again)
    assert [k.name for k in kernels] == [k.name for k in reference]
    assert want[0].keys() == got[0].keys()
    for seed in range(2):
        for name, values in want[seed].items():
            scale = max((abs(v) for v in values), default=0.0)
            assert got[seed][name] == pytest.approx(values, rel=1e-12, abs=1e-12 * scale), name
    for mine, theirs in zip(kernels, reference, strict=True):
        # A few operations either way on the smallest kernels, where the two engines'
        # searches for common sub-sums (sx.cse) take different turns.
        assert mine.ops <= max(1.05 * theirs.ops, theirs.ops + 4), (mine.name, mine.ops)
    assert sum(k.ops for k in kernels) <= 1.05 * sum(k.ops for k in reference)


def test_symengine_merges_mirrored_differences_and_odd_functions() -> None:
    """SymEngine keeps ``-(x - y)`` a product and ``tanh((a - t)/x)`` and
    ``tanh((t - a)/x)`` apart, as SymPy does the latter: both are merged all the same."""
    with sx.using("symengine"):
        t, x, y, z, a = sx.symbols(["t", "x", "y", "z", "a"])
        c, d, e, f = sx.symbols(["c", "d", "e", "f"])
        memo: dict[Any, Any] = {}
        first = cse.canonical_odd(sx.tanh((a - t) / x), memo)
        second = cse.canonical_odd(sx.tanh((t - a) / x), memo)
        assert first == -second
        program = [(c, y - x), (d, x - y), (e, sx.tanh((a - t) / x)), (f, sx.tanh((t - a) / x))]
        outputs = [c * z + d * y, e * z + f * y, c * e + d * f + z]
        signed = [(sym, cse.canonical_odd(value, memo)) for sym, value in program]
        body, outs = cse.ordered_cse(signed, outputs, search=False)
        assert len(body) == 2  # x - y once, and one tanh
        point = {"t": 0.3, "x": 1.7, "y": -0.4, "z": 0.9, "a": 0.2}
        env = dict(point)
        for sym, value in program:
            env[str(sym)] = float_value(value, env, {}, str)
        want = [float_value(o, env, {}, str) for o in outputs]
        env = dict(point)
        for sym, value in body:
            env[str(sym)] = float_value(value, env, {}, str)
        assert [float_value(o, env, {}, str) for o in outs] == pytest.approx(want, rel=1e-14)


def test_symengine_inlining_collects_terms_as_sympy_does() -> None:
    """``2*_g - 2*a`` with ``_g = a + b`` inlined is ``2*b`` on both engines (SymEngine
    keeps ``2*(a + b)`` a product unless the CSE distributes it): terms that cancel
    vanish, as most of a chain's jet does."""
    for engine in ("sympy", "symengine"):
        with sx.using(engine):
            a, b, g, h = sx.symbols(["a", "b", "_g", "_h"])
            order = [(g, a + b), (h, 2 * g - 2 * a)]
            kept, outs = numbering._inline_single_use(order, [a * h + b * h])
            assert kept == [(h, 2 * b)], engine
            assert outs == [a * h + b * h]


def test_engine_cse_searches_sums_and_names_in_order_on_both_engines() -> None:
    for engine in ("sympy", "symengine"):
        with sx.using(engine):
            x, y, z, taken = sx.symbols(["x", "y", "z", "_cse0"])
            exprs = [x * y * z + sx.sin(x * y) + taken, x * y * taken + 2 * sx.sin(x * y)]
            replacements, reduced = sx.cse(exprs, numbering.numbered("_cse"))
            assert [str(sym) for sym, _ in replacements] == ["_cse1", "_cse2"], engine
            values = dict(replacements)
            assert values[sx.symbol("_cse1")] == x * y
            inline = {sym: value.xreplace(values) for sym, value in replacements}
            assert [e.xreplace(inline) for e in reduced] == exprs


#: A small program's CSE on SymEngine, as text: mirrored odd functions and differences.
_SMALL_KERNEL = """
from tvopt_codegen import cse
from tvopt_codegen import symbolic as sx


def text():
    with sx.using("symengine"):
        t, x, y, z, a, b, g0, g1, g2, g3 = sx.symbols(
            ["t", "x", "y", "z", "a", "b", "_g0", "_g1", "_g2", "_g3"]
        )
        program = [
            (g0, sx.tanh((a - t) / b) * x),
            (g1, sx.tanh((t - a) / b) + y - x),
            (g2, (x - y) * g0 + z),
            (g3, g1 * g2 + sx.sin(z - t)),
        ]
        odd = {}
        program = [(sym, cse.canonical_odd(value, odd)) for sym, value in program]
        body, outs = cse.ordered_cse(program, [g3 + g2, g3 * x - g0, sx.sin(t - z) * g1])
        return f"{body} {outs}"
"""


def test_symengine_kernels_do_not_depend_on_the_hash_seed() -> None:
    """SymEngine's argument order comes from its C++ hashes, not Python's: a process with
    another PYTHONHASHSEED makes the same kernel."""
    namespace: dict[str, Any] = {}
    exec(_SMALL_KERNEL, namespace)  # noqa: S102 - the test's own program, run twice
    here = namespace["text"]()
    seed = "2" if os.environ.get("PYTHONHASHSEED") == "1" else "1"
    env = {**os.environ, "PYTHONHASHSEED": seed, "TVOPT_CODEGEN_ENGINE": "symengine"}
    there = subprocess.run(
        [sys.executable, "-c", _SMALL_KERNEL + "\nprint(text())"],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    assert "tanh" in here and there.strip() == here


def test_symengine_symbols_in_is_the_union_of_free_symbols() -> None:
    with sx.using("symengine"):
        x, y, z, t = sx.symbols(["x", "y", "z", "t"])
        exprs = [x * y + sx.sin(z), sx.Integer(2), sx.tanh((t - x) / y) ** 2, 3]
        assert cse.symbols_in(exprs) == {x, y, z, t}
        assert cse.symbols_in([]) == set()
        out = [("o", (1,), [x * y], "")]
        given = [Arg("s", (x, y), ("x", "y"), "")]
        assert cse.make_kernel("k", "", given, [], out, {}).ops == 1
        # A kernel reading y, which it is not given, is refused.
        with pytest.raises(AssertionError, match=r"unbound symbols \['y'\]"):
            cse.make_kernel("k", "", [Arg("s", (x,), ("x",), "")], [], out, {})


def _dag_program(seed: int, size: int) -> tuple[list[tuple[Any, Any]], list[Any]]:
    """A random three-address program over x, y, z: sums, products, negations, sines,
    squares and differences both ways round (merged), each reading earlier symbols."""
    rng = random.Random(seed)
    known = list(sx.symbols(["x", "y", "z"]))
    program = []
    for i in range(size):
        a, b = rng.choice(known), rng.choice(known)
        value = rng.choice(
            [a + b, a * b, a - b, b - a, 2 * a - 3 * b, sx.sin(a - b), a**2 + 1, -a * b]
        )
        sym = sx.symbol(f"_g{i}")
        program.append((sym, value))
        known.append(sym)
    outputs = [known[-1] + known[-2], known[-3] * known[5] - known[7], sx.sin(known[-4])]
    return program, outputs


def _program_values(program: Any, outputs: Any, point: dict[str, float]) -> list[float]:
    env = dict(point)
    for sym, value in program:
        env[str(sym)] = float_value(value, env, {}, str)
    return [float_value(o, env, {}, str) for o in outputs]


def test_dag_cse_computes_the_expression_walks_values_in_as_few_operations() -> None:
    """ordered_cse on SymEngine (over the DAG of ids) against the walks over expressions
    it replaced (numbering._reduce), on random programs: the same values, no more
    operations, and the same text when made again."""
    point = {"x": 0.31, "y": -0.77, "z": 1.3}
    with sx.using("symengine"):
        for seed in range(4):
            program, outputs = _dag_program(seed, 60)
            body, outs = cse.ordered_cse(program, outputs, search=False)
            again = cse.ordered_cse(program, outputs, search=False)
            walked, walked_outs = numbering._number(
                *numbering._reduce(program, outputs, search=False)
            )
            want = _program_values(program, outputs, point)
            assert _program_values(body, outs, point) == pytest.approx(want, rel=1e-12)
            assert _program_values(walked, walked_outs, point) == pytest.approx(want, rel=1e-12)
            ops = cse.operation_count([v for _, v in body] + list(outs))
            walked_ops = cse.operation_count([v for _, v in walked] + list(walked_outs))
            assert ops <= walked_ops, seed
            assert str((body, outs)) == str(again)
            searched = cse.ordered_cse(program, outputs)
            assert _program_values(*searched, point) == pytest.approx(want, rel=1e-12)


def test_dag_nodes_made_on_ids_are_what_their_expressions_are() -> None:
    """Nodes made on ids (renames, spliced sums and products) count the operations of
    the expressions the engine builds for them, and read back as themselves."""
    with sx.using("symengine"):
        for seed in range(3):
            program, outputs = _dag_program(seed, 50)
            dag = Dag()
            ids = [(dag.intern(sym), dag.intern(value)) for sym, value in program]
            numbering._reduce_dag(dag, ids, [dag.intern(e) for e in outputs], False)
            made = [i for i, e in enumerate(dag.expr) if e is None]
            assert made, seed
            for i in made:
                expr = dag.expression(i)
                assert dag.operations([i]) == cse.operation_count([expr]), expr
                fresh = Dag()
                assert fresh.operations([fresh.intern(expr)]) == dag.operations([i])


def test_dag_shares_equal_subtrees_and_tells_functions_apart() -> None:
    with sx.using("symengine"):
        x, y, z = sx.symbols(["x", "y", "z"])
        dag = Dag()
        first = dag.intern(sx.sin(x * y) + x * y + z)
        second = dag.intern(z + y * x + sx.sin(y * x))
        assert first == second
        assert dag.intern(sx.Function("f")(x)) != dag.intern(sx.Function("g")(x))
        assert dag.expression(first) == sx.sin(x * y) + x * y + z
        # Operations counted on ids are operation_count's.
        exprs = [first, dag.intern(-x * y + (x - y) / z), dag.intern(x**-1 * (y - 1) / 3)]
        assert dag.operations(exprs) == cse.operation_count([dag.expression(e) for e in exprs])


def test_dag_negation_reads_opposites_off_the_table() -> None:
    """-(x - y) is y - x, -(2*x*y) is -2*x*y, when the table holds them; None when not."""
    with sx.using("symengine"):
        x, y, z = sx.symbols(["x", "y", "z"])
        dag = Dag()
        difference = dag.intern(x - y)
        assert dag.negation(difference) is None
        assert dag.negation(dag.intern(y - x)) == difference
        product = dag.intern(2 * x * y)
        assert dag.negation(product) is None
        assert dag.negation(dag.intern(-2 * x * y)) == product
        opposite = dag.intern(x * sx.sin(z))
        assert dag.negation(dag.intern(-x * sx.sin(z))) == opposite
        minus_sine = dag.intern(-sx.sin(z))
        assert dag.negation(dag.intern(sx.sin(z))) == minus_sine


def test_dag_substitutions_build_what_the_constructor_builds() -> None:
    """A substitution that only renames, splices sums or products, or collects like
    terms with rational coefficients is made on ids (its expression built when asked);
    one that would make factors meet (x*y**2 with x -> y), cancel a sum whole or give a
    function equal arguments is built by the engine's constructor."""
    with sx.using("symengine"):
        x, y, z, w = sx.symbols(["x", "y", "z", "w"])
        dag = Dag()
        cases = [
            (x + sx.sin(z), w, w + sx.sin(z), True),
            (x * y * z, w, w * y * z, True),
            (sx.atan2(x, z), w, sx.atan2(w, z), True),
            (3 * x * y, -w, -3 * w * y, True),  # a sign goes to the coefficient
            (x + z, -w, z - w, True),
            (x + 2 * y + z, y, 3 * y + z, True),  # like terms collected
            (x + 2 * w * z, w * z, 3 * w * z, True),
            (y * x, y + z, y * (y + z), True),
            (x - y + z, y - z, sx.Integer(0) + y - y, False),
            (x * y**2, y, y**3, False),
            (sx.atan2(x, y), y, sx.atan2(y, y), False),
            (x + 0.5 * y, y, 1.5 * y, False),  # a float's sum is the engine's
        ]
        for before, value, after, on_ids in cases:
            node = dag.intern(before)
            made = dag.substitute(node, {dag.intern(x): dag.intern(value)}, {})
            assert (dag.expr[made] is None) == on_ids, before
            assert dag.expression(made) == after, before
            assert dag.intern(after) == made
        # Splicing: a product into a product, a sum into a sum, numbers folded.
        node = dag.intern(2 * x * z + 1)
        made = dag.substitute(node, {dag.intern(x): dag.intern(3 * w * y)}, {})
        assert dag.expression(made) == 6 * w * y * z + 1
        made = dag.substitute(dag.intern(x + y + 1), {dag.intern(x): dag.intern(z + 2)}, {})
        assert dag.expression(made) == y + z + 3
