"""What the spec language can say, checked as the project's reader checks it.

Names, numbers and expressions that :func:`~tvopt_codegen.mechanics.spec_from_sympy`
takes from SymPy are checked here, node by node and without recursion: a function the
spec language lacks, the imaginary unit, an infinity, nesting deeper than the reader
takes or an expression too large to print is one :class:`~tvopt_codegen.errors.SpecError`
naming the field. The reciprocal functions (``sec``, ``cot``, ...) are rewritten as the
quotients the language has.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Callable, Mapping

import numpy as np
import sympy as sp

from tvopt_codegen.errors import SpecError, clip, one_line
from tvopt_codegen.spec.names import name_problem
from tvopt_codegen.spec.parse import FUNCTIONS, MAX_DEPTH

#: What errors of :func:`~tvopt_codegen.mechanics.spec_from_sympy` name as their source.
SOURCE_SYMPY = "spec_from_sympy"

#: Most nodes (counted as a tree) one expression may print: the reader takes at most
#: 1,000,000 characters, and an expression sharing subtrees can print exponentially long.
MAX_NODES = 200_000

#: Functions the spec language lacks that are exactly quotients of ones it has.
_RECIPROCALS: tuple[tuple[type[sp.Function], Callable[[sp.Expr], sp.Expr]], ...] = (
    (sp.sec, lambda a: 1 / sp.cos(a)),
    (sp.csc, lambda a: 1 / sp.sin(a)),
    (sp.cot, lambda a: sp.cos(a) / sp.sin(a)),
    (sp.sech, lambda a: 1 / sp.cosh(a)),
    (sp.csch, lambda a: 1 / sp.sinh(a)),
    (sp.coth, lambda a: sp.cosh(a) / sp.sinh(a)),
)

#: The sympy classes of the spec language's functions (sqrt is a power in sympy): SymPy's
#: whatever the engine, as what this module checks comes from SymPy.
_ALLOWED_CLASSES = frozenset(
    getattr(sp, name) for name in FUNCTIONS if isinstance(getattr(sp, name), type)
)
_ALLOWED_TEXT = ", ".join(sorted(FUNCTIONS))


def _fail(field: str, problem: str) -> SpecError:
    # A name may hold a newline: the message stays one line.
    return SpecError(SOURCE_SYMPY, one_line(field), one_line(problem))


def _symbol_name(symbol: object) -> str:
    """A dynamic symbol's, a symbol's or a string's name."""
    if isinstance(symbol, sp.core.function.AppliedUndef):
        return str(symbol.func.__name__)
    if isinstance(symbol, sp.Symbol):
        return str(symbol.name)
    return symbol if isinstance(symbol, str) else repr(symbol)


def _name(symbol: object, field: str) -> str:
    """A dynamic symbol's or a symbol's name, checked as the spec reader checks names."""
    name = _symbol_name(symbol)
    problem = name_problem(name)
    if problem:
        raise _fail(field, problem)
    return name


def _number(value: object, field: str) -> float:
    """A finite real number from a Python, NumPy or SymPy number; else one SpecError."""
    if isinstance(value, bool | np.bool_) or value is None or isinstance(value, str):
        raise _fail(field, f"expected a number, got {type(value).__name__} {clip(repr(value))}")
    if isinstance(value, sp.Basic):
        if not value.is_number or not value.is_real:
            raise _fail(field, f"expected a real number, got {clip(sp.sstr(value))}")
    elif not isinstance(value, numbers.Real):
        raise _fail(field, f"expected a number, got {type(value).__name__}")
    try:
        result = float(value)
    except (TypeError, ValueError, OverflowError) as exc:
        raise _fail(field, f"expected a real number ({exc})") from None
    if not math.isfinite(result):
        raise _fail(field, f"expected a finite number, got {result}")
    return result


def _refusal(node: sp.Basic) -> str | None:
    """Why the spec language cannot say ``node`` (one node, not its arguments), or None."""
    if isinstance(node, sp.Symbol | sp.Rational | sp.Add | sp.Mul | sp.Pow):
        return None
    if node is sp.pi or node is sp.E:
        return None
    if isinstance(node, sp.Float):
        # sympy's floats reach 1e400 and beyond; the spec's numbers are doubles.
        finite = node.is_finite and math.isfinite(float(node))
        return None if finite else f"holds the number {clip(str(node))}, which no double holds"
    if node is sp.I or isinstance(node, sp.core.numbers.ImaginaryUnit):
        return "holds the imaginary unit I (spec expressions are real)"
    if node in (sp.zoo, sp.oo, sp.S.NegativeInfinity, sp.nan):
        return f"holds {node}, which is infinite or undefined"
    if isinstance(node, sp.AccumBounds):
        # sympy's value of a function at an infinity (atan(zoo), sin(oo)): a range.
        return f"holds {clip(sp.sstr(node))}, a range from an infinite or undefined argument"
    if isinstance(node, sp.NumberSymbol):
        return f"holds the constant {node}, which the spec language lacks (it has pi)"
    if isinstance(node, sp.Derivative):
        return f"holds the derivative {clip(sp.sstr(node))}"
    if isinstance(node, sp.core.function.AppliedUndef):
        return (
            f"holds {clip(sp.sstr(node))}, which is neither a coordinate, a rate nor an input "
            "(dynamic symbols are functions of t alone)"
        )
    if type(node) in _ALLOWED_CLASSES:
        return None
    name = type(node).__name__
    if not isinstance(node, sp.Function):
        return f"{name} is not part of the spec language (+ - * / **, pi, {_ALLOWED_TEXT})"
    return (
        f"{name} is not a function of the spec language (its functions are smooth: "
        f"{_ALLOWED_TEXT}); write the model without it"
    )


