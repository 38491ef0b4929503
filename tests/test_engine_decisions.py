"""The stages that decide things, on both engines: the same decisions, the same numbers.

det R (Berkowitz's determinant, its factored form and singular set), where the law is
undefined, the objective's Hessian, the constraints' convexity, the extended-state
observer's rows and the disturbance observer's rows of ``G``. Each takes the inputs a
SymPy derivation of a bundled example gives it, converted with ``from_sympy`` under
SymEngine, and must decide as on SymPy and give the same numbers (1e-12 relative).
Each test names both engines (``sx.using("sympy")`` for the reference, ``_on_symengine``
for the fast one): none relies on which engine is the process's default.
"""

from __future__ import annotations

import copy
import dataclasses
import tomllib
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import pytest
import sympy as sp

from tvopt_codegen import symbolic as sx
from tvopt_codegen.derivation import derive
from tvopt_codegen.derivation.convexity import _culprit, _evaluator_at, _hessian, nonconvex
from tvopt_codegen.derivation.linearization import (
    _decoupling,
    _Linearization,
    _rows_text,
    _with_gains,
    law_expressions,
)
from tvopt_codegen.derivation.meter import _DET_SIMPLIFY_NODES, _Meter, tree_size
from tvopt_codegen.derivation.model import build_model
from tvopt_codegen.derivation.record import Derivation
from tvopt_codegen.derivation.rejection import discrete_gains, observer_field, rejection
from tvopt_codegen.derivation.robust import robustness
from tvopt_codegen.derivation.singularity import _singular_set, simplified_det, undefined_causes
from tvopt_codegen.errors import AssumptionError
from tvopt_codegen.limits import Budget
from tvopt_codegen.spec import load_spec, spec_from_dict
from tvopt_codegen.symbolic import linalg
from tvopt_codegen.symbolic.border import from_sympy, to_sympy

from .conftest import SPECS, derivation
from .test_trust import GEOFENCE as TRUST_GEOFENCE

#: Bundled examples with det R expanded (m <= 4), two with a mass matrix.
EXAMPLES = (
    "pvtol",
    "unicycle_switch",
    "two_unicycles_barrier",
    "planar_arm3",
    "drag_vehicle",
    "arm_on_line",
)
#: Test plants whose law is undefined somewhere (a denominator, tan) or whose det R
#: holds the spec's decimals.
UNDEFINED = (str(SPECS / "attitude.toml"), str(SPECS / "kinematic_car.toml"), "arm_on_line")
DECIMALS = str(SPECS / "coupled3.toml")


def _values(exprs: Sequence[Any], seed: int) -> np.ndarray:
    """SymPy expressions' values at 16 random points in [0.5, 1.5] of every symbol."""
    symbols = sorted(set().union(*(e.free_symbols for e in exprs)), key=str)
    rng = np.random.default_rng(seed)
    points = rng.uniform(0.5, 1.5, size=(16, len(symbols)))
    function = sp.lambdify(symbols, list(exprs), "numpy")
    return np.array([np.broadcast_to(function(*row), (len(exprs),)) for row in points], float)


def _same_numbers(reference: Sequence[Any], symengine: Sequence[Any]) -> None:
    """Both lists of SymPy expressions (the second converted back) agree at random points."""
    assert len(reference) == len(symengine)
    together = [*reference, *symengine]
    values = _values(together, 3)
    first, second = values[:, : len(reference)], values[:, len(reference) :]
    assert np.all(np.isfinite(first))
    np.testing.assert_allclose(second, first, rtol=1e-12, atol=1e-12 * np.abs(first).max())


def _on_symengine(function: Callable[[], Any]) -> Any:
    with sx.using("symengine"):
        return function()


def _reference(name: str) -> Derivation:
    """``name``'s derivation on SymPy, the reference engine (SymPy trees throughout)."""
    with sx.using("sympy"):
        return derivation(name)


def _converted(values: Any) -> Any:
    """A tuple or matrix of SymPy expressions as one of the engine (nested tuples kept)."""
    if isinstance(values, tuple):
        return tuple(_converted(v) for v in values)
    return from_sympy(values)


