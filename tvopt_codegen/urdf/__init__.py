"""A spec from a robot's URDF file: a fixed-base serial chain in mass-matrix form.

:func:`spec_from_urdf` reads the file with ``yourdfpy`` (the ``urdf`` extra; the text
is XML, parsed strictly, and never executed), checks it where it enters as Pinocchio,
Drake and MuJoCo check theirs (a regular file of at most 1 MB, decoded before a DOCTYPE
is looked for; names unique once made spec names; finite origins, axes and limits;
positive masses; positive-definite inertias obeying the triangle inequality: see
:func:`~tvopt_codegen.urdf.elements._check_elements`), checks that it describes what the
method can control (with a tip, the joints beyond it are held fixed), and builds
``M(q)`` and the bias forces symbolically by the recursive
Newton-Euler algorithm: the bias ``C(q, q') q' + g(q)`` is one pass at zero joint
acceleration, column ``j`` of ``M`` one pass at unit acceleration of joint ``j`` without
velocity and gravity. That is algebra on rotations and cross products, never a
derivative and never an inverse, and it is what Pinocchio computes numerically (the
tests compare the two). Every vector the algorithm forms is a named definition of the
spec (``[system.mechanics] definitions``), so that each stays a few operations long:
substituted into one another they would grow with the cube of the chain's length.

The spec it returns (see :func:`tvopt_codegen.mechanics.spec_toml` for its text) has
the movable joints as coordinates (``d<joint>`` their rates), a torque or force
``tau_<joint>`` per joint, every link's mass and inertia as named parameters
(``m_<link>``, ``Ixx_<link>``, ...) that ``--plant-param`` can perturb, and a quadratic
tracking objective to edit: each joint follows a slow sine about its start, or, with
``tip``, the tip link's position follows a circle in the horizontal plane (the tip's
``px, py, pz`` replace the first three joints as outputs, so that the outputs still
number the inputs). That circle is checked along the run the law makes
(:func:`~tvopt_codegen.urdf.objective._tip_circle`): where it would come near a
singularity of the decoupling matrix or out of reach, three other joints, a smaller
circle or another plane is taken, and the notes say which.

The steps, a module each, in the order an import takes them: ``reading`` (the file's
bytes, text, strict XML and ``yourdfpy`` robot) over ``elements`` (every name and number
checked where the file gives it), ``chain`` (the bodies and the driven and held joints),
``dynamics`` (the Newton-Euler passes and their named vectors), ``objective`` (the
default objective and its tip circle) and ``mapping`` (the spec mapping, and the checks
of the caller's arguments). This module runs them.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import sympy as sp

# ``NAME as NAME`` re-exports the limits from here, where the one-module import had them.
from tvopt_codegen.urdf.chain import MAX_JOINTS as MAX_JOINTS
from tvopt_codegen.urdf.chain import MAX_LINKS as MAX_LINKS
from tvopt_codegen.urdf.chain import _Body, _chain, _inertial_values, _snap
from tvopt_codegen.urdf.dynamics import _Lets, _NameTakenError, _newton_euler, _placements
from tvopt_codegen.urdf.elements import TRIANGLE_TOLERANCE as TRIANGLE_TOLERANCE
from tvopt_codegen.urdf.elements import _fail, _identifier
from tvopt_codegen.urdf.mapping import (
    _check_size,
    _description,
    _gravity,
    _mapping,
    _owners,
    _start,
)
from tvopt_codegen.urdf.objective import SAFE_CONDITION as SAFE_CONDITION
from tvopt_codegen.urdf.objective import _objective
from tvopt_codegen.urdf.reading import MAX_ELEMENTS as MAX_ELEMENTS
from tvopt_codegen.urdf.reading import _load

__all__ = ["spec_from_urdf"]


def spec_from_urdf(
    path: str | Path,
    *,
    tip: str | None = None,
    gravity: Sequence[float] = (0.0, 0.0, -9.81),
    name: str | None = None,
    initial: Mapping[str, float] | None = None,
    notes: list[str] | None = None,
    stage: Callable[[str], None] | None = None,
) -> dict[str, Any]:
    """The spec of a URDF robot in mass-matrix form (see the module docstring).

    Parameters
    ----------
    path : str or pathlib.Path
        The URDF file.
    tip : str, optional
        A link whose frame origin's position (``px, py, pz``) the objective tracks. The
        joints off the way from the base to it (a gripper's) are held fixed.
    gravity : sequence of 3 floats
        The gravity vector in the base frame.
    name : str, optional
        The spec's name (default: the robot's, made an identifier).
    initial : mapping of str to float, optional
        Initial joint positions by coordinate name (default: the middle of each joint's
        limits, else 0); the targets move about the pose they give.
    notes : list of str, optional
        Receives what the import decided for the user to know: the joints held fixed,
        the default objective's circle and its distance from a singularity.
    stage : callable, optional
        Called with the name of each stage as it starts (the command line names the
        stage a time budget stopped).

    Returns
    -------
    dict
        The spec as a mapping (:func:`tvopt_codegen.mechanics.spec_toml` writes it).

    Raises
    ------
    SpecError
        A file that is not a regular file of at most 1 MB, not well-formed, or holds a
        DOCTYPE; a link or joint whose name, mass, inertia, origin, axis or limits are
        refused (see :func:`~tvopt_codegen.urdf.elements._check_elements`); a floating
        base, a closed chain, a driven mimic joint, a branching chain, an unknown
        ``tip``, a held joint in ``initial``: one line, naming the file, the element, the
        field and the value.
    BudgetError
        A chain of more than :data:`MAX_JOINTS` driven joints or :data:`MAX_LINKS`
        links, before any algebra.
    """
    path = Path(path)
    source = str(path)
    notes = [] if notes is None else notes
    report = stage or (lambda _stage: None)
    report("reading the URDF")
    _, robot = _load(path)
    report("checking the chain")
    bodies, movable, held = _chain(robot, source, tip)
    names = [_identifier(j, "joint") for j in movable]
    gravity = _gravity(gravity, source)
    _check_size(len(bodies), len(names), source)
    if held:
        listed = ", ".join(f"{joint} = {value:.6g}" for joint, value in held.items())
        notes.append(f"held fixed beyond or beside the tip {tip!r}: {listed}")
    values = _inertial_values(robot)
    owners = _owners(source, movable, names, robot, values)
    start = _start(robot, movable, names, held, initial, source)
    if tip is not None and len(names) < 3:
        raise _fail(source, "--tip", f"the chain has {len(names)} joints; a tip position needs 3")
    q = [sp.Symbol(c, real=True) for c in names]
    equations = _equations(bodies, q, names, gravity, owners, source, report)
    objective = _objective(bodies, tip, q, names, start, notes, report)
    spec_name = name or _identifier(robot.name or path.stem, "robot").lower()
    description = _description(path, movable, held, gravity)
    return _mapping(spec_name, description, names, equations, objective, values, start)


def _equations(
    bodies: Sequence[_Body],
    q: Sequence[sp.Symbol],
    names: Sequence[str],
    gravity: Sequence[float],
    owners: Mapping[str, str],
    source: str,
    report: Callable[[str], None],
) -> tuple[_Lets, list[list[sp.Expr]], list[sp.Expr]]:
    """The named vectors, ``M(q)`` and the bias forces, by Newton-Euler passes.

    One pass at zero acceleration gives the bias, one per joint at its unit acceleration
    (no velocity, no gravity) a column of ``M``; ``report`` names each as it starts. A
    vector's name that a joint or link already makes is refused, naming that element.

    Here rather than in :mod:`~tvopt_codegen.urdf.dynamics`: it calls the pass by this
    package's name, ``tvopt_codegen.urdf._newton_euler``, which the tests replace to
    interrupt an import inside it.
    """
    n = len(names)
    dq = [sp.Symbol(f"d{c}", real=True) for c in names]
    let = _Lets(owners)
    try:
        trig = [
            (let(f"cos_{c}", sp.cos(qc)), let(f"sin_{c}", sp.sin(qc)))
            for c, qc in zip(names, q, strict=True)
        ]
        placements = _placements(bodies, q, trig)
        g = sp.Matrix([_snap(v) for v in gravity])
        report("Newton-Euler: bias forces")
        bias = _newton_euler(bodies, placements, dq, [sp.Integer(0)] * n, g, let, "")
        columns = []
        for j in range(n):
            report(f"Newton-Euler: column {j + 1} of {n} of M")
            columns.append(
                _newton_euler(
                    bodies,
                    placements,
                    [sp.Integer(0)] * n,
                    [sp.Integer(1 if i == j else 0) for i in range(n)],
                    sp.zeros(3, 1),
                    let,
                    f"_m{j + 1}",
                )
            )
    except _NameTakenError as exc:
        owner, problem = exc.args
        raise _fail(source, owner, problem) from None
    # The lower triangle, mirrored: M is symmetric by construction, and one expression per
    # pair keeps it symmetric in the text as well.
    mass = [[columns[min(i, j)][max(i, j)] for j in range(n)] for i in range(n)]
    return let, mass, bias
