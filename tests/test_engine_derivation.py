"""The derivation on SymEngine gives SymPy's numbers (issue 49: one symbolic API, two engines).

Each bundled example is derived on both engines and the law is compared as functions:
every expression the code generators read (the closed-loop field, the jet's right-hand
side and its programs, R, p, the Hessian's entries, the plant input) is evaluated on
each engine at the same random points, every free symbol (states, t, parameters,
jets, the law's unknowns) drawn by name, each program's assignments in order. The two
engines build different trees (SymEngine keeps ``2*(x + y)``, orders terms its own way)
and so different programs; the values agree to rounding.
"""

from __future__ import annotations

import functools
import tomllib
import zlib
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import sympy as sp

from tvopt_codegen import symbolic as sx
from tvopt_codegen.derivation import Derivation, calculus, derive
from tvopt_codegen.derivation.law import control_law, diagonal_blocks
from tvopt_codegen.derivation.model import build_model
from tvopt_codegen.errors import SpecError
from tvopt_codegen.maths.lie import Extension
from tvopt_codegen.maths.numeric import Evaluator
from tvopt_codegen.spec import load_spec
from tvopt_codegen.symbolic.border import to_sympy

from .engine_cases import ON_A_LINE

EXAMPLES = Path(__file__).resolve().parents[1] / "tvopt_codegen" / "examples"
ENGINES = ("sympy", "symengine")
#: Sample points per comparison.
POINTS = 16


@functools.cache
def _derived(name: str, engine: str) -> Derivation:
    with sx.using(engine):
        if name == "on_a_line":
            return derive(tomllib.loads(ON_A_LINE))
        return derive(load_spec(str(EXAMPLES / f"{name}.toml")))


def _draw(name: str) -> np.ndarray:
    """The values of the symbol called ``name`` at the sample points: the same on both engines.

    Positive and away from 0, so that square roots, logarithms and quotients stay defined.
    """
    rng = np.random.default_rng(zlib.crc32(name.encode()))
    return rng.uniform(0.3, 1.3, POINTS)


def _evaluate(
    engine: str,
    exprs: Sequence[sx.Expr],
    assignments: Iterable[tuple[sx.Expr, sx.Expr]] = (),
    *,
    undefined: bool = False,
    at: Mapping[str, np.ndarray] | None = None,
) -> np.ndarray:
    """``exprs`` at the sample points (rows), on ``engine``, after the programs' assignments.

    The symbols named in ``at`` take its values, the others :func:`_draw`'s. NaN where
    undefined, when ``undefined`` allows it; otherwise everything is defined.
    """
    given = dict(at or {})
    with sx.using(engine):
        program = list(assignments)
        defined = {symbol for symbol, _ in program}
        exprs = [sx.sympify(e) for e in exprs]
        free: set[sx.Expr] = set()
        for e in (*exprs, *(value for _, value in program)):
            free |= e.free_symbols
        evaluate = Evaluator({s: given.get(str(s), _draw(str(s))) for s in free - defined})
        for symbol, value in program:
            evaluate.define(symbol, value)
        rows = [np.broadcast_to(np.asarray(evaluate(e), dtype=complex), (POINTS,)) for e in exprs]
    values = np.array(rows).reshape(len(exprs), POINTS)
    finite = np.isfinite(values)
    assert undefined or np.all(finite), "a sample point outside an expression's domain"
    return np.where(finite & (np.abs(values.imag) <= 1e-12), values.real, np.nan)


def _same(sympy_values: np.ndarray, symengine_values: np.ndarray, what: str) -> None:
    """Equal to 1e-12, relative to each quantity's own scale (an exact 0 against rounding)."""
    assert sympy_values.shape == symengine_values.shape, what
    if not sympy_values.size:
        return
    defined = np.isfinite(sympy_values)
    assert np.array_equal(defined, np.isfinite(symengine_values)), f"{what}: domains differ"
    assert defined.any(), f"{what}: defined nowhere"
    sympy_values = np.where(defined, sympy_values, 0.0)
    symengine_values = np.where(defined, symengine_values, 0.0)
    scale = np.maximum(np.abs(sympy_values).max(axis=-1, keepdims=True), 1.0)
    error = np.abs(sympy_values - symengine_values) / scale
    assert error.max(initial=0.0) <= 1e-12, f"{what}: {error.max():.3g}"


