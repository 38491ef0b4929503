"""Equality constraints: the Jacobian of ``a``, its checks and the Lagrangian.

The rank checks, where the constraints' gradients are dependent, the Lagrangian
``L = f0 + nu^T a`` and the multipliers' start.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator

import numpy as np

from tvopt_codegen import symbolic as sx
from tvopt_codegen.derivation.convexity import _evaluator_at
from tvopt_codegen.derivation.linearization import _States
from tvopt_codegen.derivation.meter import _DET_SIMPLIFY_NODES, _Meter, tree_size
from tvopt_codegen.derivation.model import Model
from tvopt_codegen.derivation.objective import _Objective, _programs_of, objective_start
from tvopt_codegen.derivation.singularity import _singular_set, simplified_det
from tvopt_codegen.errors import AssumptionError
from tvopt_codegen.symbolic import linalg


def _equality_jacobian(model: Model) -> list[list[sx.Expr]]:
    """``J_a``: the equalities' derivatives in the outputs, (q, m)."""
    return [[sx.diff(c.g, y) for y in model.y] for c in model.equalities]


def _equality_checks(model: Model, y0: np.ndarray) -> tuple[str, ...]:
    """Refuse equalities the KKT law cannot keep: too many, dependent, or not affine.

    Equalities not affine in the outputs make the feasible set non-convex: refused
    unless ``allow_nonconvex``, and then a warning says the certificate is local only.
    Dependence is decided on ``J_a`` at the initial outputs over the horizon (at every
    output when ``J_a`` is constant).
    """
    if not model.equalities:
        return ()
    settings = model.settings
    q, m = len(model.equalities), len(model.y)
    names = ", ".join(c.name for c in model.equalities)
    if q > m:
        raise AssumptionError(
            settings.source,
            "constraints",
            f"{q} equality constraints ({names}) on {m} outputs: at most {m} can be independent",
        )
    warnings: tuple[str, ...] = ()
    curved = [
        c.name
        for c in model.equalities
        if any(sx.diff(c.g, yi, yj) != 0 for yi in model.y for yj in model.y)
    ]
    if curved:
        if not settings.allow_nonconvex:
            raise AssumptionError(
                settings.source,
                f"constraints.{curved[0]}",
                f"not affine in the outputs: {', '.join(curved)}; the feasible set of a "
                "curved equality is not convex (set allow_nonconvex = true to accept a "
                "local certificate)",
            )
        warnings = (
            f"equality constraints not affine in the outputs: {', '.join(curved)}; "
            "the certificate is local only",
        )
    jacobian_a = _equality_jacobian(model)
    points = 5
    ts = np.linspace(0.0, settings.t_final, points)
    evaluate = _evaluator_at(model, np.repeat(y0[None, :], points, axis=0), ts)
    matrices = np.zeros((points, q, m))
    for i, row in enumerate(jacobian_a):
        for j, entry in enumerate(row):
            if entry != 0:
                matrices[:, i, j] = np.broadcast_to(np.real(evaluate(entry)), (points,))
    constant = all(sx.sympify(e).is_Number for row in jacobian_a for e in row)
    for index in range(points):
        singular = np.linalg.svd(matrices[index], compute_uv=False)
        if not singular[-1] > 1e-9 * max(1.0, float(singular[0])):
            where = "everywhere" if constant else f"at the initial outputs and t = {ts[index]:g}"
            raise AssumptionError(
                settings.source,
                "constraints",
                f"the equality constraints {names} are dependent: their gradients in the "
                f"outputs have rank {int(np.sum(singular > 1e-9 * singular[0]))} < {q} "
                f"{where} (drop or combine the redundant ones)",
            )
    return warnings


def _dependent_set(model: Model) -> tuple[str, ...]:
    """Where the equalities' gradients are dependent (K singular), in words.

    ``det(J_a J_a^T) = 0``, factored, for up to four equalities of small expressions; a
    note saying it was not computed otherwise.
    """
    q = len(model.equalities)
    if not q:
        return ()
    if q > 4:
        return (f"not computed symbolically (q = {q} > 4)",)
    jacobian_a = sx.Matrix(_equality_jacobian(model))
    gram = jacobian_a * jacobian_a.T
    det = linalg.det(gram)
    if tree_size(det, _DET_SIMPLIFY_NODES) > _DET_SIMPLIFY_NODES:
        return (f"not simplified symbolically (more than {_DET_SIMPLIFY_NODES} expression nodes)",)
    return _singular_set(simplified_det(det))


def _lagrangian(
    model: Model, objective: _Objective, names: Iterator[sx.Expr], meter: _Meter
) -> _Objective:
    """With equalities, the KKT map ``F = grad L`` over (y, nu) and its Hessian ``K``.

    ``L = f0 + nu^T a``: its gradient is ``[grad f0 + J_a^T nu; a]`` and its Hessian the
    KKT matrix ``[[grad_yy L, J_a^T], [J_a, 0]]``, so the paper's law written for
    ``L`` over (y, nu) is the KKT law (docs/constraints.md). Without equalities, the
    objective itself.
    """
    if not model.equalities:
        return objective
    variables = (*model.y, *model.multipliers)
    gradient, program, current, hessian_program, entries, _ = _programs_of(
        model.lagrangian, variables, names, meter
    )
    # The (nu, nu) block is structurally zero; its diagonal is stored all the same, as
    # the elimination fills it (the Schur complement -J Hess^-1 J^T).
    m = len(variables)
    value = dict(entries)
    entries = tuple(
        sorted(value.items() | {((i, i), sx.Integer(0)) for i in range(m) if (i, i) not in value})
    )
    return _Objective(
        gradient,
        program,
        current,
        hessian_program,
        entries,
        objective.convexity,
        objective.warnings,
    )


def _multipliers_start(model: Model, states: _States, objective: _Objective) -> _States:
    """The multiplier chains' initial values: nu(0) by least squares, its derivatives 0.

    ``nu(0)`` minimises ``|grad f0 + J_a^T nu|`` at the initial outputs and t = 0, so the
    KKT map starts as small as the plant's state allows; any start is admissible (the
    theorem holds for every ``E_F(0)``). Values given in ``[simulation]`` are kept.
    """
    if not model.equalities:
        return states
    y0 = objective_start(model, states)
    evaluate = _evaluator_at(model, y0[None, :], np.zeros(1))
    m, q = len(model.y), len(model.equalities)
    g = np.array(
        [float(np.real(np.broadcast_to(evaluate(e), (1,))[0])) for e in objective.gradient]
    )
    jacobian_a = np.array(
        [
            [float(np.real(np.broadcast_to(evaluate(e), (1,))[0])) for e in row]
            for row in _equality_jacobian(model)
        ]
    ).reshape(q, m)
    nu0 = np.linalg.lstsq(jacobian_a.T, -g, rcond=None)[0]
    given = dict(model.settings.initial_state)
    initial = list(states.initial)
    for chain, value in zip(states.multipliers, nu0, strict=True):
        if chain[0] not in given:
            initial[states.names.index(chain[0])] = float(value)
    return dataclasses.replace(states, initial=tuple(initial))
