"""The spec of a robot whose equations of motion SymPy mechanics formed.

:func:`spec_from_sympy` reads the equations (:mod:`.equations`), checks every expression
as the spec language can say it (:mod:`.language`), writes each as text the reader reads
back (:mod:`.printing`), assembles the spec mapping here, and returns it only once the
project's own reader has read it back as the same ``M``, ``F``, ``B`` and outputs
(:mod:`.readback`).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import sympy as sp

from tvopt_codegen.errors import clip
from tvopt_codegen.mechanics.equations import (
    _formed_equations,
    _Plant,
    _plant,
    _Symbols,
    _symbols,
)
from tvopt_codegen.mechanics.language import _check_depths, _fail, _number, _symbol_name
from tvopt_codegen.mechanics.printing import _text
from tvopt_codegen.mechanics.readback import _reads_back
from tvopt_codegen.spec.names import name_problem

#: The poles a spec from :func:`spec_from_sympy` asks for unless told (k = 2).
DEFAULT_POLES = (-2.0, -3.0)


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
    mass, forcing, q, rates = _formed_equations(eoms)
    _check_depths(mass, forcing, outputs, objective, signals)
    symbols = _symbols(q, rates, mass, forcing, inputs)
    plant = _plant(mass, forcing, symbols, simplify)
    h = _outputs(outputs, symbols)
    values = _parameters(parameters, symbols, plant, h)
    spec: dict[str, Any] = {"name": name}
    if description:
        spec["description"] = description
    spec["system"] = _system_table(symbols, plant, h)
    spec["parameters"] = values
    if signals:
        spec["signals"] = _signals(signals, symbols)
    f0 = (
        objective
        if isinstance(objective, str)
        else _text(symbols.to_plain(objective, "objective.f0"), "objective.f0", string=True)
    )
    spec["objective"] = {"f0": f0}
    spec["error_dynamics"] = {"poles": _poles(poles)}
    spec["simulation"] = _simulation(t_final, initial_state, symbols)
    _reads_back(spec, plant.mass, plant.rest, plant.gain, h)
    return spec


def _outputs(outputs: Mapping[str, sp.Expr | str], symbols: _Symbols) -> dict[str, sp.Expr | str]:
    """Each output's name and its expression in real symbols (text is kept as given).

    Parameters
    ----------
    outputs : mapping of str to sympy.Expr or str
        The outputs as given.
    symbols : _Symbols
        The states' and inputs' names, and the map to plain symbols.

    Returns
    -------
    dict of str to sympy.Expr or str
        The outputs, in the order given.

    Raises
    ------
    SpecError
        When ``outputs`` is not a mapping, a name is not a string, or an expression is
        not sayable.
    """
    if not isinstance(outputs, Mapping):
        raise _fail("system.outputs", f"expected a mapping, got {type(outputs).__name__}")
    h: dict[str, sp.Expr | str] = {}
    for key, value in outputs.items():
        field = f"system.outputs.{key}"
        if not isinstance(key, str):
            raise _fail("system.outputs", f"output names are strings, got {type(key).__name__}")
        h[key] = value if isinstance(value, str) else symbols.to_plain(value, field)
    return h


def _parameters(
    parameters: Mapping[sp.Symbol | str, float],
    symbols: _Symbols,
    plant: _Plant,
    outputs: Mapping[str, sp.Expr | str],
) -> dict[str, float]:
    """``[parameters]``: a finite value for every free symbol, none named as a state.

    Parameters
    ----------
    parameters : mapping of sympy.Symbol or str to float
        The values as given.
    symbols : _Symbols
        The states' and inputs' names.
    plant : _Plant
        ``M`` and the forcing, whose free symbols need values.
    outputs : mapping of str to sympy.Expr or str
        The outputs, whose free symbols need values too (text is read later).

    Returns
    -------
    dict of str to float
        Each parameter's name and value, in the order given.

    Raises
    ------
    SpecError
        When a name or value is refused, a parameter has the name of a state or an
        input, or a free symbol has no value.
    """
    values = _parameter_values(parameters)
    states = symbols.states
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
            for e in (*(e for row in plant.mass for e in row), *plant.forces, *outputs.values())
            if not isinstance(e, str)
        )
    )
    missing = sorted(
        s.name for s in used if s.name.casefold() not in states and s.name not in values
    )
    if missing:
        raise _fail(f"parameters.{missing[0]}", f"no value in parameters for {', '.join(missing)}")
    return values


def _system_table(
    symbols: _Symbols, plant: _Plant, outputs: Mapping[str, sp.Expr | str]
) -> dict[str, Any]:
    """``[system]``: the names, ``[system.mechanics]`` as text, and the outputs.

    Parameters
    ----------
    symbols : _Symbols
        The coordinates', rates' and inputs' names.
    plant : _Plant
        ``M``, ``F`` and ``B`` in real symbols.
    outputs : mapping of str to sympy.Expr or str
        The outputs in real symbols, or as text.

    Returns
    -------
    dict
        The table, each expression as spec text (a number the reader's literals take
        stays a number in ``[system.mechanics]``).

    Raises
    ------
    SpecError
        When an expression nests too deep to print.
    """
    M, n = plant.mass, len(plant.mass)
    return {
        "coordinates": symbols.coordinates,
        "inputs": symbols.inputs,
        "mechanics": {
            "rates": symbols.rates,
            "mass_matrix": [
                [_text(M[i][j], f"system.mechanics.mass_matrix[{i}][{j}]") for j in range(n)]
                for i in range(n)
            ],
            "forces": [_text(e, f"system.mechanics.forces[{i}]") for i, e in enumerate(plant.rest)],
            "input_matrix": [
                [_text(e, f"system.mechanics.input_matrix[{i}][{j}]") for j, e in enumerate(row)]
                for i, row in enumerate(plant.gain)
            ],
        },
        "outputs": {
            key: value
            if isinstance(value, str)
            else _text(value, f"system.outputs.{key}", string=True)
            for key, value in outputs.items()
        },
    }


def _signals(signals: Mapping[str, str | sp.Expr], symbols: _Symbols) -> dict[str, Any]:
    """``[signals]``: each signal as text (text given is kept as given).

    Parameters
    ----------
    signals : mapping of str to str or sympy.Expr
        The signals as given.
    symbols : _Symbols
        The states' and inputs' names, and the map to plain symbols.

    Returns
    -------
    dict of str to str
        Each signal's name and text.

    Raises
    ------
    SpecError
        When ``signals`` is not a mapping or an expression is not sayable.
    """
    if not isinstance(signals, Mapping):
        raise _fail("signals", f"expected a mapping, got {type(signals).__name__}")
    return {
        key: value
        if isinstance(value, str)
        else _text(symbols.to_plain(value, f"signals.{key}"), f"signals.{key}", string=True)
        for key, value in signals.items()
    }


def _poles(poles: Sequence[float] | np.ndarray) -> list[float]:
    """``[error_dynamics] poles``: a list of finite numbers; else one SpecError."""
    if isinstance(poles, str | bytes) or not isinstance(poles, Sequence | np.ndarray):
        raise _fail("error_dynamics.poles", f"expected a list of numbers, got {poles!r}")
    return [_number(p, f"error_dynamics.poles[{i}]") for i, p in enumerate(poles)]


def _simulation(
    t_final: float, initial_state: Mapping[str, float] | None, symbols: _Symbols
) -> dict[str, Any]:
    """``[simulation]``: ``t_final`` and, when given, every state's start.

    Parameters
    ----------
    t_final : float
        The simulated time, finite.
    initial_state : mapping of str to float, optional
        Starts by state name (omitted states start at 0).
    symbols : _Symbols
        The states' names.

    Returns
    -------
    dict
        The table.

    Raises
    ------
    SpecError
        When a number is not finite, or a start is given for what is not a state.
    """
    simulation: dict[str, Any] = {"t_final": _number(t_final, "simulation.t_final")}
    if initial_state:
        start = _initial_state(initial_state, [*symbols.coordinates, *symbols.rates])
        simulation["initial_state"] = start
    return simulation


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
