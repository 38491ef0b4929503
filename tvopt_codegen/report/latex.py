r"""LaTeX of either engine's expressions, as SymPy writes it.

SymPy's ``latex(expr, order="none", mul_symbol=r"\,")`` character for character: a sum's
terms and a product's factors in SymPy's order of its arguments.
"""

from __future__ import annotations

import functools
import re
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

_SEPARATOR = r"\,"
_NUMBER_SEPARATOR = r" \cdot "
#: Between two numbers a product shows a dot (SymPy's ``_between_two_numbers_p``).
_ENDS_IN_NUMBER = re.compile(r"[0-9][} ]*$")
_STARTS_WITH_NUMBER = re.compile(r"(\d|\\frac{\d+}{\d+})")

_TEX_GREEK = {
    "Alpha": r"\mathrm{A}",
    "Beta": r"\mathrm{B}",
    "Gamma": r"\Gamma",
    "Delta": r"\Delta",
    "Epsilon": r"\mathrm{E}",
    "Zeta": r"\mathrm{Z}",
    "Eta": r"\mathrm{H}",
    "Theta": r"\Theta",
    "Iota": r"\mathrm{I}",
    "Kappa": r"\mathrm{K}",
    "Lambda": r"\Lambda",
    "Mu": r"\mathrm{M}",
    "Nu": r"\mathrm{N}",
    "Xi": r"\Xi",
    "omicron": "o",
    "Omicron": r"\mathrm{O}",
    "Pi": r"\Pi",
    "Rho": r"\mathrm{P}",
    "Sigma": r"\Sigma",
    "Tau": r"\mathrm{T}",
    "Upsilon": r"\Upsilon",
    "Phi": r"\Phi",
    "Chi": r"\mathrm{X}",
    "Psi": r"\Psi",
    "Omega": r"\Omega",
    "lamda": r"\lambda",
    "Lamda": r"\Lambda",
    "khi": r"\chi",
    "Khi": r"\mathrm{X}",
    "varepsilon": r"\varepsilon",
    "varkappa": r"\varkappa",
    "varphi": r"\varphi",
    "varpi": r"\varpi",
    "varrho": r"\varrho",
    "varsigma": r"\varsigma",
    "vartheta": r"\vartheta",
}
_OTHER_SYMBOLS = frozenset("aleph beth daleth gimel ell eth hbar hslash mho wp".split())


def _wrap(left: str, right: str) -> Callable[[str], str]:
    return lambda s: left + s + right


#: Name modifiers (``xdot`` is x with a dot), longest first as SymPy tries them.
_MODIFIERS: list[tuple[str, Callable[[str], str]]] = sorted(
    {
        "mathring": _wrap(r"\mathring{", "}"),
        "ddddot": _wrap(r"\ddddot{", "}"),
        "dddot": _wrap(r"\dddot{", "}"),
        "ddot": _wrap(r"\ddot{", "}"),
        "dot": _wrap(r"\dot{", "}"),
        "check": _wrap(r"\check{", "}"),
        "breve": _wrap(r"\breve{", "}"),
        "acute": _wrap(r"\acute{", "}"),
        "grave": _wrap(r"\grave{", "}"),
        "tilde": _wrap(r"\tilde{", "}"),
        "hat": _wrap(r"\hat{", "}"),
        "bar": _wrap(r"\bar{", "}"),
        "vec": _wrap(r"\vec{", "}"),
        "prime": _wrap("{", "}'"),
        "prm": _wrap("{", "}'"),
        "bold": _wrap(r"\boldsymbol{", "}"),
        "bm": _wrap(r"\boldsymbol{", "}"),
        "cal": _wrap(r"\mathcal{", "}"),
        "scr": _wrap(r"\mathscr{", "}"),
        "frak": _wrap(r"\mathfrak{", "}"),
        "norm": _wrap(r"\left\|{", r"}\right\|"),
        "avg": _wrap(r"\left\langle{", r"}\right\rangle"),
        "abs": _wrap(r"\left|{", r"}\right|"),
        "mag": _wrap(r"\left|{", r"}\right|"),
    }.items(),
    key=lambda item: len(item[0]),
    reverse=True,
)
_ACCEPTED_FUNCTIONS = frozenset(
    "arcsin arccos arctan sin cos tan sinh cosh tanh sqrt ln log sec csc cot coth re im "
    "frac root arg".split()
)


