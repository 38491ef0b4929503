"""A batch evaluated in blocks of columns that stay in the CPU caches.

A block's error names its column in the whole batch, and a Python float's overflow is
reported as the C reports an infinity.
"""

from __future__ import annotations

from collections.abc import Callable as _Callable

import numpy
import numpy.typing

from tvopt_codegen.backends.python.runtime.errors import ControllerError
from tvopt_codegen.backends.python.runtime.provided import STATUS_NONFINITE_OUTPUT, _law
from tvopt_codegen.backends.python.runtime.statuses import _error

# --- copied verbatim into the generated controller below this line ---


#: Columns evaluated at once. The temporaries of one block stay in the CPU caches, where
#: one pass over a batch of 10^5 columns streams every temporary through main memory.
_BLOCK = 8192


def _blockwise(
    function: _Callable[
        [float, numpy.typing.NDArray[numpy.float64], numpy.typing.NDArray[numpy.float64]],
        numpy.typing.NDArray[numpy.float64],
    ],
    t: float,
    s: numpy.typing.NDArray[numpy.float64],
    p: numpy.typing.NDArray[numpy.float64],
) -> numpy.typing.NDArray[numpy.float64]:
    """``function(t, s, p)`` over blocks of ``_BLOCK`` columns, joined on the last axis."""
    count = s.shape[1]
    if count <= _BLOCK:
        return _overflow_checked(function, t, s, p)
    parts = []
    for start in range(0, count, _BLOCK):
        try:
            parts.append(_overflow_checked(function, t, s[:, start : start + _BLOCK], p))
        except ControllerError as error:
            raise _shifted(error, start) from None
    return numpy.concatenate(parts, axis=-1)


def _overflow_checked(
    function: _Callable[
        [float, numpy.typing.NDArray[numpy.float64], numpy.typing.NDArray[numpy.float64]],
        numpy.typing.NDArray[numpy.float64],
    ],
    t: float,
    s: numpy.typing.NDArray[numpy.float64],
    p: numpy.typing.NDArray[numpy.float64],
) -> numpy.typing.NDArray[numpy.float64]:
    """``function(t, s, p)``, with a Python float's overflow reported as the C reports inf."""
    try:
        return function(t, s, p)
    except OverflowError:
        # Terms of t alone are Python floats, which raise (t**2 at |t| = 1e200) where numpy
        # and the C give inf.
        raise _error(STATUS_NONFINITE_OUTPUT, 0, "a result") from None


def _shifted(error: ControllerError, offset: int) -> ControllerError:
    """``error`` of a block that starts at column ``offset``, told in whole-batch columns."""
    if error.index is None:
        return error
    index = error.index + offset
    message = str(error).replace(f"(column {error.index})", f"(column {index})", 1)
    return type(error)(message, index)


def _control_values(
    t: float, s: numpy.typing.NDArray[numpy.float64], p: numpy.typing.NDArray[numpy.float64]
) -> numpy.typing.NDArray[numpy.float64]:
    """The plant input at every column of ``s`` (the law without its rates)."""
    return _blockwise(lambda t, s, p: _law(t, s, p, rates=False)[1], t, s, p)


def _rhs_values(
    t: float, s: numpy.typing.NDArray[numpy.float64], p: numpy.typing.NDArray[numpy.float64]
) -> numpy.typing.NDArray[numpy.float64]:
    """The closed loop's rates at every column of ``s``."""
    return _blockwise(lambda t, s, p: _law(t, s, p)[0], t, s, p)
