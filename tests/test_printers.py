"""The backends' printers, on hand-made expressions."""

from __future__ import annotations

import numpy as np
import sympy as sp

from tvopt_codegen.printers import CPrinter, PythonPrinter, PythonScalarPrinter

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
        x**7: ("numpy.power(x, 7)", "float(numpy.power(x, 7.0))"),
        2 * x + 1: ("2*x + 1", "2.0*x + 1.0"),
        sp.sqrt(x): ("numpy.sqrt(x)", "float(numpy.sqrt(x))"),
        x**y: ("numpy.power(x, y)", "float(numpy.power(x, y))"),
        sp.tanh(x) + 1: ("numpy.tanh(x) + 1", "float(numpy.tanh(x)) + 1.0"),
    }
    for expr, (want_array, want_scalar) in cases.items():
        assert array.doprint(expr) == want_array
        assert scalar.doprint(expr) == want_scalar
    # Same bits on both paths: NumPy's own routine, whatever the argument's type.
    values = np.linspace(-3, 3, 101)
    for expr in (x**7, x**3, sp.tanh(x), 2 * x - 3):
        batch = eval(array.doprint(expr), {"numpy": np, "x": values})  # noqa: S307
        single = [
            eval(scalar.doprint(expr), {"numpy": np, "x": float(v)})  # noqa: S307
            for v in values
        ]
        assert np.array_equal(batch, single)
