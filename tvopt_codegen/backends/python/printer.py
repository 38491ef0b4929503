"""The Python backend's printers: NumPy for a batch, floats for one point, both at once."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, ClassVar

from tvopt_codegen import symbolic as sx
from tvopt_codegen.lowering.printers import (
    MUL,
    RELATIONS,
    ExpressionPrinter,
    UnprintableError,
    float_digits,
)

#: The NumPy ufunc of each function an expression may apply, by the name both engines
#: give it; ``Abs`` is Python's ``abs`` (any number's), ``Max`` and ``Min`` are printed
#: apart.
NUMPY_FUNCTIONS = {
    "sin": "numpy.sin",
    "cos": "numpy.cos",
    "tan": "numpy.tan",
    "asin": "numpy.arcsin",
    "acos": "numpy.arccos",
    "atan": "numpy.arctan",
    "atan2": "numpy.arctan2",
    "sinh": "numpy.sinh",
    "cosh": "numpy.cosh",
    "tanh": "numpy.tanh",
    "asinh": "numpy.arcsinh",
    "acosh": "numpy.arccosh",
    "atanh": "numpy.arctanh",
    "exp": "numpy.exp",
    "log": "numpy.log",
    "sign": "numpy.sign",
    "floor": "numpy.floor",
    "ceiling": "numpy.ceil",
    "Abs": "abs",
}

#: NumPy's name of each relation of a condition.
_RELATIONS = {
    "<": "less",
    "<=": "less_equal",
    ">": "greater",
    ">=": "greater_equal",
    "==": "equal",
    "!=": "not_equal",
}

#: Python's keywords: a symbol so named prints with ``_`` appended, as SymPy's printer
#: had it (spec names never are one).
_RESERVED = frozenset(
    "and as assert break class continue def del elif else except finally for from global "
    "if import in is lambda not or pass raise return try while with yield None False "
    "nonlocal True".split()
)


class PythonPrinter(ExpressionPrinter):
    """NumPy printer for kernel bodies, strict about anything it cannot translate.

    Kernel expressions are elementwise over a batch of states, so every function
    maps to its ``numpy`` ufunc; a node with no translation is an error at generation
    time instead of broken code at run time. What SymPy's NumPy printer wrote, as the
    golden files hold it, with these choices:

    * Small integer powers are products (``x*x``), and their reciprocals ``1/(x*x)``:
      exact for squares, as the C backend writes them, and the same bits whether ``x``
      is a NumPy array or a Python float (``float.__pow__`` calls libm's ``pow``, NumPy
      its own, and they differ in the last bit).
    * Every other power is ``numpy.power(x, e)``, one routine for arrays and scalars
      alike; square roots are ``numpy.sqrt``.
    """

    reserved_words: ClassVar[frozenset[str]] = _RESERVED

    # -- numbers ---------------------------------------------------------------------

    def _print_Integer(self, expr: Any) -> str:
        return str(int(expr))

    def _print_Rational(self, expr: Any) -> str:
        return f"{int(expr.p)}/{int(expr.q)}"

    def _print_Float(self, expr: Any) -> str:
        # SymPy's Float of a double: 15 significant digits, trailing zeros dropped
        # inside an expression.
        return float_digits(float(expr), 15, strip_zeros=True)

    def _print_top(self, expr: Any) -> str:
        if expr.is_Float:  # a lone Float kept its zeros (2.50000000000000)
            return float_digits(float(expr), 15, strip_zeros=False)
        return self._print(expr)

    def _print_Pi(self, expr: Any) -> str:
        return "numpy.pi"

    def _print_Exp1(self, expr: Any) -> str:
        return "numpy.e"

    # -- operations ------------------------------------------------------------------

    def _power(self, base: Any, exponent: Any) -> str:
        if exponent.is_Integer and 1 <= abs(int(exponent)) <= 4:
            n = int(exponent)
            text = self.parenthesize(base, MUL)
            product = "*".join([text] * abs(n))
            if n > 0:
                return f"({product})" if n > 1 else product
            one = self._print(sx.ONE)
            return f"{one}/{text}" if n == -1 else f"{one}/({product})"
        if _is_half(exponent, 1):
            return self._call(f"numpy.sqrt({self._print(base)})")
        if _is_half(exponent, -1):
            return f"{self._print(sx.ONE)}/{self._call(f'numpy.sqrt({self._print(base)})')}"
        return self._call(f"numpy.power({self._print(base)}, {self._print(exponent)})")

    def _function(self, name: str, args: tuple[Any, ...]) -> str:
        if name in ("Max", "Min"):
            if len(args) == 1:
                return self._print(args[0])
            ufunc = "numpy.maximum" if name == "Max" else "numpy.minimum"
            return f"functools.reduce({ufunc}, [{', '.join(self._print(a) for a in args)}])"
        known = NUMPY_FUNCTIONS.get(name)
        if known is None:
            raise UnprintableError(f"NumPy has no function {name!r}")
        return self._called(f"{known}({', '.join(self._print(a) for a in args)})")

    _print_Max = _print_Min = ExpressionPrinter._print_Function

    def _print_Piecewise(self, expr: Any) -> str:
        """``numpy.select`` of the pieces (NaN where none holds)."""
        pairs = sx.piecewise_pairs(expr)
        conditions = ",".join(self._print(c) for _, c in pairs)
        values = ",".join(self._print(v) for v, _ in pairs)
        return self._called(f"numpy.select([{conditions}], [{values}], default=numpy.nan)")

    def _print_BooleanTrue(self, expr: Any) -> str:
        return "True"

    def _print_Relational(self, expr: Any) -> str:
        lhs, rhs = expr.args
        ufunc = _RELATIONS[RELATIONS[type(expr).__name__]]
        return f"numpy.{ufunc}({self._print(lhs)}, {self._print(rhs)})"

    _print_StrictLessThan = _print_LessThan = _print_StrictGreaterThan = _print_Relational
    _print_GreaterThan = _print_Equality = _print_Unequality = _print_Relational

    def _print_And(self, expr: Any) -> str:
        return f"numpy.logical_and.reduce(({','.join(self._print(a) for a in expr.args)}))"

    def _print_Or(self, expr: Any) -> str:
        return f"numpy.logical_or.reduce(({','.join(self._print(a) for a in expr.args)}))"

    def _print_Not(self, expr: Any) -> str:
        return f"numpy.logical_not({self._print(expr.args[0])})"

    def _called(self, text: str) -> str:
        """A function node's text: a NumPy call is one the scalar printer converts."""
        return self._call(text) if text.startswith("numpy.") else text

    def _call(self, text: str) -> str:
        """A call of a NumPy function, as printed (the scalar printer converts it)."""
        return text


