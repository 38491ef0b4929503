"""Tree rewriting that keeps the engine's canonical form.

Operation counts, free symbols, substitution by splicing, and odd functions of mirrored
arguments merged (:func:`canonical_odd`), on either engine of :mod:`tvopt_codegen.symbolic`.
On SymPy, rebuilding a node is the expensive part, and :func:`_rebuild` avoids its
constructors where they would find nothing to do; SymEngine's cost a microsecond and are
called as they are.
"""

from __future__ import annotations

import functools
import operator
from collections.abc import Callable, Iterable, Mapping, Sequence
from typing import Any

from tvopt_codegen import symbolic as sx
from tvopt_codegen.maths.jet import release


def _expr(value: Any) -> sx.Expr:
    """``value`` as an expression: numbers the callers pass as Python ints converted."""
    return value if isinstance(value, sx.Basic) else sx.sympify(value)


def _same() -> Callable[[Any, Any], bool]:
    """How a walk tells a node's rebuilt argument from its own: ``is`` on SymPy.

    SymEngine hands out a new Python object for each argument on every ``.args``: an
    argument left alone is equal to the node's, not the same object. Its ``==`` checks
    the C++ pointers first, so that comparison costs no walk.
    """
    return operator.eq if sx.SYMENGINE else operator.is_


def _unchanged(
    same: Callable[[Any, Any], bool], old: Sequence[sx.Expr], new: Sequence[sx.Expr]
) -> bool:
    """Whether ``new`` are ``old`` (a node's arguments), by ``same`` (:func:`_same`)."""
    return len(new) == len(old) and all(map(same, new, old))


def operation_count(exprs: Iterable[sx.Expr], memo: dict[sx.Expr, int] | None = None) -> int:
    """Count the arithmetic operations and function calls that printing ``exprs`` costs.

    A sum or product of ``n`` terms is ``n - 1`` operations (a factor ``-1`` is the
    negation, or nothing in a sum, where it makes the subtraction; a factor ``b**-1`` is
    the division), every other power and every function call one, a negative or
    fractional literal one. Expressions are counted as trees, like sympy's
    ``count_ops``, but in one memoized pass: linear in the size of the DAG, where
    ``count_ops`` walks each expression anew. ``memo`` (a node -> the operations below
    it) may span calls over the same nodes (the kernels cut from one program).
    """
    below: dict[sx.Expr, int] = {} if memo is None else memo

    minus_one = _minus_one()

    # Each takes the node's arguments, fetched once: SymEngine builds them anew on every
    # .args, and a node's were asked for three times.
    def own(node: sx.Expr, parent: str, args: Sequence[sx.Expr]) -> int:
        if node.is_Number:
            if parent == "mul":
                return 0
            return int(node.is_negative is True) + int(node.is_Rational and not node.is_Integer)
        if node.is_Atom:
            return 0
        if node.is_Add:
            return len(args) - 1
        if node.is_Mul:
            first = args[0]
            negated = parent == "add" and first.is_Number and first.is_negative
            return len(args) - 1 - int(bool(negated) and first == minus_one)
        if node.is_Pow and args[1] == minus_one:
            return 0 if parent == "mul" else 1
        return 1

    def count(node: sx.Expr, args: Sequence[sx.Expr]) -> int:
        # A node's own operations depend on its parent's kind; those of its subtree
        # do not, and are what the memo keeps. Leaves have no subtree, and symbols cost
        # nothing: only numbers among them are looked at (half the calls were symbols).
        total = below.get(node)
        if total is None:
            kind = "mul" if node.is_Mul else "add" if node.is_Add else ""
            total = 0
            for arg in args:
                sub = arg.args
                if sub:
                    total += own(arg, kind, sub) + count(arg, sub)
                elif arg.is_Number:
                    total += own(arg, kind, sub)
            below[node] = total
        return total

    total = 0
    for e in exprs:
        node = _expr(e)
        args = node.args
        total += own(node, "", args) + count(node, args)
    release(count)
    return total


