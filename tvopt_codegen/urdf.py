"""A spec from a robot's URDF file: a fixed-base serial chain in mass-matrix form.

:func:`spec_from_urdf` reads the file with ``yourdfpy`` (the ``urdf`` extra; the text
is XML, parsed strictly, and never executed), checks that it describes what the method
can control, and builds ``M(q)`` and the bias forces symbolically by the recursive
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
number the inputs).
"""

from __future__ import annotations

import io
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import sympy as sp

from tvopt_codegen.errors import SpecError
from tvopt_codegen.names import name_problem
from tvopt_codegen.spec.files import MAX_SPEC_BYTES
from tvopt_codegen.toml_shape import MAX_NESTING

__all__ = ["spec_from_urdf"]

#: The joint types of a fixed-base serial chain the import accepts.
_MOVABLE = ("revolute", "continuous", "prismatic")

#: Numbers this close to 0 or +-1 in a joint's placement are those (an rpy of pi/2 gives
#: cos = 6e-17): the expressions stay short and exact where the file meant exactness.
_SNAP = 1e-12

#: Most XML elements a URDF file may hold (the spec's own limits are on bytes and depth).
MAX_ELEMENTS = 200_000


@dataclass(frozen=True)
class _Body:
    """One link of the chain and the joint that carries it (fixed joints included)."""

    link: str
    joint: str
    kind: str  # revolute, prismatic or fixed (continuous is revolute)
    parent: int  # index of the parent body, -1 for the base
    rotation: sp.Matrix  # the joint frame in the parent's, at q = 0
    offset: sp.Matrix  # the joint frame's origin in the parent's
    axis: sp.Matrix  # unit axis in the joint frame
    mass: sp.Expr
    com: sp.Matrix  # centre of mass in the link frame
    inertia: sp.Matrix  # about the centre of mass, in the link frame
    coordinate: int  # index among the movable joints, -1 for fixed


def _fail(source: str, where: str, problem: str) -> SpecError:
    return SpecError(source, where, problem)


def _snap(value: float) -> sp.Expr:
    """A float of the file as an exact 0 or +-1 where it is one to rounding, else a Float."""
    if abs(value) < _SNAP:
        return sp.Integer(0)
    if abs(abs(value) - 1.0) < _SNAP:
        return sp.Integer(1 if value > 0 else -1)
    return sp.Float(repr(float(value)), 17)


def _matrix(values: np.ndarray) -> sp.Matrix:
    rows = values.shape[0]
    cols = values.shape[1] if values.ndim > 1 else 1
    return sp.Matrix(rows, cols, [_snap(float(v)) for v in values.ravel()])


def _identifier(name: str, prefix: str) -> str:
    """A spec name from a URDF name: other characters as ``_``, ``prefix`` if need be."""
    text = re.sub(r"[^A-Za-z0-9_]", "_", name).strip("_") or prefix
    if not text[0].isalpha():
        text = f"{prefix}_{text}"
    return text[:48]


class _Lets:
    """Named intermediate values, the spec's ``definitions``.

    Each non-trivial expression the algorithm forms gets a name, so that every one stays
    a few operations long.
    """

    def __init__(self, taken: set[str]) -> None:
        self.items: list[tuple[str, sp.Expr]] = []
        self.taken = {name.casefold() for name in taken}

    def __call__(self, name: str, expr: sp.Expr) -> sp.Expr:
        expr = sp.sympify(expr)
        if expr.is_Atom or (
            expr.is_Mul and len(expr.args) == 2 and expr.args[0].is_Number and expr.args[1].is_Atom
        ):
            return expr
        if name.casefold() in self.taken:
            raise ValueError(f"the intermediate name {name!r} is taken by a joint or link name")
        self.taken.add(name.casefold())
        self.items.append((name, expr))
        return sp.Symbol(name, real=True)

    def vector(self, name: str, vector: sp.Matrix) -> sp.Matrix:
        return sp.Matrix([self(f"{name}{axis}", e) for axis, e in zip("xyz", vector, strict=True)])


