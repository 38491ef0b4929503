"""The reference estimator: its start and extrapolation, and the NumPy backend's own.

Sections: ``start`` (the checked start and the extrapolation the template's
``_ReferenceEstimator`` calls; its class stays in the template, whose docstrings name
the references' sizes) and ``python`` (``ReferenceEstimator`` of the NumPy backend: the
differentiator of ``differentiator_linear`` or ``differentiator_levant`` in Python; the
C backend's runs its C).
"""

from __future__ import annotations

import math

import numpy
import numpy.typing

from tvopt_codegen.backends.python.runtime.arguments import (
    _check_measurement,
    _reference_jet,
    _time,
    _vector,
)
from tvopt_codegen.backends.python.runtime.chains import _taylor_shift
from tvopt_codegen.backends.python.runtime.differentiator_linear import _estimator_step
from tvopt_codegen.backends.python.runtime.provided import (
    _ESTIMATOR_ORDER,
    REFERENCE_NAMES,
    REFERENCE_ORDER,
    NonFiniteInputError,
    NonFiniteOutputError,
    _ReferenceEstimator,
)

# --- copied verbatim into the generated controller below this line ---


# --- section: start ---
def _estimator_start(
    samples: object, t0: object, jets0: object
) -> tuple[float, numpy.typing.NDArray[numpy.float64]]:
    """An estimator's start, checked: ``(t0, jets)``, one row per reference.

    Without ``jets0`` the jets start at the samples, with zero derivatives.
    """
    t0 = _time(t0)
    values = _vector("samples", samples, len(REFERENCE_NAMES))
    _check_measurement(t0, values, REFERENCE_NAMES)
    if jets0 is None:
        start = numpy.zeros((len(REFERENCE_NAMES), REFERENCE_ORDER + 1))
        start[:, 0] = values
    else:
        start = _reference_jet(jets0).reshape(len(REFERENCE_NAMES), REFERENCE_ORDER + 1)
    return t0, start


def _extrapolated(estimator: ReferenceEstimator, t: object) -> numpy.typing.NDArray[numpy.float64]:
    """The estimator's jets at ``t``, checked: ``t`` a finite time, the jets finite."""
    t = _time(t)
    if not math.isfinite(t):
        raise NonFiniteInputError(f"t = {t!r} is not finite")
    jets = estimator._jets(t)
    if jets is None or not numpy.all(numpy.isfinite(jets)):
        # So far from the last update that the Taylor polynomial overflows.
        raise NonFiniteOutputError(
            f"the estimate extrapolated to t = {t!r} is not finite ({t - estimator.t!r} s after "
            "the last update)",
            None,
        )
    return jets


# --- section: python ---
class ReferenceEstimator(_ReferenceEstimator):  # noqa: D101 - the template's docstring
    __doc__ = _ReferenceEstimator.__doc__

    def _begin(self, t: float, start: numpy.typing.NDArray[numpy.float64]) -> None:
        xi = numpy.zeros((len(REFERENCE_NAMES), _ESTIMATOR_ORDER + 1))
        xi[:, : REFERENCE_ORDER + 1] = start
        self._t, self._xi, self._last = t, xi.ravel(), start[:, 0].tolist()

    def _jets(self, t: float) -> numpy.typing.NDArray[numpy.float64]:
        rows = self._xi.reshape(len(REFERENCE_NAMES), _ESTIMATOR_ORDER + 1).tolist()
        with numpy.errstate(all="ignore"):
            return numpy.array(
                [_taylor_shift(row, t - self.t)[: REFERENCE_ORDER + 1] for row in rows]
            )

    def _update(
        self, t: float, values: numpy.typing.NDArray[numpy.float64]
    ) -> numpy.typing.NDArray[numpy.float64]:
        rows = self._xi.reshape(len(REFERENCE_NAMES), _ESTIMATOR_ORDER + 1).tolist()
        h = t - self._t
        new = [
            _estimator_step(row, last, float(sample), h)
            for row, last, sample in zip(rows, self._last, values, strict=True)
        ]
        xi = numpy.array(new).ravel()
        if not numpy.all(numpy.isfinite(xi)):
            raise NonFiniteOutputError("the reference estimate is not finite", None)
        self._t, self._xi, self._last = t, xi, values.tolist()
        return xi.reshape(len(REFERENCE_NAMES), _ESTIMATOR_ORDER + 1)[
            :, : REFERENCE_ORDER + 1
        ].copy()