def _mechanics(d: Derivation) -> Any:
    """The spec's mechanics with the expressions :func:`_with_gains` reads converted."""
    mechanics = d.model.mechanics
    if mechanics is None:
        return None
    return dataclasses.replace(
        mechanics,
        input_matrix=_converted(mechanics.input_matrix),
        gains=_converted(mechanics.gains),
    )


def _symengine_det(matrix: Any) -> Any:
    with sx.using("symengine"):
        return to_sympy(linalg.det(from_sympy(matrix)))


def test_the_determinant_is_sympys_on_both_engines() -> None:
    x, y, z = sp.symbols("x y z", real=True)
    rng = np.random.default_rng(5)
    pool = [0, 0, 1, x, x * sp.sin(y), z**2 + 1, x * y - 3, sp.Rational(1, 3), 1 / (x + y)]
    for n in (0, 1, 2, 2, 3, 3, 4, 4, 5):
        # Larger ones of polynomials, whose difference expands to 0 when they agree.
        choices = len(pool) if n <= 3 else len(pool) - 1
        entries = [pool[k] for k in rng.integers(0, choices, size=n * n)]
        matrix = sp.ImmutableMatrix(n, n, entries)
        reference = matrix.det(method="berkowitz")
        with sx.using("sympy"):
            assert linalg.det(matrix) == reference  # SymPy's own on SymPy
        found = _symengine_det(matrix)
        if n <= 3:  # written out and simplified as SymPy does: the very expression
            assert found == reference, n
        else:
            assert sp.expand(found - reference) == 0, n
    # Block triangular: the product of the strongly connected blocks' determinants.
    blocks = sp.ImmutableMatrix(
        [[x, 1, 0, 0, y], [2, z, 0, 0, 0], [x, 0, y, 1, 0], [0, 0, 3, x, 0], [0, 0, 0, 0, z]]
    )
    assert sp.factor(_symengine_det(blocks)) == sp.factor((x * z - 2) * (x * y - 3) * z)


@pytest.mark.parametrize("name", EXAMPLES)
def test_det_r_and_its_singular_set_are_decided_alike(name: str) -> None:
    d = _reference(name)
    R = d.linearization.R
    with sx.using("sympy"):
        reference = linalg.det(_with_gains(R, d.model.mechanics))
        simplified = simplified_det(reference)
        singular = _singular_set(simplified)
        reference_small = tree_size(reference, _DET_SIMPLIFY_NODES) <= _DET_SIMPLIFY_NODES
    # What the derivation itself found, through the same functions.
    assert simplified == d.decoupling.det_R and singular == d.decoupling.singular_set
    assert singular  # every one of these plants has a singular set

    def run() -> tuple[Any, Any, bool, tuple[str, ...]]:
        det = linalg.det(_with_gains(from_sympy(R), _mechanics(d)))
        small = tree_size(det, _DET_SIMPLIFY_NODES) <= _DET_SIMPLIFY_NODES
        short = simplified_det(det)
        assert isinstance(short, sx.Basic)  # back on the engine, for the stages after
        return to_sympy(det), to_sympy(short), small, _singular_set(short)

    det, short, small, found = _on_symengine(run)
    assert found == singular
    assert small == reference_small
    # The factored form: the same expression once in SymPy (SymPy's Mul spreads a
    # number over a sum there: (2800*c - 240)/1000 comes back as 14*c/5 - 6/25).
    assert sp.cancel(short - simplified) == 0
    _same_numbers([reference, simplified], [det, short])


def test_det_r_of_decimal_gains_is_factored_to_the_same_text() -> None:
    """Decimal gains (exact rationals on both engines) give the same singular set's text."""
    test_det_r_and_its_singular_set_are_decided_alike(DECIMALS)


