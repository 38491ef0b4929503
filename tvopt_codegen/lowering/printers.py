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


#: The parts of a node's record in a printer's memo: the node, its text and precedence
#: (None until printed), its arguments, its :func:`canonical_key` and its arguments'
#: records (None until asked).
_NODE, _TEXT, _LEVEL, _ARGS, _KEY, _CHILDREN = range(6)


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
        #: One record per node (:data:`_NODE`, :data:`_TEXT`, ...): one lookup of the
        #: node gives all the walk keeps of it.
        self._memo: dict[Any, list[Any]] = {}
        self._methods: dict[type, Callable[[Any], str]] = {}
        #: The precedence of the node classes whose precedence is their class's alone.
        self._levels: dict[type, float] = {}
        #: The record of the node whose method runs (until it prints another).
        self._current: list[Any] = [None]
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
        record = self._record(expr)
        text: str | None = record[_TEXT]
        return text if text is not None else str(self._printed(record)[_TEXT])

    def _record(self, expr: Any) -> list[Any]:
        """The record of a node: made at first sight, its parts filled when asked."""
        key = expr if self._by_value else id(expr)
        record = self._memo.get(key)
        if record is None:
            # The node itself is kept: an identity is not reused while it lives.
            record = self._memo[key] = [expr, None, 0.0, None, None, None]
        return record

    def _printed(self, record: list[Any]) -> list[Any]:
        """``record`` with its node's text and precedence."""
        if record[_TEXT] is None:
            expr = record[_NODE]
            kind = type(expr)
            method = self._methods.get(kind) or self._method(kind)
            level = self._levels.get(kind)
            # The method's first question is the node's arguments (_arguments).
            self._current = record
            text = method(expr)
            record[_LEVEL] = self.precedence(expr) if level is None else level
            record[_TEXT] = text
        return record

    def _entry(self, expr: Any) -> list[Any]:
        """A node's record with its text and precedence, computed once."""
        record = self._record(expr)
        return record if record[_TEXT] is not None else self._printed(record)

    def _arguments(self, expr: Any) -> tuple[Any, ...]:
        """A node's arguments, read once per node.

        Each ``.args`` of a SymEngine node builds new Python objects for its arguments
        (a microsecond or more); the walk asks for a node's arguments when it prints
        the node, when it prints its parent and when it orders it. SymPy's are a
        tuple the node holds.
        """
        if not self._by_value:
            return expr.args  # type: ignore[no-any-return]
        current = self._current
        return self._record_args(current if current[_NODE] is expr else self._record(expr))

    @staticmethod
    def _record_args(record: list[Any]) -> tuple[Any, ...]:
        args: tuple[Any, ...] | None = record[_ARGS]
        if args is None:
            args = record[_ARGS] = record[_NODE].args
        return args

    def _children(self, record: list[Any]) -> list[list[Any]]:
        """The records of a node's arguments, looked up once per node.

        Ordering a sum's terms asks for the keys of the terms' own arguments, and
        printing asks for their texts: on SymEngine each lookup hashes and compares a new
        Python object (about a microsecond), once per node here instead of once per ask.
        """
        children: list[list[Any]] | None = record[_CHILDREN]
        if children is None:
            find = self._record
            children = record[_CHILDREN] = [find(arg) for arg in self._record_args(record)]
        return children

    def _node_children(self, expr: Any) -> list[list[Any]]:
        """:meth:`_children` of ``expr``, the node whose method runs (or any other)."""
        current = self._current
        return self._children(current if current[_NODE] is expr else self._record(expr))

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
        if expr.is_Mul:
            return ADD if negative_number(self._arguments(expr)[0]) else MUL
        if expr.is_Pow:
            return FUNC if _is_e(self._arguments(expr)[0]) else POW
        if expr.is_Number:
            if negative_number(expr):
                return ADD
            return MUL if expr.is_Rational and not expr.is_Integer else ATOM
        # The rest binds as its class does: asked once per class.
        if expr.is_Add:
            level = ADD
        elif expr.is_Symbol or expr.is_Atom:
            level = ATOM
        elif expr.is_Function:
            level = FUNC
        else:
            name = type(expr).__name__
            if name in RELATIONS:
                level = RELATIONAL
            else:
                level = {"And": AND, "Or": OR, "Not": NOT}.get(name, ATOM)
        self._levels[type(expr)] = level
        return level

    def parenthesize(self, expr: Any, level: float) -> str:
        """``expr``'s text, in brackets unless it binds more strongly than ``level``."""
        record = self._entry(expr)
        text: str = record[_TEXT]
        return f"({text})" if record[_LEVEL] <= level else text

    # -- sums and products ---------------------------------------------------------------

    def _ordered(self, records: list[list[Any]]) -> list[list[Any]]:
        """Records as a new list, in the engine's order or SymPy's where it follows hashes."""
        records = list(records)
        if self._by_value and len(records) > 1:
            records.sort(key=self._record_key)
        return records

    def _key(self, expr: Any) -> tuple[Any, ...]:
        """:func:`canonical_key` of a node, computed once."""
        return self._record_key(self._record(expr))

    def _record_key(self, record: list[Any]) -> tuple[Any, ...]:
        key: tuple[Any, ...] | None = record[_KEY]
        if key is None:
            # Its arguments' keys from their records (canonical_key takes them as args).
            key = record[_KEY] = canonical_key(
                record[_NODE], self._record_key, self._children(record)
            )
        return key

    def _negative_term(self, record: list[Any]) -> bool:
        """Whether a term prints with a leading minus sign (:func:`negative_term`)."""
        term = record[_NODE]
        return negative_number(self._record_args(record)[0] if term.is_Mul else term)

    def _print_Add(self, expr: Any) -> str:
        terms = self._ordered(self._node_children(expr))
        numbers = [r for r in terms if r[_NODE].is_Number]
        if numbers:
            terms = [r for r in terms if not r[_NODE].is_Number] + numbers
        if self._negative_term(terms[0]):
            first = next((i for i, term in enumerate(terms) if not self._negative_term(term)), 0)
            terms.insert(0, terms.pop(first))
        pieces: list[str] = []
        printed = self._printed
        for record in terms:
            text = record[_TEXT]
            if text is None:
                text = printed(record)[_TEXT]
            sign = "+"
            if record[_NODE].is_Add:
                text = f"({text})"
            elif text[0] == "-":
                sign, text = "-", text[1:]
            pieces += [sign, text]
        first_sign = pieces.pop(0)
        return ("" if first_sign == "+" else first_sign) + " ".join(pieces)

    def _print_Mul(self, expr: Any) -> str:
        """A product: its coefficient's sign first, negative powers as a denominator."""
        args = self._arguments(expr)
        children = self._node_children(expr)
        coefficient = args[0] if args[0].is_Number else None
        factors = self._ordered(children[1:] if coefficient is not None else children)
        sign = ""
        level: float = MUL
        if coefficient is not None and negative_number(coefficient):
            sign, coefficient, level = "-", -coefficient, ADD
            if not (coefficient.is_Integer and int(coefficient) == 1):
                factors.insert(0, self._record(coefficient))
        elif coefficient is not None and not (coefficient.is_Integer and int(coefficient) == 1):
            factors.insert(0, children[0])
        numerator: list[list[Any]] = []
        denominator: list[str] = []
        for record in factors:
            factor = record[_NODE]
            exponent = self._record_args(record)[1] if factor.is_Pow else None
            if exponent is not None and exponent.is_Rational and negative_number(exponent):
                base = self._record_args(record)[0]
                if exponent.is_Integer and int(exponent) == -1:
                    text = self.parenthesize(base, level)
                    # A product to the power -1 keeps its brackets (SymPy's #14160).
                    bracketed = base.is_Mul and len(self._arguments(base)) != 1
                    denominator.append(f"({text})" if bracketed else text)
                else:
                    denominator.append(self._power(base, -exponent))
            else:
                numerator.append(record)
        if not numerator:
            numerator_text = [self._print(sx.ONE)]
        else:
            if len(numerator) == 1 and sign:
                level = _NEGATED
            numerator_text = []
            printed = self._printed
            for record in numerator:
                if record[_TEXT] is None:
                    printed(record)
                text = record[_TEXT]
                numerator_text.append(f"({text})" if record[_LEVEL] <= level else text)
        text = sign + "*".join(numerator_text)
        if len(denominator) == 1:
            return f"{text}/{denominator[0]}"
        if denominator:
            return f"{text}/({'*'.join(denominator)})"
        return text

    def _print_Pow(self, expr: Any) -> str:
        base, exponent = self._arguments(expr)
        if _is_e(base):  # SymEngine's exp(x) is E**x
            return self._function("exp", (exponent,))
        return self._power(base, exponent)

    def _power(self, base: Any, exponent: Any) -> str:
        """``base**exponent`` (also a denominator's power, which is no node of its own)."""
        raise NotImplementedError

    # -- functions and leaves ----------------------------------------------------------

    def _print_Function(self, expr: Any) -> str:
        return self._function(sx.function_name(expr), tuple(self._arguments(expr)))

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
