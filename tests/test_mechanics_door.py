"""The door of the mass-matrix form (issue 45): spec_from_sympy, spec_toml, hand-written M.

What spec_from_sympy and spec_toml return reads back, through the project's own reader,
as the same M, F, B, outputs and objective; what the spec language cannot say is one
SpecError naming the field. A hand-written ``[system.mechanics]`` is checked where the
symmetry check samples it: finite, and positive definite.
"""

from __future__ import annotations

import keyword
import math
import tomllib
from pathlib import Path
from typing import Any, cast

import numpy as np
import pytest
import sympy as sp
import sympy.physics.mechanics as me
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st
from sympy.printing.numpy import NumPyPrinter

from tvopt_codegen.cli import main
from tvopt_codegen.errors import EXIT_ASSUMPTION, SpecError
from tvopt_codegen.mechanics import spec_from_sympy, spec_toml
from tvopt_codegen.spec import Spec, load_spec, spec_from_dict
from tvopt_codegen.symbolic.border import to_sympy

from .conftest import SPECS

ARM2 = SPECS / "arm2_mass.toml"
T = me.dynamicsymbols._t
THETA = me.dynamicsymbols("theta")
TORQUE = me.dynamicsymbols("torque")
MASS, LENGTH, GRAVITY = sp.symbols("m l g", positive=True)
VALUES: dict[sp.Symbol | str, float] = {MASS: 1.2, LENGTH: 0.5, GRAVITY: 9.81}


def pendulum(extra: sp.Expr = sp.S.Zero) -> me.LagrangesMethod:
    """A point mass on a rod, driven by a torque, with ``extra`` torque about the pivot."""
    frame = me.ReferenceFrame("N")
    pivot = me.Point("O")
    pivot.set_vel(frame, 0)
    arm = frame.orientnew("A", "Axis", [THETA, frame.z])
    arm.set_ang_vel(frame, THETA.diff() * frame.z)
    bob = pivot.locatenew("P", LENGTH * arm.x)
    bob.v2pt_theory(pivot, frame, arm)
    particle = me.Particle("bob", bob, MASS)
    particle.potential_energy = -MASS * GRAVITY * LENGTH * sp.cos(THETA)
    loads = [(arm, (TORQUE + extra) * frame.z)]
    method = me.LagrangesMethod(
        me.Lagrangian(frame, particle), [THETA], forcelist=loads, frame=frame
    )
    method.form_lagranges_equations()
    return method


class Equations:
    """Equations of motion as spec_from_sympy reads them: M, the forcing, the coordinates."""

    def __init__(self, mass: sp.Matrix, forcing: sp.Matrix, q: list[sp.Expr]) -> None:
        self._mass, self._forcing, self._q = mass, forcing, q

    @property
    def mass_matrix(self) -> sp.Matrix:
        return self._mass

    @property
    def forcing(self) -> sp.Matrix:
        return self._forcing

    @property
    def q(self) -> list[sp.Expr]:
        return self._q


def _plain(expr: sp.Expr) -> sp.Expr:
    """A SymPy mechanics expression in the spec's plain real symbols."""
    table: dict[sp.Basic, sp.Basic] = {}
    for node in sp.preorder_traversal(expr):
        if isinstance(node, sp.Derivative):
            table[node] = sp.Symbol("d" + node.args[0].func.__name__, real=True)
    out = sp.sympify(expr).xreplace(table)
    table = {}
    for node in sp.preorder_traversal(out):
        if isinstance(node, sp.core.function.AppliedUndef) and node.args == (T,):
            table[node] = sp.Symbol(node.func.__name__, real=True)
        elif isinstance(node, sp.Symbol) and node != T:
            table[node] = sp.Symbol(node.name, real=True)
    return out.xreplace(table)


def _numpy(symbols: list[sp.Symbol], expr: sp.Expr) -> Any:
    """sympy's lambdify, printing terms in sympy's order and writing no docstring.

    The default order (and the docstring's str()) evaluates constant terms with mpmath
    to sort them: hours for sin(exp(exp(40))).
    """
    printer = NumPyPrinter({"fully_qualified_modules": False, "inline": True, "order": "none"})
    return sp.lambdify(symbols, expr, modules="numpy", printer=printer, docstring_limit=0)


