"""What the engine tests share: a small KKT spec, and a Python run on SymEngine."""

from __future__ import annotations

import os
import subprocess
import sys

from .conftest import ROOT

#: A small plant held on a moving line (an equality) with an objective that is not
#: quadratic: the KKT law, its multiplier's pivots, the sweep's equality kernel.
ON_A_LINE = """
name = "on_a_line"
[system]
states = ["x1", "x2"]
inputs = ["u1", "u2"]
[system.dynamics]
x1 = "u1"
x2 = "u2"
[system.outputs]
y1 = "x1"
y2 = "x2"
[parameters]
w = 2.0
[objective]
f0 = "log(cosh(y1 - 1)) + 0.5*w*(y2 - sin(t))**2 + 0.1*y1**2"
[constraints]
line = "cos(0.1*t)*y1 + sin(0.1*t)*y2 == 1 + 0.1*t"
[error_dynamics]
poles = [-1.0]
[simulation]
t_final = 5.0
initial_state = { x1 = 0.5, x2 = 0.2 }
"""


def run_on_symengine(code: str) -> subprocess.CompletedProcess[str]:
    """``python -c code`` in a fresh process whose engine is SymEngine (it may fail)."""
    return subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        env={**os.environ, "TVOPT_CODEGEN_ENGINE": "symengine"},
        cwd=ROOT,
        timeout=120,
        check=False,
    )
