"""Actuator limits and anti-windup for a controller with a [limits] table.

The input applied within the limits and rate limits (:func:`_limit`), and what the
controller's states do while an input is clipped (:func:`_unwind`).
"""

from __future__ import annotations

import math

from tvopt_codegen.backends.python.runtime.provided import (
    _CHAINS,
    _INPUT_CHAINS,
    _INTEGRAL_CHAINS,
    INPUT_HIGH,
    INPUT_LOW,
    INPUT_RATE,
)

# --- copied verbatim into the generated controller below this line ---


def _limit(
    commanded: list[float], previous: list[float] | None, h: float | None
) -> tuple[list[float], list[bool]]:
    """The input to apply and which entries were clipped.

    The commanded input within [INPUT_LOW, INPUT_HIGH] and, after a first step (``h``
    and ``previous`` not None), within INPUT_RATE * h of the last.
    """
    applied, clipped = [], []
    for i, value in enumerate(commanded):
        low, high = INPUT_LOW[i], INPUT_HIGH[i]
        if previous is not None and h is not None and INPUT_RATE[i] < math.inf:
            # Comparisons, as the C does, and no call of max or min on the step's path.
            if previous[i] - INPUT_RATE[i] * h > low:  # noqa: PLR1730
                low = previous[i] - INPUT_RATE[i] * h
            if previous[i] + INPUT_RATE[i] * h < high:  # noqa: PLR1730
                high = previous[i] + INPUT_RATE[i] * h
        out = low if value < low else (high if value > high else value)
        applied.append(out)
        clipped.append(out != value)
    return applied, clipped


def _unwind(
    z: list[float],
    drive: list[float],
    commanded: list[float],
    applied: list[float],
    clipped: list[bool],
    estimate: list[float],
) -> None:
    """Anti-windup, in place.

    While an input is clipped the integral states hold, and a clipped prolonged input's
    chain is set to give the applied input (its derivatives and drive, where they push
    further out, to zero).
    """
    if not any(clipped):
        return
    for chain in _INTEGRAL_CHAINS:
        drive[chain] = 0.0
    for i, chain in enumerate(_INPUT_CHAINS):
        if chain < 0 or not clipped[i]:
            continue
        start, length = _CHAINS[chain]
        excess = commanded[i] - applied[i]
        z[start] = applied[i] + estimate[i]
        for j in range(start + 1, start + length):
            if z[j] * excess > 0.0:
                z[j] = 0.0
        if drive[chain] * excess > 0.0:
            drive[chain] = 0.0
