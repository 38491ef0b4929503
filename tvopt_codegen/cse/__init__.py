"""Optimising kernels: operation counts, substitution, ordered CSE, and hoisting.

:func:`make_kernel` turns a derived program and its outputs into a :class:`Kernel`:
slot symbols substituted, odd functions of mirrored arguments merged
(:func:`canonical_odd`), common subexpressions found and named in evaluation order
(:func:`ordered_cse`). :func:`split_invariant` splits off the part of a kernel that
depends on time and parameters alone, computed once per batch of states.
"""

from __future__ import annotations

from tvopt_codegen.cse.assembly import Outputs, make_kernel, make_kernels, split_invariant
from tvopt_codegen.cse.numbering import SMALL_PROGRAM_OPS, ordered_cse
from tvopt_codegen.cse.rewrite import canonical_odd, operation_count, symbols_in

__all__ = [
    "Outputs",
    "SMALL_PROGRAM_OPS",
    "canonical_odd",
    "make_kernel",
    "make_kernels",
    "operation_count",
    "ordered_cse",
    "split_invariant",
    "symbols_in",
]
