"""The target ``y*(t)``, found independently of the law.

Damped Newton on f0 (and on the KKT map with equality constraints), followed backward
from the end of the horizon: never read off the controller.
"""

from __future__ import annotations

import types
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np

from tvopt_codegen.limits import START_ITERATIONS
from tvopt_codegen.renderer.runtime import NEWTON
from tvopt_codegen.simulation.direct import point_function


class _AtOnePoint:
    """A module's ``objective``, ``gradient`` and ``hessian`` with ``params`` bound.

    Called as the module's own (``f(t, y, params, **extra)``, the ``params`` given then
    ignored), by :func:`~tvopt_codegen.simulation.direct.point_function`: the module's
    numbers to the bit, and its errors, without its checks of the arguments on every
    call, which were most of a Newton iteration's cost for a small spec.
    """

    def __init__(self, controller: types.ModuleType, params: Mapping[str, float] | None):
        self._functions = {
            name: point_function(controller, name, params)
            for name in ("objective", "gradient", "hessian")
        }

    def objective(self, t: float, y: np.ndarray, params: Any = None, **extra: Any) -> Any:
        """f0 at ``(t, y)``."""
        return self._functions["objective"](t, y, **extra)

    def gradient(self, t: float, y: np.ndarray, params: Any = None, **extra: Any) -> Any:
        """The gradient of f0 at ``(t, y)``."""
        return self._functions["gradient"](t, y, **extra)

    def hessian(self, t: float, y: np.ndarray, params: Any = None, **extra: Any) -> Any:
        """The Hessian of f0 at ``(t, y)``."""
        return self._functions["hessian"](t, y, **extra)


#: What the Newton iterations below evaluate f0 by: a module, or its one-point functions.
_Objective = types.ModuleType | _AtOnePoint


def minimizer_path(
    controller: types.ModuleType,
    ts: np.ndarray,
    start: np.ndarray,
    params: Mapping[str, float] | None,
    refs: Callable[[float], dict[str, Any]] | None = None,
    inside: np.ndarray | None = None,
    quadratic: bool = False,
) -> np.ndarray:
    """``y*(t) = argmin_y f0(y, t)`` at each time, by a damped Newton method.

    The path is followed backward in time from ``start`` (the final output),
    warm-starting every time from the previous one, with Armijo backtracking and steps
    capped at ``NEWTON.step_cap``. For strongly convex f0 this is the unique minimizer
    whatever the start. A barrier that is finite only on a domain (``tan^2`` in the paper's Sec.
    V-B) is periodic, with its global minimizer beyond the barrier: continuation from
    the converged end of the run stays on the in-domain branch the paper means.

    Parameters
    ----------
    controller : module
        A generated module (its ``objective``, ``gradient`` and ``hessian``).
    ts : numpy.ndarray
        Increasing output times.
    start : numpy.ndarray
        Starting point at ``ts[-1]``.
    params : mapping or None
        Parameter overrides (None: the defaults).
    refs : callable, optional
        ``refs(t)``: the keyword arguments that give the module the reference jets at
        ``t`` (for a spec with references).
    inside : numpy.ndarray, shape (m, T), optional
        A point of f0's domain at each time (the run's outputs): the start whenever the
        warm start has left the domain (a barrier of moving constraints).
    quadratic : bool
        f0 is quadratic in y (its Hessian a constant matrix): then one Newton step from
        any point is the minimizer, up to rounding, which a second step removes. No
        continuation, line search or cap is needed, and each time costs two steps where
        the general path takes five substeps of several (most of a small ``simulate``).

    Returns
    -------
    numpy.ndarray, shape (m, T)
        ``y*`` at each time.
    """
    functions = _AtOnePoint(controller, params)
    if quadratic:
        return _quadratic_path(functions, ts, start, params, refs)

    def step(t: float, y: np.ndarray, index: int, budget: int) -> np.ndarray:
        extra = (refs or (lambda t: {}))(t)
        if inside is not None and not _defined(functions, t, y, params, extra):
            y = np.array(inside[:, index], dtype=float)
        solved = _newton(functions, t, y, params, extra, budget)
        assert solved is not None
        return solved

    def jump(t: float, y: np.ndarray) -> np.ndarray | None:
        extra = (refs or (lambda t: {}))(t)
        if not _defined(functions, t, y, params, extra):
            return None
        return _newton(functions, t, y, params, extra, NEWTON.iterations, strict=True)

    return _backward(ts, start, step, jump)


