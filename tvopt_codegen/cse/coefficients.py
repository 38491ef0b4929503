"""A kernel's last pass on SymEngine: sums whose terms share one coefficient, factored.

SymEngine's derivative of a square leaves many sums such as ``2*a*b + 2*c*d`` (a ring's
barriers, whose chain rule doubles every term): five operations, where ``2*(a*b + c*d)``
is four. :func:`factored` writes them so, on the :class:`~tvopt_codegen.cse.dag.Dag`'s
ids, after the passes of :mod:`~tvopt_codegen.cse.numbering` and
:mod:`~tvopt_codegen.cse.programs`.
"""

from __future__ import annotations

from collections.abc import Sequence

from tvopt_codegen import symbolic as sx
from tvopt_codegen.cse.dag import _ADD, _COMPOUND, _MUL, _NUMBER, Dag, Program, walked


def factored(dag: Dag, program: Program, outputs: Sequence[int]) -> tuple[Program, list[int]]:
    """A program's sums whose terms share one rational coefficient, written ``c*(...)``.

    In a product with a coefficient of its own the ``c`` merges into that one. Only sums
    that are values, terms or factors are rewritten, not a function's argument or a
    power's base (whose signs and expansion are the engine's), and only exact
    coefficients (a float's product rounds). Nodes are rebuilt by the engine's
    constructors, which keep ``c*(a + b)`` whole (:meth:`Dag.distribute` is not applied
    here: this is the kernel's last pass).

    A node's result is the table's (``dag.factorings``), kept across calls: the kernels
    cut from one reduced program (the jet's and the optimality error's) share most of
    their nodes.
    """
    args, kind = dag.args, dag.kind
    memo = dag.factorings

    def visit(node: int) -> int:
        own = args[node]
        k = kind[node]
        if not own or k not in (_ADD, _MUL):
            return node
        done = memo.get(node)
        if done is not None:
            return done
        new = tuple([visit(c) if kind[c] in _COMPOUND else c for c in own])
        done = node
        if new != own:
            exprs = [dag.expression(c) for c in new]
            done = dag.intern(sx.Add(*exprs) if k == _ADD else sx.Mul(*exprs))
        if kind[done] == _ADD:
            done = _common_coefficient(dag, done)
        memo[node] = done
        return done

    return walked(program, outputs, visit)


def _common_coefficient(dag: Dag, total: int) -> int:
    """The sum ``total`` as ``c*(...)`` when all its terms' coefficients are ``+-c``."""
    kind, args = dag.kind, dag.args
    common = None
    for term in args[total]:
        if kind[term] == _NUMBER:
            coefficient = term
        elif kind[term] == _MUL and kind[args[term][0]] == _NUMBER:
            coefficient = args[term][0]
        else:
            return total
        if not dag.is_rational(coefficient):
            return total
        if dag.cost[coefficient]:  # a negative or a fraction: compare magnitudes
            magnitude = _magnitude(dag, coefficient)
        else:
            magnitude = coefficient
        if magnitude == dag.one or (common is not None and magnitude != common):
            return total
        common = magnitude
    if common is None:
        return total
    c = dag.expression(common)
    inverse = 1 / c
    inner = sx.Add(*[dag.expression(term) * inverse for term in args[total]])
    return dag.intern(sx.Mul(c, inner))


def _magnitude(dag: Dag, number: int) -> int:
    """The node ``|number|``, kept per number (``dag.magnitudes``): a kernel's sums share a few."""
    found = dag.magnitudes.get(number)
    if found is None:
        value = dag.expression(number)
        found = dag.magnitudes[number] = dag.intern(-value if value.is_negative else value)
    return found
