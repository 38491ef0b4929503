"""SymPy's order of the arguments of a sum or a product, on either engine.

SymEngine orders arguments by its C++ hashes: the same in every run, but not SymPy's.
What writes text a reader or a golden file sees in SymPy's order (the printers, the
conditions where R or p is undefined) sorts a SymEngine node's arguments by
:func:`canonical_key`, which needs no SymPy.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

from tvopt_codegen import symbolic as sx

__all__ = ["canonical_key", "sympy_ordered"]


#: SymPy's order of node classes (``sympy.core.basic.ordering_of_classes``) for those a
#: kernel holds; the others (the functions, named in lower case) follow, by name.
_CLASS_ORDER = {
    name: rank
    for rank, name in enumerate(
        "Zero One Half Infinity NaN NegativeOne NegativeInfinity Integer Rational Float "
        "Exp1 Pi ImaginaryUnit Symbol Wild Pow Mul Add Derivative Integral".split()
    )
}
_POW, _E = _CLASS_ORDER["Pow"], _CLASS_ORDER["Exp1"]
#: SymEngine's names of classes SymPy names otherwise.
_SYMPY_NAMES = {"RealDouble": "Float"}


def canonical_key(
    expr: Any, key: Callable[[Any], tuple[Any, ...]], args: Sequence[Any] | None = None
) -> tuple[Any, ...]:
    """The place of ``expr`` in SymPy's order of the arguments of a sum or a product.

    SymPy sorts them by ``Basic.compare``: the class (by its rank in SymPy's list of
    classes, else by name), then the number of its parts, then the parts in turn (a
    symbol's name, a number's value, a node's arguments, those of a sum or a product
    sorted). ``key`` gives the key of an argument (a memoised call of this function).
    ``args`` are ``expr``'s arguments as ``key`` takes them (by default ``expr.args``): a
    caller that keeps its own record of each argument passes those, so that neither the
    arguments (new Python objects at each SymEngine ``.args``) nor their records are
    looked up again.
    """
    name = type(expr).__name__
    name = _SYMPY_NAMES.get(name, name)
    rank = _CLASS_ORDER.get(name, len(_CLASS_ORDER))
    parts: tuple[Any, ...]
    if sx.SYMENGINE:
        # Two nodes SymPy names otherwise: SymEngine's exp(x) is the power E**x, SymPy's
        # the function exp (after sums and products among a node's arguments); a user's
        # applied function is a FunctionSymbol, in SymPy of the class of its name. E is
        # the one node of its rank: its key tells.
        if rank == _POW:
            if args is None:
                args = expr.args
            base = key(args[0])
            if base[0] == _E:
                return (len(_CLASS_ORDER), "exp", 1, key(args[1]))
            return (rank, "", 2, base, key(args[1]))
        if name == "FunctionSymbol":
            parts = tuple(key(arg) for arg in (expr.args if args is None else args))
            return (len(_CLASS_ORDER), sx.function_name(expr), len(parts), *parts)
    if expr.is_Symbol:
        parts = (expr.name,)
    elif expr.is_Rational:
        parts = (int(expr.p),) if expr.is_Integer else (int(expr.p), int(expr.q))
    elif expr.is_Float:
        from mpmath.libmp import from_float  # noqa: PLC0415 - only a float needs it

        parts = (from_float(float(expr)), 53)  # SymPy's Float: its mpf and precision
    elif expr.is_Add or expr.is_Mul:
        parts = tuple(sorted(key(arg) for arg in (expr.args if args is None else args)))
    else:
        parts = tuple(key(arg) for arg in (expr.args if args is None else args))
    return (rank, name if rank == len(_CLASS_ORDER) else "", len(parts), *parts)


def sympy_ordered(args: Sequence[Any], keys: dict[Any, tuple[Any, ...]] | None = None) -> list[Any]:
    """``args`` in the order SymPy keeps them (as they are on SymPy).

    ``keys`` memoises the nodes' keys across calls over one expression.
    """
    if not sx.SYMENGINE or len(args) < 2:
        return list(args)
    known: dict[Any, tuple[Any, ...]] = {} if keys is None else keys

    def key(expr: Any) -> tuple[Any, ...]:
        found = known.get(expr)
        if found is None:
            found = known[expr] = canonical_key(expr, key)
        return found

    return sorted(args, key=key)
