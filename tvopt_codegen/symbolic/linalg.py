"""Determinants as SymPy finds them, on either engine (det R, the equalities' Gram).

Beside the API rather than in it: a small determinant is simplified through the border
(:mod:`tvopt_codegen.symbolic.border`), which itself builds on the API.
"""

from __future__ import annotations

from typing import Any

from tvopt_codegen import symbolic as sx
from tvopt_codegen.symbolic.border import from_sympy, to_sympy

__all__ = ["det", "sized_det"]


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
        expanded = _expanded(rows)
        if expanded is not None and expanded[1] == _POLYNOMIAL:
            return expanded[0]  # a polynomial in its atoms: SymPy only expands it
        if expanded is not None:
            # dotprodsimp's cancel, where its form is sure (a mass-matrix arm's det R).
            from tvopt_codegen.symbolic.trigforms import cancelled  # noqa: PLC0415

            found = cancelled(_deep_expanded(_written_out(rows), {}), expanded[0])
            if found is not None:
                return found
        # The border, for one small expression (SymPy's private step, as of SymPy 1.14).
        from sympy.matrices.utilities import _dotprodsimp  # noqa: PLC0415

        return from_sympy(_dotprodsimp(to_sympy(_written_out(rows))))
    product = sx.ONE
    for block in _strong_blocks(rows):
        sub = [[rows[i][j] for j in block] for i in block]
        product *= (-1) ** len(sub) * _berkowitz(sub)[-1]
    return product


def sized_det(matrix: Any, nodes: int) -> tuple[Any, bool]:
    """A determinant equal to :func:`det`'s, and whether :func:`det`'s has at most ``nodes`` nodes.

    On SymPy, :func:`det` itself. On SymEngine a 2 x 2 or 3 x 3 determinant with
    denominators is not simplified through the border when it need not be: SymPy's
    ``dotprodsimp`` expands it and puts it over one denominator (``cancel``), and when
    every denominator is a power of a symbol or of a function, the expansion's terms
    and atoms bound the size of what ``cancel`` can write, so the expansion stands for
    it (det R is then simplified from the expansion, without SymPy: a quadrotor's
    ``(T sin^2 + T cos^2)/(J m^2)``). Where the bound says nothing, :func:`det`'s own,
    which writes ``cancel``'s form itself where it is sure of it (a denominator that is
    a sum: a mass-matrix arm's).
    """
    if sx.SYMENGINE and 2 <= len(matrix.tolist()) <= 3:
        expanded = _expanded(matrix.tolist())
        if expanded is not None and expanded[1] != _SUMS:
            value, below = expanded
            size = sx.tree_size(value, nodes)
            if below == _POLYNOMIAL:
                return value, size <= nodes
            if max(size, _cancelled_bound(value)) <= nodes:
                return value, True
    value = det(matrix)
    size = sx.tree_size(value, 2 * nodes)
    if sx.SYMENGINE and len(matrix.tolist()) >= 4 and nodes // 2 < size <= 2 * nodes:
        # A 4 x 4's Berkowitz terms come out otherwise on SymEngine than on SymPy: near
        # the limit, the size of SymPy's own (of a small matrix, at the border) decides,
        # so that both engines simplify det R, or not, alike.
        return value, sx.tree_size(to_sympy(matrix).det(method="berkowitz"), nodes) <= nodes
    return value, size <= nodes


#: What an expansion has below (:func:`_expanded`): no denominator, powers of symbols and
#: functions only, or some other denominator (a sum).
_POLYNOMIAL, _MONOMIALS, _SUMS = "polynomial", "monomials", "sums"


def _expanded(rows: list[list[Any]]) -> tuple[Any, str] | None:
    """A small determinant written out and expanded as SymPy's ``dotprodsimp`` expands it.

    Returns the expansion and what its denominators are (``_POLYNOMIAL``: none, where
    ``dotprodsimp`` stops; ``_MONOMIALS``; ``_SUMS``: a denominator that is a sum, where
    the expansion is SymPy's in value only), or None where it might not be SymPy's even
    so: a double (SymPy's 15 digits), a power to a fraction.
    """
    written = _written_out(rows)
    # dotprodsimp expands sums, products and powers only (an entry alone stays as it is).
    simple = not (written.is_Add or written.is_Mul or written.is_Pow)
    expanded = written if simple else sx.expand(_deep_expanded(written, {}))
    below = _POLYNOMIAL
    stack = [expanded]
    while stack:
        node = stack.pop()
        if node.is_Float:
            return None
        if node.is_Pow:
            base, exponent = node.args
            if not exponent.is_Integer:
                return None
            if exponent.is_negative and below != _SUMS:
                below = _MONOMIALS if base.is_Symbol or base.is_Function else _SUMS
        stack.extend(node.args)
    return expanded, below


def _deep_expanded(expr: Any, memo: dict[Any, Any]) -> Any:
    """``expr`` with every function's arguments expanded (SymPy's ``expand(deep=True)``)."""
    done = memo.get(expr)
    if done is not None:
        return done
    if not expr.args or expr.is_Number:  # SymEngine's zoo has an argument, and no func
        out = expr
    elif expr.is_Function:
        out = expr.func(*[sx.expand(_deep_expanded(arg, memo)) for arg in expr.args])
    else:
        out = expr.func(*[_deep_expanded(arg, memo) for arg in expr.args])
    memo[expr] = out
    return out


def _cancelled_bound(expanded: Any) -> int:
    """Most nodes SymPy's ``cancel`` can write for an expansion over monomial denominators.

    ``cancel`` writes ``c P / Q``: ``P`` has at most as many terms as the expansion, each
    a number times powers of the expansion's atoms (symbols and functions), and ``Q``
    is powers of those atoms.
    """
    terms = expanded.args if expanded.is_Add else (expanded,)
    atoms: set[Any] = set()
    stack = list(terms)
    while stack:
        node = stack.pop()
        if node.is_Symbol or node.is_Function or not node.args:
            if not node.is_Number:
                atoms.add(node)
        else:
            stack.extend(node.args)
    powers = sum(2 + sx.tree_size(atom, 10_000) for atom in atoms)
    return 4 + (len(terms) + 1) * (2 + powers)


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
