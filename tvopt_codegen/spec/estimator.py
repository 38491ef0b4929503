"""The reference differentiators' gains (``[references.estimator]``).

``linear``: the high-gain linear differentiator ``xi_j' = xi_{j+1} + l_j (r - xi_0)``
(``xi_q' = l_q (r - xi_0)``) with every pole at ``-bandwidth``: its characteristic
polynomial is ``(s + bandwidth)^(q+1)``, so ``l_j = C(q + 1, j + 1) bandwidth^(j+1)``.

``levant``: Levant's robust exact differentiator in its recursive form (Levant 2003,
"Higher-order sliding modes, differentiation and output-feedback control"), with his
parameters ``lambda_0 .. lambda_5 = 1.1, 1.5, 2, 3, 5, 8`` and the bound ``L`` on the
references' derivative of order ``q + 1``.
"""

from __future__ import annotations

import math

from tvopt_codegen.spec import Estimator

#: ``bandwidth * gap`` beyond which the linear differentiator has forgotten its state.
#: Its error decays as ``p(bandwidth t) e^(-bandwidth t)`` with ``p`` of degree at most
#: its order (7 at most): at 80, ``80^7 / 7! e^(-80)`` is below 1e-24, so after such a
#: gap its state is the steady state on the samples' straight line (the newest sample,
#: the line's slope, zero beyond) to rounding; the generated code sets it so, in one step
#: instead of ``4 bandwidth gap`` RK4 steps (a Unix-time gap would take hours, and a
#: step count beyond a C ``long`` is undefined behaviour).
FORGETTING_GAP = 80.0

#: Levant's lambda_i for differentiators of order up to 5.
LEVANT_LAMBDAS = (1.1, 1.5, 2.0, 3.0, 5.0, 8.0)


def estimator_order(estimator: Estimator, order: int) -> int:
    """The highest derivative the differentiator estimates, for a law that reads ``order``.

    The linear differentiator's last state is its least accurate (its steady error on a
    smooth signal is of the next derivative over ``bandwidth``): it estimates one
    derivative beyond what the law reads, so that the law's highest derivative carries
    the error of the one after next, over ``bandwidth^2``. Levant's is exact on signals
    with a bounded next derivative and estimates ``order`` itself.
    """
    return order + 1 if estimator.kind == "linear" else order


def estimator_gains(estimator: Estimator, order: int) -> tuple[float, ...]:
    """The gains the generated differentiator of order ``order`` uses.

    Parameters
    ----------
    estimator : Estimator
        The spec's choice.
    order : int
        ``q``: the highest derivative estimated.

    Returns
    -------
    tuple of float
        ``l_0 .. l_q`` (linear) or ``lambda_0 .. lambda_q`` (levant).

    Raises
    ------
    ValueError
        For a Levant differentiator of order above 5 (no tuned parameters).
    """
    if estimator.kind == "linear":
        return tuple(
            math.comb(order + 1, j + 1) * estimator.bandwidth ** (j + 1) for j in range(order + 1)
        )
    if order >= len(LEVANT_LAMBDAS):
        raise ValueError(
            f"Levant's differentiator is tuned here up to order {len(LEVANT_LAMBDAS) - 1}; "
            f'the law needs order {order}: use kind = "linear"'
        )
    return LEVANT_LAMBDAS[: order + 1]
