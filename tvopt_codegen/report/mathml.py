"""Presentation MathML of either engine's expressions, SymPy's markup as the report customizes it.

SymPy's ``MathMLPresentationPrinter`` for the same nodes and in the same order as the
LaTeX, with the report's two changes: matrices as ``mtable`` of class ``matrix`` without
fences, and a thin space around an invisible times beside a name of several letters or
a function.
"""

from __future__ import annotations

import functools
import re
import unicodedata
from collections.abc import Callable, Sequence
from typing import Any

from tvopt_codegen import symbolic as sx
from tvopt_codegen.report.nodes import (
    GREEKS,
    MUL,
    POW,
    RELATIONS,
    Unprintable,
    exp_argument,
    float_digits,
    fraction,
    function_name,
    is_exp,
    is_relation,
    is_true,
    negative,
    node_name,
    precedence,
    shared_memo,
    split_super_sub,
)

#: SymPy's MathML names of functions named otherwise.
_MATHML_FUNCTIONS = {
    "asin": "arcsin",
    "acos": "arccos",
    "atan": "arctan",
    "atan2": "arctan",
    "asinh": "arcsinh",
    "acosh": "arccosh",
    "atanh": "arctanh",
    "acot": "arccot",
}


_TIMES = "<mo>&InvisibleTimes;</mo>"
_SPACED_TIMES = '<mo lspace="0.1667em" rspace="0.1667em">&InvisibleTimes;</mo>'
_FIRST_TOKEN = re.compile(r"<(mi|mn|mo)(?:\s[^>]*)?>([^<]*)<")


def _greek_unicode() -> dict[str, str]:
    """``sympy.printing.pretty.pretty_symbology.greek_unicode``."""
    table: dict[str, str] = {}
    for letter in GREEKS:
        spelled = "lamda" if letter == "lambda" else letter
        small = unicodedata.lookup(f"GREEK SMALL LETTER {spelled.upper()}")
        capital = unicodedata.lookup(f"GREEK CAPITAL LETTER {spelled.upper()}")
        table[letter], table[letter.capitalize()] = small, capital
        table[spelled], table[spelled.capitalize()] = small, capital
    table["varsigma"] = unicodedata.lookup("GREEK SMALL LETTER FINAL SIGMA")
    return table


_GREEK_UNICODE = _greek_unicode()


def _mi(text: str) -> str:
    return f"<mi>{text}</mi>"


def _mn(text: str) -> str:
    return f"<mn>{text}</mn>"


def _mo(text: str) -> str:
    return f"<mo>{text}</mo>"


def _row(*parts: str) -> str:
    return "<mrow>" + "".join(parts) + "</mrow>"


def _parenthesized(markup: str) -> str:
    return _row(_mo("("), markup, _mo(")"))


def _wide(markup: str) -> bool:
    """Whether a factor starts with a name of several letters (or is a function)."""
    found = _FIRST_TOKEN.match(markup) or _FIRST_TOKEN.search(markup)
    if found is None:
        return False
    tag, text = found.groups()
    return tag == "mi" and len(text) > 1 and not text.startswith("&")


def _product_row(parts: Sequence[str]) -> str:
    """Factors side by side, a thin space around the invisible times beside a wide one."""
    out = []
    for i, part in enumerate(parts):
        if i:
            wide = _wide(parts[i - 1]) or _wide(part)
            out.append(_SPACED_TIMES if wide else _TIMES)
        out.append(part)
    return "".join(out)


@functools.cache
def _mathml_name(text: str) -> str:
    name, supers, subs = split_super_sub(text)

    def join(items: list[str]) -> str:
        items = [_GREEK_UNICODE.get(item, item) for item in items]
        if len(items) == 1:
            return _mi(items[0])
        return _row(*[(_mo(" ") if i else "") + _mi(item) for i, item in enumerate(items)])

    head = _mi(_GREEK_UNICODE.get(name, name))
    if not supers and not subs:
        return head
    if not supers:
        return f"<msub>{head}{join(subs)}</msub>"
    if not subs:
        return f"<msup>{head}{join(supers)}</msup>"
    return f"<msubsup>{head}{join(subs)}{join(supers)}</msubsup>"


