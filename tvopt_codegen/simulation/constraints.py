"""The constraints' certificate of a run, and the equality constraints in numbers.

What ``simulate`` checks of a run with ``[constraints]`` (see
:mod:`tvopt_codegen.spec.constraints` for the barrier objective and the claims): the margins
``s(t) - g_i``, the equalities' drift, the distance to an independent constrained
minimiser (SLSQP), and the KKT matrix of equality constraints. Every derivative comes
from :mod:`tvopt_codegen.derivation.calculus`; nothing here differentiates.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from tvopt_codegen import symbolic as sx
from tvopt_codegen.derivation import calculus
from tvopt_codegen.runs.side import Side
from tvopt_codegen.spec.constraints import inline_signals


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
        ``|y(t) - y*_B(t)| + sqrt(2 p mu(t) / m_f)`` at those times, ``m_f`` the smallest
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


#: A function of ``(t, y, references)`` returning an array: a vector or a matrix.
Vector = Callable[[float, np.ndarray, list[float]], np.ndarray]

#: The groups of :attr:`_Problem.solver`'s values, in its order.
_F0, _F0_GRAD, _G, _G_GRAD, _DOMAIN, _DOMAIN_GRAD, _A, _A_GRAD = range(8)


@dataclass(frozen=True)
class _Problem:
    """The constrained problem in numbers: the g_i and a_j along a run, all of it for SLSQP.

    Each is one function returning all its values (lambdify's printing and compiling is
    paid per function: one per expression was most of a constrained ``simulate``'s check).

    Attributes
    ----------
    g, a : callable
        The inequalities' ``g_i`` and the equalities' ``a_j`` at ``(t, y, r)``.
    numeric : callable
        Lambdifies expressions of ``(t, y, r)`` the same way (see :func:`_problem`).
    refs_at : callable
        The references' values at a time.
    solver : callable
        Everything SLSQP asks for at ``(t, y, r)``, in one call: the groups numbered
        ``_F0`` to ``_A_GRAD``, matrices as (rows, m).
    prepare : callable
        Lambdifies :attr:`solver`'s function now (else on its first call).
    """

    g: Vector
    a: Vector
    numeric: Callable[..., Vector]
    refs_at: Callable[[float], list[float]]
    solver: Callable[[float, np.ndarray, list[float]], tuple[np.ndarray, ...]]
    prepare: Callable[[], object]


def _problem(model: Any, values: Mapping[sx.Expr, float], references: Any) -> _Problem:
    """Lambdify the problem of :func:`check_run` (signals and parameters substituted)."""
    t = model.t
    signals = {s: e for s, e in model.signals}
    fixed = {q: sx.real(v) for q, v in values.items()}
    arguments = [t, model.y, model.references]

    def numeric(exprs: Sequence[sx.Expr], rows: int | None = None) -> Vector:
        """All of ``exprs`` in one function: an array, ``rows`` x the rest when given."""
        inlined = [inline_signals(e, signals).xreplace(fixed) for e in exprs]
        shape = (len(inlined),) if rows is None else (rows, len(inlined) // max(rows, 1))
        if not inlined:
            return lambda _t, _y, _r: np.zeros(shape)
        function = sx.lambdify(arguments, inlined, "math")
        return lambda time, y, r: np.array(function(time, y, r), dtype=float).reshape(shape)

    def refs_at(time: float) -> list[float]:
        if not model.references or references is None:
            return []
        jets = (references.exact or references.jets)(time)
        return [float(v) for v in jets[:, 0]]

    domain, domain_grad = calculus.objective_domain(model)
    equal = calculus.equality_calculus(model)
    p, q = len(model.constraints), len(model.equalities)
    # What the solver asks for at a point, in the order _F0 .. _A_GRAD, each with its
    # rows when a matrix: f0, its gradient (exact: f0's barriers, the paper's tan, are
    # steep), the g_i and their gradients, f0's domain and its gradient, the a_j and
    # their Jacobian.
    groups: list[tuple[list[sx.Expr], int | None]] = [
        ([calculus.objective_of(model)], None),
        (list(calculus.objective_gradient(model)), None),
        ([c.g for c in model.constraints], None),
        ([e for row in calculus.constraint_gradients(model) for e in row], p),
        (list(domain), None),
        ([e for row in domain_grad for e in row], len(domain)),
        ([c.g for c in model.equalities], None),
        (list(equal.jacobian), q),
    ]
    # Lambdified on first use: not where a side process does the solves.
    everything = functools.cache(lambda: numeric([e for exprs, _ in groups for e in exprs]))
    ends = np.cumsum([0, *(len(exprs) for exprs, _ in groups)])
    m = len(model.y)

    def solver(time: float, y: np.ndarray, r: list[float]) -> tuple[np.ndarray, ...]:
        values = everything()(time, y, r)
        return tuple(
            values[start:end] if rows is None else values[start:end].reshape(rows, m)
            for start, end, (_, rows) in zip(ends[:-1], ends[1:], groups, strict=True)
        )

    return _Problem(
        g=numeric([c.g for c in model.constraints]),
        a=numeric([c.g for c in model.equalities]),
        numeric=numeric,
        refs_at=refs_at,
        solver=solver,
        prepare=everything,
    )


class _AtPoint:
    """The solver's functions of ``y`` at one time: one evaluation of them all per point.

    SLSQP asks for f0, each group of constraints and their gradients one at a time, at
    the same ``y``: one lambdified call each was most of the check's time. Here the last
    point's values are kept, and a new point evaluates every group in one call.
    """

    def __init__(self, problem: _Problem, time: float, r: list[float]) -> None:
        self._problem, self._time, self._r = problem, time, r
        self._key: bytes | None = None
        self._values: tuple[np.ndarray, ...] = ()

    def __call__(self, y: np.ndarray, group: int) -> np.ndarray:
        """Group ``group`` of :attr:`_Problem.solver`'s at ``y`` (a copy: the solver's own)."""
        point = np.asarray(y, dtype=float)
        key = point.tobytes()
        if key != self._key:
            self._values = self._problem.solver(self._time, point, self._r)
            self._key = key
        return self._values[group].copy()


def _minimise(
    problem: _Problem, time: float, r: list[float], s: float, centre: np.ndarray, radius: float
) -> np.ndarray:
    """f0's minimiser subject to ``g_i <= s`` and ``a_j = 0``, by SLSQP near ``centre``.

    The search stays in the box of half-width ``radius`` around ``centre``. Each group of
    constraints is one vector constraint of SLSQP's (its rows in order, as the solver
    stacks them).
    """
    from scipy.optimize import minimize  # noqa: PLC0415 - only simulate needs it

    at = _AtPoint(problem, time, r)
    constraints: list[dict[str, Any]] = []
    if at(centre, _G).size:
        constraints.append(
            {
                "type": "ineq",
                "fun": lambda y: s - at(y, _G),
                "jac": lambda y: -at(y, _G_GRAD),
            }
        )
    if at(centre, _DOMAIN).size:
        constraints.append(
            {
                "type": "ineq",
                "fun": lambda y: at(y, _DOMAIN),
                "jac": lambda y: at(y, _DOMAIN_GRAD),
            }
        )
    if at(centre, _A).size:
        constraints.append(
            {
                "type": "eq",
                "fun": lambda y: at(y, _A),
                "jac": lambda y: at(y, _A_GRAD),
            }
        )
    result = minimize(
        lambda y: float(at(y, _F0)[0]),
        centre,
        jac=lambda y: at(y, _F0_GRAD),
        method="SLSQP",
        bounds=[(c - radius, c + radius) for c in centre],
        constraints=constraints,
        options={"ftol": 1e-15, "maxiter": 1000},
    )
    minimiser: np.ndarray = result.x
    return minimiser


def parameter_values(model: Any, params: Mapping[str, float]) -> dict[sx.Expr, float]:
    """The model's parameters at ``params`` (by name), the others at their defaults."""
    return {q: params.get(q.name, v) for q, v in zip(model.params, model.defaults, strict=True)}


