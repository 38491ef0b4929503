"""Sparse linear algebra, generated: the LDL^T program of the Hessian and LU costs.

The generated controller never inverts a matrix symbolically. ``Hess z = c`` is solved by
a straight-line, square-root-free sparse Cholesky (:func:`cholesky_program`) in an
elimination order chosen to fill little (:func:`elimination_order`); ``R w = b`` by LU
with partial pivoting at run time, block by diagonal block, whose cost
:func:`lu_operations` counts.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence

import numpy as np

from tvopt_codegen import symbolic as sx
from tvopt_codegen.maths.jet import Assignment, fresh_symbols


def lu_operations(size: int) -> int:
    """Operations of the generated LU solve with partial pivoting of one block."""
    factor = sum(1 + 2 * (size - j) + 2 for j in range(size) for _ in range(j + 1, size))
    return factor + sum(2 * (size - j - 1) + 1 for j in range(size))


def _fill(pattern: set[tuple[int, int]], order: Sequence[int]) -> list[list[int]]:
    """Column patterns of the Cholesky factor of a symmetric pattern in a given order.

    ``pattern`` holds the structurally nonzero ``(i, j)`` of the matrix; the result
    lists, for each column ``b`` of the permuted factor, the rows ``a > b`` that are
    nonzero in L (the matrix's own entries plus fill from elimination).
    """
    position = {index: a for a, index in enumerate(order)}
    below: list[set[int]] = [set() for _ in order]
    for i, j in pattern:
        a, b = position[i], position[j]
        if a > b:
            below[b].add(a)
    columns: list[list[int]] = []
    for b in range(len(order)):
        rows = sorted(below[b])
        columns.append(rows)
        # Eliminating b connects all its later neighbours: that is the fill.
        for x, first in enumerate(rows):
            for second in rows[x + 1 :]:
                below[first].add(second)
    return columns


def elimination_order(
    pattern: set[tuple[int, int]], m: int, leading: int | None = None
) -> tuple[int, ...]:
    """Order the Cholesky elimination: natural, or reverse Cuthill-McKee if it fills less.

    With ``leading``, indices ``0 .. leading - 1`` are eliminated first, each block ordered
    on its own (a KKT matrix: the outputs' block, positive definite, before the
    multipliers', whose diagonal is zero until the elimination fills it).
    """
    if leading is not None and 0 < leading < m:
        first = {(i, j) for i, j in pattern if i < leading and j < leading}
        second = {(i - leading, j - leading) for i, j in pattern if i >= leading and j >= leading}
        return (
            *elimination_order(first, leading),
            *(leading + i for i in elimination_order(second, m - leading)),
        )
    natural = tuple(range(m))

    def size(order: Sequence[int]) -> int:
        return sum(len(c) for c in _fill(pattern, order))

    # No order fills less than none: then the natural one stands.
    entries = len({(max(i, j), min(i, j)) for i, j in pattern if i != j})
    fill = size(natural)
    if fill == entries:
        return natural
    rcm = reverse_cuthill_mckee(pattern, m)
    return rcm if size(rcm) < fill else natural


def reverse_cuthill_mckee(pattern: set[tuple[int, int]], m: int) -> tuple[int, ...]:
    """The reverse Cuthill-McKee order of a symmetric pattern (Cuthill and McKee, 1969).

    Breadth first from each node not yet reached, seeds taken by increasing degree; a
    node's unreached neighbours join in index order, then sorted stably by degree; the
    whole order reversed. The ties are broken as ``scipy.sparse.csgraph`` breaks them (a
    test holds the two equal), so the generated code is the same as when scipy chose
    the order: importing scipy's sparse package was a tenth of a small team's command.
    A node's degree counts its diagonal entry twice, as scipy's does.
    """
    neighbours: list[list[int]] = [[] for _ in range(m)]
    for i, j in sorted(pattern):
        neighbours[i].append(j)
    degree = np.array([len(row) + (i in row) for i, row in enumerate(neighbours)], dtype=np.int32)
    # numpy's argsort as scipy calls it: its order among equal degrees is the seeds'.
    seeds = [int(i) for i in np.argsort(degree)]
    reached = [False] * m
    order: list[int] = []
    for seed in seeds:
        if reached[seed]:
            continue
        reached[seed] = True
        order.append(seed)
        head = len(order) - 1
        while head < len(order):
            node = order[head]
            head += 1
            fresh = [j for j in neighbours[node] if not reached[j]]
            for j in fresh:
                reached[j] = True
            order.extend(sorted(fresh, key=lambda j: degree[j]))
    return tuple(order[::-1])


def cholesky_program(
    entries: Sequence[tuple[int, int]],
    m: int,
    h: Sequence[sx.Expr],
    c: Sequence[sx.Expr],
    leading: int | None = None,
) -> tuple[list[Assignment], list[sx.Expr], list[sx.Expr]]:
    """A straight-line sparse, square-root-free Cholesky (LDL^T) solve of ``Hess z = c``.

    Parameters
    ----------
    entries : sequence of (int, int)
        The structurally nonzero ``(i, j)``, ``i >= j``, of the symmetric matrix, in the
        order of its input symbols ``h``.
    m : int
        The matrix size.
    h, c : sequence of symbol
        Symbols of the entries and of the right-hand side.
    leading : int, optional
        Eliminate indices below this first (see :func:`elimination_order`): the pivots
        of a KKT matrix are then positive for the outputs and negative for the
        multipliers, in that order.

    Returns
    -------
    assignments : list of (symbol, expression)
        The factorization and both triangular solves, one small expression each.
    z : list of expression
        The solution, in the matrix's own order.
    pivots : list of expression
        ``D_b = A_bb - sum_k L_bk^2 D_k`` of each elimination step, the squares of the
        pivots of the classical Cholesky factor: the matrix is positive definite (to the
        tolerance) when every one is positive, checked by the caller before the result
        is used.

    Notes
    -----
    ``Hess = L D L^T`` with unit lower-triangular ``L``: one reciprocal per pivot and no
    square root, where the classical factor needs ``1/sqrt`` per pivot (a ``pow`` call
    in C, several times the cost of a division). Only the entries of L that the pattern
    and its fill make nonzero are formed, in an elimination order chosen to fill little
    (:func:`elimination_order`): for a ring of agents that is linear in their number
    where a dense factorization is cubic.
    """
    program, (z,), pivots = ldl_program(entries, m, h, [c], leading)
    return program, z, pivots


def _minus(first: sx.Expr, products: Iterable[tuple[sx.Expr, sx.Expr]]) -> sx.Expr:
    """``first - sum(a*b)``, each product negated on its own: ``first - a*b - c*d``.

    SymEngine keeps ``x - (a*b + c*d)`` as a negated sum, which lowering distributes again
    (:meth:`.Dag.distribute`, a rebuild of every elimination step); SymPy's ``Mul``
    distributes it itself. Built distributed, both engines give the same sum at once.
    """
    return sx.Add(first, *(-(a * b) for a, b in products))


def ldl_program(
    entries: Sequence[tuple[int, int]],
    m: int,
    h: Sequence[sx.Expr],
    rhs: Sequence[Sequence[sx.Expr]],
    leading: int | None = None,
    prefix: str = "_chol",
) -> tuple[list[Assignment], list[list[sx.Expr]], list[sx.Expr]]:
    """:func:`cholesky_program` for several right-hand sides: one factorization, a solve each.

    Parameters
    ----------
    entries, m, leading
        As for :func:`cholesky_program`.
    h : sequence of expression
        The entries (symbols, or expressions: an entry is assigned where first used).
    rhs : sequence of sequence of expression
        The right-hand sides, each of length ``m``.
    prefix : str
        The prefix of the program's symbols (distinct programs in one kernel need
        distinct prefixes).

    Returns
    -------
    assignments : list of (symbol, expression)
        The factorization and the triangular solves.
    solutions : list of list of expression
        One solution per right-hand side, in the matrix's own order.
    pivots : list of expression
        As for :func:`cholesky_program`.
    """
    pattern = {(i, j) for i, j in entries} | {(j, i) for i, j in entries}
    order = elimination_order(pattern, m, leading)
    position = {index: a for a, index in enumerate(order)}
    value: dict[tuple[int, int], sx.Expr] = {}
    for symbol, (i, j) in zip(h, entries, strict=True):
        a, b = sorted((position[i], position[j]), reverse=True)
        value[(a, b)] = symbol
    columns = _fill(pattern, order)
    names = fresh_symbols(prefix)
    program: list[Assignment] = []

    def assign(expr: sx.Expr) -> sx.Expr:
        if expr.is_Atom:
            return expr
        symbol = next(names)
        program.append((symbol, expr))
        return symbol

    # scaled[(a, k)] = L[a, k] * D[k]: formed once, it turns every later dot product
    # into plain multiply-adds.
    unit: dict[tuple[int, int], sx.Expr] = {}
    scaled: dict[tuple[int, int], sx.Expr] = {}
    row_entries: list[list[int]] = [[] for _ in range(m)]  # columns k < a with L[a, k] != 0
    inverse: list[sx.Expr] = []
    pivots: list[sx.Expr] = []
    for b in range(m):
        pivot = assign(
            _minus(
                value.get((b, b), sx.Integer(0)),
                ((unit[(b, k)], scaled[(b, k)]) for k in row_entries[b]),
            )
        )
        pivots.append(pivot)
        inverse.append(assign(1 / pivot))
        for a in columns[b]:
            shared = set(row_entries[a]) & set(row_entries[b])
            dot = ((unit[(a, k)], scaled[(b, k)]) for k in sorted(shared))
            scaled[(a, b)] = assign(_minus(value.get((a, b), sx.Integer(0)), dot))
            unit[(a, b)] = assign(scaled[(a, b)] * inverse[b])
            row_entries[a].append(b)
    solutions = []
    for c in rhs:
        forward: list[sx.Expr] = []
        for a in range(m):
            dot = ((unit[(a, k)], forward[k]) for k in row_entries[a])
            forward.append(assign(_minus(c[order[a]], dot)))
        backward: dict[int, sx.Expr] = {}
        for a in reversed(range(m)):
            dot = ((unit[(k, a)], backward[k]) for k in columns[a])
            backward[a] = assign(_minus(forward[a] * inverse[a], dot))
        solutions.append([backward[position[i]] for i in range(m)])
    return program, solutions, pivots
