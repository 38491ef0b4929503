"""The report, the summary and simulate's numeric helpers on both engines: the same numbers.

Each example is derived on SymPy (the reference) and on SymEngine two ways: derived
there (``derived``), and converted from SymPy's derivation at the border
(``converted``: :func:`tvopt_codegen.symbolic.border.from_sympy`, deep through the
records), which tests these modules apart from the derivation's port. The report prints
either engine's expressions itself (:mod:`tvopt_codegen.report.printing`): every
displayed expression must equal the SymPy engine's at random points (1e-12 relative),
and every word around them must be the same but where a derivation on SymEngine words
it its own way (the order of an expression's terms, a straight-line program's length).
"""

from __future__ import annotations

import copy
import dataclasses
import functools
import re
import sys
import types
from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest
import sympy as sp

from tvopt_codegen import symbolic as sx
from tvopt_codegen.derivation import Derivation, derive
from tvopt_codegen.lowering.ir import KernelSet
from tvopt_codegen.report import (
    Math,
    Section,
    document,
    entries,
    report_sections,
)
from tvopt_codegen.runs.figures import _signal_values
from tvopt_codegen.runs.summary import format_summary
from tvopt_codegen.simulation import constraints
from tvopt_codegen.simulation.references import exact_jets, nominal_source
from tvopt_codegen.simulation.run import decoupling_determinant
from tvopt_codegen.spec import load_spec
from tvopt_codegen.symbolic.border import from_sympy

from .conftest import ROOT, derivation, kernels
from .engine_cases import run_on_symengine

RELATIVE = 1e-12

#: The plain law, an extension, a mass-matrix plant, a barrier objective, inequality
#: constraints (mu(t) and s(t) in words) and an equality (the KKT law).
REPORTED = (
    "integrator",
    "pvtol",
    "planar_arm3",
    "two_unicycles_barrier",
    "two_unicycles_corridor",
    "arm_on_line",
)


def _converted(value: Any, memo: dict[Any, Any]) -> Any:
    """``value`` with every SymPy expression in it (records, tuples, dicts) SymEngine's."""
    if isinstance(value, sp.Basic | sp.MatrixBase):
        return from_sympy(value, memo)
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        out = copy.copy(value)
        names = {f.name for f in dataclasses.fields(value)}
        for name in names:
            object.__setattr__(out, name, _converted(getattr(value, name), memo))
        # functools.cached_property values were computed from the SymPy fields.
        for key in [k for k in vars(out) if k not in names]:
            del vars(out)[key]
        return out
    if isinstance(value, tuple) and hasattr(value, "_fields"):
        return type(value)(*(_converted(v, memo) for v in value))
    if isinstance(value, tuple | list | frozenset | set):
        return type(value)(_converted(v, memo) for v in value)
    if isinstance(value, dict):
        return {_converted(k, memo): _converted(v, memo) for k, v in value.items()}
    return value


#: A derivation on SymEngine: SymPy's converted, or derived there.
SOURCES = ("converted", "derived")


@functools.cache
def symengine_derivation(name: str, source: str = "converted") -> Derivation:
    """``name``'s derivation on SymEngine: SymPy's converted, or SymEngine's own."""
    reference = sympy_derivation(name)
    with sx.using("symengine"):
        if source == "derived":
            return derive(load_spec(name))
        converted: Derivation = _converted(reference, {})
    return converted


def sympy_derivation(name: str) -> Derivation:
    """``name``'s derivation on SymPy, the reference, whatever the default engine."""
    with sx.using("sympy"):
        return derivation(name)


def sympy_kernels(name: str) -> KernelSet:
    """``name``'s kernels lowered on SymPy (the summary and the report print their counts)."""
    with sx.using("sympy"):
        return kernels(name)


def _no_timings(d: Derivation) -> Derivation:
    return dataclasses.replace(d, timings=tuple((stage, 0.0) for stage, _ in d.timings))