def _quadratic_path(
    controller: _Objective,
    ts: np.ndarray,
    start: np.ndarray,
    params: Mapping[str, float] | None,
    refs: Callable[[float], dict[str, Any]] | None,
) -> np.ndarray:
    """``y*`` of an f0 quadratic in y: two full Newton steps at each time, from the last."""
    path = np.empty((len(start), len(ts)))
    y = np.array(start, dtype=float)
    for index in range(len(ts) - 1, -1, -1):
        t = float(ts[index])
        extra = (refs or (lambda t: {}))(t)
        hessian = controller.hessian(t, y, params, **extra)
        for _ in range(2):
            y = y - np.linalg.solve(hessian, controller.gradient(t, y, params, **extra))
        path[:, index] = y
    return path


def _backward(
    ts: np.ndarray,
    start: np.ndarray,
    step: Callable[[float, np.ndarray, int, int], np.ndarray],
    jump: Callable[[float, np.ndarray], np.ndarray | None] | None = None,
) -> np.ndarray:
    """Follow a solution backward in time from ``start`` at ``ts[-1]``, warm-starting.

    ``step(t, w, index, budget)`` solves at time ``t`` from ``w`` (``index``: the output
    time being approached) in at most ``budget`` iterations; five substeps lie between
    output times. The first point may start far from the solution (a run that has not
    converged): its capped steps get :data:`START_ITERATIONS`, the warm starts NEWTON.iterations.

    ``jump(t, w)``, when given, is tried first at each output time, from the last two
    solutions' linear extrapolation: a solve that answers None unless it stayed where
    Newton's method converges by itself (no step capped or cut back), and so reaches
    the same solution the substeps would. Where it answers None the substeps run.
    """
    substeps = 5
    path = np.empty((len(start), len(ts)))
    w = np.array(start, dtype=float)
    for index in range(len(ts) - 1, -1, -1):
        later = ts[min(index + 1, len(ts) - 1)]
        if jump is not None and index < len(ts) - 2:
            slope = (path[:, index + 2] - w) / (ts[index + 2] - later)
            found = jump(float(ts[index]), w + slope * (ts[index] - later))
            if found is not None:
                w = found
                path[:, index] = w
                continue
        for t in (
            np.linspace(later, ts[index], substeps + 1)[1:] if index < len(ts) - 1 else [ts[-1]]
        ):
            budget = NEWTON.iterations if index < len(ts) - 1 else START_ITERATIONS
            w = step(float(t), w, index, budget)
        path[:, index] = w
    return path


def _defined(
    controller: _Objective,
    t: float,
    y: np.ndarray,
    params: Mapping[str, float] | None,
    extra: Mapping[str, Any],
) -> bool:
    """Whether f0 is finite at ``y`` and ``t``."""
    try:
        return bool(np.isfinite(controller.objective(t, y, params, **extra)))
    except ArithmeticError:
        return False


def _newton(
    controller: _Objective,
    t: float,
    y: np.ndarray,
    params: Mapping[str, float] | None,
    extra: Mapping[str, Any] | None = None,
    iterations: int = NEWTON.iterations,
    strict: bool = False,
) -> np.ndarray | None:
    """Minimize f0(., t) from ``y``: damped Newton with capped steps.

    ``strict``: None instead of a damped or capped step, a gradient step, or no
    convergence within ``iterations`` (the caller then takes the careful way).
    """
    extra = extra or {}
    # f0 where the line search stopped is f0 at the next iterate: no second evaluation.
    value = None
    for _ in range(iterations):
        grad = controller.gradient(t, y, params, **extra)
        hess = controller.hessian(t, y, params, **extra)
        try:
            step = np.linalg.solve(hess, grad)
        except np.linalg.LinAlgError:
            if strict:
                return None
            step = grad
        if strict:
            size = float(np.linalg.norm(step))
            if size <= NEWTON.stop * (1.0 + float(np.linalg.norm(y))):
                return y - step  # converged: f0's decrease would be below its rounding
            if grad @ step <= 0 or size > NEWTON.step_cap:
                return None
        if grad @ step <= 0:  # not a descent direction: fall back to the gradient
            step = grad
        size = float(np.linalg.norm(step))
        if size > NEWTON.step_cap:
            step = step * (NEWTON.step_cap / size)
        if value is None:
            value = controller.objective(t, y, params, **extra)
        scale = 1.0
        accepted = None
        while scale > NEWTON.smallest_scale:
            trial = y - scale * step
            try:
                trial_value = controller.objective(t, trial, params, **extra)
            except ArithmeticError:
                trial_value = np.inf
            descent = grad @ step
            noise = NEWTON.rounding * abs(value)
            if np.isfinite(trial_value) and (
                trial_value <= value - NEWTON.armijo * scale * descent
                # A whole step whose decrease is below f0's rounding cannot be judged
                # by it: the last step of Newton's method, taken (backtracking would
                # shrink it until the scale ran out, leaving y short of y*).
                or (scale == 1.0 and descent <= noise and trial_value <= value + noise)
            ):
                accepted = trial_value
                break
            if strict:
                return None
            scale *= NEWTON.shrink
        y = y - scale * step
        value = accepted
        if size * scale <= NEWTON.stop * (1.0 + float(np.linalg.norm(y))):
            return y
    return None if strict else y