def symbols_in(exprs: Iterable[sx.Expr]) -> set[sx.Expr]:
    """The symbols of all ``exprs``, each distinct subtree visited once.

    ``free_symbols`` builds a set at every node of every tree, anew for each
    expression; a kernel's expressions share most of their subtrees. SymEngine's is
    one walk in C++ over them all, packed as one function's arguments (_replace_all).
    """
    stack = [_expr(e) for e in exprs]
    if sx.SYMENGINE:
        return set(sx.Function("_cse_pack")(*stack).free_symbols) if stack else set()
    seen: set[sx.Expr] = set()
    found: set[sx.Expr] = set()
    while stack:
        node = stack.pop()
        if node in seen:
            continue
        seen.add(node)
        args = node.args
        if args:
            stack.extend(args)
        elif node.is_Symbol:
            found.add(node)
    return found


@functools.cache
def _canonical() -> Any:
    """The canonical order of a sum's terms or a product's factors: SymPy's own.

    ``Add.flatten`` and ``Mul.flatten`` sort with ``Basic.compare``; only SymPy's
    rebuilding (:func:`_sorted_args`) asks, so only SymPy's is ever kept here.
    """
    return functools.cmp_to_key(sx.Basic.compare)


def _sorted_args(node: sx.Expr, args: Sequence[sx.Expr]) -> sx.Expr | None:
    """``Add(*args)`` or ``Mul(*args)`` without ``flatten``, when nothing would combine.

    Substitution mostly renames (a state symbol for its slot, a temporary for its final
    name) or puts a temporary's value in its one use: a sum or product then needs its
    nested sums or products spliced in, its numbers folded into one coefficient and its
    terms put back in canonical order, while ``flatten``'s search for things to combine
    (sympy's most expensive constructor, half of lowering's time) finds nothing. This
    does just that, in ``flatten``'s order (numbers folded as met, spliced arguments
    last, so a Float coefficient has the same bits), and returns None whenever
    ``flatten`` could do more: two terms alike (``x + 2*x``) or factors of one base
    (``x*x**2``, ``exp(a)*exp(b)``), a power of a constant or to a sum (``2**x``,
    ``exp(b + 1)``), a zero product, a
    coefficient beside a sum in a product (which ``flatten`` may distribute), or a term
    that is a product holding a product (which ``flatten`` rebuilds). The result is then
    the very object ``flatten`` would build. SymPy only.
    """
    is_add = node.is_Add
    seq = list(args)
    coefficient: sx.Expr = sx.ZERO if is_add else sx.ONE
    seen: set[sx.Expr] = set()
    rest: list[sx.Expr] = []
    has_sum = False
    for arg in seq:  # grows while iterating: spliced arguments come last, as in flatten
        if arg.is_Number:
            if not arg.is_finite:
                return None
            coefficient = coefficient + arg if is_add else coefficient * arg
            continue
        if not arg.is_commutative or arg is sx.zoo:
            return None  # zoo is no Number, and absorbs every term as flatten builds it
        if arg.is_Add if is_add else arg.is_Mul:
            seq.extend(arg.args)
            continue
        if is_add:
            if arg.is_Pow and arg.base.is_number:
                return None
            if arg.is_Mul and any(factor.is_Mul for factor in arg.args):
                # A product holding a product (sympy's own 2*exp(a + 0.1) is 2*(c*exp(a))):
                # flatten rebuilds such a term from its coefficient and the rest.
                return None
            key = arg.as_coeff_Mul()[1] if arg.is_Mul else arg
        else:
            # A constant base (2**x, sqrt(3), exp(b + 0.1) = E**(b + 0.1)) or a sum in
            # the exponent is where flatten folds or splits powers.
            key, exponent = arg.as_base_exp()
            if key.is_number or exponent.is_Add:
                return None
            has_sum = has_sum or arg.is_Add
        if key in seen:
            return None
        seen.add(key)
        rest.append(arg)
    if is_add:
        keep = coefficient != 0
    else:
        if coefficient == 0 or (coefficient != 1 and has_sum):
            return None
        keep = coefficient != 1
    rest.sort(key=_canonical())
    if keep:
        rest.insert(0, coefficient)
    if len(rest) < 2:
        return rest[0] if rest else None
    result: sx.Expr = node.func._from_args(rest)
    return result


