"""The spec mapping an import returns, and the checks of what the caller asked for.

The movable joints are the coordinates (``d<joint>`` their rates), with a torque or force
``tau_<joint>`` per joint; every link's mass and inertia is a named parameter (``m_<link>``,
``Ixx_<link>``, ...) that ``--plant-param`` can perturb; the Newton-Euler vectors are the
definitions of ``[system.mechanics]``. No two URDF elements may make one spec name
(:func:`_owners`), and the caller's gravity, start pose and chain size are checked before
any algebra.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import sympy as sp

from tvopt_codegen.errors import BudgetError
from tvopt_codegen.spec.names import name_problem
from tvopt_codegen.urdf.chain import MAX_JOINTS, MAX_LINKS, _rest
from tvopt_codegen.urdf.dynamics import _Lets, _text
from tvopt_codegen.urdf.elements import _fail, _identifier
from tvopt_codegen.urdf.objective import _POLES, _T_FINAL


def _gravity(gravity: Sequence[float], source: str) -> tuple[float, ...]:
    """The gravity vector in the base frame: three finite numbers, else refused."""
    values = tuple(float(v) for v in gravity)
    if len(values) != 3 or not all(np.isfinite(values)):
        raise _fail(source, "--gravity", "expected three finite numbers")
    return values


def _check_size(bodies: int, joints: int, source: str) -> None:
    """Refuses a chain too long for the derivation's budget, before any algebra.

    More than :data:`MAX_LINKS` links (the base and ``bodies``) or :data:`MAX_JOINTS`
    driven ``joints`` is a :class:`~tvopt_codegen.errors.BudgetError`.
    """
    if bodies + 1 > MAX_LINKS:
        raise BudgetError(
            source,
            "chain size",
            f"{bodies + 1} links, more than the {MAX_LINKS} the derivation budget allows",
        )
    if joints > MAX_JOINTS:
        raise BudgetError(
            source,
            "chain size",
            f"{joints} driven joints, more than the {MAX_JOINTS} whose dynamics the derivation "
            "budget allows (give --tip a link nearer the base to hold the rest fixed)",
        )


def _owners(
    source: str,
    movable: Sequence[str],
    names: Sequence[str],
    robot: Any,
    values: Mapping[str, float],
) -> dict[str, str]:
    """Every spec name the import makes, casefolded, with the URDF element it comes from.

    Refused, naming both elements, when two elements make the same name: a joint
    ``m_arm`` and a link ``arm``'s mass, say.
    """
    owners: dict[str, str] = {}

    def claim(spec_name: str, owner: str) -> None:
        key = spec_name.casefold()
        if key in owners and owners[key] != owner:
            raise _fail(
                source,
                owner,
                f"its spec name {spec_name!r} is also made by {owners[key]}: rename one",
            )
        owners[key] = owner

    for joint, coordinate in zip(movable, names, strict=True):
        for candidate in (coordinate, f"d{coordinate}", f"tau_{coordinate}"):
            problem = name_problem(candidate)
            if problem:
                raise _fail(source, f"joint {joint!r}", problem)
            claim(candidate, f"joint {joint!r}")
    links = {_identifier(link.name, "link"): link.name for link in robot.links}
    for parameter in values:
        claim(parameter, f"link {links[parameter.split('_', 1)[1]]!r}")
    return owners


def _start(
    robot: Any,
    movable: Sequence[str],
    names: Sequence[str],
    held: Mapping[str, float],
    initial: Mapping[str, float] | None,
    source: str,
) -> dict[str, float]:
    """The initial joint positions by coordinate name, in chain order.

    Each joint starts at the middle of its limits, else 0, unless ``initial`` names it;
    a held joint, an unknown name or a value that is not finite is refused.
    """
    joints = {j.name: j for j in robot.joints}
    start: dict[str, float] = {
        coordinate: round(_rest(joints[joint]), 6)
        for coordinate, joint in zip(names, movable, strict=True)
    }
    for key, value in (initial or {}).items():
        if key in {_identifier(joint, "joint") for joint in held}:
            raise _fail(source, "--initial", f"{key!r} is held fixed beyond or beside the tip")
        if key not in start:
            raise _fail(source, "--initial", f"{key!r} is not a joint (joints: {', '.join(names)})")
        if not np.isfinite(value):
            raise _fail(source, "--initial", f"{key} = {value} is not finite")
        start[key] = float(value)
    return start


def _description(
    path: Path, movable: Sequence[str], held: Mapping[str, float], gravity: Sequence[float]
) -> str:
    """The spec's description: where it came from and what the import made of it."""
    fixed = f"; held fixed: {', '.join(held)}" if held else ""
    return (
        f"Imported from {path.name} by tvopt-codegen import-urdf: {len(movable)} joints "
        f"({', '.join(movable)}{fixed}); M(q) and the Coriolis, centrifugal and gravity forces "
        f"by the recursive Newton-Euler algorithm (gravity {list(gravity)}), its vectors "
        "as definitions; the links' masses and inertias as parameters. The objective is "
        "a quadratic tracking objective to edit."
    )


def _mapping(
    name: str,
    description: str,
    names: Sequence[str],
    equations: tuple[_Lets, list[list[sp.Expr]], list[sp.Expr]],
    objective: tuple[dict[str, str], dict[str, str], list[str]],
    values: dict[str, float],
    start: Mapping[str, float],
) -> dict[str, Any]:
    """The spec as a mapping, its sections in the order the spec's text gives them.

    ``equations`` are the named vectors, ``M`` and the bias forces (``F`` is their
    negative); ``objective`` the outputs, their targets as signals, and the terms of
    ``f0``; ``values`` the parameters' defaults; ``start`` the initial joint positions.
    """
    let, mass, bias = equations
    outputs, signals, terms = objective
    n = len(names)
    spec: dict[str, Any] = {"name": name, "description": description}
    spec["system"] = {
        "coordinates": list(names),
        "inputs": [f"tau_{c}" for c in names],
        "mechanics": {
            "rates": [f"d{c}" for c in names],
            "definitions": {key: _text(expr) for key, expr in let.items},
            "mass_matrix": [[_text(e) for e in row] for row in mass],
            "forces": [_text(-e) for e in bias],
            "input_matrix": [[1 if i == j else 0 for j in range(n)] for i in range(n)],
        },
        "outputs": outputs,
    }
    spec["parameters"] = values
    spec["signals"] = signals
    spec["objective"] = {"f0": " + ".join(terms)}
    spec["error_dynamics"] = {"poles": list(_POLES)}
    spec["simulation"] = {
        "t_final": _T_FINAL,
        "initial_state": {**start, **{f"d{c}": 0.0 for c in names}},
    }
    return spec
