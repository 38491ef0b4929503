"""Optimising kernels: operation counts, substitution, ordered CSE, and hoisting.

:func:`make_kernel` turns a derived program and its outputs into a :class:`Kernel`:
slot symbols substituted, odd functions of mirrored arguments merged
(:func:`canonical_odd`), common subexpressions found and named in evaluation order
(:func:`ordered_cse`). :func:`split_invariant` splits off the part of a kernel that
depends on time and parameters alone, computed once per batch of states.
"""

from __future__ import annotations

import functools
import itertools
from collections.abc import Iterable, Mapping, Sequence

import sympy as sp

from tvopt_codegen.jet import Assignment, fresh_symbols, release, unchanged
from tvopt_codegen.kernel import Arg, Kernel, Output


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


def _drop_aliases(
    assignments: Sequence[Assignment], outputs: Sequence[sp.Expr]
) -> tuple[list[Assignment], list[sp.Expr]]:
    """Substitute assignments whose value is a bare symbol or constant, or its negation."""
    alias: dict[sp.Symbol, sp.Expr] = {}
    kept: list[Assignment] = []
    # One memo for the whole program: in evaluation order a node can only hold symbols
    # assigned before it, whose aliases are all decided when it is first met.
    memo: dict[sp.Basic, sp.Basic] = {}
    for sym, raw in assignments:
        value = _substitute(raw, alias, memo)
        if value.is_Atom or _negated_atom(value):
            alias[sym] = value
        else:
            kept.append((sym, value))
    return kept, [_substitute(e, alias, memo) for e in outputs]


def _prune(
    assignments: Sequence[Assignment],
    outputs: Sequence[sp.Expr],
    symbols: dict[sp.Basic, set[sp.Basic]] | None = None,
) -> list[Assignment]:
    """Drop assignments that no output needs (signal orders a kernel does not use).

    ``symbols`` (expression -> its free symbols) may span calls over the same program:
    sympy walks the tree anew each time it is asked.
    """
    known: dict[sp.Basic, set[sp.Basic]] = {} if symbols is None else symbols

    def free(expr: sp.Basic) -> set[sp.Basic]:
        found = known.get(expr)
        if found is None:
            found = known[expr] = sp.sympify(expr).free_symbols
        return found

    needed: set[sp.Basic] = set()
    for e in outputs:
        needed |= free(e)
    kept: list[Assignment] = []
    for sym, value in reversed(assignments):
        if sym in needed:
            kept.append((sym, value))
            needed |= free(value)
    return kept[::-1]


#: Programs up to this many operations get sympy's full cse; larger ones value numbering.
SMALL_PROGRAM_OPS = 1000


def ordered_cse(
    assignments: Sequence[Assignment], outputs: Sequence[sp.Expr], search: bool = True
) -> tuple[tuple[Assignment, ...], tuple[sp.Expr, ...]]:
    """CSE a straight-line program and its outputs, keeping evaluation order valid.

    One ``sympy.cse`` pass sees every right-hand side and output. A common
    subexpression found in an assignment only uses symbols defined before it, so each
    extracted temporary is emitted just before its first use. Temporaries are then
    renamed ``_t0, _t1, ...`` in emission order, which makes the text deterministic.

    Parameters
    ----------
    assignments : sequence of (sympy.Symbol, sympy.Expr)
        The program; right-hand sides use only earlier symbols and the inputs.
    outputs : sequence of sympy.Expr
        Output expressions over the program and the inputs.
    search : bool
        Allow sympy's ``cse`` (on programs up to :data:`SMALL_PROGRAM_OPS`), which also
        finds common parts of sums and products. A program built one operation per
        assignment (the Cholesky solve) has none to find: value numbering suffices.

    Returns
    -------
    body : tuple of (sympy.Symbol, sympy.Expr)
        The temporaries in evaluation order.
    outputs : tuple of sympy.Expr
        The reduced outputs.
    """
    return _number(*_reduce(assignments, outputs, search))


