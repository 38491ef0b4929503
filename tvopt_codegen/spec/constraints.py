"""Time-varying inequality constraints by an interior-point homotopy.

A spec's ``[constraints]`` ``g_i(y, t) <= 0`` (each convex in ``y``) turn the objective
into (Fazlyab, Paternain, Preciado and Ribeiro, "Prediction-correction interior-point
method for time-varying convex optimization", IEEE TAC 2018)::

    B(y, t) = f0(y, t) - mu(t) * sum_i log(s(t) - g_i(y, t))
    mu(t) = mu_inf + (mu_0 - mu_inf) exp(-rate t),   s(t) = s_0 exp(-rate t)

``B`` is time-varying and strongly convex in ``y`` on its domain (``f0`` is, and each
``-log(s - g_i)`` is convex where ``g_i`` is), so the paper's law applies to it unchanged,
with ``mu`` and ``s`` differentiated exactly like any signal. What follows, and what
``simulate`` checks on every run:

- ``E_B(t) = expm(H t) E_B(0)``: the theorem, for ``B``;
- ``g_i(y(t), t) < s(t)`` at every instant: ``grad B`` is finite along the run (the law
  keeps it on ``expm(H t) E(0)``), and it is infinite on the barrier;
- the distance to the constrained minimiser ``y*_s(t)`` of ``f0`` subject to
  ``g_i <= s(t)``: ``f0(y*_B) - f0(y*_s) <= p mu`` (the barrier's duality gap for ``p``
  inequalities), and with ``f0`` ``m_f``-strongly convex, ``|y*_B - y*_s| <=
  sqrt(2 p mu / m_f)``; so ``|y(t) - y*_s(t)| <= |y(t) - y*_B(t)| + sqrt(2 p mu(t) / m_f)``.

The slack lets the run start outside the constraints: ``s(0)`` exceeds the largest initial
violation, and ``s`` decays to 0 at the barrier's rate.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from fractions import Fraction
from typing import Any

import numpy as np

from tvopt_codegen import symbolic as sx
from tvopt_codegen.spec import Barrier, Constraint

#: The slack's start above the largest initial violation: twice it, plus this.
SLACK_MARGIN = 0.1


def inline_signals(expr: sx.Expr, signals: Mapping[sx.Expr, sx.Expr]) -> sx.Expr:
    """``expr`` with every signal replaced by its definition, signals of signals too."""
    expr = sx.sympify(expr)
    for _ in range(len(signals) + 1):
        if not expr.free_symbols & signals.keys():
            break
        expr = expr.xreplace(signals)
    return expr


def _exact(value: float) -> sx.Expr:
    """``value`` as an exact number: SymPy's ``nsimplify`` on SymPy, else its decimal.

    ``nsimplify`` finds the simplest number within the double's precision (``1/3`` for
    0.333...); SymEngine has none, and the double's shortest decimal as a rational
    (:mod:`tvopt_codegen.spec.parse` reads literals so) agrees with it to that precision.
    """
    if not sx.SYMENGINE:
        import sympy  # noqa: PLC0415 - the SymPy engine's own; loaded with it already

        return sympy.nsimplify(value)
    exact = Fraction(repr(float(value)))
    return sx.Rational(exact.numerator, exact.denominator)


def schedule(barrier: Barrier, slack: float, t: sx.Expr) -> tuple[sx.Expr, sx.Expr]:
    """``mu(t)`` and ``s(t)`` as expressions in ``t`` (exact: they are differentiated)."""
    decay = sx.exp(-_exact(barrier.rate) * t)
    mu_inf = _exact(barrier.final_weight)
    mu = mu_inf + (_exact(barrier.initial_weight) - mu_inf) * decay
    return mu, _exact(slack) * decay


def initial_slack(
    constraints: Sequence[Constraint],
    barrier: Barrier,
    values: Mapping[sx.Expr, sx.Expr],
) -> float:
    """``s(0)``: given, or 0 for a strictly feasible start, else above the violation.

    ``values`` holds the outputs, signals, references, parameters and ``t`` at the start.
    """
    if barrier.initial_slack is not None:
        return barrier.initial_slack
    worst = max(float(sx.sympify(c.g).xreplace(dict(values))) for c in constraints)
    return 0.0 if worst < 0 else 2.0 * worst + SLACK_MARGIN


def barrier_objective(
    f0: sx.Expr, constraints: Sequence[Constraint], mu: sx.Expr, slack: sx.Expr
) -> sx.Expr:
    """``B = f0 - mu sum_i log(s - g_i)``."""
    return f0 - mu * sx.Add(*(sx.log(slack - c.g) for c in constraints))


def _violated_outside_domain(g: Any) -> Any:
    """``g``, infinitely violated where it is undefined, alike on both engines.

    SymPy's math-module lambdify raises outside a function's domain and SymEngine's
    compiled one gives NaN, which compares false both ways and would pass for feasible.
    """

    def value(y: Any, t: float) -> float:
        try:
            found = float(g(y, t))
        except (ValueError, ZeroDivisionError, OverflowError):
            return math.inf
        return found if math.isfinite(found) else math.inf

    return value


class Violation:
    """``min_y max_i g_i(y, t)`` (on the equalities) at any time, and per constraint.

    The constraints are turned into functions of ``(y, t)`` once (signals and nominal
    references inlined, references without one at 0, parameters at their defaults), so
    that the horizon can be scanned at many times for the price of one compilation.
    """

    def __init__(self, model: Any) -> None:
        at = {q: sx.real(v) for q, v in zip(model.params, model.defaults, strict=True)}
        nominal = dict(model.nominal)
        fixed = {r: nominal.get(r, sx.ZERO) for r in model.references}
        signals = dict(model.signals)
        self.names = tuple(c.name for c in model.constraints)
        self.m = len(model.y)

        def function(constraint: Any) -> Any:
            expr = inline_signals(constraint.g, signals).xreplace(fixed).xreplace(at)
            return _violated_outside_domain(sx.lambdify([model.y, model.t], expr, "math"))

        self.functions = [function(c) for c in model.constraints]
        self.equal = [function(c) for c in model.equalities]

    def least(self, t: float, y0: np.ndarray, only: int | None = None) -> tuple[float, np.ndarray]:
        """``min_y max_i g_i(y, t)`` from ``y0`` and where it is (``only``: that one alone).

        By SLSQP, as ``min z`` subject to ``g_i(y, t) <= z`` and the equalities. When
        ``y0`` is feasible itself, its ``max_i g_i`` (at most 0) is returned without a
        search: that answers the question asked, whether anything is.
        """
        m = self.m
        functions = self.functions if only is None else [self.functions[only]]
        equal = self.equal if only is None else []
        at_start = max(f(y0, t) for f in functions)
        if at_start <= 0 and all(f(y0, t) == 0 for f in equal):
            return float(at_start), y0
        from scipy.optimize import minimize  # noqa: PLC0415 - only for an infeasible start

        constraints = [
            {"type": "ineq", "fun": lambda v, f=f: v[m] - f(v[:m], t)} for f in functions
        ] + [{"type": "eq", "fun": lambda v, f=f: f(v[:m], t)} for f in equal]

        def search(point: np.ndarray) -> tuple[float, np.ndarray]:
            start = np.append(point, max(f(point, t) for f in functions) + 1.0)
            result = minimize(
                lambda v: v[m],
                start,
                method="SLSQP",
                constraints=constraints,
                options={"ftol": 1e-12, "maxiter": 500},
            )
            return float(max(f(result.x[:m], t) for f in functions)), result.x[:m]

        best = search(np.asarray(y0, dtype=float))
        if best[0] <= 0:
            return best
        # Nothing found from y0: it may be a stationary point of a non-convex constraint
        # (the centre of y1**2 + y2**2 >= r**2), where the search cannot move. A few
        # starts around it, a step of the outputs' own scale along each axis, decide.
        step = 0.1 * (1.0 + np.abs(np.asarray(y0, dtype=float)))
        for axis in range(m):
            for sign in (1.0, -1.0):
                point = np.array(y0, dtype=float)
                point[axis] += sign * step[axis]
                found = search(point)
                if found[0] < best[0]:
                    best = found
                if best[0] <= 0:
                    return best
        return best