def _agree(ours: sp.Expr, read: sp.Expr, values: dict[str, float]) -> None:
    """Equal at six random points (parameters at their values), to 1e-12 relative.

    ``read`` is the spec's expression, of the process's engine: it crosses to SymPy (real
    symbols of the same names, numbers exact) so that both go through SymPy's printer.
    """
    if not isinstance(read, sp.Basic):
        read = to_sympy(read)
    # The user's floats as the doubles they are (sympy prints a Float to 15 digits).
    ours = ours.xreplace({f: sp.Rational(repr(float(f))) for f in ours.atoms(sp.Float)})

    def doubles(expr: sp.Expr) -> sp.Expr:
        # NumPy cannot take cos of an integer beyond 64 bits: the double it rounds to.
        big = [i for i in expr.atoms(sp.Integer) if abs(int(i)) > 2**53]
        return expr.xreplace({i: sp.Float(float(i)) for i in big})

    ours, read = doubles(ours), doubles(read)
    rng = np.random.default_rng(3)
    symbols = sorted(ours.free_symbols | read.free_symbols, key=str)
    point = [values[s.name] if s.name in values else rng.uniform(-1.5, 1.5, 6) for s in symbols]
    with np.errstate(all="ignore"):
        # sympy's own printer to NumPy: a path independent of the tool's evaluator.
        a = np.broadcast_to(np.asarray(_numpy(symbols, ours)(*point), dtype=complex), (6,))
        b = np.broadcast_to(np.asarray(_numpy(symbols, read)(*point), dtype=complex), (6,))
    both = np.isfinite(a) & np.isfinite(b)
    assert np.array_equal(np.isfinite(a), np.isfinite(b)), (ours, read)
    # An ill-conditioned expression (sin(1.25e15 cot(q)) turns the last bit of cot(q)
    # against 1/tan(q) into a different value) is equal only in exact arithmetic: where
    # the doubles differ, both are evaluated again to 60 digits at the same point.
    apart = both & ~np.isclose(b, a, rtol=1e-12, atol=1e-12)
    for i in np.flatnonzero(apart):
        at = {
            s: sp.Float(float(np.broadcast_to(v, (6,))[i]), 60)
            for s, v in zip(symbols, point, strict=True)
        }
        exact_a, exact_b = complex(ours.evalf(60, subs=at)), complex(read.evalf(60, subs=at))
        assert abs(exact_b - exact_a) <= 1e-12 * max(1.0, abs(exact_a)), (i, exact_a, exact_b)


def _read_back(spec: dict[str, Any], tmp_path: Path) -> Spec:
    """The spec written by spec_toml and loaded from the file, as a user would."""
    path = tmp_path / "robot.toml"
    path.write_text(spec_toml(spec), encoding="utf-8")
    assert tomllib.loads(path.read_text(encoding="utf-8")) == spec
    return load_spec(path)


# --- what the spec language can say is carried over --------------------------------


def test_reciprocal_functions_e_and_floats_read_back_equal(tmp_path: Path) -> None:
    """cot, sec, E and a float torque: written as quotients and exp(1), read back equal."""
    damping = sp.Float(0.35)
    extra = -damping * THETA.diff() + sp.cot(THETA + 2) * sp.sec(THETA) / 10 + sp.E * 0.01
    method = pendulum(extra)
    spec = spec_from_sympy(method, {"y": THETA}, "(y - sin(t))**2", VALUES, name="pendulum")
    forces = spec["system"]["mechanics"]["forces"][0]
    assert "cot" not in forces and "sec" not in forces and "exp(1)" in forces
    mech = _read_back(spec, tmp_path).mechanics
    assert mech is not None
    values = {str(k): v for k, v in VALUES.items()}
    _agree(_plain(method.mass_matrix[0, 0]), mech.mass_matrix[0][0], values)
    torque = sp.Symbol("torque", real=True)
    whole = mech.forces[0] + mech.input_matrix[0][0] * torque
    _agree(_plain(method.forcing[0]), whole, values)
    # A number: the read-back force at theta = 0.3, dtheta = -0.7, torque = 0 by hand.
    theta, rate = 0.3, -0.7
    by_hand = (
        -1.2 * 9.81 * 0.5 * math.sin(theta)
        - 0.35 * rate
        + math.cos(theta + 2) / math.sin(theta + 2) / math.cos(theta) / 10
        + math.e * 0.01
    )
    at = {sp.Symbol("theta", real=True): theta, sp.Symbol("dtheta", real=True): rate}
    at |= {sp.Symbol(k, real=True): v for k, v in values.items()}
    assert float(mech.forces[0].xreplace(at)) == pytest.approx(by_hand, rel=1e-14)


