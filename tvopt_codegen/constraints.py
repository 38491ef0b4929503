"""Time-varying inequality constraints by an interior-point homotopy.

A spec's ``[constraints]`` ``g_i(y, t) <= 0`` (each convex in ``y``) turn the objective
into (Fazlyab, Paternain, Preciado and Ribeiro, "Prediction-correction interior-point
method for time-varying convex optimization", IEEE TAC 2018)::

    Phi(y, t) = f0(y, t) - mu(t) * sum_i log(s(t) - g_i(y, t))
    mu(t) = mu_inf + (mu_0 - mu_inf) exp(-rate t),   s(t) = s_0 exp(-rate t)

``Phi`` is time-varying and strongly convex in ``y`` on its domain (``f0`` is, and each
``-log(s - g_i)`` is convex where ``g_i`` is), so the paper's law applies to it unchanged,
with ``mu`` and ``s`` differentiated exactly like any signal. What follows, and what
``simulate`` checks on every run:

- ``E_Phi(t) = expm(H t) E_Phi(0)``: the theorem, for ``Phi``;
- ``g_i(y(t), t) < s(t)`` at every instant: ``grad Phi`` is finite along the run (the law
  keeps it on ``expm(H t) E(0)``), and it is infinite on the barrier;
- the distance to the constrained minimiser ``y*_s(t)`` of ``f0`` subject to
  ``g_i <= s(t)``: ``f0(y*_Phi) - f0(y*_s) <= p mu`` (the barrier's duality gap for ``p``
  inequalities), and with ``f0`` ``m_f``-strongly convex, ``|y*_Phi - y*_s| <=
  sqrt(2 p mu / m_f)``; so ``|y(t) - y*_s(t)| <= |y(t) - y*_Phi(t)| + sqrt(2 p mu(t) / m_f)``.

The slack lets the run start outside the constraints: ``s(0)`` exceeds the largest initial
violation, and ``s`` decays to 0 at the barrier's rate.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import sympy as sp

from tvopt_codegen.numeric import Evaluator
from tvopt_codegen.spec import Barrier, Constraint

#: The slack's start above the largest initial violation: twice it, plus this.
SLACK_MARGIN = 0.1


def inline_signals(expr: sp.Expr, signals: Mapping[sp.Symbol, sp.Expr]) -> sp.Expr:
    """``expr`` with every signal replaced by its definition, signals of signals too."""
    expr = sp.sympify(expr)
    for _ in range(len(signals) + 1):
        if not expr.free_symbols & signals.keys():
            break
        expr = expr.xreplace(signals)
    return expr


def schedule(barrier: Barrier, slack: float, t: sp.Symbol) -> tuple[sp.Expr, sp.Expr]:
    """``mu(t)`` and ``s(t)`` as expressions in ``t`` (exact: they are differentiated)."""
    decay = sp.exp(-sp.nsimplify(barrier.rate) * t)
    mu_inf = sp.nsimplify(barrier.final_weight)
    mu = mu_inf + (sp.nsimplify(barrier.initial_weight) - mu_inf) * decay
    return mu, sp.nsimplify(slack) * decay


def initial_slack(
    constraints: Sequence[Constraint],
    barrier: Barrier,
    values: Mapping[sp.Symbol, sp.Expr],
) -> float:
    """``s(0)``: given, or 0 for a strictly feasible start, else above the violation.

    ``values`` holds the outputs, signals, references, parameters and ``t`` at the start.
    """
    if barrier.initial_slack is not None:
        return barrier.initial_slack
    worst = max(float(sp.sympify(c.g).xreplace(dict(values))) for c in constraints)
    return 0.0 if worst < 0 else 2.0 * worst + SLACK_MARGIN


def barrier_objective(
    f0: sp.Expr, constraints: Sequence[Constraint], mu: sp.Expr, slack: sp.Expr
) -> sp.Expr:
    """``Phi = f0 - mu sum_i log(s - g_i)``."""
    return f0 - mu * sp.Add(*(sp.log(slack - c.g) for c in constraints))


def nonconvex(
    constraints: Sequence[Constraint],
    outputs: Sequence[sp.Symbol],
    evaluate: Evaluator,
    points: int,
) -> list[tuple[str, float]]:
    """The constraints whose Hessian in ``y`` has a negative eigenvalue at a sample point.

    ``evaluate`` holds the sample points (arrays of ``points`` values for the outputs,
    ``t``, signals and references). Returns (name, smallest eigenvalue) of each.
    """
    found = []
    m = len(outputs)
    for constraint in constraints:
        g = sp.sympify(constraint.g)
        matrices = np.zeros((points, m, m))
        for i, yi in enumerate(outputs):
            for j, yj in enumerate(outputs[: i + 1]):
                second = sp.diff(g, yi, yj)
                if second != 0:
                    value = np.broadcast_to(np.real(evaluate(second)), (points,))
                    matrices[:, i, j] = matrices[:, j, i] = value
        finite = np.all(np.isfinite(matrices), axis=(1, 2))
        if not finite.any():
            continue
        eigenvalues = np.linalg.eigvalsh(matrices[finite])
        smallest = float(eigenvalues[:, 0].min())
        scale = max(1.0, float(np.abs(eigenvalues).max()))
        if smallest < -1e-9 * scale:
            found.append((constraint.name, smallest))
    return found


def least_violation(model: Any, t: float, y0: np.ndarray) -> float:
    """``min_y max_i g_i(y, t)`` on ``a_j(y, t) = 0``: positive when nothing is feasible.

    By SLSQP, as ``min z`` subject to ``g_i(y, t) <= z`` and the equalities, from ``y0``;
    signals and nominal references at ``t`` (references without one at 0), parameters at
    their defaults. When ``y0`` is feasible itself, its ``max_i g_i`` (at most 0) is
    returned without a search: that answers the question asked, whether anything is.
    """
    at = {model.t: sp.Float(t)}
    at |= {q: sp.Float(v) for q, v in zip(model.params, model.defaults, strict=True)}
    nominal = dict(model.nominal)
    fixed = {r: nominal.get(r, sp.Integer(0)) for r in model.references}
    signals = dict(model.signals)

    def function(constraint: Any) -> Any:
        expr = inline_signals(constraint.g, signals).xreplace(fixed).xreplace(at)
        return sp.lambdify([model.y], expr, "math")

    functions = [function(c) for c in model.constraints]
    equal = [function(c) for c in model.equalities]
    m = len(model.y)
    at_start = max(f(y0) for f in functions)
    if at_start <= 0 and all(f(y0) == 0 for f in equal):
        # y0 is a feasible point already; the search (and importing scipy.optimize, a
        # sixth of such a command) would only find a smaller value, never a positive one.
        return float(at_start)
    from scipy.optimize import minimize  # noqa: PLC0415 - only for an infeasible start

    start = np.append(y0, at_start + 1.0)
    result = minimize(
        lambda v: v[m],
        start,
        method="SLSQP",
        constraints=[{"type": "ineq", "fun": lambda v, f=f: v[m] - f(v[:m])} for f in functions]
        + [{"type": "eq", "fun": lambda v, f=f: f(v[:m])} for f in equal],
        options={"ftol": 1e-12, "maxiter": 500},
    )
    return float(max(f(result.x[:m]) for f in functions))


@dataclass(frozen=True)
class RunCheck:
    """What the constraints' certificate found along a run.

    Attributes
    ----------
    margins : numpy.ndarray, shape (p, T)
        ``s(t) - g_i(y(t), t)`` at the output times: positive everywhere, by the barrier.
    slack : numpy.ndarray, shape (T,)
        ``s(t)``.
    final : tuple of (str, float)
        ``g_i(y(T), T)`` per inequality (<= 0 where it holds), then ``a_j(y(T), T)`` per
        equality.
    distance : numpy.ndarray, shape (K,)
        ``|y(t) - y*_s(t)|`` at the checked times, ``y*_s`` found by SLSQP (scipy) on f0
        subject to ``g_i <= s(t)`` and ``a_j = 0``.
    bound : numpy.ndarray, shape (K,)
        ``|y(t) - y*_Phi(t)| + sqrt(2 p mu(t) / m_f)`` at those times, ``m_f`` the smallest
        eigenvalue of the spec's f0's Hessian along the run.
    times : numpy.ndarray, shape (K,)
        The checked times.
    m_f : float
        That modulus.
    lhs, rhs : numpy.ndarray, shape (p + q, T)
        Each constraint's two sides along the run (the boundary moves with ``rhs``):
        the inequalities, then the equalities.
    equality : numpy.ndarray, shape (q, T)
        ``a_j(y(t), t)`` of each equality along the run (0 where it holds).
    """

    margins: np.ndarray
    slack: np.ndarray
    final: tuple[tuple[str, float], ...]
    distance: np.ndarray
    bound: np.ndarray
    times: np.ndarray
    m_f: float
    lhs: np.ndarray
    rhs: np.ndarray
    equality: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))


@dataclass(frozen=True)
class _Problem:
    """The constrained problem in numbers: f0, the g_i, their gradients, f0's domain."""

    f0: Any
    f0_grad: list[Any]
    g: list[Any]
    g_grad: list[list[Any]]
    a: list[Any]
    a_grad: list[list[Any]]
    domain: list[Any]
    domain_grad: list[list[Any]]
    numeric: Any
    refs_at: Any


