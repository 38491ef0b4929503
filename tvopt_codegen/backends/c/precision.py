"""The C backend's two precisions: what ``double`` and ``float`` change in the generated C.

The facts of the language live here (a literal's suffix, the ``f`` functions of C99's
``<math.h>``, the type a real number is, ctypes' and NumPy's names for it) with the
constants a controller's numerics are tuned to per precision: the pivot tolerance of
its solves, the observer's Gram tolerance and sample-time tolerance, the reference
differentiator's forgetting gap. The printer (:mod:`tvopt_codegen.backends.c.printer`)
prints literals and functions by it, and the C templates read its type name and suffix
from their context (``real``, ``F``) and its constants from the header.

Double is the default and prints exactly what the C backend printed before precisions
existed; single (``--precision single``) is for a single-precision FPU (a Cortex-M4F or
M7 in float), where double arithmetic is emulated in software.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass
from typing import Any

import jinja2

from tvopt_codegen.contract import PIVOT_TOLERANCE
from tvopt_codegen.derivation.robust import GRAM_TOLERANCE, STEP_TOLERANCE
from tvopt_codegen.errors import SpecError
from tvopt_codegen.spec.estimator import FORGETTING_GAP

#: Largest finite float (FLT_MAX): a constant beyond it has no single-precision literal.
FLOAT_MAX = struct.unpack("<f", struct.pack("<I", 0x7F7FFFFF))[0]


def to_float32(value: float) -> float:
    """``value`` rounded to the nearest float (IEEE binary32), as a Python float."""
    result: float = struct.unpack("<f", struct.pack("<f", value))[0]
    return result


def shortest_float32(value: float) -> str:
    """The shortest decimal text that reads back as the float nearest ``value``.

    Deterministic (it depends on the value alone) and at most 9 significant digits,
    which every float needs at most (FLT_DECIMAL_DIG): the single-precision analogue of
    Python's ``repr``.
    """
    target = to_float32(value)
    for digits in range(1, 10):
        # Those digits as Python writes the double they spell (``20.0``, not ``2e+01``).
        text = repr(float(f"{target:.{digits}g}"))
        if to_float32(float(text)) == target:
            return text
    return repr(float(f"{target:.9g}"))  # pragma: no cover - 9 digits always round-trip


@dataclass(frozen=True)
class Precision:
    """One precision of the generated C.

    Attributes
    ----------
    name : str
        ``"double"`` or ``"single"``, as ``--precision`` spells it.
    c_type : str
        The C type of a real number: ``double`` or ``float``.
    suffix : str
        The suffix of a literal and of a C99 ``<math.h>`` function in this precision
        (``""`` or ``"f"``: ``1.5f``, ``sinf``).
    ctypes_type : str
        The ctypes name of the type (the Python loader's arguments).
    numpy_type : str
        The NumPy dtype of the type (the Python loader's arrays).
    epsilon : float
        The machine epsilon of the type (DBL_EPSILON, FLT_EPSILON).
    pivot_tolerance : float
        A pivot not above this fraction of its matrix's largest entry makes the matrix
        singular (R) or not positive definite (the Hessian, the mass matrix).
    gram_tolerance : float
        The observer's ``G^T G`` pivot tolerance (relative to its largest diagonal entry).
    step_tolerance : float
        The relative change of the sample time below which the observers keep their gains.
    forgetting_gap : float
        ``bandwidth * gap`` beyond which the linear differentiator has forgotten its state.
    """

    name: str
    c_type: str
    suffix: str
    ctypes_type: str
    numpy_type: str
    epsilon: float
    pivot_tolerance: float
    gram_tolerance: float
    step_tolerance: float
    forgetting_gap: float

    @property
    def single(self) -> bool:
        """Whether this is single precision (the header then names its own real type)."""
        return self.name == "single"

    def type_name(self, prefix: str) -> str:
        """The name generated code spells a real number with.

        ``double`` in double precision (what it always printed); in single, the
        header's typedef ``<prefix>_real_t`` (prefixed, as every other name of the
        controller is, so that two controllers share a firmware project).
        """
        return f"{prefix}_real_t" if self.single else self.c_type

    def literal(self, value: float) -> str:
        """``value`` as a C literal of this precision.

        Double: Python's ``repr`` (17 significant digits at most, round-trip). Single:
        the shortest text that reads back as the nearest float (written as
        ``repr`` writes it: a point or an exponent always), and the ``f`` suffix. An infinity is
        ``HUGE_VAL`` in double and ``INFINITY`` (a float in C99) in single; NaN and a finite
        value beyond the type's range are refused.
        """
        if math.isinf(value):
            # INFINITY is a float (C99): a double array takes HUGE_VAL, a double's
            # infinity under IEEE 754, without -Wdouble-promotion's promotion.
            text = "HUGE_VAL" if not self.single else "INFINITY"
            return text if value > 0 else "-" + text
        if not self.single:
            return repr(value)
        if math.isnan(value) or abs(value) > FLOAT_MAX:
            raise SpecError(
                "spec",
                "precision",
                f"the constant {value!r} has no single-precision value (|x| <= {FLOAT_MAX:.7g})",
            )
        return shortest_float32(float(value)) + self.suffix

    def function(self, name: str) -> str:
        """The C99 <math.h> function ``name`` of this precision (``fabs`` -> ``fabsf``)."""
        return name + self.suffix


#: The precisions by name; double first (the default).
PRECISIONS: dict[str, Precision] = {
    "double": Precision(
        name="double",
        c_type="double",
        suffix="",
        ctypes_type="c_double",
        numpy_type="float64",
        epsilon=2.0**-52,
        pivot_tolerance=PIVOT_TOLERANCE,
        gram_tolerance=GRAM_TOLERANCE,
        step_tolerance=STEP_TOLERANCE,
        forgetting_gap=FORGETTING_GAP,
    ),
    # float's epsilon is 2^-23 = 1.2e-7. A relative pivot of 1e-5 (84 epsilon) still
    # carries two significant digits after elimination; double's 1e-12 is 4500 of its
    # epsilon, which in float would refuse every matrix conditioned beyond 2e3. The
    # sample-time tolerance covers a time's rounding in float (ulp(10 s) = 9.5e-7, a
    # thousandth of a 1 ms step). After a gap of 40 / bandwidth, the differentiator's
    # memory, p(40) e^-40 <= 40^7 / 7! e^-40 = 1.4e-10, is below float's rounding.
    "single": Precision(
        name="single",
        c_type="float",
        suffix="f",
        ctypes_type="c_float",
        numpy_type="float32",
        epsilon=2.0**-23,
        pivot_tolerance=1e-5,
        gram_tolerance=1e-5,
        step_tolerance=1e-3,
        forgetting_gap=40.0,
    ),
}

#: The default precision.
DOUBLE = PRECISIONS["double"]


@jinja2.pass_context
def c_real(context: Any, value: float) -> str:
    """The ``c_real`` filter: a number as a C literal of the template's precision.

    Double prints as ``pyrepr`` does (an int as an int); single as
    :meth:`Precision.literal`. An infinity is ``HUGE_VAL`` (double) or ``INFINITY``.
    """
    precision = context.get("precision") or DOUBLE
    if not precision.single and not isinstance(value, float):
        return repr(value)
    return str(precision.literal(float(value)))