def _programs(d: Derivation) -> list[tuple[sx.Expr, sx.Expr]]:
    """Every program's assignments, in an order that evaluates each after what it reads."""
    return [
        *d.jet.signal_program.assignments,
        *d.jet.jet_program.assignments,
        *d.objective.hessian_program.assignments,
        *d.jet.rest_program.assignments,
        *d.objective.objective_program.assignments,
    ]


def _law_parts(d: Derivation, engine: str) -> dict[str, list[sx.Expr]]:
    """What the code generators evaluate, by name (the derivation is ``engine``'s)."""
    with sx.using(engine):
        return _parts(d)


def _parts(d: Derivation) -> dict[str, list[sx.Expr]]:
    law = d.law
    return {
        "closed loop": list(law.closed_loop),
        "jet right-hand side": list(law.jet_rhs),
        "R": list(law.r_entries),
        "p": list(d.decoupling.p),
        "gradient jet": [e for row in d.jet.grad_jet for e in row],
        "rest": list(d.jet.rest),
        "Hessian": [e for _, e in d.objective.hessian_entries],
        "objective gradient": list(d.objective.objective_gradient),
        "objective Hessian": list(d.objective.objective_hessian),
        "y jet": [e for row in d.jet.y_jet_values for e in row],
        "signal jet": [e for row in d.jet.signal_jet_values for e in row],
        "plant input": list(law.plant_input),
        "y_imp": list(law.y_imp or ()),
        "phi": list(d.decoupling.phi),
        "lie": [e for row in d.linearization.lie for e in row],
        "Hessian as expressions": list(d.hessian),
    }


@pytest.mark.parametrize(
    "name",
    [
        "pvtol",
        "unicycle_switch",
        "planar_arm3",
        "two_unicycles_barrier",
        "two_unicycles_corridor",
        "unicycle_ring",
    ],
)
def test_the_law_is_the_same_function_on_both_engines(name: str) -> None:
    reference, fast = _derived(name, "sympy"), _derived(name, "symengine")
    # What is not an expression is equal outright.
    assert fast.linearization.relative_degree == reference.linearization.relative_degree
    assert fast.closed_loop.state_names == reference.closed_loop.state_names
    assert fast.law.hessian_pattern == reference.law.hessian_pattern
    assert fast.law.r_blocks == reference.law.r_blocks
    assert fast.law.chains == reference.law.chains
    assert fast.law.constant_hessian == reference.law.constant_hessian
    assert [str(s) for s in fast.law.w] == [str(s) for s in reference.law.w]
    assert [str(s) for s in fast.closed_loop.states] == [
        str(s) for s in reference.closed_loop.states
    ]
    np.testing.assert_allclose(fast.closed_loop.initial_state, reference.closed_loop.initial_state)
    np.testing.assert_allclose(fast.dynamics.coefficients, reference.dynamics.coefficients)
    assert fast.objective.convexity.method == reference.objective.convexity.method
    assert fast.objective.convexity.m_f == pytest.approx(reference.objective.convexity.m_f)
    assert len(fast.warnings) == len(reference.warnings)
    assert fast.jet.reference_order == reference.jet.reference_order
    for engine, d in (("sympy", reference), ("symengine", fast)):
        assert {type(e).__module__.split(".")[0] for e in d.law.closed_loop} == {engine}
    parts = {
        engine: _law_parts(d, engine) for engine, d in (("sympy", reference), ("symengine", fast))
    }
    values = {
        engine: {
            what: _evaluate(engine, exprs, _programs(d), undefined=True)
            for what, exprs in parts[engine].items()
        }
        for engine, d in (("sympy", reference), ("symengine", fast))
    }
    for what in parts["sympy"]:
        _same(values["sympy"][what], values["symengine"][what], f"{name}: {what}")
    # The evaluator itself checked on R and p, which hold no program symbols: SymEngine's
    # expressions crossed to SymPy and lambdified there.
    with sx.using("symengine"):
        crossed = [to_sympy(e) for e in (*parts["symengine"]["R"], *parts["symengine"]["p"])]
    free = sorted(set().union(*(e.free_symbols for e in crossed)), key=str)
    numeric = sp.lambdify(free, crossed, "numpy")(*(_draw(str(s)) for s in free))
    expected = np.vstack([values["symengine"]["R"], values["symengine"]["p"]])
    _same(np.array([np.broadcast_to(v, (POINTS,)) for v in numeric], dtype=float), expected, "R, p")
    # Not all zero: the comparison compares something.
    assert np.abs(values["sympy"]["closed loop"]).max() > 0.1
    assert np.abs(values["sympy"]["R"]).max() > 0.1


