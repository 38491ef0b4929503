"""The numerical checks of strong convexity.

Newton along ``y*(t)``, the probes of the Hessian (dense, or banded for large teams), and
the constraints' convexity and feasibility. The Hessian's numbers and the linear algebra
on them live in :mod:`tvopt_codegen.derivation.hessians`.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from tvopt_codegen import symbolic as sx
from tvopt_codegen.derivation.calculus import constraint_hessian_entries
from tvopt_codegen.derivation.hessians import (
    _PROBE_BYTES,
    _SPARSE_PROBE,
    _fading_dense,
    _fading_sparse,
    _ObjectiveNumbers,
)
from tvopt_codegen.derivation.model import Model
from tvopt_codegen.derivation.record import Convexity
from tvopt_codegen.errors import AssumptionError
from tvopt_codegen.maths.jet import Program
from tvopt_codegen.maths.numeric import Evaluator
from tvopt_codegen.spec import Constraint
from tvopt_codegen.spec.constraints import Violation

#: A Hessian whose smallest eigenvalue is below this fraction of its scale (the largest
#: eigenvalue met) is degenerate: f0 is not strongly convex there.
DEGENERATE_HESSIAN = 1e-8


#: Times along the horizon at which the minimiser y*(t) is found and checked.
_PATH_POINTS = 25


#: Times along the horizon at which the constraints' feasibility is checked, and the
#: least violation above which nothing satisfies them.
_FEASIBILITY_POINTS = 41
_INFEASIBLE = 1e-7


#: Distances from y*(t) probed for where f0 stops being strongly convex.
_PROBE_DISTANCES = (1.0, 10.0, 100.0)


#: Up to this many outputs the fading probe steps along every axis; beyond, along this
#: many fixed directions.
_PROBE_AXES = 16


def _minimiser_path(
    numbers: _ObjectiveNumbers, starts: np.ndarray, ts: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """``y*(t)`` at every time by damped Newton (all times at once), and which converged.

    Time ``ts[k]`` starts from ``starts[k]``; steps are Newton's where the Hessian is
    positive definite, the gradient's elsewhere, halved until f0 decreases.
    """
    points = len(ts)
    ys = np.array(starts, dtype=float)
    converged = np.zeros(points, dtype=bool)
    with np.errstate(all="ignore"):
        # 40 steps: Newton converges in a few on a strongly convex f0; on a flat minimum
        # ((y - r)**4: linear, by 2/3 a step) they leave a Hessian ~1e-13 of its scale.
        first: np.ndarray | None = None
        value: np.ndarray | None = None
        for _ in range(40):
            grads, newton, usable = numbers.newton(ys, ts)
            norms = np.linalg.norm(grads, axis=1)
            if first is None:
                first = norms
            descent = usable & np.all(np.isfinite(newton), axis=1)
            descent &= np.einsum("pi,pi->p", grads, newton) > 0
            steps = np.where(descent[:, None], newton, grads)
            size = np.linalg.norm(steps, axis=1)
            converged = size <= 1e-10 * (1.0 + np.linalg.norm(ys, axis=1))
            # Located: the step vanished, or the gradient fell by eight orders.
            converged |= norms <= 1e-8 * first
            if converged.all():
                break
            if value is None:
                value = numbers.value(ys, ts)
            # The full steps, then all halvings (2^-1 .. 2^-29) of the points they did not
            # improve in one call: 30 calls where a point cannot improve (out of the domain).
            full = numbers.value(ys - steps, ts)
            scale, reached = np.ones(points), full
            accepted = converged | (full < value)
            todo = np.flatnonzero(~accepted)
            if todo.size:
                halvings = 0.5 ** np.arange(1, 30)[:, None, None]
                trial = (ys[todo] - halvings * steps[todo]).reshape(-1, ys.shape[1])
                values = numbers.value(trial, np.tile(ts[todo], 29)).reshape(29, -1)
                better = values < value[todo]
                level, accepted[todo] = better.argmax(axis=0), better.any(axis=0)
                scale[todo] = np.where(accepted[todo], halvings[level, 0, 0], 1.0)
                reached[todo] = values[level, np.arange(todo.size)]
            if not (accepted & ~converged).any():
                break  # no point moves any more
            ys = np.where(accepted[:, None], ys - scale[:, None] * steps, ys)
            value = np.where(accepted, reached, value)  # f0 there was met on the way
    return ys, converged


def _check_convexity(
    model: Model,
    polynomial: sx.Expr | None,
    program: Program,
    gradient: Sequence[sx.Expr],
    entries: Sequence[tuple[tuple[int, int], sx.Expr]],
    y0: Sequence[float],
    t_final: float,
    source: str,
) -> tuple[Convexity, tuple[str, ...]]:
    """Check the strong convexity of f0 where it matters; return the evidence and warnings.

    ``program`` computes ``gradient`` and the Hessian's lower triangle ``entries``;
    ``polynomial`` is the Hessian's symbolic form when f0 is polynomial in ``y`` (then a
    Hessian free of ``y``, t and the signals is checked exactly at the parameters'
    defaults). Otherwise the Hessian is sampled near the initial outputs and along the
    minimiser ``y*(t)`` over the horizon (found by Newton's method), where the
    theorem's bound lives: a Hessian that degenerates on ``y*`` (``(y - r)**4``) is
    refused, and one that fades away from ``y*`` (``log cosh``) gives a warning.
    """
    defaults = {q: float(v) for q, v in zip(model.params, model.defaults, strict=True)}
    m = len(model.y)
    warnings: list[str] = []
    if polynomial is not None and polynomial.free_symbols <= defaults.keys():
        fixed = Evaluator(defaults)
        matrix = np.array([[fixed(polynomial[i, j]) for j in range(m)] for i in range(m)])
        if not np.all(np.isfinite(matrix)):
            raise AssumptionError(
                source,
                "objective.f0",
                "the Hessian of f0 is not finite at the parameters' defaults (does a "
                "parameter divide by zero?)",
            )
        m_f = float(np.linalg.eigvalsh(np.real(matrix)).min())
        result = Convexity("constant Hessian", m_f, 1)
    else:
        numbers = _ObjectiveNumbers(model, program, gradient, entries, defaults)
        rng = np.random.default_rng(7)
        points = 24
        ys = np.asarray(y0) + rng.uniform(-0.1, 0.1, size=(points, m))
        ts = rng.uniform(0.0, t_final, size=points)
        if model.constraints:
            # The barrier objective lives on {g_i < s(t)}: outside it the log is undefined,
            # and the barrier term's curvature, still finite there, is negative. A sample
            # outside says nothing about the law, which never goes there.
            with np.errstate(all="ignore"):
                inside = np.isfinite(numbers.value(ys, ts))
            ys, ts = ys[inside], ts[inside]
        low, high = numbers.extremes(ys, ts) if len(ts) else (np.empty(0), np.empty(0))
        path_ts = np.linspace(0.0, t_final, _PATH_POINTS)
        path, converged = _continued_path(numbers, np.asarray(y0, dtype=float), path_ts)
        path_low, path_high = numbers.extremes(path, path_ts)
        path_low = np.where(converged, path_low, np.nan)
        finite = np.isfinite(low).sum() + np.isfinite(path_low).sum()
        if not finite:
            raise AssumptionError(
                source,
                "objective.f0",
                f"the Hessian of {_named(model)} is not finite at any of {points} points near "
                "the initial outputs (overflow or outside its domain), so strong convexity "
                "cannot be checked",
            )
        # Degenerate against the Hessian's scale. Without constraints, the largest
        # eigenvalue met anywhere: a minimum flat in every direction, (y - r)**4, has a
        # Hessian near 0 at y*(t) against 12 (y - r)**2 elsewhere. With them, against the
        # Hessian at the point itself: the barrier's curvature near the start, steep
        # without bound at the domain's edge, must not make a minimum with curvature 2
        # look flat (the barrier, positive where it acts, cannot hide a flat f0 there).
        if model.constraints:
            scales = np.maximum(path_high, 1e-300)
        else:
            scales = np.full(
                len(path_ts), float(np.nanmax(np.concatenate([high, path_high, [0.0]])))
            )
        ratio = np.where(converged, path_low / scales, np.nan)
        if converged.any() and np.nanmin(ratio) <= DEGENERATE_HESSIAN:
            worst = int(np.nanargmin(ratio))
            where = ", ".join(
                f"{y.name} = {value:.6g}" for y, value in zip(model.y, path[worst], strict=True)
            )
            field, cause = _culprit(model, path[worst], float(path_ts[worst]))
            if field == "objective.f0":
                flat = "a flat minimum such as (y - r)**4: the law divides by it"
                cause = flat if model.objective is None else f"{cause}; {flat}"
            raise AssumptionError(
                source,
                field,
                f"{_named(model)} is not strongly convex at its minimiser: at t = "
                f"{path_ts[worst]:.6g}, y*(t) = ({where}), the Hessian's smallest eigenvalue "
                f"is {path_low[worst]:.3g}, below {DEGENERATE_HESSIAN:g} of its scale "
                f"{scales[worst]:.3g} ({cause})",
            )
        warnings += _fading_convexity(numbers, path, path_ts, path_low, converged)
        all_low = np.concatenate([low, path_low])
        m_f = float(np.nanmin(all_low))
        result = Convexity("sampled near y(0) and along y*(t)", m_f, int(finite))
        if not m_f > 0:
            index = int(np.nanargmin(all_low))
            at_y = np.concatenate([ys, path])[index]
            at_t = float(np.concatenate([ts, path_ts])[index])
            field, cause = _culprit(model, at_y, at_t)
            where = ", ".join(f"{y.name} = {v:.6g}" for y, v in zip(model.y, at_y, strict=True))
            raise AssumptionError(
                source,
                field,
                f"{_named(model)} is not strongly convex in the outputs: at t = {at_t:.6g}, "
                f"y = ({where}), the Hessian has eigenvalue {m_f:.6g} <= 0 ({cause})",
            )
    if not result.m_f > 0:
        raise AssumptionError(
            source,
            "objective.f0",
            "f0 is not strongly convex in the outputs: the Hessian has eigenvalue "
            f"{result.m_f:.6g} <= 0 (the method needs grad_yy f0 positive definite)",
        )
    return result, tuple(warnings)


def _named(model: Model) -> str:
    """What the law's objective is called in a message: f0, or the barrier objective."""
    return "the barrier objective B = f0 - mu sum log(s - g_i)" if model.constraints else "f0"


def _culprit(model: Model, y: np.ndarray, t: float) -> tuple[str, str]:
    """The field to blame for a Hessian that is not positive at ``(y, t)``, and why.

    Without constraints, f0. With them, f0 alone is evaluated there: when its own Hessian
    is positive definite, the barrier's term is what fails, and the constraints are named.
    """
    if model.objective is None:
        return "objective.f0", "the method needs grad_yy f0 positive definite"
    hessian = _hessian(model.objective, model.y)
    evaluate = _evaluator_at(model, np.asarray(y, dtype=float)[None, :], np.array([t]))
    m = len(model.y)
    with np.errstate(all="ignore"):
        matrix = np.array(
            [[float(np.ravel(evaluate(hessian[i][j]))[0]) for j in range(m)] for i in range(m)]
        )
    if not np.all(np.isfinite(matrix)):
        return "objective.f0", "f0's own Hessian is not finite there"
    eigenvalues = np.linalg.eigvalsh(0.5 * (matrix + matrix.T))
    if eigenvalues[0] > DEGENERATE_HESSIAN * max(abs(eigenvalues[-1]), 1e-300):
        names = ", ".join(c.name for c in model.constraints)
        return (
            "constraints",
            f"f0 alone is strongly convex there, eigenvalue {eigenvalues[0]:.3g}: the "
            f"barrier term of the constraints {names} is what fails",
        )
    return "objective.f0", f"f0's own Hessian has eigenvalue {eigenvalues[0]:.3g} there"


def _hessian(f: sx.Expr, variables: Sequence[sx.Expr]) -> list[list[sx.Expr]]:
    """The Hessian of ``f``, rows of entries: ``f.diff(v_i).diff(v_j)``, as ``sympy.hessian``.

    The upper triangle is differentiated, in SymPy's order, and mirrored.
    """
    n = len(variables)
    out: list[list[sx.Expr]] = [[sx.ZERO] * n for _ in range(n)]
    for i in range(n):
        first = f.diff(variables[i])
        for j in range(i, n):
            out[i][j] = out[j][i] = first.diff(variables[j])
    return out


def _continued_path(
    numbers: _ObjectiveNumbers, y0: np.ndarray, ts: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """``y*(t)`` at every time from ``y0``; where that fails, from the nearest one found.

    A start outside the barrier's domain at a later time (the slack shrinks) leaves
    Newton nowhere to go; the minimiser found at a neighbouring time is inside.
    """
    path, converged = _minimiser_path(numbers, np.tile(y0, (len(ts), 1)), ts)
    for _ in range(len(ts)):
        if converged.all() or not converged.any():
            break
        done = np.flatnonzero(converged)
        todo = np.flatnonzero(~converged)
        nearest = done[np.abs(ts[done][None, :] - ts[todo][:, None]).argmin(axis=1)]
        again, ok = _minimiser_path(numbers, path[nearest], ts[todo])
        if not ok.any():
            break
        path[todo[ok]] = again[ok]
        converged[todo[ok]] = True
    return path, converged


def _probe_directions(m: int) -> np.ndarray:
    """The directions in which :func:`_fading_convexity` steps away from ``y*``.

    Each axis both ways while there are at most :data:`_PROBE_AXES` outputs; beyond,
    :data:`_PROBE_AXES` fixed directions of +-1 entries (all ones, alternating signs, and
    seeded random signs, each with its opposite), so that every output moves by the
    probe's distance in every direction: the cost stays that of :data:`_PROBE_AXES`
    Hessians per point however many outputs there are (per axis it grew as m^4).
    """
    if m <= _PROBE_AXES:
        return np.concatenate([np.eye(m), -np.eye(m)])
    rng = np.random.default_rng(14)
    half = [np.ones(m), np.resize([1.0, -1.0], m)]
    half += [rng.choice([-1.0, 1.0], size=m) for _ in range(_PROBE_AXES // 2 - 2)]
    return np.concatenate([np.array(half), -np.array(half)])


def _fading_convexity(
    numbers: _ObjectiveNumbers,
    path: np.ndarray,
    ts: np.ndarray,
    path_low: np.ndarray,
    converged: np.ndarray,
) -> list[str]:
    """A warning when f0 is strongly convex near y*(t) only (its Hessian fades away)."""
    count, m = path.shape
    probes = [(d, direction) for d in _PROBE_DISTANCES for direction in _probe_directions(m)]
    # Every probe point in one array, evaluated in chunks of at most _PROBE_BYTES of
    # Hessians: the evaluator's cost is per expression, not per point.
    points = np.concatenate([path + d * direction for d, direction in probes])
    times = np.tile(ts, len(probes))
    reference = np.tile(path_low, len(probes))
    candidates = np.tile(converged, len(probes))
    # Fading, not turning negative: a barrier's periodic branches beyond its domain
    # (tan**2) are not where the outputs can go.
    if m > _SPARSE_PROBE:
        fading = _fading_sparse(numbers, points, times, 1e-6 * reference, candidates)
        if not fading.any():
            return []
        at = int(np.argmax(fading))
        low = np.full(len(points), np.nan)
        low[at] = numbers.extremes(points[None, at], times[None, at])[0][0]
    else:
        # The first fading point in the probes' order is the one named: the chunks are
        # taken in that order, and the search stops at the first chunk that has one.
        chunk = max(count, _PROBE_BYTES // (8 * m * m))
        for start in range(0, len(points), chunk):
            part = slice(start, start + chunk)
            values = numbers.hessian_entries(points[part], times[part])
            found, found_low = _fading_dense(
                numbers.gershgorin, numbers._dense, values, 1e-6 * reference[part], candidates[part]
            )
            if found.any():
                fading = np.zeros(len(points), dtype=bool)
                fading[part] = found
                low = np.full(len(points), np.nan)
                low[part] = found_low
                break
        else:
            return []
    at = int(np.argmax(fading))  # the first in the order distance, direction, time
    distance, when = probes[at // count][0], ts[at % count]
    return [
        "objective.f0: f0 is strongly convex only near its minimiser: at distance "
        f"{distance:g} "
        f"from y*(t) (t = {when:.6g}) the Hessian's smallest eigenvalue is "
        f"{low[at]:.3g}, against {reference[at]:.3g} at y*; the certificate's "
        "bound holds only while the outputs stay where it is bounded below"
    ]


def nonconvex(
    constraints: Sequence[Constraint],
    outputs: Sequence[sx.Expr],
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
        matrices = np.zeros((points, m, m))
        for i, j, second in constraint_hessian_entries(sx.sympify(constraint.g), tuple(outputs)):
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


def _constraint_convexity(model: Model, y0: np.ndarray) -> tuple[str, ...]:
    """Refuse a constraint that is not convex in the outputs, unless the spec allows it.

    Each ``g_i``'s Hessian in ``y`` is sampled around the initial outputs over the
    horizon (signals and nominal references at their values there; references without
    one at 0).
    """
    if not model.constraints:
        return ()
    rng = np.random.default_rng(18)
    points = 64
    ys = y0[None, :] + rng.uniform(-2.0, 2.0, size=(points, len(y0)))
    settings = model.settings
    evaluate = _evaluator_at(model, ys, rng.uniform(0.0, settings.t_final, size=points))
    _feasible_over_the_horizon(model, y0)
    found = nonconvex(model.constraints, model.y, evaluate, points)
    if not found:
        return ()
    names = ", ".join(f"{name} (Hessian eigenvalue {value:.3g})" for name, value in found)
    if not settings.allow_nonconvex:
        raise AssumptionError(
            settings.source,
            f"constraints.{found[0][0]}",
            f"not convex in the outputs: {names}; the barrier method needs convex "
            "inequalities (set allow_nonconvex = true to accept a local certificate)",
        )
    return (f"constraints not convex in the outputs: {names}; the certificate is local only",)


def _evaluator_at(model: Model, ys: np.ndarray, ts: np.ndarray) -> Evaluator:
    """Numbers for expressions in the outputs and t at points (one row of ``ys`` each).

    Parameters at their defaults, signals and nominal references defined (references
    without one at 0).
    """
    values: dict[sx.Expr, Any] = {y: ys[:, i] for i, y in enumerate(model.y)}
    values[model.t] = ts
    values |= {q: float(v) for q, v in zip(model.params, model.defaults, strict=True)}
    nominal = dict(model.nominal)
    values |= {r: 0.0 for r in model.references if r not in nominal}
    evaluate = Evaluator(values)
    for symbol, expr in nominal.items():
        evaluate.define(symbol, expr)
    for symbol, expr in model.signals:
        evaluate.define(symbol, expr)
    return evaluate


def _feasible_over_the_horizon(model: Model, y0: np.ndarray) -> None:
    """Refuse constraints that no output satisfies at some time of the horizon.

    The least violation is found at :data:`_FEASIBILITY_POINTS` times (each search
    starting where the last one ended), the first infeasible stretch's edges refined by
    bisection, and the constraint named when it alone holds nowhere there.
    """
    violation = Violation(model)
    t_final = model.settings.t_final
    times = np.linspace(0.0, t_final, _FEASIBILITY_POINTS)
    worst = np.empty(len(times))
    point = np.asarray(y0, dtype=float)
    for k, t in enumerate(times):
        worst[k], point = violation.least(float(t), point)
    bad = worst > _INFEASIBLE
    if not bad.any():
        return
    first = int(np.argmax(bad))
    last = first
    while last + 1 < len(times) and bad[last + 1]:
        last += 1
    start = (
        float(times[first]) if first == 0 else _edge(violation, y0, times[first - 1], times[first])
    )
    end = (
        float(times[last])
        if last == len(times) - 1
        else _edge(violation, y0, times[last + 1], times[last])
    )
    peak = first + int(np.argmax(worst[first : last + 1]))
    alone = [
        name
        for i, name in enumerate(violation.names)
        if violation.least(float(times[peak]), np.asarray(y0, dtype=float), only=i)[0] > _INFEASIBLE
    ]
    if last == len(times) - 1:
        span = f"from t = {start:.4g} to the horizon's end t = {t_final:g}"
    else:
        span = f"for t in [{start:.4g}, {end:.4g}] of the horizon [0, {t_final:g}]"
    least = f"the least violation found is {worst[peak]:.3g}, at t = {times[peak]:.4g}"
    if len(alone) == 1:
        raise AssumptionError(
            model.source,
            f"constraints.{alone[0]}",
            f"infeasible {span}: no output satisfies it there ({least})",
        )
    raise AssumptionError(
        model.source,
        "constraints",
        f"infeasible {span}: every output violates a constraint there ({least})",
    )


def _edge(violation: Violation, y0: np.ndarray, feasible: float, infeasible: float) -> float:
    """Where feasibility ends between two times, by bisection (to 1e-4 of the interval)."""
    low, high = float(feasible), float(infeasible)
    point = np.asarray(y0, dtype=float)
    for _ in range(14):
        middle = 0.5 * (low + high)
        value, found = violation.least(middle, point)
        if value > _INFEASIBLE:
            high = middle
        else:
            low, point = middle, found
    return high