def test_a_long_sum_reads_back(tmp_path: Path) -> None:
    """70 terms: the reader's nesting limit (60) is not reached, the sum is the same."""
    q = me.dynamicsymbols("q")
    u = me.dynamicsymbols("u")
    gains = sp.symbols("k0:70")
    forcing = sp.Add(*(k * sp.sin(q) ** (i % 3 + 1) for i, k in enumerate(gains))) + u
    values = {str(k): 0.01 * (i + 1) for i, k in enumerate(gains)}
    equations = Equations(sp.Matrix([[2]]), sp.Matrix([forcing]), [q])
    spec = spec_from_sympy(equations, {"y": q}, "(y - 1)**2", values, name="chain")
    mech = _read_back(spec, tmp_path).mechanics
    assert mech is not None
    at = {sp.Symbol("q", real=True): 0.4} | {sp.Symbol(k, real=True): v for k, v in values.items()}
    expected = sum(0.01 * (i + 1) * math.sin(0.4) ** (i % 3 + 1) for i in range(70))
    assert float(mech.forces[0].xreplace(at)) == pytest.approx(expected, rel=1e-13)


# --- what it cannot say is refused at the call, naming the field --------------------


@pytest.mark.parametrize(
    ("extra", "problem"),
    [
        (-0.2 * sp.sign(THETA.diff()), "sign is not a function of the spec language"),
        (
            sp.Piecewise((-3 * THETA, THETA > 0), (0, True)),
            "Piecewise is not a function of the spec language",
        ),
        (-0.1 * sp.Abs(THETA.diff()) * THETA.diff(), "Abs is not a function"),
        (sp.I * THETA, "imaginary unit I"),
        (sp.Function("friction")(THETA.diff()), "neither a coordinate, a rate nor an input"),
        (sp.sin(sp.sin(sp.sin(THETA))), None),
    ],
)
def test_forces_the_spec_cannot_say(extra: sp.Expr, problem: str | None) -> None:
    method = pendulum(extra)
    if problem is None:
        # Three nested sines are fine: the control case of this table.
        spec = spec_from_sympy(method, {"y": THETA}, "y**2", VALUES, name="pendulum")
        assert "sin(sin(sin(theta)))" in spec["system"]["mechanics"]["forces"][0]
        return
    with pytest.raises(SpecError) as info:
        spec_from_sympy(method, {"y": THETA}, "y**2", VALUES, name="pendulum")
    message = str(info.value)
    assert message.startswith("spec_from_sympy: system.mechanics.forces[0]: "), message
    assert problem in message and "\n" not in message
    if "function of the spec language" in problem:
        assert "atan2, atanh, cos, cosh, exp, log, sin, sinh, sqrt, tan, tanh" in message


def test_a_force_nested_deeper_than_the_reader_reads() -> None:
    deep = THETA
    for _ in range(70):
        deep = sp.sin(deep, evaluate=False)
    with pytest.raises(SpecError, match=r"forces\[0\]: the expression nests deeper than 60"):
        spec_from_sympy(pendulum(deep), {"y": THETA}, "y**2", VALUES, name="pendulum")
    # 3000 deep, unevaluated: no RecursionError from sympy's own recursive walks first.
    q, u = me.dynamicsymbols("q u")
    deep = q
    for i in range(3000):
        deep = sp.Add(deep, sp.Mul(i + 2, q, evaluate=False), evaluate=False)
    equations = Equations(sp.Matrix([[2]]), sp.Matrix([sp.Add(deep, u, evaluate=False)]), [q])
    with pytest.raises(SpecError, match=r"forces\[0\]: the expression nests deeper than 60"):
        spec_from_sympy(equations, {"y": q}, "y**2", {}, name="deep")
    with pytest.raises(SpecError, match=r"outputs.y: the expression nests deeper than 60"):
        spec_from_sympy(Equations(sp.Matrix([[2]]), sp.Matrix([u]), [q]), {"y": deep}, "y", {})