@pytest.mark.parametrize("name", UNDEFINED)
def test_the_law_is_undefined_at_the_same_places(name: str) -> None:
    d = _reference(name)
    with sx.using("sympy"):
        exprs = law_expressions(d.linearization.R, d.decoupling.p, d.model.mechanics)
        states = set(d.linearization.extension.x)
        reference = undefined_causes(exprs, states)
    assert reference  # each plant has a place where its law is undefined

    def run() -> tuple[tuple[str, str], ...]:
        return undefined_causes([from_sympy(e) for e in exprs], {from_sympy(s) for s in states})

    # The conditions as SymPy writes them: the generated code quotes them (golden files).
    assert _on_symengine(run) == reference


@pytest.mark.parametrize("name", (*EXAMPLES, *UNDEFINED[:2]))
def test_the_decoupling_stage_gives_the_same_record(name: str) -> None:
    d = _reference(name)
    lin = _Linearization(
        d.linearization.extension,
        d.linearization.relative_degree,
        d.linearization.lie,
        d.linearization.R,
        (),
        frozenset(),
    )
    with sx.using("sympy"):
        reference = _decoupling(lin, _Meter(name, Budget()), d.model.mechanics)

    def run() -> Any:
        ext = lin.extension
        converted = dataclasses.replace(
            lin,
            extension=dataclasses.replace(
                ext, x=_converted(ext.x), f=from_sympy(ext.f), G=from_sympy(ext.G)
            ),
            lie=_converted(lin.lie),
            R=from_sympy(lin.R),
        )
        found = _decoupling(converted, _Meter(name, Budget()), _mechanics(d))
        assert isinstance(found.p, sx.MatrixBase) and isinstance(found.phi, sx.MatrixBase)
        return dataclasses.replace(
            found,
            p=to_sympy(found.p),
            phi=to_sympy(found.phi),
            det_R=None if found.det_R is None else to_sympy(found.det_R),
        )

    found = _on_symengine(run)
    assert found.p.shape == reference.p.shape and found.phi.shape == reference.phi.shape
    assert (found.A, found.B) == (reference.A, reference.B)
    assert (found.det_R_note, found.singular) == (reference.det_R_note, reference.singular)
    assert found.undefined == reference.undefined
    assert (found.det_R is None) == (reference.det_R is None)
    mine = [*found.p, *found.phi, *([found.det_R] if found.det_R is not None else [])]
    theirs = [*reference.p, *reference.phi, *([reference.det_R] if found.det_R is not None else [])]
    _same_numbers(theirs, mine)


def test_a_decoupling_matrix_is_written_as_sympy_writes_it() -> None:
    """On SymPy, as sstr writes it (SymEngine's messages keep its own order of terms)."""
    R = _reference("two_unicycles_barrier").linearization.R
    with sx.using("sympy"):
        assert _rows_text(R) == sp.sstr(R.tolist())
    # On SymEngine, its own order of terms: read back, the same matrix.
    text = _on_symengine(lambda: _rows_text(from_sympy(R)))
    names = {s.name: s for s in R.free_symbols}
    assert sp.simplify(sp.Matrix(sp.sympify(text, locals=names)) - R) == sp.zeros(*R.shape)


@pytest.mark.parametrize("name", ("pvtol", "two_unicycles_corridor", "arm_on_line"))
def test_the_objectives_hessian_is_the_same(name: str) -> None:
    d = _reference(name)
    # With [constraints], the barrier objective: logs of the slacks.
    f0, outputs = d.model.f0, d.model.y
    reference = sp.hessian(f0, outputs)
    with sx.using("sympy"):
        assert _hessian(f0, outputs) == reference.tolist()  # SymPy's order, entry by entry
    found = _on_symengine(
        lambda: [to_sympy(e) for row in _hessian(from_sympy(f0), _converted(outputs)) for e in row]
    )
    # The objective's signals and nominal references, as numbers: t and the symbols.
    definitions = dict(d.model.signals) | dict(d.model.nominal)
    closed = [sp.sympify(e).subs(definitions) for e in (*reference, *found)]
    _same_numbers(closed[: len(found)], closed[len(found) :])


