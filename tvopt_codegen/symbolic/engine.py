"""Which symbolic engine a process uses: chosen once, before the first expression.

The engine is read from ``TVOPT_CODEGEN_ENGINE`` (``symengine`` or ``sympy``) when
:mod:`tvopt_codegen.symbolic` is first imported; the command line's ``--engine`` runs
its command on the engine it names (:func:`tvopt_codegen.symbolic.using`). Expressions
of the two engines never mix: the engine is a fact of the process while it builds
expressions, as SymForce's ``symforce.set_symbolic_api`` is.
"""

from __future__ import annotations

import os

from tvopt_codegen.errors import SpecError
from tvopt_codegen.limits import ENGINE_VARIABLE as VARIABLE
from tvopt_codegen.limits import ENGINES

__all__ = ["ENGINES", "VARIABLE", "EngineError", "checked", "current"]


class EngineError(SpecError):
    """An unknown engine named in the environment or on the command line."""


def checked(name: str, where: str) -> str:
    """``name`` if it is an engine, else an :class:`EngineError` naming ``where``."""
    if name not in ENGINES:
        raise EngineError(
            "environment" if where == VARIABLE else "command line",
            where,
            f"unknown engine {name!r}; expected one of {', '.join(ENGINES)}",
        )
    return name


def current() -> str:
    """The engine the environment names, or the default."""
    return checked(os.environ.get(VARIABLE, "") or ENGINES[0], VARIABLE)
