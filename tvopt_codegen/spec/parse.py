"""Safe parsing of spec expressions into the process's engine's expressions.

Spec text is never handed to ``eval``, ``exec``, ``sympify`` or ``parse_expr``: those
run Python. Instead :func:`parse_expression` parses with ``ast.parse(mode="eval")``,
walks an allow-list of node types, and builds expressions directly through
:mod:`tvopt_codegen.symbolic` (SymEngine's or SymPy's, the same on both: decimals are
exact rationals on either). Size, nesting, literal magnitude and exponents are bounded
so that no spec can hang the tool.
"""

from __future__ import annotations

import ast
import difflib
import io
import math
import re
import tokenize
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from fractions import Fraction

from tvopt_codegen import symbolic as sx
from tvopt_codegen.spec.folding import (
    _at_a_pole,
    _Builder,
    _distributed,
    _is_zero,
    _trig_of_pi_multiple,
    _zero_to_the,
)

#: Longest expression text accepted, in characters.
MAX_EXPRESSION_LENGTH = 1_000_000
#: Largest exact number (bits of its numerator or denominator) constant folding may
#: build: about 1e1233, far beyond any double.
MAX_CONSTANT_BITS = 4096
#: Expressions at least this long are split at their top-level sums and products and
#: the pieces parsed one by one: Python's parser nests a flat sum of n terms n deep.
#: Shorter ones (every hand-written spec) are parsed whole.
_SPLIT_LENGTH = 2000
#: Deepest nesting of operations accepted.
MAX_DEPTH = 60
#: Most brackets open at once in an expression that can be accepted: each nesting level
#: of the tree holds at most one, and a long chain (see :func:`_parse_chain`) may strip
#: MAX_DEPTH of them before its pieces are walked from depth 0.
_MAX_BRACKETS = 2 * MAX_DEPTH + 1
#: Largest magnitude of a numeric literal.
MAX_LITERAL = 1e12
#: Smallest nonzero magnitude of a numeric literal.
MIN_LITERAL = 1e-30
#: Largest magnitude of a numeric exponent.
MAX_EXPONENT = 64

#: The functions a spec may call, with their arity. All are smooth on the interior of
#: their domain, which the method needs (f0 must be C-infinity).
ARITIES: Mapping[str, int] = {
    "sin": 1,
    "cos": 1,
    "tan": 1,
    "asin": 1,
    "acos": 1,
    "atan": 1,
    "atan2": 2,
    "sinh": 1,
    "cosh": 1,
    "tanh": 1,
    "asinh": 1,
    "acosh": 1,
    "atanh": 1,
    "exp": 1,
    "log": 1,
    "sqrt": 1,
}


class _EngineFunctions(Mapping[str, tuple[_Builder, int]]):
    """Each spec function's name -> (the engine's function, arity), read when asked.

    Looked up at each access, not at import: the engine may change within a process
    (:func:`tvopt_codegen.symbolic.using`), and importing this module builds nothing.
    """

    def __getitem__(self, name: str) -> tuple[_Builder, int]:
        return sx.FUNCTIONS[name], ARITIES[name]

    def __iter__(self) -> Iterator[str]:
        return iter(ARITIES)

    def __len__(self) -> int:
        return len(ARITIES)

    def __contains__(self, name: object) -> bool:
        return name in ARITIES


class _EngineConstants(Mapping[str, sx.Expr]):
    """Each named constant -> the engine's value, read when asked (as the functions are)."""

    _NAMES = ("pi",)

    def __getitem__(self, name: str) -> sx.Expr:
        if name not in self._NAMES:
            raise KeyError(name)
        return getattr(sx, name)

    def __iter__(self) -> Iterator[str]:
        return iter(self._NAMES)

    def __len__(self) -> int:
        return len(self._NAMES)

    def __contains__(self, name: object) -> bool:
        return name in self._NAMES


#: The functions a spec may call: name -> (the engine's function, arity).
FUNCTIONS: Mapping[str, tuple[_Builder, int]] = _EngineFunctions()

#: Named constants a spec may use: name -> the engine's value.
CONSTANTS: Mapping[str, sx.Expr] = _EngineConstants()


@dataclass(frozen=True)
class ExpressionError(Exception):
    """A problem in one expression, with the 1-based column where it was found."""

    column: int
    message: str

    def __str__(self) -> str:
        return f"column {self.column}: {self.message}"


