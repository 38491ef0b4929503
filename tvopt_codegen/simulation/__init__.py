"""Closed-loop simulation and the paper's theorem, checked on the run (the certificate).

:func:`simulate` integrates ``rhs`` of a generated controller with
``scipy.integrate.solve_ivp``, finds the target path ``y*(t)`` by numerical
minimization of ``f0(., t)`` (never from the law), and checks the two claims of the
paper's theorems along the run:

1. the optimality error follows ``E(t) = expm(H t) E(0)``;
2. ``|y(t) - y*(t)| <= C e^{-alpha t}`` with ``C = c |E(0)| / m_f``, where ``c`` is the
   constant of ``|expm(H t)| <= c e^{-alpha t}`` (computed) and ``m_f`` the convexity
   modulus (estimated along the run).

Nothing here writes files or draws: :func:`tvopt_codegen.runs.artifacts.result_files` renders
the outputs and figures in memory for :mod:`tvopt_codegen.emit`.
"""

from __future__ import annotations

from tvopt_codegen.simulation.certificate import VACUOUS_M_F, format_certificate
from tvopt_codegen.simulation.result import (
    Options,
    Result,
    columns,
    load_controller,
    resolve_options,
)
from tvopt_codegen.simulation.run import MAX_GRID_STEP, simulate
from tvopt_codegen.simulation.target import kkt_path, minimizer_path

__all__ = [
    "MAX_GRID_STEP",
    "Options",
    "Result",
    "VACUOUS_M_F",
    "columns",
    "format_certificate",
    "kkt_path",
    "load_controller",
    "minimizer_path",
    "resolve_options",
    "simulate",
]