def _rebuild(node: sx.Expr, args: Sequence[sx.Expr]) -> sx.Expr:
    """``node.func(*args)``, without re-running a function's ``eval`` on symbolic args.

    Rebuilding ``tan(pi*g/(2*d))`` after a substitution makes sympy look for multiples
    of pi in the argument again, with assumption queries: four milliseconds a node, two
    seconds for a ring of 32 agents. Substituting symbols for symbols, or a temporary
    for its value, never gives ``eval`` anything new to simplify; numbers still
    evaluate (``sin(0)`` is 0). Sums and products that only need re-sorting skip
    ``flatten`` (:func:`_sorted_args`).

    On SymEngine, whose constructors cost a microsecond and never search for multiples
    of pi, the node's own constructor (a ``Piecewise`` from its pairs).
    """
    if sx.SYMENGINE:
        return _rebuild_symengine(node, args)
    if isinstance(node, sx.Function) and not all(a.is_Number for a in args):
        if isinstance(node, _even()) and args[0].is_Mul and args[0].args[0] is sx.Integer(-1):
            # cos(-x) = cos(x): a merge that finds x as the negation of an earlier
            # temporary hands an even function -_t, which eval would have signed.
            args = [-args[0]]
        return node.func(*args, evaluate=False)
    if node.is_Add or node.is_Mul:
        fast = _sorted_args(node, args)
        if fast is not None:
            return fast
    return node.func(*args)


def _rebuild_symengine(node: sx.Expr, args: Sequence[sx.Expr]) -> sx.Expr:
    """SymEngine's ``node.func(*args)``: a ``Piecewise`` takes pairs, a relation its class.

    A product is distributed as SymPy's is (:func:`_distributed`).
    """
    if node.is_Mul:
        return _distributed(sx.Mul(*args))
    if sx.is_piecewise(node):
        return sx.Piecewise(*zip(args[::2], args[1::2], strict=True))
    try:
        func = node.func
    except AttributeError:  # relations and logic have no func: their class builds them
        func = type(node)
    return func(*args)


def _distributed(product: sx.Expr) -> sx.Expr:
    """``c*(a + b)`` as ``c*a + c*b`` for a rational ``c``, as SymPy's ``Mul`` builds it.

    SymEngine keeps the product. Inlining a temporary into ``a + 2*_t`` then leaves
    ``a + 2*(a + b)`` where SymPy collects ``3*a + 2*b``, and terms that cancel (most
    of a chain's jet, where half the kernel's temporaries vanish so) stay.
    """
    if product.is_Mul:
        factors = product.args
        if len(factors) == 2 and factors[0].is_Rational and factors[1].is_Add:
            coefficient = factors[0]
            return sx.Add(*[_distributed(coefficient * term) for term in factors[1].args])
    return product


def _substitute(
    expr: sx.Expr,
    mapping: Mapping[sx.Expr, sx.Expr],
    memo: dict[sx.Expr, sx.Expr] | None = None,
    odd: dict[sx.Expr, sx.Expr] | None = None,
) -> sx.Expr:
    """``expr.xreplace(mapping)`` with :func:`_rebuild`; ``memo`` may span many calls.

    With ``odd`` (a memo of odd functions -> their signed forms), every odd function of
    the result gets its canonical sign (:func:`canonical_odd`) as it is rebuilt: the
    substituted tree is not walked a second time to sign it.
    """
    if isinstance(expr, sx.Basic) and not expr.args and expr not in mapping:
        return expr  # a number or a symbol left alone: most of a team's Hessian
    table: dict[sx.Expr, sx.Expr] = {} if memo is None else memo
    same = _same()
    odd_functions = _odd()

    def visit(node: sx.Expr) -> sx.Expr:
        if node in mapping:
            return mapping[node]
        own = node.args
        if not own:
            return node
        if node in table:
            return table[node]
        args = [visit(arg) for arg in own]
        new = node if _unchanged(same, own, args) else _rebuild(node, args)
        if odd is not None and isinstance(new, odd_functions):
            new = _signed_odd(new, odd)
        elif odd is not None and isinstance(node, odd_functions):
            # The constructor pulled a minus sign out of the new argument
            # (sin(-2.5*(a + c)) -> -sin(2.5*(a + c))): the odd function under that
            # sign is signed as canonical_odd would sign it in a second walk.
            inner = -new
            if isinstance(inner, odd_functions):
                new = -_signed_odd(inner, odd)
        table[node] = new
        return new

    result = visit(_expr(expr))
    release(visit)
    return result


