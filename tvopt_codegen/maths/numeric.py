"""Numeric evaluation of expressions (either engine's) over NumPy arrays, without printing code.

The derivation samples expressions at a few dozen points (is a Lie derivative
identically zero? is the Hessian positive definite near the start?). ``lambdify``
prints each expression to Python source and compiles it: for the Hessian of a ring of
32 agents that printing took two seconds, longer than deriving the Hessian. Here the
expression DAG is walked once, every distinct node evaluated once over the whole array
of points (the Hessian's entries share most of their subtrees). Nothing is printed,
nothing executed.
"""

from __future__ import annotations

from collections.abc import Callable, Container, Iterable, Iterator, Mapping, Sequence
from typing import Any

import numpy as np

from tvopt_codegen import symbolic as sx

Array = Any  # a float or complex ndarray, or a Python scalar broadcast against one

#: The NumPy counterparts of the functions by name. Every function a spec may call
#: (parse.FUNCTIONS) and the ones their derivatives introduce (Abs, sign) are here.
_NUMPY: Mapping[str, Callable[..., Array]] = {
    "sin": np.sin,
    "cos": np.cos,
    "tan": np.tan,
    "asin": np.arcsin,
    "acos": np.arccos,
    "atan": np.arctan,
    "atan2": np.arctan2,
    "sinh": np.sinh,
    "cosh": np.cosh,
    "tanh": np.tanh,
    "asinh": np.arcsinh,
    "acosh": np.arccosh,
    "atanh": np.arctanh,
    "exp": np.exp,
    "log": np.log,
    "Abs": np.abs,
    "sign": np.sign,
}

#: The engine's function classes and their NumPy counterparts, per engine: a node is
#: looked up by its class (a user's function named ``sin`` is no sine).
_FUNCTIONS: dict[str, dict[type, Callable[..., Array]]] = {}


def _functions() -> dict[type, Callable[..., Array]]:
    """The engine's function classes and their NumPy counterparts."""
    table = _FUNCTIONS.get(sx.ENGINE)
    if table is None:
        # SymEngine's exp is a function that builds a power, no class: see _operation.
        table = {
            sx.FUNCTIONS[name]: function
            for name, function in _NUMPY.items()
            if isinstance(sx.FUNCTIONS[name], type)
        }
        _FUNCTIONS[sx.ENGINE] = table
    return table


class Evaluator:
    """Evaluates expressions for bound values of their symbols, sharing work across calls.

    Parameters
    ----------
    values : mapping of symbol to array or float
        Values of the free symbols (arrays of one shape, or scalars).

    Notes
    -----
    Results are memoized per node, so evaluating many expressions that share subtrees
    costs the size of their DAG. Out-of-domain points give NaN (or complex values when
    the values are complex), never an exception: callers decide what an undefined
    sample means.
    """

    def __init__(self, values: Mapping[sx.Expr, Array]) -> None:
        self._memo: dict[sx.Expr, Array] = dict(values)
        self._definitions: dict[sx.Expr, sx.Expr] = {}

    def define(self, symbol: sx.Expr, expr: sx.Expr) -> None:
        """Let ``symbol`` stand for ``expr`` (an assignment of a straight-line program).

        Evaluated on first use only: a program's assignments that the requested
        expressions do not need cost nothing.
        """
        self._definitions[symbol] = expr

    def __call__(self, expr: sx.Expr) -> Array:
        """The value of ``expr`` at every point."""
        memo = self._memo
        if expr in memo:
            return memo[expr]
        with np.errstate(all="ignore"):
            for node, defined, children in _post_order(expr, memo, self._definitions):
                if defined is not None:
                    memo[node] = memo[defined]
                else:
                    memo[node] = self._apply(node, [memo[arg] for arg in children])
        return memo[expr]

    @staticmethod
    def _apply(node: sx.Expr, args: list[Array]) -> Array:
        if node.is_Symbol:
            raise ValueError(f"no value for the symbol {node}")
        if node.is_Atom:  # a number, pi, E, I, oo or zoo
            return _constant(node)
        return _operation(node)(*args)


