"""The C backend: a self-contained C99 pair and a Python module that compiles and loads it."""

from __future__ import annotations

from typing import TYPE_CHECKING

from tvopt_codegen.backends.base import Backend

if TYPE_CHECKING:
    from sympy.printing.codeprinter import CodePrinter


def _printer() -> CodePrinter:
    from tvopt_codegen.printers import CPrinter  # noqa: PLC0415 - sympy only when rendering

    return CPrinter()


#: The C backend. The Python module has the Python backend's contract exactly.
C = Backend(
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
)
