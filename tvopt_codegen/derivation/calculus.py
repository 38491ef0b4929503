"""The derivatives the later stages evaluate, taken here: no stage after this differentiates.

Verification (the constraints' certificate, the KKT path), the sweep's check kernels and
the FMU's start read these expressions; they lambdify or lower them, they never call
``diff`` themselves. Each function takes the :class:`~tvopt_codegen.derivation.model.Model` and
returns plain sympy expressions (signals not inlined, parameters symbolic), in the order
its callers index them. They are computed on demand: a ``generate`` that needs none of
them pays for none.
"""

from __future__ import annotations

from dataclasses import dataclass

import sympy as sp

from tvopt_codegen.derivation.model import Model
from tvopt_codegen.spec.constraints import inline_signals


def objective_of(model: Model) -> sp.Expr:
    """The objective the constraints' certificate judges: the spec's f0 (not the barrier's)."""
    return sp.sympify(model.f0 if model.objective is None else model.objective)


def objective_gradient(model: Model) -> list[sp.Expr]:
    """``grad_y f0`` of :func:`objective_of`, one entry per output."""
    objective = objective_of(model)
    return [sp.diff(objective, yi) for yi in model.y]


def objective_hessian(model: Model) -> list[list[sp.Expr]]:
    """``grad_yy f0`` of :func:`objective_of`, row by row.

    Each row differentiates one entry of the gradient, and the upper triangle is the
    lower one's (Schwarz): second derivatives of the whole objective, entry by entry,
    took the gradient again for each (a second of a constrained ``simulate``).
    """
    gradient = objective_gradient(model)
    m = len(model.y)
    lower = [[sp.diff(gradient[i], model.y[j]) for j in range(i + 1)] for i in range(m)]
    return [[lower[max(i, j)][min(i, j)] for j in range(m)] for i in range(m)]


def constraint_gradients(model: Model) -> list[list[sp.Expr]]:
    """``grad_y g_i`` of each inequality constraint, row by row."""
    return [[sp.diff(sp.sympify(c.g), yi) for yi in model.y] for c in model.constraints]


@dataclass(frozen=True)
class EqualityCalculus:
    """The equality constraints and their derivatives in ``y``.

    Attributes
    ----------
    values : list of sympy.Expr
        ``a_j(y, t)``.
    jacobian : list of sympy.Expr
        ``J_a`` row-major, (q, m): ``d a_j / d y_i`` at ``j * m + i``.
    hessians : list of list of sympy.Expr
        ``grad_yy a_j`` of each, row-major (m * m entries).
    """

    values: list[sp.Expr]
    jacobian: list[sp.Expr]
    hessians: list[list[sp.Expr]]

    def curvature(self, multipliers: tuple[sp.Symbol, ...]) -> list[sp.Expr]:
        """``sum_j nu_j grad_yy a_j``, row-major, for multiplier symbols ``nu``."""
        size = len(self.hessians[0]) if self.hessians else 0
        return [
            sp.Add(*(nu * h[k] for nu, h in zip(multipliers, self.hessians, strict=True)))
            for k in range(size)
        ]


def equality_calculus(model: Model) -> EqualityCalculus:
    """``a``, ``J_a`` and each ``grad_yy a_j`` of the model's equality constraints."""
    a = [sp.sympify(c.g) for c in model.equalities]
    return EqualityCalculus(
        values=a,
        jacobian=[sp.diff(e, y) for e in a for y in model.y],
        hessians=[[sp.diff(e, yi, yj) for yi in model.y for yj in model.y] for e in a],
    )


def objective_domain(model: Model) -> tuple[list[sp.Expr], list[list[sp.Expr]]]:
    """f0's principal domain as expressions that must stay positive, and their gradients.

    tan's argument within (-pi/2, pi/2) and log's positive: the barrier objective never
    leaves it, and the independent constrained solver keeps to it too.
    """
    signals = dict(model.signals)
    domain: list[sp.Expr] = []
    for node in sp.preorder_traversal(inline_signals(objective_of(model), signals)):
        if isinstance(node, sp.tan):
            domain += [sp.pi / 2 - node.args[0], node.args[0] + sp.pi / 2]
        elif isinstance(node, sp.log):
            domain.append(node.args[0])
    return domain, [[sp.diff(e, yi) for yi in model.y] for e in domain]


def nominal_jets(model: Model, order: int) -> list[list[sp.Expr]]:
    """Each reference's nominal closed form and its time derivatives up to ``order``.

    A reference with no nominal closed form gets zeros (the FMU starts from them; the
    certificate refuses such a spec before asking).
    """
    nominal = dict(model.nominal)
    return [
        [sp.diff(nominal.get(r, sp.Integer(0)), model.t, j) for j in range(order + 1)]
        for r in model.references
    ]


def constraint_hessian_entries(
    g: sp.Expr, outputs: tuple[sp.Symbol, ...]
) -> list[tuple[int, int, sp.Expr]]:
    """The nonzero entries ``(i, j, d2 g / dy_i dy_j)``, ``j <= i``, of a constraint's Hessian."""
    entries = []
    for i, yi in enumerate(outputs):
        for j, yj in enumerate(outputs[: i + 1]):
            second = sp.diff(g, yi, yj)
            if second != 0:
                entries.append((i, j, second))
    return entries
