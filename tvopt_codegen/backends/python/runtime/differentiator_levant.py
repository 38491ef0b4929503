"""Levant's robust exact differentiator, discretized with Taylor terms.

Its recursive right-hand side and one step (Livne and Levant, "Proper discretization of
homogeneity-based differentiators", 2014). The C twin is in
``templates/c/runtime/controller.jinja``, operation for operation.
"""

from __future__ import annotations

import math

from tvopt_codegen.backends.python.runtime.chains import _taylor_shift
from tvopt_codegen.backends.python.runtime.provided import (
    _ESTIMATOR_GAINS,
    _ESTIMATOR_ORDER,
    ESTIMATOR_LIPSCHITZ,
)

# --- copied verbatim into the generated controller below this line ---


def _estimator_rates(xi: list[float], sample: float) -> list[float]:
    """The differentiator's right-hand side for one reference (xi: its jet estimate)."""
    rates = []
    # Levant's recursive form: v_0 from the sampling error, each v_j from z_j - v_{j-1}.
    q = _ESTIMATOR_ORDER
    previous = sample
    for j in range(q + 1):
        power = (q - j) / (q + 1 - j)
        gain = _ESTIMATOR_GAINS[q - j] * ESTIMATOR_LIPSCHITZ ** (1.0 / (q + 1 - j))
        error = xi[j] - previous
        correction = -gain * abs(error) ** power * math.copysign(1.0, error) if error else 0.0
        rates.append(correction + (xi[j + 1] if j < q else 0.0))
        previous = rates[-1]
    return rates


def _estimator_step(xi: list[float], previous: float, sample: float, h: float) -> list[float]:
    """One reference's jet estimate ``h`` seconds on, given the last sample and the newest."""
    # Euler with the Taylor terms of the chain (Livne and Levant, "Proper discretization
    # of homogeneity-based differentiators", 2014): exact for the chain itself.
    q = _ESTIMATOR_ORDER
    rates = _estimator_rates(xi, sample)
    shifted = _taylor_shift(xi, h)
    return [shifted[j] + h * (rates[j] - (xi[j + 1] if j < q else 0.0)) for j in range(q + 1)]
