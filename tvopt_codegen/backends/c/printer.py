"""The C backend's printer: C99 with ``<math.h>`` only, strict, every constant a literal."""

from __future__ import annotations

import math
from typing import Any, ClassVar

from tvopt_codegen import symbolic as sx
from tvopt_codegen.backends.c.precision import DOUBLE, Precision
from tvopt_codegen.lowering.printers import (
    AND,
    MUL,
    NOT,
    OR,
    POW,
    RELATIONS,
    ExpressionPrinter,
    UnprintableError,
    float_digits,
)

#: Integers beyond this magnitude are not all floats: in single precision they print
#: as float literals, so that no int is converted to float with a change of value.
_EXACT_IN_FLOAT = 2**24

#: The <math.h> function of each function an expression may apply (the ``f`` variant
#: in single precision), by the name both engines give it. ``sign``, ``Max`` and
#: ``Min`` are printed apart.
C_FUNCTIONS = {
    "Abs": "fabs",
    "sin": "sin",
    "cos": "cos",
    "tan": "tan",
    "asin": "asin",
    "acos": "acos",
    "atan": "atan",
    "atan2": "atan2",
    "exp": "exp",
    "log": "log",
    "sinh": "sinh",
    "cosh": "cosh",
    "tanh": "tanh",
    "asinh": "asinh",
    "acosh": "acosh",
    "atanh": "atanh",
    "sqrt": "sqrt",
    "floor": "floor",
    "ceiling": "ceil",
}

#: The words of C99 a symbol is renamed from (``int`` prints ``int_``), as SymPy's C99
#: printer had them; spec names never are one (:data:`~tvopt_codegen.backends.c.C_KEYWORDS`).
_RESERVED = frozenset(
    "auto break case char const continue default do double else enum extern float for goto "
    "if int long register return short signed sizeof static struct entry switch typedef "
    "union unsigned void volatile while inline restrict".split()
)


class CPrinter(ExpressionPrinter):
    """C99 printer for kernel bodies: only ``<math.h>``, strict, full precision.

    What SymPy's C99 printer wrote, as the golden files hold it, with these choices:

    * every constant a literal: ``pi`` and ``E`` as numbers (``M_PI``, ``M_E`` are POSIX,
      not C99, and ``-std=c99 -pedantic`` hides them);
    * small integer powers as products (``x*x``): exact for squares and cheaper than
      ``pow`` everywhere without relying on ``-ffast-math``; negative integer powers as
      ``1.0/(...)``;
    * a double literal with 17 significant digits, a single one the shortest text that
      reads back as the nearest float, suffixed (:meth:`Precision.literal`), as every
      ``<math.h>`` function of that precision (``sinf``).

    Parameters
    ----------
    precision : Precision, optional
        Double (the default) or single: the type of the literals and functions printed.
    """

    reserved_words: ClassVar[frozenset[str]] = _RESERVED

    def __init__(self, precision: Precision = DOUBLE) -> None:
        super().__init__()
        self.precision = precision
        self._suffix = precision.suffix
        self._one = precision.literal(1.0)

    # -- numbers ---------------------------------------------------------------------

    def _print_Integer(self, expr: Any) -> str:
        value = int(expr)
        if self.precision.single and abs(value) > _EXACT_IN_FLOAT:
            # An int that a float does not hold would change value on conversion.
            return self.precision.literal(float(value))
        return str(value)

    def _print_Rational(self, expr: Any) -> str:
        suffix = self._suffix
        return f"{int(expr.p)}.0{suffix}/{int(expr.q)}.0{suffix}"

    def _print_Float(self, expr: Any) -> str:
        value = float(expr)
        if self.precision.single:
            return self.precision.literal(value)
        # 17 significant digits, the zeros after the last nonzero one dropped.
        mantissa, *exponent = float_digits(value, 17, strip_zeros=False).split("e")
        if not exponent and "." not in mantissa:
            mantissa += ".0"
        mantissa = mantissa.rstrip("0")
        if mantissa.endswith("."):
            mantissa += "0"
        return "e".join([mantissa, *exponent])

    def _print_Pi(self, expr: Any) -> str:
        return self.precision.literal(math.pi)

    def _print_Exp1(self, expr: Any) -> str:
        return self.precision.literal(math.e)

    # -- operations ------------------------------------------------------------------

    def _power(self, base: Any, exponent: Any) -> str:
        one = self._one
        if exponent.is_Integer:
            n = int(exponent)
            if 2 <= abs(n) <= 4:
                product = "*".join([self.parenthesize(base, MUL)] * abs(n))
                return f"({product})" if n > 0 else f"({one}/({product}))"
            if n == -1:
                return f"({one}/{self.parenthesize(base, MUL)})"
        suffix = self._suffix
        if exponent.is_Float and float(exponent) == -1.0:
            return f"{one}/{self.parenthesize(base, POW)}"
        if exponent.is_Number and not exponent.is_Integer and float(exponent) == 0.5:
            return f"sqrt{suffix}({self._print(base)})"
        if exponent.is_Rational and not exponent.is_Integer and (exponent.p, exponent.q) == (1, 3):
            return f"cbrt{suffix}({self._print(base)})"
        return f"pow{suffix}({self._print(base)}, {self._print(exponent)})"

    def _function(self, name: str, args: tuple[Any, ...]) -> str:
        if name == "sign":
            # An int, as SymPy printed it: (x > 0) - (x < 0).
            return "((({0}) > 0) - (({0}) < 0))".format(self._print(args[0]))
        if name in ("Max", "Min"):
            # fmax(a, fmax(b, c)): C's is binary.
            call = ("fmax" if name == "Max" else "fmin") + self._suffix
            text = self._print(args[-1])
            for arg in reversed(args[:-1]):
                text = f"{call}({self._print(arg)}, {text})"
            return text
        known = C_FUNCTIONS.get(name)
        if known is None:
            raise UnprintableError(f"C has no function {name!r}")
        return f"{known}{self._suffix}({', '.join(self._print(a) for a in args)})"

    _print_Max = _print_Min = ExpressionPrinter._print_Function

    def _print_Piecewise(self, expr: Any) -> str:
        """Nested conditional expressions, the last piece's condition true."""
        pairs = sx.piecewise_pairs(expr)
        if type(pairs[-1][1]).__name__ != "BooleanTrue":
            raise ValueError("a Piecewise needs a last piece that holds everywhere")
        text = f"({self._print(pairs[-1][0])})"
        for value, condition in reversed(pairs[:-1]):
            text = f"(({self._print(condition)}) ? ({self._print(value)}) : {text})"
        return text

    def _print_Relational(self, expr: Any) -> str:
        lhs, rhs = expr.args
        return f"{self._print(lhs)} {RELATIONS[type(expr).__name__]} {self._print(rhs)}"

    _print_StrictLessThan = _print_LessThan = _print_StrictGreaterThan = _print_Relational
    _print_GreaterThan = _print_Equality = _print_Unequality = _print_Relational

    def _print_And(self, expr: Any) -> str:
        return " && ".join(self.parenthesize(a, AND) for a in sorted(expr.args, key=self._print))

    def _print_Or(self, expr: Any) -> str:
        return " || ".join(self.parenthesize(a, OR) for a in sorted(expr.args, key=self._print))

    def _print_Not(self, expr: Any) -> str:
        return "!" + self.parenthesize(expr.args[0], NOT)
