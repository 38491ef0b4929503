"""The DAG's CSE on SymEngine (tvopt_codegen.cse.dag): forms it writes, in numbers.

A rational times a sum distributed on ids (as the engine's rebuild distributes it), sums
of terms with one coefficient written ``c*(...)``, ``(1/2)*_t`` of ``_t = 2*x`` read as
``x``, and sums whose SymEngine hashes collide kept apart.
"""

from __future__ import annotations

import pytest

from tvopt_codegen import cse
from tvopt_codegen import symbolic as sx
from tvopt_codegen.cse.coefficients import factored
from tvopt_codegen.cse.dag import Dag
from tvopt_codegen.cse.rewrite import _distributed
from tvopt_codegen.lowering.kernel import Arg

from .engine_cases import float_value

POINT = {"a": 0.31, "b": -0.77, "c": 1.3, "d": 0.45, "x": -1.1, "y": 0.6}


def _value(expr: sx.Expr, env: dict[str, float] | None = None) -> float:
    value: float = float_value(expr, POINT if env is None else env, {}, str)
    return value


def _program_values(
    body: tuple[tuple[sx.Expr, sx.Expr], ...], outs: tuple[sx.Expr, ...]
) -> list[float]:
    env = dict(POINT)
    for sym, value in body:
        env[str(sym)] = _value(value, env)
    return [_value(o, env) for o in outs]


def test_dag_distributes_a_rational_over_a_sum_on_ids() -> None:
    """c*x with x a sum is made on ids as the engine's rebuild makes it (c*a + c*b, a
    term that is a number times a sum distributed in turn, like terms collected), with
    the same value; a float coefficient is not distributed."""
    with sx.using("symengine"):
        a, b, c, x = sx.symbols(["a", "b", "c", "x"])
        half = sx.Rational(1, 2)
        cases = [
            (2 * x, a + b),
            (-x, a - b * c),
            (half * x, 2 * a + 2 * b - 4),
            (3 * x, a + sx.Mul(2, b + c)),  # SymEngine keeps 2*(b + c) as a term
            (-3 * x, 1 + a + sx.sin(b)),
        ]
        for before, value in cases:
            dag = Dag()
            made = dag.substitute(dag.intern(before), {dag.intern(x): dag.intern(value)}, {})
            assert dag.expr[made] is None, before  # made on ids, not by the engine
            built = dag.expression(made)
            want = _distributed(before.xreplace({x: value}))
            assert built == want, (before, value)
            assert _value(built) == pytest.approx(_value(before.xreplace({x: value})))
        assert dag.expression(made) == -3 - 3 * a - 3 * sx.sin(b)
        dag = Dag()
        floating = dag.substitute(
            dag.intern(sx.Float(0.5) * x), {dag.intern(x): dag.intern(a + b)}, {}
        )
        assert dag.expression(floating).is_Mul  # 0.5*(a + b): the engine's, whole


def test_dag_writes_sums_of_one_coefficient_as_a_product() -> None:
    """2*a*b + 2*c*d (five operations) becomes 2*(a*b + c*d) (four), -2*a + 2*b
    2*(b - a), and a coefficient merges into a product's; mixed, unit and float
    coefficients and a function's argument are left alone."""
    with sx.using("symengine"):
        a, b, c, d, x, y = sx.symbols(["a", "b", "c", "d", "x", "y"])
        cases = [
            (2 * a * b + 2 * c * d, 2 * (a * b + c * d), 1),
            (-2 * a + 2 * b, 2 * (b - a), 1),
            (3 * x * (2 * a + 2 * b), 6 * x * (a + b), 2),
            (sx.Rational(1, 2) * x * (2 * a + 2 * b), x * (a + b), 3),
            (sx.Rational(3, 2) * a + sx.Rational(-3, 2) * b - sx.Rational(3, 2), None, 2),
            (2 * a + 3 * b, None, 0),
            (a + b, None, 0),
            (2.0 * a + 2.0 * b, None, 0),
            (sx.sin(2 * a + 2 * b), None, 0),
        ]
        for expr, want, saved in cases:
            dag = Dag()
            node = dag.intern(expr)
            program, (out,) = factored(dag, [(dag.intern(y), node)], [dag.intern(y + x)])
            ((_, made),) = program
            built = dag.expression(made)
            if want is not None:
                assert built == want, expr
            elif not saved:
                assert built == expr, expr
            assert _value(built) == pytest.approx(_value(expr), rel=1e-14), expr
            assert dag.operations([made]) == cse.operation_count([expr]) - saved, expr
            assert dag.operations([made]) == cse.operation_count([built]), expr
            assert out == dag.intern(y + x)