def _post_order(
    expr: sx.Expr, known: Container[sx.Expr], definitions: Mapping[sx.Expr, sx.Expr]
) -> Iterator[tuple[sx.Expr, sx.Expr | None, tuple[sx.Expr, ...]]]:
    """The nodes of ``expr`` not ``known``, each after its arguments, with its definition.

    A symbol that ``definitions`` defines comes after its definition, with it; any other
    node with None and its arguments (read once: SymEngine builds a new tuple of new
    Python objects at each ``.args``). The caller makes each node known before taking
    the next. An explicit stack: a long sum, or a long chain of program assignments,
    nests deeper than Python's recursion limit.
    """
    # (node, None, ()) is a node to expand; (node, definition, children) one expanded.
    expand = None
    stack: list[tuple[sx.Expr, Any, tuple[sx.Expr, ...]]] = [(expr, expand, ())]
    while stack:
        node, defined, children = stack.pop()
        if node in known:
            continue
        if defined is not expand:
            yield node, (None if defined is _NONE else defined), children
            continue
        defined = definitions.get(node) if node.is_Symbol else None
        children = node.args if defined is None else (defined,)
        stack.append((node, _NONE if defined is None else defined, children))
        stack.extend((child, expand, ()) for child in children if child not in known)


#: The definition of a node that has none, once expanded (None marks one to expand).
_NONE = object()


def _operation(node: sx.Expr) -> Callable[..., Array]:
    """The NumPy operation of an expression node that is not an atom, on its args' values."""
    if node.is_Add:
        return _sum
    if node.is_Mul:
        return _product
    if node.is_Pow:
        base, exponent = node.args
        if exponent == sx.Rational(1, 2):
            return _square_root
        # SymEngine's exp(x) is the power E**x: NumPy's exp, as for SymPy's exp.
        return _exponential if sx.SYMENGINE and base == sx.E else _power
    functions = _functions()
    function = functions.get(type(node))
    if function is None and not sx.SYMENGINE:
        function = functions.get(node.func)
    if function is None:
        raise ValueError(f"cannot evaluate {type(node).__name__} numerically")
    return function


def _sum(*args: Array) -> Array:
    return _fold(np.add, args)


def _product(*args: Array) -> Array:
    return _fold(np.multiply, args)


def _power(base: Array, exponent: Array) -> Array:
    return np.power(base, exponent)


def _exponential(_base: Array, exponent: Array) -> Array:
    return np.exp(exponent)


def _square_root(base: Array, _exponent: Array) -> Array:
    # The exponent (1/2) is an argument like any other: evaluated, and not needed.
    return np.sqrt(base)


