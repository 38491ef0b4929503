"""Specs from robot models as roboticists write them: SymPy mechanics.

:func:`spec_from_sympy` turns the equations of motion that ``sympy.physics.mechanics``
forms (``KanesMethod``, ``LagrangesMethod``, or a ``System`` after ``form_eoms()``)
into a spec in mass-matrix form (``[system.mechanics]``, docs/spec.md): the
generalized coordinates and their rates become the states, the other dynamic symbols
of the forcing the inputs, and every other free symbol a named parameter that
``--plant-param`` can perturb. :func:`spec_toml` writes that mapping as TOML text.

Both are total: what they return reads back, through the project's own reader, as
the same spec; what the spec language cannot say is refused at the call, with one
:class:`~tvopt_codegen.errors.SpecError` naming the field, and nothing is written.

``M`` is never inverted here or later: the generated code factors it at run time.
"""

from __future__ import annotations

import decimal
import math
import numbers
import re
import tomllib
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np
import sympy as sp
from sympy.printing.str import StrPrinter

from tvopt_codegen.errors import SpecError, clip, one_line
from tvopt_codegen.names import name_problem
from tvopt_codegen.numeric import Evaluator
from tvopt_codegen.parse import FUNCTIONS, MAX_DEPTH, MAX_EXPONENT, MAX_LITERAL, MIN_LITERAL
from tvopt_codegen.spec.implicit import affine_split

__all__ = ["spec_from_sympy", "spec_toml"]

#: The poles a spec from :func:`spec_from_sympy` asks for unless told (k = 2).
DEFAULT_POLES = (-2.0, -3.0)

#: What errors of :func:`spec_from_sympy` and :func:`spec_toml` name as their source.
SOURCE_SYMPY = "spec_from_sympy"
SOURCE_TOML = "spec_toml"

#: Most nodes (counted as a tree) one expression may print: the reader takes at most
#: 1,000,000 characters, and an expression sharing subtrees can print exponentially long.
MAX_NODES = 200_000

#: Deepest nesting of tables and lists :func:`spec_toml` writes (a spec nests four).
MAX_TOML_DEPTH = 32

#: Sums and products with more terms than this are printed in parenthesized groups:
#: the reader nests a chain of n terms n deep, and refuses more than MAX_DEPTH.
_CHAIN = 24
_GROUPS = 8

#: Functions the spec language lacks that are exactly quotients of ones it has.
_RECIPROCALS: tuple[tuple[type[sp.Function], Callable[[sp.Expr], sp.Expr]], ...] = (
    (sp.sec, lambda a: 1 / sp.cos(a)),
    (sp.csc, lambda a: 1 / sp.sin(a)),
    (sp.cot, lambda a: sp.cos(a) / sp.sin(a)),
    (sp.sech, lambda a: 1 / sp.cosh(a)),
    (sp.csch, lambda a: 1 / sp.sinh(a)),
    (sp.coth, lambda a: sp.cosh(a) / sp.sinh(a)),
)

#: The sympy classes of the spec language's functions (sqrt is a power in sympy).
_ALLOWED_CLASSES = frozenset(f for f, _ in FUNCTIONS.values() if isinstance(f, type))
_ALLOWED_TEXT = ", ".join(sorted(FUNCTIONS))


def _rate_of(coordinate: sp.Expr) -> sp.Expr:
    """The symbol ``q'(t)`` of a coordinate ``q(t)``, as SymPy mechanics spells it."""
    if not isinstance(coordinate, sp.core.function.AppliedUndef):
        raise ValueError(f"coordinate {coordinate} is not a dynamic symbol")
    return sp.physics.mechanics.dynamicsymbols(coordinate.func.__name__, 1)


def _equations(eoms: Any) -> tuple[sp.Matrix, sp.Matrix, list[sp.Expr], dict[sp.Expr, sp.Expr]]:
    """``M``, the forcing, the coordinates and the map of each ``q_i'`` to its rate symbol.

    Kane's speeds must be the coordinates' derivatives (``q_i' = u_j``, in any order):
    the rows and columns of Kane's mass matrix are then reordered to the coordinates'.
    """
    method = getattr(eoms, "eom_method", None)
    if method is not None and not isinstance(eoms, sp.physics.mechanics.KanesMethod):
        eoms = method  # a System: the method it formed its equations with
    kind = type(eoms)
    if not hasattr(kind, "mass_matrix") or not hasattr(kind, "forcing"):
        raise TypeError(
            "expected a KanesMethod, a LagrangesMethod or a System after form_eoms(), got "
            f"{type(eoms).__name__}"
        )
    try:
        mass, forcing = sp.Matrix(eoms.mass_matrix), sp.Matrix(eoms.forcing)
    except (AttributeError, ValueError) as exc:
        raise ValueError(f"the equations of motion are not formed yet ({exc})") from None
    q = list(eoms.q)
    if isinstance(eoms, sp.physics.mechanics.KanesMethod):
        speeds = list(eoms.u)
        kinematics = eoms.kindiffdict()
        order: list[int] = []
        for coordinate in q:
            rate = kinematics.get(_rate_of(coordinate))
            if rate not in speeds or rate in (speeds[i] for i in order):
                raise ValueError(
                    f"the speeds must be the coordinates' derivatives: {_rate_of(coordinate)} = "
                    f"{rate} is not one speed of {speeds}"
                )
            order.append(speeds.index(rate))
        mass = mass.extract(order, order)
        forcing = forcing.extract(order, [0])
        rates = {_rate_of(coordinate): speeds[j] for coordinate, j in zip(q, order, strict=True)}
    else:
        rates = {_rate_of(coordinate): _rate_of(coordinate) for coordinate in q}
    return mass, forcing, q, rates


