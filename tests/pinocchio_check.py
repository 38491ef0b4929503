"""Our imported robot's M(q) and bias forces beside Pinocchio's, at one state.

One comparison for the URDF tests, the door's tests and the fuzzer: a continuous joint is
(cos q, sin q) in Pinocchio's configuration, and Pinocchio's CRBA fills the upper
triangle of M only.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from tvopt_codegen.spec import Mechanics
from tvopt_codegen.spec.implicit import evaluator, mass_matrix_at


def configuration(model: Any, q: np.ndarray) -> np.ndarray:
    """Pinocchio's configuration of joint positions ``q``, joint by joint in order."""
    import pinocchio as pin  # type: ignore[import-untyped]

    config: np.ndarray = pin.neutral(model)
    for k, joint in enumerate(model.joints[1:]):
        assert joint.idx_v == k
        if joint.nq == 2:
            config[joint.idx_q : joint.idx_q + 2] = np.cos(q[k]), np.sin(q[k])
        else:
            config[joint.idx_q] = q[k]
    return config


def both_at(
    mech: Mechanics,
    params: Mapping[Any, float],
    model: Any,
    data: Any,
    q: np.ndarray,
    v: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``(M ours, M Pinocchio's, bias ours, bias Pinocchio's)`` at positions ``q``, rates ``v``.

    ``params`` maps the spec's parameters, by name or by symbol of either engine, to
    their values.

    The bias forces are ``M q'' - B u`` at zero input: ours ``-F``, Pinocchio's RNEA at
    zero acceleration.
    """
    import pinocchio as pin

    # Keyed by name: ``params`` by names or by either engine's symbols, as the product's
    # evaluators take them (the fuzzer's are SymPy's, the spec's expressions SymEngine's).
    values: dict[Any, float] = dict(params)
    values |= dict(zip(mech.coordinates, q, strict=True))
    values |= dict(zip(mech.rates, v, strict=True))
    ours = mass_matrix_at(mech, values)[0]
    evaluate = evaluator(mech, values)
    bias = -np.array([float(evaluate(e)) for e in mech.forces])
    config = configuration(model, q)
    theirs = pin.crba(model, data, config)
    theirs = np.triu(theirs) + np.triu(theirs, 1).T
    their_bias = pin.rnea(model, data, config, v, np.zeros(model.nv))
    return ours, theirs, bias, their_bias
