"""Sampled-data simulation: the stateful controller stepped every H seconds.

The true plant ``x' = f(x) + G(x) u`` runs continuously with the input held over each
sampling interval (zero-order hold); at ``t_k = k H`` the controller measures ``x(t_k)``,
:meth:`Controller.step` advances its own states and returns the next input. This is how
the controller runs on a robot, and the paper's theorem is about the continuous-time
loop: the certificate here states what holds under sampling, next to the continuous
run's certificate:

- the deviation of the sampled outputs from the continuous ones (at the sample times);
- the ultimate tracking error ``|y - y*|`` over the last tenth of the horizon, for both;
- with the convergence check, the same at ``H/2`` and the observed order
  ``log2(deviation(H) / deviation(H/2))``: 1 for a zero-order hold.

Between samples the plant is integrated by the classical Runge-Kutta method with steps
of at most ``H`` and at most :data:`MAX_SUBSTEP`: its error, ``O(step^4)``, is far below
the sampling effect, ``O(H)``.
"""

from __future__ import annotations

import math
import time
import types
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from tvopt_codegen.derivation import Derivation
from tvopt_codegen.errors import AssumptionError, SpecError
from tvopt_codegen.maths import hurwitz
from tvopt_codegen.simulation.certificate import augmented_error
from tvopt_codegen.simulation.direct import plant_function, point_function
from tvopt_codegen.simulation.references import nominal_source
from tvopt_codegen.simulation.result import Options, Result
from tvopt_codegen.simulation.run import bumpless_start, simulate

#: Longest Runge-Kutta step of the plant between samples.
MAX_SUBSTEP = 1e-2
#: Fewest samples a run may have (a coarser H says nothing about sampling).
MIN_SAMPLES = 10
#: Most samples of one run (the sampled run is a Python loop over them).
MAX_SAMPLES = 2_000_000
#: The observed order below which the sampled loop is not converging to the continuous one.
ORDER_FLOOR = 0.75
#: Halvings of H beyond H/2 tried when the order at (H, H/2) is below the floor: a coarse
#: H can be pre-asymptotic (order 0.7 there, 0.94 at H/5), which is not divergence.
EXTRA_HALVINGS = 2


@dataclass(frozen=True)
class SampledRun:
    """One sampled-data run.

    Attributes
    ----------
    h : float
        Sample time.
    t : numpy.ndarray, shape (K,)
        Sample times ``t_k``.
    states : numpy.ndarray, shape (n, K)
        ``[x(t_k); z_k]``: the measured plant state and the controller's states after
        its step at ``t_k``.
    inputs : numpy.ndarray, shape (m, K)
        The input computed at ``t_k`` and held until ``t_{k+1}``.
    outputs : numpy.ndarray, shape (m, K)
        ``y(t_k)``.
    distance : numpy.ndarray, shape (K,)
        ``|y(t_k) - y_continuous(t_k)|``, the continuous run read at the sample times
        from its interpolant.
    deviation : float
        Its largest value.
    ultimate : float
        ``max |y - y*|`` over the last tenth of the horizon.
    wall_time : float
        Seconds the run took.
    saturated_time : float
        Time with an input clipped by the controller's ``[limits]`` (0 without limits).
    disturbance : float
        ``sup_k |w_k| / h`` where ``E_{k+1} = expm(H h) E_k + w_k`` along the samples: what
        sampling, a wrong plant, noise and the limits add to the error dynamics (E is
        ``col(z_I, E)`` with integral action).
    iss_ratio : float
        The largest ``|E_k|`` over its input-to-state bound
        ``c e^(-alpha t_k) |E_0| + sum_j c e^(-alpha (t_k - t_{j+1})) |w_j|``.
    """

    h: float
    t: np.ndarray
    states: np.ndarray
    inputs: np.ndarray
    outputs: np.ndarray
    distance: np.ndarray
    deviation: float
    ultimate: float
    wall_time: float
    saturated_time: float = 0.0
    disturbance: float = float("nan")
    iss_ratio: float = float("nan")


@dataclass(frozen=True)
class SampledResult:
    """A sampled-data run beside the continuous one, and what holds under sampling.

    Attributes
    ----------
    continuous : Result
        The continuous-time run and its certificate.
    runs : tuple of SampledRun
        At ``H``, and at ``H/2`` when the convergence order was asked for.
    order : float or None
        ``log2(deviation(h) / deviation(h/2))`` at the finest pair of runs, or None.
    orders : tuple of float
        The observed order of every consecutive pair of runs, coarsest first: more than
        one when the first was below :data:`ORDER_FLOOR` and H was halved again.
    continuous_ultimate : float
        The continuous run's ``max |y - y*|`` over the last tenth of the horizon.
    passed : bool
        The continuous certificate passed, every sampled run finished, and the observed
        order (when asked for) is at least :data:`ORDER_FLOOR`.
    failures : tuple of str
        Why not.
    plant_params : tuple of (str, float)
        The true plant's parameters where they are not the controller's (empty: none).
    """

    continuous: Result
    runs: tuple[SampledRun, ...]
    order: float | None
    continuous_ultimate: float
    passed: bool
    failures: tuple[str, ...]
    plant_params: tuple[tuple[str, float], ...] = ()
    orders: tuple[float, ...] = ()


