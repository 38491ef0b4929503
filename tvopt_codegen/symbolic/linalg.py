"""Determinants as SymPy finds them, on either engine (det R, the equalities' Gram).

Beside the API rather than in it: a small determinant is simplified through the border
(:mod:`tvopt_codegen.symbolic.border`), which itself builds on the API.
"""

from __future__ import annotations

from typing import Any

from tvopt_codegen import symbolic as sx
from tvopt_codegen.symbolic.border import from_sympy, to_sympy

__all__ = ["det"]


def det(matrix: Any) -> Any:
    """The determinant of a square matrix, as SymPy's ``det(method="berkowitz")`` finds it.

    SymPy writes a 2 x 2 or 3 x 3 determinant out and simplifies it (its ``dotprodsimp``:
    a two-link arm's det R has 42 nodes, not 542), and splits a larger matrix into its
    strongly connected blocks (a team's R), each expanded by Berkowitz's division-free
    algorithm. SymEngine's own ``det`` divides, as Bareiss's does; here it takes SymPy's
    steps, the simplification of a small determinant through the border, so that both
    engines give det R of the same size and decide alike whether to factor it.
    """
    if not sx.SYMENGINE:
        return matrix.det(method="berkowitz")
    rows = matrix.tolist()
    n = len(rows)
    if n == 0:
        return sx.ONE
    if n == 1:
        return rows[0][0]
    if n <= 3:
        # The border, for one small expression (SymPy's private step, as of SymPy 1.14).
        from sympy.matrices.utilities import _dotprodsimp  # noqa: PLC0415

        return from_sympy(_dotprodsimp(to_sympy(_written_out(rows))))
    product = sx.ONE
    for block in _strong_blocks(rows):
        sub = [[rows[i][j] for j in block] for i in block]
        product *= (-1) ** len(sub) * _berkowitz(sub)[-1]
    return product


def _written_out(rows: list[list[Any]]) -> Any:
    """A 2 x 2 or 3 x 3 determinant written out, in SymPy's order of terms."""
    (a, b, *c), (d, e, *f), *rest = rows
    if not rest:
        return a * e - b * d
    (g, h, i) = rest[0]
    return a * e * i + b * f[0] * g + c[0] * d * h - c[0] * e * g - a * f[0] * h - b * d * i


def _strong_blocks(rows: list[list[Any]]) -> list[list[int]]:
    """The strongly connected components of a matrix's nonzero pattern, each ascending.

    ``i`` reaches ``j`` through a nonzero ``(i, j)``; the determinant is the product of
    the diagonal blocks' (SymPy's ``strongly_connected_components``, in another order).
    """
    n = len(rows)
    reach = [[i == j or rows[i][j] != 0 for j in range(n)] for i in range(n)]
    for k in range(n):  # Warshall's transitive closure: n is det R's m, a handful
        for i in range(n):
            if reach[i][k]:
                reach[i] = [r or s for r, s in zip(reach[i], reach[k], strict=True)]
    blocks: list[list[int]] = []
    placed: set[int] = set()
    for i in range(n):
        if i not in placed:
            block = [j for j in range(n) if reach[i][j] and reach[j][i]]
            placed.update(block)
            blocks.append(block)
    return blocks


def _berkowitz(rows: list[list[Any]]) -> list[Any]:
    """The characteristic polynomial's coefficients of ``rows``, leading 1 first."""
    n = len(rows)
    if n == 1:
        return [sx.ONE, -rows[0][0]]
    corner, right = rows[0][0], rows[0][1:]
    column, rest = [row[0] for row in rows[1:]], [row[1:] for row in rows[1:]]
    # The Toeplitz matrix's diagonals: 1, -a, -R C, -R A C, -R A^2 C, ...
    powers = [column]
    for _ in range(n - 2):
        last = powers[-1]
        powers.append([sx.Add(*(a * c for a, c in zip(row, last, strict=True))) for row in rest])
    diagonals = [sx.ONE, -corner]
    diagonals += [-sx.Add(*(r * c for r, c in zip(right, p, strict=True))) for p in powers]
    below = _berkowitz(rest)
    return [
        sx.Add(*(diagonals[i - j] * below[j] for j in range(min(i + 1, n)))) for i in range(n + 1)
    ]