def test_planar_arm3_reads_the_mass_matrix_run_time_symbols_on_both_engines() -> None:
    reference, fast = _derived("planar_arm3", "sympy"), _derived("planar_arm3", "symengine")
    names = {
        engine: sorted(str(s) for s in d.model.opaque)
        for engine, d in (("sympy", reference), ("symengine", fast))
    }
    assert names["sympy"] == names["symengine"]
    assert names["sympy"]  # M^-1 F and M^-1 B, solved at run time
    free = {str(s) for e in fast.law.closed_loop for s in e.free_symbols}
    assert set(names["symengine"]) & free


def test_the_barrier_objective_is_the_same_on_both_engines() -> None:
    # [constraints]: f0 becomes B = f0 - mu(t) sum log(s(t) - g_i).
    reference, fast = (
        _derived("two_unicycles_corridor", "sympy"),
        _derived("two_unicycles_corridor", "symengine"),
    )
    # B is defined where s(t) > g_i: near the start (t = 0, the initial outputs), where
    # s(0) exceeds the largest violation.
    model = reference.model
    at = {q.name: np.full(POINTS, v) for q, v in zip(model.params, model.defaults, strict=True)}
    at |= {
        name: np.full(POINTS, value)
        for name, value in zip(
            reference.closed_loop.state_names, reference.closed_loop.initial_state, strict=True
        )
    }
    y0 = _evaluate("sympy", list(model.h), at=at)
    at |= {y.name: y0[i] + 1e-3 * _draw(y.name) for i, y in enumerate(model.y)}
    at["t"] = 1e-3 * _draw("t")
    for what in ("f0", "mu", "slack"):
        _same(
            _evaluate("sympy", [getattr(reference.model, what)], at=at),
            _evaluate("symengine", [getattr(fast.model, what)], at=at),
            what,
        )
    assert len(fast.model.constraints) == len(reference.model.constraints) > 0
    _same(
        _evaluate("sympy", [c.g for c in reference.model.constraints]),
        _evaluate("symengine", [c.g for c in fast.model.constraints]),
        "g",
    )
    assert fast.model.objective is not None
    _same(
        _evaluate("sympy", [reference.model.objective]),
        _evaluate("symengine", [fast.model.objective]),
        "the spec's f0",
    )


@pytest.mark.parametrize("name", ["two_unicycles_barrier", "two_unicycles_corridor"])
def test_calculus_gives_the_same_derivatives_on_both_engines(name: str) -> None:
    # tan's domain in the first, the constraints' gradients in the second.
    reference, fast = _derived(name, "sympy"), _derived(name, "symengine")
    sizes: list[int] = []
    for function in (
        calculus.objective_gradient,
        calculus.objective_hessian,
        calculus.constraint_gradients,
        lambda model: calculus.nominal_jets(model, 3),
        lambda model: calculus.objective_domain(model)[0],
        lambda model: calculus.objective_domain(model)[1],
    ):
        out = {}
        for engine, d in (("sympy", reference), ("symengine", fast)):
            with sx.using(engine):
                result = function(d.model)
            flat = [e for row in result for e in (row if isinstance(row, list) else [row])]
            out[engine] = _evaluate(engine, flat)
        _same(out["sympy"], out["symengine"], str(function))
        sizes.append(len(out["sympy"]))
    # The gradient and Hessian; then tan's domain (2 per tan), or the constraints' gradients.
    assert sizes[0] and sizes[1]
    assert sizes[2] if name == "two_unicycles_corridor" else sizes[4]