def _replace_all(
    exprs: Sequence[sx.Expr],
    mapping: Mapping[sx.Expr, sx.Expr],
    odd: dict[sx.Expr, sx.Expr] | None = None,
) -> list[sx.Expr]:
    """``[e.xreplace(mapping) for e in exprs]`` in one walk of SymEngine's, in C++.

    Odd functions are signed with ``odd`` as :func:`_substitute` signs them. SymEngine
    only.

    The expressions are packed as the arguments of one function, which SymEngine keeps
    in order and walks once, its nodes shared by several expressions rebuilt once: a
    Python walk costs a few microseconds a node on SymEngine (each ``.args`` makes new
    Python objects, each dictionary hit compares two of them), this a fraction of one.
    SymEngine's constructors rebuild the nodes, which do not distribute a number over a
    sum (:func:`_distributed`): for renaming symbols, and for substituting the slots.
    """
    if not exprs:
        return []
    packed = sx.Function("_cse_pack")(*exprs)
    if mapping:
        packed = packed.xreplace(dict(mapping))
    if odd is not None:
        found = packed.atoms(*_odd())
        if found:
            signed = {node: _signed_nested(node, odd) for node in found}
            changed = {node: new for node, new in signed.items() if new != node}
            if changed:
                packed = packed.xreplace(changed)
    return list(packed.args)


def _signed_nested(node: sx.Expr, odd: dict[sx.Expr, sx.Expr]) -> sx.Expr:
    """The odd function ``node``, signed, and the odd functions inside it, inner first.

    As :func:`_substitute` decides them as it rebuilds.
    """
    inner = node.args[0].atoms(*_odd())
    if inner:
        changed = {i: new for i in inner if (new := _signed_nested(i, odd)) != i}
        if changed:
            node = node.func(node.args[0].xreplace(changed))
            if not isinstance(node, _odd()):  # SymEngine signed it itself
                return node
    return _signed_odd(node, odd)


def _negated_atom(value: sx.Expr) -> bool:
    """Whether ``value`` is ``-x`` for a symbol or constant ``x`` (printing it costs nothing)."""
    if not value.is_Mul:
        return False
    # One .args (SymEngine builds them anew each time), compared with the engine's -1:
    # comparing with Python's converts it first, four microseconds on SymEngine.
    args = value.args
    return bool(len(args) == 2 and args[0] == _minus_one() and args[1].is_Atom)


_MINUS_ONE: dict[str, sx.Expr] = {}


def _minus_one() -> sx.Expr:
    """The engine's -1, made once per engine."""
    one = _MINUS_ONE.get(sx.ENGINE)
    if one is None:
        one = _MINUS_ONE[sx.ENGINE] = sx.Integer(-1)
    return one


#: Sums up to this many terms are looked up negated too (:func:`_merge_equal`).
_NEGATED_TERMS = 4


def _negate(value: sx.Expr) -> sx.Expr:
    """``-value``, a sum's terms negated (SymEngine keeps ``-(a - b)`` as a product).

    On SymPy, the terms are re-sorted without ``flatten`` where possible.
    """
    if value.is_Add:
        if sx.SYMENGINE:
            return sx.Add(*[-term for term in value.args])
        fast = _sorted_args(value, [-term for term in value.args])
        if fast is not None:
            return fast
    negated: sx.Expr = -value
    return negated


def _even() -> tuple[Any, ...]:
    """The engine's even functions: f(-x) = f(x)."""
    return (sx.cos, sx.cosh, sx.sec, sx.sech)


def _odd() -> tuple[Any, ...]:
    """The engine's odd functions: f(-x) = -f(x)."""
    return (sx.sin, sx.tan, sx.sinh, sx.tanh, sx.asin, sx.atan, sx.asinh, sx.atanh)


