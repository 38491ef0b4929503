r"""The report's LaTeX and MathML, printed from either engine's expressions without SymPy.

Converting what the report shows to SymPy and printing it there took most of a report's
time (``ur5_tip``: 341 definitions and six matrices, 3.6 s, SymPy's import alone 0.5-1.3
s). These printers walk the expressions through the :mod:`~tvopt_codegen.symbolic` API
for the nodes a derivation holds (sums, products, powers, symbols, numbers, the
elementary functions, ``Piecewise`` and relations) and raise :class:`Unprintable` on any
other, which :mod:`~tvopt_codegen.report.entries` then hands to SymPy's printers.

The LaTeX is SymPy's ``latex(expr, order="none", mul_symbol=r"\,")`` character for
character (the tests hold it on real derivations): a sum's terms and a product's factors
in SymPy's order of its arguments (:func:`~tvopt_codegen.symbolic.order.sympy_ordered`,
the same from either engine) rather than SymPy's default printing order, whose sorting
was a third of its printing time. The MathML is SymPy's presentation markup for the same
nodes, in the same order, with the report's two changes (matrices as ``mtable`` of class
``matrix`` without fences; a thin space around an invisible times beside a name of
several letters or a function).
"""

from __future__ import annotations

import functools
import re
import unicodedata
from collections.abc import Callable, Sequence
from typing import Any

from tvopt_codegen import symbolic as sx
from tvopt_codegen.symbolic.order import canonical_key

__all__ = ["Unprintable", "count_ops", "latex", "mathml", "text"]


class Unprintable(Exception):  # noqa: N818 - a signal to fall back, not an error
    """A node the report's printers do not print (SymPy's printers do)."""


# ---------------------------------------------------------------------------------------
# What both printers share: a node's kind, its sign, its numerator and denominator.

#: SymPy's traditional precedences (``sympy.printing.precedence``) of the nodes printed.
_ADD, _MUL, _POW, _FUNC, _ATOM, _RELATION = 40, 50, 60, 70, 1000, 35

#: Relations by class name: LaTeX and MathML operators.
_RELATIONS = {
    "StrictLessThan": ("<", "&lt;"),
    "LessThan": (r"\leq", "&#x2264;"),
    "StrictGreaterThan": (">", "&gt;"),
    "GreaterThan": (r"\geq", "&#x2265;"),
    "Equality": ("=", "="),
    "Unequality": (r"\neq", "&#x2260;"),
}

