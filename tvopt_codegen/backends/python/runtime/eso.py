"""The extended-state observer of a controller with ``[robust.eso]``, sampled.

Its discrete gains for a sample time, its step (prediction with each output's ``v``
held, then correction by the newest outputs) and the ``v`` it holds. The C twin is in
``templates/c/runtime/controller.jinja``, operation for operation.
"""

from __future__ import annotations

import math

from tvopt_codegen.backends.python.runtime.linalg import _finite
from tvopt_codegen.backends.python.runtime.provided import (
    _ESO_POLYNOMIALS,
    _ESO_RECOVERY,
    _ESO_ROWS,
    ESO_BANDWIDTH,
    PLANT_STATE_NAMES,
    NonFiniteInputError,
)

# --- copied verbatim into the generated controller below this line ---


#: The largest order among the outputs, the number of gains (r_i + 1 per output), and
#: where the controller states start among the closed loop's rates.
_ESO_ORDER = max(len(rows) for rows in _ESO_ROWS) - 1
_ESO_GAINS = sum(len(rows) for rows in _ESO_ROWS)
_ESO_AT = len(PLANT_STATE_NAMES)


def _eso_gains(h: float) -> list[float]:
    """The extended-state observer's discrete gains for a step h, output by output.

    Each is a polynomial in gamma = 1 - exp(-omega h) over h^j (derivation.rejection
    .discrete_gains): the estimation error's poles all at exp(-omega h).
    """
    gamma = -math.expm1(-ESO_BANDWIDTH * h)
    gains = []
    for polynomials in _ESO_POLYNOMIALS:
        scale = 1.0
        for coefficients in polynomials:
            total = 0.0
            for c in reversed(coefficients):
                total = total * gamma + c
            gains.append(total * gamma / scale)
            scale *= h
    # Then h / k, k = 1 .. the largest order: the prediction's Taylor factors, divided
    # once per sample time rather than at every step.
    return gains + [h / k for k in range(1, _ESO_ORDER + 1)]


def _eso_update(
    z: list[float], y: list[float], v: list[float], gains: list[float], h: float, t: float
) -> list[float]:
    """The extended-state observer h seconds on.

    Each chain of estimates is moved with its v held (Taylor, exact), then corrected by
    the newest outputs y; d_hat by y alone.
    """
    out = list(z)
    factors = gains[_ESO_GAINS - 1 :]
    g = 0
    for i, rows in enumerate(_ESO_ROWS):
        order = len(rows) - 1
        predicted = []
        for j in range(order):
            total = v[i]
            for k in range(order - 1, j - 1, -1):
                total = z[rows[k]] + total * factors[k - j + 1]
            predicted.append(total)
        error = y[i] - predicted[0]
        for j in range(order):
            out[rows[j]] = predicted[j] + gains[g + j] * error
        out[rows[order]] = z[rows[order]] + gains[g + order] * error
        g += order + 1
    if not _finite(out):
        raise NonFiniteInputError(
            f"the extended-state observer's states are not finite at t = {t!r}, {h!r} s after "
            "the last step: the step is too long for them"
        )
    return out


def _eso_inputs(ds: list[float]) -> list[float]:
    """Each output's v from the closed loop's rates: eta_top' - (l_r / l_(r+1)) d_hat'."""
    return [
        ds[_ESO_AT + rows[-2]] - ratio * ds[_ESO_AT + rows[-1]]
        for rows, ratio in zip(_ESO_ROWS, _ESO_RECOVERY, strict=True)
    ]