def _rodrigues(axis: sp.Matrix, c: sp.Expr, s: sp.Expr) -> sp.Matrix:
    """The rotation about the unit ``axis`` by the angle whose cosine and sine are given."""
    x, y, z = axis
    cross = sp.Matrix([[0, -z, y], [z, 0, -x], [-y, x, 0]])
    outer = axis * axis.T
    return c * sp.eye(3) + s * cross + (1 - c) * outer


def _load(path: Path) -> Any:
    """The URDF model through yourdfpy, after the text's own limits are checked."""
    source = str(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise _fail(source, "(file)", f"cannot read: {exc.strerror or exc}") from None
    if len(data) > MAX_SPEC_BYTES:
        raise _fail(source, "(file)", f"larger than {MAX_SPEC_BYTES} bytes")
    text = data.decode("utf-8", "replace")
    if re.search(r"<!(DOCTYPE|ENTITY)", text, re.IGNORECASE):
        # Entities expand (a billion laughs) or reach files (XXE): a robot needs neither.
        raise _fail(source, "(file)", "holds a DOCTYPE or ENTITY declaration, which is refused")
    if text.count("<") > MAX_ELEMENTS:
        raise _fail(source, "(file)", f"more than {MAX_ELEMENTS} XML elements")
    try:
        import yourdfpy  # noqa: PLC0415 - the urdf extra, on use
        from lxml import etree  # noqa: PLC0415 - yourdfpy's own XML library
    except ImportError:
        raise _fail(
            source, "(file)", "reading URDF needs yourdfpy: pip install 'tvopt-codegen[urdf]'"
        ) from None
    # Well-formedness first, strictly: yourdfpy falls back to a recovering parser, which
    # would read a broken file as some other robot.
    parser = etree.XMLParser(resolve_entities=False, no_network=True, huge_tree=False)
    try:
        root = etree.fromstring(data, parser=parser)
    except etree.XMLSyntaxError as exc:
        raise _fail(source, "(file)", f"not well-formed XML: {exc}") from None
    if root.tag != "robot":
        raise _fail(source, "(file)", f"the root element is <{root.tag}>, not <robot>")
    # The spec's nesting limit: a robot is a few levels deep.
    deepest = max((sum(1 for _ in node.iterancestors()) for node in root.iter()), default=0)
    if deepest > MAX_NESTING:
        raise _fail(source, "(file)", f"elements nest {deepest} deep (at most {MAX_NESTING})")
    try:
        # No meshes are read and no scene graph is built: the dynamics need neither.
        model = yourdfpy.URDF.load(
            io.BytesIO(data),
            build_scene_graph=False,
            build_collision_scene_graph=False,
            load_meshes=False,
            load_collision_meshes=False,
        )
    except (ValueError, TypeError, AttributeError, KeyError, IndexError) as exc:
        raise _fail(source, "(file)", f"not a URDF robot: {exc}") from None
    return model.robot


def _chain(robot: Any, source: str) -> tuple[list[_Body], list[str]]:
    """The bodies in parent-first order, and the movable joints' names in chain order."""
    links = {link.name: link for link in robot.links}
    children: dict[str, list[Any]] = {}
    parents: dict[str, Any] = {}
    for joint in robot.joints:
        where = f"joint {joint.name!r}"
        if joint.type in ("floating", "planar"):
            raise _fail(
                source,
                where,
                f"a {joint.type} joint (a floating base) is not supported: fixed-base serial "
                "chains only",
            )
        if joint.type not in (*_MOVABLE, "fixed"):
            raise _fail(source, where, f"unknown joint type {joint.type!r}")
        if joint.mimic is not None:
            raise _fail(source, where, "mimic joints are not supported (each joint is driven)")
        limit = joint.limit
        if (
            joint.type == "continuous"
            and limit is not None
            and (limit.lower is not None or limit.upper is not None)
        ):
            raise _fail(
                source, where, "a continuous joint has no position limits; make it revolute"
            )
        for end in (joint.parent, joint.child):
            if end not in links:
                raise _fail(source, where, f"link {end!r} is not declared")
        if joint.child in parents:
            raise _fail(
                source,
                where,
                f"link {joint.child!r} has a second parent joint: a closed chain is not supported",
            )
        parents[joint.child] = joint
        children.setdefault(joint.parent, []).append(joint)
    roots = [name for name in links if name not in parents]
    if len(roots) != 1:
        found = ", ".join(roots[:4]) or "none: the joints form a loop"
        raise _fail(source, "(robot)", f"expected one root link, found {len(roots)} ({found})")
    bodies: list[_Body] = []
    movable: list[str] = []
    order: list[tuple[str, int]] = [(roots[0], -1)]
    seen = {roots[0]}
    while order:
        link_name, parent = order.pop(0)
        below = children.get(link_name, [])
        if sum(1 for j in below if _moves(j, children)) > 1:
            raise _fail(
                source, f"link {link_name!r}", "has more than one moving branch: not a serial chain"
            )
        for joint in below:
            if joint.child in seen:
                raise _fail(source, f"joint {joint.name!r}", "closes a loop")
            seen.add(joint.child)
            coordinate = len(movable) if joint.type in _MOVABLE else -1
            bodies.append(_body(joint, links[joint.child], parent, coordinate, source))
            if joint.type in _MOVABLE:
                movable.append(joint.name)
            order.append((joint.child, len(bodies) - 1))
    if len(seen) != len(links):
        raise _fail(source, "(robot)", "some links are not reached from the root: a loop")
    if not movable:
        raise _fail(source, "(robot)", "no revolute, continuous or prismatic joint to drive")
    return bodies, movable


def _moves(joint: Any, children: dict[str, list[Any]]) -> bool:
    """Whether a joint or any joint below it moves."""
    if joint.type in _MOVABLE:
        return True
    return any(_moves(j, children) for j in children.get(joint.child, []))


def _body(joint: Any, link: Any, parent: int, coordinate: int, source: str) -> _Body:
    """One body: its joint's placement and axis, and its link's inertial parameters."""
    origin = np.asarray(joint.origin if joint.origin is not None else np.eye(4), dtype=float)
    axis = np.asarray(joint.axis if joint.axis is not None else (1.0, 0.0, 0.0), dtype=float)
    if not np.all(np.isfinite(origin)):
        raise _fail(source, f"joint {joint.name!r}", "its origin is not finite")
    if joint.type in _MOVABLE:
        norm = float(np.linalg.norm(axis))
        if not np.isfinite(norm) or norm == 0.0:
            raise _fail(source, f"joint {joint.name!r}", "its axis is zero or not finite")
        axis = axis / norm
    name = _identifier(link.name, "link")
    inertial = link.inertial
    mass: sp.Expr = sp.Integer(0)
    com = sp.zeros(3, 1)
    inertia = sp.zeros(3, 3)
    if inertial is not None and inertial.mass is not None and float(inertial.mass) > 0:
        placement = np.asarray(
            inertial.origin if inertial.origin is not None else np.eye(4), dtype=float
        )
        mass = sp.Symbol(f"m_{name}", real=True)
        com = _matrix(placement[:3, 3])
        entries = {
            key: sp.Symbol(f"I{key}_{name}", real=True)
            for key in ("xx", "yy", "zz", "xy", "xz", "yz")
        }
        own = sp.Matrix(
            [
                [entries["xx"], entries["xy"], entries["xz"]],
                [entries["xy"], entries["yy"], entries["yz"]],
                [entries["xz"], entries["yz"], entries["zz"]],
            ]
        )
        turn = _matrix(placement[:3, :3])
        inertia = own if turn == sp.eye(3) else turn * own * turn.T
    return _Body(
        link=link.name,
        joint=joint.name,
        kind={"continuous": "revolute"}.get(joint.type, joint.type),
        parent=parent,
        rotation=_matrix(origin[:3, :3]),
        offset=_matrix(origin[:3, 3]),
        axis=_matrix(axis),
        mass=mass,
        com=com,
        inertia=inertia,
        coordinate=coordinate,
    )


def _inertial_values(robot: Any) -> dict[str, float]:
    """The file's mass and inertia entries, by parameter name."""
    values: dict[str, float] = {}
    where = {"xx": (0, 0), "yy": (1, 1), "zz": (2, 2), "xy": (0, 1), "xz": (0, 2), "yz": (1, 2)}
    for link in robot.links:
        inertial = link.inertial
        if inertial is None or inertial.mass is None or float(inertial.mass) <= 0:
            continue
        name = _identifier(link.name, "link")
        values[f"m_{name}"] = float(inertial.mass)
        matrix = np.asarray(inertial.inertia, dtype=float)
        for key, (i, j) in where.items():
            values[f"I{key}_{name}"] = float(matrix[i, j])
    return values


def _placements(
    bodies: Sequence[_Body],
    q: Sequence[sp.Expr],
    trig: Sequence[tuple[sp.Expr, sp.Expr]] | None = None,
) -> list[tuple[sp.Matrix, sp.Matrix]]:
    """Each body's frame in its parent's: the rotation ``E`` and the origin ``p``.

    ``trig`` gives each coordinate's cosine and sine (names of definitions); by default
    ``cos(q)`` and ``sin(q)`` themselves.
    """
    out = []
    for body in bodies:
        if body.kind == "revolute":
            i = body.coordinate
            c, s = trig[i] if trig is not None else (sp.cos(q[i]), sp.sin(q[i]))
            rotation = body.rotation * _rodrigues(body.axis, c, s)
            offset = body.offset
        elif body.kind == "prismatic":
            rotation = body.rotation
            offset = body.offset + body.rotation * body.axis * q[body.coordinate]
        else:
            rotation, offset = body.rotation, body.offset
        out.append((rotation, offset))
    return out


def _newton_euler(
    bodies: Sequence[_Body],
    placements: Sequence[tuple[sp.Matrix, sp.Matrix]],
    dq: Sequence[sp.Expr],
    ddq: Sequence[sp.Expr],
    gravity: sp.Matrix,
    let: _Lets,
    tag: str,
) -> list[sp.Expr]:
    """The joint forces of the recursive Newton-Euler algorithm, in body frames.

    Every vector it forms is named (``let``; ``tag`` ends each name): angular velocity
    ``om``, angular and linear acceleration ``al`` and ``ac``, and the force and torque
    ``fo`` and ``to`` that each body passes to its parent.
    """
    zero = sp.zeros(3, 1)
    omega: list[sp.Matrix] = []
    alpha: list[sp.Matrix] = []
    accel: list[sp.Matrix] = []
    for number, (body, (E, p)) in enumerate(zip(bodies, placements, strict=True), start=1):
        if body.parent < 0:
            w0, a0, v0 = zero, zero, -gravity
        else:
            w0, a0, v0 = omega[body.parent], alpha[body.parent], accel[body.parent]
        carried = E.T * w0
        linear = E.T * (v0 + a0.cross(p) + w0.cross(w0.cross(p)))
        angular = E.T * a0
        if body.kind == "revolute":
            spin = body.axis * dq[body.coordinate]
            w = carried + spin
            angular = angular + body.axis * ddq[body.coordinate] + carried.cross(spin)
        else:
            w = carried
            if body.kind == "prismatic":
                slide = body.axis * dq[body.coordinate]
                linear = linear + 2 * carried.cross(slide) + body.axis * ddq[body.coordinate]
        # The velocities are those of the bias pass alone (the mass matrix's have none).
        omega.append(let.vector(f"om{number}", w) if any(e != 0 for e in w) else w)
        alpha.append(let.vector(f"al{number}{tag}", angular))
        accel.append(let.vector(f"ac{number}{tag}", linear))
    force: list[sp.Matrix] = []
    torque: list[sp.Matrix] = []
    for body, w, a, v in zip(bodies, omega, alpha, accel, strict=True):
        centre = v + a.cross(body.com) + w.cross(w.cross(body.com))
        f = body.mass * centre
        force.append(f)
        torque.append(body.inertia * a + w.cross(body.inertia * w) + body.com.cross(f))
    for index in reversed(range(len(bodies))):
        force[index] = let.vector(f"fo{index + 1}{tag}", force[index])
        torque[index] = let.vector(f"to{index + 1}{tag}", torque[index])
        parent = bodies[index].parent
        if parent >= 0:
            E, p = placements[index]
            moved = E * force[index]
            force[parent] = force[parent] + moved
            torque[parent] = torque[parent] + E * torque[index] + p.cross(moved)
    out: list[sp.Expr] = [sp.Integer(0)] * len(dq)
    for body, f, n in zip(bodies, force, torque, strict=True):
        if body.kind == "revolute":
            out[body.coordinate] = (body.axis.T * n)[0]
        elif body.kind == "prismatic":
            out[body.coordinate] = (body.axis.T * f)[0]
    return out


def _position(
    bodies: Sequence[_Body], placements: Sequence[tuple[sp.Matrix, sp.Matrix]], link: str
) -> sp.Matrix:
    """The origin of ``link``'s frame in the base frame."""
    index = next(i for i, body in enumerate(bodies) if body.link == link)
    position = sp.zeros(3, 1)
    while index >= 0:
        E, p = placements[index]
        position = E * position + p
        index = bodies[index].parent
    return position


def _text(expr: sp.Expr) -> str:
    """An expression as spec text."""
    return str(sp.sstr(expr))


def spec_from_urdf(
    path: str | Path,
    *,
    tip: str | None = None,
    gravity: Sequence[float] = (0.0, 0.0, -9.81),
    name: str | None = None,
    initial: Mapping[str, float] | None = None,
) -> dict[str, Any]:
    """The spec of a URDF robot in mass-matrix form (see the module docstring).

    Parameters
    ----------
    path : str or pathlib.Path
        The URDF file.
    tip : str, optional
        A link whose frame origin's position (``px, py, pz``) the objective tracks.
    gravity : sequence of 3 floats
        The gravity vector in the base frame.
    name : str, optional
        The spec's name (default: the robot's, made an identifier).
    initial : mapping of str to float, optional
        Initial joint positions by coordinate name (default: the middle of each joint's
        limits, else 0); the targets move about the pose they give.

    Returns
    -------
    dict
        The spec as a mapping (:func:`tvopt_codegen.mechanics.spec_toml` writes it).

    Raises
    ------
    SpecError
        A malformed file, a floating base, a closed chain, a mimic joint, a continuous
        joint with limits, a branching chain, an unknown ``tip``: one line, naming the
        file and the element.
    """
    path = Path(path)
    source = str(path)
    robot = _load(path)
    bodies, movable = _chain(robot, source)
    joints = {j.name: j for j in robot.joints}
    names = [_identifier(j, "joint") for j in movable]
    if len({n.casefold() for n in names}) != len(names):
        raise _fail(source, "(joints)", f"joint names collide once made identifiers: {names}")
    for joint, coordinate in zip(movable, names, strict=True):
        for candidate in (coordinate, f"d{coordinate}", f"tau_{coordinate}"):
            problem = name_problem(candidate)
            if problem:
                raise _fail(source, f"joint {joint!r}", problem)
    gravity = tuple(float(v) for v in gravity)
    if len(gravity) != 3 or not all(np.isfinite(gravity)):
        raise _fail(source, "--gravity", "expected three finite numbers")
    n = len(names)
    q = [sp.Symbol(c, real=True) for c in names]
    dq = [sp.Symbol(f"d{c}", real=True) for c in names]
    values = _inertial_values(robot)
    let = _Lets({*names, *(f"d{c}" for c in names), *(f"tau_{c}" for c in names), *values})
    try:
        trig = [
            (let(f"cos_{c}", sp.cos(qc)), let(f"sin_{c}", sp.sin(qc)))
            for c, qc in zip(names, q, strict=True)
        ]
        placements = _placements(bodies, q, trig)
        g = sp.Matrix([_snap(v) for v in gravity])
        bias = _newton_euler(bodies, placements, dq, [sp.Integer(0)] * n, g, let, "")
        columns = [
            _newton_euler(
                bodies,
                placements,
                [sp.Integer(0)] * n,
                [sp.Integer(1 if i == j else 0) for i in range(n)],
                sp.zeros(3, 1),
                let,
                f"_m{j + 1}",
            )
            for j in range(n)
        ]
    except ValueError as exc:
        raise _fail(source, "(names)", str(exc)) from None
    # The lower triangle, mirrored: M is symmetric by construction, and one expression per
    # pair keeps it symmetric in the text as well.
    mass = [[columns[min(i, j)][max(i, j)] for j in range(n)] for i in range(n)]
    start: dict[str, float] = {}
    for coordinate, joint in zip(names, movable, strict=True):
        limit = joints[joint].limit
        low = getattr(limit, "lower", None)
        high = getattr(limit, "upper", None)
        middle = 0.5 * (low + high) if low is not None and high is not None else 0.0
        start[coordinate] = round(float(middle), 6)
    for key, value in (initial or {}).items():
        if key not in start:
            raise _fail(source, "--initial", f"{key!r} is not a joint (joints: {', '.join(names)})")
        if not np.isfinite(value):
            raise _fail(source, "--initial", f"{key} = {value} is not finite")
        start[key] = float(value)
    outputs: dict[str, str] = {}
    signals: dict[str, str] = {}
    terms: list[str] = []
    tracked = names
    if tip is not None:
        if tip not in {body.link for body in bodies}:
            raise _fail(source, "--tip", f"no link {tip!r} below the base")
        if n < 3:
            raise _fail(source, "--tip", f"the chain has {n} joints; a tip position needs 3")
        position = _position(bodies, _placements(bodies, q), tip)
        point = dict(zip(q, start.values(), strict=True))
        motions = ("0.1*cos(0.5*t)", "0.1*sin(0.5*t)", "")
        for axis, expr, motion in zip("xyz", position, motions, strict=True):
            centre = round(float(expr.xreplace(point)), 6)
            outputs[f"p{axis}"] = _text(expr)
            signals[f"o{axis}"] = f"{centre!r} + {motion}" if motion else repr(centre)
            terms.append(f"(p{axis} - o{axis})**2")
        tracked = names[3:]
    for coordinate in tracked:
        outputs[f"y_{coordinate}"] = coordinate
        signals[f"r_{coordinate}"] = f"{start[coordinate]!r} + 0.2*sin(0.5*t)"
        terms.append(f"(y_{coordinate} - r_{coordinate})**2")
    spec_name = name or _identifier(robot.name or path.stem, "robot").lower()
    description = (
        f"Imported from {path.name} by tvopt-codegen import-urdf: {n} joints "
        f"({', '.join(movable)}); M(q) and the Coriolis, centrifugal and gravity forces "
        f"by the recursive Newton-Euler algorithm (gravity {list(gravity)}), its vectors "
        "as definitions; the links' masses and inertias as parameters. The objective is "
        "a quadratic tracking objective to edit."
    )
    spec: dict[str, Any] = {"name": spec_name, "description": description}
    spec["system"] = {
        "coordinates": names,
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
    spec["error_dynamics"] = {"poles": [-2.0, -3.0]}
    spec["simulation"] = {
        "t_final": 10.0,
        "initial_state": {**start, **{f"d{c}": 0.0 for c in names}},
    }
    return spec
