"""The printers on both engines (issue 49): the same code, whichever engine built the tree.

Every kind of node a kernel may hold is printed from expressions built through the
symbolic API on SymPy and on SymEngine; the NumPy text is evaluated with NumPy and the
C text compiled and run, and both give the value computed directly with ``math``. The
literals are spelled as the golden files spell them, on both engines, and SymEngine's
text is the same whatever Python's hash seed.
"""

from __future__ import annotations

import math
import os
import shutil
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from tvopt_codegen import symbolic as sx
from tvopt_codegen.backends.c.precision import PRECISIONS
from tvopt_codegen.backends.c.printer import CPrinter
from tvopt_codegen.backends.python.printer import (
    PythonJointPrinter,
    PythonPrinter,
    PythonScalarPrinter,
)
from tvopt_codegen.lowering.printers import UnprintableError

from .conftest import ROOT

ENGINES = ("sympy", "symengine")
#: The point every case is evaluated at: inside every function's domain.
X, Y, Z = 0.3, 1.7, -0.6

#: Each case: the expression from the API's names and the symbols x, y, z, and its value
#: computed directly.
Case = tuple[Callable[[Any, Any, Any], Any], Callable[[float, float, float], float]]
CASES: dict[str, Case] = {
    "sum": (lambda x, y, z: x - 2 * y + 3, lambda x, y, z: x - 2 * y + 3),
    "negative sum": (lambda x, y, z: -x - y - 3, lambda x, y, z: -x - y - 3),
    "product": (lambda x, y, z: -3 * x * y * z, lambda x, y, z: -3 * x * y * z),
    "quotient": (lambda x, y, z: x / (y * z), lambda x, y, z: x / (y * z)),
    "quotient by a sum": (lambda x, y, z: x / (y + z), lambda x, y, z: x / (y + z)),
    "product of a sum": (lambda x, y, z: 2 * (x + y) * z, lambda x, y, z: 2 * (x + y) * z),
    "rational": (lambda x, y, z: sx.Rational(-1, 3) * x + y / 7, lambda x, y, z: -x / 3 + y / 7),
    "square": (lambda x, y, z: (x + y) ** 2, lambda x, y, z: (x + y) ** 2),
    "cube over": (lambda x, y, z: y / z**3, lambda x, y, z: y / z**3),
    "inverse square": (lambda x, y, z: (x - y) ** -2, lambda x, y, z: (x - y) ** -2),
    "inverse": (lambda x, y, z: 1 / (x + y), lambda x, y, z: 1 / (x + y)),
    "fifth power": (lambda x, y, z: y**5, lambda x, y, z: y**5),
    "negative power": (lambda x, y, z: y**-5 + x, lambda x, y, z: y**-5 + x),
    "rational power": (lambda x, y, z: y ** sx.Rational(3, 2), lambda x, y, z: y**1.5),
    "cube root": (lambda x, y, z: y ** sx.Rational(1, 3), lambda x, y, z: y ** (1 / 3)),
    "symbolic power": (lambda x, y, z: y**x, lambda x, y, z: y**x),
    "float power": (lambda x, y, z: y ** sx.real(1.5), lambda x, y, z: y**1.5),
    "square root": (lambda x, y, z: sx.sqrt(y + x), lambda x, y, z: math.sqrt(y + x)),
    "inverse root": (lambda x, y, z: 1 / sx.sqrt(y), lambda x, y, z: 1 / math.sqrt(y)),
    "root below": (lambda x, y, z: x / sx.sqrt(y), lambda x, y, z: x / math.sqrt(y)),
    "float": (lambda x, y, z: sx.real(0.1) * x - sx.real(2.5e-7), lambda x, y, z: 0.1 * x - 2.5e-7),
    "integer and float": (
        lambda x, y, z: sx.Integer(2) * x + sx.real(2.0) * y,
        lambda x, y, z: 2 * x + 2.0 * y,
    ),
    "floats in order": (
        lambda x, y, z: (
            sx.sin(sx.real(1.5) * x) + sx.sin(sx.real(2.0) * x) + sx.cos(sx.real(0.5) * y)
        ),
        lambda x, y, z: math.sin(1.5 * x) + math.sin(2.0 * x) + math.cos(0.5 * y),
    ),
    "big integer": (lambda x, y, z: sx.Integer(2**30) * x, lambda x, y, z: 2**30 * x),
    "pi and E": (lambda x, y, z: sx.pi * x / 4 + sx.E, lambda x, y, z: math.pi * x / 4 + math.e),
    "sin": (lambda x, y, z: sx.sin(x), lambda x, y, z: math.sin(x)),
    "cos": (lambda x, y, z: sx.cos(x) ** -1, lambda x, y, z: 1 / math.cos(x)),
    "tan": (lambda x, y, z: sx.tan(x) ** 2, lambda x, y, z: math.tan(x) ** 2),
    "asin": (lambda x, y, z: sx.asin(x), lambda x, y, z: math.asin(x)),
    "acos": (lambda x, y, z: sx.acos(z), lambda x, y, z: math.acos(z)),
    "atan": (lambda x, y, z: sx.atan(y), lambda x, y, z: math.atan(y)),
    "atan2": (lambda x, y, z: sx.atan2(z, x), lambda x, y, z: math.atan2(z, x)),
    "sinh": (lambda x, y, z: sx.sinh(z), lambda x, y, z: math.sinh(z)),
    "cosh": (lambda x, y, z: sx.cosh(z), lambda x, y, z: math.cosh(z)),
    "tanh": (lambda x, y, z: 1 - sx.tanh(z) ** 2, lambda x, y, z: 1 - math.tanh(z) ** 2),
    "asinh": (lambda x, y, z: sx.asinh(z), lambda x, y, z: math.asinh(z)),
    "acosh": (lambda x, y, z: sx.acosh(y), lambda x, y, z: math.acosh(y)),
    "atanh": (lambda x, y, z: sx.atanh(x), lambda x, y, z: math.atanh(x)),
    "exp": (lambda x, y, z: 3 * sx.exp(-x), lambda x, y, z: 3 * math.exp(-x)),
    "log": (lambda x, y, z: sx.log(y) / x, lambda x, y, z: math.log(y) / x),
    "Abs": (lambda x, y, z: sx.Abs(z) * y, lambda x, y, z: abs(z) * y),
    "sign": (lambda x, y, z: sx.sign(z) * y, lambda x, y, z: math.copysign(1.0, z) * y),
    "Max": (lambda x, y, z: 2 * sx.Max(x, y, z), lambda x, y, z: 2 * max(x, y, z)),
    "Min": (lambda x, y, z: sx.Min(x, z) + 1, lambda x, y, z: min(x, z) + 1),
    "Piecewise": (
        lambda x, y, z: sx.Piecewise((x, x > y), (y * z, z < x), (z, True)),
        lambda x, y, z: x if x > y else (y * z if z < x else z),
    ),
}

