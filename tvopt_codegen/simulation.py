"""Closed-loop simulation and the paper's theorem, checked on the run (the certificate).

:func:`simulate` integrates ``rhs`` of a generated controller with
``scipy.integrate.solve_ivp``, finds the target path ``y*(t)`` by numerical
minimization of ``f0(., t)`` (never from the law), and checks the two claims of the
paper's theorems along the run:

1. the optimality error follows ``E(t) = expm(H t) E(0)``;
2. ``|y(t) - y*(t)| <= C e^{-alpha t}`` with ``C = c |E(0)| / m_f``, where ``c`` is the
   constant of ``|expm(H t)| <= c e^{-alpha t}`` (computed) and ``m_f`` the convexity
   modulus (estimated along the run).

Nothing here writes files or draws: :func:`tvopt_codegen.artifacts.result_files` renders
the outputs and figures in memory for :mod:`tvopt_codegen.emit`.
"""

from __future__ import annotations

import importlib.util
import math
import tempfile
import time
import types
import warnings
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import sympy as sp
from scipy.integrate import solve_ivp
from scipy.interpolate import CubicHermiteSpline
from scipy.linalg import expm

from tvopt_codegen import hurwitz
from tvopt_codegen.backends import BACKENDS
from tvopt_codegen.derivation import Derivation
from tvopt_codegen.emit import write_files
from tvopt_codegen.errors import AssumptionError, BuildError, SpecError
from tvopt_codegen.ir import KernelSet
from tvopt_codegen.limits import MAX_T_FINAL, START_ITERATIONS
from tvopt_codegen.references import ReferenceSource, nominal_source
from tvopt_codegen.rendering import render

#: The certificate is vacuous when the convexity modulus along the run is below this
#: fraction of the Hessian's scale there (its largest eigenvalue in magnitude).
VACUOUS_M_F = 1e-6


def load_controller(kernels: KernelSet, backend: str = "python") -> types.ModuleType:
    """Render a backend and load its Python module.

    The Python backend is compiled from memory (the text is tvopt-codegen's own output;
    spec text appears in it only inside escaped literals and comments). Other backends
    are written to a private temporary folder through :func:`~tvopt_codegen.emit.write_files`
    and imported from there (the C backend compiles and caches its library on import).
    """
    files = render(kernels, backend)
    name = kernels.derivation.spec.name
    module_file = BACKENDS[backend].module.format(name=name)
    if backend == "python":
        module = types.ModuleType(name)
        module.__file__ = f"<generated {module_file}>"
        exec(compile(files[module_file], module.__file__, "exec"), module.__dict__)  # noqa: S102
        return module
    with tempfile.TemporaryDirectory(prefix="tvopt-codegen-") as folder:
        write_files(files, folder)
        spec = importlib.util.spec_from_file_location(
            f"_tvopt_{backend}_{name}", Path(folder) / module_file
        )
        assert spec is not None and spec.loader is not None
        module = importlib.util.module_from_spec(spec)
        try:
            spec.loader.exec_module(module)
        except ImportError as exc:  # the C backend's build failed: say why, in one line
            raise BuildError(" ".join(str(exc).split())) from None
    return module


@dataclass(frozen=True)
class Options:
    """How to run one simulation.

    Attributes
    ----------
    t_final : float
        Horizon.
    initial_state : tuple of float
        Closed-loop initial state in ``STATE_NAMES`` order.
    params : mapping of str to float
        Parameter overrides.
    method : str
        ``solve_ivp`` method; RK45 (Dormand-Prince) as in the paper.
    rtol, atol : float
        Integration tolerances.
    points : int
        Number of output times.
    tolerance : float
        Largest accepted relative deviation of E from ``expm(H t) E(0)``.
    """

    t_final: float
    initial_state: tuple[float, ...]
    params: Mapping[str, float] = field(default_factory=dict)
    method: str = "RK45"
    rtol: float = 1e-10
    atol: float = 1e-12
    points: int = 401
    tolerance: float = 1e-6


