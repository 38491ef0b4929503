"""Which symbolic engine a process uses: chosen once, before the first expression.

The engine is read from ``TVOPT_CODEGEN_ENGINE`` (``symengine`` or ``sympy``) when
:mod:`tvopt_codegen.symbolic` is first imported, or set before that by :func:`choose`
(the command line's ``--engine``). Expressions of the two engines never mix: the
engine is a fact of the process, as SymForce's ``symforce.set_symbolic_api`` is.
"""

from __future__ import annotations

import os

#: The engines, the default first.
ENGINES = ("sympy", "symengine")

#: The environment variable naming the engine.
VARIABLE = "TVOPT_CODEGEN_ENGINE"

_chosen: str | None = None


class EngineError(ValueError):
    """An unknown engine, or a second choice after the first expression was built."""


def _checked(name: str, where: str) -> str:
    if name not in ENGINES:
        raise EngineError(f"{where}: unknown engine {name!r}; expected one of {', '.join(ENGINES)}")
    return name


def choose(name: str) -> None:
    """Choose the engine for this process.

    Parameters
    ----------
    name : str
        ``"symengine"`` or ``"sympy"``.

    Raises
    ------
    EngineError
        If the name is unknown, or another engine was already bound (expressions of the
        first would not mix with the second's).
    """
    global _chosen  # noqa: PLW0603 - one choice per process, by design
    _checked(name, "--engine")
    if _chosen is not None and _chosen != name:
        raise EngineError(
            f"--engine {name}: this process already uses {_chosen}; choose the engine "
            "before the first expression is built"
        )
    _chosen = name
    os.environ[VARIABLE] = name


def current() -> str:
    """The process's engine, binding the default (or the environment's) on first use."""
    global _chosen  # noqa: PLW0603 - one choice per process, by design
    if _chosen is None:
        _chosen = _checked(os.environ.get(VARIABLE, "") or ENGINES[0], VARIABLE)
    return _chosen
