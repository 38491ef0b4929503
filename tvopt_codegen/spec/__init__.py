"""Stage 1: read a spec file, validate it, and parse its expressions.

The result, :class:`Spec`, holds names, numbers and sympy expressions; nothing in it
has been derived yet. Every problem is a :class:`~tvopt_codegen.errors.SpecError`
naming the file, the field and the problem.
"""

from __future__ import annotations

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
    TIME,
    Barrier,
    Constraint,
    Estimator,
    Limit,
    Mechanics,
    Robust,
    Spec,
    TuneSettings,
    symbol,
)

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
    "TuneSettings",
    "bundled_examples",
    "load_spec",
    "parse_spec",
    "read_spec_bytes",
    "spec_from_dict",
    "symbol",
]