class Tape:
    """Expressions compiled once into a list of NumPy operations, run for many inputs.

    :class:`Evaluator` walks the expression graph on every call; a Newton search for the
    minimiser evaluates f0 and its derivatives hundreds of times at new points, and the
    walk (hashing nodes, dispatching on their type) cost more than the arithmetic. Here
    the walk is done once: a call runs the operations in order over a list of values,
    the same operations in the same order as :class:`Evaluator`'s, so the results are
    the same bits.

    Parameters
    ----------
    inputs : sequence of symbol
        The symbols whose values each call passes, in this order.
    outputs : sequence of expression
        The expressions each call returns.
    definitions : mapping of symbol to expression
        Symbols that stand for an expression (a program's assignments); only those the
        outputs need are compiled.
    constants : mapping of symbol to array or float
        Values fixed for every call (parameters at their defaults).
    """

    def __init__(
        self,
        inputs: Sequence[sx.Expr],
        outputs: Sequence[sx.Expr],
        definitions: Mapping[sx.Expr, sx.Expr],
        constants: Mapping[sx.Expr, Array],
    ) -> None:
        slot: dict[sx.Expr, int] = {sym: i for i, sym in enumerate(inputs)}
        values: list[Array] = [None] * len(inputs)
        operations: list[tuple[Callable[..., Array], tuple[int, ...], int]] = []
        for sym, value in constants.items():
            if sym not in slot:
                slot[sym] = len(values)
                values.append(value)

        def place(expr: sx.Expr) -> int:
            for node, defined, children in _post_order(expr, slot, definitions):
                if defined is not None:
                    slot[node] = slot[defined]
                elif node.is_Symbol:
                    raise ValueError(f"no value for the symbol {node}")
                elif node.is_Atom:
                    slot[node] = len(values)
                    values.append(_constant(node))
                else:
                    slot[node] = len(values)
                    values.append(None)
                    args = tuple(slot[arg] for arg in children)
                    operations.append((_binary(_operation(node), len(args)), args, slot[node]))
            return slot[expr]

        self._outputs = [place(e) for e in outputs]
        self._size = len(inputs)
        self._values = values
        self._operations = self._scheduled(operations)

    def _scheduled(
        self, operations: Sequence[tuple[Callable[..., Array], tuple[int, ...], int]]
    ) -> list[tuple[Callable[..., Array], tuple[int, ...], int, tuple[int, ...]]]:
        """``operations`` with the slots each frees once it has run."""
        # Each intermediate value is dropped after its last use: a batch of thousands of
        # points keeps only the values still needed, not every node's array at once.
        last: dict[int, int] = {}
        for step, (_, args, _) in enumerate(operations):
            for a in args:
                last[a] = step
        kept = (
            set(self._outputs)
            | set(range(self._size))
            | {i for i, value in enumerate(self._values) if value is not None}
        )
        dead: list[list[int]] = [[] for _ in operations]
        for slot_index, step in last.items():
            if slot_index not in kept:
                dead[step].append(slot_index)
        return [
            (operation, args, out, tuple(dead[step]))
            for step, (operation, args, out) in enumerate(operations)
        ]

    def only(self, indices: Sequence[int]) -> Tape:
        """The tape of the outputs at ``indices`` alone, running only what they need.

        The same operations in the same order, so the same bits, without compiling the
        expressions again (the walk over a team's Hessian is most of a tape's cost).
        """
        tape = Tape.__new__(Tape)
        tape._size, tape._values = self._size, self._values
        tape._outputs = [self._outputs[i] for i in indices]
        needed = set(tape._outputs)
        kept: list[tuple[Callable[..., Array], tuple[int, ...], int]] = []
        for operation, args, out, _ in reversed(self._operations):
            if out in needed:
                kept.append((operation, args, out))
                needed.update(args)
        tape._operations = tape._scheduled(kept[::-1])
        return tape

    def __call__(self, *inputs: Array) -> list[Array]:
        """The outputs' values for the inputs' (arrays of one shape, or scalars)."""
        values = list(self._values)
        values[: self._size] = inputs
        with np.errstate(all="ignore"):
            for operation, args, out, dead in self._operations:
                values[out] = operation(*[values[a] for a in args])
                for slot_index in dead:
                    values[slot_index] = None
        return [values[i] for i in self._outputs]


#: Values of the numbers met so far. An evaluator's memo lives for one batch of points;
#: the numbers recur across batches (a Newton search builds hundreds of evaluators), and
#: ``complex()`` goes through SymPy's evalf each time.
_CONSTANTS: dict[sx.Expr, complex | float] = {}


#: SymEngine's numbers without a ``complex()``, by class, at SymPy's ``complex()`` of them.
_SPECIAL: Mapping[str, complex] = {
    "Infinity": complex(np.inf, 0.0),
    "NegativeInfinity": complex(-np.inf, 0.0),
    "ComplexInfinity": complex(np.nan, np.nan),
    "NaN": complex(np.nan, np.nan),
}


def _constant(node: sx.Expr) -> complex | float:
    value = _CONSTANTS.get(node)
    if value is None:
        special = _SPECIAL.get(type(node).__name__) if sx.SYMENGINE else None
        # SymEngine's infinities and NaN have no complex(): SymPy's values of them.
        number = complex(node) if special is None else special
        value = number.real if number.imag == 0 else number
        _CONSTANTS[node] = value
    return value


def _binary(operation: Callable[..., Array], count: int) -> Callable[..., Array]:
    """NumPy's own ufunc for a sum or product of two: the fold's one step, without it."""
    if count == 2 and operation is _sum:
        return np.add
    if count == 2 and operation is _product:
        return np.multiply
    return operation


def _fold(op: Callable[[Array, Array], Array], args: Iterable[Array]) -> Array:
    items = iter(args)
    total = next(items)
    for item in items:
        total = op(total, item)
    return total
