"""The backends' printers, on hand-made expressions."""

from __future__ import annotations

import math

import numpy as np
import pytest
import sympy as sp

from tvopt_codegen.backends.c.printer import CPrinter
from tvopt_codegen.backends.python.printer import PythonPrinter, PythonScalarPrinter

t, x, y, a = sp.symbols("t x y a", real=True)


def test_sums_start_positive_and_end_with_their_constant() -> None:
    py, c = PythonPrinter(), CPrinter()
    assert py.doprint(1 - x) == "1 - x"
    assert py.doprint(t - 25) == "t - 25"
    assert py.doprint(sp.Rational(1, 2) - sp.tanh((t - a) / x) / 2) == (
        "1/2 - 1/2*numpy.tanh((t - a)/x)"
    )
    assert py.doprint(-x - y - 3) == "-x - y - 3"
    assert c.doprint(x * y - 2 * t + 10) == "x*y - 2*t + 10"
    # Equal expressions print equally however they were built.
    assert py.doprint(sp.Add(y, -x, 4)) == py.doprint(sp.Add(4, -x, y)) == "y - x + 4"


def test_python_powers_print_alike_for_arrays_and_floats() -> None:

    x, y = sp.symbols("x y")
    array, scalar = PythonPrinter(), PythonScalarPrinter()
    cases = {
        x**2: ("(x*x)", "(x*x)"),
        x**-3: ("1/(x*x*x)", "1.0/(x*x*x)"),
        x**7: ("numpy.power(x, 7)", "float(_np_power(x, 7.0))"),
        2 * x + 1: ("2*x + 1", "2.0*x + 1.0"),
        sp.sqrt(x): ("numpy.sqrt(x)", "float(_np_sqrt(x))"),
        x**y: ("numpy.power(x, y)", "float(_np_power(x, y))"),
        sp.tanh(x) + 1: ("numpy.tanh(x) + 1", "float(_np_tanh(x)) + 1.0"),
    }
    from tvopt_codegen.backends.python.printer import PythonJointPrinter

    joint, texts = PythonJointPrinter(), PythonJointPrinter.texts()
    cases[-(sp.sin(x) ** 2) - 3 * sp.exp(-x) + sp.Rational(1, 3)] = (
        "1/3 - (numpy.sin(x)*numpy.sin(x)) - 3*numpy.exp(-x)",
        "1/3 - (float(_np_sin(x))*float(_np_sin(x))) - 3.0*float(_np_exp(-x))",
    )
    for expr, (want_array, want_scalar) in cases.items():
        assert array.doprint(expr) == want_array
        assert scalar.doprint(expr) == want_scalar
        marked = joint.doprint(expr)
        assert (texts[""](marked), texts["1"](marked)) == (want_array, want_scalar)
    # Same bits on both paths: NumPy's own routine, whatever the argument's type.
    values = np.linspace(-3, 3, 101)
    for expr in (x**7, x**3, sp.tanh(x), 2 * x - 3):
        batch = eval(array.doprint(expr), {"numpy": np, "x": values})  # noqa: S307
        single = [
            eval(scalar.doprint(expr), {"_np_power": np.power, "_np_tanh": np.tanh, "x": float(v)})  # noqa: S307
            for v in values
        ]
        assert np.array_equal(batch, single)


def _one_point_function(kernel: object) -> str:
    """A kernel printed for one point as a plain function, as the Python template lays it."""
    k = kernel
    lines = [f"def f({', '.join(arg.name for arg in k.args)}):"]  # type: ignore[attr-defined]
    for arg in k.args:  # type: ignore[attr-defined]
        if arg.slots:
            lines.append(f"    {arg.unpack} = {arg.name}")
    lines += [f"    {name} = {code}" for name, code in k.body]  # type: ignore[attr-defined]
    outs = ["[" + ", ".join(code for _, _, code in out.elements) + "]" for out in k.outputs]  # type: ignore[attr-defined]
    lines.append(f"    return {', '.join(outs)}")
    return "\n".join(lines)


def test_register_renaming_keeps_every_value_and_needs_fewer_names() -> None:
    """The Python backend's registers filter: the same results, bit for bit, from reused names."""
    import math
    import re

    import numpy

    from tests.conftest import kernels
    from tvopt_codegen.backends.python.filters import registers
    from tvopt_codegen.renderer.rendering import print_kernel

    for spec in ("two_unicycles_barrier", "unicycle_ring"):
        ks = kernels(spec)
        for name in ("jet", "cholesky"):
            printed = print_kernel(ks[name], PythonScalarPrinter())
            renamed = registers(printed)
            rng = np.random.default_rng(5)
            inputs = [
                rng.uniform(0.2, 0.6, arg.size).tolist() if arg.name != "t" else 0.7
                for arg in printed.args
            ]
            results = []
            for k in (printed, renamed):
                scope = {"numpy": numpy, "math": math}
                scope |= {f"_np_{n}": getattr(numpy, n) for n in ("cos", "sin", "tan")}
                exec(_one_point_function(k), scope)  # noqa: S102 - our own generated text
                results.append(scope["f"](*inputs))
            assert results[0] == results[1]  # lists of floats: exact equality
            before = {n for n, _ in printed.body}
            before |= {slot.symbol for arg in printed.args for slot in arg.slots}
            after = set(re.findall(r"_r\d+", _one_point_function(renamed)))
            assert len(after) < len(before)


def test_c_constants_are_c99_literals_not_posix_macros() -> None:
    """M_PI_4, M_E, M_1_PI are POSIX: -std=c99 -pedantic hides them. sympy's C99
    printer uses them for pi/4, E, 1/pi, ... (a ring of eight agents has pi/4)."""
    printer = CPrinter()
    constants = (x + sp.pi / 4, x + sp.pi / 2, x * sp.E, x / sp.pi, x * sp.sqrt(2), x + sp.log(2))
    for expr in constants:
        code = printer.doprint(expr)
        assert "M_" not in code and ";" not in code, code
        python = code.replace("sqrt", "math.sqrt").replace("log", "math.log")
        value = eval(python, {"math": math, "x": 0.5})  # noqa: S307 - our printed arithmetic
        assert value == pytest.approx(float(expr.subs(x, 0.5)), rel=1e-15)


def test_the_joint_printing_is_both_python_printings_for_every_example() -> None:
    """Rendering prints the Python kernels once (PythonJointPrinter) and derives both texts:
    each must be, character for character, what its own printer prints."""
    from tests.conftest import kernels
    from tvopt_codegen.backends.python.printer import PythonJointPrinter
    from tvopt_codegen.renderer.rendering import _translated, print_kernel
    from tvopt_codegen.spec import bundled_examples

    texts = PythonJointPrinter.texts()
    compared = 0
    for spec in bundled_examples():
        for kernel in kernels(spec).kernels:
            joint = print_kernel(kernel, PythonJointPrinter())
            assert _translated(joint, texts[""]) == print_kernel(kernel, PythonPrinter())
            assert _translated(joint, texts["1"]) == print_kernel(kernel, PythonScalarPrinter())
            compared += 1
    assert compared > 100
