"""CasADi peers of the laws ``bench_c.casadi_law`` cannot build: mass-matrix plants, equalities.

``bench_c.casadi_law`` takes the extended plant's ``f`` and ``G`` as explicit expressions
and the objective's gradient as the function whose jet the law cancels. Two kinds of
bundled example fall outside it:

- **Mass-matrix plants** (``[system.mechanics]``: planar_arm3, ur5_tip). Their ``f`` and
  ``G`` hold the run-time symbols ``a = M^-1 F`` and ``W = M^-1 B`` (docs/architecture.md
  section 3a). Here they are CasADi expressions: ``M``, ``F`` and ``B`` (and the spec's
  definitions before them) evaluated on CasADi symbols, and ``[a W] = ca.solve(M, [F B])``,
  one solve of all right-hand sides. ``ca.solve`` on SX is what a CasADi user writes for a
  forward-dynamics model (``ddq = solve(M, tau - C)``), and what ``casadi_law`` already
  uses for the Hessian and ``R``. CasADi expands it into expressions its AD and code
  generator take like any other: up to 3 x 3 the adjugate over the determinant
  (planar_arm3's ``M``), above that a QR factorization whose generated C calls ``sqrt``
  (ur5_tip's 6 x 6 ``M``). An LDL^T written out by hand in CasADi expressions would be
  our own factorization translated, not the peer's.
- **Equality constraints** (arm_on_line). The law is the paper's law for the Lagrangian
  ``L = f0 + nu^T a`` over ``(y, nu)`` (docs/constraints.md): its gradient is the KKT map
  ``F``, its Hessian the KKT matrix ``K``. The multiplier and its first ``k - 1``
  derivatives are the controller's states ``nu_<name>_0 .. nu_<name>_<k-1>`` (after the
  plant's in the closed-loop state); ``F``'s jet is taken along ``(t, y, .., y^(k-1), nu,
  .., nu^(k-1))``, and ``(y^(k), nu^(k)) = K^-1 [sum_i c_i F^(i) - rest]``. ``y^(k)``
  reaches the inputs through ``R`` as in ``casadi_law``; ``nu^(k)`` drives the chain and
  is not an input, so ``control`` does not return it.

Everything else is ``casadi_law``'s construction: Lie derivatives by ``jtimes``, the
gradient's jet by ``jtimes`` along time and the output jets, ``ca.solve`` for the Hessian
(or ``K``) and for ``R``.
"""

from __future__ import annotations

from typing import Any

import casadi as ca
import sympy as sp
from casadi_peer import _to_casadi


def _plant(d: Any, X: ca.SX, P: ca.SX) -> tuple[ca.SX, ca.SX, list[Any], list[Any]]:
    """``f`` and ``G`` of ``d``'s extended plant on CasADi symbols.

    Returns
    -------
    f, G : casadi.SX
        The vector field and the input matrix.
    base, values : list
        The sympy symbols (states, parameters) and their CasADi values.
    """
    model, ext = d.model, d.linearization.extension
    n = len(ext.x)
    base: list[Any] = [*ext.x, *model.params]
    values: list[Any] = [X[i] for i in range(n)] + [P[i] for i in range(len(model.params))]
    mechanics = model.mechanics
    opaque: list[Any] = []
    solved: list[Any] = []
    if mechanics is not None:
        scope, scope_values = list(base), list(values)
        # The definitions in order, each in the states, parameters and the earlier ones.
        for symbol, expr in mechanics.definitions:
            scope_values.append(_to_casadi(expr, scope, scope_values))
            scope.append(symbol)
        nq = len(mechanics.coordinates)

        def sx(expr: sp.Expr) -> ca.SX:
            return ca.SX(_to_casadi(expr, scope, scope_values))

        mass = ca.vertcat(
            *[ca.horzcat(*[sx(mechanics.mass_matrix[i][j]) for j in range(nq)]) for i in range(nq)]
        )
        width = len(mechanics.input_matrix[0]) if mechanics.input_matrix else 0
        rhs = ca.horzcat(
            ca.vertcat(*[sx(e) for e in mechanics.forces]),
            *[
                ca.vertcat(*[sx(mechanics.input_matrix[i][j]) for i in range(nq)])
                for j in range(width)
            ],
        )
        solution = ca.solve(mass, rhs)
        for i in range(nq):
            if isinstance(mechanics.accelerations[i], sp.Symbol):
                opaque.append(mechanics.accelerations[i])
                solved.append(solution[i, 0])
            for j in range(width):
                if isinstance(mechanics.gains[i][j], sp.Symbol):
                    opaque.append(mechanics.gains[i][j])
                    solved.append(solution[i, j + 1])
    scope, scope_values = [*base, *opaque], [*values, *solved]
    f = ca.vertcat(*[ca.SX(_to_casadi(e, scope, scope_values)) for e in ext.f])
    G = ca.horzcat(
        *[
            ca.vertcat(*[ca.SX(_to_casadi(ext.G[i, j], scope, scope_values)) for i in range(n)])
            for j in range(ext.G.shape[1])
        ]
    )
    return f, G, base, values


