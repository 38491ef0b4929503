"""Text and operation counts of either engine's expressions, as SymPy's.

One line of text is SymPy's ``sstr(expr, order="none")``; the count SymPy's
``count_ops``, the measure of the report's cap on an inlined gradient jet.
"""

from __future__ import annotations

from typing import Any

from tvopt_codegen import symbolic as sx
from tvopt_codegen.report.nodes import (
    Unprintable,
    distributed,
    exp_argument,
    function_name,
    is_exp,
    is_exp1,
    negative,
    node_name,
    shared_memo,
)

# SymPy's count_ops: the inlining cap's measure of a gradient jet, without SymPy.


def count_ops(expr: Any) -> int:
    """SymPy's ``count_ops(expr)`` of an expression of either engine, without SymPy.

    Each sum or product of n terms counts n - 1 (a subtraction as one), a negation, a
    division, a power and a function call one each (``x/y`` one division, ``-x`` one
    negation, ``x**-2`` a power and a negation); the nodes are SymPy's (a rational times
    a sum distributed). Raises :class:`Unprintable` for what it cannot decide as SymPy
    does (a power to a negative constant that is not a number).
    """
    count = 0
    stack = [sx.as_expr(expr)]
    while stack:
        node = distributed(stack.pop())
        if node.is_Rational:
            if node != 1:
                count += (int(node.p) < 0) + (int(node.q) != 1)
                continue
        elif node.is_Mul:
            if negative(node):
                count += 1
                node = distributed(-node)
            if node.is_Mul or node.is_Pow or is_exp(node):
                numerator, denominator = _evaluated_fraction(node)
                if numerator.is_Integer:
                    count += 1 + bool(numerator < 0)
                    stack.append(denominator)
                    continue
                if denominator != 1:
                    if not denominator.is_Integer:
                        stack.append(denominator)
                    count += 1
                    stack.append(numerator)
                    continue
        elif node.is_Add:
            terms = list(node.args)
            negatives = 0
            for i, term in enumerate(terms):
                if negative(term):
                    negatives += 1
                    stack.append(-term)
                else:
                    stack.append(term)
                count += i > 0  # an addition or a subtraction
            count += negatives == len(terms)  # -x - y: a negation and a subtraction
            continue
        if node.is_Pow and not is_exp(node) and node.args[1] == -1:
            count += 1
            stack.append(node.args[0])
            continue
        if is_exp1(node):
            count += 1
            continue
        if is_exp(node):
            count += 1
            stack.append(exp_argument(node))
            continue
        if node.is_Mul or (node.is_Function and sx.function_name(node) in ("Max", "Min")):
            count += len(node.args) - 1
        elif node.args and (node.is_Pow or node.is_Function) and not sx.is_piecewise(node):
            count += 1
        elif sx.is_piecewise(node):
            count += 1
        if not node.is_Symbol:
            stack.extend(node.args)
    return count


def _evaluated_fraction(expr: Any) -> tuple[Any, Any]:
    """SymPy's ``fraction(expr)`` (not exact): numerator and denominator, evaluated."""
    numerator: list[Any] = []
    denominator: list[Any] = []
    for term in expr.args if expr.is_Mul else [expr]:
        if term.is_Pow or is_exp(term):
            base, exponent = (sx.E, exp_argument(term)) if is_exp(term) else term.args
            if exponent.is_Number:
                if exponent < 0:
                    denominator.append(base ** (-exponent))
                else:
                    numerator.append(term)
            elif not exponent.free_symbols:
                raise Unprintable(term)
            elif exponent.is_Mul:
                # SymPy's as_numer_denom: a negative coefficient puts it below.
                if negative(exponent):
                    denominator.append(base ** (-exponent))
                else:
                    numerator.append(term)
            else:
                numerator.append(term)
        elif term.is_Rational and not term.is_Integer:
            if int(term.p) != 1:
                numerator.append(sx.Integer(int(term.p)))
            denominator.append(sx.Integer(int(term.q)))
        else:
            numerator.append(term)
    return distributed(sx.Mul(*numerator)), distributed(sx.Mul(*denominator))


#: SymPy's (not traditional) precedences of a sum, a product, a power, a function, an atom.
_STR_ADD, _STR_MUL, _STR_POW, _STR_FUNC, _STR_ATOM = 40, 50, 60, 70, 1000


def _str_precedence(expr: Any) -> int:
    """SymPy's ``precedence``: a product or number that is negative binds as a sum."""
    if expr.is_Add:
        return _STR_ADD
    if expr.is_Mul:
        return _STR_ADD if negative(expr) else _STR_MUL
    if is_exp(expr) or expr.is_Function:
        return _STR_FUNC
    if expr.is_Pow:
        return _STR_POW
    if expr.is_Number:
        if expr < 0:
            return _STR_ADD
        return _STR_MUL if expr.is_Rational and not expr.is_Integer else _STR_ATOM
    return _STR_ATOM


