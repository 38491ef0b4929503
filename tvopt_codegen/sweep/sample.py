"""One sample: run the compiled loop and measure it (errors, settling, the certificate)."""

from __future__ import annotations

import dataclasses
import math
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from tvopt_codegen.contract import Status
from tvopt_codegen.maths.hurwitz import bound_ratio, tracking_bound

if TYPE_CHECKING:
    pass
from tvopt_codegen.sweep.options import SETTLING, Outcome, SweepOptions
from tvopt_codegen.sweep.program import (
    Draw,
    Loop,
    SweepProgram,
    draw,
    loop_for,
    sample_seed,
    tail,
)
from tvopt_codegen.sweep.table import failed_row


@dataclass(frozen=True)
class SampleResult:
    """One row of the summary and, when kept, the run's trajectory.

    Attributes
    ----------
    row : dict
        The summary's columns for this sample.
    trajectory : numpy.ndarray or None
        ``points x columns`` (NaN after a failure); see :attr:`SweepProgram.columns`.
    """

    row: dict[str, Any]
    trajectory: np.ndarray | None


def _settling(t: np.ndarray, error: np.ndarray, fraction: float) -> float:
    """The first time after which ``error`` stays at or below ``fraction`` of its start."""
    above = np.nonzero(error > fraction * error[0])[0]
    if not len(above):
        return 0.0
    last = int(above[-1])
    return float(t[last + 1]) if last + 1 < len(t) else math.nan


def _after(t: np.ndarray, error: np.ndarray, window: float) -> tuple[float, float]:
    """``integral |y - y*| dt`` from ``window`` to the end, and the largest ``|y - y*|`` there.

    The integral is the trapezoid rule's on the output grid: exactly the integral of the
    piecewise-linear interpolant of the error, whose value at ``window`` (between two
    output times) is interpolated. The largest error is at output times ``>= window``.
    """
    inside = t >= window
    kept_t, kept = t[inside], error[inside]
    if not len(kept_t):
        return math.nan, math.nan
    if window < kept_t[0]:
        kept_t = np.concatenate(([window], kept_t))
        kept = np.concatenate(([np.interp(window, t, error)], kept))
    return float(np.trapezoid(kept, kept_t)), float(np.max(error[inside]))


def _certificate(
    program: SweepProgram,
    loop: Loop,
    sample: Draw,
    t: np.ndarray,
    convexity: np.ndarray,
    error: np.ndarray,
) -> bool:
    """Whether ``|y - y*| <= c |E(0)| / m_f e^(-alpha t)`` held (the nominal theorem).

    ``m_f`` is the least eigenvalue of f0's Hessian at y, y* and their midpoint along
    the run (the C loop's last column), as :mod:`tvopt_codegen.simulation` estimates it;
    the bound and the test are :mod:`tvopt_codegen.maths.hurwitz`'s, which ``simulate`` asks too.
    ``program``'s c and alpha (a candidate's gains), not those of the program ``loop`` was
    loaded for (:func:`loop_for` shares a loop among the programs of one key).
    """
    p = program
    cp = sample.cp if len(sample.cp) else np.zeros(1)
    # With integral action the theorem's error is col(z_I, E).
    integrals = sample.s0[list(p.integral_rows)]
    norm0 = float(
        np.hypot(np.linalg.norm(loop.optimality_error(sample.s0, cp)), np.linalg.norm(integrals))
    )
    smallest = float(np.min(convexity))
    if not smallest > 0:
        return False
    _, bound = tracking_bound(t, p.transient(), p.alpha, norm0, smallest)
    return bound_ratio(error, bound) <= 1.0


def _bumpless(program: SweepProgram, options: SweepOptions, loop: Loop, sample: Draw) -> Draw:
    """The draw with integral states that ``--initial`` does not set at ``z*(E(0))``.

    As ``simulate`` and the generated Controller start them (see
    :func:`~tvopt_codegen.maths.hurwitz.integral_split`); E at the model's parameters.
    """
    if not program.integral_rows:
        return sample
    given = {name for name, _ in options.initial}
    cp = sample.cp if len(sample.cp) else np.zeros(1)
    width = len(program.integral_rows)
    error = loop.optimality_error(sample.s0, cp).reshape(program.k, width)
    start = np.asarray(program.bumpless) @ error
    s0 = sample.s0.copy()
    for row, value in zip(program.integral_rows, start, strict=True):
        if program.state_names[row] not in given and np.isfinite(value):
            s0[row] = value
    return dataclasses.replace(sample, s0=s0)