def _plant(controller: types.ModuleType, params: dict[str, float]) -> Callable[..., Any]:
    """The true plant ``f(x) + G(x) u``: the generated module's own ``plant`` at ``params``.

    Where it is not finite the state becomes NaN, and the controller's next step reports
    it (NonFiniteInputError), as a run leaving the plant's domain is reported. The
    kernel behind ``plant`` answers where the module has one (simulation.direct): the
    same numbers, without the public function's checks on every call (most of its cost).
    Call it under ``numpy.errstate(all="ignore")``, as ``plant`` calls its kernel.
    """
    function = plant_function(controller, params or None)

    def plant(t: float, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        try:
            return function(t, x, u)
        except ArithmeticError as exc:
            if not hasattr(exc, "status"):
                raise
            return np.full(len(x), np.nan)

    return plant


def _sampled_input_to_state(
    d: Derivation,
    controller: types.ModuleType,
    params: dict[str, float],
    times: np.ndarray,
    states: np.ndarray,
    extra: Callable[[float], dict[str, Any]],
) -> tuple[float, float]:
    """``sup |w_k| / h`` and the largest ``|E_k|`` over its input-to-state bound.

    ``E_{k+1} = expm(H h) E_k + w_k`` defines ``w``; the bound is the variation of
    constants in discrete time, exact for any ``w`` given ``|expm(H t)| <= c e^(-alpha t)``.
    """
    optimality_error = point_function(controller, "optimality_error", params or None)
    with np.errstate(all="ignore"):
        rows = [
            np.asarray(optimality_error(float(t), states[:, k], **extra(float(t)))).ravel()
            for k, t in enumerate(times)
        ]
    errors = augmented_error(d, states, np.array(rows))
    h = float(times[1] - times[0])
    # expm(H h) = expm(companion(a) h) kron I_m: only the k x k exponential is computed.
    step = np.kron(
        hurwitz.exponential(hurwitz.companion(d.dynamics.coefficients) * h), np.eye(d.jet.n_kkt)
    )
    w = np.linalg.norm(errors[1:] - errors[:-1] @ step.T, axis=1)
    alpha, c = d.dynamics.certified_rate, d.dynamics.transient_constant
    decay = math.exp(-alpha * h)
    bound = np.empty(len(times))
    bound[0] = c * float(np.linalg.norm(errors[0]))
    forced = 0.0
    for k in range(1, len(times)):
        forced = forced * decay + c * float(w[k - 1])
        bound[k] = c * math.exp(-alpha * float(times[k])) * float(np.linalg.norm(errors[0]))
        bound[k] += forced
    norms = np.linalg.norm(errors, axis=1)
    ratio = float(np.max((norms - 1e-9) / np.maximum(bound, 1e-300)))
    return float(np.max(w)) / h, ratio


def hold(
    plant: Callable[[float, np.ndarray, np.ndarray], np.ndarray],
    t0: float,
    t1: float,
    x: np.ndarray,
    u: np.ndarray,
) -> np.ndarray:
    """The plant state at ``t1`` from ``x`` at ``t0`` under the input ``u`` held between.

    Classical Runge-Kutta with steps of at most :data:`MAX_SUBSTEP` (one step for a
    sample time below it): ``plant(t, x, u)`` is ``x'``.
    """
    pieces = max(1, math.ceil((t1 - t0) / MAX_SUBSTEP - 1e-9))
    dt = (t1 - t0) / pieces
    for piece in range(pieces):
        t = t0 + piece * dt
        k1 = plant(t, x, u)
        k2 = plant(t + dt / 2, x + dt / 2 * k1, u)
        k3 = plant(t + dt / 2, x + dt / 2 * k2, u)
        k4 = plant(t + dt, x + dt * k3, u)
        x = x + dt / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    return x


def _tail(t: np.ndarray, horizon: float) -> np.ndarray:
    """The last tenth of the horizon (at least the last point)."""
    tail = t >= 0.9 * horizon
    tail[-1] = True
    return tail


def sampled_run(
    derivation: Derivation,
    controller: types.ModuleType,
    options: Options,
    h: float,
    continuous: Result,
    progress: Callable[[float, float], None] | None = None,
    plant_params: dict[str, float] | None = None,
) -> SampledRun:
    """The sampled-data loop at sample time ``h`` (see the module docstring).

    ``plant_params`` are the true plant's parameters where they differ from the
    controller's (model mismatch, as a sweep sample draws it).

    Raises
    ------
    AssumptionError
        When the law is undefined at a sample (the time and the controller's reason).
    """
    d = derivation
    params = dict(options.params)
    n = len(d.spec.states)
    plant = _plant(controller, params | (plant_params or {}))
    horizon = options.t_final
    count = math.ceil(horizon / h - 1e-9)
    times = np.minimum(np.arange(count + 1) * h, horizon)
    initial = np.array(options.initial_state)
    started = time.perf_counter()
    x = initial[:n].copy()
    # A spec with references: the nominal closed forms' exact jets at every sample.
    jets = nominal_source(d, params).jets if d.model.references else None

    def extra(t: float) -> dict[str, Any]:
        return {} if jets is None else {"refs": jets(t)}

    step = controller.Controller(x, 0.0, initial[n:], params or None, **extra(0.0))
    states = np.empty((len(initial), count + 1))
    inputs = np.empty((len(d.spec.inputs), count + 1))
    states[:, 0], inputs[:, 0] = np.concatenate([x, step.state]), step.u
    u = step.u
    saturated_time = 0.0
    next_report = started + 2.0
    for k in range(count):
        t0, t1 = float(times[k]), float(times[k + 1])
        if getattr(step, "saturated", None) is not None and step.saturated.any():
            saturated_time += t1 - t0
        with np.errstate(all="ignore"):  # the plant's kernel's, as plant's own
            x = hold(plant, t0, t1, x, u)
        try:
            u = step.step(t1, x, **extra(t1))
        except ArithmeticError as exc:
            if not hasattr(exc, "status"):
                raise
            raise AssumptionError(
                d.spec.source,
                "simulation",
                f"the law became undefined along the sampled run (H = {h:g}) at t = {t1:.6g}: "
                f"{exc}",
            ) from None
        states[:, k + 1] = np.concatenate([x, step.state])
        inputs[:, k + 1] = u
        if progress is not None and time.perf_counter() >= next_report:
            progress(t1, horizon)
            next_report = time.perf_counter() + 0.5
    disturbance, iss_ratio = _sampled_input_to_state(d, controller, params, times, states, extra)
    outputs = np.asarray(controller.outputs(0.0, states[:n], params or None))
    if outputs.ndim == 1:
        outputs = outputs[:, None]
    reference = np.asarray(continuous.dense(times))[:n]
    reference_y = np.asarray(controller.outputs(0.0, reference, params or None))
    reference_y = reference_y.reshape(outputs.shape)
    distance = np.linalg.norm(outputs - reference_y, axis=0)
    # |y - y*| where the continuous run knows y*; the sampled y between its samples is
    # interpolated (an O(H^2) error, below the O(H) effect of sampling).
    tail = _tail(continuous.t, horizon)
    sampled_y = np.array([np.interp(continuous.t[tail], times, row) for row in outputs])
    ultimate = float(np.max(np.linalg.norm(sampled_y - continuous.target[:, tail], axis=0)))
    return SampledRun(
        h=h,
        t=times,
        states=states,
        inputs=inputs,
        outputs=outputs,
        distance=distance,
        deviation=float(np.max(distance)),
        ultimate=ultimate,
        wall_time=time.perf_counter() - started,
        saturated_time=saturated_time,
        disturbance=disturbance,
        iss_ratio=iss_ratio,
    )


def check_sample_time(h: float, horizon: float) -> None:
    """Refuse a sample time that is not a positive number giving a sensible sample count.

    Raises
    ------
    SpecError
        Naming ``--sample-time``.
    """
    if not 0 < h < math.inf:
        raise SpecError("command line", "--sample-time", "must be positive and finite")
    count = math.ceil(horizon / h - 1e-9)
    if count < MIN_SAMPLES:
        raise SpecError(
            "command line",
            "--sample-time",
            f"{h:g} leaves fewer than {MIN_SAMPLES} samples over the horizon {horizon:g}",
        )
    if count > MAX_SAMPLES:
        raise SpecError(
            "command line",
            "--sample-time",
            f"{h:g} makes {count} samples over the horizon {horizon:g}; at most {MAX_SAMPLES}",
        )


def simulate_sampled(
    derivation: Derivation,
    controller: types.ModuleType,
    options: Options,
    h: float,
    convergence_order: bool = False,
    progress: Callable[[float, float], None] | None = None,
    plant_params: dict[str, float] | None = None,
) -> SampledResult:
    """The continuous run, the sampled run at ``h`` and, if asked, at ``h / 2``.

    Parameters
    ----------
    derivation : Derivation
        The derivation the controller was generated from.
    controller : module
        The generated controller (its ``Controller``, ``rhs`` and ``outputs``).
    options : Options
        Horizon, initial state, parameters and the continuous run's solver settings.
    h : float
        Sample time.
    convergence_order : bool, optional
        Also run at ``h / 2`` and report the observed order.
    progress : callable, optional
        As for :func:`~tvopt_codegen.simulation.simulate`.
    plant_params : dict, optional
        The true plant's parameters where they differ from the controller's: the
        sampled runs are of that plant (the continuous one stays the nominal theorem's).

    Returns
    -------
    SampledResult
        Both runs and what holds under sampling.
    """
    check_sample_time(h / 2 if convergence_order else h, options.t_final)
    references = (
        nominal_source(derivation, dict(options.params)) if derivation.model.references else None
    )
    options = bumpless_start(derivation, controller, options, references)
    continuous = simulate(derivation, controller, options, progress=progress)
    failures = list(continuous.failures)
    runs = [sampled_run(derivation, controller, options, h, continuous, progress, plant_params)]
    order = None
    failures += [
        f"|E| exceeds its input-to-state bound along the sampled run (H = {run.h:g}) by a "
        f"factor {run.iss_ratio:.3g}"
        for run in runs
        if not run.iss_ratio <= 1.0
    ]
    orders: list[float] = []
    if convergence_order:
        step = h
        while True:
            step /= 2
            runs.append(
                sampled_run(
                    derivation, controller, options, step, continuous, progress, plant_params
                )
            )
            coarse, fine = runs[-2].deviation, runs[-1].deviation
            order = math.log2(coarse / fine) if coarse > 0 and fine > 0 else float("nan")
            orders.append(order)
            finer = options.t_final / (step / 2) <= MAX_SAMPLES
            if order >= ORDER_FLOOR or len(orders) > EXTRA_HALVINGS or not finer:
                break
        if not order >= ORDER_FLOOR:
            listed = ", ".join(f"{value:.3g}" for value in orders)
            failures.append(
                f"the sampled loop does not approach the continuous one as H shrinks "
                f"(observed order {listed} from H = {h:g} to {step:g}, below {ORDER_FLOOR:g})"
            )
    tail = _tail(continuous.t, options.t_final)
    return SampledResult(
        continuous=continuous,
        runs=tuple(runs),
        order=order,
        continuous_ultimate=float(np.max(continuous.error[tail])),
        passed=not failures,
        failures=tuple(failures),
        plant_params=tuple(
            (name, value)
            for name, value in (plant_params or {}).items()
            if value != (dict(derivation.spec.parameters) | dict(options.params)).get(name)
        ),
        orders=tuple(orders),
    )


def format_sampled(derivation: Derivation, result: SampledResult) -> str:
    """The lines the sampled run adds to the continuous certificate."""
    lines = ["  under sampling (zero-order hold, controller stepped every H):"]
    if result.plant_params:
        mismatch = ", ".join(f"{name} = {value:g}" for name, value in result.plant_params)
        lines.append(
            f"    on a plant that is not the model ({mismatch}): the continuous run is the "
            "nominal theorem's, the sampled ones are the mismatched plant's"
        )
    error = "col(z_I, E)" if derivation.closed_loop.integral_states else "E"
    for run in result.runs:
        saturated = f"; saturated {run.saturated_time:.3g} s" if run.saturated_time else ""
        lines.append(
            f"    H = {run.h:.4g}: max |y - y_continuous| {run.deviation:.3e}; "
            f"ultimate |y - y*| {run.ultimate:.3e} (continuous {result.continuous_ultimate:.3e})"
            f"{saturated}; {len(run.t) - 1} steps in {run.wall_time:.2f} s"
        )
        lines.append(
            f"      input-to-state: {error}_(k+1) = expm(H h) {error}_k + w_k with sup |w| / h "
            f"{run.disturbance:.3g}; |{error}| / its bound max {run.iss_ratio:.3g}"
        )
    if len(result.orders) > 1:
        pairs = ", ".join(
            f"{value:.3g} (H/{2**k:g} to H/{2 ** (k + 1):g})" if k else f"{value:.3g} (H to H/2)"
            for k, value in enumerate(result.orders)
        )
        lines.append(
            f"    observed order in H: {pairs} (1 for a zero-order hold): not yet asymptotic "
            "at H, so H was halved again"
        )
    elif result.order is not None:
        lines.append(f"    observed order in H: {result.order:.3g} (1 for a zero-order hold)")
    lines.append(
        "  sampled certificate: "
        + ("PASSED" if result.passed else "FAILED: " + "; ".join(result.failures))
    )
    return "\n".join(lines)
