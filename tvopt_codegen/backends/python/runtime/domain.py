"""Where the law leaves its domain: a mass matrix not positive definite, a barrier crossed.

Sections: ``definite`` (the mass matrix's LDL^T pivots) and ``margin`` (the inequality
constraints' margins), each emitted only when the law's plan needs it.
"""

from __future__ import annotations

import numpy
import numpy.typing

from tvopt_codegen.backends.python.runtime.provided import (
    PIVOT_TOLERANCE,
    STATUS_MASS_MATRIX_NOT_PD,
    STATUS_OUTSIDE_BARRIER,
)
from tvopt_codegen.backends.python.runtime.statuses import _error

# --- copied verbatim into the generated controller below this line ---


# --- section: definite ---
def _check_definite(
    mass: numpy.typing.NDArray[numpy.float64], pivot: numpy.typing.NDArray[numpy.float64]
) -> None:
    """M(q) must be positive definite.

    Every pivot of its LDL^T must be above the tolerance relative to the largest entry. A
    non-finite M passes here: the finiteness check that follows reports it.
    """
    scale = numpy.max(numpy.abs(mass), axis=0)
    ok = (pivot > PIVOT_TOLERANCE * scale) | ~numpy.isfinite(scale)
    bad = ~numpy.all(ok, axis=0)
    if bad.any():
        raise _error(STATUS_MASS_MATRIX_NOT_PD, int(numpy.argmax(bad)))


# --- section: margin ---
def _check_margin(margin: numpy.typing.NDArray[numpy.float64]) -> None:
    """Every inequality's margin s(t) - g_i(y, t) must be positive.

    Past a barrier the law's 1/(s - g_i) is finite and meaningless. A non-finite margin
    passes here: the finiteness check that follows reports it.
    """
    bad = ~numpy.all((margin > 0.0) | ~numpy.isfinite(margin), axis=0)
    if bad.any():
        raise _error(STATUS_OUTSIDE_BARRIER, int(numpy.argmax(bad)))
