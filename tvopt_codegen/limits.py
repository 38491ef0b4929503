"""Limits and choices the command line offers, importable without the heavy stages.

``tvopt-codegen --help`` and ``--version`` read these without loading sympy, numpy or
scipy; the stages that enforce them import them from here.
"""

from __future__ import annotations

from dataclasses import dataclass

#: Longest simulation horizon: a run is integrated and sampled step by step, so a
#: horizon of 1e300 would never end.
MAX_T_FINAL = 1e6
#: Most output times of a simulation (each is a row of the trajectory table).
MAX_POINTS = 100_000
#: Integration methods of solve_ivp offered on the command line.
METHODS = ("RK45", "DOP853", "RK23", "Radau", "BDF", "LSODA")


@dataclass(frozen=True)
class Budget:
    """Limits one derivation may use before it is stopped with a :class:`BudgetError`.

    Attributes
    ----------
    seconds : float
        Wall time for the whole derivation.
    size : int
        Largest expression tree (nodes, shared subtrees counted each time they occur)
        any stage may build: Lie derivatives, gradient, Hessian, jet assignments.
    """

    seconds: float = 120.0
    size: int = 20_000


#: Newton iterations at the first point of a minimiser path (steps are capped at 0.02: up
#: to 2,000 units from y*); the warm-started points take at most 200.
START_ITERATIONS = 100_000