def test_nominal_jets_are_the_derivatives_of_the_closed_form_on_both_engines() -> None:
    reference, fast = _derived("pvtol_refs", "sympy"), _derived("pvtol_refs", "symengine")
    jets = {}
    for engine, d in (("sympy", reference), ("symengine", fast)):
        with sx.using(engine):
            jets[engine] = calculus.nominal_jets(d.model, 3)
    assert [len(row) for row in jets["sympy"]] == [len(row) for row in jets["symengine"]] != []
    flat = {engine: [e for row in rows for e in row] for engine, rows in jets.items()}
    _same(_evaluate("sympy", flat["sympy"]), _evaluate("symengine", flat["symengine"]), "jets")
    # The first derivative is the closed form's, by a difference quotient.
    with sx.using("symengine"):
        model = fast.model
        nominal, first = jets["symengine"][0][0], jets["symengine"][0][1]
        t = model.t
        at = {q: sx.real(v) for q, v in zip(model.params, model.defaults, strict=True)}
        h = 1e-6
        quotient = (
            float(nominal.xreplace(at).xreplace({t: sx.real(0.4 + h)}))
            - float(nominal.xreplace(at).xreplace({t: sx.real(0.4 - h)}))
        ) / (2 * h)
        assert float(first.xreplace(at).xreplace({t: sx.real(0.4)})) == pytest.approx(
            quotient, rel=1e-6, abs=1e-8
        )


def test_equality_calculus_and_the_kkt_law_on_both_engines() -> None:
    reference, fast = _derived("on_a_line", "sympy"), _derived("on_a_line", "symengine")
    out = {}
    for engine, d in (("sympy", reference), ("symengine", fast)):
        with sx.using(engine):
            eq = calculus.equality_calculus(d.model)
            out[engine] = [*eq.values, *eq.jacobian, *eq.curvature(d.model.multipliers)]
        assert d.jet.n_kkt == len(d.model.y) + len(d.model.equalities)
    _same(_evaluate("sympy", out["sympy"]), _evaluate("symengine", out["symengine"]), "a, J_a")
    assert fast.decoupling.dependent_set == () or len(fast.decoupling.dependent_set) == len(
        reference.decoupling.dependent_set
    )
    for engine, d in (("sympy", reference), ("symengine", fast)):
        with sx.using(engine):
            out[engine] = list(d.kkt_hessian)
        assert len(out[engine]) == d.jet.n_kkt**2
    _same(_evaluate("sympy", out["sympy"]), _evaluate("symengine", out["symengine"]), "KKT")
    for what in ("closed loop", "jet right-hand side", "Hessian", "R"):
        _same(
            _evaluate("sympy", _law_parts(reference, "sympy")[what], _programs(reference)),
            _evaluate("symengine", _law_parts(fast, "symengine")[what], _programs(fast)),
            f"on_a_line: {what}",
        )


@pytest.mark.parametrize("engine", ENGINES)
def test_a_constant_hessian_is_inverted_exactly(engine: str) -> None:
    with sx.using(engine):
        y1, y2, g0, g1, x1, x2 = sx.symbols(["y1", "y2", "g0", "g1", "x1", "x2"])
        half = sx.Rational(1, 2)
        extension = Extension(
            states=(),
            inputs=("u1", "u2"),
            x=(x1, x2),
            f=sx.ImmutableMatrix([sx.ZERO, sx.ZERO]),
            G=sx.ImmutableMatrix([[sx.ONE, sx.ZERO], [sx.ZERO, sx.ONE]]),
            counts=(),
        )
        u = sx.symbols(["u1", "u2"])
        law = control_law(
            hessian_entries=[((0, 0), sx.Integer(2)), ((1, 0), half), ((1, 1), sx.Integer(1))],
            grad_jet=[[g0, g1]],
            rest=[sx.ZERO, sx.ZERO],
            R=sx.ImmutableMatrix([[sx.ONE, sx.ZERO], [sx.ZERO, sx.ONE]]),
            extension=extension,
            plant_inputs=u,
            padding=((), ()),
            states=(x1, x2),
            state_names=("x1", "x2"),
        )
        assert law.y_imp is not None
        a0 = law.a[0]
        # [[2, 1/2], [1/2, 1]]^-1 = [[4/7, -2/7], [-2/7, 8/7]], exactly.
        expected = [
            sx.Rational(4, 7) * a0 * g0 - sx.Rational(2, 7) * a0 * g1,
            -sx.Rational(2, 7) * a0 * g0 + sx.Rational(8, 7) * a0 * g1,
        ]
        for got, want in zip(law.y_imp, expected, strict=True):
            assert sx.expand(got - want) == 0
        assert law.hessian == (2, half, half, 1)
        assert diagonal_blocks(sx.ImmutableMatrix([[1, 0, 0], [0, 1, 2], [0, 3, 1]])) == (
            (0,),
            (1, 2),
        )