#: Functions printed as ``name(args)`` by both of SymPy's printers (no printer of their own).
_PLAIN_FUNCTIONS = frozenset(
    "sin cos tan cot sec csc asin acos atan atan2 sinh cosh tanh coth sech csch "
    "asinh acosh atanh sign".split()
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


class _Shared:
    """What both printers and every formula of a report share, node by node.

    A report prints each expression twice (LaTeX and MathML) and many subexpressions
    more often (a robot's matrices repeat its sines and cosines): the order of a node's
    arguments, its SymPy form and what each printer made of it are kept, for the
    process's engine (:func:`_shared` starts afresh when it changes).
    """

    def __init__(self, engine: str) -> None:
        self.engine = engine
        self.keys: dict[Any, tuple[Any, ...]] = {}
        self.orders: dict[Any, list[Any]] = {}
        self.forms: dict[Any, Any] = {}
        self.latex: dict[Any, str] = {}
        self.mathml: dict[Any, str] = {}

    def ordered(self, expr: Any) -> list[Any]:
        found = self.orders.get(expr)
        if found is None:
            args = expr.args
            found = self.orders[expr] = sorted(args, key=self.key) if sx.SYMENGINE else list(args)
        return found

    def key(self, expr: Any) -> tuple[Any, ...]:
        """SymPy's place of ``expr`` among a sum's or a product's arguments.

        :func:`~tvopt_codegen.symbolic.order.canonical_key`, but for two nodes SymPy
        names otherwise: SymEngine's power of E is SymPy's function ``exp`` (after a
        sum, not before it as a power), and an applied function of the user's is of
        the class of its name.
        """
        found = self.keys.get(expr)
        if found is None:
            if _is_exp(expr):
                found = (_function_rank(), "exp", 1, self.key(_exp_argument(expr)))
            elif _name(expr) == "FunctionSymbol":
                parts = tuple(self.key(arg) for arg in expr.args)
                found = (_function_rank(), sx.function_name(expr), len(parts), *parts)
            else:
                found = canonical_key(expr, self.key)
            self.keys[expr] = found
        return found

    def form(self, expr: Any) -> Any:
        """:func:`_distributed`, memoised."""
        found = self.forms.get(expr)
        if found is None:
            found = self.forms[expr] = _distributed(expr)
        return found

    def size(self) -> int:
        return len(self.keys) + len(self.orders) + len(self.latex) + len(self.mathml)


@functools.cache
def _function_rank() -> int:
    """canonical_key's rank of a function: after every class SymPy ranks."""
    rank: int = canonical_key(sx.sin(sx.Symbol("x")), lambda arg: ())[0]
    return rank


#: Nodes remembered at most (a few hundred MB at worst), then forgotten all at once.
_MEMO_LIMIT = 500_000
_SHARED: list[_Shared] = []


def _shared() -> _Shared:
    """The memo of the process's engine."""
    if not _SHARED or _SHARED[0].engine != sx.ENGINE or _SHARED[0].size() > _MEMO_LIMIT:
        _SHARED[:] = [_Shared(sx.ENGINE)]
    return _SHARED[0]


def _name(expr: Any) -> str:
    return type(expr).__name__


def _is_exp1(expr: Any) -> bool:
    return _name(expr) == "Exp1"


def _is_exp(expr: Any) -> bool:
    """``exp(x)``: SymPy's function, SymEngine's power of E."""
    return (expr.is_Pow and _is_exp1(expr.args[0])) or (
        not sx.SYMENGINE and expr.is_Function and _name(expr) == "exp"
    )


def _exp_argument(expr: Any) -> Any:
    return expr.args[-1]


def _is_true(expr: Any) -> bool:
    return _name(expr) == "BooleanTrue"


def _is_relation(expr: Any) -> bool:
    return _name(expr) in _RELATIONS


def _negative(expr: Any) -> bool:
    """SymPy's ``could_extract_minus_sign`` for a term of a sum (never a sum itself)."""
    if expr.is_Number:
        return bool(expr < 0)
    if expr.is_Mul:
        first = _first_factor(expr)
        return bool(first.is_Number and first < 0)
    return False


def _first_factor(expr: Any) -> Any:
    # Numbers sort first among a product's factors, and there is at most one.
    for arg in expr.args:
        if arg.is_Number:
            return arg
    return expr.args[0]


def _precedence(expr: Any) -> int:
    """SymPy's ``precedence_traditional``."""
    if expr.is_Add:
        return _ADD
    if expr.is_Mul:
        return _MUL
    if expr.is_Pow and not _is_exp(expr):
        return _POW
    if expr.is_Number:
        if expr < 0:
            return _ADD
        return _MUL if expr.is_Rational and not expr.is_Integer else _ATOM
    if _is_relation(expr):
        return _RELATION
    if expr.is_Function or _is_exp(expr):
        return _FUNC
    return _ATOM


def _distributed(expr: Any) -> Any:
    """A sum or product as SymPy holds it: a rational times a sum distributed over it.

    SymEngine keeps ``2*(x + y)``, SymPy makes it ``2*x + 2*y`` (and, as a term of a
    sum, merges those terms into the sum's); a product of more factors both keep.
    """
    if not sx.SYMENGINE:
        return expr
    if expr.is_Mul and len(expr.args) == 2:
        terms = _spread(expr)
        return sx.Add(*terms) if terms is not None else expr
    if expr.is_Add:
        spread = [_spread(term) for term in expr.args]
        if any(terms is not None for terms in spread):
            flat = [
                t
                for term, terms in zip(expr.args, spread, strict=True)
                for t in (terms if terms is not None else [term])
            ]
            return sx.Add(*flat)
    return expr


def _spread(expr: Any) -> list[Any] | None:
    """The terms of a product of a rational and a sum, distributed (else None)."""
    if not (expr.is_Mul and len(expr.args) == 2):
        return None
    a, b = expr.args
    if b.is_Rational:
        a, b = b, a
    if a.is_Rational and b.is_Add:
        return [a * term for term in b.args]
    return None


def _fraction(expr: Any, shared: _Shared) -> tuple[list[Any], list[Any]]:
    """SymPy's ``fraction(expr, exact=True)`` as lists of factors, in order."""
    numerator: list[Any] = []
    denominator: list[Any] = []
    factors = shared.ordered(expr) if expr.is_Mul else [expr]
    for term in factors:
        if term.is_Pow or _is_exp(term):
            base, exponent = (sx.E, _exp_argument(term)) if _is_exp(term) else term.args
            if exponent.is_Number:
                if exponent < 0:
                    denominator.append(base if exponent == -1 else base ** (-exponent))
                else:
                    numerator.append(term)
            elif not exponent.free_symbols:
                raise Unprintable(term)  # a constant's sign: SymPy decides it
            else:
                numerator.append(term)
        elif term.is_Rational and not term.is_Integer:
            p, q = int(term.p), int(term.q)
            if p != 1:
                numerator.append(sx.Integer(p))
            denominator.append(sx.Integer(q))
        else:
            numerator.append(term)
    return numerator, denominator


def _function_name(expr: Any) -> str:
    """An applied function's name, or Unprintable for a function with its own printer."""
    name = sx.function_name(expr)
    if name in _PLAIN_FUNCTIONS:
        return name
    if sx.SYMENGINE and _name(expr) == "FunctionSymbol":
        return name
    if not sx.SYMENGINE and _is_undefined(expr):
        return name
    raise Unprintable(expr)


def _is_undefined(expr: Any) -> bool:
    from sympy.core.function import AppliedUndef  # noqa: PLC0415 - SymPy's engine only

    return isinstance(expr, AppliedUndef)


#: ``sympy.printing.conventions``: a name ending in digits has them as a subscript.
_NAME_WITH_DIGITS = re.compile(r"^([^\W\d_]+)(\d+)$", re.UNICODE)


def _split_super_sub(text: str) -> tuple[str, list[str], list[str]]:
    """SymPy's ``split_super_sub``: ``x_1^2`` is ``("x", ["2"], ["1"])``."""
    if not text:
        return text, [], []
    pos = 0
    name: str | None = None
    supers: list[str] = []
    subs: list[str] = []
    while pos < len(text):
        start = pos + 1
        if text[pos : pos + 2] == "__":
            start += 1
        pos_hat = text.find("^", start)
        if pos_hat < 0:
            pos_hat = len(text)
        pos_usc = text.find("_", start)
        if pos_usc < 0:
            pos_usc = len(text)
        pos_next = min(pos_hat, pos_usc)
        part = text[pos:pos_next]
        pos = pos_next
        if name is None:
            name = part
        elif part.startswith("^"):
            supers.append(part[1:])
        elif part.startswith("__"):
            supers.append(part[2:])
        else:
            subs.append(part[1:])
    assert name is not None
    match = _NAME_WITH_DIGITS.match(name)
    if match:
        name, sub = match.groups()
        subs.insert(0, sub)
    return name, supers, subs


# ---------------------------------------------------------------------------------------
# LaTeX: sympy.printing.latex.LatexPrinter with order="none" and mul_symbol=r"\,".

_SEPARATOR = r"\,"
_NUMBER_SEPARATOR = r" \cdot "
#: Between two numbers a product shows a dot (SymPy's ``_between_two_numbers_p``).
_ENDS_IN_NUMBER = re.compile(r"[0-9][} ]*$")
_STARTS_WITH_NUMBER = re.compile(r"(\d|\\frac{\d+}{\d+})")

_GREEKS = (
    "alpha beta gamma delta epsilon zeta eta theta iota kappa lambda mu nu xi omicron pi "
    "rho sigma tau upsilon phi chi psi omega"
).split()
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
    if text.lower() in _GREEKS:
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
    name, supers, subs = _split_super_sub(text)
    name = _translate(name)
    if supers:
        name += "^{{{}}}".format(" ".join(_translate(s) for s in supers))
    if subs:
        name += "_{{{}}}".format(" ".join(_translate(s) for s in subs))
    return name


def _float_digits(expr: Any) -> str:
    """A float as SymPy writes it: 15 significant digits (a SymPy float: its own)."""
    from mpmath.libmp import from_float, prec_to_dps, to_str  # noqa: PLC0415

    if sx.SYMENGINE:
        return str(to_str(from_float(float(expr)), 15, strip_zeros=True))
    return str(to_str(expr._mpf_, prec_to_dps(expr._prec), strip_zeros=True))


class _Latex:
    def __init__(self) -> None:
        self.shared = _shared()

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
        if _is_exp(expr):
            return f"e^{{{self.print(_exp_argument(expr))}}}"
        if expr.is_Pow:
            return self._pow(expr)
        if sx.is_piecewise(expr):
            return self._piecewise(expr)
        if expr.is_Function:
            return self._function(expr, None)
        if _is_relation(expr):
            lhs, rhs = expr.args
            return f"{self.print(lhs)} {_RELATIONS[_name(expr)][0]} {self.print(rhs)}"
        return self._atom(expr)

    def _atom(self, expr: Any) -> str:
        name = _name(expr)
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
        text = _float_digits(expr)
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
            elif _negative(term):
                tex += " - "
                term = -term
            else:
                tex += " + "
            printed = self.print(term)
            if term.is_Add or _is_relation(term):
                printed = rf"\left({printed}\right)"
            tex += printed
        return tex

    def _needs_mul_brackets(self, term: Any, first: bool) -> bool:
        if term.is_Mul:
            if not first and _negative(term):
                return True
        elif _precedence(term) < _MUL or _is_relation(term):
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
        if _negative(expr):
            expr = self.shared.form(-expr)
            tex = "- "
            if expr.is_Add:
                tex += "("
                parens = True
        numerator, denominator = _fraction(expr, self.shared)
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
        if _is_exp(base):
            raise Unprintable(expr)  # SymPy brackets e^x before raising it
        if base.is_Function:
            return self.print(base, exp=self.print(exponent))
        printed = self.print(base)
        if _precedence(base) <= _POW:
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
        if _is_true(condition):
            rows.append(rf"{self.print(value)} & \text{{otherwise}}")
        else:
            rows.append(rf"{self.print(value)} & \text{{for}}\: {self.print(condition)}")
        return r"\begin{{cases}} {} \end{{cases}}".format(r" \\".join(rows))

    def _function(self, expr: Any, exp: str | None) -> str:
        if sx.is_piecewise(expr) or _is_exp(expr):
            raise Unprintable(expr)  # SymPy's own forms with an exponent
        name = sx.function_name(expr)
        if name == "log":
            tex = rf"\log{{\left({self.print(expr.args[0])} \right)}}"
            return tex if exp is None else f"{tex}^{{{exp}}}"
        if name == "Abs":
            tex = rf"\left|{{{self.print(expr.args[0])}}}\right|"
            return tex if exp is None else f"{tex}^{{{exp}}}"
        name = _function_name(expr)
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


# ---------------------------------------------------------------------------------------
# MathML: sympy.printing.mathml.MathMLPresentationPrinter, as the report customizes it.

_TIMES = "<mo>&InvisibleTimes;</mo>"
_SPACED_TIMES = '<mo lspace="0.1667em" rspace="0.1667em">&InvisibleTimes;</mo>'
_FIRST_TOKEN = re.compile(r"<(mi|mn|mo)(?:\s[^>]*)?>([^<]*)<")


def _greek_unicode() -> dict[str, str]:
    """``sympy.printing.pretty.pretty_symbology.greek_unicode``."""
    table: dict[str, str] = {}
    for letter in _GREEKS:
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
    name, supers, subs = _split_super_sub(text)

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
        self.shared = _shared()

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
        if _is_exp(expr):
            return f"<msup>{_mi('&ExponentialE;')}{self.print(_exp_argument(expr))}</msup>"
        if expr.is_Pow:
            return self._pow(expr)
        if sx.is_piecewise(expr):
            return self._piecewise(expr)
        if expr.is_Function:
            return self._function(expr)
        if _is_relation(expr):
            lhs, rhs = expr.args
            return _row(self.print(lhs), _mo(_RELATIONS[_name(expr)][1]), self.print(rhs))
        return self._atom(expr)

    def _atom(self, expr: Any) -> str:
        name = _name(expr)
        if name == "Pi":
            return _mi("&pi;")
        if name == "Exp1":
            return _mi("&ExponentialE;")
        if name in ("BooleanTrue", "BooleanFalse"):
            return _mi(name[len("Boolean") :])
        raise Unprintable(expr)

    def _float(self, expr: Any) -> str:
        text = _float_digits(expr)
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
            if i and _negative(term):
                parts += [_mo("-"), self.print(-term)]
            else:
                parts += [_mo("+")] if i else []
                parts.append(self.print(term))
        return _row(*parts)

    def _factor(self, term: Any) -> str:
        printed = self.print(term)
        return _parenthesized(printed) if _precedence(term) <= _MUL else printed

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
        if _negative(expr):
            sign = _mo("-")
            expr = self.shared.form(-expr)
        numerator, denominator = _fraction(expr, self.shared)
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
        return _parenthesized(printed) if _precedence(base) <= _POW else printed

    def _piecewise(self, expr: Any) -> str:
        rows = []
        for value, condition in sx.piecewise_pairs(expr):
            when = (
                "<mtext>otherwise</mtext>"
                if _is_true(condition)
                else "<mtext>for&#160;</mtext>" + self.print(condition)
            )
            rows.append(f"<mtr><mtd>{self.print(value)}</mtd><mtd>{when}</mtd></mtr>")
        return _row(_mo("{"), '<mtable columnalign="left">' + "".join(rows) + "</mtable>")

    def _function(self, expr: Any) -> str:
        name = sx.function_name(expr)
        if name == "Abs":
            return _row(_mo("|"), self.print(expr.args[0]), _mo("|"))
        if name != "log":
            name = _function_name(expr)
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


# ---------------------------------------------------------------------------------------
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
        node = _distributed(stack.pop())
        if node.is_Rational:
            if node != 1:
                count += (int(node.p) < 0) + (int(node.q) != 1)
                continue
        elif node.is_Mul:
            if _negative(node):
                count += 1
                node = _distributed(-node)
            if node.is_Mul or node.is_Pow or _is_exp(node):
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
                if _negative(term):
                    negatives += 1
                    stack.append(-term)
                else:
                    stack.append(term)
                count += i > 0  # an addition or a subtraction
            count += negatives == len(terms)  # -x - y: a negation and a subtraction
            continue
        if node.is_Pow and not _is_exp(node) and node.args[1] == -1:
            count += 1
            stack.append(node.args[0])
            continue
        if _is_exp1(node):
            count += 1
            continue
        if _is_exp(node):
            count += 1
            stack.append(_exp_argument(node))
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
        if term.is_Pow or _is_exp(term):
            base, exponent = (sx.E, _exp_argument(term)) if _is_exp(term) else term.args
            if exponent.is_Number:
                if exponent < 0:
                    denominator.append(base ** (-exponent))
                else:
                    numerator.append(term)
            elif not exponent.free_symbols:
                raise Unprintable(term)
            elif exponent.is_Mul:
                # SymPy's as_numer_denom: a negative coefficient puts it below.
                if _negative(exponent):
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
    return _distributed(sx.Mul(*numerator)), _distributed(sx.Mul(*denominator))


# ---------------------------------------------------------------------------------------
# One line of text: sympy.printing.str.StrPrinter with order="none" (``sstr``).

#: SymPy's (not traditional) precedences of a sum, a product, a power, a function, an atom.
_STR_ADD, _STR_MUL, _STR_POW, _STR_FUNC, _STR_ATOM = 40, 50, 60, 70, 1000


def _str_precedence(expr: Any) -> int:
    """SymPy's ``precedence``: a product or number that is negative binds as a sum."""
    if expr.is_Add:
        return _STR_ADD
    if expr.is_Mul:
        return _STR_ADD if _negative(expr) else _STR_MUL
    if _is_exp(expr) or expr.is_Function:
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
        self.shared = _shared()

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
        if _is_exp(expr):
            return f"exp({self.print(_exp_argument(expr))})"
        if expr.is_Pow:
            return self._pow(expr)
        if expr.is_Function and not sx.is_piecewise(expr):
            name = sx.function_name(expr)
            if name not in ("log", "Abs"):
                name = _function_name(expr)
            return f"{name}({', '.join(self.print(arg) for arg in expr.args)})"
        name = _name(expr)
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
        if _negative(expr):
            sign = "-"
            expr = self.shared.form(-expr)
        numerator: list[Any] = []
        denominator: list[Any] = []
        for item in self.shared.ordered(expr) if expr.is_Mul else [expr]:
            if item.is_Pow and not _is_exp(item) and _negative_exponent(item.args[1]):
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
        return _negative(exponent)
    return False


def text(expr: Any) -> str:
    """``expr`` as one line of text, as SymPy's ``sstr(expr, order="none")`` writes it.

    Raises :class:`Unprintable` for a node it does not print.
    """
    return _Text().print(sx.as_expr(expr), level=1)
