"""The Python (NumPy) backend: one importable module per spec."""

from __future__ import annotations

from tvopt_codegen.backends.base import Backend
from tvopt_codegen.printers import PythonPrinter

#: The Python backend.
PYTHON = Backend(
    name="python",
    description="NumPy module with control, rhs, optimality_error, objective, gradient, hessian",
    printer=PythonPrinter,
    templates=(("python/controller.py.jinja", "{name}.py"),),
    module="{name}.py",
)