class _Text:
    def __init__(self) -> None:
        self.shared = shared_memo()

    def print(self, expr: Any, level: int = 2) -> str:
        """``expr`` as text; ``level`` 1 is the whole expression (a float keeps its zeros)."""
        expr = self.shared.form(expr)
        if expr.is_Symbol:
            return str(expr.name)
        if expr.is_Integer:
            return str(int(expr))
        if expr.is_Rational:
            return f"{int(expr.p)}/{int(expr.q)}"
        if expr.is_Float:
            return self._float(expr, strip=level > 1)
        if expr.is_Add:
            return self._add(expr)
        if expr.is_Mul:
            return self._mul(expr)
        if is_exp(expr):
            return f"exp({self.print(exp_argument(expr))})"
        if expr.is_Pow:
            return self._pow(expr)
        if expr.is_Function and not sx.is_piecewise(expr):
            name = sx.function_name(expr)
            if name not in ("log", "Abs"):
                name = function_name(expr)
            return f"{name}({', '.join(self.print(arg) for arg in expr.args)})"
        name = node_name(expr)
        if name in ("Pi", "Exp1"):
            return "pi" if name == "Pi" else "E"
        raise Unprintable(expr)

    def _float(self, expr: Any, strip: bool) -> str:
        from mpmath.libmp import from_float, prec_to_dps, to_str  # noqa: PLC0415

        if sx.SYMENGINE:
            text = str(to_str(from_float(float(expr)), 15, strip_zeros=strip))
        else:
            text = str(to_str(expr._mpf_, prec_to_dps(expr._prec), strip_zeros=strip))
        if text.startswith("-.0"):
            text = "-0." + text[3:]
        elif text.startswith(".0"):
            text = "0." + text[2:]
        if text in ("+inf", "-inf"):
            raise Unprintable(expr)
        return text

    def _parenthesized(self, expr: Any, level: int) -> str:
        printed = self.print(expr)
        return f"({printed})" if _str_precedence(expr) <= level else printed

    def _add(self, expr: Any) -> str:
        parts: list[str] = []
        for term in self.shared.ordered(expr):
            printed = self.print(term)
            sign = "+"
            if printed.startswith("-") and not term.is_Add:
                sign, printed = "-", printed[1:]
            if _str_precedence(term) < _STR_ADD or term.is_Add:
                printed = f"({printed})"
            parts += [sign, printed]
        first = parts.pop(0)
        return ("" if first == "+" else first) + " ".join(parts)

    def _mul(self, expr: Any) -> str:
        level = _str_precedence(expr)
        sign = ""
        if negative(expr):
            sign = "-"
            expr = self.shared.form(-expr)
        numerator: list[Any] = []
        denominator: list[Any] = []
        for item in self.shared.ordered(expr) if expr.is_Mul else [expr]:
            if item.is_Pow and not is_exp(item) and _negative_exponent(item.args[1]):
                base, exponent = item.args
                denominator.append(base if exponent == -1 else _Unevaluated(base, -exponent))
            elif item.is_Rational:
                if int(item.p) != 1:
                    numerator.append(sx.Integer(int(item.p)))
                if int(item.q) != 1:
                    denominator.append(sx.Integer(int(item.q)))
            else:
                numerator.append(item)
        above = "*".join(self._factor(x, level) for x in numerator or [sx.ONE])
        below = [self._factor(x, level) for x in denominator]
        if not below:
            return sign + above
        if len(below) == 1:
            return f"{sign}{above}/{below[0]}"
        return f"{sign}{above}/({'*'.join(below)})"

    def _factor(self, item: Any, level: int) -> str:
        if isinstance(item, _Unevaluated):
            # A power in a denominator, its exponent's sign turned: a power binds tighter.
            return item.text(self)
        return self._parenthesized(item, level)

    def _pow(self, expr: Any) -> str:
        base, exponent = expr.args
        if exponent.is_Rational and not exponent.is_Integer and int(exponent.q) == 2:
            if int(exponent.p) == 1:
                return f"sqrt({self.print(base)})"
            if int(exponent.p) == -1:
                return f"1/sqrt({self.print(base)})"
        if exponent.is_Integer and int(exponent) == -1:
            return f"1/{self._parenthesized(base, _STR_POW)}"
        return f"{self._parenthesized(base, _STR_POW)}**{self._parenthesized(exponent, _STR_POW)}"


class _Unevaluated:
    """``base**exponent`` as SymPy writes it in a denominator (``Pow(.., evaluate=False)``)."""

    def __init__(self, base: Any, exponent: Any) -> None:
        self.base, self.exponent = base, exponent

    def text(self, printer: _Text) -> str:
        base, exponent = self.base, self.exponent
        if exponent.is_Rational and not exponent.is_Integer and int(exponent.q) == 2:
            if int(exponent.p) == 1:
                return f"sqrt({printer.print(base)})"
        base_text = printer._parenthesized(base, _STR_POW)
        return f"{base_text}**{printer._parenthesized(exponent, _STR_POW)}"


def _negative_exponent(exponent: Any) -> bool:
    """SymPy's ``exp.as_coeff_Mul()[0] < 0``: a negative number, or a negative coefficient."""
    if exponent.is_Number:
        return bool(exponent < 0)
    if exponent.is_Mul:
        return negative(exponent)
    return False


def text(expr: Any) -> str:
    """``expr`` as one line of text, as SymPy's ``sstr(expr, order="none")`` writes it.

    Raises :class:`Unprintable` for a node it does not print.
    """
    return _Text().print(sx.as_expr(expr), level=1)