def _problem(model: Any, values: Mapping[sp.Symbol, float], references: Any) -> _Problem:
    """Lambdify the problem of :func:`check_run` (signals and parameters substituted)."""
    t = model.t
    signals = {s: e for s, e in model.signals}
    fixed = {q: sp.Float(v) for q, v in values.items()}

    def numeric(expr: sp.Expr) -> Any:
        expr = inline_signals(expr, signals).xreplace(fixed)
        return sp.lambdify([t, model.y, model.references], expr, "math")

    def refs_at(time: float) -> list[float]:
        if not model.references or references is None:
            return []
        jets = (references.exact or references.jets)(time)
        return [float(v) for v in jets[:, 0]]

    objective = sp.sympify(model.f0 if model.objective is None else model.objective)
    # f0's principal domain, which the barrier objective never leaves: tan's argument
    # within (-pi/2, pi/2) and log's positive; the independent solver keeps to it too.
    domain = []
    for node in sp.preorder_traversal(inline_signals(objective, signals)):
        if isinstance(node, sp.tan):
            domain += [sp.pi / 2 - node.args[0], node.args[0] + sp.pi / 2]
        elif isinstance(node, sp.log):
            domain.append(node.args[0])
    return _Problem(
        f0=numeric(objective),
        # Exact gradients for the solver: f0's barriers (the paper's tan) are steep.
        f0_grad=[numeric(sp.diff(objective, yi)) for yi in model.y],
        g=[numeric(c.g) for c in model.constraints],
        g_grad=[
            [numeric(sp.diff(sp.sympify(c.g), yi)) for yi in model.y] for c in model.constraints
        ],
        a=[numeric(c.g) for c in model.equalities],
        a_grad=[
            [numeric(sp.diff(sp.sympify(c.g), yi)) for yi in model.y] for c in model.equalities
        ],
        domain=[numeric(e) for e in domain],
        domain_grad=[[numeric(sp.diff(e, yi)) for yi in model.y] for e in domain],
        numeric=numeric,
        refs_at=refs_at,
    )