#: The names the scalar printer's calls use (the Python template defines them).
_ALIASES = {f"_np_{name}": getattr(np, name) for name in dir(np) if not name.startswith("_")}


def _built(engine: str) -> dict[str, Any]:
    """Every case's expression built on ``engine``."""
    with sx.using(engine):
        x, y, z = sx.symbols("xyz")
        return {name: build(x, y, z) for name, (build, _) in CASES.items()}


def _printed(engine: str, make: Callable[[], Any]) -> dict[str, str]:
    """Every case printed on ``engine`` by one printer."""
    expressions = _built(engine)
    with sx.using(engine):
        printer = make()
        return {name: printer.doprint(expr) for name, expr in expressions.items()}


def _numpy_value(text: str) -> float:
    scope = {"numpy": np, "functools": __import__("functools"), "x": X, "y": Y, "z": Z}
    return float(eval(text, scope | _ALIASES))  # noqa: S307 - our own printed arithmetic


@pytest.mark.parametrize("engine", ENGINES)
def test_numpy_text_has_the_value_on_both_engines(engine: str) -> None:
    batch = _printed(engine, PythonPrinter)
    scalar = _printed(engine, PythonScalarPrinter)
    joint = _printed(engine, PythonJointPrinter)
    texts = PythonJointPrinter.texts()
    for name, (_, value) in CASES.items():
        want = value(X, Y, Z)
        assert _numpy_value(batch[name]) == pytest.approx(want, rel=1e-12), (name, batch[name])
        assert _numpy_value(scalar[name]) == pytest.approx(want, rel=1e-12), (name, scalar[name])
        assert texts[""](joint[name]) == batch[name]
        assert texts["1"](joint[name]) == scalar[name]
    # A NumPy array through the batch text: elementwise, as the kernels run.
    grid = np.linspace(0.1, 0.5, 5)
    scope = {"numpy": np, "x": grid, "y": Y, "z": Z}
    values = eval(batch["exp"], scope)  # noqa: S307
    assert np.allclose(values, 3 * np.exp(-grid), rtol=1e-14)