def _reduce(
    assignments: Sequence[Assignment],
    outputs: Sequence[sp.Expr],
    search: bool,
    symbols: dict[sp.Basic, set[sp.Basic]] | None = None,
) -> tuple[list[Assignment], list[sp.Expr]]:
    """:func:`ordered_cse` up to naming: temporaries in evaluation order, reduced outputs.

    ``symbols`` is :func:`_prune`'s memo of free symbols, when the caller has one.
    """
    kept, outs = _drop_aliases(_prune(assignments, outputs, symbols), outputs)
    exprs = [value for _, value in kept] + outs
    names = sp.numbered_symbols("_cse", real=True)
    if search and operation_count(exprs) <= SMALL_PROGRAM_OPS:
        # sympy's cse also finds common parts of sums and products (a*b in a*b*c and
        # a*b*d): worth its superlinear time on the programs of a few agents only.
        replacements, reduced = sp.cse(exprs, symbols=names, order="canonical")
    else:
        replacements, reduced = _value_numbering(exprs, names)
    defined = dict(replacements)
    order: list[Assignment] = []
    emitted: set[sp.Symbol] = set()

    def need(expr: sp.Expr) -> None:
        # Not free_symbols & defined.keys() - emitted: "-" binds first, and the difference
        # of the two large sets, once per value, was quadratic in the program's size.
        missing = [s for s in expr.free_symbols if s in defined and s not in emitted]
        for sym in sorted(missing, key=_cse_index):
            need(defined[sym])
            if sym not in emitted:
                emitted.add(sym)
                order.append((sym, defined[sym]))

    for (sym, _), value in zip(kept, reduced[: len(kept)], strict=True):
        need(value)
        order.append((sym, value))
    for value in reduced[len(kept) :]:
        need(value)
    release(need)
    outs = list(reduced[len(kept) :])
    # Merging equal values can leave a temporary with one use, and inlining can make
    # two values equal: alternate to a fixed point (two rounds in practice). Each pass
    # reaches its own fixed point, and inlining changes the program exactly when it
    # removes a temporary: a round whose inlining removed none ends the loop.
    while True:
        order, outs = _merge_equal(order, outs)
        size = len(order)
        order, outs = _inline_single_use(order, outs)
        if len(order) == size:
            break
    return order, outs


def _number(
    order: Sequence[Assignment], outs: Sequence[sp.Expr]
) -> tuple[tuple[Assignment, ...], tuple[sp.Expr, ...]]:
    """Rename the temporaries ``_t0, _t1, ...`` in evaluation order."""
    renames: dict[sp.Symbol, sp.Expr] = {}
    body: list[Assignment] = []
    # One memo, as in _drop_aliases: a node holds only symbols renamed before it is met.
    memo: dict[sp.Basic, sp.Basic] = {}
    for index, (sym, value) in enumerate(order):
        new = sp.Symbol(f"_t{index}", real=True)
        body.append((new, _substitute(value, renames, memo)))
        renames[sym] = new
    return tuple(body), tuple(_substitute(e, renames, memo) for e in outs)


def _value_numbering(
    exprs: Sequence[sp.Expr], names: Iterable[sp.Symbol]
) -> tuple[list[Assignment], list[sp.Expr]]:
    """Common subexpression elimination by value numbering, linear in the DAG size.

    Every compound subexpression that occurs more than once becomes a temporary. This
    is the tree pass of ``sympy.cse`` without its search for common subsets of sums
    and products, which is quadratic in their number of terms and took minutes on a
    ring of three agents (issue 7). The jet arrives in three-address form, where
    such subsets are already separate assignments, so little is lost.
    """
    names = iter(names)
    seen: set[sp.Basic] = set()
    repeated: set[sp.Basic] = set()

    def worth(node: sp.Basic) -> bool:
        # A negated symbol or number is not worth a temporary: printing it is free.
        return not (node.is_Atom or _negated_atom(node))

    def find(node: sp.Basic) -> None:
        stack = [node]
        while stack:
            current = stack.pop()
            if not worth(current):
                continue
            if current in seen:
                repeated.add(current)
                continue
            seen.add(current)
            stack.extend(current.args)

    for expr in exprs:
        find(expr)
    replacements: list[Assignment] = []
    built: dict[sp.Basic, sp.Expr] = {}

    def build(node: sp.Basic) -> sp.Expr:
        if node.is_Atom:
            return node
        if node in built:
            return built[node]
        args = [build(arg) for arg in node.args]
        new = node if unchanged(node, args) else _rebuild(node, args)
        if node in repeated:
            sym = next(names)
            replacements.append((sym, new))
            new = sym
        built[node] = new
        return new

    reduced = [build(sp.sympify(e)) for e in exprs]
    release(build)
    return replacements, reduced