def _literal(value: object, column: int) -> sx.Expr:
    """Turn a Python literal from the parse tree into an exact number of the engine."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise ExpressionError(column, f"unsupported literal {value!r}")
    if isinstance(value, float) and not math.isfinite(value):
        raise ExpressionError(column, "non-finite number")
    magnitude = abs(value)
    if magnitude > MAX_LITERAL:
        raise ExpressionError(column, f"number {value!r} exceeds {MAX_LITERAL:g} in magnitude")
    if magnitude and magnitude < MIN_LITERAL:
        raise ExpressionError(column, f"number {value!r} is below {MIN_LITERAL:g} in magnitude")
    if isinstance(value, int):
        return sx.Integer(value)
    # The shortest repr of a float is the decimal the user wrote (up to trailing
    # zeros); keeping it as a rational keeps the derivation exact and the report
    # readable, and printing p/q rounds to the same double as the literal. The same
    # rational on both engines: 0.0 is zero (1/0.0 is refused), 2.0 an integer exponent.
    exact = Fraction(repr(value))
    return sx.Rational(exact.numerator, exact.denominator)


def _power(base: sx.Expr, exponent: sx.Expr, column: int) -> sx.Expr:
    """Build ``base**exponent``, refusing numeric exponents that could explode."""
    if sx.SYMENGINE and not base.is_Number and _is_zero(base):
        base = sx.ZERO  # what SymPy built: sqrt(8) - 2*sqrt(2) is 0 there
    # SymEngine counts a complex number (2*I) as a number; SymPy as a product. Only a
    # real number is bounded here, on both engines; the rest is SymPy's case below.
    if exponent.is_Number and not (sx.SYMENGINE and exponent.is_real is False):
        if abs(exponent) > MAX_EXPONENT:
            raise ExpressionError(column, f"exponent {exponent} exceeds {MAX_EXPONENT}")
        if base.is_Number and base == 0 and exponent.is_negative:
            raise ExpressionError(column, "zero raised to a negative power")
        if base.is_Rational and exponent.is_Integer:
            # Checked before the engine folds it: (((9**64)**64)**64)**64 has 10^8 digits.
            bits = abs(int(exponent)) * max(_bits(base), 1)
            if bits > MAX_CONSTANT_BITS:
                raise _too_large(column, bits)
    elif sx.SYMENGINE and base.is_Number and base == 0:
        return _zero_to_the(exponent)
    return _bounded(sx.Pow(base, exponent), column)


def _bits(number: sx.Expr) -> int:
    """Bits of the larger of a rational's numerator and denominator."""
    p, q = number.as_numer_denom()
    return max(abs(int(p)).bit_length(), abs(int(q)).bit_length())


def _too_large(column: int, bits: int) -> ExpressionError:
    return ExpressionError(
        column, f"constant too large (about 10^{int(bits * 0.30103)}; the limit is 10^1233)"
    )


def _bounded(value: sx.Expr, column: int) -> sx.Expr:
    """``value``, unless constant folding made an exact number too large to be useful."""
    if value.is_Rational:
        bits = _bits(value)
        if bits > MAX_CONSTANT_BITS:
            raise _too_large(column, bits)
    return value


#: Most terms all ``sum(i, ...)`` of one expression may expand to.
MAX_SUM_TERMS = 4096


def indexed_name(base: str, value: int) -> str:
    """The declared name that ``base[value]`` stands for (``x[2]`` is ``x_2``)."""
    return f"{base}_{value}"


@dataclass(frozen=True)
class Indexing:
    """Indices of a spec with repeated parts (the ``[index]`` table).

    Attributes
    ----------
    counts : mapping of str to int
        Each index name and how many values it takes (``0 .. count - 1``).
    families : mapping of str to int
        Each indexed name's base and its length: ``x[i]`` declared with ``i = 4``
        declares ``x_0 .. x_3``, and ``x[k]`` reads ``x_(k mod 4)`` (so ``x[i + 1]``
        wraps around a ring).
    bound : mapping of str to int
        The value of each index in scope (from an indexed key or an enclosing sum).
    """

    counts: Mapping[str, int]
    families: Mapping[str, int]
    bound: Mapping[str, int]

    def bind(self, index: str, value: int) -> Indexing:
        """The same indexing with ``index`` bound to ``value``."""
        return Indexing(self.counts, self.families, {**self.bound, index: value})


NO_INDEXING = Indexing({}, {}, {})