def _c_program(functions: dict[str, tuple[str, str]]) -> str:
    """A C program printing each expression's value at (X, Y, Z), one per line."""
    lines = ["#include <math.h>", "#include <stdio.h>", "int main(void) {"]
    lines.append(f"  volatile double vx = {X!r}, vy = {Y!r}, vz = {Z!r};")
    lines.append("  double xd = vx, yd = vy, zd = vz;")
    lines.append("  float xf = (float)vx, yf = (float)vy, zf = (float)vz;")
    for key, (c_type, text) in functions.items():
        suffix = "f" if c_type == "float" else "d"
        body = text
        for name in "xyz":
            body = _rename(body, name, name + suffix)
        lines.append(f'  {{ {c_type} v = {body}; printf("{key} %.17g\\n", (double)v); }}')
    lines += ["  return 0;", "}"]
    return "\n".join(lines)


def _rename(text: str, old: str, new: str) -> str:
    """``text`` with the one-letter name ``old`` replaced (no other name holds it)."""
    out = []
    for i, char in enumerate(text):
        is_name = char == old and not (i and (text[i - 1].isalnum() or text[i - 1] == "_"))
        is_name = is_name and not (i + 1 < len(text) and (text[i + 1].isalnum()))
        out.append(new if is_name else char)
    return "".join(out)


@pytest.mark.skipif(shutil.which("cc") is None, reason="no C compiler (cc)")
def test_c_text_compiles_and_has_the_value_on_both_engines(tmp_path: Path) -> None:
    single = PRECISIONS["single"]
    functions: dict[str, tuple[str, str]] = {}
    for engine in ENGINES:
        double_texts = _printed(engine, CPrinter)
        single_texts = _printed(engine, lambda: CPrinter(single))
        for i, name in enumerate(CASES):
            functions[f"{engine}:d:{i}"] = ("double", double_texts[name])
            functions[f"{engine}:f:{i}"] = ("float", single_texts[name])
    source = tmp_path / "values.c"
    source.write_text(_c_program(functions), encoding="utf-8")
    program = tmp_path / "values"
    flags = ["-std=c99", "-pedantic", "-Wall", "-Werror", "-Wno-unused-variable"]
    subprocess.run(["cc", *flags, str(source), "-o", str(program), "-lm"], check=True)
    output = subprocess.run([str(program)], check=True, capture_output=True, text=True).stdout
    values = dict(line.split(" ") for line in output.splitlines())
    assert len(values) == len(functions)
    for engine in ENGINES:
        for i, (name, (_, value)) in enumerate(CASES.items()):
            want = value(X, Y, Z)
            double = float(values[f"{engine}:d:{i}"])
            assert double == pytest.approx(want, rel=1e-12), (engine, name)
            # Single precision: float's own rounding (a few ulp of 1.2e-7).
            assert float(values[f"{engine}:f:{i}"]) == pytest.approx(want, rel=2e-6, abs=1e-6), (
                engine,
                name,
            )


