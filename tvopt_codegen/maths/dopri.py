"""Dormand-Prince RK45 with scipy's error control and dense output, in NumPy.

The same arithmetic as ``scipy.integrate.solve_ivp(method="RK45", dense_output=True)``,
operation for operation, so that its steps and states are scipy's bit for bit
(``tests/test_simulate.py`` compares them). ``simulate`` integrates with it because
``scipy.integrate`` cannot be imported alone: its package pulls in ``scipy.optimize``,
``scipy.special`` and ``scipy.spatial``, a third of a small ``simulate``'s time. The
other ``--method`` choices still go to ``solve_ivp``.

The tableau here is also the one the C run-time library prints
(``templates/c/runtime/rk45.jinja``), so the sweep's compiled loop and ``simulate``
step alike.

References: J. R. Dormand, P. J. Prince, "A family of embedded Runge-Kutta formulae",
J. Comput. Appl. Math. 6 (1980); L. F. Shampine, "Some Practical Runge-Kutta Formulas",
Math. Comp. 46 (1986) for the dense output; E. Hairer, S. P. Norsett, G. Wanner,
"Solving Ordinary Differential Equations I", Sec. II.4 for the first step.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

C = np.array([0, 1 / 5, 3 / 10, 4 / 5, 8 / 9, 1])
A = np.array(
    [
        [0, 0, 0, 0, 0],
        [1 / 5, 0, 0, 0, 0],
        [3 / 40, 9 / 40, 0, 0, 0],
        [44 / 45, -56 / 15, 32 / 9, 0, 0],
        [19372 / 6561, -25360 / 2187, 64448 / 6561, -212 / 729, 0],
        [9017 / 3168, -355 / 33, 46732 / 5247, 49 / 176, -5103 / 18656],
    ]
)
B = np.array([35 / 384, 0, 500 / 1113, 125 / 192, -2187 / 6784, 11 / 84])
E = np.array([-71 / 57600, 0, 71 / 16695, -71 / 1920, 17253 / 339200, -22 / 525, 1 / 40])
#: Shampine's dense output, the coefficients of x, x^2, x^3, x^4 per stage.
P = np.array(
    [
        [1, -8048581381 / 2820520608, 8663915743 / 2820520608, -12715105075 / 11282082432],
        [0, 0, 0, 0],
        [
            0,
            131558114200 / 32700410799,
            -68118460800 / 10900136933,
            87487479700 / 32700410799,
        ],
        [0, -1754552775 / 470086768, 14199869525 / 1410260304, -10690763975 / 1880347072],
        [
            0,
            127303824393 / 49829197408,
            -318862633887 / 49829197408,
            701980252875 / 199316789632,
        ],
        [0, -282668133 / 205662961, 2019193451 / 616988883, -1453857185 / 822651844],
        [0, 40617522 / 29380423, -110615467 / 29380423, 69997945 / 29380423],
    ]
)
#: The step-size controller's safety factor and its bounds on a step's change.
SAFETY, MIN_FACTOR, MAX_FACTOR = 0.9, 0.2, 10
#: The error estimate is of order 4: a step's factor is error_norm ** (-1 / 5).
ERROR_EXPONENT = -1 / 5
#: The smallest relative tolerance honoured (scipy raises smaller ones to it).
SMALLEST_RTOL = 100 * np.finfo(float).eps

REACHED = "The solver successfully reached the end of the integration interval."
TOO_SMALL = "Required step size is less than spacing between numbers."

Field = Callable[[float, np.ndarray], np.ndarray]


def _rms(x: np.ndarray) -> float:
    """The root mean square of ``x`` (scipy's norm of a scaled error)."""
    return float(np.linalg.norm(x) / x.size**0.5)


class DenseSolution:
    """The run between its steps: Shampine's quartic on each step, as ``OdeSolution``.

    At a step's end point the earlier step is used, as scipy's.
    """

    def __init__(self, ts: np.ndarray, starts: np.ndarray, widths: np.ndarray, q: np.ndarray):
        self.ts = ts
        self._starts = starts  # (segments, n): the state at each step's start
        self._widths = widths  # (segments,): each step's length
        self._q = q  # (segments, n, 4): K^T P of each step

    def _segment(self, t: np.ndarray) -> np.ndarray:
        index = np.searchsorted(self.ts, t, side="left") - 1
        return np.clip(index, 0, len(self._widths) - 1)

    def __call__(self, t: float | np.ndarray) -> np.ndarray:
        """The state at ``t`` (shape ``(n,)``), or at each of several (``(n, len(t))``)."""
        t = np.asarray(t, dtype=float)
        if t.ndim == 0:
            i = int(self._segment(t))
            h = self._widths[i]
            p = np.cumprod(np.tile((t - self.ts[i]) / h, 4))
            y: np.ndarray = h * np.dot(self._q[i], p)
            y += self._starts[i]
            return y
        out = np.empty((self._starts.shape[1], len(t)))
        segments = self._segment(t)
        for i in np.unique(segments):
            chosen = segments == i
            h = self._widths[i]
            x = (t[chosen] - self.ts[i]) / h
            p = np.cumprod(np.tile(x, (4, 1)), axis=0)
            part = h * np.dot(self._q[i], p)
            part += self._starts[i][:, None]
            out[:, chosen] = part
        return out


@dataclass(frozen=True)
class Solution:
    """What ``solve_ivp`` returns that a run needs: steps, states, dense output."""

    t: np.ndarray
    y: np.ndarray
    sol: DenseSolution | None
    nfev: int
    success: bool
    message: str


def first_step(
    fun: Field, t0: float, y0: np.ndarray, f0: np.ndarray, interval: float, rtol: float, atol: float
) -> float:
    """Hairer, Norsett and Wanner's first step, from two evaluations of the field."""
    if interval == 0.0:
        return 0.0
    scale = atol + np.abs(y0) * rtol
    d0, d1 = _rms(y0 / scale), _rms(f0 / scale)
    h0 = 1e-6 if d0 < 1e-5 or d1 < 1e-5 else 0.01 * d0 / d1
    h0 = min(h0, interval)
    f1 = fun(t0 + h0, y0 + h0 * f0)
    d2 = _rms((f1 - f0) / scale) / h0
    if d1 <= 1e-15 and d2 <= 1e-15:
        h1 = max(1e-6, h0 * 1e-3)
    else:
        h1 = (0.01 / max(d1, d2)) ** (1 / 5)
    return min(100 * h0, h1, interval)


def integrate(fun: Field, t_final: float, y0: np.ndarray, rtol: float, atol: float) -> Solution:
    """Integrate ``y' = fun(t, y)`` from 0 to ``t_final`` (positive), as scipy's RK45.

    Exceptions of ``fun`` propagate. A step that would be shorter than ten units in the
    last place of ``t`` ends the run unsuccessfully, as scipy's does.
    """
    calls = [0]

    def field(t: float, y: np.ndarray) -> np.ndarray:
        calls[0] += 1
        return np.asarray(fun(t, y), dtype=float)

    rtol = max(rtol, SMALLEST_RTOL)
    y = np.asarray(y0, dtype=float)
    t = 0.0
    f = field(t, y)
    h_abs = first_step(field, t, y, f, abs(t_final - t), rtol, atol)
    K = np.empty((7, len(y)))
    times, states, starts, widths, qs = [t], [y], [], [], []
    success, message = True, REACHED
    while t != t_final:
        min_step = 10 * np.abs(np.nextafter(t, np.inf) - t)
        h_abs = max(h_abs, min_step)
        rejected = False
        while True:
            if h_abs < min_step:
                success, message = False, TOO_SMALL
                break
            t_new = min(t + h_abs, t_final)
            h = t_new - t
            h_abs = np.abs(h)
            K[0] = f
            for s in range(1, 6):
                K[s] = field(t + C[s] * h, y + np.dot(K[:s].T, A[s, :s]) * h)
            y_new = y + h * np.dot(K[:-1].T, B)
            f_new = field(t + h, y_new)
            K[-1] = f_new
            scale = atol + np.maximum(np.abs(y), np.abs(y_new)) * rtol
            error_norm = _rms(np.dot(K.T, E) * h / scale)
            if error_norm < 1:
                factor = (
                    MAX_FACTOR
                    if error_norm == 0
                    else min(MAX_FACTOR, SAFETY * error_norm**ERROR_EXPONENT)
                )
                h_abs *= min(1, factor) if rejected else factor
                break
            h_abs *= max(MIN_FACTOR, SAFETY * error_norm**ERROR_EXPONENT)
            rejected = True
        if not success:
            break
        starts.append(y)
        widths.append(h)
        qs.append(K.T.dot(P))
        t, y, f = t_new, y_new, f_new
        times.append(t)
        states.append(y)
    ts = np.array(times)
    dense = None
    if widths:
        dense = DenseSolution(ts, np.array(starts), np.array(widths), np.array(qs))
    return Solution(ts, np.array(states).T, dense, calls[0], success, message)
