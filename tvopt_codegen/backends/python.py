"""The Python (NumPy) backend: one importable module per spec."""

from __future__ import annotations

from typing import TYPE_CHECKING

from tvopt_codegen.backends.base import Backend

if TYPE_CHECKING:
    from sympy.printing.codeprinter import CodePrinter


def _printer() -> CodePrinter:
    from tvopt_codegen.printers import PythonPrinter  # noqa: PLC0415 - sympy only when rendering

    return PythonPrinter()


def _scalar_printer() -> CodePrinter:
    from tvopt_codegen.printers import PythonScalarPrinter  # noqa: PLC0415

    return PythonScalarPrinter()


#: The Python backend.
PYTHON = Backend(
    name="python",
    description="NumPy module with control, rhs, optimality_error, objective, gradient, hessian",
    printer=_printer,
    templates=(("python/controller.py.jinja", "{name}.py"),),
    module="{name}.py",
    # The same kernels for one point (lists of floats): a single state in microseconds.
    variants=(("1", _scalar_printer),),
)