def _fail(field: str, problem: str) -> SpecError:
    # A name may hold a newline: the message stays one line.
    return SpecError(SOURCE_SYMPY, one_line(field), one_line(problem))


def _symbol_name(symbol: object) -> str:
    """A dynamic symbol's, a symbol's or a string's name."""
    if isinstance(symbol, sp.core.function.AppliedUndef):
        return str(symbol.func.__name__)
    if isinstance(symbol, sp.Symbol):
        return str(symbol.name)
    return symbol if isinstance(symbol, str) else repr(symbol)


def _name(symbol: object, field: str) -> str:
    """A dynamic symbol's or a symbol's name, checked as the spec reader checks names."""
    name = _symbol_name(symbol)
    problem = name_problem(name)
    if problem:
        raise _fail(field, problem)
    return name


def _natural(name: str) -> tuple[list[int | str], str]:
    """Sort key that puts ``tau2`` before ``tau10``."""
    parts = re.split(r"(\d+)", name)
    return [int(p) if p.isdigit() else p for p in parts], name


def _number(value: object, field: str) -> float:
    """A finite real number from a Python, NumPy or SymPy number; else one SpecError."""
    if isinstance(value, bool | np.bool_) or value is None or isinstance(value, str):
        raise _fail(field, f"expected a number, got {type(value).__name__} {clip(repr(value))}")
    if isinstance(value, sp.Basic):
        if not value.is_number or not value.is_real:
            raise _fail(field, f"expected a real number, got {clip(sp.sstr(value))}")
    elif not isinstance(value, numbers.Real):
        raise _fail(field, f"expected a number, got {type(value).__name__}")
    try:
        result = float(value)
    except (TypeError, ValueError, OverflowError) as exc:
        raise _fail(field, f"expected a real number ({exc})") from None
    if not math.isfinite(result):
        raise _fail(field, f"expected a finite number, got {result}")
    return result


class _Printer(StrPrinter):  # type: ignore[misc]
    """sympy's text form, as the spec reader reads it back.

    Floats are written as the shortest decimal of their double (what the reader makes
    of them), ``E`` as ``exp(1)``, and long sums and products in parenthesized groups
    so that the reader's nesting limit is not reached by a flat chain of terms.
    """

    def _print_Float(self, expr: sp.Float) -> str:
        value = float(expr)
        if value == 0 or MIN_LITERAL <= abs(value) <= MAX_LITERAL:
            return repr(value)
        # Beyond the reader's literals: the same decimal as an exact product it folds.
        sign, digits, exponent = decimal.Decimal(repr(value)).as_tuple()
        assert isinstance(exponent, int)
        mantissa = int("".join(map(str, digits))) * (-1 if sign else 1)
        return f"({_exact(mantissa)}*{_power_of_ten(exponent)})"

    def _print_Integer(self, expr: sp.Integer) -> str:
        return _exact(int(expr))

    def _print_Rational(self, expr: sp.Rational) -> str:
        return f"{_exact(int(expr.p))}/{_exact(int(expr.q))}"

    def _print_Exp1(self, expr: sp.Expr) -> str:
        return "exp(1)"

    def _print_Add(self, expr: sp.Add, order: str | None = None) -> str:
        terms = list(expr.args)
        if len(terms) <= _CHAIN:
            return str(super()._print_Add(expr, order=order))
        terms = self._as_ordered_terms(expr, order=order)
        return " + ".join(f"({self._print(sp.Add(*g, evaluate=False))})" for g in _groups(terms))

    def _print_Mul(self, expr: sp.Mul) -> str:
        factors = list(expr.args)
        if len(factors) <= _CHAIN:
            return str(super()._print_Mul(expr))
        return "*".join(f"({self._print(sp.Mul(*g, evaluate=False))})" for g in _groups(factors))


def _exact(number: int) -> str:
    """An integer as text the reader folds back exactly (its literals stop at 1e12)."""
    if abs(number) <= MAX_LITERAL:
        return str(number)
    chunk = 10**12
    rest, terms, power = abs(number), [], 0
    while rest:
        rest, digits = divmod(rest, chunk)
        if digits:
            terms.append(str(digits) if power == 0 else f"{digits}*{chunk}**{power}")
        power += 1
    return f"({'-' if number < 0 else ''}({' + '.join(reversed(terms))}))"


def _power_of_ten(exponent: int) -> str:
    """``10**exponent`` in factors whose exponents the reader takes (at most 64)."""
    step = MAX_EXPONENT if exponent > 0 else -MAX_EXPONENT
    factors = []
    while abs(exponent) > MAX_EXPONENT:
        factors.append(f"10**{step}" if step > 0 else f"10**({step})")
        exponent -= step
    factors.append(f"10**{exponent}" if exponent >= 0 else f"10**({exponent})")
    return "*".join(factors)