def casadi_peer_law(d: Any) -> ca.Function:
    """The paper's law of ``d`` derived by CasADi's AD, for mass-matrix plants and equalities.

    Parameters
    ----------
    d : Derivation
        A derivation of uniform relative degree, without references measured at run time,
        inequalities, padding chains, an observer or integral action (the bundled examples
        this serves: planar_arm3, ur5_tip, arm_on_line).

    Returns
    -------
    casadi.Function
        ``casadi_law(t, X, P) -> u``, ``X`` the closed-loop state in ``control``'s order
        (the plant's states, then the multipliers' chains), ``P`` the parameters.
    """
    model, ext, loop = d.model, d.linearization.extension, d.closed_loop
    assert d.dynamics.uniform, "the benchmark builds uniform-relative-degree laws only"
    assert not model.references and not model.constraints, "no references or inequalities"
    assert not any(loop.padding) and not loop.integral_states, "no padding or integral chains"
    n, m, k, q = len(ext.x), len(model.y), d.dynamics.k, len(model.equalities)
    assert len(loop.state_names) == n + q * k, "plant states, then the multipliers' chains"
    t = ca.SX.sym("t")
    plant = ca.SX.sym("X", n)
    multipliers = ca.SX.sym("nu", q * k)
    P = ca.SX.sym("P", max(1, len(model.params)))
    f, G, base, values = _plant(d, plant, P)
    h = [_to_casadi(e, base, values) for e in model.h]
    params = values[n:]
    signal_values = [
        _to_casadi(e, [model.t, *model.params], [t, *params]) for _, e in model.signals
    ]
    # Y[i, j]: output i's j-th derivative; N[i, j]: multiplier i's.
    Y = ca.SX.sym("Y", m, k + 1)
    N = ca.SX.sym("N", q, k + 1)
    lagrangian = _to_casadi(
        model.lagrangian,
        [*model.y, *model.multipliers, *(s for s, _ in model.signals), *model.params, model.t],
        [*(Y[i, 0] for i in range(m)), *(N[i, 0] for i in range(q)), *signal_values, *params, t],
    )
    now = ca.vertcat(Y[:, 0], N[:, 0])
    jet = [ca.gradient(lagrangian, now)]
    moving = ca.vertcat(t, ca.vec(Y[:, :k]), ca.vec(N[:, :k]))
    rates = ca.vertcat(1, ca.vec(Y[:, 1:]), ca.vec(N[:, 1:]))
    for _ in range(k):
        jet.append(ca.jtimes(jet[-1], moving, rates))
    rest = ca.substitute(jet[k], ca.vertcat(Y[:, k], N[:, k]), ca.DM.zeros(m + q))
    hess = ca.hessian(lagrangian, now)[0]
    c = sum(d.dynamics.coefficients[j] * jet[j] for j in range(k)) - rest
    lie, rows, p = [], [], []
    for i in range(m):
        chain = [h[i]]
        for _ in range(k):
            chain.append(ca.jtimes(chain[-1], plant, f))
        lie.append(chain[:k])
        rows.append(ca.mtimes(ca.jacobian(chain[k - 1], plant), G))
        p.append(chain[k])
    # The outputs' jets from the Lie chains; the multipliers' from their controller states.
    known = ca.vertcat(*[lie[i][j] for j in range(k) for i in range(m)])
    chains = ca.vertcat(*[multipliers[i * k + j] for j in range(k) for i in range(q)])
    c = ca.substitute(c, ca.vertcat(ca.vec(Y[:, :k]), ca.vec(N[:, :k])), ca.vertcat(known, chains))
    hess = ca.substitute(
        hess, ca.vertcat(ca.vec(Y[:, :k]), ca.vec(N[:, :k])), ca.vertcat(known, chains)
    )
    z = ca.solve(hess, c)
    w = ca.solve(ca.vertcat(*rows), z[:m] - ca.vertcat(*p))
    index = {s.name: i for i, s in enumerate(ext.x)}
    u = ca.vertcat(
        *[plant[index[uj.name]] if uj.name in ext.states else w[j] for j, uj in enumerate(model.u)]
    )
    return ca.Function("casadi_law", [t, ca.vertcat(plant, multipliers), P], [u])