@pytest.mark.parametrize("engine", ENGINES)
def test_literals_are_spelled_as_the_golden_files_spell_them(engine: str) -> None:
    """Double: 17 digits of a float, ``(1.0/3.0)``, pi and E as numbers, ``x*x`` and
    ``(1.0/(x*x))``; single: the shortest float text with ``f``, and the ``f`` functions.
    The same spelling whichever engine built the expression."""
    single = PRECISIONS["single"]
    with sx.using(engine):
        x = sx.symbol("x")
        c, cf, py, one = CPrinter(), CPrinter(single), PythonPrinter(), PythonScalarPrinter()
        cases = {
            sx.real(0.1) * x: ("0.10000000000000001*x", "0.1f*x", "0.1*x", "0.1*x"),
            sx.real(1e-20) * x: ("9.9999999999999995e-21*x", "1e-20f*x", "1.0e-20*x", "1.0e-20*x"),
            sx.real(123456789.123) * x: (
                "123456789.123*x",
                "123456790.0f*x",
                "123456789.123*x",
                "123456789.123*x",
            ),
            x / 3: ("(1.0/3.0)*x", "(1.0f/3.0f)*x", "(1/3)*x", "(1/3)*x"),
            -x / 3: ("-1.0/3.0*x", "-1.0f/3.0f*x", "-1/3*x", "-1/3*x"),
            sx.Integer(2**30) * x: (
                "1073741824*x",
                "1073741800.0f*x",
                "1073741824*x",
                "1073741824.0*x",
            ),
            sx.pi * x: ("3.141592653589793*x", "3.1415927f*x", "numpy.pi*x", "numpy.pi*x"),
            sx.E * x: ("2.718281828459045*x", "2.7182817f*x", "numpy.e*x", "numpy.e*x"),
            x**-2: ("(1.0/(x*x))", "(1.0f/(x*x))", "1/(x*x)", "1.0/(x*x)"),
            x**3: ("(x*x*x)", "(x*x*x)", "(x*x*x)", "(x*x*x)"),
            1 / x: ("(1.0/x)", "(1.0f/x)", "1/x", "1.0/x"),
            x**7: ("pow(x, 7)", "powf(x, 7)", "numpy.power(x, 7)", "float(_np_power(x, 7.0))"),
            1 / sx.sqrt(x): (
                "pow(x, -1.0/2.0)",
                "powf(x, -1.0f/2.0f)",
                "1/numpy.sqrt(x)",
                "1.0/float(_np_sqrt(x))",
            ),
            sx.exp(x): ("exp(x)", "expf(x)", "numpy.exp(x)", "float(_np_exp(x))"),
            sx.atanh(x): ("atanh(x)", "atanhf(x)", "numpy.arctanh(x)", "float(_np_arctanh(x))"),
            -(x**2): ("-(x*x)", "-(x*x)", "-(x*x)", "-(x*x)"),
            sx.real(2.5): ("2.5", "2.5f", "2.50000000000000", "2.50000000000000"),
        }
        for expr, want in cases.items():
            got = (c.doprint(expr), cf.doprint(expr), py.doprint(expr), one.doprint(expr))
            assert got == want, (engine, expr)


def test_a_node_the_language_lacks_is_refused() -> None:
    for engine in ENGINES:
        with sx.using(engine):
            x = sx.symbol("x")
            for printer in (CPrinter(), PythonPrinter()):
                with pytest.raises(UnprintableError, match="cot"):
                    printer.doprint(sx.cot(x) + 1)


