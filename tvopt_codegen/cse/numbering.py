"""Ordered common-subexpression elimination, in evaluation order.

Value numbering, merging equal values and inlining values used once.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from typing import Any

from tvopt_codegen import symbolic as sx
from tvopt_codegen.cse.dag import Dag, Program
from tvopt_codegen.cse.programs import (
    drop_aliases,
    inline_single_use,
    inline_waves,
    leaves,
    needed,
    value_numbering,
)
from tvopt_codegen.cse.rewrite import (
    _NEGATED_TERMS,
    _expr,
    _negate,
    _negated_atom,
    _rebuild,
    _replace_all,
    _same,
    _substitute,
    _unchanged,
    operation_count,
)
from tvopt_codegen.maths.jet import Assignment, release


def numbered(prefix: str) -> Iterator[sx.Expr]:
    """Endless real symbols ``prefix0, prefix1, ...`` of the engine."""
    index = 0
    while True:
        yield sx.symbol(f"{prefix}{index}")
        index += 1


def _drop_aliases(
    assignments: Sequence[Assignment], outputs: Sequence[sx.Expr]
) -> tuple[list[Assignment], list[sx.Expr]]:
    """Substitute assignments whose value is a bare symbol or constant, or its negation."""
    if sx.SYMENGINE:
        return _drop_aliases_in_rounds(assignments, outputs)
    alias: dict[sx.Expr, sx.Expr] = {}
    kept: list[Assignment] = []
    # One memo for the whole program: in evaluation order a node can only hold symbols
    # assigned before it, whose aliases are all decided when it is first met.
    memo: dict[sx.Expr, sx.Expr] = {}
    for sym, raw in assignments:
        value = _substitute(raw, alias, memo)
        if value.is_Atom or _negated_atom(value):
            alias[sym] = value
        else:
            kept.append((sym, value))
    return kept, [_substitute(e, alias, memo) for e in outputs]


def _prune(
    assignments: Sequence[Assignment],
    outputs: Sequence[sx.Expr],
    symbols: dict[sx.Expr, set[sx.Expr]] | None = None,
) -> list[Assignment]:
    """Drop assignments that no output needs (signal orders a kernel does not use).

    ``symbols`` (expression -> its free symbols) may span calls over the same program:
    sympy walks the tree anew each time it is asked. SymEngine's walk is in C++ and
    is not memoised (see below).
    """
    known: dict[sx.Expr, set[sx.Expr]] = {} if symbols is None else symbols

    def free(expr: sx.Expr) -> set[sx.Expr]:
        found = known.get(expr)
        if found is None:
            found = known[expr] = _expr(expr).free_symbols
        return found

    if sx.SYMENGINE:
        # SymEngine's free_symbols is one walk in C++, shared nodes once; a dictionary
        # hit on an expression that is equal but not the same object compares the two
        # trees whole, which cost more than the walk (ten times, on a chain's jet).
        def free(expr: sx.Expr) -> set[sx.Expr]:  # noqa: F811
            return set(_expr(expr).free_symbols)

    needed: set[sx.Expr] = set()
    for e in outputs:
        needed |= free(e)
    kept: list[Assignment] = []
    for sym, value in reversed(assignments):
        if sym in needed:
            kept.append((sym, value))
            needed |= free(value)
    return kept[::-1]


#: Programs up to this many operations get the engine's full cse; larger ones value numbering.
SMALL_PROGRAM_OPS = 1000


def ordered_cse(
    assignments: Sequence[Assignment], outputs: Sequence[sx.Expr], search: bool = True
) -> tuple[tuple[Assignment, ...], tuple[sx.Expr, ...]]:
    """CSE a straight-line program and its outputs, keeping evaluation order valid.

    One pass of the engine's ``cse`` (:func:`~tvopt_codegen.symbolic.cse`) sees every
    right-hand side and output. A common subexpression found in an assignment only uses
    symbols defined before it, so each extracted temporary is emitted just before its
    first use. Temporaries are then renamed ``_t0, _t1, ...`` in emission order, which
    makes the text deterministic (on SymEngine too: its argument order comes from its
    C++ hashes of the expressions, the same in every run, never Python's).

    Parameters
    ----------
    assignments : sequence of (symbol, expression)
        The program; right-hand sides use only earlier symbols and the inputs.
    outputs : sequence of expressions
        Output expressions over the program and the inputs.
    search : bool
        Allow the engine's ``cse`` (on programs up to :data:`SMALL_PROGRAM_OPS`), which
        also finds common parts of sums and products. A program built one operation per
        assignment (the Cholesky solve) has none to find: value numbering suffices.

    Returns
    -------
    body : tuple of (symbol, expression)
        The temporaries in evaluation order.
    outputs : tuple of expressions
        The reduced outputs.
    """
    if sx.SYMENGINE:
        dag = Dag()
        program = [(dag.intern(sym), dag.intern(_expr(value))) for sym, value in assignments]
        order, outs = _reduce_dag(dag, program, [dag.intern(_expr(e)) for e in outputs], search)
        return _number_dag(dag, order, outs)
    return _number(*_reduce(assignments, outputs, search))


def _reduce_dag(
    dag: Dag,
    program: Program,
    outputs: Sequence[int],
    search: bool,
    prefix: str = "_cse",
    pruned: bool = False,
) -> tuple[Program, list[int]]:
    """:func:`_reduce` on SymEngine, over the ids of ``dag``: the same steps, on ints.

    A program that may be searched and, inlined, is small enough for the engine's
    search (:data:`SMALL_PROGRAM_OPS`) is searched (once more) after inlining, its
    temporaries named ``prefix`` apart from the first search's. Inlining flattens
    products: SymEngine's derivation associates ``pi*p0*g/p1`` as ``pi*(g/p1)`` times
    ``p0``, each a temporary used once, and the products that result share
    ``pi*p0/p1``, which only a search of the inlined program finds (a ring of four
    unicycles: 1920 operations, 1616 so; SymPy's 1735).

    ``pruned`` says that ``program`` is what ``outputs`` need already
    (:func:`.programs.needed`): the callers that counted its operations first have
    walked it, and a walk of a jet's DAG is not free.
    """
    if not pruned:
        program = needed(dag, program, outputs)
    kept, outs = drop_aliases(dag, *dag.distribute(program, outputs))
    exprs = [value for _, value in kept] + outs
    names = numbered(prefix)
    searched = search and dag.operations(exprs) <= SMALL_PROGRAM_OPS
    if searched:
        found, cut = sx.cse([dag.expression(e) for e in exprs], names)
        replacements = [(dag.intern(sym), dag.intern(value)) for sym, value in found]
        reduced = [dag.intern(e) for e in cut]
    else:
        replacements, reduced = value_numbering(dag, exprs, names)
    defined = dict(replacements)

    def missing(expr: int, emitted: set[int]) -> list[int]:
        return [s for s in leaves(dag, expr, defined) if s not in emitted]

    order, outs = _emitted(
        kept, reduced, defined, missing, lambda s: _cse_index(dag.expr[s], prefix)
    )
    order, outs = _merged_and_inlined(
        order, outs, dag.merge_equal, functools.partial(inline_single_use, dag)
    )
    if (
        search
        and prefix == "_cse"
        and dag.operations([value for _, value in order] + outs) <= SMALL_PROGRAM_OPS
    ):
        return _reduce_dag(dag, order, outs, search, "_cse_again")
    return order, outs


def _number_dag(
    dag: Dag,
    order: Program,
    outs: Sequence[int],
    rename: Mapping[sx.Expr, sx.Expr] | None = None,
) -> tuple[tuple[Assignment, ...], tuple[sx.Expr, ...]]:
    """:func:`_number` of a program on ids: its expressions, temporaries renamed."""
    expr = dag.expression
    return _number([(expr(s), expr(v)) for s, v in order], [expr(e) for e in outs], rename)


def _reduce(
    assignments: Sequence[Assignment],
    outputs: Sequence[sx.Expr],
    search: bool,
    symbols: dict[sx.Expr, set[sx.Expr]] | None = None,
) -> tuple[list[Assignment], list[sx.Expr]]:
    """:func:`ordered_cse` up to naming: temporaries in evaluation order, reduced outputs.

    ``symbols`` is :func:`_prune`'s memo of free symbols, when the caller has one.
    """
    kept, outs = _drop_aliases(_prune(assignments, outputs, symbols), outputs)
    exprs = [value for _, value in kept] + outs
    names = numbered("_cse")
    if search and operation_count(exprs) <= SMALL_PROGRAM_OPS:
        # The engine's cse also finds common parts of sums and products (a*b in a*b*c
        # and a*b*d): worth its superlinear time on the programs of a few agents only.
        replacements, reduced = sx.cse(exprs, names)
    else:
        replacements, reduced = _value_numbering(exprs, names)
    defined = dict(replacements)

    def missing(expr: sx.Expr, emitted: set[sx.Expr]) -> list[sx.Expr]:
        # Not free_symbols & defined.keys() - emitted: "-" binds first, and the difference
        # of the two large sets, once per value, was quadratic in the program's size.
        return [s for s in expr.free_symbols if s in defined and s not in emitted]

    order, outs = _emitted(kept, reduced, defined, missing, _cse_index)
    order, outs = _merged_and_inlined(order, outs, _merge_equal, _inline_single_use)
    return order, outs


def _emitted(
    kept: Sequence[tuple[Any, Any]],
    reduced: Sequence[Any],
    defined: dict[Any, Any],
    missing: Callable[[Any, set[Any]], list[Any]],
    index: Callable[[Any], int],
) -> tuple[list[tuple[Any, Any]], list[Any]]:
    """The reduced program in evaluation order, each temporary before its first reader.

    ``kept`` are the program's assignments and ``reduced`` their values then the
    outputs, after the search; ``defined`` the search's temporaries, ``missing`` those an
    expression reads that are not yet emitted, ``index`` their order. The same steps on
    expressions (SymPy's path) and on the DAG's ids (SymEngine's).
    """
    order: list[tuple[Any, Any]] = []
    emitted: set[Any] = set()

    def need(expr: Any) -> None:
        for sym in sorted(missing(expr, emitted), key=index):
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
    return order, list(reduced[len(kept) :])


def _merged_and_inlined(
    order: list[tuple[Any, Any]],
    outs: list[Any],
    merge: Callable[..., tuple[list[tuple[Any, Any]], list[Any]]],
    inline: Callable[..., tuple[list[tuple[Any, Any]], list[Any]]],
) -> tuple[list[tuple[Any, Any]], list[Any]]:
    """Merge equal values and inline single uses, alternately, to a fixed point.

    Merging equal values can leave a temporary with one use, and inlining can make two
    values equal (two rounds in practice). Each pass reaches its own fixed point, and
    inlining changes the program exactly when it removes a temporary: a round whose
    inlining removed none ends the loop. So does a merge that changed nothing after an
    inlining: that inlining's fixed point is the program still, and inlining it again
    (a pass over every value) would find nothing; most kernels end so.
    """
    inlined = False
    while True:
        merged, merged_outs = merge(order, outs)
        if inlined and merged == order and merged_outs == outs:
            return merged, merged_outs
        size = len(merged)
        order, outs = inline(merged, merged_outs)
        inlined = True
        if len(order) == size:
            return order, outs


def _number(
    order: Sequence[Assignment],
    outs: Sequence[sx.Expr],
    rename: Mapping[sx.Expr, sx.Expr] | None = None,
) -> tuple[tuple[Assignment, ...], tuple[sx.Expr, ...]]:
    """Rename the temporaries ``_t0, _t1, ...`` in evaluation order.

    ``rename`` renames inputs in the same walk: a kernel cut from another's program
    (:func:`.assembly.make_kernels`' riders) reads its own arguments' symbols.
    """
    if sx.SYMENGINE:
        names = _temporaries(len(order))
        # Each value holds only symbols renamed before it: one renaming of all at once.
        mapping = {sym: name for (sym, _), name in zip(order, names, strict=True)}
        values = _replace_all(
            [value for _, value in order] + list(outs), mapping | dict(rename or {})
        )
        return tuple(zip(names, values[: len(order)], strict=True)), tuple(values[len(order) :])
    renames: dict[sx.Expr, sx.Expr] = dict(rename or {})
    body: list[Assignment] = []
    # One memo, as in _drop_aliases: a node holds only symbols renamed before it is met.
    memo: dict[sx.Expr, sx.Expr] = {}
    for index, (sym, value) in enumerate(order):
        new = sx.symbol(f"_t{index}")
        body.append((new, _substitute(value, renames, memo)))
        renames[sym] = new
    return tuple(body), tuple(_substitute(e, renames, memo) for e in outs)


#: The symbols ``_t0, _t1, ...`` made so far, by engine: every kernel's temporaries are
#: named from 0, and making the symbols anew for each kernel was a hundredth of lowering.
_NAMES: dict[bool, list[sx.Expr]] = {}


def _temporaries(count: int) -> list[sx.Expr]:
    """The engine's symbols ``_t0 .. _t{count - 1}``."""
    names = _NAMES.setdefault(sx.SYMENGINE, [])
    names.extend(sx.symbol(f"_t{index}") for index in range(len(names), count))
    return names[:count]


def _value_numbering(
    exprs: Sequence[sx.Expr], names: Iterable[sx.Expr]
) -> tuple[list[Assignment], list[sx.Expr]]:
    """Common subexpression elimination by value numbering, linear in the DAG size.

    Every compound subexpression that occurs more than once becomes a temporary. This
    is the tree pass of ``sympy.cse`` without its search for common subsets of sums
    and products, which is quadratic in their number of terms and took minutes on a
    ring of three agents (issue 7). The jet arrives in three-address form, where
    such subsets are already separate assignments, so little is lost.
    """
    names = iter(names)
    seen: set[sx.Expr] = set()
    repeated: set[sx.Expr] = set()

    def worth(node: sx.Expr) -> bool:
        # A negated symbol or number is not worth a temporary: printing it is free.
        return not (node.is_Atom or _negated_atom(node))

    def find(node: sx.Expr) -> None:
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
    built: dict[sx.Expr, sx.Expr] = {}
    same = _same()

    def build(node: sx.Expr) -> sx.Expr:
        if node.is_Atom:
            return node
        if node in built:
            return built[node]
        own = node.args
        args = [build(arg) for arg in own]
        new = node if _unchanged(same, own, args) else _rebuild(node, args)
        if node in repeated:
            sym = next(names)
            replacements.append((sym, new))
            new = sym
        built[node] = new
        return new

    reduced = [build(_expr(e)) for e in exprs]
    release(build)
    return replacements, reduced


def _merge_equal(
    order: list[Assignment], outputs: list[sx.Expr]
) -> tuple[list[Assignment], list[sx.Expr]]:
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
    first: dict[sx.Expr, sx.Expr] = {}
    rename: dict[sx.Expr, sx.Expr] = {}
    # A node is rewritten once: a renamed symbol is only used after its assignment,
    # so no node seen before a rename can contain it.
    memo: dict[sx.Expr, sx.Expr] = {}
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


def _drop_aliases_in_rounds(
    order: Sequence[Assignment], outputs: Sequence[sx.Expr]
) -> tuple[list[Assignment], list[sx.Expr]]:
    """:func:`_drop_aliases` on SymEngine: aliases found in rounds, substituted in C++.

    Substituting each value as it is met is a Python walk of its nodes, microseconds
    each on SymEngine. Here each round finds the values that are aliases, then
    substitutes them into every value at once (:func:`_replace_all`: an alias is a
    symbol, a number or a negated one, nothing for a number to distribute over), until
    a round finds none: a value that becomes an alias only once an earlier one is
    substituted (``a + b`` with ``b = -a``) waits for the next round. The program
    arrives in three-address form, where that is rare: one round, or two. (Merging equal
    values, whose matches turn up the next ones a level at a time, a dozen levels in a
    chain's jet, stays one pass: :func:`_merge_equal`.)
    """
    symbols = [sym for sym, _ in order]
    values = [value for _, value in order]
    rename: dict[sx.Expr, sx.Expr] = {}
    kept = list(range(len(order)))
    while True:
        found = {
            symbols[i]: values[i] for i in kept if values[i].is_Atom or _negated_atom(values[i])
        }
        if not found:
            break
        # An alias may be of a symbol aliased in the same round, always an earlier one:
        # in evaluation order, one lookup each resolves them all.
        rename.update(found)
        for sym in symbols:
            target = rename.get(sym)
            if target is not None:
                rename[sym] = _resolved(target, rename)
        kept = [i for i in kept if symbols[i] not in found]
        fresh = _replace_all([values[i] for i in kept], rename)
        for i, value in zip(kept, fresh, strict=True):
            values[i] = value
    return [(symbols[i], values[i]) for i in kept], _replace_all(list(outputs), rename)


def _resolved(target: sx.Expr, rename: dict[sx.Expr, sx.Expr]) -> sx.Expr:
    """``target`` (a symbol, a number, or a negated one) with its symbol renamed."""
    if target.is_Symbol:
        return rename.get(target, target)
    if _negated_atom(target):
        inner = rename.get(target.args[1])
        if inner is not None:
            return -inner
    return target


def _occurrences(expr: sx.Expr, position: dict[sx.Expr, int]) -> dict[int, int]:
    """How often each temporary occurs in ``expr`` as a tree: ``x*x`` uses ``x`` twice.

    Temporaries are counted by their place in the program (``position``): the counts
    are then kept by integer, where a symbol as key cost a comparison of two SymEngine
    objects at every hit (each ``.args`` gives new ones). A plain stack walk: sympy's
    ``preorder_traversal`` costs a generator step per node, and this counts every value
    of a program (a fifth of inlining's time).
    """
    # A plain dict: building a Counter (a Python-level __init__) for every value of a
    # program was a tenth of inlining's time.
    found: dict[int, int] = {}
    stack = [expr]
    while stack:
        node = stack.pop()
        args = node.args
        if args:
            stack.extend(args)
        elif node.is_Symbol:
            i = position.get(node)
            if i is not None:
                found[i] = found.get(i, 0) + 1
    return found


def _inline_single_use(
    order: list[Assignment], outputs: list[sx.Expr]
) -> tuple[list[Assignment], list[sx.Expr]]:
    """Substitute temporaries used exactly once back into their one user; drop the unused.

    The jet is derived in three-address form (one operation per assignment), which
    makes differentiation linear; printed that way, every operation would become a
    named array in NumPy. Shared work stays in temporaries; the rest reads as the
    expression it is.

    Inlining can collect terms: ``a + 2*(a + b)`` becomes ``3*a + 3*b``, and ``a``,
    used twice before, is now used once. A pass over the whole program finds one level
    of such temporaries at a time (a k = 12 jet needed a dozen). Here every
    expression's counts of temporaries are kept; after the first wave, each wave
    substitutes into the expressions the last one changed, until no temporary is used
    once.
    """
    return inline_waves(order, outputs, _substitute, _occurrences)


def _cse_index(sym: sx.Expr, prefix: str = "_cse") -> int:
    return int(sym.name[len(prefix) :])