def _is_half(exponent: Any, sign: int) -> bool:
    """Whether ``exponent`` is the rational ``sign/2`` (a float 0.5 is a power)."""
    return bool(
        exponent.is_Rational
        and not exponent.is_Integer
        and (int(exponent.p), int(exponent.q)) == (sign, 2)
    )


class PythonScalarPrinter(PythonPrinter):
    """The NumPy printer for one point: every NumPy function's result becomes a ``float``.

    The one-point kernels run on Python floats. A NumPy function returns a NumPy
    scalar, on which every later operation costs about three times a float's; the
    value is the same, so it is converted at once, through the module's alias
    ``_np_<name>`` of ``numpy.<name>`` (one global lookup instead of a global and an
    attribute: the template defines the aliases the code uses). The function stays
    NumPy's: its bits then equal those of the batch path (libm's ``math`` functions
    differ from NumPy's vectorized ones in the last bit). Integers print as floats
    (``2.0``): CPython's fast path multiplies two floats, not an int and a float; the
    value is the same (an int converts exactly).
    """

    def _call(self, text: str) -> str:
        return f"float(_np_{text.removeprefix('numpy.')})"

    def _print_Integer(self, expr: Any) -> str:
        return f"{int(expr)}.0"


#: Where :class:`PythonJointPrinter`'s two texts differ: a NumPy call's start and end,
#: and an integer's end. Control characters: no name or number contains one.
_CALL, _END, _INTEGER = "\x01", "\x02", "\x03"


def _batch_text(text: str) -> str:
    return text.replace(_CALL, "numpy.").replace(_END, "").replace(_INTEGER, "")


def _scalar_text(text: str) -> str:
    return text.replace(_CALL, "float(_np_").replace(_END, ")").replace(_INTEGER, ".0")


class PythonJointPrinter(PythonPrinter):
    """:class:`PythonPrinter`'s and :class:`PythonScalarPrinter`'s texts from one printing.

    The two differ only where the second wraps a NumPy call in ``float`` through an
    alias and writes an integer as a float; no printing method reads those pieces'
    text back (a sum's sign is read from its term's first character, which they leave
    alone). So this printer marks those places and :meth:`texts` replaces the marks:
    the Python backend prints its kernels once instead of twice (a third of rendering
    time). A test holds both texts equal to the two printers' own, for every bundled
    example.
    """

    def _call(self, text: str) -> str:
        return f"{_CALL}{text.removeprefix('numpy.')}{_END}"

    def _print_Integer(self, expr: Any) -> str:
        return f"{int(expr)}{_INTEGER}"

    @staticmethod
    def texts() -> dict[str, Callable[[str], str]]:
        """Functions from the marked text to each printing's: ``""`` batch, ``"1"`` one point."""
        return {"": _batch_text, "1": _scalar_text}
