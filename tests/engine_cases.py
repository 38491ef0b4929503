"""What the engine tests share: a small KKT spec, a float walk of either engine's trees,
and a Python run on SymEngine."""

from __future__ import annotations

import contextlib
import json
import math
import os
import subprocess
import sys
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path
from typing import Any

from tvopt_codegen import symbolic as sx

from .conftest import REFUSE_SYMPY, ROOT, remembered, shared

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
    once = remembered(original)

    def simplify(expr: Any, *args: Any, **kwargs: Any) -> Any:
        return original(expr, *args, **kwargs) if args or kwargs else once(expr)

    sympy.simplify = simplify
    try:
        yield
    finally:
        sympy.simplify = original


#: The bundled examples and test specs.
EXAMPLES = sorted(p.stem for p in (ROOT / "tvopt_codegen" / "examples").glob("*.toml"))
#: Examples whose derivation still crosses the border on SymEngine: none. arm_on_line's
#: det R, a denominator that is a sum, is written as SymPy's ``dotprodsimp`` writes it
#: (``trigforms.cancelled``, ``tests/test_linalg_native.py``), simplified and its singular
#: and undefined sets found natively (``tests/test_det_native.py``).
BORDER: tuple[str, ...] = ()
#: The arm's det R as the derivation hands it to simplified_det, as SymPy prints it
#: (``test_det_native.ARM_DET``, which checks the two are one).
ARM_DET_TEXT = (
    "(-sin(q1)*cos(q1 + q2) + sin(q1 + q2)*cos(q1))/"
    "(l1*l2*m1*m2 - l1*l2*m2**2*cos(q2)**2 + l1*l2*m2**2)"
)

#: One SymEngine process for three files' checks that SymPy is not needed (a cold
#: process is a quarter of a second of imports, and each ran its own): with SymPy's
#: import refused, the arm's det R decided (test_det_native), ``generate arm_on_line`` on
#: both backends (test_det_native), every bundled example derived, lowered and rendered
#: (test_engine_det); then with the refusal lifted (as test_report_printing's own process
#: ran it: an import that a fallback would swallow under the refusal is seen),
#: ``report ur5_tip`` and the modules it imported; last, with SymPy allowed, the
#: ``BORDER`` examples. Each part reports its own failure, so each test sees only its own.
_SYMPY_FREE = (
    "import json, sys, tempfile, traceback\n"
    + REFUSE_SYMPY
    + """
args = json.loads(sys.argv[1])
out = {}
def sympy_modules():
    return sorted(m for m in sys.modules if m.split(".")[0] == "sympy")[:3]
guard = Refuse()
sys.meta_path.insert(0, guard)
try:
    from tvopt_codegen import symbolic as sx
    from tvopt_codegen.derivation.singularity import _singular_set, simplified_det
    det = sx.sympify(args["det"])
    found = simplified_det(det)
    out["det"] = [sx.text(found), list(_singular_set(found))]
    assert "sympy" not in sys.modules
except BaseException:
    out["det failed"] = traceback.format_exc()
try:
    from tvopt_codegen.cli import main
    for backend in ("python", "c"):
        code = main(["generate", "arm_on_line", "--backend", backend, "--out", args["out"],
                     "--quiet"])
        assert code == 0, code
    out["sympy modules"] = sympy_modules()
except BaseException:
    out["generate failed"] = traceback.format_exc()
records = {}
def record(name):
    from tvopt_codegen import symbolic as sx
    from tvopt_codegen.spec import load_spec
    from tvopt_codegen.derivation import derive
    from tvopt_codegen.lowering.ir import lower
    from tvopt_codegen.renderer.rendering import render
    d = derive(load_spec(name))
    render(lower(d), "python")
    dec = d.decoupling
    records[name] = [list(dec.singular_set), list(dec.undefined_set), dec.det_R_note,
                     None if dec.det_R is None else sx.text(dec.det_R)]
try:
    for name in args["free"]:
        record(name)
    assert "sympy" not in sys.modules
except BaseException:
    out["records failed"] = traceback.format_exc()
sys.meta_path.remove(guard)
try:
    from tvopt_codegen.cli import main
    main(["report", "ur5_tip", "--out", tempfile.mkdtemp()])
    out["report's sympy modules"] = sorted(
        m for m in sys.modules if m.split(".")[0] == "sympy")
except BaseException:
    out["report failed"] = traceback.format_exc()
try:
    for name in args["border"]:
        record(name)
except BaseException:
    out["records failed"] = traceback.format_exc()
out["records"] = records
print(json.dumps(out))
"""
)


def sympy_free_run() -> tuple[dict[str, Any], Path]:
    """What the SymPy-refusing process found, and the folder it generated into.

    Once per run, whichever worker asks first (conftest's ``shared``): its parts are
    test_det_native's, test_engine_det's and test_report_printing's.
    """

    def build(folder: Path) -> None:
        args = {
            "det": ARM_DET_TEXT,
            "out": str(folder / "generated"),
            "free": [name for name in EXAMPLES if name not in BORDER],
            "border": list(BORDER),
        }
        ran = subprocess.run(
            [sys.executable, "-c", _SYMPY_FREE, json.dumps(args)],
            capture_output=True,
            text=True,
            env={**os.environ, "TVOPT_CODEGEN_ENGINE": "symengine"},
            cwd=ROOT,
            check=False,
            timeout=600,
        )
        assert ran.returncode == 0, ran.stderr[-3000:]
        (folder / "found.json").write_text(ran.stdout.splitlines()[-1], encoding="utf-8")

    folder = shared("sympy-free-run", build)
    found: dict[str, Any] = json.loads((folder / "found.json").read_text(encoding="utf-8"))
    return found, folder / "generated"


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
