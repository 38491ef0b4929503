"""Expression printers: sympy's own, subclassed where generated code needs it."""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import sympy as sp
from sympy.printing.c import C99CodePrinter
from sympy.printing.numpy import NumPyPrinter
from sympy.printing.precedence import PRECEDENCE


class _CanonicalOrder:
    """Canonical order of terms and factors, and one expression printed directly.

    sympy's default ("lex") order sorts the terms of every sum by monomial degrees,
    which computes each term's coefficient (with ``evalf``) and sort key: half of all
    printing time for a large controller. The canonical order is already
    deterministic (sympy sorts arguments when it builds a sum or product), so it is
    used as is, with the constant moved to the end where a reader expects it and a
    positive term first when there is one (``1 - x``, not ``-x + 1``).
    """

    _print: Any  # sympy's Printer._print, from the printer this is mixed into

    def doprint(self, expr: Any, assign_to: Any = None) -> str:
        """Print one expression.

        sympy's ``doprint`` first rebuilds the whole expression to unwrap ``re`` of
        unevaluated expressions (kernels have none) and formats the text as lines of
        code: a quarter of printing time for a large controller. One expression that
        prints as one line, with no number constant to declare, is printed directly;
        anything else goes through ``doprint`` as before.
        """
        if assign_to is None and isinstance(expr, sp.Basic):
            self._not_supported: set[Any] = set()
            self._number_symbols: set[Any] = set()
            text: str = self._print(expr)
            if "\n" not in text and not self._number_symbols and not self._not_supported:
                return text
        printed: str = super().doprint(expr, assign_to)  # type: ignore[misc]
        return printed

    def _as_ordered_terms(self, expr: sp.Expr, order: str | None = None) -> list[sp.Expr]:
        args = list(expr.args)
        terms = [a for a in args if not a.is_Number] + [a for a in args if a.is_Number]
        if _negative(terms[0]):
            first = next((i for i, term in enumerate(terms) if not _negative(term)), 0)
            terms.insert(0, terms.pop(first))
        return terms


def _negative(term: sp.Expr) -> bool:
    """Whether a term prints with a leading minus sign."""
    coefficient = term.args[0] if term.is_Mul else term
    return bool(coefficient.is_Number and coefficient.is_negative)


class PythonPrinter(_CanonicalOrder, NumPyPrinter):  # type: ignore[misc]
    """NumPy printer for kernel bodies, strict about anything it cannot translate.

    Kernel expressions are elementwise over a batch of states, so every function
    maps to its ``numpy`` ufunc. Strict mode makes an untranslatable node an error at
    generation time instead of broken code at run time.
    """

    def __init__(self) -> None:
        super().__init__(
            {
                "strict": True,
                "fully_qualified_modules": True,
                "allow_unknown_functions": False,
                "order": "none",
            }
        )

    def _print_Pow(self, expr: sp.Pow, rational: bool = False) -> str:
        """Customizations.

        * Small integer powers are products (``x*x``), and their reciprocals
          ``1/(x*x)``: exact for squares, as the C backend writes them, and the same
          bits whether ``x`` is a NumPy array or a Python float (``float.__pow__``
          calls libm's ``pow``, NumPy its own, and they differ in the last bit).
        * Every other power is ``numpy.power(x, e)``, one routine for arrays and
          scalars alike; square roots stay ``numpy.sqrt``.
        * ``x**-1`` is ``1/x``: NumPyPrinter writes ``x**(-1.0)``.
        """
        exp = expr.exp
        if exp.is_Integer and 1 <= abs(int(exp)) <= 4:
            base = self.parenthesize(expr.base, PRECEDENCE["Mul"])
            product = "*".join([base] * abs(int(exp)))
            if exp > 0:
                return f"({product})" if abs(int(exp)) > 1 else product
            one = self._print(sp.S.One)
            return f"{one}/{base}" if exp == -1 else f"{one}/({product})"
        if exp == sp.S.Half:
            return self._call(f"numpy.sqrt({self._print(expr.base)})")
        if exp == -sp.S.Half:
            one = self._print(sp.S.One)
            return f"{one}/{self._call(f'numpy.sqrt({self._print(expr.base)})')}"
        return self._call(f"numpy.power({self._print(expr.base)}, {self._print(exp)})")

    def _call(self, text: str) -> str:
        """A call of a NumPy function, as printed (the scalar printer converts it)."""
        return text


class PythonScalarPrinter(PythonPrinter):
    """The NumPy printer for one point: every NumPy function's result becomes a ``float``.

    The one-point kernels run on Python floats. A NumPy function returns a NumPy
    scalar, on which every later operation costs about three times a float's; the
    value is the same, so it is converted at once. The function stays NumPy's: its
    bits then equal those of the batch path (libm's ``math`` functions differ from
    NumPy's vectorized ones in the last bit).
    """

    def _print(self, expr: Any, **kwargs: Any) -> str:
        """Customizations.

        * A function printed as a NumPy call is wrapped in ``float(...)`` and calls the
          module's alias ``_np_<name>`` of ``numpy.<name>`` (one global lookup instead of
          a global and an attribute: the template defines the aliases the code uses).
        """
        text: str = super()._print(expr, **kwargs)
        if isinstance(expr, sp.Function) and text.startswith("numpy."):
            return f"float(_np_{text.removeprefix('numpy.')})"
        return text

    def _call(self, text: str) -> str:
        """Customizations.

        * ``numpy.power`` and ``numpy.sqrt`` from powers are wrapped in ``float(...)``,
          through their aliases.
        """
        return f"float(_np_{text.removeprefix('numpy.')})"

    def _print_Integer(self, expr: sp.Integer) -> str:
        """Customizations.

        * Integers print as floats (``2.0``): CPython's fast path multiplies two floats,
          not an int and a float; the value is the same (an int converts exactly).
        """
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

    def _print(self, expr: Any, **kwargs: Any) -> str:
        """Customizations.

        * A function printed as a NumPy call is marked, as the scalar printer wraps it.
        """
        text: str = super()._print(expr, **kwargs)
        if isinstance(expr, sp.Function) and text.startswith("numpy."):
            return self._call(text)
        return text

    def _call(self, text: str) -> str:
        """Customizations.

        * ``numpy.power`` and ``numpy.sqrt`` from powers are marked, as the scalar printer
          wraps them.
        """
        return f"{_CALL}{text.removeprefix('numpy.')}{_END}"

    def _print_Integer(self, expr: sp.Integer) -> str:
        """Customizations.

        * An integer's end is marked, where the scalar printer adds ``.0``.
        """
        return f"{int(expr)}{_INTEGER}"

    @staticmethod
    def texts() -> dict[str, Callable[[str], str]]:
        """Functions from the marked text to each printing's: ``""`` batch, ``"1"`` one point."""
        return {"": _batch_text, "1": _scalar_text}


class CPrinter(_CanonicalOrder, C99CodePrinter):  # type: ignore[misc]
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
