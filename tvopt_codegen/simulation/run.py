"""The closed loop: integrate the generated controller's ``rhs`` and certify the run."""

from __future__ import annotations

import dataclasses
import math
import time
import types
import warnings
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any, NoReturn

import numpy as np

from tvopt_codegen import symbolic as sx
from tvopt_codegen.contract import Status
from tvopt_codegen.derivation import Derivation
from tvopt_codegen.errors import AssumptionError, SpecError
from tvopt_codegen.maths import dopri
from tvopt_codegen.runs.side import Side
from tvopt_codegen.simulation.certificate import _certify
from tvopt_codegen.simulation.direct import point_kernel
from tvopt_codegen.simulation.references import ReferenceSource, nominal_source
from tvopt_codegen.simulation.result import Options, Result, Trajectories

#: A run whose integrator stopped (its step size collapsed) where ``|det R|`` had fallen
#: below this fraction of its value at t = 0 ran into the singular set of R: the law's
#: failure, told in its own words, not the integrator's "required step size is less than
#: spacing between numbers".
DET_COLLAPSE = 1e-4

#: When a check of the certificate fails, the run is integrated again with this method
#: and these tolerances (or the user's, if tighter), and that run is the one reported:
#: an integrator's error is not the theorem's failure.
CHECK_METHOD = "DOP853"
CHECK_RTOL = 1e-13
CHECK_ATOL = 1e-14


