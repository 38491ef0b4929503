"""The certificate of a run: what the paper's theorem promises, checked.

``E`` against ``expm(H t) E(0)``, the bound on ``|y - y*|``, the constraints' margins and
the input-to-state bound with estimated reference jets.
"""

from __future__ import annotations

import math
import types
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np

from tvopt_codegen.derivation import Derivation
from tvopt_codegen.maths import hurwitz
from tvopt_codegen.runs.side import Side
from tvopt_codegen.simulation.direct import point_function, point_kernel
from tvopt_codegen.simulation.references import ReferenceSource
from tvopt_codegen.simulation.result import Options, Result, Trajectories
from tvopt_codegen.simulation.target import _reference_values, kkt_path, minimizer_path

#: The certificate is vacuous when the convexity modulus along the run is below this
#: fraction of the Hessian's scale there (its largest eigenvalue in magnitude).
VACUOUS_M_F = 1e-6


_Jets = Callable[[float], dict[str, Any]]


def _jets(references: ReferenceSource | None) -> tuple[_Jets, _Jets]:
    """The reference jets the controller got, and the true ones E and y* are measured with.

    When the jets are estimated, the estimate's error is the disturbance d of
    ``E' = H E + d``.
    """
    given: _Jets = lambda t: {}  # noqa: E731
    if references is None:
        return given, given
    source = references
    truth = source.exact or source.jets
    return (lambda t: {"refs": source.jets(t)}), (lambda t: {"refs": truth(t)})


def _target(
    d: Derivation,
    controller: types.ModuleType,
    options: Options,
    ts: np.ndarray,
    states: np.ndarray,
    outputs: np.ndarray,
    true: _Jets,
) -> tuple[np.ndarray, Any, Any, Any]:
    """``y*`` along the run, found without the law (with equalities, ``(y*, nu*)``).

    Returns the target, and with equality constraints their evaluator, the multipliers
    along the run and the KKT path (``None`` otherwise).
    """
    # No overrides is None: the module's one-point path then skips reading a mapping.
    params = dict(options.params) or None
    if not d.model.equalities:
        return (
            minimizer_path(
                controller,
                ts,
                outputs[:, -1],
                params,
                true,
                outputs,
                quadratic=d.objective.convexity.quadratic,
            ),
            None,
            None,
            None,
        )
    from tvopt_codegen.simulation.constraints import equalities  # noqa: PLC0415

    values = {
        q: options.params.get(q.name, v)
        for q, v in zip(d.model.params, d.model.defaults, strict=True)
    }
    eq = equalities(d.model, values)
    rows = [d.closed_loop.state_names.index(chain[0]) for chain in d.closed_loop.multiplier_states]
    multipliers = states[rows]
    start = np.concatenate([outputs[:, -1], multipliers[:, -1]])
    kkt = kkt_path(controller, eq, ts, start, params, true)
    return kkt[: len(d.spec.outputs)], eq, multipliers, kkt


def _modulus(
    d: Derivation,
    controller: types.ModuleType,
    params: Mapping[str, float] | None,
    ts: np.ndarray,
    outputs: np.ndarray,
    target: np.ndarray,
    equalities: tuple[Any, Any, Any],
    true: _Jets,
    failures: list[str],
) -> float:
    """m_f along the run (with equalities, the KKT matrix's smallest singular value).

    A modulus that is not positive, or vacuously small against the Hessian's scale, is a
    failure (and NaN).
    """
    eq, multipliers, kkt = equalities
    if eq is not None:
        # |w - w*| <= |F(w)| / sigma_min(K) along the segment, and |y - y*| <= |w - w*|:
        # the KKT matrix's smallest singular value takes m_f's place.
        eigenvalues = np.abs(
            _kkt_eigenvalues(d, controller, eq, ts, outputs, multipliers, kkt, params, true)
        )
    else:
        hessian = point_function(controller, "hessian", params)
        matrices = []
        for i, t in enumerate(ts):
            extra = true(t)
            for point in (outputs[:, i], target[:, i], 0.5 * (outputs[:, i] + target[:, i])):
                matrices.append(hessian(t, point, **extra))
        # One call on the stack: LAPACK's solver on each matrix, as one call per matrix
        # (the same values), without NumPy's cost per call, most of it for a small m.
        eigenvalues = np.linalg.eigvalsh(np.array(matrices, dtype=float))
    m_f = float(eigenvalues.min())
    scale = float(np.abs(eigenvalues).max())
    if eq is not None and not m_f > 0:
        failures.append(f"the KKT matrix is singular along the run (sigma_min = {m_f:.3g})")
        return float("nan")
    if not m_f > 0:
        failures.append(f"f0 is not strongly convex along the run (m_f = {m_f:.3g})")
        return float("nan")
    if m_f <= VACUOUS_M_F * scale and eq is not None:
        failures.append(
            f"the bound is vacuous: the KKT matrix's smallest singular value {m_f:.3g} is "
            f"below {VACUOUS_M_F:g} of its scale {scale:.3g} along the run (the constraints "
            "are nearly dependent or in conflict there, not f0 flat)"
        )
    elif m_f <= VACUOUS_M_F * scale:
        failures.append(
            f"the bound is vacuous: m_f = {m_f:.3g} is below {VACUOUS_M_F:g} of the Hessian's "
            f"scale {scale:.3g} along the run (f0 is barely strongly convex there)"
        )
    return m_f


