"""What the report's printers share: a node's kind, sign, order, numerator and denominator.

The printers (:mod:`~tvopt_codegen.report.printing`) walk either engine's expressions
through the :mod:`~tvopt_codegen.symbolic` API; this module says what a node is as SymPy
would hold it (a rational times a sum distributed, SymEngine's power of E as ``exp``),
in SymPy's order of its arguments, and remembers it for every formula of a report.
"""

from __future__ import annotations

import re
from typing import Any

from tvopt_codegen import symbolic as sx
from tvopt_codegen.symbolic.order import canonical_key


class Unprintable(Exception):  # noqa: N818 - a signal to fall back, not an error
    """A node the report's printers do not print (SymPy's printers do)."""


# ---------------------------------------------------------------------------------------
# What both printers share: a node's kind, its sign, its numerator and denominator.

#: SymPy's traditional precedences (``sympy.printing.precedence``) of the nodes printed.
ADD, MUL, POW, FUNC, ATOM, RELATION = 40, 50, 60, 70, 1000, 35

#: Relations by class name: LaTeX and MathML operators.
RELATIONS = {
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


class Shared:
    """What both printers and every formula of a report share, node by node.

    A report prints each expression twice (LaTeX and MathML) and many subexpressions
    more often (a robot's matrices repeat its sines and cosines): the order of a node's
    arguments, its SymPy form and what each printer made of it are kept, for the
    process's engine (:func:`shared_memo` starts afresh when it changes).
    """

    def __init__(self, engine: str) -> None:
        self.engine = engine
        self.keys: dict[Any, tuple[Any, ...]] = {}
        self.orders: dict[Any, list[Any]] = {}
        self.forms: dict[Any, Any] = {}
        self.latex: dict[Any, str] = {}
        self.mathml: dict[Any, str] = {}

    def ordered(self, expr: Any) -> list[Any]:
        """``expr``'s arguments in SymPy's order."""
        found = self.orders.get(expr)
        if found is None:
            args = expr.args
            found = self.orders[expr] = sorted(args, key=self.key) if sx.SYMENGINE else list(args)
        return found

    def key(self, expr: Any) -> tuple[Any, ...]:
        """SymPy's place of ``expr`` among a sum's or a product's arguments.

        :func:`~tvopt_codegen.symbolic.order.canonical_key`, memoised.
        """
        found = self.keys.get(expr)
        if found is None:
            found = self.keys[expr] = canonical_key(expr, self.key)
        return found

    def form(self, expr: Any) -> Any:
        """:func:`distributed`, memoised."""
        found = self.forms.get(expr)
        if found is None:
            found = self.forms[expr] = distributed(expr)
        return found

    def size(self) -> int:
        """How many entries the memo holds."""
        return len(self.keys) + len(self.orders) + len(self.latex) + len(self.mathml)


#: Nodes remembered at most (a few hundred MB at worst), then forgotten all at once.
_MEMO_LIMIT = 500_000
_SHARED: list[Shared] = []


def shared_memo() -> Shared:
    """The memo of the process's engine."""
    if not _SHARED or _SHARED[0].engine != sx.ENGINE or _SHARED[0].size() > _MEMO_LIMIT:
        _SHARED[:] = [Shared(sx.ENGINE)]
    return _SHARED[0]


def node_name(expr: Any) -> str:
    """The class name of ``expr`` (``Exp1``, ``Piecewise``, ``StrictLessThan``)."""
    return type(expr).__name__


def is_exp1(expr: Any) -> bool:
    """Whether ``expr`` is the number e."""
    return node_name(expr) == "Exp1"


def is_exp(expr: Any) -> bool:
    """``exp(x)``: SymPy's function, SymEngine's power of E."""
    return (expr.is_Pow and is_exp1(expr.args[0])) or (
        not sx.SYMENGINE and expr.is_Function and node_name(expr) == "exp"
    )


def exp_argument(expr: Any) -> Any:
    """``x`` of ``exp(x)`` (SymPy's only argument, SymEngine's exponent)."""
    return expr.args[-1]


def is_true(expr: Any) -> bool:
    """Whether ``expr`` is the condition True (a ``Piecewise``'s otherwise)."""
    return node_name(expr) == "BooleanTrue"


def is_relation(expr: Any) -> bool:
    """Whether ``expr`` is a relation the printers print (``x < 1``)."""
    return node_name(expr) in RELATIONS


def negative(expr: Any) -> bool:
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


def precedence(expr: Any) -> int:
    """SymPy's ``precedence_traditional``."""
    if expr.is_Add:
        return ADD
    if expr.is_Mul:
        return MUL
    if expr.is_Pow and not is_exp(expr):
        return POW
    if expr.is_Number:
        if expr < 0:
            return ADD
        return MUL if expr.is_Rational and not expr.is_Integer else ATOM
    if is_relation(expr):
        return RELATION
    if expr.is_Function or is_exp(expr):
        return FUNC
    return ATOM


def distributed(expr: Any) -> Any:
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


def fraction(expr: Any, shared: Shared) -> tuple[list[Any], list[Any]]:
    """SymPy's ``fraction(expr, exact=True)`` as lists of factors, in order."""
    numerator: list[Any] = []
    denominator: list[Any] = []
    factors = shared.ordered(expr) if expr.is_Mul else [expr]
    for term in factors:
        if term.is_Pow or is_exp(term):
            base, exponent = (sx.E, exp_argument(term)) if is_exp(term) else term.args
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


def function_name(expr: Any) -> str:
    """An applied function's name, or Unprintable for a function with its own printer."""
    name = sx.function_name(expr)
    if name in _PLAIN_FUNCTIONS:
        return name
    if sx.SYMENGINE and node_name(expr) == "FunctionSymbol":
        return name
    if not sx.SYMENGINE and _is_undefined(expr):
        return name
    raise Unprintable(expr)


def _is_undefined(expr: Any) -> bool:
    from sympy.core.function import AppliedUndef  # noqa: PLC0415 - SymPy's engine only

    return isinstance(expr, AppliedUndef)


#: ``sympy.printing.conventions``: a name ending in digits has them as a subscript.
_NAME_WITH_DIGITS = re.compile(r"^([^\W\d_]+)(\d+)$", re.UNICODE)


def split_super_sub(text: str) -> tuple[str, list[str], list[str]]:
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


GREEKS = (
    "alpha beta gamma delta epsilon zeta eta theta iota kappa lambda mu nu xi omicron pi "
    "rho sigma tau upsilon phi chi psi omega"
).split()


def float_digits(expr: Any) -> str:
    """A float as SymPy writes it: 15 significant digits (a SymPy float: its own)."""
    from mpmath.libmp import from_float, prec_to_dps, to_str  # noqa: PLC0415

    if sx.SYMENGINE:
        return str(to_str(from_float(float(expr)), 15, strip_zeros=True))
    return str(to_str(expr._mpf_, prec_to_dps(expr._prec), strip_zeros=True))