class _TreeBuilder:
    """Walks a parse tree and builds the engine's expression, rejecting anything else."""

    def __init__(self, names: Mapping[str, sx.Expr], indexing: Indexing) -> None:
        self.names = names
        self.indexing = indexing
        self.sum_terms = 0

    def build(self, node: ast.AST, depth: int) -> sx.Expr:
        # The source was wrapped in one pair of parentheses: offsets are already 1-based.
        column = max(1, getattr(node, "col_offset", 1))
        if depth > MAX_DEPTH:
            raise ExpressionError(column, f"nesting deeper than {MAX_DEPTH}")
        if isinstance(node, ast.Constant):
            return _literal(node.value, column)
        if isinstance(node, ast.Name):
            return self.name(node.id, column)
        if isinstance(node, ast.UnaryOp):
            operand = self.build(node.operand, depth + 1)
            if isinstance(node.op, ast.USub):
                return _distributed(-operand)
            if isinstance(node.op, ast.UAdd):
                return operand
            raise ExpressionError(column, f"operator {type(node.op).__name__} is not allowed")
        if isinstance(node, ast.BinOp):
            return self.binop(node, depth, column)
        if isinstance(node, ast.Call):
            return self.call(node, depth, column)
        if isinstance(node, ast.Subscript) and self.indexing.families:
            return self.subscript(node, column)
        raise ExpressionError(column, _describe_forbidden(node))

    def name(self, ident: str, column: int) -> sx.Expr:
        if ident in self.indexing.bound:
            return sx.Integer(self.indexing.bound[ident])
        if ident in self.indexing.counts:
            raise ExpressionError(
                column,
                f"index {ident!r} is not bound here: use it inside sum({ident}, ...) or in a "
                f"key written with [{ident}]",
            )
        if ident in self.names:
            return self.names[ident]
        if ident in CONSTANTS:
            return CONSTANTS[ident]
        if ident in FUNCTIONS:
            raise ExpressionError(column, f"function {ident!r} used without arguments")
        raise ExpressionError(column, f"unknown name {ident!r}{self.nearest(ident)}")

    def nearest(self, ident: str) -> str:
        """``: did you mean 'x'?`` for the known name closest to a misspelt one, or nothing."""
        if len(ident) > 64:  # a generated name, not a typo; difflib is quadratic in length
            return ""
        known = [*self.names, *CONSTANTS, *self.indexing.bound]
        close = difflib.get_close_matches(ident, known, n=1, cutoff=0.7)
        return f": did you mean {close[0]!r}?" if close else ""

    def binop(self, node: ast.BinOp, depth: int, column: int) -> sx.Expr:
        if isinstance(node.op, ast.BitXor):
            raise ExpressionError(column, "'^' is not a power; write '**'")
        left = self.build(node.left, depth + 1)
        right = self.build(node.right, depth + 1)
        if isinstance(node.op, ast.Add):
            return _bounded(left + right, column)
        if isinstance(node.op, ast.Sub):
            # left + (-1)*right, the minus multiplied into a sum as SymPy does (and as a
            # long chain's pieces are): x - (x + y) is -y on both engines.
            return _bounded(left + _distributed(-right), column)
        if isinstance(node.op, ast.Mult):
            return _bounded(_distributed(left * right), column)
        if isinstance(node.op, ast.Div):
            if _is_zero(right):
                raise ExpressionError(column, "division by zero")
            return _bounded(_distributed(left / right), column)
        if isinstance(node.op, ast.Pow):
            return _power(left, right, column)
        raise ExpressionError(column, f"operator {type(node.op).__name__} is not allowed")

    def subscript(self, node: ast.Subscript, column: int) -> sx.Expr:
        """``x[k]``: the member ``k mod len(x)`` of an indexed family."""
        families = self.indexing.families
        if not isinstance(node.value, ast.Name) or node.value.id not in families:
            what = ast.unparse(node.value)
            known = ", ".join(sorted(families))
            raise ExpressionError(
                column, f"{what!r} is not an indexed name (indexed names: {known})"
            )
        base = node.value.id
        value = self.integer(node.slice, column) % families[base]
        return self.name(indexed_name(base, value), column)

    def integer(self, node: ast.AST, column: int) -> int:
        """Evaluate an index expression: integers, bound indices, len(i), + - * // %."""
        if isinstance(node, ast.Constant) and type(node.value) is int:
            if abs(node.value) > MAX_LITERAL:
                raise ExpressionError(column, "index literal too large")
            return node.value
        if isinstance(node, ast.Name) and node.id in self.indexing.bound:
            return self.indexing.bound[node.id]
        if isinstance(node, ast.Name) and node.id in self.indexing.counts:
            raise ExpressionError(column, f"index {node.id!r} is not bound here")
        if isinstance(node, ast.Call) and self.is_len(node):
            return self.indexing.counts[node.args[0].id]  # type: ignore[attr-defined]
        if isinstance(node, ast.UnaryOp) and isinstance(node.op, ast.USub):
            return -self.integer(node.operand, column)
        if isinstance(node, ast.BinOp):
            left = self.integer(node.left, column)
            right = self.integer(node.right, column)
            if isinstance(node.op, ast.Add):
                return left + right
            if isinstance(node.op, ast.Sub):
                return left - right
            if isinstance(node.op, ast.Mult):
                return left * right
            if isinstance(node.op, ast.FloorDiv | ast.Mod):
                if right == 0:
                    raise ExpressionError(column, "index division by zero")
                return left // right if isinstance(node.op, ast.FloorDiv) else left % right
        raise ExpressionError(
            column,
            "an index must be an integer expression of indices, whole numbers, len(i) "
            "and + - * // %",
        )

    def is_len(self, node: ast.Call) -> bool:
        return (
            isinstance(node.func, ast.Name)
            and node.func.id == "len"
            and len(node.args) == 1
            and not node.keywords
            and isinstance(node.args[0], ast.Name)
            and node.args[0].id in self.indexing.counts
        )

    def indexed_sum(self, node: ast.Call, depth: int, column: int) -> sx.Expr:
        """``sum(i, body)``: body added up over every value of the index ``i``."""
        counts = self.indexing.counts
        if len(node.args) != 2 or node.keywords or not isinstance(node.args[0], ast.Name):
            raise ExpressionError(column, "write a sum as sum(i, expression) with an index i")
        index = node.args[0].id
        if index not in counts:
            known = ", ".join(sorted(counts)) or "none declared"
            raise ExpressionError(column, f"sum over {index!r}, which is not an index ({known})")
        if index in self.indexing.bound:
            raise ExpressionError(column, f"index {index!r} is already bound here")
        self.sum_terms += counts[index]
        if self.sum_terms > MAX_SUM_TERMS:
            raise ExpressionError(column, f"sums expand to more than {MAX_SUM_TERMS} terms")
        outer = self.indexing
        terms = []
        try:
            for value in range(counts[index]):
                self.indexing = outer.bind(index, value)
                terms.append(self.build(node.args[1], depth + 1))
        finally:
            self.indexing = outer
        return sx.Add(*terms)

    def call(self, node: ast.Call, depth: int, column: int) -> sx.Expr:
        if isinstance(node.func, ast.Name) and self.indexing.counts:
            if node.func.id == "sum":
                return self.indexed_sum(node, depth, column)
            if node.func.id == "len":
                if not self.is_len(node):
                    raise ExpressionError(column, "len() takes one index name")
                return sx.Integer(self.integer(node, column))
        if not isinstance(node.func, ast.Name) or node.func.id not in FUNCTIONS:
            what = ast.unparse(node.func)
            what = what if len(what) <= 40 else what[:37] + "..."
            allowed = ", ".join(sorted(FUNCTIONS))
            raise ExpressionError(column, f"cannot call {what!r}; allowed functions: {allowed}")
        if node.keywords:
            raise ExpressionError(column, f"{node.func.id}() takes no keyword arguments")
        func, arity = FUNCTIONS[node.func.id]
        if any(isinstance(arg, ast.Starred) for arg in node.args):
            raise ExpressionError(column, "starred arguments are not allowed")
        if len(node.args) != arity:
            raise ExpressionError(
                column, f"{node.func.id}() takes {arity} argument(s), got {len(node.args)}"
            )
        args = [self.build(arg, depth + 1) for arg in node.args]
        result = _trig_of_pi_multiple(func, args[0]) if arity == 1 else None
        if result is None:
            result = func(*args)
        if result.has(sx.zoo, sx.nan, sx.oo, -sx.oo) or _at_a_pole(node.func.id, args):
            raise ExpressionError(column, f"{node.func.id}() is undefined for these arguments")
        return result


