"""The public functions' and the controller's argument conversion and checks.

Sections: ``defaults`` (the default parameter vector), ``convert`` (time, arrays,
parameters), ``check`` (finite inputs, for a backend whose evaluators do not check
them), ``references`` (the reference jets below a batch), ``finite`` (finite results),
``plant`` (the plant's arguments), ``measurement`` (the vectors and times of a
stateful controller and of a reference estimator) and
``reference_jet`` (one checked jet).
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy
import numpy.typing

from tvopt_codegen.backends.python.runtime.provided import (
    INPUT_NAMES,
    PARAMETERS,
    PLANT_STATE_NAMES,
    REFERENCE_NAMES,
    REFERENCE_ORDER,
    STATUS_NONFINITE_OUTPUT,
    DecreasingTimeError,
    NonFiniteInputError,
)
from tvopt_codegen.backends.python.runtime.statuses import _error

# --- copied verbatim into the generated controller below this line ---


# --- section: defaults ---
_DEFAULT_P = numpy.array(list(PARAMETERS.values()), dtype=float)


# --- section: convert ---
def _time(t: object) -> float:
    """``t`` as a float: a real number, not an array (one time per call)."""
    if isinstance(t, (int, float, numpy.integer, numpy.floating)):
        return float(t)
    raise TypeError(f"t must be a real number, got {type(t).__name__}")


def _columns(
    name: str, value: object, rows: int
) -> tuple[numpy.typing.NDArray[numpy.float64], bool]:
    """Return ``value`` as a float array of shape (rows, N) and whether it was 1-D."""
    array = numpy.asarray(value)
    if array.dtype.kind == "c" or (
        array.dtype.kind == "O"
        and any(isinstance(v, (complex, numpy.complexfloating)) for v in array.flat)
    ):
        # numpy would drop the imaginary part with only a warning.
        raise TypeError(f"{name} must be real, got complex values")
    array = numpy.asarray(array, dtype=float)
    if array.ndim == 1 and array.shape[0] == rows:
        return array[:, None], True
    if array.ndim == 2 and array.shape[0] == rows:
        return array, False
    raise ValueError(f"{name} must have shape ({rows},) or ({rows}, N), got {array.shape}")


def _parameters(params: object) -> numpy.typing.NDArray[numpy.float64]:
    """Parameter vector in declaration order; unknown names are an error."""
    if params is None:
        return _DEFAULT_P
    if not isinstance(params, Mapping):
        raise TypeError(f"params must be a mapping from name to value, got {type(params).__name__}")
    unknown = [key for key in params if key not in PARAMETERS]
    if unknown:
        raise ValueError(f"unknown parameter(s) {unknown}; known: {list(PARAMETERS)}")
    values = []
    for key, default in PARAMETERS.items():
        value = params.get(key, default)
        if isinstance(value, (complex, numpy.complexfloating)):
            raise TypeError(f"parameter {key!r} must be real, got {value!r}")
        values.append(float(value))
    return numpy.array(values)


# --- section: check ---
def _check_inputs(
    t: float,
    array: numpy.typing.NDArray[numpy.float64],
    p: numpy.typing.NDArray[numpy.float64],
    what: str,
) -> None:
    """Raise NonFiniteInputError where ``t``, a column of ``array`` or ``p`` is not finite."""
    if not numpy.isfinite(t):
        raise NonFiniteInputError(f"t = {t!r} is not finite")
    bad = ~numpy.all(numpy.isfinite(array), axis=0)
    if bad.any():
        index = int(numpy.argmax(bad))
        raise NonFiniteInputError(f"the {what} is not finite (column {index})", index)
    if not numpy.all(numpy.isfinite(p)):
        raise NonFiniteInputError("a parameter is not finite")


# --- section: references ---
def _with_references(
    array: numpy.typing.NDArray[numpy.float64], refs: object
) -> numpy.typing.NDArray[numpy.float64]:
    """``array`` (rows, N) with the reference jets stacked below it, one jet per column."""
    rows, count = len(REFERENCE_NAMES), REFERENCE_ORDER + 1
    if refs is None:
        raise TypeError(f"refs is required: the jets of REFERENCE_NAMES, shape ({rows}, {count})")
    jets = numpy.asarray(refs)
    if jets.dtype.kind == "c":
        raise TypeError("refs must be real, got complex values")
    jets = numpy.asarray(jets, dtype=float)
    points = array.shape[1]
    if jets.shape == (rows, count):
        flat = numpy.repeat(jets.reshape(rows * count, 1), points, axis=1)
    elif jets.shape == (rows, count, points):
        flat = jets.reshape(rows * count, points)
    else:
        raise ValueError(
            f"refs must have shape ({rows}, {count}) or ({rows}, {count}, "
            f"{points}), got {jets.shape}"
        )
    bad = ~numpy.all(numpy.isfinite(flat), axis=0)
    if bad.any():
        index = int(numpy.argmax(bad))
        raise NonFiniteInputError(f"a reference is not finite (column {index})", index)
    return numpy.vstack([array, flat])


# --- section: finite ---
def _check_finite(what: str, *arrays: numpy.typing.NDArray[numpy.float64]) -> None:
    """Raise the NONFINITE_OUTPUT error at the first column that is not finite.

    A column is the last axis of each of ``arrays``; ``what`` names them in the message.
    """
    for array in arrays:
        if array.size == 0:  # a batch of no columns
            continue
        bad = ~numpy.all(numpy.isfinite(array.reshape(-1, array.shape[-1])), axis=0)
        if bad.any():
            index = int(numpy.argmax(bad))
            raise _error(STATUS_NONFINITE_OUTPUT, index, what)


# --- section: plant ---
def _plant_arguments(
    t: object, x: object, params: object, u: object = None
) -> tuple[
    float, list[numpy.typing.NDArray[numpy.float64]], numpy.typing.NDArray[numpy.float64], bool
]:
    """The plant's arguments converted and checked: (t, [x] or [x, u], p, whether 1-D)."""
    t = _time(t)
    states, single = _columns("x", x, len(PLANT_STATE_NAMES))
    p = _parameters(params)
    if not numpy.isfinite(t):
        raise NonFiniteInputError(f"t = {t!r} is not finite")
    arrays = [("plant state", states)]
    if u is not None:
        inputs, _ = _columns("u", u, len(INPUT_NAMES))
        if inputs.shape[1] != states.shape[1]:
            raise ValueError(
                f"x and u must have as many columns, got {states.shape[1]} and {inputs.shape[1]}"
            )
        arrays.append(("input", inputs))
    for what, array in arrays:
        bad = ~numpy.all(numpy.isfinite(array), axis=0)
        if bad.any():
            index = int(numpy.argmax(bad))
            raise NonFiniteInputError(f"the {what} is not finite (column {index})", index)
    if not numpy.all(numpy.isfinite(p)):
        raise NonFiniteInputError("a parameter is not finite")
    return t, [a for _, a in arrays], p, single


