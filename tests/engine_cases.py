"""What the engine tests share: a small KKT spec, a float walk of either engine's trees,
and a Python run on SymEngine."""

from __future__ import annotations

import contextlib
import math
import os
import subprocess
import sys
from collections.abc import Callable, Iterator, Mapping
from typing import Any

from tvopt_codegen import symbolic as sx

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


@contextlib.contextmanager
def remembered_simplify() -> Iterator[None]:
    """SymPy's top-level ``simplify`` worked out once per expression, for the block.

    A test that compares ``simplified_det`` with ``factor(simplify(det))`` asks SymPy for
    the same ``simplify(det)`` as the branch it checks took (a few tenths of a second
    each): ``simplify`` is a function of its input alone, so the second answer is the
    first. The product reads ``sympy.simplify`` at each call (``border.sympy()``), and so
    does a test that writes ``sp.simplify``; SymPy's own inner calls are not touched. A
    call that raised (the product's time limit) is not remembered.
    """
    import sympy  # noqa: PLC0415 - only the tests that compare with SymPy need it

    original = sympy.simplify
    known: dict[Any, Any] = {}

    def simplify(expr: Any, *args: Any, **kwargs: Any) -> Any:
        if args or kwargs:
            return original(expr, *args, **kwargs)
        try:
            return known[expr]
        except KeyError:
            known[expr] = found = original(expr)
            return found
        except TypeError:  # a mutable matrix: not a key
            return original(expr)

    sympy.simplify = simplify
    try:
        yield
    finally:
        sympy.simplify = original


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


_UNARY: dict[str, Callable[[float], float]] = {
    "sin": math.sin,
    "cos": math.cos,
    "tan": math.tan,
    "asin": math.asin,
    "acos": math.acos,
    "atan": math.atan,
    "sinh": math.sinh,
    "cosh": math.cosh,
    "tanh": math.tanh,
    "asinh": math.asinh,
    "acosh": math.acosh,
    "atanh": math.atanh,
    "exp": math.exp,
    "log": math.log,
    "sqrt": math.sqrt,
    "Abs": abs,
    "sign": lambda v: float((v > 0) - (v < 0)),
    "cot": lambda v: 1 / math.tan(v),
    "sec": lambda v: 1 / math.cos(v),
    "csc": lambda v: 1 / math.sin(v),
    "coth": lambda v: 1 / math.tanh(v),
    "sech": lambda v: 1 / math.cosh(v),
    "csch": lambda v: 1 / math.sinh(v),
}
_RELATIONS: dict[str, Callable[[float, float], bool]] = {
    "StrictLessThan": lambda a, b: a < b,
    "LessThan": lambda a, b: a <= b,
    "StrictGreaterThan": lambda a, b: a > b,
    "GreaterThan": lambda a, b: a >= b,
    "Equality": lambda a, b: a == b,
    "Unequality": lambda a, b: a != b,
}


def float_value(
    node: Any,
    env: Mapping[Any, float],
    memo: dict[Any, Any],
    key: Callable[[Any], Any] = lambda symbol: symbol,
) -> Any:
    """``node`` of either engine in floats (a bool for a condition), walked from the tree.

    What a backend's printer would make of it: its symbols' values are ``env[key(s)]``
    (the symbol itself, or its name with ``key=str``).
    """
    done = memo.get(node)
    if done is not None:
        return done
    kind = type(node).__name__
    if node.is_Symbol:
        out: Any = env[key(node)]
    elif kind in ("BooleanTrue", "BooleanAtom") and bool(node):
        out = True
    elif kind in ("BooleanTrue", "BooleanFalse", "BooleanAtom"):
        out = kind == "BooleanTrue"
    elif node.is_Number or node in (sx.pi, sx.E):
        out = float(node)
    elif sx.is_piecewise(node):
        out = math.nan
        for piece, condition in sx.piecewise_pairs(node):
            if float_value(condition, env, memo, key):
                out = float_value(piece, env, memo, key)
                break
    else:
        args = [float_value(arg, env, memo, key) for arg in node.args]
        if node.is_Add:
            out = math.fsum(args)
        elif node.is_Mul:
            out = math.prod(args)
        elif node.is_Pow:
            out = _power(*args)
        elif kind in _RELATIONS:
            out = _RELATIONS[kind](*args)
        elif kind == "And":
            out = all(args)
        elif kind == "Or":
            out = any(args)
        elif kind == "Not":
            out = not args[0]
        else:
            name = sx.function_name(node)
            if name == "atan2":
                out = math.atan2(*args)
            elif name in ("Max", "Min"):
                out = max(args) if name == "Max" else min(args)
            else:
                out = _UNARY[name](*args)
    memo[node] = out
    return out


def _power(base: float, exponent: float) -> float:
    try:
        return float(base**exponent)
    except (OverflowError, ZeroDivisionError):
        return math.inf