def _merge_equal(
    order: list[Assignment], outputs: list[sp.Expr]
) -> tuple[list[Assignment], list[sp.Expr]]:
    """Merge temporaries that compute the same value as an earlier one, or its negation.

    CSE compares expressions, not values, before its own replacements: two products
    that only become equal once their factors are named stay apart (``a**2 + 1`` twice
    after ``a = tan(...)`` was extracted). And a pairwise term such as a barrier between
    agents a and b differentiates into ``xa - xb`` for one and ``xb - xa`` for the other.
    One pass in evaluation order catches both, each match turning the next ones up.

    Temporaries whose value is a symbol or constant, or its negation, are substituted
    too, in the same walk (:func:`_drop_aliases` did it in a pass of its own): CSE
    leaves them where the program computed a value found elsewhere first, a merge where
    ``a - b`` meets ``b - a``, and inlining where terms cancel.
    """
    first: dict[sp.Basic, sp.Symbol] = {}
    rename: dict[sp.Symbol, sp.Expr] = {}
    # A node is rewritten once: a renamed symbol is only used after its assignment,
    # so no node seen before a rename can contain it.
    memo: dict[sp.Basic, sp.Basic] = {}
    kept: list[Assignment] = []
    for sym, raw in order:
        value = _substitute(raw, rename, memo)
        if value.is_Atom or _negated_atom(value):
            rename[sym] = value
            continue
        if value in first:
            rename[sym] = first[value]
            continue
        # Negating a long sum builds a new one term by term; exact opposites are short
        # differences (xa - xb) and products, so longer sums are not tried.
        if not (value.is_Add and len(value.args) > _NEGATED_TERMS):
            negated = _negate(value)
            if negated in first:
                rename[sym] = -first[negated]
                continue
        first[value] = sym
        kept.append((sym, value))
    return kept, [_substitute(e, rename, memo) for e in outputs]


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


def _occurrences(expr: sp.Basic) -> dict[sp.Symbol, int]:
    """How often each symbol occurs in ``expr`` as a tree: ``x*x`` uses ``x`` twice.

    A plain stack walk: sympy's ``preorder_traversal`` costs a generator step per node,
    and this counts every value of a program (a fifth of inlining's time).
    """
    # A plain dict: building a Counter (a Python-level __init__) for every value of a
    # program was a tenth of inlining's time.
    found: dict[sp.Symbol, int] = {}
    stack = [expr]
    while stack:
        node = stack.pop()
        args = node.args
        if args:
            stack.extend(args)
        elif node.is_Symbol:
            found[node] = found.get(node, 0) + 1
    return found


def _inline_single_use(
    order: list[Assignment], outputs: list[sp.Expr]
) -> tuple[list[Assignment], list[sp.Expr]]:
    """Substitute temporaries used exactly once back into their one user; drop the unused.

    The jet is derived in three-address form (one operation per assignment), which
    makes differentiation linear; printed that way, every operation would become a
    named array in NumPy. Shared work stays in temporaries; the rest reads as the
    expression it is.

    Inlining can collect terms: ``a + 2*(a + b)`` becomes ``3*a + 3*b``, and ``a``,
    used twice before, is now used once. A pass over the whole program finds one level
    of such temporaries at a time (a k = 12 jet needed a dozen). Here every
    expression's symbol counts are kept; after the first wave, each wave substitutes
    into the expressions the last one changed, until no temporary is used once.
    """
    n = len(order)
    values: list[sp.Expr] = [value for _, value in order] + list(outputs)
    position = {sym: i for i, (sym, _) in enumerate(order)}
    counts = [_occurrences(value) for value in values]
    uses: dict[sp.Symbol, int] = {}
    holders: dict[sp.Symbol, set[int]] = {}
    for i, count in enumerate(counts):
        for sym, times in count.items():
            uses[sym] = uses.get(sym, 0) + times
            holders.setdefault(sym, set()).add(i)
    gone: set[int] = set()
    wave = {i for i, (sym, _) in enumerate(order) if uses.get(sym, 0) <= 1}
    while wave:
        inline: dict[sp.Symbol, sp.Expr] = {}
        # One memo for the wave: in evaluation order a node holds only earlier
        # symbols, whose values are final when it is first met (as in _drop_aliases).
        memo: dict[sp.Basic, sp.Basic] = {}
        users: set[int] = set()
        changed: set[sp.Symbol] = set()
        for i in sorted(wave):
            sym = order[i][0]
            inline[sym] = _substitute(values[i], inline, memo)
            users |= holders.get(sym, set())
            gone.add(i)
            changed |= counts[i].keys()
            for other, times in counts[i].items():
                uses[other] -= times
                holders[other].discard(i)
        for user in sorted(users - gone):
            before = counts[user]
            values[user] = _substitute(values[user], inline, memo)
            after = counts[user] = _occurrences(values[user])
            for other in before.keys() | after.keys():
                was, now = before.get(other, 0), after.get(other, 0)
                if was != now:
                    uses[other] = uses.get(other, 0) + now - was
                    changed.add(other)
                if not now:
                    holders[other].discard(user)
                elif not was:
                    holders.setdefault(other, set()).add(user)
        wave = {
            j
            for j in (position.get(sym) for sym in changed)
            if j is not None and j not in gone and uses.get(order[j][0], 0) <= 1
        }
    kept = [(order[i][0], values[i]) for i in range(n) if i not in gone]
    return kept, values[n:]


