"""Stage 1: read a spec file, validate it, and parse its expressions.

The result, :class:`Spec`, holds names, numbers and expressions of the process's engine
(:mod:`tvopt_codegen.symbolic`; reading a spec imports no SymPy on SymEngine); nothing
in it has been derived yet. Every problem is a :class:`~tvopt_codegen.errors.SpecError`
naming the file, the field and the problem.
"""

from __future__ import annotations

from typing import Any

from tvopt_codegen.spec.files import (
    BUNDLED_SUFFIX,
    MAX_SPEC_BYTES,
    bundled_examples,
    load_spec,
    parse_spec,
    read_spec_bytes,
    spec_from_dict,
)
from tvopt_codegen.spec.reader import MAX_INDEX_COUNT
from tvopt_codegen.spec.types import (
    ESTIMATOR_KINDS,
    MAX_INTEGRATORS,
    TIME_NAME,
    Barrier,
    Constraint,
    Estimator,
    Limit,
    Mechanics,
    Robust,
    Spec,
    TuneSettings,
    symbol,
    time_symbol,
)


def __getattr__(name: str) -> Any:
    # ``TIME``, the symbol for time, of the engine in use when asked (see spec.types).
    if name == "TIME":
        return time_symbol()
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = [
    "BUNDLED_SUFFIX",
    "Barrier",
    "Constraint",
    "ESTIMATOR_KINDS",
    "Estimator",
    "Limit",
    "Mechanics",
    "Robust",
    "MAX_INDEX_COUNT",
    "MAX_INTEGRATORS",
    "MAX_SPEC_BYTES",
    "Spec",
    "TIME",
    "TIME_NAME",
    "TuneSettings",
    "bundled_examples",
    "load_spec",
    "parse_spec",
    "read_spec_bytes",
    "spec_from_dict",
    "symbol",
    "time_symbol",
]