def _assert_same_values(reference: list[Any], other: list[Any], what: str) -> None:
    """SymPy values (expressions, matrices, numbers) equal at random points, pairwise."""
    assert len(other) == len(reference), what

    def flat(values: list[Any]) -> list[Any]:
        out: list[Any] = []
        for value in values:
            out.extend(list(value) if isinstance(value, sp.MatrixBase) else [value])
        return out

    shapes = [getattr(v, "shape", ()) for v in reference]
    assert [getattr(v, "shape", ()) for v in other] == shapes, what
    left, right = flat(reference), flat(other)
    symbols = sorted(
        set().union(*(sp.sympify(e).free_symbols for e in left + right)), key=lambda s: s.name
    )
    rng = np.random.default_rng(49)
    # Positive and away from the integers: logs, roots and tan's poles stay defined.
    points = rng.uniform(0.3, 1.3, size=(3, len(symbols)))
    a = sp.lambdify(symbols, left, modules="numpy")
    b = sp.lambdify(symbols, right, modules="numpy")
    with np.errstate(all="ignore"):
        for point in points:
            expected = np.array(np.broadcast_arrays(*a(*point)), dtype=complex).ravel()
            got = np.array(np.broadcast_arrays(*b(*point)), dtype=complex).ravel()
            assert np.isfinite(expected).mean() > 0.5, what  # the points say something
            np.testing.assert_allclose(
                got,
                expected,
                rtol=RELATIVE,
                atol=RELATIVE * (1 + np.nanmax(np.abs(expected))),
                err_msg=what,
            )


#: The section whose inlined gradient jets a derivation on SymEngine may show where
#: SymPy's does not: each is shown under INLINE_OPS operations, and SymEngine's jet is a
#: different expression of the same values (two_unicycles_barrier's grad^(1) f0: 400
#: operations against SymPy's 424).
LAW = "Control law"

#: The provenance's row naming SymEngine, on SymEngine only.
ENGINE_ROW = "symengine (derivation)"


def _recorded(d: Derivation) -> tuple[list[tuple[bool, Any]], tuple[Section, ...]]:
    """The report's sections of ``d``, and every value it showed (of ``d``'s engine) in
    order, each with whether the control law showed it.

    The kernels are SymPy's on both engines: their operation counts are the lowering's,
    not the report's, to compare.
    """
    shown: list[tuple[bool, Any]] = []
    original, control_law = entries.shown, document._control_law
    in_law = [False]

    def recording(expr: object) -> Any:
        value = original(expr)
        shown.append((in_law[0], value))
        return value

    def recording_law(derivation: Derivation) -> Section:
        in_law[0] = True
        try:
            return control_law(derivation)
        finally:
            in_law[0] = False

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(entries, "shown", recording)
        patch.setattr(document, "_control_law", recording_law)
        built = report_sections(_no_timings(d), sympy_kernels(d.spec.name), None)
    return shown, built


@functools.cache
def _reference(name: str) -> tuple[list[tuple[bool, Any]], tuple[Section, ...]]:
    """What the report of ``name`` shows on SymPy."""
    with sx.using("sympy"):
        return _recorded(derivation(name))


def _without_law(
    recorded: tuple[list[tuple[bool, Any]], tuple[Section, ...]], law: bool
) -> tuple[list[Any], tuple[Section, ...]]:
    shown, built = recorded
    if law:
        return [v for _, v in shown], built
    return [v for in_law, v in shown if not in_law], tuple(s for s in built if s.title != LAW)


def _words(built: tuple[Section, ...]) -> Iterator[object]:
    """Everything a section says but its formulas (whose values are compared instead)."""
    for section in built:
        yield section.title
        for entry in section.entries:
            yield (entry.kind, entry.text, entry.header, entry.name, entry.math is None)
            for row in entry.rows:
                if row[0] != ENGINE_ROW:
                    yield tuple("<math>" if isinstance(cell, Math) else cell for cell in row)


@pytest.mark.parametrize("source", SOURCES)
@pytest.mark.parametrize("name", REPORTED)
def test_the_report_shows_the_same_on_both_engines(name: str, source: str) -> None:
    law = source == "converted"
    reference, built = _without_law(_reference(name), law)
    with sx.using("symengine"):
        printed, other = _without_law(_recorded(symengine_derivation(name, source)), law)
        # What the report shows is SymEngine's own (printed without crossing to SymPy),
        # converted here to compare it with SymPy's.
        assert any(isinstance(v, sx.Basic | sx.MatrixBase) for v in printed)
        shown = [entries.as_sympy(v) for v in printed]
    assert len(reference) > 10
    _assert_same_values(reference, shown, name)
    _assert_same_words(tuple(_words(built)), tuple(_words(other)), source)
    # The provenance names the engine that derived, on SymEngine only.
    rows = {
        engine: [r[0] for s in parts for e in s.entries for r in e.rows]
        for engine, parts in (("sympy", built), ("symengine", other))
    }
    assert ENGINE_ROW in rows["symengine"] and ENGINE_ROW not in rows["sympy"]
    # Floats are shown as the spec wrote them (15 digits), not as the double's 17.
    assert not re.search(r"\d\.\d{16}", "".join(str(w) for w in _words(other)))