@pytest.mark.parametrize(
    ("name", "problem"),
    [
        ("lambda", "is a Python keyword"),
        ("a b", "is not an identifier"),
        ("ρ", "is not ASCII"),
        ("sqrt", "built-in function or constant"),
        ("_hidden", "starts with an underscore"),
        ("theta", "has the name of the coordinate theta"),
        ("Theta", "has the name of the coordinate theta"),
        ("dtheta", "has the name of the rate dtheta"),
        ("torque", "has the name of the input torque"),
    ],
)
def test_parameter_names_the_reader_refuses(name: str, problem: str) -> None:
    """In the equations (a symbol) or only in parameters: refused, naming it."""
    stiffness = sp.Symbol(name)
    method = pendulum(-stiffness * THETA)
    with pytest.raises(SpecError, match=f"parameters.{name}") as info:
        spec_from_sympy(method, {"y": THETA}, "y**2", {**VALUES, name: 2.0}, name="pendulum")
    assert problem in str(info.value)
    with pytest.raises(SpecError, match=f"parameters.{name}") as info:
        spec_from_sympy(pendulum(), {"y": THETA}, "y**2", {**VALUES, name: 2.0}, name="pendulum")
    assert problem.replace("has the name", "has the name") in str(info.value)


def test_one_name_given_two_values() -> None:
    values = {**VALUES, "m": 3.0}
    with pytest.raises(SpecError, match=r"parameters.m: given twice, as 1.2 and 3.0"):
        spec_from_sympy(pendulum(), {"y": THETA}, "y**2", values, name="pendulum")


@pytest.mark.parametrize(
    ("where", "options", "problem"),
    [
        ("system.outputs.y", {"outputs": {"y": "__import__('os').system('true')"}}, "column"),
        ("objective.f0", {"objective": "(lambda: 1)()"}, "cannot call 'lambda: 1'"),
        ("objective.f0", {"objective": "y.__class__"}, "attribute access"),
        ("signals.r", {"signals": {"r": "open('x')"}}, "cannot call 'open'"),
        ("description", {"description": "a\x00b"}, "control character U+0000"),
        ("name", {"name": "os"}, "shadows the Python standard module"),
        ("simulation.initial_state.theta", {"initial_state": {"theta": math.nan}}, "finite"),
        ("simulation.initial_state.theta", {"initial_state": {"theta": None}}, "NoneType"),
        ("simulation.initial_state.omega", {"initial_state": {"omega": 1.0}}, "not a state"),
        ("error_dynamics.poles[1]", {"poles": [-2.0, math.inf]}, "finite"),
        ("simulation.t_final", {"t_final": math.nan}, "finite"),
        ("parameters.m", {"parameters": {**VALUES, MASS: math.nan}}, "finite"),
        ("parameters.l", {"parameters": {**VALUES, LENGTH: None}}, "expected a number"),
        ("parameters.g", {"parameters": {**VALUES, GRAVITY: np.bool_(True)}}, "expected a num"),
        ("parameters.g", {"parameters": {**VALUES, GRAVITY: "9.81"}}, "expected a number"),
    ],
)
def test_fields_the_reader_refuses(where: str, options: dict[str, Any], problem: str) -> None:
    """Each one SpecError naming the field, raised by the call (nothing to read back)."""
    call: dict[str, Any] = {
        "outputs": {"y": THETA},
        "objective": "(y - sin(t))**2",
        "parameters": VALUES,
        "name": "pendulum",
    } | options
    with pytest.raises(SpecError) as info:
        spec_from_sympy(
            pendulum(), call.pop("outputs"), call.pop("objective"), call.pop("parameters"), **call
        )
    message = str(info.value)
    assert f": {where}: " in message and problem in message and "\n" not in message, message


def test_numpy_and_sympy_numbers_are_values(tmp_path: Path) -> None:
    values = {MASS: np.float64(1.2), LENGTH: np.float32(0.5), GRAVITY: sp.Float(9.81)}
    spec = spec_from_sympy(
        pendulum(),
        {"y": THETA},
        "(y - sin(t))**2",
        values,
        name="pendulum",
        initial_state={"theta": np.float64(0.25)},
        poles=np.array([-2.0, -3.0]),
    )
    assert spec["parameters"] == {"m": 1.2, "l": float(np.float32(0.5)), "g": 9.81}
    assert spec["simulation"]["initial_state"] == {"theta": 0.25, "dtheta": 0.0}
    read = _read_back(spec, tmp_path)
    assert dict(read.parameters) == {"m": 1.2, "l": 0.5, "g": 9.81}