def canonical_odd(expr: sx.Expr, memo: dict[sx.Expr, sx.Expr] | None = None) -> sx.Expr:
    """Write every odd function with the sign of its argument pulled out.

    sympy keeps ``tanh((a - t)/b)`` and ``tanh((t - a)/b)`` apart (neither argument
    "extracts" a minus sign, so neither is rewritten), and CSE then evaluates both. Of
    such a pair the argument with the smaller canonical sort key is kept; sympy leaves
    it alone on re-evaluation because it does not extract a sign either.

    ``memo`` (an odd function -> its signed form) may be shared between calls: the
    kernels of one controller repeat the same trigonometry, and each is decided once.
    """
    signs: dict[sx.Expr, sx.Expr] = {} if memo is None else memo
    expr = _expr(expr)
    # With a shared memo, no search for odd functions first: atoms() walks the whole
    # tree on every call, where the memo makes each node's decision a lookup.
    if memo is None and not expr.atoms(*_odd()):
        return expr
    # A substitution of nothing that signs odd functions as it rebuilds: one walk.
    return _substitute(expr, {}, None, signs)


def _signed_odd(node: sx.Expr, memo: dict[sx.Expr, sx.Expr]) -> sx.Expr:
    """An odd function whose argument is already canonical, with its sign decided.

    ``memo`` holds the odd functions decided so far, with their signed forms.
    """
    known = memo.get(node)
    if known is not None:
        return known
    signed = node
    if sx.SYMENGINE:
        mirrored = _mirrored_symengine(node)
        if mirrored is not None:
            signed = -mirrored
    elif _flips(node):
        # Not re-evaluated: eval would find nothing the original's did not.
        signed = -node.func(_negated_argument(node.args[0]), evaluate=False)
    memo[node] = signed
    return signed


def _negated_argument(arg: sx.Expr) -> sx.Expr:
    """``-arg``, the sign distributed into a sum factor: -(a - t)/b becomes (t - a)/b."""
    if arg.is_Mul:
        for i, factor in enumerate(arg.args):
            if factor.is_Add:
                return sx.Mul(*arg.args[:i], _negated_sum(factor), *arg.args[i + 1 :])
    return _negated_sum(arg) if arg.is_Add else -arg


def _negated_sum(value: sx.Expr) -> sx.Expr:
    """``-value`` for a sum, its terms negated (SymPy distributes the sign itself)."""
    if sx.SYMENGINE:
        return sx.Add(*[-term for term in value.args])
    return -value


def _flips(e: sx.Expr) -> bool:
    """Whether the odd function ``e`` is written with its argument negated, canonically.

    SymPy only; SymEngine's is :func:`_mirrored_symengine`.
    """
    arg = e.args[0]
    other = _negated_argument(arg)
    if other.could_extract_minus_sign():
        return False
    expanded = sx.expand(arg)
    # Expanding is canonical: with exact coefficients, the negation's expansion is the
    # expansion's terms negated, and one expansion (half of this decision's time) is
    # saved. Floats may round apart in the two expansions: both are made.
    if expanded.has(sx.Float):
        negated = sx.expand(other)
    else:
        negated = _negate(expanded)
    # SymPy's own order, as the golden kernels were made with it.
    from sympy import default_sort_key  # noqa: PLC0415 - loaded with the engine already

    return bool(default_sort_key(negated) < default_sort_key(expanded))


def _mirrored_symengine(e: sx.Expr) -> sx.Expr | None:
    """``f(-x)`` for the odd function ``e = f(x)`` when that is its canonical spelling.

    SymEngine signs ``f(-x)`` itself where the argument "extracts" a minus sign (a
    negative coefficient), as SymPy does, and keeps ``tanh((a - t)/b)`` and
    ``tanh((t - a)/b)`` apart as SymPy does. Of such a pair the argument whose expansion
    has the smaller :func:`~tvopt_codegen.symbolic.sort_key` (text, the same in every
    run) is kept. None when ``e`` is canonical already, or SymEngine signs the mirror.
    """
    arg = e.args[0]
    other = _negated_argument(arg)
    mirrored = e.func(other)
    if mirrored.is_Mul:  # SymEngine pulled the sign out again: e is its canonical form
        return None
    expanded = sx.expand(arg)
    # As on SymPy: exact coefficients negate exactly, floats may round apart.
    if expanded.atoms(sx.Float):
        negated = sx.expand(other)
    else:
        negated = _negate(expanded)
    if sx.sort_key(negated) < sx.sort_key(expanded):
        return mirrored
    return None