def _assert_same_words(expected: object, got: object, source: str) -> None:
    """The report's words (nested tuples of them) the same, see :func:`_assert_same_prose`."""
    if isinstance(expected, tuple):
        assert isinstance(got, tuple) and len(got) == len(expected), (expected, got)
        for a, b in zip(expected, got, strict=True):
            _assert_same_words(a, b, source)
    elif expected != got:
        assert isinstance(expected, str) and isinstance(got, str), (expected, got)
        if source == "derived":
            # The jet's program is SymEngine's own, and so is its length.
            expected = _PROGRAM.sub("Program size: N", expected)
            got = _PROGRAM.sub("Program size: N", got)
        if expected != got:
            _assert_same_prose(expected, got)


def test_the_report_module_shows_an_engine_expression() -> None:
    """formula() and plain() of one expression built on either engine: the same text,
    SymPy's LaTeX and sstr (in the order of the arguments)."""
    x, y = sp.symbols("x y", real=True)
    expr = sp.sin(x) * y**2 / 10 + sp.Rational(1, 3) * sp.atan2(y, x)
    with sx.using("sympy"):
        expected = entries.formula(expr)
        ops = entries.count_ops(expr)
        text = entries.plain(expr)
    with sx.using("symengine"):
        converted = from_sympy(expr)
        assert isinstance(converted, sx.Basic)
        math = entries.formula(converted)
        assert entries.count_ops(converted) == ops
        assert entries.plain(converted) == text
    assert math == expected
    assert math.latex == sp.latex(expr, order="none", mul_symbol=r"\,")
    assert ops == sp.count_ops(expr)
    assert text == sp.sstr(expr, order="none") == "atan2(y, x)/3 + y**2*sin(x)/10"


#: The jet's program's length in the control law's words.
_PROGRAM = re.compile(r"Program size: \d+ assignments for grad\^\(j\), j < k, and \d+")


def _assert_same_prose(expected: str, got: str) -> None:
    """The same words, with expressions (``det R = ...``, ``mu(t) = ...``) perhaps
    spelled otherwise (SymEngine orders terms its own way) but equal at random points."""
    # At "; ", " = ", " where " and ", " outside parentheses.
    split = re.compile(r"; | = | where |, (?![^(]*\))")
    left, right = split.split(expected), split.split(got)
    assert len(left) == len(right), (expected, got)
    pairs = [(a, b) for a, b in zip(left, right, strict=True) if a != b]
    try:
        parsed = [(sp.parse_expr(a), sp.parse_expr(b)) for a, b in pairs]
    except (SyntaxError, TypeError, ValueError, AttributeError):
        raise AssertionError(f"{expected!r} != {got!r}") from None
    _assert_same_values([a for a, _ in parsed], [b for _, b in parsed], f"{expected!r} / {got!r}")


@pytest.mark.parametrize("source", SOURCES)
@pytest.mark.parametrize("name", REPORTED)
def test_the_summary_says_the_same_on_both_engines(name: str, source: str) -> None:
    """Line for line the same words; the expressions the same at random points."""
    with sx.using("sympy"):
        expected = format_summary(_no_timings(derivation(name)), kernels(name)).splitlines()
    with sx.using("symengine"):
        e = _no_timings(symengine_derivation(name, source))
        got = format_summary(e, sympy_kernels(name)).splitlines()
    assert len(got) == len(expected)
    for a, b in zip(expected, got, strict=True):
        if a != b:
            _assert_same_prose(a, b)