def _translate(text: str) -> str:
    """SymPy's ``translate``: Greek letters, other symbols and modifiers in LaTeX."""
    tex = _TEX_GREEK.get(text)
    if tex:
        return tex
    if text.lower() in GREEKS:
        return "\\" + text.lower()
    if text in _OTHER_SYMBOLS:
        return "\\" + text
    for key, modify in _MODIFIERS:
        if text.lower().endswith(key) and len(text) > len(key):
            return modify(_translate(text[: -len(key)]))
    return text


@functools.cache
def _tex_name(text: str) -> str:
    """SymPy's ``_deal_with_super_sub``: a name with its super- and subscripts."""
    if "{" in text:
        return text
    name, supers, subs = split_super_sub(text)
    name = _translate(name)
    if supers:
        name += "^{{{}}}".format(" ".join(_translate(s) for s in supers))
    if subs:
        name += "_{{{}}}".format(" ".join(_translate(s) for s in subs))
    return name


class _Latex:
    def __init__(self) -> None:
        self.shared = shared_memo()

    def print(self, expr: Any, exp: str | None = None) -> str:
        if exp is not None:
            return self._function(expr, exp)
        found = self.shared.latex.get(expr)
        if found is None:
            found = self.shared.latex[expr] = self._print(self.shared.form(expr))
        return found

    def _print(self, expr: Any) -> str:
        if expr.is_Symbol:
            return _tex_name(str(expr.name))
        if expr.is_Integer:
            return str(int(expr))
        if expr.is_Rational:
            p, q = int(expr.p), int(expr.q)
            return ("- " if p < 0 else "") + rf"\frac{{{abs(p)}}}{{{q}}}"
        if expr.is_Float:
            return self._float(expr)
        if expr.is_Add:
            return self._add(expr)
        if expr.is_Mul:
            return self._mul(expr)
        if is_exp(expr):
            return f"e^{{{self.print(exp_argument(expr))}}}"
        if expr.is_Pow:
            return self._pow(expr)
        if sx.is_piecewise(expr):
            return self._piecewise(expr)
        if expr.is_Function:
            return self._function(expr, None)
        if is_relation(expr):
            lhs, rhs = expr.args
            return f"{self.print(lhs)} {RELATIONS[node_name(expr)][0]} {self.print(rhs)}"
        return self._atom(expr)

    def _atom(self, expr: Any) -> str:
        name = node_name(expr)
        if name == "Pi":
            return r"\pi"
        if name == "Exp1":
            return "e"
        if name == "BooleanTrue":
            return r"\text{True}"
        if name == "BooleanFalse":
            return r"\text{False}"
        raise Unprintable(expr)

    def _float(self, expr: Any) -> str:
        text = float_digits(expr)
        if "e" in text:
            mantissa, exponent = text.split("e")
            if exponent[0] == "+":
                exponent = exponent[1:]
            return f"{mantissa}{_NUMBER_SEPARATOR}10^{{{exponent}}}"
        if text in ("+inf", "-inf"):
            raise Unprintable(expr)
        return text

    def _add(self, expr: Any) -> str:
        tex = ""
        for i, arg in enumerate(self.shared.ordered(expr)):
            term = arg
            if i == 0:
                pass
            elif negative(term):
                tex += " - "
                term = -term
            else:
                tex += " + "
            printed = self.print(term)
            if term.is_Add or is_relation(term):
                printed = rf"\left({printed}\right)"
            tex += printed
        return tex

    def _needs_mul_brackets(self, term: Any, first: bool) -> bool:
        if term.is_Mul:
            if not first and negative(term):
                return True
        elif precedence(term) < MUL or is_relation(term):
            return True
        return bool(sx.is_piecewise(term))

    def _factors(self, factors: Sequence[Any]) -> str:
        """SymPy's ``convert_args``: factors side by side, numbers apart by a dot."""
        tex = last = ""
        for i, term in enumerate(factors):
            printed = self.print(term)
            if self._needs_mul_brackets(term, first=i == 0):
                printed = rf"\left({printed}\right)"
            if _ENDS_IN_NUMBER.search(last) and _STARTS_WITH_NUMBER.match(printed):
                tex += _NUMBER_SEPARATOR
            elif tex:
                tex += _SEPARATOR
            tex += printed
            last = printed
        return tex

    def _convert(self, factors: Sequence[Any]) -> str:
        """SymPy's ``convert`` of an unevaluated product of ``factors``."""
        if not factors:
            return "1"
        if len(factors) == 1:
            only = factors[0]
            return self._factors(self.shared.ordered(only)) if only.is_Mul else self.print(only)
        return self._factors(factors)

    def _mul(self, expr: Any) -> str:
        tex = ""
        parens = False
        if negative(expr):
            expr = self.shared.form(-expr)
            tex = "- "
            if expr.is_Add:
                tex += "("
                parens = True
        numerator, denominator = fraction(expr, self.shared)
        if not denominator:
            tex += self._convert([expr])
        else:
            tex += rf"\frac{{{self._convert(numerator)}}}{{{self._convert(denominator)}}}"
        return tex + (")" if parens else "")

    def _pow(self, expr: Any) -> str:
        base, exponent = expr.args
        if exponent.is_Rational:
            p, q = int(exponent.p), int(exponent.q)
            if abs(p) == 1 and q != 1:
                inner = self.print(base)
                tex = rf"\sqrt{{{inner}}}" if q == 2 else rf"\sqrt[{q}]{{{inner}}}"
                return rf"\frac{{1}}{{{tex}}}" if p < 0 else tex
            if p < 0:
                if base == 1 or base.is_Rational:
                    raise Unprintable(expr)
                denominator = base if exponent == -1 else base ** (-exponent)
                return rf"\frac{{1}}{{{self._convert([denominator])}}}"
        if is_exp(base):
            raise Unprintable(expr)  # SymPy brackets e^x before raising it
        if base.is_Function:
            return self.print(base, exp=self.print(exponent))
        printed = self.print(base)
        if precedence(base) <= POW:
            printed = rf"\left({printed}\right)"
        if base.is_Symbol:
            if "^" in printed:
                printed = rf"\left({printed}\right)"
        elif base.is_Float:
            printed = f"{{{printed}}}"
        return f"{printed}^{{{self.print(exponent)}}}"

    def _piecewise(self, expr: Any) -> str:
        pairs = sx.piecewise_pairs(expr)
        rows = [
            rf"{self.print(value)} & \text{{for}}\: {self.print(condition)}"
            for value, condition in pairs[:-1]
        ]
        value, condition = pairs[-1]
        if is_true(condition):
            rows.append(rf"{self.print(value)} & \text{{otherwise}}")
        else:
            rows.append(rf"{self.print(value)} & \text{{for}}\: {self.print(condition)}")
        return r"\begin{{cases}} {} \end{{cases}}".format(r" \\".join(rows))

    def _function(self, expr: Any, exp: str | None) -> str:
        if sx.is_piecewise(expr) or is_exp(expr):
            raise Unprintable(expr)  # SymPy's own forms with an exponent
        name = sx.function_name(expr)
        if name == "log":
            tex = rf"\log{{\left({self.print(expr.args[0])} \right)}}"
            return tex if exp is None else f"{tex}^{{{exp}}}"
        if name == "Abs":
            tex = rf"\left|{{{self.print(expr.args[0])}}}\right|"
            return tex if exp is None else f"{tex}^{{{exp}}}"
        name = function_name(expr)
        args = ",".join(self.print(arg) for arg in expr.args)
        head = self._function_head(name)
        if exp is not None:
            if "^" in head:
                head = rf"\left({head}\right)"
            head = f"{head}^{{{exp}}}"
        return head + rf"{{\left({args} \right)}}"

    @staticmethod
    def _function_head(name: str) -> str:
        """SymPy's ``_hprint_Function``."""
        func = _tex_name(name)
        superscript, subscript = func.find("^"), func.find("_")
        if func in _ACCEPTED_FUNCTIONS:
            return "\\" + func
        if len(func) == 1 or func.startswith("\\") or subscript == 1 or superscript == 1:
            return func
        cut = [i for i in (superscript, subscript) if i > 0]
        if cut:
            return rf"\operatorname{{{func[: min(cut)]}}}{func[min(cut) :]}"
        return rf"\operatorname{{{func}}}"

    def matrix(self, rows: int, cols: int, entry: Callable[[int, int], Any]) -> str:
        lines = [" & ".join(self.print(entry(i, j)) for j in range(cols)) for i in range(rows)]
        body = r"\\".join(lines)
        if cols <= 10:
            return rf"\left[\begin{{matrix}}{body}\end{{matrix}}\right]"
        return r"\left[\begin{{array}}{{{}}}{}\end{{array}}\right]".format("c" * cols, body)


def latex(expr: Any) -> str:
    """``expr`` (an expression or a matrix of either engine) in LaTeX, as SymPy prints it.

    Raises :class:`Unprintable` for a node it does not print.
    """
    printer = _Latex()
    if isinstance(expr, sx.MatrixBase):
        rows, cols = expr.shape
        return printer.matrix(rows, cols, lambda i, j: expr[i, j])
    return printer.print(sx.as_expr(expr))
