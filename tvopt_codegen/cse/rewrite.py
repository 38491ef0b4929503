"""Tree rewriting that keeps sympy's canonical form.

Operation counts, free symbols, substitution by splicing, and odd functions of mirrored
arguments merged (:func:`canonical_odd`).
"""

from __future__ import annotations

import functools
from collections.abc import Iterable, Mapping, Sequence

import sympy as sp

from tvopt_codegen.maths.jet import release, unchanged


def operation_count(exprs: Iterable[sp.Expr], memo: dict[sp.Basic, int] | None = None) -> int:
    """Count the arithmetic operations and function calls that printing ``exprs`` costs.

    A sum or product of ``n`` terms is ``n - 1`` operations (a factor ``-1`` is the
    negation, or nothing in a sum, where it makes the subtraction; a factor ``b**-1`` is
    the division), every other power and every function call one, a negative or
    fractional literal one. Expressions are counted as trees, like sympy's
    ``count_ops``, but in one memoized pass: linear in the size of the DAG, where
    ``count_ops`` walks each expression anew. ``memo`` (a node -> the operations below
    it) may span calls over the same nodes (the kernels cut from one program).
    """
    below: dict[sp.Basic, int] = {} if memo is None else memo

    def own(node: sp.Basic, parent: str) -> int:
        if node.is_Number:
            if parent == "mul":
                return 0
            return int(node.is_negative is True) + int(node.is_Rational and not node.is_Integer)
        if node.is_Atom:
            return 0
        if node.is_Add:
            return len(node.args) - 1
        if node.is_Mul:
            negated = parent == "add" and node.args[0].is_Number and node.args[0].is_negative
            return len(node.args) - 1 - int(bool(negated) and node.args[0] == -1)
        if node.is_Pow and node.exp == -1:
            return 0 if parent == "mul" else 1
        return 1

    def count(node: sp.Basic) -> int:
        # A node's own operations depend on its parent's kind; those of its subtree
        # do not, and are what the memo keeps. Leaves have no subtree, and symbols cost
        # nothing: only numbers among them are looked at (half the calls were symbols).
        total = below.get(node)
        if total is None:
            kind = "mul" if node.is_Mul else "add" if node.is_Add else ""
            total = 0
            for arg in node.args:
                if arg.args:
                    total += own(arg, kind) + count(arg)
                elif arg.is_Number:
                    total += own(arg, kind)
            below[node] = total
        return total

    exprs = [sp.sympify(e) for e in exprs]
    total = sum(own(e, "") + count(e) for e in exprs)
    release(count)
    return total


def symbols_in(exprs: Iterable[sp.Basic]) -> set[sp.Basic]:
    """The symbols of all ``exprs``, each distinct subtree visited once.

    ``free_symbols`` builds a set at every node of every tree, anew for each
    expression; a kernel's expressions share most of their subtrees.
    """
    seen: set[sp.Basic] = set()
    found: set[sp.Basic] = set()
    stack = [sp.sympify(e) for e in exprs]
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


#: The canonical order of a sum's terms or a product's factors: sympy's own
#: (``Add.flatten`` and ``Mul.flatten`` sort with ``Basic.compare``).
_CANONICAL = functools.cmp_to_key(sp.Basic.compare)