@pytest.mark.parametrize("name", ("two_unicycles_corridor", str(SPECS / "figure8_wall.toml")))
def test_constraint_convexity_is_decided_alike(name: str) -> None:
    d = _reference(name)
    model = d.model
    assert model.constraints
    rng = np.random.default_rng(18)
    points = 32
    y0 = np.array([0.3 * (i + 1) for i in range(len(model.y))])
    ys = y0[None, :] + rng.uniform(-2.0, 2.0, size=(points, len(y0)))
    ts = rng.uniform(0.0, model.settings.t_final, size=points)
    # Beside the spec's (linear), a curved convex constraint and a concave one: the check
    # must name the concave one alone, on both engines.
    first, second = model.y[0], model.y[1]
    disc = dataclasses.replace(
        model.constraints[0],
        name="disc",
        op="<=",
        lhs=first**2 + first * second + second**2,
        rhs=sp.Integer(9),
    )
    dome = dataclasses.replace(
        model.constraints[0],
        name="dome",
        op=">=",
        lhs=sp.cos(first) + second**2,
        rhs=sp.Integer(-5),
    )
    constraints = (*model.constraints, disc, dome)
    with sx.using("sympy"):
        reference = nonconvex(constraints, model.y, _evaluator_at(model, ys, ts), points)

    def run() -> list[tuple[str, float]]:
        converted = dataclasses.replace(
            model,
            y=_converted(model.y),
            t=from_sympy(model.t),
            params=_converted(model.params),
            references=_converted(model.references),
            nominal=tuple((from_sympy(s), from_sympy(e)) for s, e in model.nominal),
            signals=tuple((from_sympy(s), from_sympy(e)) for s, e in model.signals),
        )
        mine = tuple(
            dataclasses.replace(c, lhs=from_sympy(c.lhs), rhs=from_sympy(c.rhs))
            for c in constraints
        )
        return nonconvex(mine, converted.y, _evaluator_at(converted, ys, ts), points)

    found = _on_symengine(run)
    assert [n for n, _ in found] == [n for n, _ in reference]
    assert [name for name, _ in reference] == ["dome"]
    np.testing.assert_allclose([v for _, v in found], [v for _, v in reference], rtol=1e-12)


def test_the_observer_rows_are_the_same() -> None:
    d = _reference(str(SPECS / "robust_pvtol.toml"))
    degrees = d.linearization.relative_degree
    outputs = d.model.output_names
    observer = rejection(7.5, degrees, outputs)
    assert observer.discrete == tuple(discrete_gains(r) for r in degrees)
    chains = [[sp.Symbol(name, real=True) for name in chain] for chain in observer.states]
    v = sp.symbols(f"v0:{len(degrees)}", real=True)
    h = list(d.model.h)
    with sx.using("sympy"):
        reference = observer_field(observer, chains, h, v)

    def run() -> list[Any]:
        estimates = [[from_sympy(s) for s in chain] for chain in chains]
        rows = observer_field(observer, estimates, [from_sympy(e) for e in h], _converted(v))
        assert all(isinstance(row, sx.Basic) for row in rows)
        return [to_sympy(row) for row in rows]

    found = _on_symengine(run)
    assert len(found) == sum(r + 1 for r in degrees)
    _same_numbers(reference, found)


@pytest.mark.parametrize("name", ("pvtol", "planar_arm3"))
def test_the_disturbance_observers_rows_of_g_are_the_same(name: str) -> None:
    d = _reference(name)
    model = d.model
    settings = dataclasses.replace(
        model.settings, robust=dataclasses.replace(model.settings.robust, observer=5.0)
    )
    model = dataclasses.replace(model, settings=settings)
    arguments = (d.law, d.linearization.extension, d.closed_loop.state_names, (), (), None)
    with sx.using("sympy"):
        reference = robustness(model, *arguments)
    assert reference.observer_rows and any(reference.observer_rows)
    found = _on_symengine(
        lambda: robustness(dataclasses.replace(model, G=from_sympy(model.G)), *arguments)
    )
    assert found == reference


#: A unicycle kept inside a disc while it follows a point on a circle (tests/test_trust.py's).
GEOFENCE = TRUST_GEOFENCE.format(fence="y1**2 + y2**2 <= 9", y0=-1.0)


