"""SymPy expressions as spec text the project's reader reads back as the same expression.

Floats are written as the shortest decimal of their double, numbers beyond the
reader's literals as exact products it folds, and long sums and products in
parenthesized groups, so that no flat chain of terms reaches the reader's nesting limit.
"""

from __future__ import annotations

import decimal
from collections.abc import Sequence

import sympy as sp
from sympy.printing.str import StrPrinter

from tvopt_codegen.mechanics.language import _fail
from tvopt_codegen.spec.parse import MAX_DEPTH, MAX_EXPONENT, MAX_LITERAL, MIN_LITERAL

#: Sums and products with more terms than this are printed in parenthesized groups:
#: the reader nests a chain of n terms n deep, and refuses more than MAX_DEPTH.
_CHAIN = 24
_GROUPS = 8


class _Printer(StrPrinter):  # type: ignore[misc]
    """sympy's text form, as the spec reader reads it back.

    Floats are written as the shortest decimal of their double (what the reader makes
    of them), ``E`` as ``exp(1)``, and long sums and products in parenthesized groups
    so that the reader's nesting limit is not reached by a flat chain of terms.
    """

    def _print_Float(self, expr: sp.Float) -> str:
        value = float(expr)
        if value == 0 or MIN_LITERAL <= abs(value) <= MAX_LITERAL:
            return repr(value)
        # Beyond the reader's literals: the same decimal as an exact product it folds.
        sign, digits, exponent = decimal.Decimal(repr(value)).as_tuple()
        assert isinstance(exponent, int)
        mantissa = int("".join(map(str, digits))) * (-1 if sign else 1)
        return f"({_exact(mantissa)}*{_power_of_ten(exponent)})"

    def _print_Integer(self, expr: sp.Integer) -> str:
        return _exact(int(expr))

    def _print_Rational(self, expr: sp.Rational) -> str:
        return f"{_exact(int(expr.p))}/{_exact(int(expr.q))}"

    def _print_Exp1(self, expr: sp.Expr) -> str:
        return "exp(1)"

    def _print_Add(self, expr: sp.Add, order: str | None = None) -> str:
        terms = list(expr.args)
        if len(terms) <= _CHAIN:
            return str(super()._print_Add(expr, order=order))
        terms = self._as_ordered_terms(expr, order=order)
        return " + ".join(f"({self._print(sp.Add(*g, evaluate=False))})" for g in _groups(terms))

    def _print_Mul(self, expr: sp.Mul) -> str:
        factors = list(expr.args)
        if len(factors) <= _CHAIN:
            return str(super()._print_Mul(expr))
        return "*".join(f"({self._print(sp.Mul(*g, evaluate=False))})" for g in _groups(factors))


def _exact(number: int) -> str:
    """An integer as text the reader folds back exactly (its literals stop at 1e12)."""
    if abs(number) <= MAX_LITERAL:
        return str(number)
    chunk = 10**12
    rest, terms, power = abs(number), [], 0
    while rest:
        rest, digits = divmod(rest, chunk)
        if digits:
            terms.append(str(digits) if power == 0 else f"{digits}*{chunk}**{power}")
        power += 1
    return f"({'-' if number < 0 else ''}({' + '.join(reversed(terms))}))"


def _power_of_ten(exponent: int) -> str:
    """``10**exponent`` in factors whose exponents the reader takes (at most 64)."""
    step = MAX_EXPONENT if exponent > 0 else -MAX_EXPONENT
    factors = []
    while abs(exponent) > MAX_EXPONENT:
        factors.append(f"10**{step}" if step > 0 else f"10**({step})")
        exponent -= step
    factors.append(f"10**{exponent}" if exponent >= 0 else f"10**({exponent})")
    return "*".join(factors)


def _groups(items: Sequence[sp.Expr]) -> list[list[sp.Expr]]:
    """``items`` in at most :data:`_GROUPS` consecutive groups of near-equal size."""
    size = -(-len(items) // _GROUPS)
    return [list(items[i : i + size]) for i in range(0, len(items), size)]


# Terms in sympy's own order: the printer's default order evaluates constant terms
# with mpmath to sort them, which takes hours for sin(exp(exp(40))).
_PRINTER = _Printer({"full_prec": True, "order": "none"})


def _text(expr: sp.Expr, field: str, *, string: bool = False) -> str | int | float:
    """An expression as spec text; an integer or a float stays a number unless ``string``."""
    # A number the reader's literals take stays a number; others are folded text.
    if not string and isinstance(expr, sp.Integer) and abs(int(expr)) <= MAX_LITERAL:
        return int(expr)
    if (
        not string
        and isinstance(expr, sp.Float)
        and (expr == 0 or MIN_LITERAL <= abs(float(expr)) <= MAX_LITERAL)
    ):
        return float(expr)
    try:
        return str(_PRINTER.doprint(expr))
    except RecursionError:
        raise _fail(field, f"the expression nests deeper than {MAX_DEPTH} operations") from None
