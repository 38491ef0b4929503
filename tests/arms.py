"""Planar serial arms built with SymPy mechanics (Kane's method), for the mass-matrix tests.

Link ``i`` is a uniform rod of mass ``m<i>`` and length ``l<i>`` turning about the
previous link's tip by the relative angle ``q<i>``, driven by the torque ``tau<i>``
(and reacting on the previous link); gravity ``g`` acts along ``-y``.
"""

from __future__ import annotations

import sympy as sp
import sympy.physics.mechanics as me


def planar_arm(links: int) -> tuple[me.KanesMethod, list[sp.Expr], dict[sp.Symbol, float]]:
    """Kane's equations of a planar arm, its joint angles and parameter values."""
    q = me.dynamicsymbols(f"q1:{links + 1}")
    u = me.dynamicsymbols(f"dq1:{links + 1}")
    tau = me.dynamicsymbols(f"tau1:{links + 1}")
    m = sp.symbols(f"m1:{links + 1}", positive=True)
    lengths = sp.symbols(f"l1:{links + 1}", positive=True)
    g = sp.Symbol("g", positive=True)
    world = me.ReferenceFrame("N")
    base = me.Point("O")
    base.set_vel(world, 0)
    frames, bodies, loads = [], [], []
    parent, joint = world, base
    for i in range(links):
        frame = parent.orientnew(f"L{i + 1}", "Axis", [q[i], parent.z])
        frame.set_ang_vel(parent, u[i] * parent.z)
        centre = joint.locatenew(f"C{i + 1}", lengths[i] / 2 * frame.x)
        centre.v2pt_theory(joint, world, frame)
        tip = joint.locatenew(f"P{i + 1}", lengths[i] * frame.x)
        tip.v2pt_theory(joint, world, frame)
        inertia = me.inertia(frame, 0, 0, m[i] * lengths[i] ** 2 / 12)
        bodies.append(me.RigidBody(f"B{i + 1}", centre, frame, m[i], (inertia, centre)))
        loads.append((centre, -m[i] * g * world.y))
        loads.append((frame, tau[i] * world.z))
        if i > 0:
            loads.append((parent, -tau[i] * world.z))
        frames.append(frame)
        parent, joint = frame, tip
    kane = me.KanesMethod(
        world, q_ind=q, u_ind=u, kd_eqs=[qi.diff() - ui for qi, ui in zip(q, u, strict=True)]
    )
    kane.kanes_equations(bodies, loads)
    values: dict[sp.Symbol, float] = {g: 9.81}
    for i in range(links):
        values[m[i]] = round(2.0 - 0.25 * i, 2)
        values[lengths[i]] = round(0.6 - 0.05 * i, 2)
    return kane, list(q), values
