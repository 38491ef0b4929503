"""The C backend: a self-contained C99 pair and a Python module that compiles and loads it."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from tvopt_codegen.backends.base import Backend

if TYPE_CHECKING:
    from tvopt_codegen.backends.c.precision import Precision
    from tvopt_codegen.lowering.ir import KernelSet
    from tvopt_codegen.lowering.printers import ExpressionPrinter

#: Keywords of C99 (and the C11 ones a C99 compiler may reserve).
C_KEYWORDS = frozenset(
    "auto break case char const continue default do double else enum extern float for goto if "
    "inline int long register restrict return short signed sizeof static struct switch typedef "
    "union unsigned void volatile while _Bool _Complex _Imaginary _Alignas _Alignof _Atomic "
    "_Generic _Noreturn _Static_assert _Thread_local".split()
)

#: Names from <math.h> and the C library that a generated C file may see. The POSIX
#: Bessel functions j0, j1, jn, y0, y1, yn are deliberately absent: y1, y2 are what
#: control engineers call outputs, and user names never become C identifiers.
C_LIBRARY_NAMES = frozenset(
    "acos acosh asin asinh atan atan2 atanh cbrt ceil copysign cos cosh erf erfc exp exp2 expm1 "
    "fabs fdim floor fma fmax fmin fmod frexp hypot ilogb ldexp lgamma llrint llround log log10 "
    "log1p log2 logb lrint lround modf nan nearbyint nextafter pow remainder remquo rint round "
    "scalbln scalbn sin sinh sqrt tan tanh tgamma trunc isfinite isnan isinf "
    "signbit fpclassify NAN INFINITY HUGE_VAL errno assert abs exit main malloc free memcpy "
    "memset printf size_t NULL int8_t int16_t int32_t int64_t uint8_t uint16_t uint32_t "
    "uint64_t".split()
)


def _printer(precision: Precision | None = None) -> ExpressionPrinter:
    from tvopt_codegen.backends.c.precision import DOUBLE  # noqa: PLC0415 - only when rendering
    from tvopt_codegen.backends.c.printer import CPrinter  # noqa: PLC0415

    return CPrinter(precision or DOUBLE)


def _context(
    kernels: KernelSet, precision: Precision | None = None, prefix: str | None = None
) -> dict[str, Any]:
    """The C templates' own variables.

    The precision's: ``precision`` (the record), ``real`` (the C spelling of a real
    number: ``double``, or the header's ``<name>_real_t``), ``F`` (the suffix of a literal
    and of a <math.h> function: ``""`` or ``"f"``) and the tolerances it tunes, which
    replace the shared context's. ``prefix`` renames the C's identifiers (``prefix``,
    ``guard``): the sweep's loop includes a controller of each precision.
    """
    from tvopt_codegen.backends.c.precision import DOUBLE  # noqa: PLC0415

    d = kernels.derivation
    precision = precision or DOUBLE
    renamed = {} if prefix is None else {"prefix": prefix, "guard": prefix.upper()}
    return {
        **renamed,
        "precision": precision,
        "real": precision.type_name(prefix or d.spec.name),
        "F": precision.suffix,
        "pivot_tolerance": precision.pivot_tolerance,
        "gram_tolerance": precision.gram_tolerance,
        "step_tolerance": precision.step_tolerance,
        "estimator_gap": precision.forgetting_gap,
        # The CPython entry point: its module name, and the size of its largest single
        # result (rhs, optimality error or Hessian).
        "extension_name": f"_{d.spec.name}_ext",
        "result_max": max(
            len(d.closed_loop.state_names),
            d.dynamics.k * len(d.spec.outputs),
            len(d.spec.outputs) ** 2,
        ),
    }


def _filters() -> dict[str, Callable[..., Any]]:
    """The C templates' own filters.

    ``c_real``: a number as a literal of the precision; ``c_stack_bounds``: the header's
    static stack bound per public function (:mod:`tvopt_codegen.backends.c.stack`).
    """
    from tvopt_codegen.backends.c.precision import c_real  # noqa: PLC0415 - when rendering
    from tvopt_codegen.backends.c.stack import header_bounds  # noqa: PLC0415

    return {"c_real": c_real, "c_stack_bounds": header_bounds}


#: The C backend. The Python module has the Python backend's contract exactly.
BACKEND = Backend(
    name="c",
    description=(
        "C99 <name>.h/<name>.c (no heap, re-entrant), <name>_c.py loading them and "
        "<name>.ext.c, its CPython entry point"
    ),
    printer=_printer,
    templates=(
        ("c/controller.h.jinja", "{name}.h"),
        ("c/controller.c.jinja", "{name}.c"),
        ("c/wrapper.py.jinja", "{name}_c.py"),
        ("c/extension.c.jinja", "{name}.ext.c"),
    ),
    # Not <name>.py: the NumPy module of the same spec may sit in the same folder.
    module="{name}_c.py",
    context=_context,
    filters=_filters,
    reserved=C_KEYWORDS | C_LIBRARY_NAMES,
    reserved_as=(
        ("a C keyword", C_KEYWORDS),
        ("a C library or math function name", C_LIBRARY_NAMES),
    ),
)


#: The C backend's file of the CPython entry point, which single precision leaves out.
_EXTENSION_TEMPLATE = "c/extension.c.jinja"


def with_precision(name: str, prefix: str | None = None) -> Backend:
    """The C backend generating C of the precision ``name`` (``"double"`` or ``"single"``).

    Double is :data:`BACKEND` itself. Single prints every real as the header's
    ``<name>_real_t`` (a float), every literal with its ``f`` and the ``f`` functions
    of <math.h>, with the single-precision tolerances; its Python module loads the C
    through ctypes with ``c_float`` arrays, without the CPython entry point (which
    trades in Python's doubles).

    ``prefix`` (default: the spec's name) names the C's identifiers, for a translation
    unit that holds the controller in both precisions (the sweep's loop); the files keep
    their names.

    Raises
    ------
    KeyError
        For a name that is not a precision.
    """
    from tvopt_codegen.backends.c.precision import PRECISIONS  # noqa: PLC0415

    precision = PRECISIONS[name]
    if not precision.single and prefix is None:
        return BACKEND

    def printer() -> ExpressionPrinter:
        return _printer(precision)

    def context(kernels: KernelSet) -> dict[str, Any]:
        return _context(kernels, precision, prefix)

    templates = BACKEND.templates
    if precision.single:
        templates = tuple(t for t in templates if t[0] != _EXTENSION_TEMPLATE)
    return dataclasses.replace(BACKEND, printer=printer, context=context, templates=templates)