def _fitted_rate(ts: np.ndarray, flat: np.ndarray, t_end: float) -> float:
    """|E|'s decay rate, fitted where the slowest pole dominates.

    That is the second half of the stretch where |E| is still above the integration
    noise.
    """
    norms = np.linalg.norm(flat, axis=1)
    valid = norms > 1e-9 * max(float(norms[0]), 1e-300)
    last = ts[valid][-1] if valid.any() else t_end
    window = valid & (ts >= last / 2)
    if window.sum() < 3:
        return float("nan")
    return float(-np.polyfit(ts[window], np.log(norms[window]), 1)[0])


def augmented_error(d: Derivation, states: np.ndarray, flat: np.ndarray) -> np.ndarray:
    """The error the theorem is about, one row per time: ``E``, or ``col(z_I, E)``.

    With integral action the controller's integrals of ``grad f0`` come first: that is
    the state of ``col(z_I, E)' = H_I col(z_I, E)`` (``states``: one column per time).
    """
    if not d.closed_loop.integral_states:
        return flat
    rows = [d.closed_loop.state_names.index(name) for name in d.closed_loop.integral_states]
    return np.hstack([states[rows].T, flat])


def _certify(
    d: Derivation,
    controller: types.ModuleType,
    options: Options,
    solution: Any,
    wall: float,
    references: ReferenceSource | None = None,
    side: Side | None = None,
    early: Callable[[Trajectories], None] | None = None,
) -> Result:
    """Sample the run and check the theorem along it.

    ``side``: see :func:`tvopt_codegen.simulation.constraints.check_run`; ``early`` is
    given the sampled run before the checks.
    """
    # One pass over the run's samples, each check of the certificate in the order the
    # summary prints them; the heavy parts are the helpers above.
    # No overrides is None: the module's one-point path then skips reading a mapping.
    params = dict(options.params) or None
    given, true = _jets(references)
    failures: list[str] = []
    if not solution.success:
        failures.append(f"integration stopped: {solution.message}")
    t_end = float(solution.t[-1])
    ts = np.linspace(0.0, t_end, options.points)
    states = solution.sol(ts)
    # The module's one-point kernels where it has them (simulation.direct): the same
    # numbers as its public functions, without their checks of these arrays.
    control = point_function(controller, "control", params)
    optimality_error = point_function(controller, "optimality_error", params)
    with np.errstate(all="ignore"):
        inputs = np.array([control(t, states[:, i], **given(t)) for i, t in enumerate(ts)]).T
        E = np.array([optimality_error(t, states[:, i], **true(t)) for i, t in enumerate(ts)])
    # y = h(x) by the generated module's own outputs (h holds no t).
    outputs = np.asarray(controller.outputs(0.0, states[: len(d.spec.states)], params))
    target, eq, multipliers, kkt = _target(d, controller, options, ts, states, outputs, true)
    if early is not None:
        early(Trajectories(options, ts, states, inputs, outputs, target, references))
    error = np.linalg.norm(outputs - target, axis=0)

    flat = augmented_error(d, states, E.reshape(len(ts), -1))
    norm0 = float(np.linalg.norm(flat[0]))
    predicted = hurwitz.flow(d.dynamics.coefficients, d.jet.n_kkt, flat[0], ts)
    deviation = float(np.max(np.linalg.norm(flat - predicted, axis=1))) / max(norm0, 1e-300)
    estimated = references is not None and references.estimated
    disturbance = iss_ratio = iss_final = float("nan")
    if estimated:
        disturbance, iss_ratio, iss_final = _input_to_state(
            d, controller, params, solution, ts, flat, true
        )
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
    alpha, c = d.dynamics.certified_rate, d.dynamics.transient_constant
    m_f = _modulus(
        d, controller, params, ts, outputs, target, (eq, multipliers, kkt), true, failures
    )
    C, bound = hurwitz.tracking_bound(ts, c, alpha, norm0, m_f)
    if not estimated and np.isfinite(C) and error[0] > 0 and bound[-1] >= error[0]:
        failures.append(
            f"the bound is vacuous: C e^(-alpha t) = {bound[-1]:.3g} at the end of the run "
            f"is still above the initial |y - y*| = {error[0]:.3g}"
        )
    ratio = hurwitz.bound_ratio(error, bound)
    if not estimated and not ratio <= 1.0:
        failures.append(f"|y - y*| exceeds the bound C e^(-alpha t) by a factor {ratio:.3g}")
    constrained = _constraint_check(
        d, options, ts, outputs, error, target, references, failures, side
    )
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
    return Result(
        options=options,
        t=ts,
        states=states,
        inputs=inputs,
        outputs=outputs,
        target=target,
        error=error,
        E=E,
        E_predicted=predicted[:, flat.shape[1] - E[0].size :].reshape(E.shape),
        alpha=alpha,
        alpha_exact=d.dynamics.certified_rate_exact,
        c=c,
        m_f=m_f,
        C=C,
        bound=bound,
        deviation=deviation,
        bound_ratio=ratio,
        fitted_rate=_fitted_rate(ts, flat, t_end),
        nfev=int(solution.nfev),
        wall_time=wall,
        passed=not failures,
        failures=tuple(failures),
        dense=solution.sol,
        references=references,
        disturbance=disturbance,
        iss_ratio=iss_ratio,
        iss_final=iss_final,
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
    params: Mapping[str, float] | None,
    true: Callable[[float], dict[str, Any]],
) -> np.ndarray:
    """The KKT matrix's eigenvalues at the run's (y, nu), at (y*, nu*) and midway."""
    from tvopt_codegen.simulation.constraints import kkt_matrix  # noqa: PLC0415

    m = len(d.model.y)
    run = np.vstack([outputs, multipliers])
    found = []
    for i, t in enumerate(ts):
        extra = true(float(t))
        r = _reference_values(extra)
        for point in (run[:, i], kkt[:, i], 0.5 * (run[:, i] + kkt[:, i])):
            y, nu = point[:m], point[m:]
            hess = controller.hessian(float(t), y, params, **extra)
            matrix = kkt_matrix(hess + eq.curvature(t, y, r, nu), eq.jacobian_a(t, y, r))
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
    side: Side | None = None,
) -> Any:
    """For a spec with constraints: check them along the run, adding to ``failures``."""
    if not d.model.constraints and not d.model.equalities:
        return None
    from tvopt_codegen.simulation.constraints import (  # noqa: PLC0415
        check_run,
        parameter_values,
    )

    values = parameter_values(d.model, options.params)
    constrained = check_run(d.model, ts, outputs, error, target, values, references, side=side)
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
    params: Mapping[str, float] | None,
    solution: Any,
    ts: np.ndarray,
    flat: np.ndarray,
    true: Callable[[float], dict[str, Any]],
) -> tuple[float, float, float]:
    """``sup |d|`` of ``E' = H E + d``, the largest ``|E| / bound``, and the final bound.

    ``E'`` by central differences of ``E`` read from the run's interpolant, on a grid ten
    times finer than the output's; the bound is the variation-of-constants one,
    ``c e^{-alpha t} |E(0)| + int_0^t c e^{-alpha (t - s)} |d(s)| ds``, with the certified
    ``alpha`` and ``c`` of ``|expm(H t)| <= c e^{-alpha t}``: the disturbance fades from it
    as it fades from E (the estimator's start does not weigh on the end of the run).
    """
    H = hurwitz.error_matrix(d.dynamics.coefficients, d.jet.n_kkt)
    horizon = float(ts[-1])
    fine = np.linspace(0.0, horizon, 10 * (len(ts) - 1) + 1)
    step = 1e-6 * max(1.0, horizon)
    # E at every fine time and a step on either side, as rows: the run's state read
    # from its interpolant (at all times at once where that is each time's value to
    # the bit), E by the module's one-point kernel where it answers (simulation.direct).
    base: list[float] = fine.tolist()
    times = [*base, *(t + step for t in base), *(t - step for t in base)]
    clamped = [min(max(t, 0.0), horizon) for t in times]
    if getattr(solution, "pointwise", False):
        states = np.asarray(solution.sol(np.array(clamped)), dtype=float)
        columns = [states[:, i] for i in range(len(times))]
    else:
        columns = [np.asarray(solution.sol(t), dtype=float) for t in clamped]
    kernel = point_kernel(controller, "optimality_error", params)
    rows = []
    with np.errstate(all="ignore"):
        for t, state in zip(times, columns, strict=True):
            extra = true(t)
            value: Any = None
            if kernel is not None and state.ndim == 1:
                refs = extra.get("refs")
                jets = None if refs is None else np.asarray(refs, dtype=float).ravel().tolist()
                value = kernel(t, state.tolist(), jets)
            if value is None:
                value = np.asarray(
                    controller.optimality_error(t, state, params, **extra), dtype=float
                ).ravel()
            rows.append(value)
    flat = np.array(rows, dtype=float)
    if d.closed_loop.integral_states:
        flat = augmented_error(d, np.column_stack(columns), flat)
    count = len(fine)
    errors = flat[:count]
    rates = (flat[count : 2 * count] - flat[2 * count :]) / (2 * step)
    d_norm = np.linalg.norm(rates - errors @ H.T, axis=1)
    d_norm[0], d_norm[-1] = d_norm[1], d_norm[-2]  # one-sided there: take the neighbours'
    alpha, c = d.dynamics.certified_rate, d.dynamics.transient_constant
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
    return float(np.max(d_norm)), ratio, float(bound[-1])