def _describe_forbidden(node: ast.AST) -> str:
    """Explain, in the user's terms, why a syntax element is refused."""
    kinds = {
        ast.Attribute: "attribute access is",
        ast.Subscript: "indexing is",
        ast.Lambda: "lambda is",
        ast.IfExp: "conditional expressions are",
        ast.Compare: "comparisons are",
        ast.BoolOp: "logical operators are",
        ast.JoinedStr: "f-strings are",
        ast.ListComp: "comprehensions are",
        ast.GeneratorExp: "comprehensions are",
        ast.DictComp: "comprehensions are",
        ast.SetComp: "comprehensions are",
        ast.NamedExpr: "assignment expressions are",
    }
    if isinstance(node, ast.Compare):
        return "comparisons are not allowed in expressions (a constraint goes in [constraints])"
    for kind, text in kinds.items():
        if isinstance(node, kind):
            return f"{text} not allowed in expressions"
    return f"{type(node).__name__} is not allowed in expressions"


def parse_expression(
    text: str, names: Mapping[str, sx.Expr], indexing: Indexing = NO_INDEXING
) -> sx.Expr:
    """Parse one spec expression into the engine's without evaluating any Python.

    Parameters
    ----------
    text : str
        The expression as written in the spec, e.g. ``"v*cos(theta)"``.
    names : Mapping[str, Expr]
        The names the expression may use and the expressions they stand for.
    indexing : Indexing, optional
        Indices of a spec with repeated parts: then ``x[i + 1]``, ``sum(i, ...)`` and
        ``len(i)`` are understood.

    Returns
    -------
    Expr
        The expression, of the process's engine, exact (decimal literals become
        rationals).

    Raises
    ------
    ExpressionError
        For anything outside the allow-list: unknown names, calls other than the
        functions in :data:`FUNCTIONS`, attribute access, comparisons, ``^``, literals
        or exponents beyond the bounds, and text that is too long or too deep.
    """
    if not isinstance(text, str):
        raise ExpressionError(1, f"expected an expression string, got {type(text).__name__}")
    if len(text) > MAX_EXPRESSION_LENGTH:
        raise ExpressionError(1, f"expression longer than {MAX_EXPRESSION_LENGTH} characters")
    if not text.isascii():
        bad = next(i for i, ch in enumerate(text) if not ch.isascii())
        raise ExpressionError(bad + 1, f"non-ASCII character {text[bad]!r}")
    if not text.strip():
        raise ExpressionError(1, "empty expression")
    if "#" in text:
        raise ExpressionError(text.index("#") + 1, "comments are not allowed in expressions")
    # Multi-line TOML strings are welcome: line breaks become spaces (columns keep
    # their offsets) and the parentheses allow the continuation lines' indentation.
    flat = text.replace("\r", " ").replace("\n", " ").replace("\t", " ")
    flat = _without_redundant_parentheses(flat)
    if _deepest_allowed(flat, _MAX_BRACKETS):
        # Sure to be refused (below), and a pure-Python tokenize of 100,000 levels to
        # split a long chain would take seconds first.
        raise ExpressionError(_deepest_allowed(flat), f"nesting deeper than {MAX_DEPTH}")
    builder = _TreeBuilder(names, indexing)
    expr = _parse_chain(flat, 0, builder, ("+", "-"))
    if expr.has(sx.zoo, sx.nan, sx.oo, -sx.oo):
        raise ExpressionError(1, "expression is infinite or undefined")
    return expr