@dataclass(frozen=True)
class Result:
    """A simulated closed loop and its certificate.

    Attributes
    ----------
    t : numpy.ndarray, shape (T,)
        Output times.
    states : numpy.ndarray, shape (n, T)
        Closed-loop states.
    inputs : numpy.ndarray, shape (m, T)
        Plant inputs.
    outputs, target : numpy.ndarray, shape (m, T)
        ``y`` and ``y*``.
    error : numpy.ndarray, shape (T,)
        ``|y - y*|``.
    E, E_predicted : numpy.ndarray, shape (T, K, m)
        The optimality error and ``expm(H t) E(0)``.
    alpha, c, m_f, C : float
        The theorem's constants (``alpha_exact`` tells whether alpha is the slowest
        pole's decay or reduced by the Jordan-block margin).
    bound : numpy.ndarray, shape (T,)
        ``C e^{-alpha t}``.
    deviation : float
        ``max_t |E(t) - expm(H t) E(0)| / |E(0)|``.
    bound_ratio : float
        ``max_t |y - y*| / (C e^{-alpha t})`` (where the bound exceeds 1e-10).
    fitted_rate : float
        Decay rate of ``|E|`` fitted along the run.
    nfev : int
        Right-hand side evaluations.
    wall_time : float
        Seconds spent integrating.
    passed : bool
        Whether the certificate holds.
    failures : tuple of str
        Why it does not.
    dense : callable or None
        The integrator's interpolant: the closed-loop state at any time of the run
        (``dense(t)``, shape (n,) or (n, T)).
    references : ReferenceSource or None
        Where the reference jets came from (None without references).
    disturbance : float
        With estimated reference jets: ``sup |d|`` of ``E' = H E + d`` along the run
        (NaN otherwise).
    iss_ratio : float
        With estimated reference jets: ``max_t |E(t)| / (c e^{-alpha t} |E(0)| +
        (c / alpha)(1 - e^{-alpha t}) sup |d|)``, which the certificate checks is at most 1.
    constraints : RunCheck or None
        For a spec with ``[constraints]``: margins, final values and the distance to the
        constrained minimiser along the run (:func:`tvopt_codegen.constraints.check_run`).
    """

    options: Options
    t: np.ndarray
    states: np.ndarray
    inputs: np.ndarray
    outputs: np.ndarray
    target: np.ndarray
    error: np.ndarray
    E: np.ndarray
    E_predicted: np.ndarray
    alpha: float
    alpha_exact: bool
    c: float
    m_f: float
    C: float
    bound: np.ndarray
    deviation: float
    bound_ratio: float
    fitted_rate: float
    nfev: int
    wall_time: float
    passed: bool
    failures: tuple[str, ...]
    dense: Any = None
    references: Any = None
    disturbance: float = float("nan")
    iss_ratio: float = float("nan")
    constraints: Any = None


def resolve_options(
    derivation: Derivation,
    t_final: float | None = None,
    initial: Mapping[str, float] | None = None,
    params: Mapping[str, float] | None = None,
    **rest: Any,
) -> Options:
    """Build :class:`Options` from the spec's ``[simulation]`` and overrides by name.

    Raises
    ------
    SpecError
        For an unknown state or parameter name, or a non-positive horizon (the field
        is the command-line option).
    """
    names = derivation.state_names
    state = dict(zip(names, derivation.initial_state, strict=True))
    for key, value in (initial or {}).items():
        if key not in state:
            raise SpecError(
                "command line", "--initial", f"unknown state {key!r} (states: {', '.join(names)})"
            )
        state[key] = float(value)
    known = {n for n, _ in derivation.spec.parameters}
    for key in params or {}:
        if key not in known:
            raise SpecError(
                "command line",
                "--param",
                f"unknown parameter {key!r} (parameters: {', '.join(sorted(known))})",
            )
    horizon = derivation.spec.t_final if t_final is None else float(t_final)
    if not 0 < horizon <= MAX_T_FINAL:
        raise SpecError(
            "command line", "--t-final", f"must be positive and at most {MAX_T_FINAL:g}"
        )
    return Options(
        t_final=horizon,
        initial_state=tuple(state[n] for n in names),
        params=dict(params or {}),
        **rest,
    )


def minimizer_path(
    controller: types.ModuleType,
    ts: np.ndarray,
    start: np.ndarray,
    params: Mapping[str, float],
    refs: Callable[[float], dict[str, Any]] | None = None,
    inside: np.ndarray | None = None,
) -> np.ndarray:
    """``y*(t) = argmin_y f0(y, t)`` at each time, by a damped Newton method.

    The path is followed backward in time from ``start`` (the final output),
    warm-starting every time from the previous one, with Armijo backtracking and steps
    capped at 0.02. For strongly convex f0 this is the unique minimizer whatever the
    start. A barrier that is finite only on a domain (``tan^2`` in the paper's Sec.
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
    params : mapping
        Parameter overrides.
    refs : callable, optional
        ``refs(t)``: the keyword arguments that give the module the reference jets at
        ``t`` (for a spec with references).
    inside : numpy.ndarray, shape (m, T), optional
        A point of f0's domain at each time (the run's outputs): the start whenever the
        warm start has left the domain (a barrier of moving constraints).

    Returns
    -------
    numpy.ndarray, shape (m, T)
        ``y*`` at each time.
    """

    def step(t: float, y: np.ndarray, index: int, budget: int) -> np.ndarray:
        extra = (refs or (lambda t: {}))(t)
        if inside is not None and not _defined(controller, t, y, params, extra):
            y = np.array(inside[:, index], dtype=float)
        return _newton(controller, t, y, params, extra, budget)

    return _backward(ts, start, step)