def _refusal(data: dict[str, Any]) -> str:
    """The one-line refusal ``derive`` gives the spec ``data``, on the current engine."""
    with pytest.raises(AssumptionError) as info:
        derive(spec_from_dict(copy.deepcopy(data)))
    return str(info.value)


@pytest.mark.parametrize(
    ("table", "key", "value", "expected"),
    [
        # A flat minimum: refused at y*(t), f0 blamed (Newton, then the culprit).
        ("objective", "f0", "(y1 - ox)**4 + (y2 - oy)**2", "not strongly convex at its minimiser"),
        # A concave constraint: refused by the sampled constraint check.
        ("constraints", "fence", "y1**2 - y2**2 <= 9", "constraints.fence: not convex"),
    ],
)
def test_refusals_of_convexity_read_the_same(
    table: str, key: str, value: str, expected: str
) -> None:
    data = tomllib.loads(GEOFENCE)
    data[table][key] = value
    if table == "objective":
        del data["constraints"]  # the barrier's curvature would hide the flat minimum
    with sx.using("sympy"):
        reference = _refusal(data)
    assert expected in reference
    with sx.using("symengine"):
        assert _refusal(data) == reference


def test_a_failing_hessian_is_blamed_alike() -> None:
    """The barrier's term (f0 alone is convex there) and f0's own Hessian, on both engines."""
    data = tomllib.loads(GEOFENCE)
    flat = copy.deepcopy(data)
    flat["objective"]["f0"] = "(y1 - ox)**4 + (y2 - oy)**2"
    cases = [(data, np.array([0.0, -3.5])), (flat, np.array([4 * np.cos(3.0), 0.0]))]
    with sx.using("sympy"):
        reference = [
            _culprit(build_model(spec_from_dict(copy.deepcopy(d))), y, 10.0) for d, y in cases
        ]
    assert reference[0][0] == "constraints" and reference[1][0] == "objective.f0"
    with sx.using("symengine"):
        found = [_culprit(build_model(spec_from_dict(copy.deepcopy(d))), y, 10.0) for d, y in cases]
    assert found == reference


@pytest.mark.parametrize("name", (*EXAMPLES, UNDEFINED[1]))
def test_the_whole_derivation_decides_alike_on_symengine(name: str) -> None:
    """derive on SymEngine: the relative degrees, det R's verdicts, warnings, convexity."""
    reference = _reference(name)
    with sx.using("symengine"):
        d = derive(load_spec(name))
        det = None if d.decoupling.det_R is None else to_sympy(d.decoupling.det_R)
    assert d.linearization.relative_degree == reference.linearization.relative_degree
    mine, theirs = d.decoupling, reference.decoupling
    assert (mine.singular_set, mine.det_R_note) == (theirs.singular_set, theirs.det_R_note)
    assert mine.undefined_set == theirs.undefined_set
    assert d.warnings == reference.warnings  # kinematic_car's: undefined at its start
    assert d.objective.convexity.method == reference.objective.convexity.method
    np.testing.assert_allclose(d.objective.convexity.m_f, reference.objective.convexity.m_f, 1e-12)
    assert det is not None and theirs.det_R is not None
    _same_numbers([theirs.det_R], [det])


def test_undefined_conditions_are_found_in_sympy_s_order_on_both_engines() -> None:
    """Which conditions are listed, and in which order, is the same on both engines.

    The walk visits arguments in SymPy's order on SymEngine too (whose own order follows
    its hashes): with more conditions than are kept, the kept ones must not depend on it.
    """
    found = []
    for engine in ("sympy", "symengine"):
        with sx.using(engine):
            a, b, c, d, e, f, g, x = sx.symbols(list("abcdefgx"))
            expr = (
                a / (b + 1)
                + sx.tan(c) * d
                + sx.log(e)
                + 1 / (f - 2)
                + sx.sqrt(g)
                + 1 / (x * a + 3)
                + sx.cot(b * c)
                + 1 / (d + e)
            )
            found.append(undefined_causes([expr], {a, b, c, d, e, f, g, x}))
    assert found[0] == found[1]
    assert len(found[0]) == 6  # the cut at _MAX_UNDEFINED is reached
