"""The stateful ``Controller``'s start, checked.

The class itself stays in the template: its signatures and docstrings name the spec's
sizes and arguments (references, limits). Its steps check their measurement with
``_measured`` (``arguments``) and move with a backend's ``_begin`` and ``_move``.
"""

from __future__ import annotations

import numpy
import numpy.typing

from tvopt_codegen.backends.python.runtime.arguments import (
    _check_measurement,
    _parameters,
    _time,
    _vector,
)
from tvopt_codegen.backends.python.runtime.provided import (
    CONTROLLER_STATE_NAMES,
    DEFAULT_STATE,
    PLANT_STATE_NAMES,
    NonFiniteInputError,
)

# --- copied verbatim into the generated controller below this line ---


def _start(
    x0: object, t0: object, z0: object, params: object
) -> tuple[
    float,
    numpy.typing.NDArray[numpy.float64],
    numpy.typing.NDArray[numpy.float64],
    numpy.typing.NDArray[numpy.float64],
]:
    """A controller's (re)start, checked: ``(t0, x0, z0, p)`` as floats and float arrays.

    Without ``z0`` the controller states start at those of ``DEFAULT_STATE``.
    """
    t0 = _time(t0)
    x = _vector("x0", x0, len(PLANT_STATE_NAMES))
    if z0 is None:
        z = numpy.array(DEFAULT_STATE[len(PLANT_STATE_NAMES) :], dtype=float)
    else:
        z = _vector("z0", z0, len(CONTROLLER_STATE_NAMES))
    p = _parameters(params)
    _check_measurement(t0, x, PLANT_STATE_NAMES)
    _check_measurement(t0, z, CONTROLLER_STATE_NAMES)
    if not numpy.all(numpy.isfinite(p)):
        raise NonFiniteInputError("a parameter is not finite")
    return t0, x, z, p