def _backward(
    ts: np.ndarray, start: np.ndarray, step: Callable[[float, np.ndarray, int, int], np.ndarray]
) -> np.ndarray:
    """Follow a solution backward in time from ``start`` at ``ts[-1]``, warm-starting.

    ``step(t, w, index, budget)`` solves at time ``t`` from ``w`` (``index``: the output
    time being approached) in at most ``budget`` iterations; five substeps lie between
    output times. The first point may start far from the solution (a run that has not
    converged): its capped steps get :data:`START_ITERATIONS`, the warm starts 200.
    """
    substeps = 5
    path = np.empty((len(start), len(ts)))
    w = np.array(start, dtype=float)
    for index in range(len(ts) - 1, -1, -1):
        later = ts[min(index + 1, len(ts) - 1)]
        for t in (
            np.linspace(later, ts[index], substeps + 1)[1:] if index < len(ts) - 1 else [ts[-1]]
        ):
            budget = 200 if index < len(ts) - 1 else START_ITERATIONS
            w = step(float(t), w, index, budget)
        path[:, index] = w
    return path


def _defined(
    controller: types.ModuleType,
    t: float,
    y: np.ndarray,
    params: Mapping[str, float],
    extra: Mapping[str, Any],
) -> bool:
    """Whether f0 is finite at ``y`` and ``t``."""
    try:
        return bool(np.isfinite(controller.objective(t, y, params, **extra)))
    except ArithmeticError:
        return False


def _newton(
    controller: types.ModuleType,
    t: float,
    y: np.ndarray,
    params: Mapping[str, float],
    extra: Mapping[str, Any] | None = None,
    iterations: int = 200,
) -> np.ndarray:
    """Minimize f0(., t) from ``y``: damped Newton with capped steps."""
    extra = extra or {}
    for _ in range(iterations):
        grad = controller.gradient(t, y, params, **extra)
        hess = controller.hessian(t, y, params, **extra)
        try:
            step = np.linalg.solve(hess, grad)
        except np.linalg.LinAlgError:
            step = grad
        if grad @ step <= 0:  # not a descent direction: fall back to the gradient
            step = grad
        size = float(np.linalg.norm(step))
        if size > 0.02:
            step = step * (0.02 / size)
        value = controller.objective(t, y, params, **extra)
        scale = 1.0
        while scale > 1e-8:
            trial = y - scale * step
            try:
                trial_value = controller.objective(t, trial, params, **extra)
            except ArithmeticError:
                trial_value = np.inf
            if np.isfinite(trial_value) and trial_value <= value - 1e-4 * scale * (grad @ step):
                break
            scale *= 0.5
        y = y - scale * step
        if size * scale <= 1e-14 * (1.0 + float(np.linalg.norm(y))):
            break
    return y