def _cse_index(sym: sp.Symbol) -> int:
    return int(sym.name[len("_cse") :])


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


#: A kernel's outputs: (name, shape, expressions in row-major order, description).
Outputs = Sequence[tuple[str, tuple[int, ...], Sequence[sp.Expr], str]]


def _prepare(
    assignments: Sequence[Assignment],
    exprs: Sequence[sp.Expr],
    subs: Mapping[sp.Symbol, sp.Expr],
    odd: dict[sp.Basic, sp.Expr] | None,
    symbols: dict[sp.Basic, set[sp.Basic]] | None = None,
) -> tuple[list[Assignment], list[sp.Expr]]:
    """What ``exprs`` need of the program, with slots substituted and odd functions signed."""
    # Only what the outputs need: the gradient kernel, say, reads the jet's first part.
    assignments = _prune(assignments, exprs, symbols)
    slots: dict[sp.Basic, sp.Basic] = {}
    signs: dict[sp.Basic, sp.Expr] = {} if odd is None else odd
    # Slots are symbols: substituting and signing odd functions is one pass.
    if not all(value.is_Atom for value in subs.values()):
        subs = {sym: canonical_odd(value, signs) for sym, value in subs.items()}
    program = [(sym, _substitute(value, subs, slots, signs)) for sym, value in assignments]
    return program, [_substitute(e, subs, slots, signs) for e in exprs]


def _package(
    name: str,
    doc: str,
    inputs: Sequence[Arg],
    outputs: Outputs,
    body: Sequence[Assignment],
    reduced: Sequence[sp.Expr],
    before: int,
) -> Kernel:
    """The kernel of a CSE'd program, its outputs cut to their shapes; checks its symbols."""
    packed: list[Output] = []
    start = 0
    for out_name, shape, exprs, out_doc in outputs:
        packed.append(Output(out_name, shape, tuple(reduced[start : start + len(exprs)]), out_doc))
        start += len(exprs)
    allowed = {s for arg in inputs for s in arg.symbols} | {sym for sym, _ in body}
    allowed.add(sp.Symbol("t", real=True))
    stray = symbols_in([v for _, v in body] + list(reduced)) - allowed
    if stray:
        raise AssertionError(f"kernel {name}: unbound symbols {sorted(map(str, stray))}")
    return Kernel(
        name,
        doc,
        tuple(inputs),
        tuple(body),
        tuple(packed),
        operation_count([v for _, v in body] + list(reduced)),
        before,
    )


def _flat(outputs: Outputs) -> list[sp.Expr]:
    return [e for _, _, exprs, _ in outputs for e in exprs]


def _symbolic(outputs: Outputs) -> tuple[list[sp.Expr], list[int]]:
    """A kernel's output expressions that are not numbers, and their places in ``_flat``.

    Numbers need no substitution, CSE or inlining, but each pass did its per-expression
    work on every one: a team's Hessian is almost all zeros (259 thousand of its 262
    thousand entries at 256 agents), and lowering it took longer than the objective's
    and gradient's kernels together.
    """
    flat = _flat(outputs)
    where = [i for i, e in enumerate(flat) if not isinstance(e, sp.Number)]
    return [flat[i] for i in where], where


