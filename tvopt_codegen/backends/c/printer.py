"""The C backend's printer: C99 with ``<math.h>`` only, strict, every constant a literal."""

from __future__ import annotations

import math

import sympy as sp
from sympy.codegen.ast import float32, real
from sympy.printing.c import C99CodePrinter
from sympy.printing.precedence import PRECEDENCE

from tvopt_codegen.backends.c.precision import DOUBLE, Precision
from tvopt_codegen.lowering.printers import CanonicalOrder

#: Integers beyond this magnitude are not all floats: in single precision they print
#: as float literals, so that no int is converted to float with a change of value.
_EXACT_IN_FLOAT = 2**24


class CPrinter(CanonicalOrder, C99CodePrinter):  # type: ignore[misc]
    """C99 printer for kernel bodies: only ``<math.h>``, strict, full precision.

    Customizations are listed on each override; everything else is sympy's C99 printer.

    Parameters
    ----------
    precision : Precision, optional
        Double (the default) or single: the type of the literals and functions printed.
    """

    def __init__(self, precision: Precision = DOUBLE) -> None:
        self.precision = precision
        settings: dict[str, object] = {
            "strict": True,
            "precision": 17,
            "allow_unknown_functions": False,
            "order": "none",
            # M_PI_4, M_SQRT2, M_E, ... are POSIX, not C99: -std=c99 -pedantic hides
            # them (a ring of 8 agents has pi/4). Constants print as numbers.
            "math_macros": {},
        }
        if precision.single:
            # sympy's float32 alias: sinf, fabsf, powf, ... and the suffix on its literals.
            settings["type_aliases"] = {real: float32}
        super().__init__(settings)

    def _literal(self, value: float) -> str:
        """A number as a literal of the printer's precision."""
        return self.precision.literal(value)

    def _get_literal_suffix(self, type_: object) -> str:
        """Customizations.

        * The precision's suffix (``f``, lower case as C programmers write it; sympy
          writes ``F``).
        """
        return self.precision.suffix

    def _print_Float(self, flt: sp.Float) -> str:
        """Customizations.

        * Single precision: the shortest literal that reads back as the nearest float
          (at most 9 significant digits), suffixed; double is sympy's.
        """
        if self.precision.single:
            return self._literal(float(flt))
        result: str = super()._print_Float(flt)
        return result

    def _print_Integer(self, expr: sp.Integer) -> str:
        """Customizations.

        * Single precision: an integer that a float does not hold exactly prints as a
          float literal (its conversion from int would change its value).
        """
        if self.precision.single and abs(int(expr)) > _EXACT_IN_FLOAT:
            return self._literal(float(expr))
        result: str = super()._print_Integer(expr)
        return result

    def _print_Pi(self, expr: sp.Expr) -> str:
        """Customizations.

        * A literal instead of ``M_PI``: the macro is POSIX, not C99, and ``-std=c99
          -pedantic`` hides it.
        """
        return "3.141592653589793" if not self.precision.single else self._literal(math.pi)

    def _print_Exp1(self, expr: sp.Expr) -> str:
        """Customizations.

        * A literal instead of ``M_E`` (POSIX, not C99) or, without the macro, sympy's
          declaration of a constant ``E`` in the middle of an expression.
        """
        return self._literal(math.e)

    def _print_Pow(self, expr: sp.Pow, rational: bool = False) -> str:
        """Customizations.

        * Small integer powers are products (``x*x``): exact for squares and cheaper than
          ``pow`` everywhere without relying on ``-ffast-math``.
        * Negative integer powers are ``1.0/(...)`` (``1.0f`` in single precision).
        """
        exp = expr.exp
        one = self._literal(1.0)
        if exp.is_Integer and 2 <= abs(int(exp)) <= 4:
            base = self.parenthesize(expr.base, PRECEDENCE["Mul"])
            product = "*".join([base] * abs(int(exp)))
            return f"({product})" if exp > 0 else f"({one}/({product}))"
        if exp == -1:
            return f"({one}/{self.parenthesize(expr.base, PRECEDENCE['Mul'])})"
        result: str = super()._print_Pow(expr)
        return result
