"""The NumPy backend's evaluators of the plant and outputs, and a barrier's one-point guard.

Sections: ``inside`` (a one-point evaluator that answers None past a barrier, for the
array path to raise) and ``plant`` (the plant's vector field and outputs over a batch,
checked to be finite).
"""

from __future__ import annotations

from collections.abc import Callable as _Callable

import numpy
import numpy.typing

from tvopt_codegen.backends.python.runtime.arguments import _check_finite
from tvopt_codegen.backends.python.runtime.provided import _outputs, _plant

# --- copied verbatim into the generated controller below this line ---


# --- section: inside ---
def _inside_1(
    fast: _Callable[..., list[float] | None], margin: _Callable[..., list[float]]
) -> _Callable[..., list[float] | None]:
    """``fast``, answering None past a barrier (the array path then raises)."""

    def checked(*args: object) -> list[float] | None:
        return fast(*args) if min(margin(*args)) > 0.0 else None

    return checked


# --- section: plant ---
def _plant_values(
    t: float,
    x: numpy.typing.NDArray[numpy.float64],
    u: numpy.typing.NDArray[numpy.float64],
    p: numpy.typing.NDArray[numpy.float64],
) -> numpy.typing.NDArray[numpy.float64]:
    """The plant's vector field at every column of ``x`` and ``u``, checked finite."""
    with numpy.errstate(all="ignore"):
        dx = _plant(t, x, u, p)
    _check_finite("the plant's vector field", dx)
    return dx


def _outputs_values(
    t: float, x: numpy.typing.NDArray[numpy.float64], p: numpy.typing.NDArray[numpy.float64]
) -> numpy.typing.NDArray[numpy.float64]:
    """The outputs at every column of ``x``, checked finite."""
    with numpy.errstate(all="ignore"):
        y = _outputs(t, x, p)
    _check_finite("the outputs", y)
    return y