def test_sums_read_the_same_on_both_engines() -> None:
    """Terms of the same tree print alike up to their order: a positive term first, the
    constant last, on both engines."""
    texts = {}
    for engine in ENGINES:
        with sx.using(engine):
            x, y = sx.symbols("xy")
            printer = CPrinter()
            texts[engine] = [printer.doprint(e) for e in (1 - x, -x - y - 3, y - x + 4, x * y - 2)]
    assert texts["sympy"] == ["1 - x", "-x - y - 3", "y - x + 4", "x*y - 2"]
    assert texts["symengine"] == ["1 - x", "-x - y - 3", "y - x + 4", "x*y - 2"]


_SCRIPT = """
from tvopt_codegen import symbolic as sx
from tvopt_codegen.backends.c.printer import CPrinter
from tvopt_codegen.backends.python.printer import PythonPrinter


def texts():
    s = sx.symbols(["a%d" % i for i in range(40)])
    e = 0
    for i in range(39):
        e = e + (i - 19) * s[i] * s[i + 1] + sx.sin(s[i]) / (s[(7 * i) % 40] + 3) - s[i] ** 2
    f = sx.expand(e * (s[0] - s[1]))
    return [p.doprint(x) for p in (CPrinter(), PythonPrinter()) for x in (e, f)]
"""


def test_symengine_text_is_the_same_whatever_the_hash_seed() -> None:
    """A process of another hash seed prints SymEngine's expressions as this one does."""
    scope: dict[str, Any] = {}
    exec(_SCRIPT, scope)  # noqa: S102 - the test's own script
    with sx.using("symengine"):
        here = scope["texts"]()
    seed = "4242" if os.environ.get("PYTHONHASHSEED") != "4242" else "17"
    env = dict(os.environ, PYTHONHASHSEED=seed, TVOPT_CODEGEN_ENGINE="symengine")
    there = subprocess.run(
        [sys.executable, "-c", _SCRIPT + "print(repr(texts()))"],
        cwd=ROOT,
        env=env,
        check=True,
        capture_output=True,
        text=True,
    ).stdout
    assert eval(there) == here  # noqa: S307 - a list of strings this test printed
    assert len(here) == 4 and "sin(a3)" in here[0]


#: The cases whose trees the engines build differently: SymPy distributes ``2*(x + y)``
#: and writes ``x > y`` where SymEngine writes ``y < x``.
_TREES_DIFFER = {"product of a sum", "Piecewise"}


def test_the_same_tree_prints_the_same_text_on_both_engines() -> None:
    """SymEngine's arguments are put in SymPy's order: equal trees, equal code."""
    single = PRECISIONS["single"]
    for make in (CPrinter, lambda: CPrinter(single), PythonJointPrinter):
        texts = {engine: _printed(engine, make) for engine in ENGINES}
        for name in CASES:
            if name not in _TREES_DIFFER:
                assert texts["sympy"][name] == texts["symengine"][name], name


def test_a_controller_prints_alike_from_either_engine() -> None:
    """Every expression of an example's kernels, and the same converted to SymEngine:
    the same C and NumPy text, line for line."""
    from tests.conftest import kernels
    from tvopt_codegen.symbolic.border import from_sympy

    with sx.using("sympy"):  # SymPy's kernels, whichever engine is the default
        expressions = [
            value
            for kernel in kernels("pvtol").kernels
            for value in [v for _, v in kernel.body] + [e for o in kernel.outputs for e in o.exprs]
        ]
    assert len(expressions) > 50
    assert all(type(e).__module__.startswith("sympy") for e in expressions)
    for make in (CPrinter, PythonJointPrinter):
        with sx.using("sympy"):
            printer = make()
            want = [printer.doprint(e) for e in expressions]
        with sx.using("symengine"):
            memo: dict[Any, Any] = {}
            converted = [from_sympy(e, memo) for e in expressions]
            printer = make()
            assert [printer.doprint(e) for e in converted] == want