def _scatter(outputs: Outputs, where: Sequence[int], reduced: Sequence[sp.Expr]) -> list[sp.Expr]:
    """The outputs, flat, with the reduced expressions put back at ``where``."""
    flat = _flat(outputs)
    for i, expr in zip(where, reduced, strict=True):
        flat[i] = expr
    return flat


def make_kernel(
    name: str,
    doc: str,
    inputs: Sequence[Arg],
    assignments: Sequence[Assignment],
    outputs: Outputs,
    subs: Mapping[sp.Symbol, sp.Expr],
    odd: dict[sp.Basic, sp.Expr] | None = None,
    search: bool = True,
    symbols: dict[sp.Basic, set[sp.Basic]] | None = None,
) -> Kernel:
    """Substitute slot symbols, CSE, and package a kernel.

    ``odd`` is the :func:`canonical_odd` memo shared by one controller's kernels, and
    ``symbols`` the memo of free symbols (:func:`_prune`): the kernels read the same
    programs. ``search=False`` skips sympy's search for common sub-sums
    (:func:`ordered_cse`).
    """
    exprs, where = _symbolic(outputs)
    program, flat = _prepare(assignments, exprs, subs, odd, symbols)
    before = operation_count([v for _, v in program] + flat)
    body, reduced = ordered_cse(program, flat, search)
    return _package(name, doc, inputs, outputs, body, _scatter(outputs, where, reduced), before)


def make_kernels(
    kernels: Sequence[tuple[str, str, Sequence[Arg], Outputs]],
    assignments: Sequence[Assignment],
    subs: Mapping[sp.Symbol, sp.Expr],
    odd: dict[sp.Basic, sp.Expr] | None = None,
    symbols: dict[sp.Basic, set[sp.Basic]] | None = None,
) -> list[Kernel]:
    """Kernels (name, doc, inputs, outputs) over one program, lowered together when large.

    ``odd`` and ``symbols`` are memos one controller's kernels share (:func:`make_kernel`).

    The jet kernel and the optimality error read the same gradient jet; lowered apart,
    each substitutes, numbers and inlines it anew (a third of lowering's time on a ring
    of 64 agents, half of it for a k = 12 chain). When every kernel is large enough
    for value numbering alone (:data:`SMALL_PROGRAM_OPS`), the program and all outputs
    are reduced once, and each kernel keeps what its outputs need, inlining what is
    then used once. Smaller kernels are made one by one, as :func:`make_kernel` would:
    sympy's fuller search suits them, and a union could pass its size limit.
    """
    symbolic = [_symbolic(outputs) for *_, outputs in kernels]
    sizes = [len(exprs) for exprs, _ in symbolic]
    # The kernels cut from one program share its nodes: each is walked once.
    symbols = {} if symbols is None else symbols
    program, flat = _prepare(
        assignments, [e for exprs, _ in symbolic for e in exprs], subs, odd, symbols
    )
    ends = list(itertools.accumulate(sizes))
    parts = [flat[end - size : end] for size, end in zip(sizes, ends, strict=True)]
    counts: dict[sp.Basic, int] = {}
    programs = [_prune(program, part, symbols) for part in parts]
    befores = [
        operation_count([v for _, v in mine] + part, counts)
        for mine, part in zip(programs, parts, strict=True)
    ]
    wheres = [where for _, where in symbolic]
    if len(kernels) < 2 or min(befores) <= SMALL_PROGRAM_OPS:
        made = []
        for (name, doc, inputs, outputs), mine, part, where, before in zip(
            kernels, programs, parts, wheres, befores, strict=True
        ):
            body, reduced = ordered_cse(mine, part)
            made.append(
                _package(
                    name, doc, inputs, outputs, body, _scatter(outputs, where, reduced), before
                )
            )
        return made
    order, outs = _reduce(program, flat, search=False, symbols=symbols)
    made = []
    for (name, doc, inputs, outputs), size, end, where, before in zip(
        kernels, sizes, ends, wheres, befores, strict=True
    ):
        mine = outs[end - size : end]
        body, reduced = _number(*_inline_single_use(_prune(order, mine, symbols), mine))
        made.append(
            _package(name, doc, inputs, outputs, body, _scatter(outputs, where, reduced), before)
        )
    return made


#: Inputs that are the same for every state of a batch (one time, one parameter vector).
_INVARIANT_INPUTS = ("t", "p", "a")


