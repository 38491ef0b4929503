"""The linear (high-gain) reference differentiator, every pole at -bandwidth.

Its right-hand side and one step, integrated by RK4 on the samples' straight line. The
C twin is in ``templates/c/runtime/controller.jinja``, operation for operation.
"""

from __future__ import annotations

import math

from tvopt_codegen.backends.python.runtime.provided import (
    _ESTIMATOR_GAINS,
    _ESTIMATOR_ORDER,
    _FORGETTING_GAP,
    ESTIMATOR_BANDWIDTH,
)

# --- copied verbatim into the generated controller below this line ---


def _estimator_rates(xi: list[float], sample: float) -> list[float]:
    """The differentiator's right-hand side for one reference (xi: its jet estimate)."""
    rates = []
    error = sample - xi[0]
    for j, gain in enumerate(_ESTIMATOR_GAINS):
        rates.append((xi[j + 1] if j < _ESTIMATOR_ORDER else 0.0) + gain * error)
    return rates


def _estimator_step(xi: list[float], previous: float, sample: float, h: float) -> list[float]:
    """One reference's jet estimate ``h`` seconds on, given the last sample and the newest."""
    # The linear differentiator integrated exactly enough: RK4 with steps of at most a
    # quarter of 1/bandwidth (its poles are all at -bandwidth), the reference between
    # the two samples on their straight line (a first-order hold: holding the newest
    # sample instead leaves an O(h) error in every derivative).
    if h * ESTIMATOR_BANDWIDTH > _FORGETTING_GAP:
        # A gap the estimator has forgotten its state over: its state is the steady state
        # on the samples' line, to rounding (see tvopt_codegen.spec.estimator.FORGETTING_GAP).
        return [sample, (sample - previous) / h] + [0.0] * (_ESTIMATOR_ORDER - 1)
    pieces = max(1, math.ceil(h * ESTIMATOR_BANDWIDTH / 0.25))
    dt = h / pieces
    slope = (sample - previous) / h if h > 0.0 else 0.0
    for piece in range(pieces):
        start = previous + slope * (piece * dt)
        middle = previous + slope * (piece * dt + dt / 2)
        end = previous + slope * ((piece + 1) * dt)
        k1 = _estimator_rates(xi, start)
        k2 = _estimator_rates([a + dt / 2 * b for a, b in zip(xi, k1, strict=True)], middle)
        k3 = _estimator_rates([a + dt / 2 * b for a, b in zip(xi, k2, strict=True)], middle)
        k4 = _estimator_rates([a + dt * b for a, b in zip(xi, k3, strict=True)], end)
        xi = [
            a + dt / 6 * (b + 2 * c + 2 * e + f)
            for a, b, c, e, f in zip(xi, k1, k2, k3, k4, strict=True)
        ]
    return xi