# --- the input order ----------------------------------------------------------------


def _two_inputs(names: str) -> tuple[Equations, list[sp.Expr]]:
    q = me.dynamicsymbols("q1:3")
    u = me.dynamicsymbols(names)
    forcing = sp.Matrix([u[0] + 2 * u[1], 3 * u[1] - sp.sin(q[0])])
    return Equations(sp.Matrix([[2, 0], [0, 1]]), forcing, list(q)), list(u)


def test_the_default_input_order_compares_digits_as_numbers() -> None:
    equations, _ = _two_inputs("u10 u2")
    spec = spec_from_sympy(equations, {"y1": "q1", "y2": "q2"}, "y1**2 + y2**2", {}, name="two")
    assert spec["system"]["inputs"] == ["u2", "u10"]
    # B's columns follow: u10 enters row 0 once, u2 twice and row 1 three times.
    assert spec["system"]["mechanics"]["input_matrix"] == [[2, 1], [3, 0]]


def test_the_input_order_can_be_given(tmp_path: Path) -> None:
    equations, u = _two_inputs("u10 u2")
    spec = spec_from_sympy(
        equations, {"y1": "q1", "y2": "q2"}, "y1**2 + y2**2", {}, name="two", inputs=[u[0], "u2"]
    )
    assert spec["system"]["inputs"] == ["u10", "u2"]
    assert spec["system"]["mechanics"]["input_matrix"] == [[1, 2], [0, 3]]
    read = _read_back(spec, tmp_path)
    assert read.inputs == ("u10", "u2")
    assert read.mechanics is not None and read.mechanics.input_matrix == ((1, 2), (0, 3))
    for order, problem in [
        (["u2"], "the order leaves out the input(s) u10"),
        (["u2", "u2", "u10"], "input u2 is listed twice"),
        (["u2", "tau"], "'tau' is not an input of the forcing (its inputs: u2, u10)"),
    ]:
        with pytest.raises(SpecError, match=r"system.inputs: ") as info:
            spec_from_sympy(equations, {"y1": "q1", "y2": "q2"}, "y1", {}, name="two", inputs=order)
        assert problem in str(info.value)


# --- spec_toml ----------------------------------------------------------------------


def test_spec_toml_writes_numpy_values_as_python_ones() -> None:
    data = {
        "a": np.float64(0.1),
        "b": np.int64(-3),
        "c": np.bool_(True),
        "d": np.array([[1.5, 2.0], [0.0, -1.0]]),
        "e": (np.float32(0.5),),
        "f": sp.Integer(7),
    }
    back = tomllib.loads(spec_toml(data))
    assert back == {
        "a": 0.1,
        "b": -3,
        "c": True,
        "d": [[1.5, 2.0], [0.0, -1.0]],
        "e": [0.5],
        "f": 7,
    }
    assert type(back["c"]) is bool and type(back["b"]) is int


def test_spec_toml_keys_and_strings_that_would_break_toml() -> None:
    data = {
        "description": 'a "quoted" line\nthen a tab\t, a backslash \\, é, 😀 and \x7f',
        'odd "key"': {"with\nnewline": 1, "a.b": [1, 2], "": "empty"},
        "plain": "'''",
    }
    assert tomllib.loads(spec_toml(data)) == data


@pytest.mark.parametrize(
    ("data", "problem"),
    [
        ({"simulation": {"initial_state": {"q": None}}}, "simulation.initial_state.q: None"),
        ({"parameters": {"m": float("nan")}}, "parameters.m: nan is not a finite number"),
        ({"x": np.float64("inf")}, "x: inf is not a finite number"),
        ({"x": {1, 2}}, "x: no TOML spelling for a set"),
        ({"x": sp.Symbol("m") + 1}, "x: the sympy expression m + 1: give its text"),
        ({1: 2}, "(spec): keys are strings"),
        ({"x": 2**64}, "beyond TOML's 64 bits"),
        ({"x": "\ud800"}, "lone surrogate"),
    ],
)
def test_spec_toml_refuses_what_toml_cannot_hold(data: dict[Any, Any], problem: str) -> None:
    with pytest.raises(SpecError) as info:
        spec_toml(data)
    assert str(info.value).startswith("spec_toml: ") and problem in str(info.value)