def _groups(items: Sequence[sp.Expr]) -> list[list[sp.Expr]]:
    """``items`` in at most :data:`_GROUPS` consecutive groups of near-equal size."""
    size = -(-len(items) // _GROUPS)
    return [list(items[i : i + size]) for i in range(0, len(items), size)]


# Terms in sympy's own order: the printer's default order evaluates constant terms
# with mpmath to sort them, which takes hours for sin(exp(exp(40))).
_PRINTER = _Printer({"full_prec": True, "order": "none"})


def _refusal(node: sp.Basic) -> str | None:
    """Why the spec language cannot say ``node`` (one node, not its arguments), or None."""
    if isinstance(node, sp.Symbol | sp.Rational | sp.Add | sp.Mul | sp.Pow):
        return None
    if node is sp.pi or node is sp.E:
        return None
    if isinstance(node, sp.Float):
        # sympy's floats reach 1e400 and beyond; the spec's numbers are doubles.
        finite = node.is_finite and math.isfinite(float(node))
        return None if finite else f"holds the number {clip(str(node))}, which no double holds"
    if node is sp.I or isinstance(node, sp.core.numbers.ImaginaryUnit):
        return "holds the imaginary unit I (spec expressions are real)"
    if node in (sp.zoo, sp.oo, sp.S.NegativeInfinity, sp.nan):
        return f"holds {node}, which is infinite or undefined"
    if isinstance(node, sp.AccumBounds):
        # sympy's value of a function at an infinity (atan(zoo), sin(oo)): a range.
        return f"holds {clip(sp.sstr(node))}, a range from an infinite or undefined argument"
    if isinstance(node, sp.NumberSymbol):
        return f"holds the constant {node}, which the spec language lacks (it has pi)"
    if isinstance(node, sp.Derivative):
        return f"holds the derivative {clip(sp.sstr(node))}"
    if isinstance(node, sp.core.function.AppliedUndef):
        return (
            f"holds {clip(sp.sstr(node))}, which is neither a coordinate, a rate nor an input "
            "(dynamic symbols are functions of t alone)"
        )
    if type(node) in _ALLOWED_CLASSES:
        return None
    name = type(node).__name__
    if not isinstance(node, sp.Function):
        return f"{name} is not part of the spec language (+ - * / **, pi, {_ALLOWED_TEXT})"
    return (
        f"{name} is not a function of the spec language (its functions are smooth: "
        f"{_ALLOWED_TEXT}); write the model without it"
    )


def _check_depth(expr: object, field: str) -> None:
    """Nesting within the reader's limit, checked before any recursive sympy operation.

    By object identity, without hashing: hashing a node hashes its arguments, and a tree
    thousands deep would exhaust Python's recursion there.
    """
    if not isinstance(expr, sp.Basic):
        return
    deepest: dict[int, int] = {}
    stack = [(expr, 1)]
    while stack:
        node, depth = stack.pop()
        if depth > MAX_DEPTH:
            raise _fail(field, f"the expression nests deeper than {MAX_DEPTH} operations")
        if deepest.get(id(node), 0) >= depth:
            continue
        deepest[id(node)] = depth
        stack.extend((a, depth + 1) for a in node.args)


def _check_tree(expr: sp.Basic, field: str) -> None:
    """Every node sayable, nesting and printed size bounded; iterative (no recursion)."""
    depth: dict[sp.Basic, int] = {}
    size: dict[sp.Basic, int] = {}
    stack: list[tuple[sp.Basic, bool]] = [(expr, False)]
    while stack:
        node, done = stack.pop()
        if node in depth:
            continue
        if done:
            depth[node] = 1 + max((depth[a] for a in node.args), default=0)
            size[node] = 1 + sum(size[a] for a in node.args)
            if depth[node] > MAX_DEPTH:
                raise _fail(field, f"the expression nests deeper than {MAX_DEPTH} operations")
            if size[node] > MAX_NODES:
                raise _fail(
                    field, f"the expression is larger than {MAX_NODES} operations written out"
                )
            continue
        problem = _refusal(node)
        if problem:
            raise _fail(field, problem)
        stack.append((node, True))
        stack.extend((a, False) for a in node.args if a not in depth)


def _sayable(expr: object, field: str) -> sp.Expr:
    """``expr`` as a sympy expression the spec language can say (reciprocal trig rewritten)."""
    if isinstance(expr, bool | np.bool_) or expr is None:
        raise _fail(field, f"expected an expression, got {type(expr).__name__}")
    if isinstance(expr, int | np.integer):
        expr = sp.Integer(int(expr))
    elif isinstance(expr, numbers.Real) and not isinstance(expr, sp.Basic):
        expr = sp.Float(_number(expr, field))
    try:
        value = sp.sympify(expr, strict=True)
    except (sp.SympifyError, TypeError, ValueError):
        raise _fail(field, f"expected a sympy expression, got {type(expr).__name__}") from None
    if not isinstance(value, sp.Expr):
        raise _fail(field, f"{type(value).__name__} is not an expression the spec can hold")
    for kind, rewrite in _RECIPROCALS:
        if value.has(kind):
            value = value.replace(kind, rewrite)
    _check_tree(value, field)
    return value


def _text(expr: sp.Expr, field: str, *, string: bool = False) -> str | int | float:
    """An expression as spec text; an integer or a float stays a number unless ``string``."""
    # A number the reader's literals take stays a number; others are folded text.
    if not string and isinstance(expr, sp.Integer) and abs(int(expr)) <= MAX_LITERAL:
        return int(expr)
    if (
        not string
        and isinstance(expr, sp.Float)
        and (expr == 0 or MIN_LITERAL <= abs(float(expr)) <= MAX_LITERAL)
    ):
        return float(expr)
    try:
        return str(_PRINTER.doprint(expr))
    except RecursionError:
        raise _fail(field, f"the expression nests deeper than {MAX_DEPTH} operations") from None


def _rational(expr: sp.Expr) -> sp.Expr:
    """``expr`` with each float as the exact decimal the reader makes of it."""
    floats = expr.atoms(sp.Float)
    if not floats:
        return expr
    return expr.xreplace({f: sp.Rational(repr(float(f))) for f in floats})


def _same(ours: sp.Expr, read: sp.Expr) -> bool:
    """Whether the reader's expression is ours: structurally, else at random points.

    Evaluated, not simplified: a nonzero difference at a random point is a proof, and
    simplify on a robot's forcing takes minutes.
    """
    ours = _rational(ours)
    if ours == read:
        return True
    symbols = sorted(ours.free_symbols | read.free_symbols, key=str)
    rng = np.random.default_rng(20191127)
    points = 6
    values = {
        s: rng.uniform(0.3, 1.7, points) * np.where(rng.uniform(size=points) < 0.5, -1, 1)
        for s in symbols
    }
    evaluate = Evaluator(values)
    a = np.broadcast_to(np.asarray(evaluate(ours), dtype=complex), (points,))
    b = np.broadcast_to(np.asarray(evaluate(read), dtype=complex), (points,))
    defined = np.isfinite(a) & np.isfinite(b)
    if not np.array_equal(np.isfinite(a), np.isfinite(b)):
        return False
    if not defined.any():
        return True  # undefined at every point, both: no simplify (minutes on a robot)
    scale = max(1.0, float(np.max(np.abs(a[defined]))))
    return bool(np.all(np.abs(a[defined] - b[defined]) <= 1e-9 * scale))


def spec_from_sympy(
    eoms: Any,
    outputs: Mapping[str, sp.Expr | str],
    objective: str | sp.Expr,
    parameters: Mapping[sp.Symbol | str, float],
    *,
    name: str = "robot",
    description: str = "",
    signals: Mapping[str, str | sp.Expr] | None = None,
    poles: Sequence[float] | np.ndarray = DEFAULT_POLES,
    t_final: float = 10.0,
    initial_state: Mapping[str, float] | None = None,
    simplify: bool = False,
    inputs: Sequence[sp.Expr | str] | None = None,
) -> dict[str, Any]:
    """The spec of a robot whose equations of motion SymPy mechanics formed.

    Parameters
    ----------
    eoms : KanesMethod, LagrangesMethod or System
        After ``kanes_equations``, ``form_lagranges_equations`` or ``form_eoms``. Kane's
        speeds must be the coordinates' derivatives (``q_i' = u_j``).
    outputs : mapping of str to sympy.Expr or str
        Each output's name and its expression in the coordinates (dynamic symbols, or
        text in their names).
    objective : str or sympy.Expr
        ``f0`` in the outputs, the signals, the parameters and ``t``.
    parameters : mapping of sympy.Symbol or str to float
        A finite value for every free symbol of the equations and the outputs (Python,
        NumPy or SymPy numbers).
    name, description : str
        The spec's (and the generated module's) name, and its description.
    signals : mapping of str to str or sympy.Expr, optional
        ``[signals]``: named expressions in ``t`` and the parameters.
    poles : sequence of float or numpy.ndarray
        ``[error_dynamics] poles``, finite.
    t_final : float
        ``[simulation] t_final``.
    initial_state : mapping of str to float, optional
        ``[simulation] initial_state`` by state name (omitted states start at 0).
    simplify : bool
        Write each entry of ``M``, ``F`` and ``B`` after ``trigsimp`` (a readable spec;
        its cost grows quickly with the number of links). The derivation does not need
        it: expressions are evaluated as written, with common subexpressions shared.
    inputs : sequence of sympy.Expr or str, optional
        The inputs (dynamic symbols of the forcing, or their names) in the order the
        spec declares them: the order of ``B``'s columns and of the controller's
        output. Each input once, all of them. Unless given, sorted by name with digits
        compared as numbers (``tau2`` before ``tau10``).

    Returns
    -------
    dict
        The spec as a mapping: :func:`tvopt_codegen.spec_from_dict` reads it back as
        the same ``M``, ``F``, ``B``, outputs and objective (checked before returning),
        and :func:`spec_toml` writes it.

    Raises
    ------
    SpecError
        One line naming the field and the problem, for anything the spec cannot say:
        ``eoms`` of another kind or not formed, a speed that is not a coordinate's
        derivative, forcing not affine in the inputs or depending on time, a function
        outside the spec language (``sign``, ``Abs``, ``Piecewise``; the message lists
        the allowed ones), the imaginary unit, a name the reader refuses or two things
        of one name, a parameter without a finite value, an input order that is not
        the inputs, a non-finite pole, time or initial value.
    """
    try:
        mass, forcing, q, rates = _equations(eoms)
    except (TypeError, ValueError) as exc:
        raise _fail("eoms", str(exc)) from None
    except RecursionError:
        raise _fail("eoms", f"an expression nests deeper than {MAX_DEPTH} operations") from None
    for i in range(mass.rows):
        for j in range(mass.cols):
            _check_depth(mass[i, j], f"system.mechanics.mass_matrix[{i}][{j}]")
    for i, entry in enumerate(forcing):
        _check_depth(entry, f"system.mechanics.forces[{i}]")
    if isinstance(outputs, Mapping):
        for key, value in outputs.items():
            _check_depth(value, f"system.outputs.{key}")
    _check_depth(objective, "objective.f0")
    if isinstance(signals, Mapping):
        for key, value in signals.items():
            _check_depth(value, f"signals.{key}")
    t = sp.physics.mechanics.dynamicsymbols._t
    coordinates = [_name(c, "system.coordinates") for c in q]
    # Kane's speeds keep their names; a Lagrangian's rates are d<coordinate>.
    rate_names = [
        _name(rates[_rate_of(c)], "system.mechanics.rates")
        if rates[_rate_of(c)] != _rate_of(c)
        else f"d{name_}"
        for c, name_ in zip(q, coordinates, strict=True)
    ]
    for rate in rate_names:
        problem = name_problem(rate)
        if problem:
            raise _fail("system.mechanics.rates", f"the rate {problem}")
    plain: dict[sp.Expr, sp.Expr] = {}
    for c, coordinate, rate in zip(q, coordinates, rate_names, strict=True):
        plain[rates[_rate_of(c)]] = sp.Symbol(rate, real=True)
        plain[_rate_of(c)] = sp.Symbol(rate, real=True)
        plain[c] = sp.Symbol(coordinate, real=True)
    known = set(q) | set(rates.values())
    found = sp.physics.mechanics.find_dynamicsymbols(
        forcing
    ) | sp.physics.mechanics.find_dynamicsymbols(mass)
    extra = [s for s in found if s not in known and s not in plain]
    derivatives = sorted((s for s in extra if isinstance(s, sp.Derivative)), key=str)
    if derivatives:
        raise _fail(
            "system.mechanics.forces",
            f"the equations hold {clip(sp.sstr(derivatives[0]))}, a derivative that is not "
            "a rate (the forcing is a function of q, q' and the inputs)",
        )
    # An input is a function of t alone; f(q(t)) is an unknown function (refused below).
    extra = [s for s in extra if s.args == (t,)]
    extra = sorted(extra, key=lambda s: _natural(_symbol_name(s)))
    input_names = [_name(s, "system.inputs") for s in extra]
    extra, input_names = _input_order(extra, input_names, inputs)
    _unique(
        [
            *(("system.coordinates", n) for n in coordinates),
            *(("system.mechanics.rates", n) for n in rate_names),
            *(("system.inputs", n) for n in input_names),
        ]
    )
    plain |= {s: sp.Symbol(n, real=True) for s, n in zip(extra, input_names, strict=True)}
    states = {n.casefold(): f"{what} {n}" for what, ns in (
        ("coordinate", coordinates), ("rate", rate_names), ("input", input_names)
    ) for n in ns}  # fmt: skip

    def to_plain(expr: object, field: str) -> sp.Expr:
        value = _sayable(expr, field) if not isinstance(expr, sp.Basic) else sp.sympify(expr)
        # Derivatives first: q1(t) inside Derivative(q1(t), t) must not be replaced alone.
        derivs = {k: v for k, v in plain.items() if isinstance(k, sp.Derivative)}
        value = value.xreplace(derivs).xreplace(plain)
        # Every other symbol is a parameter, read back as a real symbol of its name.
        table: dict[sp.Basic, sp.Basic] = {}
        for s in value.free_symbols:
            if s == t or s in plain.values():
                continue
            assert isinstance(s, sp.Symbol)
            problem = name_problem(s.name)
            if problem:
                raise _fail(f"parameters.{s.name}", f"a symbol of {field}: {problem}")
            exact = {n.casefold(): n for n in (*coordinates, *rate_names, *input_names)}
            if not field.startswith("system.mechanics") and exact.get(s.name.casefold()) == s.name:
                # Outputs, signals and f0 may name a state by a plain symbol of its name.
                table[s] = sp.Symbol(s.name, real=True)
                continue
            if s.name.casefold() in states:
                raise _fail(
                    f"parameters.{s.name}",
                    f"the symbol {s.name} of {field} has the name of the "
                    f"{states[s.name.casefold()]} (names are unique, ignoring case): rename "
                    "one of them",
                )
            table[s] = sp.Symbol(s.name, real=True)
        return _sayable(value.xreplace(table), field)

    n = mass.rows
    M = [
        [to_plain(mass[i, j], f"system.mechanics.mass_matrix[{i}][{j}]") for j in range(n)]
        for i in range(n)
    ]
    forces = [to_plain(e, f"system.mechanics.forces[{i}]") for i, e in enumerate(forcing)]
    if simplify:
        # trigsimp may write cot or sec, which the spec language says as quotients.
        M = [
            [
                _sayable(sp.factor_terms(sp.trigsimp(e)), f"system.mechanics.mass_matrix[{i}][{j}]")
                for j, e in enumerate(row)
            ]
            for i, row in enumerate(M)
        ]
        forces = [
            _sayable(sp.factor_terms(sp.trigsimp(e)), f"system.mechanics.forces[{i}]")
            for i, e in enumerate(forces)
        ]
    u = [sp.Symbol(name_, real=True) for name_ in input_names]
    for i in range(n):
        for j in range(n):
            held = sorted(s.name for s in M[i][j].free_symbols & set(u))
            if held:
                raise _fail(
                    f"system.mechanics.mass_matrix[{i}][{j}]",
                    f"M depends on the input {held[0]} (M is a function of the coordinates)",
                )
    try:
        gain, rest = affine_split(forces, u)
    except ValueError as exc:
        raise _fail(
            "system.mechanics.forces", f"the forcing is not affine in the inputs: {exc}"
        ) from None
    if any(t in e.free_symbols for e in (*(e for row in M for e in row), *rest, *sum(gain, ()))):
        raise _fail(
            "system.mechanics", "the equations depend on time t: the plant must be time-invariant"
        )
    if not isinstance(outputs, Mapping):
        raise _fail("system.outputs", f"expected a mapping, got {type(outputs).__name__}")
    h: dict[str, sp.Expr | str] = {}
    for key, value in outputs.items():
        field = f"system.outputs.{key}"
        if not isinstance(key, str):
            raise _fail("system.outputs", f"output names are strings, got {type(key).__name__}")
        h[key] = value if isinstance(value, str) else to_plain(value, field)
    values = _parameter_values(parameters)
    for key in values:
        if key.casefold() in states:
            raise _fail(
                f"parameters.{key}",
                f"has the name of the {states[key.casefold()]} (names are unique, ignoring "
                "case): rename the parameter",
            )
    used = set().union(
        *(
            e.free_symbols
            for e in (*(e for row in M for e in row), *forces, *h.values())
            if not isinstance(e, str)
        )
    )
    missing = sorted(
        s.name for s in used if s.name.casefold() not in states and s.name not in values
    )
    if missing:
        raise _fail(f"parameters.{missing[0]}", f"no value in parameters for {', '.join(missing)}")
    spec: dict[str, Any] = {"name": name}
    if description:
        spec["description"] = description
    spec["system"] = {
        "coordinates": coordinates,
        "inputs": input_names,
        "mechanics": {
            "rates": rate_names,
            "mass_matrix": [
                [_text(M[i][j], f"system.mechanics.mass_matrix[{i}][{j}]") for j in range(n)]
                for i in range(n)
            ],
            "forces": [_text(e, f"system.mechanics.forces[{i}]") for i, e in enumerate(rest)],
            "input_matrix": [
                [_text(e, f"system.mechanics.input_matrix[{i}][{j}]") for j, e in enumerate(row)]
                for i, row in enumerate(gain)
            ],
        },
        "outputs": {
            key: value
            if isinstance(value, str)
            else _text(value, f"system.outputs.{key}", string=True)
            for key, value in h.items()
        },
    }
    spec["parameters"] = values
    if signals:
        if not isinstance(signals, Mapping):
            raise _fail("signals", f"expected a mapping, got {type(signals).__name__}")
        spec["signals"] = {
            key: value
            if isinstance(value, str)
            else _text(to_plain(value, f"signals.{key}"), f"signals.{key}", string=True)
            for key, value in signals.items()
        }
    f0 = (
        objective
        if isinstance(objective, str)
        else _text(to_plain(objective, "objective.f0"), "objective.f0", string=True)
    )
    spec["objective"] = {"f0": f0}
    if isinstance(poles, str | bytes) or not isinstance(poles, Sequence | np.ndarray):
        raise _fail("error_dynamics.poles", f"expected a list of numbers, got {poles!r}")
    spec["error_dynamics"] = {
        "poles": [_number(p, f"error_dynamics.poles[{i}]") for i, p in enumerate(poles)]
    }
    spec["simulation"] = {"t_final": _number(t_final, "simulation.t_final")}
    if initial_state:
        start = _initial_state(initial_state, [*coordinates, *rate_names])
        spec["simulation"]["initial_state"] = start
    _reads_back(spec, M, rest, gain, h)
    return spec


def _input_order(
    found: list[sp.Expr], names: list[str], given: Sequence[sp.Expr | str] | None
) -> tuple[list[sp.Expr], list[str]]:
    """The inputs in the caller's order, each once and all of them; else sorted."""
    if given is None:
        return found, names
    field = "system.inputs"
    if isinstance(given, str) or not isinstance(given, Sequence):
        raise _fail(field, f"inputs: expected a list of dynamic symbols or names, got {given!r}")
    order: list[int] = []
    for item in given:
        wanted = _symbol_name(item)
        if wanted not in names:
            raise _fail(
                field,
                f"{clip(wanted)!r} is not an input of the forcing (its inputs: "
                f"{', '.join(names) or 'none'})",
            )
        index = names.index(wanted)
        if index in order:
            raise _fail(field, f"input {wanted} is listed twice")
        order.append(index)
    left = [names[i] for i in range(len(names)) if i not in order]
    if left:
        raise _fail(field, f"the order leaves out the input(s) {', '.join(left)}")
    return [found[i] for i in order], [names[i] for i in order]


def _unique(named: list[tuple[str, str]]) -> None:
    """No two states or inputs of one name (ignoring case, as the reader compares)."""
    seen: dict[str, tuple[str, str]] = {}
    for field, name in named:
        other = seen.get(name.casefold())
        if other is not None:
            raise _fail(
                field,
                f"{name} is also the name of {other[0]}'s {other[1]} "
                "(names must be unique, ignoring case)",
            )
        seen[name.casefold()] = (field, name)


def _parameter_values(parameters: Mapping[sp.Symbol | str, float]) -> dict[str, float]:
    """``{name: value}``: names checked, values finite, one value per name."""
    if not isinstance(parameters, Mapping):
        raise _fail("parameters", f"expected a mapping, got {type(parameters).__name__}")
    values: dict[str, float] = {}
    for key, value in parameters.items():
        if not isinstance(key, str | sp.Symbol):
            raise _fail("parameters", f"a key is a {type(key).__name__}, not a symbol or a name")
        name = _symbol_name(key)
        field = f"parameters.{name}"
        problem = name_problem(name)
        if problem:
            raise _fail(field, problem)
        number = _number(value, field)
        if name in values and values[name] != number:
            raise _fail(field, f"given twice, as {values[name]!r} and {number!r}")
        values[name] = number
    return values


def _initial_state(given: Mapping[str, float], states: list[str]) -> dict[str, float]:
    """Every state's start (0 unless given), each given one a state with a finite value."""
    if not isinstance(given, Mapping):
        raise _fail("simulation.initial_state", f"expected a mapping, got {type(given).__name__}")
    start = dict.fromkeys(states, 0.0)
    for key, value in given.items():
        name = _symbol_name(key)
        if name not in start:
            raise _fail(
                f"simulation.initial_state.{clip(name)}",
                f"not a state (the states: {', '.join(states)})",
            )
        start[name] = _number(value, f"simulation.initial_state.{name}")
    return start


def _reads_back(
    spec: dict[str, Any],
    mass: list[list[sp.Expr]],
    forces: Sequence[sp.Expr],
    gain: Sequence[Sequence[sp.Expr]],
    outputs: Mapping[str, sp.Expr | str],
) -> None:
    """The spec, read by the project's own reader (and through TOML), is what we built."""
    from tvopt_codegen.spec import spec_from_dict  # noqa: PLC0415 - the reader imports much

    read = spec_from_dict(spec, source=SOURCE_SYMPY)
    spec_toml(spec)  # raises if the TOML would not read back as this mapping
    mech = read.mechanics
    assert mech is not None
    pairs: list[tuple[str, sp.Expr, sp.Expr]] = []
    for i, row in enumerate(mass):
        for j, entry in enumerate(row):
            pairs.append((f"mass_matrix[{i}][{j}]", entry, mech.mass_matrix[i][j]))
    for i, entry in enumerate(forces):
        pairs.append((f"forces[{i}]", entry, mech.forces[i]))
    for i, gains in enumerate(gain):
        for j, entry in enumerate(gains):
            pairs.append((f"input_matrix[{i}][{j}]", entry, mech.input_matrix[i][j]))
    for where, ours, theirs in pairs:
        if not _same(ours, theirs):
            raise _fail(
                f"system.mechanics.{where}",
                f"{clip(sp.sstr(ours))} would read back as {clip(sp.sstr(theirs))}",
            )
    for (key, value), read_expr in zip(outputs.items(), read.output_exprs, strict=True):
        if not isinstance(value, str) and not _same(value, read_expr):
            raise _fail(
                f"system.outputs.{key}",
                f"{clip(sp.sstr(value))} would read back as {clip(sp.sstr(read_expr))}",
            )


# ---------------------------------------------------------------------------------------
# TOML


def _toml_fail(field: str, problem: str) -> SpecError:
    return SpecError(SOURCE_TOML, one_line(field) or "(spec)", one_line(problem))


def _plain_data(value: object, field: str, depth: int) -> object:
    """``value`` as TOML's data: Python scalars, lists and string-keyed dicts.

    NumPy scalars and arrays become Python values and lists, SymPy integers and floats
    Python numbers; anything TOML cannot hold (None, NaN, a set, a SymPy expression) is
    one SpecError naming the key.
    """
    if depth > MAX_TOML_DEPTH:
        raise _toml_fail(field, f"nested deeper than {MAX_TOML_DEPTH} tables and lists")
    if value is None:
        raise _toml_fail(field, "None has no TOML spelling (leave the key out)")
    if isinstance(value, bool | np.bool_):
        return bool(value)
    if isinstance(value, str):
        try:
            value.encode("utf-8")
        except UnicodeEncodeError:
            raise _toml_fail(field, "the string holds a lone surrogate, not text") from None
        return str(value)
    if isinstance(value, int | np.integer) or (isinstance(value, sp.Integer)):
        number = int(value)
        if not -(2**63) <= number < 2**63:
            raise _toml_fail(field, f"the integer {number} is beyond TOML's 64 bits")
        return number
    if isinstance(value, float | np.floating) or isinstance(value, sp.Float):
        result = float(value)
        if not math.isfinite(result):
            raise _toml_fail(field, f"{result} is not a finite number")
        return result
    if isinstance(value, Mapping):
        out: dict[str, object] = {}
        for key, item in value.items():
            if not isinstance(key, str):
                raise _toml_fail(
                    field, f"keys are strings, got the {type(key).__name__} {clip(repr(key))}"
                )
            where = f"{field}.{key}" if field else str(key)
            out[str(_plain_data(key, where, depth + 1))] = _plain_data(item, where, depth + 1)
        return out
    if isinstance(value, np.ndarray):
        value = value.tolist()
    if isinstance(value, list | tuple):
        return [_plain_data(item, f"{field}[{i}]", depth + 1) for i, item in enumerate(value)]
    if isinstance(value, sp.Basic):
        raise _toml_fail(field, f"the sympy expression {clip(sp.sstr(value))}: give its text")
    raise _toml_fail(field, f"no TOML spelling for a {type(value).__name__}")


_ESCAPES = {
    '"': '\\"',
    "\\": "\\\\",
    "\b": "\\b",
    "\t": "\\t",
    "\n": "\\n",
    "\f": "\\f",
    "\r": "\\r",
}


def _string(text: str) -> str:
    """A TOML basic string in ASCII: quotes, backslashes and controls escaped."""
    out = []
    for ch in text:
        code = ord(ch)
        if ch in _ESCAPES:
            out.append(_ESCAPES[ch])
        elif code < 0x20 or 0x7F <= code <= 0xFFFF:
            out.append(f"\\u{code:04x}")
        elif code > 0xFFFF:
            out.append(f"\\U{code:08x}")
        else:
            out.append(ch)
    return '"' + "".join(out) + '"'


def _value(value: object) -> str:
    """One TOML value: a string, a number, a list or an inline table."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return _string(value)
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        return repr(value)
    if isinstance(value, Mapping):
        return "{ " + ", ".join(f"{_key(k)} = {_value(v)}" for k, v in value.items()) + " }"
    assert isinstance(value, list)
    return "[" + ", ".join(_value(v) for v in value) + "]"


_BARE_KEY = re.compile(r"[A-Za-z0-9_]+\Z")


def _key(key: str) -> str:
    return key if _BARE_KEY.match(key) else _string(key)


def spec_toml(spec: Mapping[str, Any]) -> str:
    """A spec mapping (as :func:`spec_from_sympy` returns) as TOML text.

    Keys come in the mapping's order, plain values before tables, each table under its
    dotted header; a matrix is written one row per line. NumPy scalars and arrays are
    written as the Python numbers and lists they hold. The text, read back by
    :func:`tvopt_codegen.load_spec`, is the same spec (checked before returning).

    Raises
    ------
    SpecError
        When a value has no TOML spelling (None, NaN or infinity, a set, a SymPy
        expression, a lone surrogate), a key is not a string, an integer exceeds 64
        bits, or the mapping nests deeper than :data:`MAX_TOML_DEPTH`; one line naming
        the key.
    """
    if not isinstance(spec, Mapping):
        raise _toml_fail("", f"expected a mapping, got {type(spec).__name__}")
    data = _plain_data(spec, "", 0)
    assert isinstance(data, dict)
    lines: list[str] = []

    def table(path: str, body: Mapping[str, Any]) -> None:
        plain = [
            (k, v) for k, v in body.items() if not isinstance(v, Mapping) or path == "simulation"
        ]
        nested = [
            (k, v) for k, v in body.items() if isinstance(v, Mapping) and path != "simulation"
        ]
        if path:
            lines.extend(["", f"[{path}]"])
        for key, value in plain:
            one_line = f"{_key(key)} = {_value(value)}"
            if isinstance(value, list) and value and isinstance(value[0], list | str):
                if isinstance(value[0], str) and len(one_line) <= 100:
                    lines.append(one_line)
                    continue
                # A matrix one row per line, a long list one entry per line.
                rows = ",\n".join(f"    {_value(row)}" for row in value)
                lines.append(f"{_key(key)} = [\n{rows},\n]")
            else:
                lines.append(one_line)
        for key, value in nested:
            table(f"{path}.{_key(key)}" if path else _key(key), value)

    table("", data)
    text = "\n".join(lines).lstrip("\n") + "\n"
    try:
        same = tomllib.loads(text) == data
    except tomllib.TOMLDecodeError as exc:
        raise _toml_fail("", f"the TOML written does not parse ({exc})") from None
    if not same:
        raise _toml_fail("", "the TOML written does not read back as the mapping")
    return text