def split_invariant(kernel: Kernel, name: str, doc: str) -> tuple[Kernel, Kernel] | None:
    """Split off the part of ``kernel`` that depends on time and parameters alone.

    A batch of states at one time shares everything that does not involve the state:
    the signals and their derivatives, a switch such as ``tanh((t - a)/b)``, sums of
    such terms inside a state-dependent expression. Those become a kernel of
    :data:`_INVARIANT_INPUTS` that returns them as one array ``tau``; the remaining
    kernel reads ``tau`` as an input. Temporaries keep their names; a hoisted sub-sum or
    sub-product of a larger expression gets a name ``_h0, _h1, ...``.

    Returns
    -------
    (Kernel, Kernel) or None
        The invariant kernel ``name`` and the rest (``kernel``'s name, inputs plus
        ``tau``), or None when nothing would be shared.
    """
    invariant_args = [arg for arg in kernel.inputs if arg.name in _INVARIANT_INPUTS]
    given: set[sp.Basic] = {sym for arg in invariant_args for sym in arg.symbols}
    given.add(sp.Symbol("t", real=True))
    invariant = set(given)
    time_body: list[Assignment] = []
    for sym, value in kernel.body:
        if value.free_symbols <= invariant:
            invariant.add(sym)
            time_body.append((sym, value))
    if not time_body:
        return None
    names = fresh_symbols("_h")
    shared: dict[sp.Expr, sp.Symbol] = {}  # invariant value -> the state part's name for it
    memo: dict[sp.Basic, sp.Expr] = {}

    known: dict[sp.Basic, bool] = {}

    def fixed(node: sp.Basic) -> bool:
        # Bottom-up and memoized: sympy's free_symbols walks the whole subtree on every
        # call, which made hoisting quadratic in an expression's depth.
        if not node.args:
            return not node.is_Symbol or node in invariant
        found = known.get(node)
        if found is None:
            found = known[node] = all(fixed(arg) for arg in node.args)
        return found

    def share(node: sp.Expr) -> sp.Expr:
        # Numbers and the inputs themselves are at hand in the state part already.
        if node.is_Number or node in given:
            return node
        if node not in shared:
            shared[node] = node if node in invariant else next(names)
        return shared[node]

    def hoist(node: sp.Basic) -> sp.Expr:
        if node.is_Atom:
            return share(node) if node.is_Symbol and node in invariant else node
        if node in memo:
            return memo[node]
        if fixed(node):
            new = share(node)
        elif (node.is_Add or node.is_Mul) and any(fixed(a) for a in node.args):
            # (x + t + 1) -> x + _h0: the invariant terms or factors become one.
            part = [a for a in node.args if fixed(a)]
            rest = [hoist(a) for a in node.args if not fixed(a)]
            new = _rebuild(node, [*rest, share(_rebuild(node, part))])
        else:
            args = [hoist(a) for a in node.args]
            # Nothing hoisted below: the node as it is (rebuilding would give it back).
            new = node if unchanged(node, args) else _rebuild(node, args)
        memo[node] = new
        return new

    state_body = tuple((sym, hoist(value)) for sym, value in kernel.body if sym not in invariant)
    state_outputs = tuple(
        Output(out.name, out.shape, tuple(hoist(sp.sympify(e)) for e in out.exprs), out.doc)
        for out in kernel.outputs
    )
    release(hoist)
    release(fixed)
    tau_values = list(shared)
    time_program = _prune(time_body, tau_values)
    tau = Output("tau", (len(tau_values),), tuple(tau_values), "terms of time and parameters")
    time_ops = operation_count([v for _, v in time_program] + tau_values)
    time_kernel = Kernel(
        name, doc, tuple(invariant_args), tuple(time_program), (tau,), time_ops, time_ops
    )
    arg_tau = Arg(
        "tau",
        tuple(shared.values()),
        tuple(f"{name} tau[{i}]" for i in range(len(shared))),
        f"terms of time and parameters alone ({name})",
    )
    state_ops = operation_count(
        [v for _, v in state_body] + [e for o in state_outputs for e in o.exprs]
    )
    state_kernel = Kernel(
        kernel.name,
        kernel.doc,
        (*kernel.inputs, arg_tau),
        state_body,
        state_outputs,
        state_ops,
        kernel.ops_before_cse - time_ops,
    )
    return time_kernel, state_kernel