def _sorted_args(node: sp.Basic, args: Sequence[sp.Basic]) -> sp.Basic | None:
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
    the very object ``flatten`` would build.
    """
    is_add = node.is_Add
    seq = list(args)
    coefficient: sp.Basic = sp.S.Zero if is_add else sp.S.One
    seen: set[sp.Basic] = set()
    rest: list[sp.Basic] = []
    has_sum = False
    for arg in seq:  # grows while iterating: spliced arguments come last, as in flatten
        if arg.is_Number:
            if not arg.is_finite:
                return None
            coefficient = coefficient + arg if is_add else coefficient * arg
            continue
        if not arg.is_commutative or arg is sp.S.ComplexInfinity:
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
    rest.sort(key=_CANONICAL)
    if keep:
        rest.insert(0, coefficient)
    if len(rest) < 2:
        return rest[0] if rest else None
    result: sp.Basic = node.func._from_args(rest)
    return result


def _rebuild(node: sp.Basic, args: Sequence[sp.Basic]) -> sp.Basic:
    """``node.func(*args)``, without re-running a function's ``eval`` on symbolic args.

    Rebuilding ``tan(pi*g/(2*d))`` after a substitution makes sympy look for multiples
    of pi in the argument again, with assumption queries: four milliseconds a node, two
    seconds for a ring of 32 agents. Substituting symbols for symbols, or a temporary
    for its value, never gives ``eval`` anything new to simplify; numbers still
    evaluate (``sin(0)`` is 0). Sums and products that only need re-sorting skip
    ``flatten`` (:func:`_sorted_args`).
    """
    if isinstance(node, sp.Function) and not all(a.is_Number for a in args):
        if isinstance(node, _EVEN) and args[0].is_Mul and args[0].args[0] is sp.S.NegativeOne:
            # cos(-x) = cos(x): a merge that finds x as the negation of an earlier
            # temporary hands an even function -_t, which eval would have signed.
            args = [-args[0]]
        return node.func(*args, evaluate=False)
    if node.is_Add or node.is_Mul:
        fast = _sorted_args(node, args)
        if fast is not None:
            return fast
    return node.func(*args)


def _substitute(
    expr: sp.Basic,
    mapping: Mapping[sp.Basic, sp.Basic],
    memo: dict[sp.Basic, sp.Basic] | None = None,
    odd: dict[sp.Basic, sp.Expr] | None = None,
) -> sp.Basic:
    """``expr.xreplace(mapping)`` with :func:`_rebuild`; ``memo`` may span many calls.

    With ``odd`` (a memo of odd functions -> their signed forms), every odd function of
    the result gets its canonical sign (:func:`canonical_odd`) as it is rebuilt: the
    substituted tree is not walked a second time to sign it.
    """
    if isinstance(expr, sp.Basic) and not expr.args and expr not in mapping:
        return expr  # a number or a symbol left alone: most of a team's Hessian
    table: dict[sp.Basic, sp.Basic] = {} if memo is None else memo

    def visit(node: sp.Basic) -> sp.Basic:
        if node in mapping:
            return mapping[node]
        if not node.args:
            return node
        if node in table:
            return table[node]
        args = [visit(arg) for arg in node.args]
        new = node if unchanged(node, args) else _rebuild(node, args)
        if odd is not None and isinstance(new, _ODD):
            new = _signed_odd(new, odd)
        table[node] = new
        return new

    result = visit(sp.sympify(expr))
    release(visit)
    return result


def _negated_atom(value: sp.Basic) -> bool:
    """Whether ``value`` is ``-x`` for a symbol or constant ``x`` (printing it costs nothing)."""
    return bool(
        value.is_Mul and len(value.args) == 2 and value.args[0] == -1 and value.args[1].is_Atom
    )


#: Sums up to this many terms are looked up negated too (:func:`_merge_equal`).
_NEGATED_TERMS = 4


def _negate(value: sp.Basic) -> sp.Basic:
    """``-value``; a sum's terms negated and re-sorted without ``flatten`` where possible."""
    if value.is_Add:
        fast = _sorted_args(value, [-term for term in value.args])
        if fast is not None:
            return fast
    negated: sp.Basic = -value
    return negated


#: Even functions: f(-x) = f(x).
_EVEN = (sp.cos, sp.cosh, sp.sec, sp.sech)

#: Odd functions: f(-x) = -f(x).
_ODD = (sp.sin, sp.tan, sp.sinh, sp.tanh, sp.asin, sp.atan, sp.asinh, sp.atanh)


def canonical_odd(expr: sp.Expr, memo: dict[sp.Basic, sp.Expr] | None = None) -> sp.Expr:
    """Write every odd function with the sign of its argument pulled out.

    sympy keeps ``tanh((a - t)/b)`` and ``tanh((t - a)/b)`` apart (neither argument
    "extracts" a minus sign, so neither is rewritten), and CSE then evaluates both. Of
    such a pair the argument with the smaller canonical sort key is kept; sympy leaves
    it alone on re-evaluation because it does not extract a sign either.

    ``memo`` (an odd function -> its signed form) may be shared between calls: the
    kernels of one controller repeat the same trigonometry, and each is decided once.
    """
    signs: dict[sp.Basic, sp.Expr] = {} if memo is None else memo
    expr = sp.sympify(expr)
    # With a shared memo, no search for odd functions first: atoms() walks the whole
    # tree on every call, where the memo makes each node's decision a lookup.
    if memo is None and not expr.atoms(*_ODD):
        return expr
    # A substitution of nothing that signs odd functions as it rebuilds: one walk.
    return _substitute(expr, {}, None, signs)


def _signed_odd(node: sp.Expr, memo: dict[sp.Basic, sp.Expr]) -> sp.Expr:
    """An odd function whose argument is already canonical, with its sign decided.

    ``memo`` holds the odd functions decided so far, with their signed forms.
    """
    known = memo.get(node)
    if known is not None:
        return known
    signed = node
    if _flips(node):
        # Not re-evaluated: eval would find nothing the original's did not.
        signed = -node.func(_negated_argument(node.args[0]), evaluate=False)
    memo[node] = signed
    return signed


def _negated_argument(arg: sp.Expr) -> sp.Expr:
    """``-arg``, the sign distributed into a sum factor: -(a - t)/b becomes (t - a)/b."""
    if arg.is_Mul:
        for i, factor in enumerate(arg.args):
            if factor.is_Add:
                return sp.Mul(*arg.args[:i], -factor, *arg.args[i + 1 :])
    return -arg


def _flips(e: sp.Expr) -> bool:
    """Whether the odd function ``e`` is written with its argument negated, canonically."""
    arg = e.args[0]
    other = _negated_argument(arg)
    if other.could_extract_minus_sign():
        return False
    expanded = sp.expand(arg)
    # Expanding is canonical: with exact coefficients, the negation's expansion is the
    # expansion's terms negated, and one expansion (half of this decision's time) is
    # saved. Floats may round apart in the two expansions: both are made.
    if expanded.has(sp.Float):
        negated = sp.expand(other)
    else:
        negated = _negate(expanded)
    return bool(sp.default_sort_key(negated) < sp.default_sort_key(expanded))