def run_sample(
    program: SweepProgram, options: SweepOptions, index: int, keep: bool = False
) -> SampleResult:
    """Run sample ``index`` and measure it; keep its trajectory when asked."""
    loop = loop_for(program)
    sample = _bumpless(program, options, loop, draw(program, options, index))
    outcome, rows, info = loop.run(options, sample, program)
    n, m = len(program.state_names), len(program.output_names)
    nu = len(program.input_names)
    t = rows[:, 0]
    y = rows[:, 1 + n : 1 + n + m]
    target = rows[:, 1 + n + m : 1 + n + 2 * m]
    u = rows[:, 1 + n + 2 * m : 1 + n + 2 * m + nu]
    logdet, convexity = tail(rows, "log_det_R"), tail(rows, "m_f")
    margin, largest = tail(rows, "margin"), tail(rows, "max_constraint")
    error = np.linalg.norm(y - target, axis=1) if len(rows) else np.zeros(0)
    ok = outcome == Status.OK
    saturated = tail(rows, "saturated") > 0.5
    spacing = options.t_final / (options.points - 1)
    mismatch = bool(np.any(sample.cp != sample.pp))
    nominal = (
        ok
        and not mismatch
        and not saturated.any()
        and options.sample_time is None
        and not options.noise
    )
    row: dict[str, Any] = {
        "sample": index,
        "seed": sample.seed,
        "status": outcome.label,
        "t_end": float(info[0]),
        "final_error": float(error[-1]) if ok else math.nan,
        "max_error": float(error.max()) if ok else math.nan,
        "settling_1pct": _settling(t, error, SETTLING[0]) if ok else math.nan,
        "settling_01pct": _settling(t, error, SETTLING[1]) if ok else math.nan,
    }
    row["integrated_error"], row["max_error_after"] = (
        _after(t, error, options.window) if ok else (math.nan, math.nan)
    )
    for j, name in enumerate(program.input_names):
        row[f"max_abs_{name}"] = float(np.abs(u[:, j]).max()) if len(rows) else math.nan
    row["time_saturated"] = float(saturated[:-1].sum() * spacing) if len(rows) else 0.0
    # log|det R| is -inf where R is singular: the ratio is then 0.
    if not len(rows):
        row["min_det_ratio"] = math.nan
    elif np.isfinite(logdet[0]):
        row["min_det_ratio"] = float(np.exp(np.min(logdet) - logdet[0]))
    else:
        row["min_det_ratio"] = 0.0
    if program.constraints:
        # The barrier keeps g_i < s(t) (the certificate's claim); g_i > 0 alone is allowed
        # while the slack is still open.
        row["min_margin"] = float(np.min(margin)) if len(rows) else math.nan
        row["violations"] = int(np.sum(margin <= 0.0))
        row["time_outside"] = float(np.sum(largest[:-1] > 0.0) * spacing) if len(rows) else 0.0
        row["final_constraint"] = float(largest[-1]) if ok else math.nan
    if program.equalities:
        # max_j |a_j| along the run: the KKT law drives it to 0 like E.
        drift = tail(rows, "max_equality")
        row["max_equality"] = float(np.max(drift)) if len(rows) else math.nan
        row["final_equality"] = float(drift[-1]) if ok else math.nan
    row["steps"] = int(info[2])
    row["rejected_steps"] = int(info[3])
    row["nominal"] = nominal
    row["certificate_holds"] = (
        _certificate(program, loop, sample, t, convexity, error) if nominal else None
    )
    row |= sample.values
    row["error"] = None
    return SampleResult(row, rows if keep else None)


#: The nominal check's horizon, as a fraction of the sweep's: the law's first instants.
NOMINAL_SPAN = 1e-9


def nominal_start(program: SweepProgram, options: SweepOptions) -> Outcome:
    """How the loop starts from the sweep's centre: the law's status at its first instant.

    The centre is the spec's initial state with each ``--initial`` at its centre (mean,
    midpoint, median), and the spec's parameters for the controller and the plant alike
    (the nominal plant is the model); no noise. The loop runs for a vanishing horizon
    (:data:`NOMINAL_SPAN` of the sweep's), so the outcome is the law's at t = 0: a
    status other than ``OK`` means the law is undefined where every sample starts or
    near it.
    """
    loop = loop_for(program)
    s0 = np.array(program.initial_state, dtype=float)
    for name, dist in options.initial:
        s0[program.state_names.index(name)] = dist.centre
    defaults = np.array(program.defaults, dtype=float)
    centre = Draw(-1, 0, {}, s0, defaults, defaults.copy(), None)
    centre = _bumpless(program, options, loop, centre)
    span = options.t_final * NOMINAL_SPAN
    # A horizon near the smallest float would underflow to 0: then the whole (tiny) run.
    if not span >= sys.float_info.min:
        span = options.t_final
    brief = dataclasses.replace(options, t_final=span, points=2, noise=0.0)
    outcome, _, _ = loop.run(brief, centre, program)
    return outcome


def run_chunk(
    program: SweepProgram, options: SweepOptions, indices: Sequence[int], keep: bool
) -> list[SampleResult]:
    """Samples ``indices`` in this process (what one Dask task runs).

    A sample whose run raises is a row with status ``error`` and the exception's
    message: one sample never stops the sweep (nor loses its chunk's other samples).
    """
    results = []
    for index in indices:
        try:
            results.append(run_sample(program, options, index, keep))
        except Exception as exc:  # noqa: BLE001 - any failure of one sample is its outcome
            seed = sample_seed(options.seed, index)
            results.append(SampleResult(failed_row(program, options, index, seed, exc), None))
    return results