def parse_comparison(
    text: str, names: Mapping[str, sx.Expr], indexing: Indexing = NO_INDEXING
) -> tuple[str, sx.Expr, sx.Expr]:
    """Parse one constraint, ``lhs <= rhs``, ``lhs >= rhs`` or ``lhs == rhs``.

    The comparison is found at the top level (outside parentheses); each side is parsed
    by :func:`parse_expression`, with columns counted in the whole text.

    Returns
    -------
    op : str
        ``"<="``, ``">="`` or ``"=="``.
    lhs, rhs : Expr
        The two sides, of the process's engine.

    Raises
    ------
    ExpressionError
        For no comparison, a chained one, ``!=``, a strict ``<`` or ``>``, or a side that
        :func:`parse_expression` refuses.
    """
    if not isinstance(text, str):
        raise ExpressionError(1, f"expected a constraint string, got {type(text).__name__}")
    if len(text) > MAX_EXPRESSION_LENGTH:
        raise ExpressionError(1, f"expression longer than {MAX_EXPRESSION_LENGTH} characters")
    depth, found, index = 0, [], 0
    while index < len(text):
        char = text[index]
        if char in "([{":
            depth += 1
        elif char in ")]}":
            depth -= 1
        elif depth == 0:
            pair = text[index : index + 2]
            if pair in ("<=", ">=", "==", "!="):
                found.append((index, pair))
                index += 2
                continue
            if char in "<>":
                found.append((index, char))
        index += 1
    if not found:
        raise ExpressionError(1, "expected a comparison: lhs <= rhs, lhs >= rhs or lhs == rhs")
    if len(found) > 1:
        raise ExpressionError(
            found[1][0] + 1, "a chained comparison: write one comparison per constraint"
        )
    position, op = found[0]
    if op == "!=":
        raise ExpressionError(position + 1, "!= is not a constraint: use <=, >= or ==")
    if op in ("<", ">"):
        raise ExpressionError(position + 1, f"a strict {op} is not supported: use {op}=")
    lhs = parse_expression(text[:position], names, indexing)
    start = position + len(op)
    try:
        rhs = parse_expression(text[start:], names, indexing)
    except ExpressionError as exc:
        raise ExpressionError(start + exc.column, exc.message) from None
    return op, lhs, rhs