def _kkt_newton(
    controller: types.ModuleType,
    eq: Any,
    t: float,
    w: np.ndarray,
    params: Mapping[str, float],
    extra: Mapping[str, Any],
    iterations: int = 200,
) -> np.ndarray:
    """Solve the KKT system ``F(y, nu, t) = 0`` from ``w = (y, nu)``: damped Newton.

    ``F = [grad f0 + J_a^T nu; a]`` (f0's gradient and Hessian from the module, the
    equalities from ``eq``, :func:`tvopt_codegen.constraints.equalities`), backtracking
    on ``|F|^2`` within f0's domain, the outputs' steps capped at 0.02 like
    :func:`_newton`'s.
    """
    from tvopt_codegen.constraints import kkt_matrix  # noqa: PLC0415

    m = len(controller.OUTPUT_NAMES)
    r = _reference_values(extra)

    def residual(point: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        y, nu = point[:m], point[m:]
        try:
            grad = controller.gradient(t, y, params, **extra)
            hess = controller.hessian(t, y, params, **extra)
        except ArithmeticError:
            return None
        jac = eq.jacobian(t, y, r)
        value = np.concatenate([grad + jac.T @ nu, eq.value(t, y, r)])
        if not np.all(np.isfinite(value)):
            return None
        return value, kkt_matrix(hess + eq.curvature(t, y, r, nu), jac)

    w = np.array(w, dtype=float)
    current = residual(w)
    if current is None:
        return w
    for _ in range(iterations):
        value, matrix = current
        try:
            step = np.linalg.solve(matrix, value)
        except np.linalg.LinAlgError:
            step = np.linalg.lstsq(matrix, value, rcond=None)[0]
        size = float(np.linalg.norm(step[:m]))
        if size > 0.02:
            step = step * (0.02 / size)
        norm = float(value @ value)
        scale = 1.0
        while scale > 1e-8:
            trial = residual(w - scale * step)
            if trial is not None and float(trial[0] @ trial[0]) <= norm * (1 - 1e-4 * scale):
                break
            scale *= 0.5
        else:
            break
        w = w - scale * step
        current = trial
        assert current is not None
        if float(np.linalg.norm(step)) * scale <= 1e-14 * (1.0 + float(np.linalg.norm(w))):
            break
    return w


def _reference_values(extra: Mapping[str, Any]) -> list[float]:
    """The references' values (their jets' first column) in a call's keyword arguments."""
    refs = extra.get("refs")
    return [] if refs is None else [float(v) for v in np.asarray(refs)[:, 0]]


def kkt_path(
    controller: types.ModuleType,
    eq: Any,
    ts: np.ndarray,
    start: np.ndarray,
    params: Mapping[str, float],
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
        return _kkt_newton(controller, eq, t, w, params, extra, budget)

    return _backward(ts, start, step)


def simulate(
    derivation: Derivation,
    controller: types.ModuleType,
    options: Options,
    progress: Callable[[float, float], None] | None = None,
    references: ReferenceSource | None = None,
) -> Result:
    """Integrate the closed loop and check the theorem along the run.

    Parameters
    ----------
    derivation : Derivation
        The derivation the controller was generated from.
    controller : module
        The generated controller (any backend with the Python contract).
    options : Options
        Horizon, initial state, parameters, solver and tolerances.
    progress : callable, optional
        Called with (simulated time reached, horizon) at most twice a second once a
        run has taken two seconds.
    references : ReferenceSource, optional
        The reference jets, for a spec with references (default: the exact jets of the
        nominal closed forms).

    Returns
    -------
    Result
        Trajectories, the theorem's quantities and the certificate.
    """
    d = derivation
    params = dict(options.params)
    if d.model.references and references is None:
        references = nominal_source(d, params)
    source = references
    started = time.perf_counter()
    last_report = [started + 2.0]

    def rhs(t: float, s: np.ndarray) -> np.ndarray:
        if progress is not None:
            now = time.perf_counter()
            if now >= last_report[0]:
                progress(float(t), options.t_final)
                last_report[0] = now + 0.5
        if source is not None:
            jets: np.ndarray = controller.rhs(t, s, params, refs=source.jets(t))
            return jets
        result: np.ndarray = controller.rhs(t, s, params)
        return result

    _check_initial_state(d, controller, options, source)
    reached = [0.0]

    def tracked(t: float, s: np.ndarray) -> np.ndarray:
        reached[0] = float(t)
        return rhs(t, s)

    try:
        # A run that overflows ends in a ControllerError with its time; numpy's own
        # warnings on the way would only add lines to that one-line message.
        with np.errstate(all="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            if source is not None and source.estimated and source.times is not None:
                solution = _on_the_sample_grid(
                    tracked, options.t_final, np.array(options.initial_state), source.times
                )
            else:
                solution = solve_ivp(
                    tracked,
                    (0.0, options.t_final),
                    np.array(options.initial_state),
                    method=options.method,
                    rtol=options.rtol,
                    atol=options.atol,
                    dense_output=True,
                )
        return _certify(d, controller, options, solution, time.perf_counter() - started, source)
    except ArithmeticError as exc:
        if not hasattr(exc, "status"):
            raise
        raise AssumptionError(
            d.spec.source,
            "simulation",
            f"the law became undefined along the run, near t = {reached[0]:.6g}: {exc}",
        ) from None


#: Longest step of the fixed-grid integration of a loop fed with estimated references.
MAX_GRID_STEP = 1e-2


@dataclass(frozen=True)
class _GridSolution:
    """What ``solve_ivp`` returns, for a run integrated on the reference samples' grid."""

    t: np.ndarray
    y: np.ndarray
    sol: Any
    nfev: int
    success: bool = True
    message: str = "the end of the horizon was reached"


def _on_the_sample_grid(
    rhs: Callable[[float, np.ndarray], np.ndarray],
    horizon: float,
    start: np.ndarray,
    sample_times: np.ndarray,
) -> _GridSolution:
    """Integrate by classical RK4 with steps that end on every reference sample.

    Steps are at most :data:`MAX_GRID_STEP`. Estimated jets jump at the samples and are
    smooth between them, where an adaptive method would spend its steps rediscovering
    each jump.
    """
    inside = sample_times[(sample_times > 0.0) & (sample_times < horizon)]
    knots = [0.0]
    for end in (*inside.tolist(), horizon):
        pieces = max(1, math.ceil((end - knots[-1]) / MAX_GRID_STEP - 1e-9))
        knots += list(np.linspace(knots[-1], end, pieces + 1)[1:])
    grid = np.array(knots)
    states = np.empty((len(start), len(grid)))
    rates = np.empty_like(states)
    x = start.astype(float)
    states[:, 0] = x
    for i in range(len(grid) - 1):
        t, h = float(grid[i]), float(grid[i + 1] - grid[i])
        k1 = rhs(t, x)
        rates[:, i] = k1
        k2 = rhs(t + h / 2, x + h / 2 * k1)
        k3 = rhs(t + h / 2, x + h / 2 * k2)
        k4 = rhs(t + h, x + h * k3)
        x = x + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
        states[:, i + 1] = x
    # The last rate: the left limit of the last interval's (the jets jump at samples).
    rates[:, -1] = k4
    interpolant = CubicHermiteSpline(grid, states, rates, axis=1)
    return _GridSolution(grid, states, interpolant, 4 * (len(grid) - 1))


def _check_initial_state(
    d: Derivation,
    controller: types.ModuleType,
    options: Options,
    references: ReferenceSource | None = None,
) -> None:
    """Refuse, before integrating, an initial state where the law is undefined."""
    s0 = np.array(options.initial_state)
    extra = {} if references is None else {"refs": references.jets(0.0)}
    try:
        controller.rhs(0.0, s0, dict(options.params), **extra)
    except ArithmeticError as exc:
        if not hasattr(exc, "status"):
            raise
        where = ", ".join(
            f"{name} = {value:.6g}" for name, value in zip(d.state_names, s0, strict=True)
        )
        if options.params:
            where += "; parameters " + ", ".join(
                f"{name} = {value:.6g}" for name, value in options.params.items()
            )
        if len(where) > 160:
            where = where[:157] + "..."
        kind = AssumptionError if exc.status in (2, 3) else SpecError
        raise kind(
            d.spec.source,
            "simulation.initial_state",
            f"the law is undefined at the initial state ({where}): {exc}",
        ) from None


def _certify(
    d: Derivation,
    controller: types.ModuleType,
    options: Options,
    solution: Any,
    wall: float,
    references: ReferenceSource | None = None,
) -> Result:
    """Sample the run and check the theorem along it."""
    # Long on purpose: one pass over the run's samples, each check of the certificate
    # in the order the summary prints them; the heavy parts are helpers.
    params = dict(options.params)
    # The controller got these jets; E and y* are measured against the true ones when
    # they are known (an estimate's error is then the disturbance d of E' = H E + d).
    given: Callable[[float], dict[str, Any]] = lambda t: {}  # noqa: E731
    true = given
    if references is not None:
        source = references
        given = lambda t: {"refs": source.jets(t)}  # noqa: E731
        truth = source.exact or source.jets
        true = lambda t: {"refs": truth(t)}  # noqa: E731
    failures: list[str] = []
    if not solution.success:
        failures.append(f"integration stopped: {solution.message}")
    t_end = float(solution.t[-1])
    ts = np.linspace(0.0, t_end, options.points)
    states = solution.sol(ts)
    m = len(d.spec.outputs)
    inputs = np.array(
        [controller.control(t, states[:, i], params, **given(t)) for i, t in enumerate(ts)]
    ).T
    E = np.array(
        [controller.optimality_error(t, states[:, i], params, **true(t)) for i, t in enumerate(ts)]
    )

    values = {
        q.name: options.params.get(q.name, v)
        for q, v in zip(d.model.params, d.model.defaults, strict=True)
    }
    h = sp.lambdify([*d.states, *d.model.params], list(d.model.h), "numpy")
    outputs = np.array(
        [
            np.broadcast_to(np.asarray(v, dtype=float), ts.shape)
            for v in h(*states, *values.values())
        ]
    )
    eq = multipliers = kkt = None
    if d.model.equalities:
        from tvopt_codegen.constraints import equalities  # noqa: PLC0415

        eq = equalities(d.model, {q: values[q.name] for q in d.model.params})
        rows = [d.state_names.index(chain[0]) for chain in d.multiplier_states]
        multipliers = states[rows]
        start = np.concatenate([outputs[:, -1], multipliers[:, -1]])
        kkt = kkt_path(controller, eq, ts, start, params, true)
        target = kkt[:m]
    else:
        target = minimizer_path(controller, ts, outputs[:, -1], params, true, outputs)
    error = np.linalg.norm(outputs - target, axis=0)

    H = hurwitz.error_matrix(d.coefficients, d.n_kkt)
    flat = E.reshape(len(ts), -1)
    norm0 = float(np.linalg.norm(flat[0]))
    predicted = np.array([expm(H * t) @ flat[0] for t in ts])
    deviation = float(np.max(np.linalg.norm(flat - predicted, axis=1))) / max(norm0, 1e-300)
    estimated = references is not None and references.estimated
    disturbance = iss_ratio = float("nan")
    if estimated:
        disturbance, iss_ratio = _input_to_state(d, controller, params, solution, ts, flat, true)
        if not iss_ratio <= 1.0:
            failures.append(
                f"|E| exceeds its input-to-state bound by a factor {iss_ratio:.3g} "
                f"(sup |d| = {disturbance:.3g})"
            )
    elif deviation > options.tolerance:
        failures.append(
            f"E deviates from expm(H t) E(0) by {deviation:.3g} (relative) > {options.tolerance:g}"
        )

    # The theorem's constants were computed with the derivation (the report shows them too).
    alpha, c = d.certified_rate, d.transient_constant
    exact = d.certified_rate_exact
    if eq is not None:
        assert multipliers is not None and kkt is not None
        # |w - w*| <= |F(w)| / sigma_min(K) along the segment, and |y - y*| <= |w - w*|:
        # the KKT matrix's smallest singular value takes m_f's place.
        eigenvalues = np.abs(
            _kkt_eigenvalues(d, controller, eq, ts, outputs, multipliers, kkt, params, true)
        )
    else:
        eigenvalues = np.array(
            [
                np.linalg.eigvalsh(controller.hessian(t, point, params, **true(t)))
                for i, t in enumerate(ts)
                for point in (outputs[:, i], target[:, i], 0.5 * (outputs[:, i] + target[:, i]))
            ]
        )
    m_f = float(eigenvalues.min())
    scale = float(np.abs(eigenvalues).max())
    if eq is not None and not m_f > 0:
        failures.append(f"the KKT matrix is singular along the run (sigma_min = {m_f:.3g})")
        m_f = float("nan")
    elif not m_f > 0:
        failures.append(f"f0 is not strongly convex along the run (m_f = {m_f:.3g})")
        m_f = float("nan")
    elif m_f <= VACUOUS_M_F * scale:
        failures.append(
            f"the bound is vacuous: m_f = {m_f:.3g} is below {VACUOUS_M_F:g} of the Hessian's "
            f"scale {scale:.3g} along the run (f0 is barely strongly convex there)"
        )
    C = c * norm0 / m_f
    bound = C * np.exp(-alpha * ts)
    if not estimated and np.isfinite(C) and error[0] > 0 and bound[-1] >= error[0]:
        failures.append(
            f"the bound is vacuous: C e^(-alpha t) = {bound[-1]:.3g} at the end of the run "
            f"is still above the initial |y - y*| = {error[0]:.3g}"
        )
    meaningful = bound > 1e-10
    # 1e-8 absolute: the minimizer's accuracy on y*.
    ratio = (
        float(np.max((error[meaningful] - 1e-8) / bound[meaningful])) if meaningful.any() else 0.0
    )
    if not estimated and not ratio <= 1.0:
        failures.append(f"|y - y*| exceeds the bound C e^(-alpha t) by a factor {ratio:.3g}")
    constrained = _constraint_check(d, options, ts, outputs, error, target, references, failures)
    if constrained is not None and d.model.equalities:
        # a is the KKT map's last rows: |a(y(t), t)| <= |E(t)| <= c e^(-alpha t) |E(0)|.
        drift = np.linalg.norm(constrained.equality, axis=0)
        envelope = c * norm0 * np.exp(-alpha * ts)
        excess = float(np.max((drift - 1e-9) / np.maximum(envelope, 1e-300)))
        if not excess <= 1.0:
            failures.append(
                f"the equality constraints exceed their bound c e^(-alpha t) |E(0)| by a "
                f"factor {excess:.3g}"
            )
    norms = np.linalg.norm(flat, axis=1)
    # The decay rate is fitted where the slowest pole dominates: the second half of the
    # stretch where |E| is still above the integration noise.
    valid = norms > 1e-9 * max(norm0, 1e-300)
    last = ts[valid][-1] if valid.any() else t_end
    window = valid & (ts >= last / 2)
    fitted = (
        float(-np.polyfit(ts[window], np.log(norms[window]), 1)[0])
        if window.sum() >= 3
        else float("nan")
    )
    return Result(
        options=options,
        t=ts,
        states=states,
        inputs=inputs,
        outputs=outputs,
        target=target,
        error=error,
        E=E,
        E_predicted=predicted.reshape(E.shape),
        alpha=alpha,
        alpha_exact=exact,
        c=c,
        m_f=m_f,
        C=C,
        bound=bound,
        deviation=deviation,
        bound_ratio=ratio,
        fitted_rate=fitted,
        nfev=int(solution.nfev),
        wall_time=wall,
        passed=not failures,
        failures=tuple(failures),
        dense=solution.sol,
        references=references,
        disturbance=disturbance,
        iss_ratio=iss_ratio,
        constraints=constrained,
    )


def _kkt_eigenvalues(
    d: Derivation,
    controller: types.ModuleType,
    eq: Any,
    ts: np.ndarray,
    outputs: np.ndarray,
    multipliers: np.ndarray,
    kkt: np.ndarray,
    params: Mapping[str, float],
    true: Callable[[float], dict[str, Any]],
) -> np.ndarray:
    """The KKT matrix's eigenvalues at the run's (y, nu), at (y*, nu*) and midway."""
    from tvopt_codegen.constraints import kkt_matrix  # noqa: PLC0415

    m = len(d.model.y)
    run = np.vstack([outputs, multipliers])
    found = []
    for i, t in enumerate(ts):
        extra = true(float(t))
        r = _reference_values(extra)
        for point in (run[:, i], kkt[:, i], 0.5 * (run[:, i] + kkt[:, i])):
            y, nu = point[:m], point[m:]
            hess = controller.hessian(float(t), y, params, **extra)
            matrix = kkt_matrix(hess + eq.curvature(t, y, r, nu), eq.jacobian(t, y, r))
            found.append(np.linalg.eigvalsh(matrix))
    return np.array(found)


def _constraint_check(
    d: Derivation,
    options: Options,
    ts: np.ndarray,
    outputs: np.ndarray,
    error: np.ndarray,
    target: np.ndarray,
    references: ReferenceSource | None,
    failures: list[str],
) -> Any:
    """For a spec with constraints: check them along the run, adding to ``failures``."""
    if not d.model.constraints and not d.model.equalities:
        return None
    from tvopt_codegen.constraints import check_run  # noqa: PLC0415

    values = {
        q: options.params.get(q.name, v)
        for q, v in zip(d.model.params, d.model.defaults, strict=True)
    }
    constrained = check_run(d.model, ts, outputs, error, target, values, references)
    worst = float(constrained.margins.min()) if constrained.margins.size else math.inf
    if not worst > 0:
        where = np.unravel_index(int(np.argmin(constrained.margins)), constrained.margins.shape)
        failures.append(
            f"constraint {d.model.constraints[where[0]].name} reached its barrier: "
            f"s - g = {worst:.3g} at t = {ts[where[1]]:.4g}"
        )
    if not constrained.distance[-1] <= constrained.bound[-1] + 1e-6:
        failures.append(
            f"the distance to the constrained minimiser at the end, "
            f"{constrained.distance[-1]:.3g}, exceeds its bound {constrained.bound[-1]:.3g}"
        )
    return constrained


def _input_to_state(
    d: Derivation,
    controller: types.ModuleType,
    params: dict[str, float],
    solution: Any,
    ts: np.ndarray,
    flat: np.ndarray,
    true: Callable[[float], dict[str, Any]],
) -> tuple[float, float]:
    """``sup |d|`` of ``E' = H E + d`` along the run, and the largest ``|E| / bound``.

    ``E'`` by central differences of ``E`` read from the run's interpolant, on a grid ten
    times finer than the output's; the bound is the variation-of-constants one,
    ``c e^{-alpha t} |E(0)| + int_0^t c e^{-alpha (t - s)} |d(s)| ds``, with the certified
    ``alpha`` and ``c`` of ``|expm(H t)| <= c e^{-alpha t}``: the disturbance fades from it
    as it fades from E (the estimator's start does not weigh on the end of the run).
    """
    m = len(d.spec.outputs)
    H = hurwitz.error_matrix(d.coefficients, m)
    horizon = float(ts[-1])
    fine = np.linspace(0.0, horizon, 10 * (len(ts) - 1) + 1)
    step = 1e-6 * max(1.0, horizon)

    def error_at(t: float) -> np.ndarray:
        state = solution.sol(min(max(t, 0.0), horizon))
        value: np.ndarray = controller.optimality_error(t, state, params, **true(t))
        return value.ravel()

    errors = np.array([error_at(t) for t in fine])
    rates = np.array([(error_at(t + step) - error_at(t - step)) / (2 * step) for t in fine])
    d_norm = np.linalg.norm(rates - errors @ H.T, axis=1)
    d_norm[0], d_norm[-1] = d_norm[1], d_norm[-2]  # one-sided there: take the neighbours'
    alpha, c = d.certified_rate, d.transient_constant
    # int_0^t e^{-alpha (t - s)} |d(s)| ds by the trapezoid rule, recursively.
    forced = np.zeros(len(fine))
    for i in range(1, len(fine)):
        h = fine[i] - fine[i - 1]
        decay = math.exp(-alpha * h)
        forced[i] = forced[i - 1] * decay + h / 2 * (d_norm[i - 1] * decay + d_norm[i])
    bound = c * np.exp(-alpha * fine) * float(np.linalg.norm(errors[0])) + c * forced
    norms = np.linalg.norm(errors, axis=1)
    # 1e-9 absolute, and 1% for the trapezoid rule's error on a disturbance that jumps.
    ratio = float(np.max((norms - 1e-9) / np.maximum(1.01 * bound, 1e-300)))
    return float(np.max(d_norm)), ratio


def format_certificate(derivation: Derivation, result: Result) -> str:
    """The one-screen summary of a run and its certificate."""
    d, r = derivation, result
    if r.references is not None and r.references.estimated:
        return _format_estimated(d, r)
    lines = [
        f"{d.spec.name}: closed loop over [0, {r.t[-1]:g}] with {r.options.method} "
        f"(rtol {r.options.rtol:g}, atol {r.options.atol:g})",
        f"  final |y - y*|            {r.error[-1]:.3e}   (initial {r.error[0]:.3e})",
        f"  decay rate of |E|         {r.fitted_rate:.4g} fitted, alpha = {r.alpha:.4g}"
        + ("" if r.alpha_exact else " (repeated poles: 10% margin)"),
        f"  E vs expm(H t) E(0)       max relative deviation {r.deviation:.3e} "
        f"(limit {r.options.tolerance:g})",
        f"  |y - y*| <= C e^(-alpha t)  max ratio {r.bound_ratio:.3g}  "
        f"(C = {r.C:.4g}: c = {r.c:.4g}, m_f = {r.m_f:.4g}, |E(0)| = {np.linalg.norm(r.E[0]):.4g})",
        f"  RHS evaluations           {r.nfev}   wall time {r.wall_time:.2f} s",
        "  certificate: " + ("PASSED" if r.passed else "FAILED: " + "; ".join(r.failures)),
    ]
    if r.constraints is not None and d.model.equalities:
        check = r.constraints
        q = len(d.model.equalities)
        finals = ", ".join(f"{name} {value:.3g}" for name, value in check.final[-q:])
        envelope = r.c * np.linalg.norm(r.E[0]) * np.exp(-r.alpha * r.t)
        drift = np.linalg.norm(check.equality, axis=0) / np.maximum(envelope, 1e-300)
        lines[-1:-1] = [
            "  equality constraints (KKT system: E is col(F, ..., F^(k-1)), "
            "F = [grad f0 + J_a^T nu; a]; m_f is sigma_min of the KKT matrix):",
            f"    a_j at the end (0 holds)     {finals}",
            f"    max over t of |a| / (c e^(-alpha t) |E(0)|) {float(np.max(drift)):.3g}  (<= 1)",
            f"    KKT residual |F| at the end  {float(np.linalg.norm(r.E[-1][0])):.3e}",
        ]
        if not d.model.constraints:
            lines[-1:-1] = [
                f"    |y - y*_constrained| at the end {check.distance[-1]:.3e} <= "
                f"{check.bound[-1]:.3e}  (|y - y*_KKT|; SLSQP on f0 subject to a_j = 0)",
            ]
    if r.constraints is not None and d.model.constraints:
        check = r.constraints
        finals = ", ".join(
            f"{name} {value:.3g}" for name, value in check.final[: len(d.model.constraints)]
        )
        lines[-1:-1] = [
            "  constraints (interior-point homotopy on Phi = f0 - mu sum log(s - g_i)):",
            f"    min over t and i of s - g_i   {float(check.margins.min()):.3e}  (> 0: no "
            "instant on or past a barrier)",
            f"    g_i at the end (<= 0 holds)   {finals}",
            f"    |y - y*_constrained| at the end {check.distance[-1]:.3e} <= bound "
            f"{check.bound[-1]:.3e}  (|y - y*_Phi| + sqrt(2 p mu / m_f), m_f = {check.m_f:.4g}; "
            "SLSQP on f0 subject to g_i <= s" + (", a_j = 0)" if d.model.equalities else ")"),
        ]
    return "\n".join(lines)


def _format_estimated(d: Derivation, r: Result) -> str:
    """The summary of a run fed with references estimated from samples."""
    source = r.references
    kind = d.spec.estimator.kind if d.spec.estimator is not None else "?"
    noise = f", noise sd {source.noise:g}" if source.noise else ""
    samples = len(source.times)
    rate = (samples - 1) / float(source.times[-1] - source.times[0])
    lines = [
        f"{d.spec.name}: closed loop over [0, {r.t[-1]:g}], references estimated online from "
        f"{samples} samples ({rate:.4g} per second{noise}) by the {kind} "
        "differentiator; RK4 on the sample grid",
        f"  final |y - y*|            {r.error[-1]:.3e}   (initial {r.error[0]:.3e}; ratio "
        f"{r.error[-1] / max(r.error[0], 1e-300):.3e})",
        "  E' = H E + d: the jets' error is the disturbance d (the exact decay no longer holds)",
        f"  sup |d|                   {r.disturbance:.3e}",
        f"  |E| <= c e^(-alpha t)|E(0)| + int c e^(-alpha (t-s)) |d(s)| ds   max ratio "
        f"{r.iss_ratio:.3g}   (c = {r.c:.4g}, alpha = {r.alpha:.4g})",
        f"  RHS evaluations           {r.nfev}   wall time {r.wall_time:.2f} s",
        "  certificate: " + ("PASSED" if r.passed else "FAILED: " + "; ".join(r.failures)),
    ]
    if source.exact is None:
        lines.insert(3, "  (no nominal reference: E is measured against the estimate itself)")
    return "\n".join(lines)


def columns(derivation: Derivation) -> list[str]:
    """Column names of the trajectory table."""
    d = derivation
    names = ["t", *d.state_names, *(f"u_{n}" for n in d.spec.inputs)]
    names += [*(f"y_{n}" for n in d.spec.outputs), *(f"ystar_{n}" for n in d.spec.outputs)]
    names += [f"E{j}_{n}" for j in range(d.k) for n in d.spec.outputs]
    return names
