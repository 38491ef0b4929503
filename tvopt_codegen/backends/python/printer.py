"""The Python backend's printers: NumPy for a batch, floats for one point, both at once."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import sympy as sp
from sympy.printing.numpy import NumPyPrinter
from sympy.printing.precedence import PRECEDENCE

from tvopt_codegen.lowering.printers import CanonicalOrder


class PythonPrinter(CanonicalOrder, NumPyPrinter):  # type: ignore[misc]
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