def _parse_piece(text: str, offset: int, builder: _TreeBuilder) -> sx.Expr:
    """Parse ``text``, which starts at column ``offset + 1`` of the expression."""
    try:
        tree = ast.parse(f"({text})", mode="eval")
    except SyntaxError as exc:
        column = max(1, (exc.offset or 2) - 1)
        if "too many nested parentheses" in exc.msg:
            # Python's tokenizer stops at 200 open parentheses, long after MAX_DEPTH:
            # what is left after the redundant ones are gone is nesting, reported where
            # it passes MAX_DEPTH as the tree walk would.
            column = _deepest_allowed(text) or column
            raise ExpressionError(offset + column, f"nesting deeper than {MAX_DEPTH}") from None
        raise ExpressionError(offset + column, f"syntax error: {exc.msg}") from None
    except (RecursionError, MemoryError, ValueError):
        raise ExpressionError(offset + 1, "expression too deeply nested") from None
    try:
        return builder.build(tree.body, 0)
    except RecursionError:
        raise ExpressionError(offset + 1, "expression too deeply nested") from None
    except ExpressionError as exc:
        raise ExpressionError(offset + exc.column, exc.message) from None


def _parse_chain(
    text: str, offset: int, builder: _TreeBuilder, operators: tuple[str, str], depth: int = 0
) -> sx.Expr:
    """Parse ``text``, splitting a long chain of ``operators`` at its top level.

    A sum (``+ -``) or product (``* /``) of thousands of terms is associative, not
    nested: its pieces are parsed one by one and combined in one step, so neither
    Python's parser nor the nesting limit sees a deep tree. Short text takes the
    direct route. ``depth`` counts the parentheses opened on the way here: past
    :data:`MAX_DEPTH` the expression is refused as too deep, as the tree walk would.
    """
    if len(text) < _SPLIT_LENGTH:
        return _parse_piece(text, offset, builder)
    stripped = text.strip()
    if stripped.startswith("(") and _closing(stripped) == len(stripped) - 1:
        # One parenthesized operand: what is inside may be a long chain itself.
        inner = text.index("(") + 1
        if depth >= MAX_DEPTH:
            raise ExpressionError(offset + inner, f"nesting deeper than {MAX_DEPTH}")
        return _parse_chain(
            text[inner : text.rindex(")")], offset + inner, builder, ("+", "-"), depth + 1
        )
    pieces = _split_top_level(text, operators)
    if pieces is None:
        return _parse_piece(text, offset, builder)
    if len(pieces) == 1:
        if operators == ("+", "-"):
            return _parse_chain(text, offset, builder, ("*", "/"), depth)
        return _parse_piece(text, offset, builder)
    values = []
    for operator, start, piece in pieces:
        if operators == ("+", "-"):
            value = _parse_chain(piece, offset + start, builder, ("*", "/"), depth)
            values.append(_distributed(-value) if operator == "-" else value)
        else:
            value = _parse_chain(piece, offset + start, builder, ("+", "-"), depth)
            if operator == "/":
                if _is_zero(value):
                    raise ExpressionError(offset + start + 1, "division by zero")
                value = 1 / value
            values.append(value)
    combined = sx.Add(*values) if operators == ("+", "-") else _distributed(sx.Mul(*values))
    return _bounded(combined, offset + 1)


