"""One symbolic API over two engines: SymEngine (fast) and SymPy (the reference).

Every stage from the model to the printers builds and reads expressions through this
module (``from tvopt_codegen import symbolic as sx``): its classes (``sx.Symbol``,
``sx.Add``, ...), its functions (``sx.sin``, ``sx.diff``, ...) and its helpers below
are those of the process's engine, chosen once (:mod:`tvopt_codegen.symbolic.engine`).
Code written against it works on both engines as long as it reads the names when it
runs (``sx.sin(x)``; never ``from tvopt_codegen.symbolic import sin``, nor an expression
built at import time: :func:`using` switches engines within a process for the tests)
and keeps to

* the names defined here, and
* what both engines' expressions answer to: ``.args``, ``.func(*args)`` (for a node
  that is not an atom), ``.free_symbols``, ``.xreplace``, ``.subs``, ``.diff``,
  ``.expand``, arithmetic, and the ``is_Add``, ``is_Mul``, ``is_Pow``, ``is_Symbol``,
  ``is_Number``, ``is_Integer``, ``is_Rational``, ``is_Float``, ``is_Function``,
  ``is_Atom``, ``is_zero``, ``is_negative`` flags.

What only SymPy does (simplification, factoring, LaTeX and MathML, SymPy mechanics) is
the border (:mod:`tvopt_codegen.symbolic.border`): applied to the few small expressions
that decide something or are shown, converted there and back, never to the whole law.

Adding an operation: define it here for both engines (one line each when the two agree,
a function when they differ), with a test in ``tests/test_symbolic.py`` that runs it on
both engines and compares the values.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterable, Iterator, Sequence
from typing import Any

from tvopt_codegen.symbolic import engine as _engine

# Expressions are typed Any: the two engines' classes share no static type, and sympy's
# own annotations do not cover its constructors' results.
Expr = Any

#: The names every engine binds here under the same spelling.
_SAME = (
    "Symbol Integer Rational Number Float Add Mul Pow Piecewise Derivative Function Basic "
    "MatrixBase ImmutableMatrix Matrix Max Min Abs sign sqrt exp log sin cos tan cot sec "
    "csc asin acos atan atan2 sinh cosh tanh coth sech csch asinh acosh atanh pi E I oo "
    "zoo nan diff expand zeros eye sympify"
).split()
#: The elementary functions by the name both engines and the spec language give them.
_FUNCTION_NAMES = (
    "sin cos tan cot sec csc asin acos atan atan2 sinh cosh tanh coth sech csch "
    "asinh acosh atanh exp log sqrt Abs sign Max Min"
).split()

# Bound by _bind: the process's engine and its names (declared for the type checker).
ENGINE: str = ""
SYMENGINE: bool = False
_m: Any = None
Symbol: Any
Integer: Any
Rational: Any
Number: Any
#: The engine's real floating-point number class (SymEngine's ``RealDouble``).
Float: Any
Add: Any
Mul: Any
Pow: Any
Piecewise: Any
Derivative: Any
Function: Any
Basic: Any
MatrixBase: Any
ImmutableMatrix: Any
Matrix: Any
Max: Any
Min: Any
Abs: Any
sign: Any
sqrt: Any
exp: Any
log: Any
sin: Any
cos: Any
tan: Any
cot: Any
sec: Any
csc: Any
asin: Any
acos: Any
atan: Any
atan2: Any
sinh: Any
cosh: Any
tanh: Any
coth: Any
sech: Any
csch: Any
asinh: Any
acosh: Any
atanh: Any
pi: Any
E: Any
I: Any  # noqa: E741 - the engines' own name for the imaginary unit
oo: Any
zoo: Any
nan: Any
diff: Any
expand: Any
zeros: Any
eye: Any
sympify: Any
#: Zero and one of the engine.
ZERO: Any
ONE: Any
#: The elementary functions by name.
FUNCTIONS: dict[str, Any] = {}


def _bind(name: str) -> None:
    """Bind this module's names to engine ``name``'s."""
    global ENGINE, SYMENGINE, _m, ZERO, ONE  # noqa: PLW0603 - the API is the module's names
    # Only the chosen engine is imported: SymPy's import alone is 0.5-1.3 s.
    if name == "symengine":
        import symengine as module  # noqa: PLC0415
    else:
        import sympy as module  # noqa: PLC0415
    ENGINE, SYMENGINE, _m = name, name == "symengine", module
    names = globals()
    for attribute in _SAME:
        names[attribute] = getattr(module, attribute)
    ZERO, ONE = module.Integer(0), module.Integer(1)
    FUNCTIONS.clear()
    FUNCTIONS.update((n, getattr(module, n)) for n in _FUNCTION_NAMES)


_bind(_engine.current())


@contextlib.contextmanager
def using(name: str) -> Iterator[None]:
    """Run a block on engine ``name``, then return to the process's engine.

    The command line's ``--engine`` runs its command in this block (so that a caller
    that runs several commands in one process, as the tests do, gets its engine back),
    and the tests compare the two engines with it.

    Only code that reads this module's names when it runs (``sx.sin``, never a copy
    taken at import) follows the switch, as every stage does.
    """
    before = ENGINE
    _bind(_engine.checked(name, "--engine"))
    try:
        yield
    finally:
        _bind(before)


def symbol(name: str) -> Any:
    """A real symbol named ``name`` (SymPy's ``real=True``; SymEngine has no assumptions)."""
    if SYMENGINE:
        return _m.Symbol(name)
    return _m.Symbol(name, real=True)


def symbols(names: Iterable[str]) -> list[Any]:
    """Real symbols, one per name, in order."""
    return [symbol(name) for name in names]


def real(value: float) -> Any:
    """The double ``value`` as the engine's exact float (no decimal rounding)."""
    if SYMENGINE:
        return _m.RealDouble(float(value))
    return _m.Float(float(value))


def is_piecewise(expr: Any) -> bool:
    """Whether ``expr`` is a ``Piecewise``."""
    return isinstance(expr, _m.Piecewise)


def piecewise_pairs(expr: Any) -> list[tuple[Any, Any]]:
    """A ``Piecewise``'s ``(value, condition)`` pairs, in order, on either engine.

    SymPy's arguments are the pairs; SymEngine's are the values and conditions
    alternating.
    """
    if SYMENGINE:
        args = expr.args
        return [(args[i], args[i + 1]) for i in range(0, len(args), 2)]
    return [(pair.expr, pair.cond) for pair in expr.args]


def function_name(expr: Any) -> str:
    """The name of an applied function (``sin``, ``atan2``, a user's ``f``)."""
    if SYMENGINE and isinstance(expr, _m.FunctionSymbol):
        return str(expr.get_name())
    if not SYMENGINE:
        return str(expr.func.__name__)
    return type(expr).__name__


def matrix(rows: Sequence[Sequence[Any]]) -> Any:
    """An immutable matrix of the engine, from nested rows (0 x 0 when there are none)."""
    return _m.ImmutableMatrix(rows) if rows else _m.ImmutableMatrix(_m.zeros(0, 0))


def is_polynomial(expr: Any, symbols: Iterable[Any]) -> bool:
    """Whether ``expr`` is a polynomial in ``symbols``, as written (SymPy's ``is_polynomial``).

    Nothing is simplified: ``(y**2 - 1)/(y - 1)`` is not one. A sum or product of
    polynomials is, and a power of one to a nonnegative integer; a function of the
    symbols, or a power with them in its exponent, is not.
    """
    if not SYMENGINE:
        return bool(expr.is_polynomial(*symbols))
    return _polynomial(expr, frozenset(symbols), {})


def _polynomial(node: Any, symbols: frozenset[Any], memo: dict[Any, bool]) -> bool:
    done = memo.get(node)
    if done is not None:
        return done
    if not symbols & node.free_symbols or node.is_Symbol:
        out = True
    elif node.is_Add or node.is_Mul:
        out = all(_polynomial(arg, symbols, memo) for arg in node.args)
    elif node.is_Pow:
        base, exponent = node.args
        out = bool(
            not symbols & exponent.free_symbols
            and exponent.is_Integer
            and exponent >= 0
            and _polynomial(base, symbols, memo)
        )
    else:
        out = False
    memo[node] = out
    return out


def cse(exprs: Sequence[Any], names: Iterator[Any]) -> tuple[list[tuple[Any, Any]], list[Any]]:
    """Common subexpressions of ``exprs``, sums' and products' common parts included.

    Returns ``(replacements, reduced)`` as ``sympy.cse`` (``order="canonical"``): each
    replacement ``(name, value)`` uses only earlier names, the names drawn from
    ``names`` in order, skipping symbols ``exprs`` already hold. SymEngine's (in C++)
    names its own and is renamed here; the two find comparable, not identical, sets.
    """
    if not SYMENGINE:
        replacements, reduced = _m.cse(list(exprs), symbols=names, order="canonical")
        return list(replacements), list(reduced)
    replacements, reduced = _m.cse(list(exprs))
    if not replacements:
        return [], list(reduced)
    taken = set().union(*(expr.free_symbols for expr in exprs))
    rename: dict[Any, Any] = {}
    for sym, _ in replacements:
        name = next(names)
        while name in taken:
            name = next(names)
        rename[sym] = name
    renamed = [(rename[sym], value.xreplace(rename)) for sym, value in replacements]
    return renamed, [expr.xreplace(rename) for expr in reduced]


def engine_version() -> str:
    """The engine and its version, as the file stamp names them (``sympy 1.14.0``).

    Read from the engine's module, imported already (``symengine.__version__`` is what
    its metadata says): the stamp of a SymEngine run imports no SymPy, and no
    ``importlib.metadata`` (0.03 s of a cold command).
    """
    return f"{ENGINE} {_m.__version__}"


def as_expr(value: Any) -> Any:
    """``value`` as an expression of the engine (a Python number converted, else as is)."""
    return value if isinstance(value, _m.Basic) else _m.sympify(value)


def tree_size(expr: Any, limit: int, args: Sequence[Any] | None = None) -> int:
    """Nodes of ``expr``'s tree, counting at most ``limit + 1`` (so the count is cheap).

    A plain stack: sympy's ``preorder_traversal`` costs a generator step per node, and
    the budget meter sizes every expression the derivation builds. ``args`` are
    ``expr``'s arguments when the caller has read them already (each SymEngine ``.args``
    builds new Python objects).
    """
    if limit < 1:
        return 1
    stack = list(expr.args if args is None else args)
    pop, push = stack.pop, stack.extend
    count = 1
    while stack:
        count += 1
        if count > limit:
            break
        push(pop().args)
    return count


def text(expr: Any) -> str:
    """``expr`` as one line of text in the spec language's spelling (``x**2``, ``sin(x)``)."""
    if SYMENGINE:
        return str(expr)
    return str(_m.sstr(expr))


def sort_key(expr: Any) -> tuple[str, str]:
    """A total order of expressions that is the same in every run (no hash in it)."""
    return (type(expr).__name__, text(expr))


def lambdify(args: Any, exprs: Any, modules: Any = None) -> Any:
    """A numeric function computing ``exprs`` from the symbols ``args``.

    ``args`` is a symbol, or a list of one symbol or list of symbols per positional
    argument. SymPy's ``lambdify`` (``modules`` as it takes them) on SymPy; on SymEngine its
    compiled ``Lambdify``, called the same way: a number per symbol, a sequence per
    list (NumPy arrays broadcast together); a float for one expression, else an array
    of the shape of ``exprs`` (a list, nested rows or a matrix), after the broadcast
    shape. Where SymPy's ``math`` functions raise (``log(-1)``) SymEngine's give NaN.
    """
    if not SYMENGINE:
        return _m.lambdify(args, exprs, modules)
    return _Lambdified(args, exprs)


class _Lambdified:
    """SymEngine's ``Lambdify`` behind SymPy's ``lambdify``'s calling convention."""

    def __init__(self, args: Any, exprs: Any) -> None:
        self._lists = [isinstance(a, list | tuple) for a in _arguments(args)]
        flat = [
            s for a in _arguments(args) for s in (_flat(a) if isinstance(a, list | tuple) else [a])
        ]
        if isinstance(exprs, _m.MatrixBase):
            exprs = exprs.tolist()
        self._shape = _shape(exprs)
        values = _flat(exprs) if self._shape else [exprs]
        self._function = _m.Lambdify(flat, values, real=True) if values else None
        # Per argument: None for a symbol, its length for a flat list, -1 for nested lists.
        self._sizes: list[int | None] = []
        for a, is_list in zip(_arguments(args), self._lists, strict=True):
            nested = is_list and any(isinstance(s, list | tuple) for s in a)
            self._sizes.append(None if not is_list else -1 if nested else len(a))

    def __call__(self, *values: Any) -> Any:
        import numpy as np  # noqa: PLC0415 - loaded with SymEngine already

        vector = self._vector(values, np)
        if vector is not None and self._function is not None:
            # One point of plain numbers: the general path's flattening and broadcasting
            # were four fifths of a call (a solver calls it thousands of times).
            out = np.asarray(self._function(vector), dtype=float).reshape(self._shape)
            return float(out) if not out.shape else out
        point: list[Any] = []
        for given, size in zip(values, self._sizes, strict=True):
            if size is None:
                point.append(given)
            elif size == -1:
                point.extend(_flat(list(given)))
            else:
                # A flat list's entries, each a number or a batch of them (its rows when
                # the argument is an array of shape (size, ...)): not flattened further.
                point.extend(list(given))
        if any(np.ndim(v) for v in point):
            inputs = np.stack(np.broadcast_arrays(*[np.asarray(v, dtype=float) for v in point]), -1)
        else:
            inputs = np.array(point, dtype=float)
        batch = inputs.shape[:-1]
        if self._function is None:
            return np.zeros((*batch, *self._shape))
        out = np.asarray(self._function(inputs), dtype=float).reshape((*batch, *self._shape))
        return float(out) if not out.shape else out

    def _vector(self, values: Any, np: Any) -> Any:
        """The point as one vector when each value is a number or a flat vector of them."""
        parts = []
        for given, size in zip(values, self._sizes, strict=True):
            if size is None:
                if not isinstance(given, float | int):
                    return None
                parts.append((given,))
            else:
                try:
                    array = np.asarray(given, dtype=float)
                except (TypeError, ValueError):
                    return None
                if array.shape != (size,):
                    return None
                parts.append(array)
        return np.concatenate(parts, dtype=float) if parts else None


def _arguments(args: Any) -> list[Any]:
    return list(args) if isinstance(args, list | tuple) else [args]


def _flat(items: Any) -> list[Any]:
    """The leaves of nested lists (or arrays), in row-major order."""
    out: list[Any] = []
    for item in items:
        dimensions: int = getattr(item, "ndim", 0)
        if isinstance(item, list | tuple) or dimensions:
            out.extend(_flat(item))
        else:
            out.append(item)
    return out


def _shape(exprs: Any) -> tuple[int, ...]:
    """The shape of nested lists of expressions (``()`` for one expression)."""
    if not isinstance(exprs, list | tuple):
        return ()
    return (len(exprs), *(_shape(exprs[0]) if exprs else ()))


__all__ = [
    "ENGINE",
    "Expr",
    "FUNCTIONS",
    "ONE",
    "SYMENGINE",
    "ZERO",
    "as_expr",
    "engine_version",
    "cse",
    "function_name",
    "is_polynomial",
    "is_piecewise",
    "lambdify",
    "matrix",
    "piecewise_pairs",
    "real",
    "sort_key",
    "symbol",
    "symbols",
    "text",
    "tree_size",
    "using",
]