class _MathML:
    def __init__(self) -> None:
        self.shared = shared_memo()

    def print(self, expr: Any) -> str:
        found = self.shared.mathml.get(expr)
        if found is None:
            found = self.shared.mathml[expr] = self._print(self.shared.form(expr))
        return found

    def _print(self, expr: Any) -> str:
        if expr.is_Symbol:
            return _mathml_name(str(expr.name))
        if expr.is_Integer:
            return _mn(str(int(expr)))
        if expr.is_Rational:
            p, q = int(expr.p), int(expr.q)
            frac = f"<mfrac>{_mn(str(abs(p)))}{_mn(str(q))}</mfrac>"
            return _row(_mo("-"), frac) if p < 0 else frac
        if expr.is_Float:
            return self._float(expr)
        if expr.is_Add:
            return self._add(expr)
        if expr.is_Mul:
            return self._mul(expr)
        if is_exp(expr):
            return f"<msup>{_mi('&ExponentialE;')}{self.print(exp_argument(expr))}</msup>"
        if expr.is_Pow:
            return self._pow(expr)
        if sx.is_piecewise(expr):
            return self._piecewise(expr)
        if expr.is_Function:
            return self._function(expr)
        if is_relation(expr):
            lhs, rhs = expr.args
            return _row(self.print(lhs), _mo(RELATIONS[node_name(expr)][1]), self.print(rhs))
        return self._atom(expr)

    def _atom(self, expr: Any) -> str:
        name = node_name(expr)
        if name == "Pi":
            return _mi("&pi;")
        if name == "Exp1":
            return _mi("&ExponentialE;")
        if name in ("BooleanTrue", "BooleanFalse"):
            return _mi(name[len("Boolean") :])
        raise Unprintable(expr)

    def _float(self, expr: Any) -> str:
        text = float_digits(expr)
        if "e" in text:
            mantissa, exponent = text.split("e")
            if exponent[0] == "+":
                exponent = exponent[1:]
            power = f"<msup>{_mn('10')}{_mn(exponent)}</msup>"
            return _row(_mn(mantissa), _mo("&#xB7;"), power)
        if text in ("+inf", "-inf"):
            raise Unprintable(expr)
        return _mn(text)

    def _add(self, expr: Any) -> str:
        parts = []
        for i, term in enumerate(self.shared.ordered(expr)):
            if i and negative(term):
                parts += [_mo("-"), self.print(-term)]
            else:
                parts += [_mo("+")] if i else []
                parts.append(self.print(term))
        return _row(*parts)

    def _factor(self, term: Any) -> str:
        printed = self.print(term)
        return _parenthesized(printed) if precedence(term) <= MUL else printed

    def _product(self, factors: Sequence[Any]) -> str:
        """An unevaluated product of ``factors``: one of them, or a row of them."""
        if not factors:
            return _mn("1")
        if len(factors) == 1:
            return self.print(factors[0])
        return _row(self._factors(factors))

    def _factors(self, factors: Sequence[Any]) -> str:
        first, *others = factors
        parts = [self.print(first) if first.is_Number else self._factor(first)]
        parts += [self._factor(term) for term in others]
        return _product_row(parts)

    def _mul(self, expr: Any) -> str:
        sign = ""
        if negative(expr):
            sign = _mo("-")
            expr = self.shared.form(-expr)
        numerator, denominator = fraction(expr, self.shared)
        if denominator:
            return _row(
                sign, f"<mfrac>{self._product(numerator)}{self._product(denominator)}</mfrac>"
            )
        if not expr.is_Mul:
            return _row(sign, self.print(expr))
        return _row(sign, self._factors(self.shared.ordered(expr)))

    def _pow(self, expr: Any) -> str:
        base, exponent = expr.args
        if exponent.is_Rational and abs(int(exponent.p)) == 1 and int(exponent.q) != 1:
            q = int(exponent.q)
            root = (
                f"<msqrt>{self.print(base)}</msqrt>"
                if q == 2
                else f"<mroot>{self.print(base)}{_mn(str(q))}</mroot>"
            )
            return f"<mfrac>{_mn('1')}{root}</mfrac>" if exponent < 0 else root
        lifted = self._factor_pow(base)
        if exponent.is_Number and exponent < 0:
            if exponent == -1:
                return f"<mfrac>{_mn('1')}{self.print(base)}</mfrac>"
            return f"<mfrac>{_mn('1')}<msup>{lifted}{self.print(-exponent)}</msup></mfrac>"
        return f"<msup>{lifted}{self.print(exponent)}</msup>"

    def _factor_pow(self, base: Any) -> str:
        printed = self.print(base)
        return _parenthesized(printed) if precedence(base) <= POW else printed

    def _piecewise(self, expr: Any) -> str:
        rows = []
        for value, condition in sx.piecewise_pairs(expr):
            when = (
                "<mtext>otherwise</mtext>"
                if is_true(condition)
                else "<mtext>for&#160;</mtext>" + self.print(condition)
            )
            rows.append(f"<mtr><mtd>{self.print(value)}</mtd><mtd>{when}</mtd></mtr>")
        return _row(_mo("{"), '<mtable columnalign="left">' + "".join(rows) + "</mtable>")

    def _function(self, expr: Any) -> str:
        name = sx.function_name(expr)
        if name == "Abs":
            return _row(_mo("|"), self.print(expr.args[0]), _mo("|"))
        if name != "log":
            name = function_name(expr)
        name = _MATHML_FUNCTIONS.get(name, name.lower())
        arguments = [self.print(arg) for arg in expr.args]
        inner = _mo(",").join(arguments)
        return _row(_mi(name), _row(_mo("("), inner, _mo(")")))

    def matrix(self, rows: int, cols: int, entry: Callable[[int, int], Any]) -> str:
        body = "".join(
            "<mtr>"
            + "".join(f"<mtd>{self.print(entry(i, j))}</mtd>" for j in range(cols))
            + "</mtr>"
            for i in range(rows)
        )
        return f'<mtable class="matrix">{body}</mtable>'


def mathml(expr: Any) -> str:
    """``expr`` (an expression or a matrix of either engine) in presentation MathML.

    Raises :class:`Unprintable` for a node it does not print.
    """
    printer = _MathML()
    if isinstance(expr, sx.MatrixBase):
        rows, cols = expr.shape
        markup = printer.matrix(rows, cols, lambda i, j: expr[i, j])
    else:
        markup = printer.print(sx.as_expr(expr))
    # Greek letters as character references, as SymPy writes them (&#952;).
    return markup.encode("ascii", "xmlcharrefreplace").decode("ascii")
