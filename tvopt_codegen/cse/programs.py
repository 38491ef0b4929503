"""Passes over a straight-line program on a :class:`~.dag.Dag`'s ids.

What :mod:`~tvopt_codegen.cse.numbering` does to a program of expressions, done to the
ids of one DAG, step for step: pruning to what the outputs need, the symbols a kernel
reads, aliases dropped, value numbering, and temporaries used once inlined wave after
wave (:func:`inline_waves`, the one algorithm for both representations). The table and
its algebra (reading, rebuilding, negation, merging) are :class:`~.dag.Dag`'s.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Iterable, Iterator, Sequence
from typing import Any

from tvopt_codegen import symbolic as sx
from tvopt_codegen.cse.dag import _MUL, _SYMBOL, Dag, Program
from tvopt_codegen.maths.jet import release


def needed(dag: Dag, program: Program, outputs: Sequence[int]) -> Program:
    """:func:`~.numbering._prune` on ids: the assignments the outputs need."""
    args = dag.args
    # Marks by id (the table's ids are dense): cheaper than a set's hashing.
    seen = bytearray(len(args))
    # One walk of the nodes the outputs and the kept values hold, each node once; a
    # kept value's nodes are pushed on the one stack (no call per assignment).
    stack = list(outputs)
    kept: Program = []
    for sym, value in [(-1, -1), *reversed(program)]:
        if sym >= 0:
            if not seen[sym]:
                continue
            kept.append((sym, value))
            stack.append(value)
        while stack:
            node = stack.pop()
            if not seen[node]:
                seen[node] = 1
                stack.extend(args[node])
    return kept[::-1]


def symbols_read(dag: Dag, program: Program, outputs: Sequence[int]) -> set[sx.Expr]:
    """The symbols ``program`` and ``outputs`` read besides the program's own.

    One walk of the ids, each node once, for :func:`~.assembly._package`'s check of
    unbound symbols: SymEngine's ``free_symbols`` of the kernel's expressions walked
    them in C++, its set of seen nodes slowed by the sums' colliding hashes
    (:meth:`.Dag.intern`).
    """
    kind = dag.kind
    roots = [value for _, value in program] + list(outputs)
    found = {leaf for leaf in _leaves(dag, roots) if kind[leaf] == _SYMBOL}
    found.difference_update(sym for sym, _ in program)
    return {dag.expression(i) for i in found}


def drop_aliases(dag: Dag, program: Program, outputs: Sequence[int]) -> tuple[Program, list[int]]:
    """:func:`~.numbering._drop_aliases` on ids."""
    alias: dict[int, int] = {}
    memo: dict[int, int] = {}
    kept: Program = []
    for sym, raw in program:
        value = dag.substitute(raw, alias, memo)
        if dag.trivial(value):
            alias[sym] = value
        else:
            kept.append((sym, value))
    return kept, [dag.substitute(e, alias, memo) for e in outputs]


def value_numbering(
    dag: Dag, exprs: Sequence[int], names: Iterable[sx.Expr]
) -> tuple[Program, list[int]]:
    """:func:`~.numbering._value_numbering` on ids: repeated compound nodes named."""
    args, kind = dag.args, dag.kind
    minus_one = dag.minus_one
    names = iter(names)
    seen: set[int] = set()
    repeated: set[int] = set()
    for expr in exprs:
        stack = [expr]
        while stack:
            node = stack.pop()
            own = args[node]
            # Dag.trivial written out (a leaf, or minus a leaf): a call of it and of
            # negated_atom for every node, leaves too, was a third of this walk.
            if not own or (
                kind[node] == _MUL and len(own) == 2 and own[0] == minus_one and not args[own[1]]
            ):
                continue
            if node in seen:
                repeated.add(node)
                continue
            seen.add(node)
            stack.extend(own)
    replacements: Program = []
    built: dict[int, int] = {}

    def build(node: int) -> int:
        own = args[node]
        if not own:
            return node
        done = built.get(node)
        if done is not None:
            return done
        new = tuple([build(c) for c in own])
        done = node if new == own else dag.rebuild(node, new)
        if node in repeated:
            sym = dag.intern(next(names))
            replacements.append((sym, done))
            done = sym
        built[node] = done
        return done

    built_exprs = [build(e) for e in exprs]
    release(build)
    return replacements, built_exprs


def leaves(dag: Dag, root: int, wanted: dict[int, int]) -> list[int]:
    """The leaves of ``root`` that are keys of ``wanted``, each once, in :func:`_leaves`' order.

    Its own loop, not a filter of :func:`_leaves`: it is asked of every value of a
    program (:func:`.numbering._emitted`), and a generator's step per leaf was most of it.
    """
    if not wanted:
        return []
    args = dag.args
    if not args[root]:
        return [root] if root in wanted else []
    seen: set[int] = set()
    found: list[int] = []
    stack = [root]
    while stack:
        node = stack.pop()
        if node in seen:
            continue
        seen.add(node)
        own = args[node]
        if own:
            stack.extend(own)
        elif node in wanted:
            found.append(node)
    return found


def _leaves(dag: Dag, roots: list[int]) -> Iterator[int]:
    """The leaves under ``roots``, each once (one walk on one stack, each node once)."""
    args = dag.args
    seen: set[int] = set()
    stack = roots
    while stack:
        node = stack.pop()
        if node in seen:
            continue
        seen.add(node)
        own = args[node]
        if own:
            stack.extend(own)
        else:
            yield node


def occurrences(dag: Dag, root: int, position: dict[int, int]) -> dict[int, int]:
    """:func:`~.numbering._occurrences` on ids: each temporary's uses in ``root``.

    Temporaries are counted by their place in the program (``position``, symbol ->
    place), from the symbols' counts in ``root``, which are kept: the kernels cut
    from one program count the same values again.
    """
    get = position.get
    return {
        i: times for sym, times in dag.symbol_counts(root).items() if (i := get(sym)) is not None
    }


def inline_single_use(dag: Dag, order: Program, outputs: list[int]) -> tuple[Program, list[int]]:
    """:func:`~.numbering._inline_single_use` on ids."""
    return inline_waves(order, outputs, dag.substitute, functools.partial(occurrences, dag))


def inline_waves(
    order: Sequence[tuple[Any, Any]],
    outputs: Sequence[Any],
    substitute: Callable[[Any, dict[Any, Any], dict[Any, Any]], Any],
    occurrences: Callable[[Any, dict[Any, int]], dict[int, int]],
) -> tuple[list[tuple[Any, Any]], list[Any]]:
    """Inline temporaries used once, wave after wave (:func:`.numbering._inline_single_use`).

    The one algorithm for both representations: expressions (``substitute`` and
    ``occurrences`` of :mod:`.numbering`) and the DAG's ids (:class:`~.dag.Dag`'s).
    """
    n = len(order)
    values: list[Any] = [value for _, value in order] + list(outputs)
    position = {sym: i for i, (sym, _) in enumerate(order)}
    counts = [occurrences(value, position) for value in values]
    uses = [0] * n
    holders: list[set[int]] = [set() for _ in range(n)]
    for i, count in enumerate(counts):
        for j, times in count.items():
            uses[j] += times
            holders[j].add(i)
    gone: set[int] = set()
    wave = {i for i in range(n) if uses[i] <= 1}
    while wave:
        inline: dict[Any, Any] = {}
        # One memo for the wave: in evaluation order a node holds only earlier
        # symbols, whose values are final when it is first met (as in _drop_aliases).
        memo: dict[Any, Any] = {}
        users: set[int] = set()
        changed: set[int] = set()
        for i in sorted(wave):
            inline[order[i][0]] = substitute(values[i], inline, memo)
            users |= holders[i]
            gone.add(i)
            # update, not |=: a set |= a dict's keys copies the set, each time.
            changed.update(counts[i])
            for j, times in counts[i].items():
                uses[j] -= times
                holders[j].discard(i)
        for user in sorted(users - gone):
            before = counts[user]
            values[user] = substitute(values[user], inline, memo)
            after = counts[user] = occurrences(values[user], position)
            for j in before.keys() | after.keys():
                was, now = before.get(j, 0), after.get(j, 0)
                if was != now:
                    uses[j] += now - was
                    changed.add(j)
                if not now:
                    holders[j].discard(user)
                elif not was:
                    holders[j].add(user)
        wave = {j for j in changed if j not in gone and uses[j] <= 1}
    kept = [(order[i][0], values[i]) for i in range(n) if i not in gone]
    return kept, values[n:]