def simulate(
    derivation: Derivation,
    controller: types.ModuleType,
    options: Options,
    progress: Callable[[float, float], None] | None = None,
    references: ReferenceSource | None = None,
    side: Side | None = None,
    early: Callable[[Trajectories], None] | None = None,
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
    side : Side, optional
        For a spec with constraints, a
        :func:`~tvopt_codegen.simulation.constraints.minimiser_process` of its model
        started before the run: it finds the constrained minimisers the certificate
        compares the run with (the same numbers as without it, sooner).
    early : callable, optional
        Given each run integrated, sampled at the output times, before the theorem is
        checked along it (the figures of the run alone are drawn meanwhile). A failed
        check integrates again: the second run is given too, and is the one returned.

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
    options = bumpless_start(d, controller, options, source)
    started = time.perf_counter()
    _check_initial_state(d, controller, options, source)
    # No overrides is None: the module's one-point path then skips reading a mapping.
    field = _Field(controller, params or None, source, progress, options, started)

    on_grid = source is not None and source.estimated and source.times is not None

    def integrate(run: Options) -> Any:
        times = source.times if on_grid and source is not None else None
        return _integrate(field, run, times, field.lists)

    try:
        first = integrate(options)
        if not first.success:
            _refuse_singular_stop(d, options, float(first.t[-1]), np.asarray(first.y)[:, -1])
        result = _certify(
            d, controller, options, first, time.perf_counter() - started, source, side, early
        )
        accurate = dataclasses.replace(
            options,
            method=CHECK_METHOD,
            rtol=min(options.rtol, CHECK_RTOL),
            atol=min(options.atol, CHECK_ATOL),
        )
        if result.passed or on_grid or accurate == options:
            return result
        # A check failed: the integrator's error or the theorem's? The same run,
        # integrated far more accurately, tells them apart.
        second = integrate(accurate)
        if not second.success:
            _refuse_singular_stop(d, accurate, float(second.t[-1]), np.asarray(second.y)[:, -1])
        again = _certify(
            d, controller, accurate, second, time.perf_counter() - started, source, side, early
        )
        verdict = (
            "it passes: the failure was the integrator's error, not the law's"
            if again.passed
            else "it fails as well: the law's, not the integrator's"
        )
        note = (
            f"{options.method} at rtol {options.rtol:g} failed ({'; '.join(result.failures)}); "
            f"with {CHECK_METHOD} at rtol {accurate.rtol:g}, atol {accurate.atol:g} {verdict}"
        )
        return dataclasses.replace(again, reintegrated=note)
    except ArithmeticError as exc:
        if not hasattr(exc, "status"):
            raise
        state = np.asarray(field.last, dtype=float)
        _refuse_undefined(d, controller, options, exc, field.reached, state)


class _Field:
    """The closed loop's field ``rhs(t, s)`` as the integrators ask for it.

    On arrays (``field(t, s)``) or on lists of floats (``field.lists``), by the kernel
    behind the module's ``rhs`` where it has one (:mod:`~tvopt_codegen.simulation.direct`:
    the same numbers, without the public function's checks of arrays made here), else
    by ``rhs`` itself. It keeps the last point asked for (a refusal names it) and
    reports progress at most twice a second once a run has taken two seconds.
    """

    def __init__(
        self,
        controller: types.ModuleType,
        overrides: Mapping[str, float] | None,
        source: ReferenceSource | None,
        progress: Callable[[float, float], None] | None,
        options: Options,
        started: float,
    ) -> None:
        self.controller, self.overrides, self.source = controller, overrides, source
        self.progress, self.horizon = progress, options.t_final
        self.next_report = started + 2.0
        self.direct = point_kernel(controller, "rhs", overrides)
        self.reached = 0.0
        self.last: Any = np.array(options.initial_state, dtype=float)

    def _report(self, t: float) -> None:
        if self.progress is None:
            return
        now = time.perf_counter()
        if now >= self.next_report:
            self.progress(float(t), self.horizon)
            self.next_report = now + 0.5

    def _public(self, t: float, s: np.ndarray) -> np.ndarray:
        if self.source is not None:
            refs = self.source.jets(t)
            jets: np.ndarray = self.controller.rhs(t, s, self.overrides, refs=refs)
            return jets
        result: np.ndarray = self.controller.rhs(t, s, self.overrides)
        return result

    def _rhs_list(self, t: float, s: list[float]) -> list[float]:
        self._report(t)
        if self.direct is not None:
            jets = None if self.source is None else self.source.flat_jets(t)
            values = self.direct(float(t), s, jets)
            if values is not None:
                return values
        answer: list[float] = self._public(t, np.array(s, dtype=float)).tolist()
        return answer

    def lists(self, t: float, s: list[float]) -> list[float]:
        """``rhs`` on a list of floats, as a list of floats."""
        self.reached, self.last = float(t), s
        return self._rhs_list(t, s)

    def __call__(self, t: float, s: np.ndarray) -> np.ndarray:
        """``rhs`` on an array, as an array."""
        self.reached, self.last = float(t), s
        if self.direct is not None and s.ndim == 1:
            return np.array(self._rhs_list(t, s.tolist()))
        self._report(t)
        return self._public(t, s)


def _integrate(
    tracked: Callable[[float, np.ndarray], np.ndarray],
    run: Options,
    times: Any,
    tracked_list: Callable[[float, list[float]], list[float]] | None = None,
) -> Any:
    """One integration of the closed loop.

    On the references' sample grid (``times``), else by the package's Dormand-Prince
    (RK45), else by scipy's other methods. ``tracked_list`` is ``tracked`` on lists of
    floats, for the sample grid's loop.
    """
    # A run that overflows ends in a ControllerError with its time; numpy's own
    # warnings on the way would only add lines to that one-line message.
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        if times is not None:
            if tracked_list is not None:
                return _on_the_sample_grid_lists(
                    tracked_list, run.t_final, np.array(run.initial_state), times
                )
            return _on_the_sample_grid(tracked, run.t_final, np.array(run.initial_state), times)
        if run.method == "RK45":
            return dopri.integrate(
                tracked, run.t_final, np.array(run.initial_state), run.rtol, run.atol
            )
        from scipy.integrate import solve_ivp  # noqa: PLC0415 - a third of simulate

        return solve_ivp(
            tracked,
            (0.0, run.t_final),
            np.array(run.initial_state),
            method=run.method,
            rtol=run.rtol,
            atol=run.atol,
            dense_output=True,
        )


def _refuse_undefined(
    d: Derivation,
    controller: types.ModuleType,
    options: Options,
    exc: ArithmeticError,
    t: float,
    s: np.ndarray,
) -> NoReturn:
    """The one-line refusal of a run along which the law became undefined at ``(t, s)``."""
    if getattr(exc, "status", None) == Status.SINGULAR_DECOUPLING:
        # The evaluation that failed is where R is singular: say so in R's words.
        pivot = getattr(controller, "PIVOT_TOLERANCE", None)
        why = (
            f"a pivot of R's LU fell below {pivot:g} of its largest entry"
            if pivot is not None
            else str(exc)
        )
        raise AssumptionError(
            d.spec.source, "simulation", _singular_message(d, options, t, s, why)
        ) from None
    raise AssumptionError(
        d.spec.source,
        "simulation",
        f"the law became undefined along the run, near t = {t:.6g}: {exc}",
    ) from None


def _state_text(d: Derivation, s: np.ndarray, limit: int = 200) -> str:
    """``name = value, ...`` of a closed-loop state, clipped to ``limit`` characters."""
    text = ", ".join(
        f"{name} = {value:.6g}" for name, value in zip(d.closed_loop.state_names, s, strict=False)
    )
    return text if len(text) <= limit else text[: limit - 3] + "..."


def decoupling_determinant(
    d: Derivation, params: Mapping[str, float]
) -> Callable[[float, np.ndarray], float] | None:
    """``det R`` at a time and closed-loop state, evaluated numerically (None if it cannot be).

    R is the derivation's decoupling matrix; for a mass-matrix plant its entries hold the
    run-time solve ``W = M^-1 B``, done here with the model's ``M`` and ``B``. Built only
    when a run fails (lambdify costs a few milliseconds).
    """
    model = d.model
    values = {p.name: float(v) for p, v in zip(model.params, model.defaults, strict=True)}
    values |= {name: float(v) for name, v in params.items()}
    args = [model.t, *d.closed_loop.states, *model.params]
    try:
        mech = model.mechanics
        if mech is None:
            entries = sx.lambdify([args], d.linearization.R, modules="numpy")

            def matrix(t: float, s: np.ndarray, p: list[float]) -> np.ndarray:
                return np.asarray(entries([t, *s, *p]), dtype=float)

        else:
            gains = [w for row in mech.gains for w in row]
            mass = sx.lambdify([args], sx.matrix(mech.mass_matrix), modules="numpy")
            inputs = sx.lambdify([args], sx.matrix(mech.input_matrix), modules="numpy")
            entries = sx.lambdify([[*args, *gains]], d.linearization.R, modules="numpy")

            def matrix(t: float, s: np.ndarray, p: list[float]) -> np.ndarray:
                point = [t, *s, *p]
                w = np.linalg.solve(
                    np.asarray(mass(point), dtype=float), np.asarray(inputs(point), dtype=float)
                )
                return np.asarray(entries([*point, *w.ravel()]), dtype=float)

        p = [values[q.name] for q in model.params]

        def det(t: float, s: np.ndarray) -> float:
            with np.errstate(all="ignore"):
                return float(np.linalg.det(matrix(t, np.asarray(s, dtype=float), p)))

        det(
            0.0, np.asarray(d.closed_loop.initial_state, dtype=float)
        )  # fails here, not in a message
    except Exception:  # noqa: BLE001 - an R this cannot evaluate: the caller says less
        return None
    return det


def _singular_message(d: Derivation, options: Options, t: float, s: np.ndarray, why: str) -> str:
    """``det R -> 0 at t = ... s (det R = ...), state: ...``: one line."""
    det = decoupling_determinant(d, options.params)
    value = det(t, s) if det is not None else math.nan
    where = f" ({d.decoupling.singular_text})" if d.decoupling.singular_text else ""
    return (
        f"det R -> 0 at t = {t:.6g} s (det R = {value:.3g}; {why}): the run reached the "
        f"singular set of R{where}, where the law is undefined; state: {_state_text(d, s)}"
    )


def _refuse_singular_stop(d: Derivation, options: Options, t: float, s: np.ndarray) -> None:
    """A run whose step size collapsed on R's singular set fails in R's words.

    Raises
    ------
    AssumptionError
        When ``|det R|`` at the last accepted state is below :data:`DET_COLLAPSE` of its
        value at t = 0 (any other stop is left to the certificate, which reports it).
    """
    det = decoupling_determinant(d, options.params)
    if det is None:
        return
    start = abs(det(0.0, np.asarray(options.initial_state, dtype=float)))
    end = abs(det(t, s))
    if not (np.isfinite(end) and start > 0 and end <= DET_COLLAPSE * start):
        return
    why = f"{end / start:.2g} of its value at t = 0, and the integrator's step size collapsed"
    raise AssumptionError(d.spec.source, "simulation", _singular_message(d, options, t, s, why))


def bumpless_start(
    d: Derivation,
    controller: types.ModuleType,
    options: Options,
    references: ReferenceSource | None = None,
) -> Options:
    """The options with integral states that nobody gave starting at ``z*(E(0))``.

    There E moves exactly as under the law without integral action (see
    :func:`~tvopt_codegen.maths.hurwitz.integral_split`), as the generated Controller starts
    when no ``z0`` is given. Unchanged without integral action.
    """
    if not d.closed_loop.integral_states:
        return options
    s0 = np.array(options.initial_state)
    extra = {} if references is None else {"refs": references.jets(0.0)}
    try:
        error = np.asarray(
            controller.optimality_error(0.0, s0, dict(options.params), **extra), dtype=float
        )
    except ArithmeticError:
        # The law is undefined there: _check_initial_state says so, in the spec's words.
        return options
    start = np.asarray(d.dynamics.bumpless) @ error
    state = list(options.initial_state)
    for name, value in zip(d.closed_loop.integral_states, start, strict=True):
        if name not in options.given:
            state[d.closed_loop.state_names.index(name)] = float(value)
    return dataclasses.replace(options, initial_state=tuple(state))


#: Longest step of the fixed-grid integration of a loop fed with estimated references.
MAX_GRID_STEP = 1e-2


@dataclass(frozen=True)
class _GridSolution:
    """What ``solve_ivp`` returns, for a run integrated on the reference samples' grid.

    ``pointwise``: ``sol`` (a piecewise polynomial) at an array of times is ``sol`` at
    each of them, to the bit, so the certificate may ask for all at once.
    """

    t: np.ndarray
    y: np.ndarray
    sol: Any
    nfev: int
    success: bool = True
    message: str = "the end of the horizon was reached"
    pointwise: bool = True


def _sample_grid(horizon: float, sample_times: np.ndarray) -> np.ndarray:
    """The steps' ends of a run on the reference samples' grid.

    Every sample inside the horizon, the horizon, and points between two samples more
    than :data:`MAX_GRID_STEP` apart.
    """
    inside = sample_times[(sample_times > 0.0) & (sample_times < horizon)]
    knots = [0.0]
    for end in (*inside.tolist(), horizon):
        pieces = max(1, math.ceil((end - knots[-1]) / MAX_GRID_STEP - 1e-9))
        if pieces == 1:
            # linspace's last point is its end exactly: one sample interval, one step,
            # without an array per sample (20,000 of them for 20 s at 1 kHz).
            knots.append(end)
        else:
            knots += np.linspace(knots[-1], end, pieces + 1)[1:].tolist()
    return np.array(knots)


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
    grid = _sample_grid(horizon, sample_times)
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
    from scipy.interpolate import CubicHermiteSpline  # noqa: PLC0415 - on this path only

    interpolant = CubicHermiteSpline(grid, states, rates, axis=1)
    return _GridSolution(grid, states, interpolant, 4 * (len(grid) - 1))


def _on_the_sample_grid_lists(
    rhs: Callable[[float, list[float]], list[float]],
    horizon: float,
    start: np.ndarray,
    sample_times: np.ndarray,
) -> _GridSolution:
    """:func:`_on_the_sample_grid` on lists of floats, for a field that takes and gives them.

    A step's arrays of a few numbers cost NumPy more per operation than the arithmetic:
    here each entry takes the same IEEE operations in the same order as there
    (``x + h / 6 * (k1 + 2 k2 + 2 k3 + k4)`` entry by entry), so the run is the same bits.
    """
    grid = _sample_grid(horizon, sample_times)
    knots: list[float] = grid.tolist()
    x: list[float] = start.astype(float).tolist()
    states = [x]
    rates = []
    k4 = x
    for i in range(len(knots) - 1):
        t, h = knots[i], knots[i + 1] - knots[i]
        half, sixth = h / 2, h / 6
        k1 = rhs(t, x)
        rates.append(k1)
        k2 = rhs(t + half, [a + half * b for a, b in zip(x, k1, strict=True)])
        k3 = rhs(t + half, [a + half * b for a, b in zip(x, k2, strict=True)])
        k4 = rhs(t + h, [a + h * b for a, b in zip(x, k3, strict=True)])
        x = [
            a + sixth * (b + 2 * c + 2 * e + f)
            for a, b, c, e, f in zip(x, k1, k2, k3, k4, strict=True)
        ]
        states.append(x)
    # The last rate: the left limit of the last interval's (the jets jump at samples).
    rates.append(k4)
    from scipy.interpolate import CubicHermiteSpline  # noqa: PLC0415 - on this path only

    table = np.array(states, dtype=float).T
    slopes = np.array(rates, dtype=float).T
    interpolant = CubicHermiteSpline(grid, table, slopes, axis=1)
    return _GridSolution(grid, table, interpolant, 4 * (len(grid) - 1))


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
            f"{name} = {value:.6g}"
            for name, value in zip(d.closed_loop.state_names, s0, strict=True)
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