def _minimise(
    problem: _Problem, time: float, r: list[float], s: float, centre: np.ndarray, radius: float
) -> np.ndarray:
    """f0's minimiser subject to ``g_i <= s`` and ``a_j = 0``, by SLSQP near ``centre``.

    The search stays in the box of half-width ``radius`` around ``centre``.
    """
    from scipy.optimize import minimize  # noqa: PLC0415 - only simulate needs it

    inequalities = [
        {
            "type": "ineq",
            "fun": lambda y, gi=gi: s - gi(time, y, r),
            "jac": lambda y, row=row: -np.array([d(time, y, r) for d in row]),
        }
        for gi, row in zip(problem.g, problem.g_grad, strict=True)
    ] + [
        {
            "type": "ineq",
            "fun": lambda y, e=e: e(time, y, r),
            "jac": lambda y, row=row: np.array([d(time, y, r) for d in row]),
        }
        for e, row in zip(problem.domain, problem.domain_grad, strict=True)
    ]
    equal = [
        {
            "type": "eq",
            "fun": lambda y, ai=ai: ai(time, y, r),
            "jac": lambda y, row=row: np.array([d(time, y, r) for d in row]),
        }
        for ai, row in zip(problem.a, problem.a_grad, strict=True)
    ]
    result = minimize(
        lambda y: problem.f0(time, y, r),
        centre,
        jac=lambda y: np.array([d(time, y, r) for d in problem.f0_grad]),
        method="SLSQP",
        bounds=[(c - radius, c + radius) for c in centre],
        constraints=inequalities + equal,
        options={"ftol": 1e-15, "maxiter": 1000},
    )
    minimiser: np.ndarray = result.x
    return minimiser