def test_lambdify_gives_the_same_numbers_on_both_engines() -> None:
    """sx.lambdify's calling conventions on SymEngine are SymPy's, with SymPy's numbers."""
    d, e = sympy_derivation("pvtol"), symengine_derivation("pvtol")
    rng = np.random.default_rng(7)
    states = rng.uniform(0.2, 1.2, len(d.closed_loop.states))
    params = [float(v) for v in d.model.defaults]

    def values(source: Derivation) -> list[Any]:
        m = source.model
        t, x, p = m.t, list(source.closed_loop.states), list(m.params)
        # A matrix (numpy), a list from list arguments (math), one expression of a
        # broadcast time, nested rows of one symbol, and a Piecewise.
        matrix = sx.lambdify([[t, *x, *p]], source.linearization.R, modules="numpy")
        column = [source.decoupling.p[i, 0] for i in range(source.decoupling.p.shape[0])]
        listed = sx.lambdify([t, x, p], column, "math")
        scalar = sx.lambdify([t, *p], sx.sin(t) * p[0] + t**2 / p[-1])
        rows = sx.lambdify(t, [[t, 2 * t], [sx.sin(t), sx.exp(-t)]], "math")
        switch = sx.Piecewise((t**2, t < 1), (sx.log(t), True))
        piecewise = sx.lambdify([t], [switch, sx.atan2(t, 1 - t)], "math")
        times = np.linspace(0.0, 2.0, 5)
        return [
            np.asarray(matrix([0.4, *states, *params]), dtype=float),
            np.asarray(listed(0.4, states, params), dtype=float),
            np.asarray(scalar(times, *params), dtype=float),
            np.asarray(rows(0.9), dtype=float),
            np.asarray(piecewise(0.5), dtype=float),
            np.asarray(piecewise(1.5), dtype=float),
        ]

    with sx.using("sympy"):
        expected = values(d)
    with sx.using("symengine"):
        got = values(e)
        assert isinstance(sx.lambdify([sx.symbol("t")], sx.symbol("t") ** 2)(3.0), float)
        assert sx.lambdify(sx.symbol("t"), [])(1.0).shape == (0,)
    for a, b in zip(expected, got, strict=True):
        assert b.shape == a.shape
        np.testing.assert_allclose(b, a, rtol=RELATIVE, atol=1e-15)


@pytest.mark.parametrize("source", SOURCES)
@pytest.mark.parametrize("name", ["pvtol_refs", "two_unicycles_barrier_refs"])
def test_exact_jets_are_the_same_on_both_engines(name: str, source: str) -> None:
    times = (0.0, 0.7, 2.3, 11.0)
    params = {"g": 9.81} if name == "pvtol_refs" else {}
    with sx.using("sympy"):
        jets = exact_jets(derivation(name), params)
        expected = [jets(t) for t in times]
    with sx.using("symengine"):
        jets = exact_jets(symengine_derivation(name, source), params)
        got = [jets(t) for t in times]
    for a, b in zip(expected, got, strict=True):
        np.testing.assert_allclose(b, a, rtol=RELATIVE, atol=1e-14)


@pytest.mark.parametrize("source", SOURCES)
@pytest.mark.parametrize("name", ["pvtol", "planar_arm3"])
def test_det_r_is_the_same_on_both_engines(name: str, source: str) -> None:
    d = sympy_derivation(name)
    rng = np.random.default_rng(3)
    start = np.asarray(d.closed_loop.initial_state, dtype=float)
    states = [start + rng.uniform(-0.5, 0.5, start.shape) for _ in range(4)]
    with sx.using("sympy"):
        determinant = decoupling_determinant(d, {})
        assert determinant is not None
        expected = [determinant(0.3, state) for state in states]
    with sx.using("symengine"):
        determinant = decoupling_determinant(symengine_derivation(name, source), {})
        assert determinant is not None
        got = [determinant(0.3, state) for state in states]
    np.testing.assert_allclose(got, expected, rtol=1e-12)


@pytest.mark.parametrize("source", SOURCES)
def test_signal_values_are_the_same_on_both_engines(source: str) -> None:
    name = "two_unicycles_barrier"
    result = types.SimpleNamespace(
        t=np.linspace(0.0, 5.0, 11), options=types.SimpleNamespace(params={}), references=None
    )
    d = sympy_derivation(name)
    signals = [x for pair in d.spec.objects for x in pair]
    with sx.using("sympy"):
        expected = [_signal_values(d, result, s) for s in signals]  # type: ignore[arg-type]
    with sx.using("symengine"):
        e = symengine_derivation(name, source)
        got = [_signal_values(e, result, s) for s in signals]  # type: ignore[arg-type]
    np.testing.assert_allclose(got, expected, rtol=RELATIVE, atol=1e-15)


def _problem_values(d: Derivation, t: float, y: np.ndarray) -> list[np.ndarray]:
    model = d.model
    values = dict(zip(model.params, model.defaults, strict=True))
    problem = constraints._problem(model, values, None)
    # Everything SLSQP asks for (f0, the g_i, the domain, the a_j, with their
    # gradients), then the g_i and a_j the run's margins read.
    out = [np.atleast_1d(np.asarray(v, dtype=float)) for v in problem.solver(t, y, [])]
    out += [np.atleast_1d(np.asarray(f(t, y, []), dtype=float)) for f in (problem.g, problem.a)]
    if model.equalities:
        equal = constraints.equalities(model, values)
        nu = np.linspace(0.5, 1.5, len(model.equalities))
        out += [equal.value(t, y, []), equal.jacobian_a(t, y, []), equal.curvature(t, y, [], nu)]
    return out


