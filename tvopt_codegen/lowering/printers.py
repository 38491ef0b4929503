"""What every backend's printer shares: one walk over an expression, through the API.

A printer turns one expression of either engine into one line of code. It reads the
tree only through what both engines answer to (``.args``, the ``is_*`` flags, the
names of the node classes, which SymPy and SymEngine share for everything a kernel
holds, :func:`~tvopt_codegen.symbolic.function_name`, ``piecewise_pairs``), so that a
kernel prints the same whichever engine derived it, up to the order of terms.

Each backend subclasses :class:`ExpressionPrinter` in its own folder
(``backends/<name>/printer.py``) for its spelling of numbers, powers and functions. The
layout of sums and products is shared: it is what SymPy's code printers wrote, kept
character for character (the generated files are golden), with the terms in SymPy's
canonical order as it stands, the constant moved to the end and a positive term first
(``1 - x``, not ``-x + 1``). On SymEngine, whose order of arguments follows its hashes,
the terms and factors are sorted as SymPy sorts them when it builds a sum or a product
(:func:`canonical_key`): the same text in every run, and the same text as SymPy's for
the same tree.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, ClassVar, Protocol

from tvopt_codegen import symbolic as sx
from tvopt_codegen.symbolic.order import canonical_key

#: Binding strengths, as SymPy's printers rank them (a term binds weaker than a factor).
OR, AND, RELATIONAL, ADD, MUL, POW, FUNC, NOT, ATOM = 20, 30, 35, 40, 50, 60, 70, 100, 1000
#: A lone negated factor (``-x``, ``-(x*x)``): between a product and a power, as Python's
#: unary minus.
_NEGATED = (POW + MUL) / 2

#: The relations a condition may hold, by the class name both engines give them.
RELATIONS = {
    "StrictLessThan": "<",
    "LessThan": "<=",
    "StrictGreaterThan": ">",
    "GreaterThan": ">=",
    "Equality": "==",
    "Unequality": "!=",
}


class UnprintableError(NotImplementedError):
    """An expression node the printer's language has no spelling for (a bug upstream)."""