def check_run(
    model: Any,
    ts: np.ndarray,
    outputs: np.ndarray,
    to_phi: np.ndarray,
    phi_minimisers: np.ndarray,
    values: Mapping[sp.Symbol, float],
    references: Any = None,
    checked: int = 41,
) -> RunCheck:
    """Check a run against its constraints (see the module docstring).

    Parameters
    ----------
    model : Model
        With ``constraints``, ``objective`` (the spec's f0), ``mu`` and ``slack``.
    ts, outputs : numpy.ndarray
        Output times (T,) and outputs (m, T) of the run.
    to_phi : numpy.ndarray, shape (T,)
        ``|y(t) - y*_Phi(t)|``: the distance to the barrier objective's minimiser.
    phi_minimisers : numpy.ndarray, shape (m, T)
        ``y*_Phi(t)``: where the independent solver starts.
    values : mapping
        Parameter values.
    references : ReferenceSource, optional
        For a spec with references: their values (true ones when known).
    checked : int, optional
        Times at which the constrained minimiser is found (evenly spread, the last one
        the end of the run).
    """
    problem = _problem(model, values, references)
    t, numeric, refs_at = model.t, problem.numeric, problem.refs_at
    g = problem.g
    fixed = {q: sp.Float(v) for q, v in values.items()}
    slack_of = sp.lambdify(t, model.slack.xreplace(fixed), "math")
    mu_of = sp.lambdify(t, model.mu.xreplace(fixed), "math")
    slack = np.array([slack_of(float(time)) for time in ts])

    def along(functions: Sequence[Any]) -> np.ndarray:
        return np.array(
            [
                [f(float(time), outputs[:, k], refs_at(float(time))) for k, time in enumerate(ts)]
                for f in functions
            ],
            dtype=float,
        ).reshape(len(functions), len(ts))

    margins = slack[None, :] - along(g)
    equality = along(problem.a)
    end = float(ts[-1])
    final = tuple(
        (c.name, float(gi(end, outputs[:, -1], refs_at(end))))
        for c, gi in zip((*model.constraints, *model.equalities), (*g, *problem.a), strict=True)
    )
    picks = np.unique(np.linspace(0, len(ts) - 1, checked).round().astype(int))
    objective = model.f0 if model.objective is None else model.objective
    hessian = [[numeric(sp.diff(objective, yi, yj)) for yj in model.y] for yi in model.y]

    def smallest(time: float, y: np.ndarray, r: list[float]) -> float:
        matrix = np.array([[h(time, y, r) for h in row] for row in hessian], dtype=float)
        return float(np.linalg.eigvalsh(matrix)[0])

    p = len(model.constraints)
    m_f = min(smallest(float(ts[k]), outputs[:, k], refs_at(float(ts[k]))) for k in picks)
    minimisers, distance, bound = [], [], []
    for k in picks:
        time = float(ts[k])
        r = refs_at(time)
        s = slack[k]
        gap = math.sqrt(2.0 * p * mu_of(time) / m_f) if m_f > 0 else math.inf
        # A local solve from the barrier's minimiser, within twice the gap the theory
        # allows: f0 may have other branches (a periodic barrier such as tan), and the
        # constrained minimiser meant is the one of y*_Phi's branch. A solution on the box
        # is reported: the minimiser was not where the theory puts it.
        radius = 2.0 * gap + 1e-3
        centre = phi_minimisers[:, k]
        result_x = _minimise(problem, time, r, s, centre, radius)
        on_box = bool(np.any(np.abs(result_x - centre) >= radius * (1 - 1e-9)))
        minimisers.append(result_x)
        distance.append(math.inf if on_box else float(np.linalg.norm(outputs[:, k] - result_x)))
        bound.append(float(to_phi[k] + gap))
    every = (*model.constraints, *model.equalities)
    lhs = along([numeric(c.lhs) for c in every])
    rhs = along([numeric(c.rhs) for c in every])
    return RunCheck(
        margins=margins,
        slack=slack,
        final=final,
        distance=np.array(distance),
        bound=np.array(bound),
        times=ts[picks],
        m_f=m_f,
        lhs=lhs,
        rhs=rhs,
        equality=equality,
    )


