"""The dynamics of the chain, symbolically: the recursive Newton-Euler algorithm.

The bias ``C(q, q') q' + g(q)`` is one pass at zero joint acceleration, column ``j`` of
``M`` one pass at unit acceleration of joint ``j`` without velocity and gravity: algebra
on rotations and cross products, never a derivative and never an inverse. Every vector a
pass forms is named (:class:`_Lets`, the spec's ``definitions``), so that each stays a
few operations long.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import sympy as sp

from tvopt_codegen.urdf.chain import _Body


class _NameTakenError(Exception):
    """A definition's name is a joint's or link's spec name (args: the owner, the problem)."""


class _Lets:
    """Named intermediate values, the spec's ``definitions``.

    Each non-trivial expression the algorithm forms gets a name, so that every one stays
    a few operations long.
    """

    def __init__(self, owners: Mapping[str, str]) -> None:
        self.items: list[tuple[str, sp.Expr]] = []
        self.owners = dict(owners)  # casefolded name: the URDF element that made it

    def __call__(self, name: str, expr: sp.Expr) -> sp.Expr:
        expr = sp.sympify(expr)
        if expr.is_Atom or (
            expr.is_Mul and len(expr.args) == 2 and expr.args[0].is_Number and expr.args[1].is_Atom
        ):
            return expr
        owner = self.owners.get(name.casefold())
        if owner is not None:
            raise _NameTakenError(
                owner,
                f"its spec name is {name!r}, which the import also gives one of its "
                "definitions: rename it",
            )
        self.owners[name.casefold()] = "an intermediate"
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
