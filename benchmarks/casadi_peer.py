"""What every CasADi peer of the benchmarks shares: compiler flags, runs, sympy to SX."""

from __future__ import annotations

import math

import casadi as ca
import sympy as sp

CFLAGS = ["-O2", "-std=gnu99", "-fPIC"]
HARNESS_RUNS = 5

#: The harnesses' timed loop: our ``<name>_control`` and CasADi's ``casadi_law`` in
#: turns, best of REPEATS each (a burst of load on the shared machine then spoils one
#: round of each, not the side that happened to run during it). Formatted with ``name``.
TURNS = r"""    for (rep = 0; rep < REPEATS; ++rep) {{
        t0 = now();
        for (i = 0; i < calls; ++i) {{ {name}_control(1e-6 * i, s, p, u); acc += u[0]; }}
        if ((now() - t0) / calls < best_ours) best_ours = (now() - t0) / calls;
        t0 = now();
        for (i = 0; i < calls; ++i) {{
            tt = 1e-6 * i;
            casadi_law(arg, res, iw, w, 0);
            acc += u[0];
        }}
        if ((now() - t0) / calls < best_casadi) best_casadi = (now() - t0) / calls;
    }}
    printf("loop %.6e %.6e\n", best_ours, best_casadi);
"""

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
