"""Whether single precision resolves a controller's matrices at its initial state.

``check --precision single`` prints a warning naming each matrix the single-precision C
might not solve at the spec's initial state (the default parameters, t = 0): the
Hessian of f0 (with equalities, the KKT matrix), whose LDL^T pivots are refused below
the pivot tolerance relative to its largest entry, and each diagonal block of the
decoupling matrix R, solved by LU with the same test. A matrix whose condition number
exceeds ``1 / pivot_tolerance`` has a pivot that small relative to its scale somewhere
along the elimination; then rounding to float (relative error ``epsilon``) moves the
law by ``epsilon * cond``, and a step may stop with HESSIAN_NOT_PD or
SINGULAR_DECOUPLING where the double controller runs.

The quantities are evaluated from the derivation's own expressions at the start
(:func:`tvopt_codegen.derivation.model.start_evaluator`, as the start's other warnings
are): nothing is compiled.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np

from tvopt_codegen import symbolic as sx
from tvopt_codegen.backends.c.precision import Precision
from tvopt_codegen.derivation.model import start_evaluator

if TYPE_CHECKING:
    from tvopt_codegen.derivation.record import Derivation


def _condition(matrix: np.ndarray) -> float:
    """The 2-norm condition number; inf for a singular or non-finite matrix."""
    if not np.all(np.isfinite(matrix)):
        return float("inf")
    with np.errstate(all="ignore"):
        value = float(np.linalg.cond(matrix))
    return value if np.isfinite(value) else float("inf")


def start_conditions(d: Derivation) -> list[tuple[str, float]]:
    """The condition numbers at the initial state: the Hessian's, then each R block's.

    Returns an empty list when the law's pieces cannot be evaluated there (a reference
    measured at run time, a value that is not finite: the derivation warns of the
    latter already).
    """
    model = d.model
    defaults = dict(zip(model.params, model.defaults, strict=True))
    evaluate = start_evaluator(
        d.closed_loop.states, d.closed_loop.initial_state, defaults, model.mechanics
    )
    time = sx.symbol("t")
    evaluate.define(time, sx.Integer(0))
    for symbol, expr in model.signals:
        evaluate.define(symbol, expr)
    for program in (d.jet.signal_program, d.jet.jet_program, d.objective.hessian_program):
        for symbol, expr in program.assignments:
            evaluate.define(symbol, expr)
    for symbols, values in (
        *zip(d.jet.signal_jet, d.jet.signal_jet_values, strict=True),
        *zip(d.jet.y_jet, d.jet.y_jet_values, strict=True),
    ):
        for symbol, expr in zip(symbols, values, strict=False):  # the jet's known part
            evaluate.define(symbol, expr)
    law = d.law
    n = int(round(len(law.hessian) ** 0.5))
    out: list[tuple[str, float]] = []
    try:
        hessian = np.array([complex(evaluate(e)) for e in law.hessian]).reshape(n, n)
        what = "the KKT matrix" if d.model.equalities else "the Hessian of f0"
        out.append((what, _condition(hessian.real if not hessian.imag.any() else hessian)))
        at = 0
        for block in law.r_blocks:
            size = len(block)
            entries = [complex(evaluate(e)) for e in law.r_entries[at : at + size * size]]
            at += size * size
            matrix = np.array(entries).reshape(size, size)
            names = ", ".join(d.spec.outputs[i] for i in block)
            out.append((f"R's block of {names}", _condition(matrix.real)))
    except (KeyError, TypeError, ValueError):
        return []  # a symbol with no value at the start (a measured reference)
    return out


def resolution_notes(d: Derivation, precision: Precision) -> Sequence[str]:
    """One warning per matrix ``precision`` may not solve at the initial state.

    Parameters
    ----------
    d : Derivation
        The derived law.
    precision : Precision
        The generated C's precision (double resolves what the derivation accepted).

    Returns
    -------
    sequence of str
        Each names the matrix, its condition number and the precision's bound.
    """
    bound = 1.0 / precision.pivot_tolerance
    return [
        f"{what} at the initial state has condition number {cond:.3g}, beyond what "
        f"{precision.name} precision resolves (1/pivot tolerance = {bound:.3g}): the "
        f"{precision.name}-precision C may stop there with "
        + ("SINGULAR_DECOUPLING" if what.startswith("R") else "HESSIAN_NOT_PD")
        + " where the double one runs"
        for what, cond in start_conditions(d)
        if cond > bound
    ]