@dataclass(frozen=True)
class Equalities:
    """The equality constraints in numbers, for the KKT certificate.

    Each callable takes ``(t, y, r)``: time, outputs (m,) and the references' values.

    Attributes
    ----------
    value : callable
        ``a(y, t)``, shape (q,).
    jacobian : callable
        ``J_a``, shape (q, m).
    curvature : callable
        ``sum_j nu_j grad_yy a_j`` for given ``nu``: ``curvature(t, y, r, nu)``, (m, m);
        zero for affine equalities.
    """

    value: Any
    jacobian: Any
    curvature: Any


def equalities(model: Any, values: Mapping[sp.Symbol, float]) -> Equalities:
    """Lambdify the equalities of ``model`` (signals and the parameters ``values`` substituted)."""
    signals = {s: e for s, e in model.signals}
    fixed = {q: sp.Float(v) for q, v in values.items()}
    m, q = len(model.y), len(model.equalities)

    def numeric(exprs: Sequence[sp.Expr]) -> Any:
        exprs = [inline_signals(e, signals).xreplace(fixed) for e in exprs]
        return sp.lambdify([model.t, model.y, model.references], exprs, "math")

    a = [sp.sympify(c.g) for c in model.equalities]
    value = numeric(a)
    jacobian = numeric([sp.diff(e, y) for e in a for y in model.y])
    second = [[sp.diff(e, yi, yj) for yi in model.y for yj in model.y] for e in a]
    curved = any(entry != 0 for row in second for entry in row)
    hessians = [numeric(row) for row in second] if curved else []

    def curvature(t: float, y: np.ndarray, r: Sequence[float], nu: np.ndarray) -> np.ndarray:
        total = np.zeros((m, m))
        for weight, hessian in zip(nu, hessians, strict=False):
            total += weight * np.array(hessian(t, y, r), dtype=float).reshape(m, m)
        return total

    return Equalities(
        value=lambda t, y, r: np.array(value(t, y, r), dtype=float),
        jacobian=lambda t, y, r: np.array(jacobian(t, y, r), dtype=float).reshape(q, m),
        curvature=curvature,
    )


def kkt_matrix(hessian: np.ndarray, jacobian_a: np.ndarray) -> np.ndarray:
    """``K = [[grad_yy L, J_a^T], [J_a, 0]]``."""
    m, q = hessian.shape[0], jacobian_a.shape[0]
    matrix = np.zeros((m + q, m + q))
    matrix[:m, :m] = hessian
    matrix[:m, m:] = jacobian_a.T
    matrix[m:, :m] = jacobian_a
    return matrix