def _check_depth(expr: object, field: str) -> None:
    """Nesting within the reader's limit, checked before any recursive sympy operation.

    By object identity, without hashing: hashing a node hashes its arguments, and a tree
    thousands deep would exhaust Python's recursion there.
    """
    if not isinstance(expr, sp.Basic):
        return
    deepest: dict[int, int] = {}
    stack = [(expr, 1)]
    while stack:
        node, depth = stack.pop()
        if depth > MAX_DEPTH:
            raise _fail(field, f"the expression nests deeper than {MAX_DEPTH} operations")
        if deepest.get(id(node), 0) >= depth:
            continue
        deepest[id(node)] = depth
        stack.extend((a, depth + 1) for a in node.args)


def _check_tree(expr: sp.Basic, field: str) -> None:
    """Every node sayable, nesting and printed size bounded; iterative (no recursion)."""
    depth: dict[sp.Basic, int] = {}
    size: dict[sp.Basic, int] = {}
    stack: list[tuple[sp.Basic, bool]] = [(expr, False)]
    while stack:
        node, done = stack.pop()
        if node in depth:
            continue
        if done:
            depth[node] = 1 + max((depth[a] for a in node.args), default=0)
            size[node] = 1 + sum(size[a] for a in node.args)
            if depth[node] > MAX_DEPTH:
                raise _fail(field, f"the expression nests deeper than {MAX_DEPTH} operations")
            if size[node] > MAX_NODES:
                raise _fail(
                    field, f"the expression is larger than {MAX_NODES} operations written out"
                )
            continue
        problem = _refusal(node)
        if problem:
            raise _fail(field, problem)
        stack.append((node, True))
        stack.extend((a, False) for a in node.args if a not in depth)


def _sayable(expr: object, field: str) -> sp.Expr:
    """``expr`` as a sympy expression the spec language can say (reciprocal trig rewritten)."""
    if isinstance(expr, bool | np.bool_) or expr is None:
        raise _fail(field, f"expected an expression, got {type(expr).__name__}")
    if isinstance(expr, int | np.integer):
        expr = sp.Integer(int(expr))
    elif isinstance(expr, numbers.Real) and not isinstance(expr, sp.Basic):
        expr = sp.Float(_number(expr, field))
    try:
        value = sp.sympify(expr, strict=True)
    except (sp.SympifyError, TypeError, ValueError):
        raise _fail(field, f"expected a sympy expression, got {type(expr).__name__}") from None
    if not isinstance(value, sp.Expr):
        raise _fail(field, f"{type(value).__name__} is not an expression the spec can hold")
    for kind, rewrite in _RECIPROCALS:
        if value.has(kind):
            value = value.replace(kind, rewrite)
    _check_tree(value, field)
    return value


def _check_depths(
    mass: sp.Matrix, forcing: sp.Matrix, outputs: object, objective: object, signals: object
) -> None:
    """Every expression given nests within the reader's limit, before sympy recurses in it.

    Parameters
    ----------
    mass, forcing : sympy.Matrix
        ``M`` and the forcing, as SymPy mechanics formed them.
    outputs, signals : object
        The outputs and the signals as given: a mapping's values are checked, anything
        else is refused later, by name.
    objective : object
        ``f0`` as given.

    Raises
    ------
    SpecError
        Naming the first field, in that order, that nests deeper than ``MAX_DEPTH``.
    """
    for i in range(mass.rows):
        for j in range(mass.cols):
            _check_depth(mass[i, j], f"system.mechanics.mass_matrix[{i}][{j}]")
    for i, entry in enumerate(forcing):
        _check_depth(entry, f"system.mechanics.forces[{i}]")
    if isinstance(outputs, Mapping):
        for key, value in outputs.items():
            _check_depth(value, f"system.outputs.{key}")
    _check_depth(objective, "objective.f0")
    if isinstance(signals, Mapping):
        for key, value in signals.items():
            _check_depth(value, f"signals.{key}")
