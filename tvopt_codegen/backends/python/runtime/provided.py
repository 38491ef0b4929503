"""What a generated file defines around the copied run-time text: typed placeholders.

The run-time modules import these names so that they can be linted, type-checked and
imported on their own; none of this is copied. In a generated file each name is the
template's (the spec's sizes, the law's kernels, one exception class per error status);
here each holds a neutral value of the same type. ``tests/test_python_runtime_module.py``
checks that a generated module defines every name in ``__all__``.
"""

from __future__ import annotations

from typing import Any

import numpy
import numpy.typing

from tvopt_codegen.backends.python.runtime.errors import ControllerError
from tvopt_codegen.contract import PIVOT_TOLERANCE as _PIVOT_TOLERANCE
from tvopt_codegen.contract import Status

__all__ = [
    "INPUT_HIGH",
    "INPUT_LOW",
    "INPUT_NAMES",
    "INPUT_RATE",
    "CONTROLLER_STATE_NAMES",
    "DEFAULT_STATE",
    "ESTIMATOR_BANDWIDTH",
    "ESTIMATOR_LIPSCHITZ",
    "_ESTIMATOR_GAINS",
    "_ESTIMATOR_ORDER",
    "_FORGETTING_GAP",
    "_ReferenceEstimator",
    "ESO_BANDWIDTH",
    "_ESO_POLYNOMIALS",
    "_ESO_RECOVERY",
    "_ESO_ROWS",
    "PARAMETERS",
    "PIVOT_TOLERANCE",
    "PLANT_STATE_NAMES",
    "REFERENCE_NAMES",
    "REFERENCE_ORDER",
    "STATUS_MASS_MATRIX_NOT_PD",
    "STATUS_NONFINITE_OUTPUT",
    "STATUS_OUTSIDE_BARRIER",
    "STATUS_SINGULAR_DECOUPLING",
    "_CHAINS",
    "_ERRORS",
    "_INPUT_CHAINS",
    "_INTEGRAL_CHAINS",
    "_R_GROUPS",
    "DecreasingTimeError",
    "NonFiniteInputError",
    "NonFiniteOutputError",
    "_law",
    "_outputs",
    "_plant",
]

#: Parameters and their default values.
PARAMETERS: dict[str, float] = {}
#: The names of the plant states, plant inputs and references (sizes of the arguments).
PLANT_STATE_NAMES: tuple[str, ...] = ()
INPUT_NAMES: tuple[str, ...] = ()
REFERENCE_NAMES: tuple[str, ...] = ()
#: The controller's own states, and the spec's initial closed-loop state.
CONTROLLER_STATE_NAMES: tuple[str, ...] = ()
DEFAULT_STATE: tuple[float, ...] = ()
#: The highest derivative of a reference the law reads.
REFERENCE_ORDER = 0
#: A pivot below this fraction of the largest entry makes a matrix singular.
PIVOT_TOLERANCE = _PIVOT_TOLERANCE

STATUS_SINGULAR_DECOUPLING = int(Status.SINGULAR_DECOUPLING)
STATUS_NONFINITE_OUTPUT = int(Status.NONFINITE_OUTPUT)
STATUS_MASS_MATRIX_NOT_PD = int(Status.MASS_MATRIX_NOT_PD)
STATUS_OUTSIDE_BARRIER = int(Status.OUTSIDE_BARRIER)


class NonFiniteInputError(ControllerError):
    """``t``, the state or a parameter is NaN or infinite."""


class NonFiniteOutputError(ControllerError):
    """An intermediate or the result is not finite."""


class DecreasingTimeError(ControllerError, ValueError):
    """A stateful controller was stepped to a time before its last step's."""


#: Each error status: its exception, the message's head, and what follows the column.
_ERRORS: dict[int, tuple[type[ControllerError], str, str]] = {}
#: Diagonal blocks of R grouped by size: (size, where each block starts, its outputs).
_R_GROUPS: tuple[tuple[int, tuple[int, ...], tuple[tuple[int, ...], ...]], ...] = ()
#: The controller's integrator chains: (first index, length).
_CHAINS: tuple[tuple[int, int], ...] = ()
#: Actuator limits by plant input: lowest, highest value and largest rate.
INPUT_LOW: tuple[float, ...] = ()
INPUT_HIGH: tuple[float, ...] = ()
INPUT_RATE: tuple[float, ...] = ()
#: The chains of the integral states, and each input's extension chain (-1: none).
_INTEGRAL_CHAINS: tuple[int, ...] = ()
_INPUT_CHAINS: tuple[int, ...] = ()


def _law(
    t: float,
    s: numpy.typing.NDArray[numpy.float64],
    p: numpy.typing.NDArray[numpy.float64],
    rates: bool = True,
) -> tuple[Any, ...]:
    """The law over a block of columns: (ds/dt or None, u, ...); the template writes it."""
    raise NotImplementedError("written by the template into each generated file")


#: The reference differentiator: the highest derivative it estimates, its gains (one
#: per derivative), the linear one's bandwidth, Levant's bound L, and the gap (in units
#: of 1 / bandwidth) over which the linear one forgets its state.
_ESTIMATOR_ORDER = 0
_ESTIMATOR_GAINS: tuple[float, ...] = ()
ESTIMATOR_BANDWIDTH = 1.0
ESTIMATOR_LIPSCHITZ = 1.0
_FORGETTING_GAP = 1.0

#: The extended-state observer: its bandwidth; per output, its states among the
#: controller states, its discrete gains' polynomials and l_r / l_(r+1).
ESO_BANDWIDTH = 1.0
_ESO_ROWS: tuple[tuple[int, ...], ...] = ((0, 1),)
_ESO_POLYNOMIALS: tuple[tuple[tuple[float, ...], ...], ...] = ()
_ESO_RECOVERY: tuple[float, ...] = ()


class _ReferenceEstimator:
    """The template's reference estimator: its public methods, around a backend's three."""

    _t: float

    @property
    def t(self) -> float:
        """Time of the last update."""
        return self._t

    def _begin(self, t: float, start: numpy.typing.NDArray[numpy.float64]) -> None:
        raise NotImplementedError

    def _jets(self, t: float) -> numpy.typing.NDArray[numpy.float64] | None:
        raise NotImplementedError

    def _update(
        self, t: float, values: numpy.typing.NDArray[numpy.float64]
    ) -> numpy.typing.NDArray[numpy.float64]:
        raise NotImplementedError


def _plant(
    t: float,
    x: numpy.typing.NDArray[numpy.float64],
    u: numpy.typing.NDArray[numpy.float64],
    p: numpy.typing.NDArray[numpy.float64],
) -> numpy.typing.NDArray[numpy.float64]:
    """The plant's kernel: dx/dt at every column; the template writes it."""
    raise NotImplementedError("written by the template into each generated file")


def _outputs(
    t: float, x: numpy.typing.NDArray[numpy.float64], p: numpy.typing.NDArray[numpy.float64]
) -> numpy.typing.NDArray[numpy.float64]:
    """The outputs' kernel at every column; the template writes it."""
    raise NotImplementedError("written by the template into each generated file")
