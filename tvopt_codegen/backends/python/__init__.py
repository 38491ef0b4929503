"""The Python (NumPy) backend: one importable module per spec."""

from __future__ import annotations

import keyword
import types
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from tvopt_codegen.backends.base import Backend

if TYPE_CHECKING:
    from tvopt_codegen.lowering.ir import KernelSet
    from tvopt_codegen.lowering.printers import ExpressionPrinter, JointPrinter


def _printer() -> ExpressionPrinter:
    from tvopt_codegen.backends.python.printer import PythonPrinter  # noqa: PLC0415 - only when rendering

    return PythonPrinter()


def _scalar_printer() -> ExpressionPrinter:
    from tvopt_codegen.backends.python.printer import PythonScalarPrinter  # noqa: PLC0415

    return PythonScalarPrinter()


def _joint_printer() -> JointPrinter:
    from tvopt_codegen.backends.python.printer import PythonJointPrinter  # noqa: PLC0415

    return PythonJointPrinter()


def _filters() -> dict[str, Callable[..., Any]]:
    from tvopt_codegen.backends.python.filters import (  # noqa: PLC0415 - when rendering
        numpy_aliases,
        registers,
    )
    from tvopt_codegen.backends.python.runtime import verbatim  # noqa: PLC0415

    # verbatim: the fixed run-time Python, from the real modules of runtime/ (the C
    # backend's Python wrapper includes some of it too, through python/_contract.jinja).
    return {"registers": registers, "numpy_aliases": numpy_aliases, "verbatim": verbatim}


def _load(files: dict[str, str], module_file: str, name: str) -> types.ModuleType:
    """The module, compiled from memory.

    The text is tvopt-codegen's own output: spec text appears in it only inside escaped
    literals and comments.
    """
    module = types.ModuleType(name)
    module.__file__ = f"<generated {module_file}>"
    exec(compile(files[module_file], module.__file__, "exec"), module.__dict__)  # noqa: S102
    return module


def _context(kernels: KernelSet) -> dict[str, Any]:
    """The Python templates' own variables: R's diagonal blocks grouped by size."""
    groups: dict[int, tuple[list[int], list[tuple[int, ...]]]] = {}
    offset = 0
    for block in kernels.r_blocks:
        starts, rows = groups.setdefault(len(block), ([], []))
        starts.append(offset)
        rows.append(block)
        offset += len(block) ** 2
    # (size, offset of each block's entries in R, the outputs of each): blocks of one
    # size are solved together as one batch in NumPy.
    return {
        "r_groups": [(size, tuple(starts), tuple(rows)) for size, (starts, rows) in groups.items()]
    }


#: The Python backend.
BACKEND = Backend(
    name="python",
    description="NumPy module with control, rhs, optimality_error, objective, gradient, hessian",
    printer=_printer,
    templates=(("python/controller.py.jinja", "{name}.py"),),
    module="{name}.py",
    # The same kernels for one point (lists of floats): a single state in microseconds.
    variants=(("1", _scalar_printer),),
    # Both printings from one: the printers differ only in marked places.
    joint=_joint_printer,
    context=_context,
    filters=_filters,
    load=_load,
    reserved=frozenset(keyword.kwlist) | frozenset(keyword.softkwlist),
)