def test_spec_toml_bounds_nesting() -> None:
    deep: list[Any] = []
    inner = deep
    for _ in range(5000):
        inner.append([])
        inner = inner[0]
    cycle: list[Any] = []
    cycle.append(cycle)
    for value in (deep, cycle):
        with pytest.raises(SpecError, match="nested deeper than 32 tables and lists"):
            spec_toml({"x": value})


# --- the property: round-trips equal or one SpecError -------------------------------

_q = me.dynamicsymbols("q")
_u = me.dynamicsymbols("u")
_NAMES = st.one_of(
    st.just("k"),
    st.sampled_from(
        ["k", "c", "mass", "q", "Q", "dq", "u", "t", "pi", "sin", "E", "I", "print", "_k", "k1"]
        + sorted(keyword.kwlist)[:6]
    ),
    st.text(alphabet="abcxyz_ 1é\"'\n.", min_size=1, max_size=6),
)
_VALUES = st.one_of(
    st.floats(-1e3, 1e3),
    st.floats(allow_nan=True, allow_infinity=True),
    st.integers(-(10**14), 10**14),
    st.none(),
    st.booleans(),
    st.sampled_from([np.float64(2.5), np.bool_(False), np.int32(4), sp.Float(0.25), "1.0"]),
)
_LEAVES = st.one_of(
    st.just(_q),
    st.just(_q.diff()),
    st.integers(-5, 5).map(sp.Integer),
    st.sampled_from([sp.Rational(1, 3), sp.Float(0.1), sp.E, sp.pi]),
    # Rarely what the reader refuses: I, and floats beyond its literals' bounds.
    st.sampled_from([sp.I, sp.Float(1e-40), sp.Float(3e13)]) | st.just(_q),
)
# Smooth functions the spec language has (cot and sec as quotients), and more rarely
# what it lacks.
_SMOOTH = [sp.sin, sp.cos, sp.exp, sp.atan, sp.tanh, sp.cot, sp.sec]
_ROUGH = [sp.sign, sp.Abs, lambda e: sp.Piecewise((e, _q > 0), (0, True))]


def _applied(pair: tuple[Any, sp.Expr]) -> sp.Expr:
    """``f(e)``, or ``e`` alone where ``e`` is a number beyond 1e6 in size.

    SymPy evaluates a circular function of a number as it builds it, reducing the
    argument modulo pi to every digit: sin(exp(exp(40))) runs for hours, in the test's
    own strategy, before the code under test is reached.
    """
    function, argument = pair
    if argument.is_number:
        try:
            size = abs(complex(argument.evalf(15)))
        except (TypeError, ValueError, OverflowError):  # zoo, nan
            return argument
        if not size < 1e6:
            return argument
    return function(argument)


def _grow(children: st.SearchStrategy[sp.Expr]) -> st.SearchStrategy[sp.Expr]:
    smooth = st.tuples(st.sampled_from(_SMOOTH), children).map(_applied)
    sums = st.tuples(children, children).map(lambda p: p[0] + p[1])
    products = st.tuples(children, children).map(lambda p: p[0] * p[1])
    powers = st.tuples(children, st.integers(-3, 3)).map(lambda p: p[0] ** p[1])
    rough = st.tuples(st.sampled_from(_ROUGH), children).map(lambda p: p[0](p[1]))
    # One rough branch in ten: most examples must be accepted and read back.
    return st.one_of(smooth, sums, products, powers, smooth, sums, products, smooth, sums, rough)


_EXPRS = st.recursive(_LEAVES, _grow, max_leaves=6)


