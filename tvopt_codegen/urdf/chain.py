"""The kinematic chain of a URDF robot: its bodies in parent-first order, the driven joints.

:func:`_chain` checks that the file describes what the method can control (a fixed-base
serial chain; with a tip, the joints beyond it or beside the way to it are held fixed,
mimic joints at their rule) and turns each link and the joint that carries it into a
:class:`_Body`: the joint's placement and axis as exact numbers where the file meant
them, the link's mass and inertia as named parameters.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
import sympy as sp

from tvopt_codegen.urdf.elements import _MOVABLE, _fail, _identifier

#: Numbers this close to 0 or +-1 in a joint's placement are those (an rpy of pi/2 gives
#: cos = 6e-17): the expressions stay short and exact where the file meant exactness.
_SNAP = 1e-12

#: Most joints the import drives. The Newton-Euler definitions grow with the square of
#: the chain and the derivation with more (20 joints: 13 s to import and 11 s to check;
#: 32 joints: 30 s and 90 s, on a loaded core): a longer chain is refused before any
#: algebra, with the exit code of a budget, rather than run for minutes.
MAX_JOINTS = 24

#: Most links the chain may carry, fixed ones included: each is a few vectors in every
#: Newton-Euler pass (a Panda with its hand is 12, a humanoid a hundred or so).
MAX_LINKS = 256


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


def _product(a: sp.Matrix, b: sp.Matrix) -> sp.Matrix:
    """``a * b`` of 3 x 3 matrices as ``sp.Matrix`` forms it, without its bookkeeping.

    Each entry is one ``Add`` of the products of nonzero entries in order, as SymPy's
    sparse product sums them (its domains and its checks for infinities cost more than
    the algebra here), so the expressions are the same.
    """
    entries = []
    for i in range(3):
        for j in range(3):
            terms = [
                a[i, k] * b[k, j]
                for k in range(3)
                if not (_exact_zero(a[i, k]) or _exact_zero(b[k, j]))
            ]
            entries.append(sp.Add(*terms) if terms else sp.S.Zero)
    return sp.Matrix(3, 3, entries)


def _exact_zero(e: sp.Expr) -> bool:
    return bool(e.is_Number and e == 0)


def _chain(
    robot: Any, source: str, tip: str | None
) -> tuple[list[_Body], list[str], dict[str, float]]:
    """The bodies in parent-first order, the driven joints in order, the held ones.

    The driven joints are named in chain order; the held ones map to their position.

    With ``tip``, only the joints between the base and the tip are driven: those beyond
    it or on side branches (a gripper's fingers, mimic joints among them) are held fixed.
    """
    links = {link.name: link for link in robot.links}
    joints = {joint.name: joint for joint in robot.joints}
    parents, children, root = _tree(robot, links, source)
    held = _held(joints, _tip_path(tip, links, parents, root, len(joints), source), source)
    bodies, movable = _walk(root, links, children, held, source)
    _check_moves_mass(bodies, source)
    if not movable:
        raise _fail(source, "(robot)", "no revolute, continuous or prismatic joint to drive")
    return bodies, movable, held


def _tree(
    robot: Any, links: Mapping[str, Any], source: str
) -> tuple[dict[str, Any], dict[str, list[Any]], str]:
    """Each link's parent joint, each link's child joints, and the one root link.

    Refused: a floating base, an unknown joint type, a joint between undeclared links, a
    link with a second parent (a closed chain), and anything but one root.
    """
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
    return parents, children, roots[0]


def _tip_path(
    tip: str | None,
    links: Mapping[str, Any],
    parents: Mapping[str, Any],
    root: str,
    count: int,
    source: str,
) -> set[str] | None:
    """The joints on the way from the base to ``tip`` (``None`` without a tip).

    The walk stops after ``count`` (the number of joints) steps, whatever the links say.
    """
    if tip is None:
        return None
    if tip not in links or tip == root:
        raise _fail(source, "--tip", f"no link {tip!r} below the base")
    path: set[str] = set()
    link = tip
    while link in parents and len(path) <= count:
        path.add(parents[link].name)
        link = parents[link].parent
    return path


def _walk(
    root: str,
    links: Mapping[str, Any],
    children: Mapping[str, list[Any]],
    held: Mapping[str, float],
    source: str,
) -> tuple[list[_Body], list[str]]:
    """The bodies in parent-first order and the driven joints, from the root down.

    Refused: a link with more than one moving branch, a loop, a driven mimic joint, a
    link the root does not reach.
    """
    moves = _moves(root, children, held)
    bodies: list[_Body] = []
    movable: list[str] = []
    order: list[tuple[str, int]] = [(root, -1)]
    seen = {root}
    while order:
        link_name, parent = order.pop(0)
        below = children.get(link_name, [])
        if sum(1 for j in below if moves[j.name]) > 1:
            raise _fail(
                source,
                f"link {link_name!r}",
                "has more than one moving branch: not a serial chain (with --tip, the "
                "joints off the way to the tip are held fixed)",
            )
        for joint in below:
            if joint.child in seen:
                raise _fail(source, f"joint {joint.name!r}", "closes a loop")
            seen.add(joint.child)
            driven = joint.type in _MOVABLE and joint.name not in held
            if driven and joint.mimic is not None:
                raise _fail(
                    source,
                    f"joint {joint.name!r}",
                    f"mimics {joint.mimic.joint!r}: a mimic joint is not driven on its own; "
                    "give a --tip before it to hold it fixed",
                )
            coordinate = len(movable) if driven else -1
            bodies.append(
                _body(joint, links[joint.child], parent, coordinate, source, held.get(joint.name))
            )
            if driven:
                movable.append(joint.name)
            order.append((joint.child, len(bodies) - 1))
    if len(seen) != len(links):
        raise _fail(source, "(robot)", "some links are not reached from the root: a loop")
    return bodies, movable


def _check_moves_mass(bodies: list[_Body], source: str) -> None:
    """Refuses a driven joint that moves no mass.

    Every mass has a positive-definite inertia, so any one will do; without one, the
    joint's row of M is zero, and M singular everywhere.
    """
    carries = [body.mass != 0 for body in bodies]
    for index in reversed(range(len(bodies))):
        if carries[index] and bodies[index].parent >= 0:
            carries[bodies[index].parent] = True
    for body, moved in zip(bodies, carries, strict=True):
        if body.coordinate >= 0 and not moved:
            raise _fail(
                source,
                f"joint {body.joint!r}",
                "moves no mass (every link beyond it has mass 0): M would be singular",
            )


def _rest(joint: Any) -> float:
    """Where a joint starts or is held: the middle of its limits, else 0.

    A continuous joint's limits are ignored, as the URDF format says.
    """
    limit = joint.limit
    low = getattr(limit, "lower", None)
    high = getattr(limit, "upper", None)
    if joint.type == "continuous" or low is None or high is None:
        return 0.0
    return 0.5 * (float(low) + float(high))


def _held(joints: Mapping[str, Any], path: set[str] | None, source: str) -> dict[str, float]:
    """The movable joints off the way to the tip, by name, at their held position.

    A joint is held at the middle of its limits; a mimic joint where its leader puts it
    (``multiplier * leader + offset``), its leader held too.
    """
    if path is None:
        return {}
    off = [j for j in joints.values() if j.type in _MOVABLE and j.name not in path]
    held = {j.name: _rest(j) for j in off if j.mimic is None}
    waiting = [j for j in off if j.mimic is not None]
    while waiting:
        ready = [j for j in waiting if j.mimic.joint in held]
        if not ready:
            joint = waiting[0]
            leader = joint.mimic.joint
            problem = (
                "a joint the tip needs: it cannot be held fixed"
                if leader in path
                else "no held joint (a mimic loop, or undeclared)"
            )
            raise _fail(source, f"joint {joint.name!r}", f"mimics {leader!r}, {problem}")
        for joint in ready:
            multiplier = 1.0 if joint.mimic.multiplier is None else float(joint.mimic.multiplier)
            offset = 0.0 if joint.mimic.offset is None else float(joint.mimic.offset)
            held[joint.name] = multiplier * held[joint.mimic.joint] + offset
            waiting.remove(joint)
    return held


def _moves(
    root: str, children: Mapping[str, list[Any]], held: Mapping[str, float]
) -> dict[str, bool]:
    """Whether each joint, or any joint below it, is driven, by joint name.

    Walked without recursion: a chain of thousands of fixed links is no deeper for it.
    """
    order: list[Any] = []
    stack = list(children.get(root, []))
    seen: set[str] = set()
    while stack:
        joint = stack.pop()
        if joint.name in seen:  # a loop: refused where the chain is walked
            continue
        seen.add(joint.name)
        order.append(joint)
        stack.extend(children.get(joint.child, []))
    moves: dict[str, bool] = {}
    for joint in reversed(order):  # every joint after the joints above it
        below = children.get(joint.child, [])
        moves[joint.name] = (joint.type in _MOVABLE and joint.name not in held) or any(
            moves.get(j.name, False) for j in below
        )
    return moves


def _turn(axis: np.ndarray, angle: float) -> np.ndarray:
    """The rotation by ``angle`` about the unit ``axis``, numerically."""
    x, y, z = axis
    cross = np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])
    c, s = math.cos(angle), math.sin(angle)
    return np.asarray(c * np.eye(3) + s * cross + (1 - c) * np.outer(axis, axis))


def _body(
    joint: Any, link: Any, parent: int, coordinate: int, source: str, held: float | None = None
) -> _Body:
    """One body: its joint's placement and axis, and its link's inertial parameters.

    A joint ``held`` fixed is a fixed joint whose placement includes its motion there.
    """
    origin = np.asarray(joint.origin if joint.origin is not None else np.eye(4), dtype=float)
    axis = np.asarray(joint.axis if joint.axis is not None else (1.0, 0.0, 0.0), dtype=float)
    if not np.all(np.isfinite(origin)):
        raise _fail(source, f"joint {joint.name!r}", "its origin is not finite")
    kind = {"continuous": "revolute"}.get(joint.type, joint.type)
    if joint.type in _MOVABLE:
        norm = float(np.linalg.norm(axis))
        if not np.isfinite(norm) or norm == 0.0:
            raise _fail(source, f"joint {joint.name!r}", "its axis is zero or not finite")
        axis = axis / norm
        if held is not None:
            origin = origin.copy()
            if kind == "revolute":
                origin[:3, :3] = origin[:3, :3] @ _turn(axis, held)
            else:
                origin[:3, 3] = origin[:3, 3] + origin[:3, :3] @ axis * held
            kind = "fixed"
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
        inertia = own if turn == sp.eye(3) else _product(_product(turn, own), turn.T)
    return _Body(
        link=link.name,
        joint=joint.name,
        kind=kind,
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
