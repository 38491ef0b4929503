"""CasADi's independent build of a mass-matrix plant's law, with its own numeric solves.

The oracle of ``tests/oracle.py`` shares nothing with the generator but the spec's
expressions; this one also shares no numerics: CasADi's automatic differentiation
takes the outputs' Jacobian and curvature and the objective's gradient jet, and its
generated-code-capable linear solvers (``ldl`` for ``M [a W] = [F B]``, ``qr`` for
``R w = v - p``) solve, never a symbolic inverse. ``benchmarks/bench_mechanics.py``
times its generated C against ours.
"""

from __future__ import annotations

from typing import Any

import casadi as ca

from tvopt_codegen.derivation import Derivation

#: CasADi's functions by the lower-case name of the engine's function class: SymPy's
#: ``sin``, SymEngine's ``Sin``.
_FUNCTIONS = {
    "sin": ca.sin, "cos": ca.cos, "tan": ca.tan, "exp": ca.exp, "log": ca.log,
    "atan": ca.atan, "asin": ca.asin, "acos": ca.acos, "sinh": ca.sinh, "cosh": ca.cosh,
    "tanh": ca.tanh,
}  # fmt: skip


def _to_casadi(expr: Any, table: dict[Any, Any]) -> Any:
    """An expression of either engine on CasADi values: ``table`` holds its symbols' (and memoizes).

    Read through what both engines' trees answer to (``is_Add``, ``.args``, the class's
    name), not through the product's ``sx``: the oracle shares the spec's expressions
    only. SymEngine writes ``exp(x)`` as the power ``E**x``: ``E`` is a constant atom.
    """
    if expr in table:
        return table[expr]
    if expr.is_Number:
        value: Any = float(expr)
    elif expr.is_Symbol:
        raise ValueError(f"no CasADi value for the symbol {expr}")
    elif expr.is_Atom:  # pi, E
        value = float(expr)
    elif expr.is_Add:
        value = sum((_to_casadi(a, table) for a in expr.args[1:]), _to_casadi(expr.args[0], table))
    elif expr.is_Mul:
        value = _to_casadi(expr.args[0], table)
        for a in expr.args[1:]:
            value = value * _to_casadi(a, table)
    elif expr.is_Pow:
        base, exponent = expr.args
        value = _to_casadi(base, table) ** _to_casadi(exponent, table)
    elif expr.is_Function and type(expr).__name__.lower() in _FUNCTIONS:
        value = _FUNCTIONS[type(expr).__name__.lower()](_to_casadi(expr.args[0], table))
    else:
        raise ValueError(f"no CasADi twin for {type(expr).__name__}")
    table[expr] = value
    return value


def casadi_mechanics_law(d: Derivation) -> tuple[ca.Function, int]:
    """The law for ``d``'s mass-matrix plant, built by CasADi with numeric solves of M and R.

    Returns the function and its size: the SX part's instructions (M, F, B, J, the
    curvature and y_imp'') plus the MX graph's (the two solves and the products).
    """
    model = d.model
    mech = model.mechanics
    assert mech is not None and d.dynamics.k == 2
    nq, m = len(mech.coordinates), len(model.y)
    tS = ca.SX.sym("t")
    XS = ca.SX.sym("X", 2 * nq)
    PS = ca.SX.sym("P", max(1, len(model.params)))
    # Keyed by the derivation's own symbols, of the engine it was derived on.
    table: dict[Any, Any] = {s: XS[i] for i, s in enumerate(model.x)}
    table |= {p: PS[i] for i, p in enumerate(model.params)}
    table[model.t] = tS
    # The spec's definitions in order, each on CasADi's values of those before it.
    for symbol, expr in mech.definitions:
        table[symbol] = _to_casadi(expr, table)

    def cas(expr: Any) -> ca.SX:
        value: ca.SX = _to_casadi(expr, table)
        return value

    M = ca.vertcat(*[ca.horzcat(*[cas(e) for e in row]) for row in mech.mass_matrix])
    F = ca.vertcat(*[cas(e) for e in mech.forces])
    B = ca.vertcat(*[ca.horzcat(*[cas(e) for e in row]) for row in mech.input_matrix])
    h = ca.vertcat(*[cas(e) for e in model.h])
    q, dq = XS[:nq], XS[nq:]
    J = ca.jacobian(h, q)
    velocity = ca.jtimes(h, q, dq)
    curvature = ca.jtimes(velocity, q, dq)
    # y_imp'' from the objective's gradient jet, as benchmarks/bench_c.py builds it.
    for symbol, expr in model.signals:
        table[symbol] = cas(expr)
    Y = ca.SX.sym("Y", m, 3)
    table |= {y: Y[i, 0] for i, y in enumerate(model.y)}
    f0 = cas(model.f0)
    jet = [ca.gradient(f0, Y[:, 0])]
    moving = ca.vertcat(tS, ca.vec(Y[:, :2]))
    rates = ca.vertcat(1, ca.vec(Y[:, 1:]))
    for _ in range(2):
        jet.append(ca.jtimes(jet[-1], moving, rates))
    rest = ca.substitute(jet[2], Y[:, 2], ca.DM.zeros(m))
    hess = ca.hessian(f0, Y[:, 0])[0]
    c = d.dynamics.coefficients[0] * jet[0] + d.dynamics.coefficients[1] * jet[1] - rest
    state_jet = ca.vertcat(h, velocity)
    c = ca.substitute(c, ca.vec(Y[:, :2]), state_jet)
    hess = ca.substitute(hess, ca.vec(Y[:, :2]), state_jet)
    z = ca.solve(hess, c)
    parts = ca.Function("parts", [tS, XS, PS], [M, ca.horzcat(F, B), J, curvature, z])
    t = ca.MX.sym("t")
    X = ca.MX.sym("X", 2 * nq)
    P = ca.MX.sym("P", max(1, len(model.params)))
    M_, FB, J_, curv, z_ = parts(t, X, P)
    solved = ca.solve(M_, FB, "ldl")  # M^-1 [F B], numerically: never inverted
    accel, gain = solved[:, 0], solved[:, 1:]
    R = ca.mtimes(J_, gain)
    p = curv + ca.mtimes(J_, accel)
    w = ca.solve(R, z_ - p, "qr")
    law = ca.Function("casadi_law", [t, X, P], [w])
    return law, parts.n_instructions() + law.n_instructions()