def format_certificate(derivation: Derivation, result: Result) -> str:
    """The one-screen summary of a run and its certificate."""
    d, r = derivation, result
    if r.references is not None and r.references.estimated:
        return _format_estimated(d, r)
    integral = bool(d.closed_loop.integral_states)
    error0 = float(np.linalg.norm(augmented_error(d, r.states[:, :1], r.E[:1].reshape(1, -1))))
    lines = [
        f"{d.spec.name}: closed loop over [0, {r.t[-1]:g}] with {r.options.method} "
        f"(rtol {r.options.rtol:g}, atol {r.options.atol:g})",
        f"  final |y - y*|            {r.error[-1]:.3e}   (initial {r.error[0]:.3e})",
        f"  decay rate of |E|         {r.fitted_rate:.4g} fitted, alpha = {r.alpha:.4g}"
        + ("" if r.alpha_exact else " (repeated poles: 10% margin)"),
        ("  col(z_I, E) vs expm(H_I t) " if integral else "  E vs expm(H t) E(0)       ")
        + f"max relative deviation {r.deviation:.3e} (limit {r.options.tolerance:g})",
        f"  |y - y*| <= C e^(-alpha t)  max ratio {r.bound_ratio:.3g}  "
        f"(C = {r.C:.4g}: c = {r.c:.4g}, m_f = {r.m_f:.4g}, "
        f"|{'col(z_I, E)' if integral else 'E'}(0)| = {error0:.4g})",
        f"  RHS evaluations           {r.nfev}   wall time {r.wall_time:.2f} s",
        "  certificate: " + ("PASSED" if r.passed else "FAILED: " + "; ".join(r.failures)),
    ]
    if r.reintegrated:
        lines.insert(-1, f"  integrated again: {r.reintegrated}")
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
            "  constraints (interior-point homotopy on B = f0 - mu sum log(s - g_i)):",
            f"    min over t and i of s - g_i   {float(check.margins.min()):.3e}  (> 0: no "
            "instant on or past a barrier)",
            f"    g_i at the end (<= 0 holds)   {finals}",
            f"    |y - y*_constrained| at the end {check.distance[-1]:.3e} <= bound "
            f"{check.bound[-1]:.3e}  (|y - y*_B| + sqrt(2 p mu / m_f), m_f = {check.m_f:.4g}; "
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
        f"  final |y - y*| guaranteed <= {r.iss_final / r.m_f:.3e}   (the bound on |E| at "
        f"t = {r.t[-1]:g}, {r.iss_final:.3e}, over m_f = {r.m_f:.4g}; observed "
        f"{r.error[-1]:.3e})",
        f"  RHS evaluations           {r.nfev}   wall time {r.wall_time:.2f} s",
        "  certificate: " + ("PASSED" if r.passed else "FAILED: " + "; ".join(r.failures)),
    ]
    if source.exact is None:
        lines.insert(3, "  (no nominal reference: E is measured against the estimate itself)")
    return "\n".join(lines)