@pytest.mark.parametrize("source", SOURCES)
@pytest.mark.parametrize("name", ["arm_on_line", "two_unicycles_corridor"])
def test_the_constraints_in_numbers_are_the_same_on_both_engines(name: str, source: str) -> None:
    d = sympy_derivation(name)
    rng = np.random.default_rng(11)
    for t in (0.0, 1.3):
        y = rng.uniform(0.2, 0.9, len(d.model.y))
        with sx.using("sympy"):
            expected = _problem_values(d, t, y)
        with sx.using("symengine"):
            got = _problem_values(symengine_derivation(name, source), t, y)
        for a, b in zip(expected, got, strict=True):
            assert b.shape == a.shape
            np.testing.assert_allclose(b, a, rtol=RELATIVE, atol=1e-14)
    assert any(a.size for a in expected)


@pytest.mark.parametrize("source", SOURCES)
def test_the_constraints_certificate_is_the_same_on_both_engines(source: str) -> None:
    """check_run along a made-up path near a figure eight under a wall: its margins, the
    references' values, m_f and the SLSQP minimisers' distances."""
    name = str(ROOT / "tests" / "specs" / "figure8_wall.toml")
    ts = np.linspace(0.0, 12.0, 9)

    def check(source: Derivation) -> Any:
        references = nominal_source(source, {})
        # The references' own path below the wall, which cuts the top of it.
        minimisers = np.array([references.jets(t)[:, 0] for t in ts]).T
        minimisers[1] = np.minimum(minimisers[1], 1.2)
        outputs = minimisers + 1e-3
        to_phi = np.linalg.norm(outputs - minimisers, axis=0)
        values = dict(zip(source.model.params, source.model.defaults, strict=True))
        return constraints.check_run(
            source.model, ts, outputs, to_phi, minimisers, values, references, 5
        )

    with sx.using("sympy"):
        expected = check(derivation(name))
    with sx.using("symengine"):
        got = check(symengine_derivation(name, source))
    for field in ("margins", "slack", "lhs", "rhs", "bound", "times", "equality"):
        np.testing.assert_allclose(
            getattr(got, field), getattr(expected, field), rtol=RELATIVE, atol=1e-14
        )
    assert got.m_f == pytest.approx(expected.m_f, rel=RELATIVE)
    assert [n for n, _ in got.final] == [n for n, _ in expected.final]
    np.testing.assert_allclose([v for _, v in got.final], [v for _, v in expected.final])
    # SLSQP's stopping point, from functions equal to the last bits: within its tolerance.
    assert np.isfinite(expected.distance).all()
    np.testing.assert_allclose(got.distance, expected.distance, rtol=1e-6, atol=1e-9)


def test_on_symengine_these_helpers_import_no_sympy(monkeypatch: pytest.MonkeyPatch) -> None:
    """The summary and simulate's helpers run on SymEngine with SymPy unimportable."""
    with sx.using("symengine"):
        derived = {
            n: symengine_derivation(n, "derived") for n in ("pvtol", "pvtol_refs", "arm_on_line")
        }
        with monkeypatch.context() as patch:
            patch.setitem(sys.modules, "sympy", None)
            with pytest.raises(ImportError):
                import sympy  # noqa: F401, PLC0415 - the block works
            assert "R(x)" not in format_summary(derived["pvtol"])
            assert decoupling_determinant(derived["pvtol"], {}) is not None
            exact_jets(derived["pvtol_refs"], {})(0.5)
            _problem_values(derived["arm_on_line"], 0.2, np.array([0.4, 0.6]))


def test_importing_simulation_runs_and_report_on_symengine_imports_no_sympy() -> None:
    modules = (
        "tvopt_codegen.simulation",
        "tvopt_codegen.simulation.constraints",
        "tvopt_codegen.simulation.sampled",
        "tvopt_codegen.runs.artifacts",
        "tvopt_codegen.runs.figures",
        "tvopt_codegen.runs.fmu",
        "tvopt_codegen.runs.summary",
        "tvopt_codegen.report",
    )
    code = (
        "import importlib, sys\n"
        f"for name in {modules!r}:\n"
        "    importlib.import_module(name)\n"
        "print(sorted(m for m in sys.modules if m.split('.')[0] == 'sympy'))\n"
    )
    ran = run_on_symengine(code)
    assert ran.returncode == 0, ran.stderr[-2000:]
    assert ran.stdout.strip() == "[]"
