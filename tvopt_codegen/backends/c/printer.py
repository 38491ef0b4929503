"""The C backend's printer: C99 with ``<math.h>`` only, strict, every constant a literal."""

from __future__ import annotations

import math

import sympy as sp
from sympy.printing.c import C99CodePrinter
from sympy.printing.precedence import PRECEDENCE

from tvopt_codegen.lowering.printers import CanonicalOrder


class CPrinter(CanonicalOrder, C99CodePrinter):  # type: ignore[misc]
    """C99 printer for kernel bodies: only ``<math.h>``, strict, full precision.

    Customizations are listed on each override; everything else is sympy's C99 printer.
    """

    def __init__(self) -> None:
        super().__init__(
            {
                "strict": True,
                "precision": 17,
                "allow_unknown_functions": False,
                "order": "none",
                # M_PI_4, M_SQRT2, M_E, ... are POSIX, not C99: -std=c99 -pedantic hides
                # them (a ring of 8 agents has pi/4). Constants print as numbers.
                "math_macros": {},
            }
        )

    def _print_Pi(self, expr: sp.Expr) -> str:
        """Customizations.

        * A literal instead of ``M_PI``: the macro is POSIX, not C99, and ``-std=c99
          -pedantic`` hides it.
        """
        return "3.141592653589793"

    def _print_Exp1(self, expr: sp.Expr) -> str:
        """Customizations.

        * A literal instead of ``M_E`` (POSIX, not C99) or, without the macro, sympy's
          declaration of a constant ``E`` in the middle of an expression.
        """
        return repr(math.e)

    def _print_Pow(self, expr: sp.Pow, rational: bool = False) -> str:
        """Customizations.

        * Small integer powers are products (``x*x``): exact for squares and cheaper than
          ``pow`` everywhere without relying on ``-ffast-math``.
        * Negative integer powers are ``1.0/(...)``.
        """
        exp = expr.exp
        if exp.is_Integer and 2 <= abs(int(exp)) <= 4:
            base = self.parenthesize(expr.base, PRECEDENCE["Mul"])
            product = "*".join([base] * abs(int(exp)))
            return f"({product})" if exp > 0 else f"(1.0/({product}))"
        if exp == -1:
            return f"(1.0/{self.parenthesize(expr.base, PRECEDENCE['Mul'])})"
        result: str = super()._print_Pow(expr)
        return result
