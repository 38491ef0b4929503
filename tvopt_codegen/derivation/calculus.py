"""The derivatives the later stages evaluate, taken here: no stage after this differentiates.

Verification (the constraints' certificate, the KKT path), the sweep's check kernels and
the FMU's start read these expressions; they lambdify or lower them, they never call
``diff`` themselves. Each function takes the :class:`~tvopt_codegen.derivation.model.Model` and
returns plain expressions of the engine (signals not inlined, parameters symbolic), in the order
its callers index them. They are computed on demand: a ``generate`` that needs none of
them pays for none.
"""

from __future__ import annotations

from dataclasses import dataclass

from tvopt_codegen import symbolic as sx
from tvopt_codegen.derivation.model import Model
from tvopt_codegen.spec.constraints import inline_signals


def objective_of(model: Model) -> sx.Expr:
    """The objective the constraints' certificate judges: the spec's f0 (not the barrier's)."""
    return sx.sympify(model.f0 if model.objective is None else model.objective)


def objective_gradient(model: Model) -> list[sx.Expr]:
    """``grad_y f0`` of :func:`objective_of`, one entry per output."""
    objective = objective_of(model)
    return [sx.diff(objective, yi) for yi in model.y]


def objective_hessian(model: Model) -> list[list[sx.Expr]]:
    """``grad_yy f0`` of :func:`objective_of`, row by row.

    Each row differentiates one entry of the gradient, and the upper triangle is the
    lower one's (Schwarz): second derivatives of the whole objective, entry by entry,
    took the gradient again for each (a second of a constrained ``simulate``).
    """
    gradient = objective_gradient(model)
    m = len(model.y)
    lower = [[sx.diff(gradient[i], model.y[j]) for j in range(i + 1)] for i in range(m)]
    return [[lower[max(i, j)][min(i, j)] for j in range(m)] for i in range(m)]


def constraint_gradients(model: Model) -> list[list[sx.Expr]]:
    """``grad_y g_i`` of each inequality constraint, row by row."""
    return [[sx.diff(sx.sympify(c.g), yi) for yi in model.y] for c in model.constraints]


@dataclass(frozen=True)
class EqualityCalculus:
    """The equality constraints and their derivatives in ``y``.

    Attributes
    ----------
    values : list of expression
        ``a_j(y, t)``.
    jacobian : list of expression
        ``J_a`` row-major, (q, m): ``d a_j / d y_i`` at ``j * m + i``.
    hessians : list of list of expression
        ``grad_yy a_j`` of each, row-major (m * m entries).
    """

    values: list[sx.Expr]
    jacobian: list[sx.Expr]
    hessians: list[list[sx.Expr]]

    def curvature(self, multipliers: tuple[sx.Expr, ...]) -> list[sx.Expr]:
        """``sum_j nu_j grad_yy a_j``, row-major, for multiplier symbols ``nu``."""
        size = len(self.hessians[0]) if self.hessians else 0
        return [
            sx.Add(*(nu * h[k] for nu, h in zip(multipliers, self.hessians, strict=True)))
            for k in range(size)
        ]


def equality_calculus(model: Model) -> EqualityCalculus:
    """``a``, ``J_a`` and each ``grad_yy a_j`` of the model's equality constraints."""
    a = [sx.sympify(c.g) for c in model.equalities]
    return EqualityCalculus(
        values=a,
        jacobian=[sx.diff(e, y) for e in a for y in model.y],
        hessians=[[sx.diff(e, yi, yj) for yi in model.y for yj in model.y] for e in a],
    )


def objective_domain(model: Model) -> tuple[list[sx.Expr], list[list[sx.Expr]]]:
    """f0's principal domain as expressions that must stay positive, and their gradients.

    tan's argument within (-pi/2, pi/2) and log's positive: the barrier objective never
    leaves it, and the independent constrained solver keeps to it too.
    """
    signals = dict(model.signals)
    domain: list[sx.Expr] = []
    for node in _preorder(inline_signals(objective_of(model), signals)):
        name = sx.function_name(node) if node.is_Function else ""
        if name == "tan":
            domain += [sx.pi / 2 - node.args[0], node.args[0] + sx.pi / 2]
        elif name == "log":
            domain.append(node.args[0])
    return domain, [[sx.diff(e, yi) for yi in model.y] for e in domain]


def _preorder(expr: sx.Expr) -> list[sx.Expr]:
    """Every node of ``expr``'s tree, parents first, arguments in order (repeats kept).

    SymPy's ``preorder_traversal``, on either engine.
    """
    nodes = []
    stack = [expr]
    while stack:
        node = stack.pop()
        nodes.append(node)
        stack.extend(reversed(node.args))
    return nodes


def nominal_jets(model: Model, order: int) -> list[list[sx.Expr]]:
    """Each reference's nominal closed form and its time derivatives up to ``order``.

    A reference with no nominal closed form gets zeros (the FMU starts from them; the
    certificate refuses such a spec before asking).
    """
    nominal = dict(model.nominal)
    return [
        _time_derivatives(nominal.get(r, sx.Integer(0)), model.t, order) for r in model.references
    ]


def _time_derivatives(expr: sx.Expr, t: sx.Expr, order: int) -> list[sx.Expr]:
    """``expr`` and its derivatives in ``t`` up to ``order``, each taken from ``expr``.

    ``diff(expr, t, t, t)``: SymPy collects the variables into ``(t, 3)``, its own
    n-th derivative (a product's by Leibniz's formula, which the form depends on).
    """
    expr = sx.sympify(expr)
    return [expr, *(sx.diff(expr, *([t] * j)) for j in range(1, order + 1))]


def constraint_hessian_entries(
    g: sx.Expr, outputs: tuple[sx.Expr, ...]
) -> list[tuple[int, int, sx.Expr]]:
    """The nonzero entries ``(i, j, d2 g / dy_i dy_j)``, ``j <= i``, of a constraint's Hessian."""
    entries = []
    for i, yi in enumerate(outputs):
        for j, yj in enumerate(outputs[: i + 1]):
            second = sx.diff(g, yi, yj)
            if second != 0:
                entries.append((i, j, second))
    return entries