class ExpressionPrinter:
    """One expression as one line of code: the walk every backend's printer shares.

    A subclass spells the leaves and the operations of its language: ``_print_<Name>``
    for the node class named ``Name`` (or a class it derives from: ``Integer`` covers
    SymPy's ``Zero`` and ``One``), :meth:`_power` for ``base**exponent`` and
    :meth:`_function` for an applied function. Each node's text is kept, so that a
    node shared by many expressions (a kernel's common subexpressions form a DAG) is
    printed once.
    """

    #: Words of the language a symbol may not be: such a symbol prints with ``_``
    #: appended, as SymPy's printers did.
    reserved_words: ClassVar[frozenset[str]] = frozenset()

    def __init__(self) -> None:
        self._memo: dict[Any, tuple[Any, str, float]] = {}
        self._keys: dict[Any, tuple[Any, ...]] = {}
        self._methods: dict[type, Callable[[Any], str]] = {}
        self._by_value = False

    # -- the walk ----------------------------------------------------------------------

    def doprint(self, expr: Any) -> str:
        """Print one expression (a number of Python is taken as the engine's)."""
        if isinstance(expr, int | float):
            expr = sx.sympify(expr)
        # SymEngine builds a new Python object for every argument it hands out: its nodes
        # are kept by value (and its arguments, in its hashes' order, put in SymPy's).
        # SymPy's are the objects themselves, kept by identity (by value, 2 and 2.0
        # would be one node).
        self._by_value = sx.SYMENGINE
        return self._print_top(expr)

    def _print_top(self, expr: Any) -> str:
        """The text of a whole expression (a language may print a lone leaf otherwise)."""
        return self._print(expr)

    def _print(self, expr: Any) -> str:
        """The text of one node, printed once."""
        return self._entry(expr)[1]

    def _entry(self, expr: Any) -> tuple[Any, str, float]:
        """A node, its text and its precedence, computed once."""
        key = expr if self._by_value else id(expr)
        known = self._memo.get(key)
        if known is None:
            # The node itself is kept: an identity is not reused while it lives.
            known = (expr, self._method(type(expr))(expr), self.precedence(expr))
            self._memo[key] = known
        return known

    def _method(self, kind: type) -> Callable[[Any], str]:
        """The printing method of a node class: by its name, or its nearest base's."""
        method = self._methods.get(kind)
        if method is None:
            method = self._unprintable
            for base in kind.__mro__:
                found = getattr(self, f"_print_{base.__name__}", None)
                if found is not None:
                    method = found
                    break
            self._methods[kind] = method
        return method

    def _unprintable(self, expr: Any) -> str:
        raise UnprintableError(f"{type(self).__name__} cannot print {type(expr).__name__}")

    def precedence(self, expr: Any) -> float:
        """How strongly ``expr``'s text binds (SymPy's precedence of the node)."""
        if expr.is_Add:
            return ADD
        if expr.is_Mul:
            return ADD if negative_number(expr.args[0]) else MUL
        if expr.is_Pow:
            return FUNC if _is_e(expr.args[0]) else POW
        if expr.is_Number:
            if negative_number(expr):
                return ADD
            return MUL if expr.is_Rational and not expr.is_Integer else ATOM
        if expr.is_Symbol or expr.is_Atom:
            return ATOM
        if expr.is_Function:
            return FUNC
        name = type(expr).__name__
        if name in RELATIONS:
            return RELATIONAL
        return {"And": AND, "Or": OR, "Not": NOT}.get(name, ATOM)

    def parenthesize(self, expr: Any, level: float) -> str:
        """``expr``'s text, in brackets unless it binds more strongly than ``level``."""
        _, text, precedence = self._entry(expr)
        return f"({text})" if precedence <= level else text

    # -- sums and products ---------------------------------------------------------------

    def _ordered(self, args: tuple[Any, ...]) -> list[Any]:
        """Arguments in the engine's order, or in SymPy's where that follows hashes."""
        if not self._by_value or len(args) < 2:
            return list(args)
        return sorted(args, key=self._key)

    def _key(self, expr: Any) -> tuple[Any, ...]:
        """:func:`canonical_key` of a node, computed once."""
        key = self._keys.get(expr)
        if key is None:
            key = self._keys[expr] = canonical_key(expr, self._key)
        return key

    def _print_Add(self, expr: Any) -> str:
        args = self._ordered(expr.args)
        terms = [a for a in args if not a.is_Number] + [a for a in args if a.is_Number]
        if negative_term(terms[0]):
            first = next((i for i, term in enumerate(terms) if not negative_term(term)), 0)
            terms.insert(0, terms.pop(first))
        pieces: list[str] = []
        for term in terms:
            text = self._print(term)
            sign = "+"
            if text.startswith("-") and not term.is_Add:
                sign, text = "-", text[1:]
            pieces += [sign, f"({text})" if term.is_Add else text]
        first_sign = pieces.pop(0)
        return ("" if first_sign == "+" else first_sign) + " ".join(pieces)

    def _print_Mul(self, expr: Any) -> str:
        """A product: its coefficient's sign first, negative powers as a denominator."""
        args = expr.args
        level = self.precedence(expr)
        coefficient = args[0] if args[0].is_Number else None
        factors = self._ordered(args[1:] if coefficient is not None else args)
        sign = ""
        if coefficient is not None and negative_number(coefficient):
            sign, coefficient = "-", -coefficient
        if coefficient is not None and not (coefficient.is_Integer and int(coefficient) == 1):
            factors.insert(0, coefficient)
        numerator: list[str] = []
        denominator: list[str] = []
        lone: Any = None
        for factor in factors:
            exponent = factor.args[1] if factor.is_Pow else None
            if exponent is not None and exponent.is_Rational and negative_number(exponent):
                base = factor.args[0]
                if exponent.is_Integer and int(exponent) == -1:
                    text = self.parenthesize(base, level)
                    # A product to the power -1 keeps its brackets (SymPy's #14160).
                    bracketed = base.is_Mul and len(base.args) != 1
                    denominator.append(f"({text})" if bracketed else text)
                else:
                    denominator.append(self._power(base, -exponent))
            else:
                numerator.append(factor)
                lone = factor
        if not numerator:
            numerator_text = [self._print(sx.ONE)]
        elif len(numerator) == 1 and sign:
            numerator_text = [self.parenthesize(lone, _NEGATED)]
        else:
            numerator_text = [self.parenthesize(factor, level) for factor in numerator]
        text = sign + "*".join(numerator_text)
        if len(denominator) == 1:
            return f"{text}/{denominator[0]}"
        if denominator:
            return f"{text}/({'*'.join(denominator)})"
        return text

    def _print_Pow(self, expr: Any) -> str:
        base, exponent = expr.args
        if _is_e(base):  # SymEngine's exp(x) is E**x
            return self._function("exp", (exponent,))
        return self._power(base, exponent)

    def _power(self, base: Any, exponent: Any) -> str:
        """``base**exponent`` (also a denominator's power, which is no node of its own)."""
        raise NotImplementedError

    # -- functions and leaves ----------------------------------------------------------

    def _print_Function(self, expr: Any) -> str:
        return self._function(sx.function_name(expr), tuple(expr.args))

    def _function(self, name: str, args: tuple[Any, ...]) -> str:
        """An applied function ``name`` of ``args``."""
        raise NotImplementedError

    def _print_Symbol(self, expr: Any) -> str:
        name: str = expr.name
        return name + "_" if name in self.reserved_words else name


class JointPrinter(Protocol):
    """A printer whose one text stands for several printings (a backend's ``joint``)."""

    def doprint(self, expr: Any) -> str:
        """The marked text of one expression."""

    def texts(self) -> dict[str, Callable[[str], str]]:
        """Functions from the marked text to each printing's, by variant key."""


def negative_term(term: Any) -> bool:
    """Whether a term prints with a leading minus sign."""
    return negative_number(term.args[0] if term.is_Mul else term)


def negative_number(expr: Any) -> bool:
    """Whether ``expr`` is a number below zero.

    SymPy's ``is_negative`` runs its assumption system on first use (a third of printing
    time for a large controller): its rationals are read from their numerator.
    SymEngine's answers at once (and makes its numerator a Python int slowly).
    """
    if expr.is_Rational and not sx.SYMENGINE:
        return bool(expr.p < 0)
    if expr.is_Float:
        return float(expr) < 0
    return bool(expr.is_Number and expr.is_negative)


def _is_e(expr: Any) -> bool:
    """Whether ``expr`` is Euler's number (SymEngine writes ``exp(x)`` as ``E**x``)."""
    return type(expr).__name__ == "Exp1"


def float_digits(value: float, digits: int, strip_zeros: bool) -> str:
    """A double with ``digits`` significant digits, as SymPy prints its ``Float``.

    The decimal of the double's exact binary value, rounded (mpmath's layout: fixed
    point for moderate exponents, ``e`` notation beyond), so that a SymEngine
    ``RealDouble`` prints as a SymPy ``Float`` of the same value does.
    """
    from mpmath.libmp import from_float, to_str  # noqa: PLC0415 - only a float needs it

    text: str = to_str(from_float(value), digits, strip_zeros=strip_zeros)
    if text.startswith("-.0"):
        text = "-0." + text[3:]
    elif text.startswith(".0"):
        text = "0." + text[2:]
    return text.removeprefix("+")
