"""What every CasADi peer of the benchmarks shares: compiler flags, runs, sympy to SX."""

from __future__ import annotations

import math

import casadi as ca
import sympy as sp

CFLAGS = ["-O2", "-std=gnu99", "-fPIC"]
HARNESS_RUNS = 5

_CASADI_FUNCTIONS = {
    "sin": ca.sin,
    "cos": ca.cos,
    "tan": ca.tan,
    "asin": ca.asin,
    "acos": ca.acos,
    "atan": ca.atan,
    "atan2": ca.atan2,
    "sinh": ca.sinh,
    "cosh": ca.cosh,
    "tanh": ca.tanh,
    "asinh": ca.asinh,
    "acosh": ca.acosh,
    "atanh": ca.atanh,
    "exp": ca.exp,
    "log": ca.log,
    "sqrt": ca.sqrt,
    "pi": math.pi,
}


def _to_casadi(expr: sp.Expr, symbols: list[sp.Symbol], values: list[object]) -> object:
    """Evaluate a sympy expression on CasADi symbols (the peer starts from the same math)."""
    return sp.lambdify(symbols, expr, modules=[_CASADI_FUNCTIONS, "math"])(*values)