def test_ordered_cse_reads_half_of_a_doubled_temporary_as_its_half() -> None:
    """_t1 = 2*_t0 used twice, and (1/2)*_t1: that one is _t0 (unicycle_switch_refs'
    invariant part had (1/2)*(2*x)); half of a doubled sin(x + y) stays, as sin(x + y)
    alone would cost two operations where (1/2)*_t costs one."""
    with sx.using("symengine"):
        x, y, t0, t1, t2 = sx.symbols(["x", "y", "_u0", "_u1", "_u2"])
        for first, ops in ((sx.sin(x + y), 7), (x + y, 6)):
            program = [(t0, first), (t1, 2 * t0), (t2, sx.Rational(1, 2) * t1)]
            outputs = [t1 * x, t1 * y, t2 + x, t0 * y]
            body, outs = cse.ordered_cse(program, outputs, search=False)
            env = dict(POINT)
            for sym, value in program:
                env[str(sym)] = _value(value, env)
            want = [_value(o, env) for o in outputs]
            assert _program_values(body, outs) == pytest.approx(want, rel=1e-14)
            text = [str(v) for _, v in body] + [str(o) for o in outs]
            assert not any("1/2" in part for part in text), text
            assert cse.operation_count([v for _, v in body] + list(outs)) == ops, text
        doubled = [(t1, 2 * sx.sin(x + y)), (t2, sx.Rational(1, 2) * t1)]
        body, outs = cse.ordered_cse(doubled, [t1 * x, t1 * y, t2 + x], search=False)
        assert any("1/2" in str(v) for _, v in body) or any("1/2" in str(o) for o in outs)


def test_dag_keeps_sums_of_colliding_hashes_apart() -> None:
    """SymEngine's hash of a + b collides for sums of neighbouring symbols: hundreds of
    distinct sums of one hash. Each is its own node, found again as that node, and read
    back as itself."""
    with sx.using("symengine"):
        symbols = [sx.symbol(f"_g{i}") for i in range(402)]
        sums = [symbols[i] + symbols[i + 1] for i in range(400)]
        hashes = [hash(s) for s in sums]
        assert len(set(hashes)) < len(sums)  # the collisions this guards against
        dag = Dag()
        ids = [dag.intern(s) for s in sums]
        assert len(set(ids)) == len(sums)
        assert [dag.intern(s) for s in sums] == ids
        assert [dag.intern(symbols[i + 1] + symbols[i]) for i in range(400)] == ids
        assert all(dag.expression(i) == s for i, s in zip(ids, sums, strict=True))
        nested = dag.intern(sx.sin(sums[7]) * sums[7])
        assert dag.args[nested] == tuple(sorted((ids[7], dag.intern(sx.sin(sums[7])))))


def test_kernels_sign_mirrored_odd_functions_read_into_the_dag() -> None:
    """tanh((a - t)/x) and tanh((t - a)/x), their symbols renamed to slots: the kernels
    (one, and two over one program) sign them on the DAG, evaluate one tanh and compute
    the program's values."""
    with sx.using("symengine"):
        t, a, x, y, z, e, f = sx.symbols(["t", "a", "x", "y", "z", "_e", "_f"])
        p0, p1, s0, s1 = sx.symbols(["_p0", "_p1", "_s0", "_s1"])
        inputs = [
            Arg("t", (), (), "time"),
            Arg("s", (s0, s1), ("y", "z"), "state"),
            Arg("p", (p0, p1), ("a", "x"), "parameters"),
        ]
        program = [(e, sx.tanh((a - t) / x)), (f, sx.tanh((t - a) / x))]
        exprs = [e * z + f * y, e * y - f * z + sx.sinh(t - a)]
        subs = {a: p0, x: p1, y: s0, z: s1}
        env = {"t": 0.3, "a": 0.2, "x": 1.7, "y": -0.4, "z": 0.9}
        for sym, value in program:
            env[str(sym)] = _value(value, env)
        want = [_value(o, env) for o in exprs]
        slots = {"t": 0.3, "_p0": 0.2, "_p1": 1.7, "_s0": -0.4, "_s1": 0.9}
        one = cse.make_kernel("k", "", inputs, program, [("o", (2,), exprs, "")], subs, odd={})
        two = cse.make_kernels(
            [("k1", "", inputs, [("o", (1,), exprs[:1], "")])]
            + [("k2", "", inputs, [("o", (1,), exprs[1:], "")])],
            program,
            subs,
            odd={},
        )
        for kernels in ([one], two):
            got: list[float] = []
            for kernel in kernels:
                values = dict(slots)
                for sym, value in kernel.body:
                    values[str(sym)] = _value(value, values)
                got += [_value(o, values) for out in kernel.outputs for o in out.exprs]
                text = " ".join(str(v) for _, v in kernel.body) + str(kernel.outputs)
                assert text.count("tanh(") == 1, text
            assert got == pytest.approx(want, rel=1e-14)


def test_kernels_over_one_program_refuse_a_symbol_they_are_not_given() -> None:
    """The kernels cut from one program read their symbols off the DAG: the program's
    temporaries are bound, a symbol the inputs do not give is refused, by name."""
    with sx.using("symengine"):
        x, y, stray, g = sx.symbols(["x", "y", "_stray", "_g"])
        inputs = [Arg("s", (x, y), ("x", "y"), "state")]
        program = [(g, sx.sin(x) * y)]
        kernels = cse.make_kernels(
            [("k1", "", inputs, [("o", (1,), [g + x], "")])]
            + [("k2", "", inputs, [("o", (1,), [g * y], "")])],
            program,
            {},
        )
        assert [k.ops for k in kernels] == [3, 3]
        with pytest.raises(AssertionError, match=r"kernel k2: unbound symbols \['_stray'\]"):
            cse.make_kernels(
                [("k1", "", inputs, [("o", (1,), [g + x], "")])]
                + [("k2", "", inputs, [("o", (1,), [g * stray], "")])],
                program,
                {},
            )