# --- section: measurement ---
def _vector(name: str, value: object, size: int) -> numpy.typing.NDArray[numpy.float64]:
    """``value`` as a float array of shape (size,)."""
    array = numpy.asarray(value)
    if array.dtype.kind == "c":
        raise TypeError(f"{name} must be real, got complex values")
    array = numpy.array(array, dtype=float)
    if array.shape != (size,):
        raise ValueError(f"{name} must have shape ({size},), got {array.shape}")
    return array


def _check_measurement(
    t: float, x: numpy.typing.NDArray[numpy.float64], names: tuple[str, ...]
) -> None:
    """Raise NonFiniteInputError naming ``t`` or the first entry of ``x`` that is not finite."""
    if not numpy.isfinite(t):
        raise NonFiniteInputError(f"t = {t!r} is not finite")
    bad = ~numpy.isfinite(x)
    if bad.any():
        index = int(numpy.argmax(bad))
        raise NonFiniteInputError(f"{names[index]} = {float(x[index])!r} is not finite", index)


def _measured(
    t: object, name: str, value: object, names: tuple[str, ...], last: float, event: str
) -> tuple[float, numpy.typing.NDArray[numpy.float64]]:
    """A stateful object's new time and measurement, checked: ``(t, value)``.

    ``value`` (named ``name``) is one entry per name of ``names``, finite, at a finite
    time not before ``last``, the time of the last ``event`` (a step, an update).
    """
    t = _time(t)
    vector = _vector(name, value, len(names))
    _check_measurement(t, vector, names)
    if t < last:
        raise DecreasingTimeError(
            f"t = {t!r} is before the last {event}'s time {last!r}: time must not decrease"
        )
    return t, vector


# --- section: reference_jet ---
def _reference_jet(refs: object) -> numpy.typing.NDArray[numpy.float64]:
    """One reference jet, flat (row after row), checked."""
    return _with_references(numpy.empty((0, 1)), refs)[:, 0]