def _without_redundant_parentheses(text: str) -> str:
    """``text`` with each pair of parentheses that only doubles another blanked out.

    ``((a + b))`` means ``(a + b)``: an inner pair whose opening follows an opening and
    whose closing precedes that opening's closing (spaces aside) adds nothing, and
    Python's tokenizer counts it towards its limit of 200 open parentheses, while the
    recursion of :func:`_parse_chain` spends a frame on it. Three thousand of them
    around ``x`` are ``(x)``. The pairs become spaces, so every column a message names
    stays where the user sees it. One pass with a stack; text whose parentheses do not
    balance, or that holds a quote, is returned as it is for the parser to report.

    A pair holding a comma at its own level stays: ``f((a, b))`` passes one tuple,
    ``f(a, b)`` two arguments, and the parser must see the difference.
    """
    if "((" not in text.replace(" ", "") or "'" in text or '"' in text:
        return text
    closes = {")": "(", "]": "[", "}": "{"}
    # Each open bracket and where it is; a pair's index goes in ``comma`` when a comma
    # sits at its own level, and each "(" gets its ")" in ``closing``.
    stack: list[tuple[str, int]] = []
    closing: dict[int, int] = {}
    comma: set[int] = set()
    for match in _BRACKETS.finditer(text):
        char, index = match.group(), match.start()
        if char == ",":
            if stack:
                comma.add(stack[-1][1])
        elif char in closes:
            if not stack or stack[-1][0] != closes[char]:
                return text
            bracket, start = stack.pop()
            if bracket == "(":
                closing[start] = index
        else:
            stack.append((char, index))
    if stack:
        return text
    blanked = bytearray(text, "ascii")  # ASCII: parse_expression checked it
    for start, end in closing.items():
        outer = start - 1
        while outer >= 0 and text[outer] == " ":
            outer -= 1
        if outer < 0 or text[outer] != "(" or start in comma:
            continue
        after = end + 1
        while after < len(text) and text[after] == " ":
            after += 1
        if closing[outer] == after:
            blanked[start] = blanked[end] = 32  # a space
    return blanked.decode("ascii")


#: The characters :func:`_without_redundant_parentheses` looks at.
_BRACKETS = re.compile(r"[()\[\]{},]")


def _deepest_allowed(text: str, limit: int = MAX_DEPTH) -> int:
    """1-based column of the parenthesis that opens ``limit`` deep, or 0 if none does."""
    depth = 0
    for index, char in enumerate(text):
        if char in "([{":
            depth += 1
            if depth > limit:
                return index + 1
        elif char in ")]}":
            depth -= 1
    return 0


def _closing(text: str) -> int:
    """Index of the parenthesis that closes the one ``text`` starts with (-1: none)."""
    depth = 0
    for index, ch in enumerate(text):
        if ch == "(":
            depth += 1
        elif ch == ")":
            depth -= 1
            if depth == 0:
                return index
    return -1


def _split_top_level(text: str, operators: tuple[str, str]) -> list[tuple[str, int, str]] | None:
    """``(operator, start, piece)`` for each operand of a top-level chain, or None.

    Only binary operators outside parentheses and brackets split (a ``-`` after
    another operator or ``**`` is unary; ``1e-5`` is one token); None when the text
    does not tokenize, which the parser then reports.
    """
    try:
        tokens = list(tokenize.generate_tokens(io.StringIO(text).readline))
    except (tokenize.TokenError, SyntaxError, IndentationError):
        return None
    depth = 0
    pieces: list[tuple[str, int, str]] = []
    start, operator = 0, operators[0]
    previous: tokenize.TokenInfo | None = None
    for token in tokens:
        if token.type == tokenize.OP and token.string in "([{":
            depth += 1
        elif token.type == tokenize.OP and token.string in ")]}":
            depth -= 1
        elif (
            depth == 0
            and token.type == tokenize.OP
            and token.string in operators
            and previous is not None
            and (
                previous.type in (tokenize.NAME, tokenize.NUMBER)
                or (previous.type == tokenize.OP and previous.string in ")]}")
            )
        ):
            column = token.start[1]
            pieces.append((operator, start, text[start:column]))
            start, operator = column + 1, token.string
        if token.type not in (tokenize.NEWLINE, tokenize.NL, tokenize.ENDMARKER):
            previous = token
    pieces.append((operator, start, text[start:]))
    return pieces
