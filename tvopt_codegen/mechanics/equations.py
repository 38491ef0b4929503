"""Reading SymPy mechanics' equations of motion into ``M``, ``F`` and ``B``.

A ``KanesMethod``, a ``LagrangesMethod`` or a ``System`` after ``form_eoms()`` gives
the mass matrix and the forcing in dynamic symbols. Here the coordinates and their
rates become the states (Kane's speeds reordered to the coordinates' order), the other
dynamic symbols of the forcing the inputs, and every expression is rewritten in real
symbols of those names; the forcing is then split as ``F + B u``. Whatever the spec
cannot say is one :class:`~tvopt_codegen.errors.SpecError` naming the field.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import sympy as sp

from tvopt_codegen.errors import clip
from tvopt_codegen.mechanics.language import _fail, _name, _sayable, _symbol_name
from tvopt_codegen.spec.implicit import affine_split
from tvopt_codegen.spec.names import name_problem
from tvopt_codegen.spec.parse import MAX_DEPTH


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


def _formed_equations(
    eoms: Any,
) -> tuple[sp.Matrix, sp.Matrix, list[sp.Expr], dict[sp.Expr, sp.Expr]]:
    """:func:`_equations`, with what it refuses as one SpecError naming ``eoms``.

    Parameters
    ----------
    eoms : KanesMethod, LagrangesMethod or System
        The equations of motion, formed.

    Returns
    -------
    mass, forcing : sympy.Matrix
        ``M`` and the forcing, rows (and ``M``'s columns) in the coordinates' order.
    q : list of sympy.Expr
        The coordinates, dynamic symbols.
    rates : dict of sympy.Expr to sympy.Expr
        Each ``q_i'`` to its rate: Kane's speed, or ``q_i'`` itself.

    Raises
    ------
    SpecError
        When ``eoms`` is of another kind or not formed, a speed is not a coordinate's
        derivative, or an expression nests too deep for Python's recursion.
    """
    try:
        return _equations(eoms)
    except (TypeError, ValueError) as exc:
        raise _fail("eoms", str(exc)) from None
    except RecursionError:
        raise _fail("eoms", f"an expression nests deeper than {MAX_DEPTH} operations") from None


@dataclass
class _Symbols:
    """The spec's names of the model's dynamic symbols, and how expressions become plain.

    Attributes
    ----------
    coordinates, rates, inputs : list of str
        The names of the coordinates, of their rates and of the inputs, in the spec's
        order.
    plain : dict of sympy.Expr to sympy.Symbol
        Each coordinate, rate (as ``q'`` and as Kane's speed) and input, as the real
        symbol of its name.
    states : dict of str to str
        Each of those names, casefolded, to what it names (``"coordinate q1"``).
    time : sympy.Symbol
        SymPy mechanics' time ``t``.
    """

    coordinates: list[str]
    rates: list[str]
    inputs: list[str]
    plain: dict[sp.Expr, sp.Expr]
    states: dict[str, str]
    time: sp.Symbol

    def to_plain(self, expr: object, field: str) -> sp.Expr:
        """``expr`` in real symbols, as the spec language can say it.

        Parameters
        ----------
        expr : object
            A sympy expression in the dynamic symbols, or a value sympy reads.
        field : str
            The spec's field that ``expr`` becomes, named by any error.

        Returns
        -------
        sympy.Expr
            The coordinates, rates and inputs as real symbols of their names, and every
            other symbol a parameter: a real symbol of its own name.

        Raises
        ------
        SpecError
            When the expression is not sayable, or one of its symbols has a name the
            reader refuses or the name (ignoring case) of a state or an input.
        """
        plain = self.plain
        value = _sayable(expr, field) if not isinstance(expr, sp.Basic) else sp.sympify(expr)
        # Derivatives first: q1(t) inside Derivative(q1(t), t) must not be replaced alone.
        derivs = {k: v for k, v in plain.items() if isinstance(k, sp.Derivative)}
        value = value.xreplace(derivs).xreplace(plain)
        # Every other symbol is a parameter, read back as a real symbol of its name.
        table: dict[sp.Basic, sp.Basic] = {}
        for s in value.free_symbols:
            if s == self.time or s in plain.values():
                continue
            assert isinstance(s, sp.Symbol)
            problem = name_problem(s.name)
            if problem:
                raise _fail(f"parameters.{s.name}", f"a symbol of {field}: {problem}")
            exact = {n.casefold(): n for n in (*self.coordinates, *self.rates, *self.inputs)}
            if not field.startswith("system.mechanics") and exact.get(s.name.casefold()) == s.name:
                # Outputs, signals and f0 may name a state by a plain symbol of its name.
                table[s] = sp.Symbol(s.name, real=True)
                continue
            if s.name.casefold() in self.states:
                raise _fail(
                    f"parameters.{s.name}",
                    f"the symbol {s.name} of {field} has the name of the "
                    f"{self.states[s.name.casefold()]} (names are unique, ignoring case): "
                    "rename one of them",
                )
            table[s] = sp.Symbol(s.name, real=True)
        return _sayable(value.xreplace(table), field)


def _symbols(
    q: list[sp.Expr],
    rates: dict[sp.Expr, sp.Expr],
    mass: sp.Matrix,
    forcing: sp.Matrix,
    inputs: Sequence[sp.Expr | str] | None,
) -> _Symbols:
    """The states and inputs of the equations, named and checked, in the spec's order.

    Parameters
    ----------
    q : list of sympy.Expr
        The coordinates.
    rates : dict of sympy.Expr to sympy.Expr
        Each ``q_i'`` to its rate symbol, as :func:`_equations` gives them.
    mass, forcing : sympy.Matrix
        ``M`` and the forcing: their dynamic symbols that are not states are the inputs.
    inputs : sequence of sympy.Expr or str, optional
        The inputs' order the caller asks for; unless given, sorted by name.

    Returns
    -------
    _Symbols
        The names, and the map of each dynamic symbol to its plain symbol.

    Raises
    ------
    SpecError
        When the reader refuses a name, two names are one ignoring case, the equations
        hold a derivative that is not a rate, or ``inputs`` is not an order of the
        inputs.
    """
    t = sp.physics.mechanics.dynamicsymbols._t
    coordinates, rate_names = _state_names(q, rates)
    plain: dict[sp.Expr, sp.Expr] = {}
    for c, coordinate, rate in zip(q, coordinates, rate_names, strict=True):
        plain[rates[_rate_of(c)]] = sp.Symbol(rate, real=True)
        plain[_rate_of(c)] = sp.Symbol(rate, real=True)
        plain[c] = sp.Symbol(coordinate, real=True)
    known = set(q) | set(rates.values())
    extra, input_names = _found_inputs(mass, forcing, known, plain, t, inputs)
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
    return _Symbols(coordinates, rate_names, input_names, plain, states, t)


def _state_names(q: list[sp.Expr], rates: dict[sp.Expr, sp.Expr]) -> tuple[list[str], list[str]]:
    """The coordinates' names and their rates' names, checked as the reader checks names.

    Parameters
    ----------
    q : list of sympy.Expr
        The coordinates.
    rates : dict of sympy.Expr to sympy.Expr
        Each ``q_i'`` to its rate symbol.

    Returns
    -------
    coordinates, rates : list of str
        Kane's speeds keep their names; a Lagrangian's rates are ``d<coordinate>``.

    Raises
    ------
    SpecError
        When the reader refuses a coordinate's or a rate's name.
    """
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
    return coordinates, rate_names


def _found_inputs(
    mass: sp.Matrix,
    forcing: sp.Matrix,
    known: set[sp.Expr],
    plain: dict[sp.Expr, sp.Expr],
    t: sp.Symbol,
    inputs: Sequence[sp.Expr | str] | None,
) -> tuple[list[sp.Expr], list[str]]:
    """The inputs: the dynamic symbols of the equations that are not states.

    Parameters
    ----------
    mass, forcing : sympy.Matrix
        ``M`` and the forcing.
    known, plain : set and dict of sympy.Expr
        The coordinates and rates, as symbols and as the keys of ``plain``.
    t : sympy.Symbol
        Time: an input is a function of ``t`` alone.
    inputs : sequence of sympy.Expr or str, optional
        The order the caller asks for (:func:`_input_order`).

    Returns
    -------
    symbols : list of sympy.Expr
        The inputs' dynamic symbols, in the spec's order.
    names : list of str
        Their names, in the same order.

    Raises
    ------
    SpecError
        When the equations hold a derivative that is not a rate, the reader refuses an
        input's name, or ``inputs`` is not an order of the inputs.
    """
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
    return _input_order(extra, input_names, inputs)


def _natural(name: str) -> tuple[list[int | str], str]:
    """Sort key that puts ``tau2`` before ``tau10``."""
    parts = re.split(r"(\d+)", name)
    return [int(p) if p.isdigit() else p for p in parts], name


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


@dataclass
class _Plant:
    """``M`` and the forcing in real symbols, the forcing also split as ``F + B u``.

    Attributes
    ----------
    mass : list of list of sympy.Expr
        ``M``, row by row.
    forces : list of sympy.Expr
        The whole forcing, ``F + B u``.
    gain : tuple of tuple of sympy.Expr
        ``B``, row by row.
    rest : tuple of sympy.Expr
        ``F``: the forcing at ``u = 0``.
    """

    mass: list[list[sp.Expr]]
    forces: list[sp.Expr]
    gain: tuple[tuple[sp.Expr, ...], ...]
    rest: tuple[sp.Expr, ...]


def _plant(mass: sp.Matrix, forcing: sp.Matrix, symbols: _Symbols, simplify: bool) -> _Plant:
    """``M``, ``F`` and ``B`` in real symbols, checked as the spec can say them.

    Parameters
    ----------
    mass, forcing : sympy.Matrix
        ``M`` and the forcing in dynamic symbols.
    symbols : _Symbols
        The states' and inputs' names, and the map to plain symbols.
    simplify : bool
        Whether to write each entry after ``trigsimp``.

    Returns
    -------
    _Plant
        ``M``, the forcing, and its split into ``B`` and ``F``.

    Raises
    ------
    SpecError
        When an entry is not sayable, ``M`` depends on an input, the forcing is not
        affine in the inputs, or the equations depend on time.
    """
    n = mass.rows
    M = [
        [symbols.to_plain(mass[i, j], f"system.mechanics.mass_matrix[{i}][{j}]") for j in range(n)]
        for i in range(n)
    ]
    forces = [symbols.to_plain(e, f"system.mechanics.forces[{i}]") for i, e in enumerate(forcing)]
    if simplify:
        M, forces = _simplified(M, forces)
    u = [sp.Symbol(name_, real=True) for name_ in symbols.inputs]
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
    t = symbols.time
    if any(t in e.free_symbols for e in (*(e for row in M for e in row), *rest, *sum(gain, ()))):
        raise _fail(
            "system.mechanics", "the equations depend on time t: the plant must be time-invariant"
        )
    return _Plant(M, forces, gain, rest)


def _simplified(
    mass: list[list[sp.Expr]], forces: list[sp.Expr]
) -> tuple[list[list[sp.Expr]], list[sp.Expr]]:
    """``M`` and the forcing after ``trigsimp``, checked again as the spec can say them.

    Parameters
    ----------
    mass : list of list of sympy.Expr
        ``M``, row by row, in real symbols.
    forces : list of sympy.Expr
        The forcing, in real symbols.

    Returns
    -------
    mass, forces
        Each entry simplified, reciprocal functions written as quotients.

    Raises
    ------
    SpecError
        When a simplified entry is not sayable.
    """
    # trigsimp may write cot or sec, which the spec language says as quotients.
    M = [
        [
            _sayable(sp.factor_terms(sp.trigsimp(e)), f"system.mechanics.mass_matrix[{i}][{j}]")
            for j, e in enumerate(row)
        ]
        for i, row in enumerate(mass)
    ]
    simple = [
        _sayable(sp.factor_terms(sp.trigsimp(e)), f"system.mechanics.forces[{i}]")
        for i, e in enumerate(forces)
    ]
    return M, simple