def _kkt_newton(
    controller: types.ModuleType,
    eq: Any,
    t: float,
    w: np.ndarray,
    params: Mapping[str, float] | None,
    extra: Mapping[str, Any],
    iterations: int = NEWTON.iterations,
    strict: bool = False,
) -> np.ndarray | None:
    """Solve the KKT system ``F(y, nu, t) = 0`` from ``w = (y, nu)``: damped Newton.

    ``F = [grad f0 + J_a^T nu; a]`` (f0's gradient and Hessian from the module, the
    equalities from ``eq``, :func:`tvopt_codegen.simulation.constraints.equalities`), backtracking
    on ``|F|^2`` within f0's domain, the outputs' steps capped at NEWTON.step_cap like
    :func:`_newton`'s. ``strict``: as :func:`_newton`'s, None unless every step is whole.
    """
    from tvopt_codegen.simulation.constraints import kkt_matrix  # noqa: PLC0415

    m = len(controller.OUTPUT_NAMES)
    r = _reference_values(extra)

    def residual(point: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        y, nu = point[:m], point[m:]
        try:
            grad = controller.gradient(t, y, params, **extra)
            hess = controller.hessian(t, y, params, **extra)
        except ArithmeticError:
            return None
        jac = eq.jacobian_a(t, y, r)
        value = np.concatenate([grad + jac.T @ nu, eq.value(t, y, r)])
        if not np.all(np.isfinite(value)):
            return None
        return value, kkt_matrix(hess + eq.curvature(t, y, r, nu), jac)

    w = np.array(w, dtype=float)
    current = residual(w)
    if current is None:
        return None if strict else w
    for _ in range(iterations):
        value, matrix = current
        try:
            step = np.linalg.solve(matrix, value)
        except np.linalg.LinAlgError:
            if strict:
                return None
            step = np.linalg.lstsq(matrix, value, rcond=None)[0]
        size = float(np.linalg.norm(step[:m]))
        if strict:
            if float(np.linalg.norm(step)) <= NEWTON.stop * (1.0 + float(np.linalg.norm(w))):
                return w - step
            if size > NEWTON.step_cap:
                return None
        if size > NEWTON.step_cap:
            step = step * (NEWTON.step_cap / size)
        norm = float(value @ value)
        scale = 1.0
        while scale > NEWTON.smallest_scale:
            trial = residual(w - scale * step)
            if trial is not None and float(trial[0] @ trial[0]) <= norm * (
                1 - NEWTON.armijo * scale
            ):
                break
            if strict:
                return None
            scale *= NEWTON.shrink
        else:
            break
        w = w - scale * step
        current = trial
        assert current is not None
        if float(np.linalg.norm(step)) * scale <= NEWTON.stop * (1.0 + float(np.linalg.norm(w))):
            return w
    return None if strict else w


def _reference_values(extra: Mapping[str, Any]) -> list[float]:
    """The references' values (their jets' first column) in a call's keyword arguments."""
    refs = extra.get("refs")
    return [] if refs is None else [float(v) for v in np.asarray(refs)[:, 0]]


def kkt_path(
    controller: types.ModuleType,
    eq: Any,
    ts: np.ndarray,
    start: np.ndarray,
    params: Mapping[str, float] | None,
    refs: Callable[[float], dict[str, Any]] | None = None,
) -> np.ndarray:
    """``(y*, nu*)(t)``: the KKT system solved at each time.

    Followed backward like :func:`minimizer_path`, from ``start`` (the run's final
    outputs and multipliers).

    Returns
    -------
    numpy.ndarray, shape (m + q, T)
    """

    def step(t: float, w: np.ndarray, _index: int, budget: int) -> np.ndarray:
        extra = (refs or (lambda t: {}))(t)
        solved = _kkt_newton(controller, eq, t, w, params, extra, budget)
        assert solved is not None
        return solved

    def jump(t: float, w: np.ndarray) -> np.ndarray | None:
        extra = (refs or (lambda t: {}))(t)
        return _kkt_newton(controller, eq, t, w, params, extra, NEWTON.iterations, strict=True)

    return _backward(ts, start, step, jump)