@settings(
    max_examples=120,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.filter_too_much],
)
@given(
    mass=_EXPRS,
    force=_EXPRS,
    name=_NAMES,
    value=_VALUES,
    output=st.one_of(
        _EXPRS, st.sampled_from(["q", "2*q", "q.real", "__import__('os')", "sign(q)"])
    ),
    description=st.text(max_size=12),
)
def test_round_trips_equal_or_one_spec_error(
    mass: sp.Expr, force: sp.Expr, name: str, value: object, output: Any, description: str
) -> None:
    """Never another exception, never a spec that fails to read back or reads back changed."""
    parameter = sp.Symbol(name)
    forcing = force + parameter * _q + _u
    equations = Equations(sp.Matrix([[mass]]), sp.Matrix([forcing]), [_q])
    try:
        spec = spec_from_sympy(
            equations,
            {"y": output},
            "(y - sin(t))**2",
            {name: cast(Any, value)},
            name="robot",
            description=description,
        )
        text = spec_toml(spec)
    except SpecError as exc:
        assert "\n" not in str(exc)
        event(f"refused: {exc.field.split('.')[0]}")
        return
    event("accepted")
    read = spec_from_dict(tomllib.loads(text))
    assert read.mechanics is not None
    values = dict(read.parameters)
    u = sp.Symbol("u", real=True)
    _agree(_plain(mass), read.mechanics.mass_matrix[0][0], values)
    whole = read.mechanics.forces[0] + read.mechanics.input_matrix[0][0] * u
    _agree(_plain(forcing), whole, values)
    if not isinstance(output, str):
        _agree(_plain(output), read.output_exprs[0], values)
    assert read.description == description


# --- hand-written [system.mechanics]: checked where the symmetry check samples ------