def _values_key(values: Mapping[sx.Expr, float]) -> tuple[tuple[str, float], ...]:
    """``values`` as plain data, to tell a side process which problem is meant."""
    return tuple((sx.text(q), float(v)) for q, v in values.items())


def minimiser_process(model: Any, params: Mapping[str, float]) -> Side:
    """A process that gets :func:`check_run`'s SLSQP solves ready, started now.

    It imports ``scipy.optimize`` and lambdifies the problem at ``params`` (see
    :func:`parameter_values`) while this process integrates the run; :func:`check_run`
    then sends it the solves. A request at other parameter values lambdifies them anew.
    """
    built = parameter_values(model, params)

    def start() -> Callable[[Any], list[np.ndarray]]:
        from scipy.optimize import minimize  # noqa: F401, PLC0415 - why the process is there

        first = _problem(model, built, None)
        first.prepare()
        problems = {_values_key(built): first}

        def solve(request: tuple[Any, list[Any]]) -> list[np.ndarray]:
            key, tasks = request
            if key not in problems:
                names = {sx.text(q): q for q in model.params}
                problems[key] = _problem(model, {names[n]: v for n, v in key}, None)
            return [_minimise(problems[key], *task) for task in tasks]

        return solve

    return Side(start)


def check_run(
    model: Any,
    ts: np.ndarray,
    outputs: np.ndarray,
    to_phi: np.ndarray,
    phi_minimisers: np.ndarray,
    values: Mapping[sx.Expr, float],
    references: Any = None,
    checked: int = 41,
    side: Side | None = None,
) -> RunCheck:
    """Check a run against its constraints (see the module docstring).

    Parameters
    ----------
    model : Model
        With ``constraints``, ``objective`` (the spec's f0), ``mu`` and ``slack``.
    ts, outputs : numpy.ndarray
        Output times (T,) and outputs (m, T) of the run.
    to_phi : numpy.ndarray, shape (T,)
        ``|y(t) - y*_B(t)|``: the distance to the barrier objective's minimiser.
    phi_minimisers : numpy.ndarray, shape (m, T)
        ``y*_B(t)``: where the independent solver starts.
    values : mapping
        Parameter values.
    references : ReferenceSource, optional
        For a spec with references: their values (true ones when known).
    checked : int, optional
        Times at which the constrained minimiser is found (evenly spread, the last one
        the end of the run).
    side : Side, optional
        A :func:`minimiser_process` of the model, which finds them (else, or where it
        fails, they are found here: the same numbers).
    """
    problem = _problem(model, values, references)
    t, numeric, refs_at = model.t, problem.numeric, problem.refs_at
    fixed = {q: sx.real(v) for q, v in values.items()}
    slack_of = sx.lambdify(t, model.slack.xreplace(fixed), "math")
    mu_of = sx.lambdify(t, model.mu.xreplace(fixed), "math")
    slack = np.array([slack_of(float(time)) for time in ts])
    refs = [refs_at(float(time)) for time in ts]

    def along(function: Vector) -> np.ndarray:
        """A vector function's rows at every output time: shape (rows, T)."""
        values = [function(float(time), outputs[:, k], refs[k]) for k, time in enumerate(ts)]
        return np.array(values, dtype=float).reshape(len(ts), -1).T

    margins = slack[None, :] - along(problem.g)
    equality = along(problem.a)
    every = (*model.constraints, *model.equalities)
    end = float(ts[-1])
    at_end = np.concatenate(
        [problem.g(end, outputs[:, -1], refs[-1]), problem.a(end, outputs[:, -1], refs[-1])]
    )
    final = tuple((c.name, float(v)) for c, v in zip(every, at_end, strict=True))
    picks = np.unique(np.linspace(0, len(ts) - 1, checked).round().astype(int))
    hessian = numeric(
        [e for row in calculus.objective_hessian(model) for e in row], rows=len(model.y)
    )

    def smallest(time: float, y: np.ndarray, r: list[float]) -> float:
        return float(np.linalg.eigvalsh(hessian(time, y, r))[0])

    p = len(model.constraints)
    m_f = min(smallest(float(ts[k]), outputs[:, k], refs[k]) for k in picks)
    tasks, gaps = [], []
    for k in picks:
        time = float(ts[k])
        gap = math.sqrt(2.0 * p * mu_of(time) / m_f) if m_f > 0 else math.inf
        # A local solve from the barrier's minimiser, within twice the gap the theory
        # allows: f0 may have other branches (a periodic barrier such as tan), and the
        # constrained minimiser meant is the one of y*_B's branch. A solution on the box
        # is reported: the minimiser was not where the theory puts it.
        radius = 2.0 * gap + 1e-3
        tasks.append((time, refs[k], float(slack[k]), phi_minimisers[:, k], radius))
        gaps.append(gap)
    found = side.ask((_values_key(values), tasks)) if side is not None else None
    if found is None:
        found = [_minimise(problem, *task) for task in tasks]
    distance, bound = [], []
    for k, (*_, centre, radius), result_x, gap in zip(picks, tasks, found, gaps, strict=True):
        on_box = bool(np.any(np.abs(result_x - centre) >= radius * (1 - 1e-9)))
        distance.append(math.inf if on_box else float(np.linalg.norm(outputs[:, k] - result_x)))
        bound.append(float(to_phi[k] + gap))
    lhs = along(numeric([c.lhs for c in every]))
    rhs = along(numeric([c.rhs for c in every]))
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
    jacobian_a : callable
        ``J_a``, shape (q, m).
    curvature : callable
        ``sum_j nu_j grad_yy a_j`` for given ``nu``: ``curvature(t, y, r, nu)``, (m, m);
        zero for affine equalities.
    """

    value: Any
    jacobian_a: Any
    curvature: Any


def equalities(model: Any, values: Mapping[sx.Expr, float]) -> Equalities:
    """Lambdify the equalities of ``model`` (signals and the parameters ``values`` substituted)."""
    signals = {s: e for s, e in model.signals}
    fixed = {q: sx.real(v) for q, v in values.items()}
    m, q = len(model.y), len(model.equalities)

    def numeric(exprs: Sequence[sx.Expr]) -> Any:
        exprs = [inline_signals(e, signals).xreplace(fixed) for e in exprs]
        return sx.lambdify([model.t, model.y, model.references], exprs, "math")

    equal = calculus.equality_calculus(model)
    value = numeric(equal.values)
    j_a = numeric(equal.jacobian)
    second = equal.hessians
    curved = any(entry != 0 for row in second for entry in row)
    hessians = [numeric(row) for row in second] if curved else []

    def curvature(t: float, y: np.ndarray, r: Sequence[float], nu: np.ndarray) -> np.ndarray:
        total = np.zeros((m, m))
        for weight, hessian in zip(nu, hessians, strict=False):
            total += weight * np.array(hessian(t, y, r), dtype=float).reshape(m, m)
        return total

    return Equalities(
        value=lambda t, y, r: np.array(value(t, y, r), dtype=float),
        jacobian_a=lambda t, y, r: np.array(j_a(t, y, r), dtype=float).reshape(q, m),
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