@pytest.mark.parametrize("engine", ENGINES)
def test_is_polynomial_reads_the_expression_as_written(engine: str) -> None:
    with sx.using(engine):
        y, z, t = sx.symbols(["y", "z", "t"])
        polynomial = [y**2 * sx.sin(t) + z, (y + 1) ** 3 * t, sx.exp(t) * y * z, y / t, sx.ONE]
        other = [1 / y, sx.sqrt(y), y**z, sx.sin(y), 2**y, (y**2 - 1) / (y - 1), sx.log(z)]
        assert [sx.is_polynomial(e, [y, z]) for e in polynomial] == [True] * len(polynomial)
        assert [sx.is_polynomial(e, [y, z]) for e in other] == [False] * len(other)


@pytest.mark.parametrize("name", ["planar_arm3", "two_unicycles_corridor"])
def test_a_spec_of_sympy_expressions_is_taken_onto_the_engine(name: str) -> None:
    # A spec read on SymPy (as one built by hand may be): the model converts it once,
    # mass matrix and constraints too, and derives the law SymEngine's reader gives.
    with sx.using("sympy"):
        spec = load_spec(str(EXAMPLES / f"{name}.toml"))
    with sx.using("symengine"):
        model = build_model(spec)
        assert {type(e).__module__.split(".")[0] for e in model.f} == {"symengine"}
        assert all(sx.symbol(s.name) == s for s in model.opaque)
        assert bool(model.opaque) == (name == "planar_arm3")
        d = derive(spec)
    fast = _derived(name, "symengine")
    for what in ("closed loop", "R", "p", "jet right-hand side"):
        _same(
            _evaluate("symengine", _law_parts(d, "symengine")[what], _programs(d), undefined=True),
            _evaluate(
                "symengine", _law_parts(fast, "symengine")[what], _programs(fast), undefined=True
            ),
            f"{name}: {what}",
        )


def _example(name: str) -> dict[str, Any]:
    with (EXAMPLES / f"{name}.toml").open("rb") as file:
        return tomllib.load(file)


@pytest.mark.parametrize("engine", ENGINES)
def test_the_model_refuses_alike_on_both_engines(engine: str) -> None:
    # Not affine in the inputs: the message names the input, on either engine.
    data = _example("pvtol")
    data["system"]["dynamics"]["vx"] = "-thrust*torque*sin(theta)/m"
    with sx.using(engine), pytest.raises(SpecError) as affine:
        derive(data)
    assert str(affine.value).endswith(
        "system.dynamics.vx: not affine in the inputs: the coefficient of 'thrust' depends on "
        "input 'torque'"
    )
    # A mass matrix that is not symmetric: both entries quoted (SymEngine's own spelling).
    data = _example("planar_arm3")
    data["system"]["mechanics"]["mass_matrix"][1][0] = "l1*l2*m2*sin(q2)"
    with sx.using(engine), pytest.raises(SpecError) as mass:
        derive(data)
    message = str(mass.value)
    assert "system.mechanics.mass_matrix[1][0]: M is not symmetric: M[1][0] = " in message
    assert "*sin(q2) but M[0][1] = " in message


def test_the_oracle_reads_either_engines_derivation_on_either_engine() -> None:
    """tests/oracle.py's law (SymPy's, lambdified) is the same from SymPy's derivation and
    from SymEngine's, whichever engine is in use when the oracle is built."""
    from .fuzzing import sample_states  # noqa: PLC0415
    from .oracle import Oracle  # noqa: PLC0415

    reference, fast = _derived("pvtol", "sympy"), _derived("pvtol", "symengine")
    states = sample_states(reference, np.random.default_rng(3), 8)
    p = np.array(reference.model.defaults, dtype=float)
    with sx.using("sympy"):
        want = Oracle(reference).law(0.7, states, p)
    assert np.abs(want[0]).max() > 0.1
    for engine in ENGINES:
        with sx.using(engine):
            got = Oracle(fast).law(0.7, states, p)
        for a, b in zip(want, got, strict=True):
            np.testing.assert_allclose(b, a, rtol=1e-12, atol=1e-12 * np.abs(a).max())
