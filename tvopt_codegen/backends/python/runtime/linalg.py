"""The decoupling matrix's solves: LU with partial pivoting, for a batch and one point.

Sections: ``batch`` (block by block over a batch of columns, the same operations in the
same order as the C code's loop) and ``one_point`` (lists of floats, for a single state,
with the finiteness test both paths share).
"""

from __future__ import annotations

import math

import numpy
import numpy.typing

from tvopt_codegen.backends.python.runtime.provided import (
    _R_GROUPS,
    PIVOT_TOLERANCE,
    STATUS_SINGULAR_DECOUPLING,
)
from tvopt_codegen.backends.python.runtime.statuses import _error

# --- copied verbatim into the generated controller below this line ---


# --- section: batch ---
def _solve_decoupling(
    r: numpy.typing.NDArray[numpy.float64], b: numpy.typing.NDArray[numpy.float64]
) -> numpy.typing.NDArray[numpy.float64]:
    """Solve ``R w = b`` block by block; blocks of one size are one batch."""
    count = b.shape[1]
    w = numpy.empty_like(b)
    for size, starts, rows in _R_GROUPS:
        blocks = len(starts)
        if blocks == 1:
            a = r[starts[0] : starts[0] + size * size].reshape(size, size, count)
            rhs = b[list(rows[0])]
        else:
            take = numpy.add.outer(numpy.array(starts), numpy.arange(size * size))
            a = r[take].transpose(1, 0, 2).reshape(size, size, blocks * count)
            rhs = b[numpy.array(rows)].transpose(1, 0, 2).reshape(size, blocks * count)
        x = _lu_solve(a, rhs, count)
        w[numpy.array(rows)] = x.reshape(size, blocks, count).transpose(1, 0, 2)
    return w


def _lu_solve(
    a: numpy.typing.NDArray[numpy.float64], b: numpy.typing.NDArray[numpy.float64], points: int
) -> numpy.typing.NDArray[numpy.float64]:
    """Solve ``a x = b`` by LU with partial pivoting; ``a`` (m, m, N), ``b`` (m, N).

    Column ``c`` belongs to point ``c % points`` of the caller's batch. Every entry is a
    contiguous row over the batch and a row exchange is a ``where`` on the columns that
    need it: the same operations in the same order as the C code's loop.
    """
    m = b.shape[0]
    lu = [[a[i, k].copy() for k in range(m)] for i in range(m)]
    x = [b[i].copy() for i in range(m)]
    scale = numpy.max(numpy.abs(a.reshape(m * m, -1)), axis=0)
    for j in range(m):
        # The pivot row: the first of the largest |a[i, j]|, i >= j, like the C loop.
        best, row = numpy.abs(lu[j][j]), numpy.asarray(j)
        for i in range(j + 1, m):
            size = numpy.abs(lu[i][j])
            larger = size > best
            best = numpy.where(larger, size, best)
            row = numpy.where(larger, i, row)
        for i in range(j + 1, m):
            swap = row == i
            if swap.any():
                for k in range(m):
                    lu[j][k], lu[i][k] = (
                        numpy.where(swap, lu[i][k], lu[j][k]),
                        numpy.where(swap, lu[j][k], lu[i][k]),
                    )
                x[j], x[i] = numpy.where(swap, x[i], x[j]), numpy.where(swap, x[j], x[i])
        pivot = lu[j][j]
        bad = ~(numpy.abs(pivot) > PIVOT_TOLERANCE * scale)
        if bad.any():
            index = int(numpy.argmax(bad)) % points
            raise _error(STATUS_SINGULAR_DECOUPLING, index)
        for i in range(j + 1, m):
            factor = lu[i][j] / pivot
            for k in range(j + 1, m):
                lu[i][k] -= factor * lu[j][k]
            x[i] -= factor * x[j]
    for j in reversed(range(m)):
        for k in range(j + 1, m):
            x[j] -= lu[j][k] * x[k]
        x[j] /= lu[j][j]
    return numpy.array(x)


# --- section: one_point ---
# One state at a time (a user's control loop, solve_ivp without vectorized=True, a
# minimizer): the same kernels on lists of Python floats, without the per-array cost
# of NumPy. Anything unusual (a non-finite value, a singular pivot, a Python float's
# ZeroDivisionError or OverflowError) returns None, and the array path then answers
# and raises exactly as documented: the two paths never disagree.


def _finite(values: list[float]) -> bool:
    """Whether every value is finite (a sum of infinities of both signs is NaN).

    The sum alone would also call finite values whose sum overflows (1e308 twice) not
    finite, where the C backend's probe (x * 0.0) does not: then each is looked at.
    """
    return math.isfinite(sum(values)) or all(map(math.isfinite, values))


def _lu_solve_1(a: list[float], b: list[float]) -> list[float] | None:
    """Solve ``a x = b`` (``a`` row-major, m*m) as :func:`_lu_solve` does; None if singular."""
    m = len(b)
    lu = [a[i * m : (i + 1) * m] for i in range(m)]
    x = list(b)
    scale = max(map(abs, a))
    for j in range(m):
        row, best = j, abs(lu[j][j])
        for i in range(j + 1, m):
            if abs(lu[i][j]) > best:
                row, best = i, abs(lu[i][j])
        if row != j:
            lu[j], lu[row] = lu[row], lu[j]
            x[j], x[row] = x[row], x[j]
        pivot = lu[j][j]
        if not abs(pivot) > PIVOT_TOLERANCE * scale:
            return None
        for i in range(j + 1, m):
            factor = lu[i][j] / pivot
            lu[i] = lu[i][: j + 1] + [lu[i][k] - factor * lu[j][k] for k in range(j + 1, m)]
            x[i] -= factor * x[j]
    for j in reversed(range(m)):
        for k in range(j + 1, m):
            x[j] -= lu[j][k] * x[k]
        x[j] /= lu[j][j]
    return x
