"""Specs from robot models as roboticists write them: SymPy mechanics.

:func:`spec_from_sympy` turns the equations of motion that ``sympy.physics.mechanics``
forms (``KanesMethod``, ``LagrangesMethod``, or a ``System`` after ``form_eoms()``)
into a spec in mass-matrix form (``[system.mechanics]``, docs/spec.md): the
generalized coordinates and their rates become the states, the other dynamic symbols
of the forcing the inputs, and every other free symbol a named parameter that
``--plant-param`` can perturb. :func:`spec_toml` writes that mapping as TOML text.

``M`` is never inverted here or later: the generated code factors it at run time.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from typing import Any

import sympy as sp

from tvopt_codegen.names import name_problem
from tvopt_codegen.spec.implicit import affine_split

__all__ = ["spec_from_sympy", "spec_toml"]

#: The poles a spec from :func:`spec_from_sympy` asks for unless told (k = 2).
DEFAULT_POLES = (-2.0, -3.0)


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


def _name(symbol: sp.Expr, what: str) -> str:
    """A dynamic symbol's or a symbol's name, checked as a spec name."""
    name = (
        symbol.func.__name__ if isinstance(symbol, sp.core.function.AppliedUndef) else str(symbol)
    )
    problem = name_problem(name)
    if problem:
        raise ValueError(f"{what} {symbol}: {problem}")
    return name


def _text(expr: sp.Expr) -> str | int | float:
    """An expression as spec text (sympy's string form, which the spec parser reads).

    An integer or a float stays a number.
    """
    if isinstance(expr, sp.Integer):
        return int(expr)
    if isinstance(expr, sp.Float):
        return float(expr)
    return str(sp.sstr(expr, full_prec=True))


def spec_from_sympy(
    eoms: Any,
    outputs: Mapping[str, sp.Expr | str],
    objective: str,
    parameters: Mapping[sp.Symbol | str, float],
    *,
    name: str = "robot",
    description: str = "",
    signals: Mapping[str, str] | None = None,
    poles: Sequence[float] = DEFAULT_POLES,
    t_final: float = 10.0,
    initial_state: Mapping[str, float] | None = None,
    simplify: bool = False,
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
    objective : str
        ``f0`` in the outputs, the signals, the parameters and ``t``.
    parameters : mapping of sympy.Symbol or str to float
        A value for every free symbol of the equations and the outputs.
    name, description : str
        The spec's (and the generated module's) name, and its description.
    signals : mapping of str to str, optional
        ``[signals]``: named expressions in ``t`` and the parameters.
    poles : sequence of float
        ``[error_dynamics] poles``.
    t_final : float
        ``[simulation] t_final``.
    initial_state : mapping of str to float, optional
        ``[simulation] initial_state`` by state name (omitted states start at 0).
    simplify : bool
        Write each entry of ``M``, ``F`` and ``B`` after ``trigsimp`` (a readable spec;
        its cost grows quickly with the number of links). The derivation does not need
        it: expressions are evaluated as written, with common subexpressions shared.

    Returns
    -------
    dict
        The spec as a mapping: :func:`tvopt_codegen.spec_from_dict` reads it,
        :func:`spec_toml` writes it.

    Raises
    ------
    TypeError
        When ``eoms`` is none of the three.
    ValueError
        When a speed is not a coordinate's derivative, the forcing is not affine in the
        inputs or depends on time, a name is not a valid spec name, or a free symbol has
        no value in ``parameters`` (one line, naming it).
    """
    mass, forcing, q, rates = _equations(eoms)
    t = sp.physics.mechanics.dynamicsymbols._t
    coordinates = [_name(c, "coordinate") for c in q]
    # Kane's speeds keep their names; a Lagrangian's rates are d<coordinate>.
    rate_names = [
        _name(rates[_rate_of(c)], "speed") if rates[_rate_of(c)] != _rate_of(c) else f"d{name_}"
        for c, name_ in zip(q, coordinates, strict=True)
    ]
    plain: dict[sp.Expr, sp.Expr] = {}
    for c, coordinate, rate in zip(q, coordinates, rate_names, strict=True):
        plain[rates[_rate_of(c)]] = sp.Symbol(rate, real=True)
        plain[_rate_of(c)] = sp.Symbol(rate, real=True)
        plain[c] = sp.Symbol(coordinate, real=True)
    known = set(q) | set(rates.values())
    found = sp.physics.mechanics.find_dynamicsymbols(
        forcing
    ) | sp.physics.mechanics.find_dynamicsymbols(mass)
    extra = sorted((s for s in found if s not in known), key=str)
    if any(s.has(sp.Derivative) for s in extra):
        raise ValueError(f"the forcing holds derivatives of inputs: {extra}")
    inputs = [_name(s, "input") for s in extra]
    plain |= {s: sp.Symbol(n, real=True) for s, n in zip(extra, inputs, strict=True)}

    def to_plain(expr: sp.Expr) -> sp.Expr:
        # Derivatives first: q1(t) inside Derivative(q1(t), t) must not be replaced alone.
        derivatives = {k: v for k, v in plain.items() if isinstance(k, sp.Derivative)}
        return sp.sympify(expr).xreplace(derivatives).xreplace(plain)

    M = mass.applyfunc(to_plain)
    forces = [to_plain(e) for e in forcing]
    if simplify:
        M = M.applyfunc(lambda e: sp.factor_terms(sp.trigsimp(e)))
        forces = [sp.factor_terms(sp.trigsimp(e)) for e in forces]
    u = [sp.Symbol(n, real=True) for n in inputs]
    try:
        gain, rest = affine_split(forces, u)
    except ValueError as exc:
        raise ValueError(f"the forcing is not affine in the inputs: {exc}") from None
    if any(t in e.free_symbols for e in (*M, *rest, *(g for row in gain for g in row))):
        raise ValueError("the equations depend on time t: the plant must be time-invariant")
    h = {
        key: to_plain(value) if not isinstance(value, str) else value
        for key, value in outputs.items()
    }
    values = {str(k): float(v) for k, v in parameters.items()}
    used = set().union(
        *(
            sp.sympify(e).free_symbols
            for e in (*M, *forces, *(v for v in h.values() if not isinstance(v, str)))
        )
    )
    states = set(coordinates) | set(rate_names) | set(inputs)
    missing = sorted(s.name for s in used if s.name not in states and s.name not in values)
    if missing:
        raise ValueError(f"no value in parameters for {', '.join(missing)}")
    for key, value in values.items():
        if not math.isfinite(value):
            raise ValueError(f"parameter {key} is not finite ({value})")
    spec: dict[str, Any] = {"name": name}
    if description:
        spec["description"] = description
    spec["system"] = {
        "coordinates": coordinates,
        "inputs": inputs,
        "mechanics": {
            "rates": rate_names,
            "mass_matrix": [[_text(M[i, j]) for j in range(M.cols)] for i in range(M.rows)],
            "forces": [_text(e) for e in rest],
            "input_matrix": [[_text(e) for e in row] for row in gain],
        },
        "outputs": {
            key: value if isinstance(value, str) else _text(value) for key, value in h.items()
        },
    }
    spec["parameters"] = values
    if signals:
        spec["signals"] = dict(signals)
    spec["objective"] = {"f0": objective}
    spec["error_dynamics"] = {"poles": [float(p) for p in poles]}
    spec["simulation"] = {"t_final": float(t_final)}
    if initial_state:
        unknown = sorted(set(initial_state) - set(coordinates) - set(rate_names))
        if unknown:
            raise ValueError(f"initial_state: {', '.join(unknown)} are not states")
        # Every state, as the spec needs once one is given.
        spec["simulation"]["initial_state"] = {
            k: float(initial_state.get(k, 0.0)) for k in (*coordinates, *rate_names)
        }
    return spec


def _value(value: object) -> str:
    """One TOML value: a string, a number, a list or an inline table."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        # A JSON string of ASCII text is a TOML basic string.
        return json.dumps(value, ensure_ascii=True)
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        if not math.isfinite(value):
            raise ValueError(f"{value} has no TOML spelling in a spec")
        return repr(value)
    if isinstance(value, Mapping):
        return "{ " + ", ".join(f"{_key(k)} = {_value(v)}" for k, v in value.items()) + " }"
    if isinstance(value, list | tuple):
        return "[" + ", ".join(_value(v) for v in value) + "]"
    raise TypeError(f"no TOML spelling for {type(value).__name__}")


def _key(key: str) -> str:
    return key if key.replace("_", "").isalnum() and key.isascii() else json.dumps(key)


def spec_toml(spec: Mapping[str, Any]) -> str:
    """A spec mapping (as :func:`spec_from_sympy` returns) as TOML text.

    Keys come in the mapping's order, plain values before tables, each table under its
    dotted header; a matrix is written one row per line. The text, read back by
    :func:`tvopt_codegen.load_spec`, is the same spec.
    """
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
                lines.append(f"{_key(key)} = {_value(value)}")
        for key, value in nested:
            table(f"{path}.{_key(key)}" if path else _key(key), value)

    table("", spec)
    return "\n".join(lines).lstrip("\n") + "\n"