def _generate(data: dict[str, Any], tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> str:
    path = tmp_path / "arm.toml"
    path.write_text(spec_toml(data), encoding="utf-8")
    out = tmp_path / "out"
    code = main(["generate", str(path), "--out", str(out)])
    err = capsys.readouterr().err
    assert code == EXIT_ASSUMPTION, err
    assert err.count("\n") == 1 and "Traceback" not in err, err
    assert not out.exists()
    return err


def _arm2() -> dict[str, Any]:
    return tomllib.loads(ARM2.read_text(encoding="utf-8"))


def test_a_mass_matrix_indefinite_away_from_the_start(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """a2 = 2: det M = 1.04 - 4 cos(q2)^2, positive at the start q2 = 1.5 only nearby."""
    data = _arm2()
    data["parameters"]["a2"] = 2.0
    data["simulation"]["initial_state"]["q2"] = 1.5
    err = _generate(data, tmp_path, capsys)
    assert "system.mechanics.mass_matrix: M is not positive definite at the sample point" in err
    # The point it names: q2 there makes det M negative, by the formula above.
    q2 = float(err.split("q2 = ")[1].split(":")[0])
    assert 1.04 - 4 * math.cos(q2) ** 2 < 0
    assert "its smallest eigenvalue is -" in err


def test_a_diagonal_entry_negative_away_from_the_start(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    data = _arm2()
    data["system"]["mechanics"]["mass_matrix"][1][1] = "a3*cos(3*q1)"
    err = _generate(data, tmp_path, capsys)
    assert "system.mechanics.mass_matrix[1][1]: M is not positive definite at the sample" in err
    q1 = float(err.split("q1 = ")[1].split(",")[0])
    value = float(err.split("M[1][1] = ")[1].split(" ")[0])
    assert value == pytest.approx(0.4 * math.cos(3 * q1), rel=1e-3) and value <= 0


def test_a_force_infinite_away_from_the_start(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """exp(9000 dq1^2) is 1 at the start (dq1 = 0) and overflows where |dq1| >= 0.3."""
    data = _arm2()
    forces = data["system"]["mechanics"]["forces"]
    forces[0] = f"{forces[0]} + exp(9000*dq1**2)"
    err = _generate(data, tmp_path, capsys)
    assert "system.mechanics.forces[0]: F[0] is infinite at the sample point q1 = " in err
    dq1 = float(err.split("dq1 = ")[1].split(",")[0])
    assert 9000 * dq1**2 > math.log(np.finfo(float).max)


def test_the_bundled_robots_pass_the_sample_checks() -> None:
    """planar_arm3 and ur5_tip: positive definite and finite at every sample point."""
    from tvopt_codegen.derivation.model import build_model

    for name in ("planar_arm3", "ur5_tip"):
        build_model(load_spec(name))


_SMOOTH_LEAVES = st.one_of(
    st.just(_q),
    st.just(_q.diff()),
    st.integers(-5, 5).map(sp.Integer),
    st.sampled_from([sp.Rational(1, 3), sp.Float(0.1), sp.E, sp.pi]),
    st.floats(-1e6, 1e6).map(sp.Float),
    # Beyond the reader's literals (1e-30 to 1e12): written as products it folds exactly.
    st.sampled_from([sp.Float(2.5e-40), sp.Float(-1.25e15), sp.Integer(10**14 + 3)]),
)


def _grow_smooth(children: st.SearchStrategy[sp.Expr]) -> st.SearchStrategy[sp.Expr]:
    return st.one_of(
        st.tuples(st.sampled_from(_SMOOTH), children).map(_applied),
        st.tuples(children, children).map(lambda p: p[0] + p[1]),
        st.tuples(children, children).map(lambda p: p[0] * p[1]),
        st.tuples(children, st.integers(-3, 3)).map(lambda p: p[0] ** p[1]),
    )


@settings(max_examples=80, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(force=st.recursive(_SMOOTH_LEAVES, _grow_smooth, max_leaves=8))
def test_smooth_forces_always_read_back_equal(force: sp.Expr) -> None:
    """What the spec language can say is carried over: accepted, and read back equal."""
    forcing = force - sp.Symbol("k") * _q + _u
    equations = Equations(sp.Matrix([[sp.Integer(2)]]), sp.Matrix([forcing]), [_q])
    try:
        spec = spec_from_sympy(equations, {"y": _q}, "(y - sin(t))**2", {"k": 1.5}, name="robot")
    except SpecError as exc:
        # Only numbers no double holds may be refused: cot(0) folded to zoo, or a
        # product of floats beyond 1.8e308.
        reasons = ("infinite or undefined", "which no double holds", "constant too large")
        assert any(reason in str(exc) for reason in reasons), str(exc)
        event("refused")
        return
    event("accepted")
    read = spec_from_dict(tomllib.loads(spec_toml(spec)))
    assert read.mechanics is not None
    whole = read.mechanics.forces[0] + read.mechanics.input_matrix[0][0] * sp.Symbol("u", real=True)
    _agree(_plain(forcing), whole, {"k": 1.5})


def test_outputs_and_objective_as_sympy_expressions(tmp_path: Path) -> None:
    """A plain symbol named like a coordinate is the coordinate in outputs and f0."""
    theta, y, t = sp.symbols("theta y t")
    spec = spec_from_sympy(
        pendulum(),
        {"y": LENGTH * sp.sin(theta)},
        (y - sp.Rational(1, 4) * sp.sin(t)) ** 2,
        VALUES,
        name="pendulum",
    )
    read = _read_back(spec, tmp_path)
    at = {sp.Symbol("theta", real=True): 0.3, sp.Symbol("l", real=True): 0.5}
    assert float(read.output_exprs[0].xreplace(at)) == pytest.approx(0.5 * math.sin(0.3))
    f0 = read.objective.xreplace({sp.Symbol("y", real=True): 0.2, sp.Symbol("t", real=True): 1})
    assert float(f0) == pytest.approx((0.2 - 0.25 * math.sin(1.0)) ** 2, rel=1e-15)


def test_a_function_of_an_infinity_is_refused_as_infinite() -> None:
    """atan(q + zoo) is sympy's range AccumBounds(-pi/2, pi/2) (found by the test above):
    refused as what it is, a value of an infinite argument, not as an unknown class."""
    forcing = sp.atan(_q + sp.zoo) - sp.Symbol("k") * _q + _u
    equations = Equations(sp.Matrix([[sp.Integer(2)]]), sp.Matrix([forcing]), [_q])
    with pytest.raises(SpecError, match="a range from an infinite or undefined argument"):
        spec_from_sympy(equations, {"y": _q}, "(y - sin(t))**2", {"k": 1.5}, name="robot")


def test_read_back_equal_means_equal_in_exact_arithmetic() -> None:
    """sin(1.25e15 cot(q)) and sin(1.25e15 / tan(q)) differ as doubles (the found example
    of the test above) and agree to 60 digits; a change of 1e-9 fails either way."""
    q = sp.Symbol("q", real=True)
    _agree(sp.sin(sp.Float(1.25e15) * sp.cot(q)), sp.sin(sp.Float(1.25e15) / sp.tan(q)), {})
    with pytest.raises(AssertionError):
        _agree(
            sp.sin(sp.Float(1.25e15) * sp.cot(q)), sp.sin(sp.Float(1.25e15) / sp.tan(q)) + 1e-9, {}
        )
    with pytest.raises(AssertionError):
        _agree(sp.sin(q), sp.sin(q) + sp.Float(1e-9), {})
