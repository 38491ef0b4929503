"""What the stateful controller does about a plant that is not its model, as data.

Integral action is part of the law (:mod:`tvopt_codegen.derivation.law`: the integrals of
``grad f0`` are closed-loop states). The rest runs in the stateful controller at each
step, in every backend the same way (the Python run-time library's ``guard`` macro and
its C twin):

- **limits**: the input applied is the commanded one clipped to ``[low, high]`` and,
  after a first step, to the slew window ``u_last -+ rate h``;
- **anti-windup**: while an input is clipped, the integral states stop integrating, and
  the extension chain of a clipped prolonged input is set to the value that gives the
  applied input (its derivatives and drive, where they push further out, to zero): every
  controller state follows the input actually applied;
- **disturbance observer** of a matched input disturbance ``d`` in
  ``x' = f(x) + G(x) (u + d)``: from the measured plant state and the applied input,
  ``r_k = (x_k - x_{k-1}) / h - (F_{k-1} + F_k) / 2`` with ``F = f(x) + G(x) u_applied``
  (the trapezoid rule: ``r_k = G d + O(h^2)``), filtered by
  ``sigma_k = sigma_{k-1} + (1 - e^(-beta h)) (r_k - sigma_{k-1})`` (every pole at
  ``-beta``), and ``d_hat`` the least-squares solution of ``G(x_k) d = sigma_k``; the
  controller commands ``u - d_hat``. ``f(x)`` and ``G(x)`` come out of the law's jet
  kernel, which evaluates them with the law's own trigonometry: no new derivative, no
  symbolic inverse, no second evaluation of the plant. The residual is kept on the rows
  ``G`` acts on (:attr:`Robustness.observed_states`): on the others ``G d`` has no
  component. The least squares are solved per
  block of inputs whose columns of ``G`` share a row (:attr:`Robustness.observer_blocks`),
  over ``G``'s structural nonzeros alone: where the columns share none, as for most
  mechanical plants, each input's estimate is one quotient.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

from tvopt_codegen.derivation.law import Law
from tvopt_codegen.derivation.model import Model
from tvopt_codegen.derivation.rejection import Rejection
from tvopt_codegen.maths.lie import Extension

#: A pivot of ``G^T G`` below this fraction of its largest diagonal entry: G has lost
#: rank at the state, and the observer keeps its last estimate.
GRAM_TOLERANCE = 1e-12

#: The observer's filter gain ``1 - exp(-beta h)`` and ``1 / h`` are computed again only
#: when the sample time moves by more than this fraction of itself. A loop at a fixed
#: rate gives steps ``t_k - t_{k-1}`` that differ in their last digits (the times'
#: rounding: 2e-12 of a 1 ms step at t = 10 s); recomputing an ``expm1`` and a
#: division for them would change nothing but the cost of a step.
STEP_TOLERANCE = 1e-9


@dataclass(frozen=True)
class Robustness:
    """The stateful controller's limits, anti-windup and observer for one spec.

    Attributes
    ----------
    low, high, rate : tuple of float
        Per plant input (``INPUT_NAMES`` order): the range and the largest ``|du/dt|``
        (``-inf``, ``inf`` and ``inf`` where the spec gives none).
    observer : float or None
        The observer's bandwidth ``beta``, rad/s; None: no observer.
    integral_chains : tuple of int
        Indices in ``Law.chains`` of the integral states' chains.
    bumpless : tuple of float
        ``b_0 .. b_{k-1}``: the integrals start at ``z*(E) = sum_j b_j E_j`` and, while an
        input is clipped, hold ``delta = z_I - z*(E)`` (see
        :func:`~tvopt_codegen.maths.hurwitz.integral_split`).
    integral_rows : tuple of int
        Where the integral states are among the controller states.
    input_chains : tuple of int
        Per plant input, the index in ``Law.chains`` of its extension chain (-1: the
        input is not prolonged).
    observer_rows : tuple of tuple of int
        Per plant input, the plant states whose row of ``G`` is not structurally zero
        in that input's column (empty without an observer).
    observer_blocks : tuple of tuple of int
        The plant inputs in blocks, ascending: two inputs share a block when their
        columns of ``G`` share a row, directly or through others. ``G^T G`` is block
        diagonal along them, so each block's least squares are solved alone.
    eso : Rejection or None
        The extended-state observer (``[robust.eso]``), None without one.
    eso_rows : tuple of tuple of int
        Per output, where the extended-state observer's states are among the
        controller states (the estimates, then ``d_hat``).
    """

    low: tuple[float, ...]
    high: tuple[float, ...]
    rate: tuple[float, ...]
    observer: float | None
    integral_chains: tuple[int, ...]
    input_chains: tuple[int, ...]
    bumpless: tuple[float, ...] = ()
    integral_rows: tuple[int, ...] = ()
    observer_rows: tuple[tuple[int, ...], ...] = ()
    observer_blocks: tuple[tuple[int, ...], ...] = ()
    eso: Rejection | None = None
    eso_rows: tuple[tuple[int, ...], ...] = ()

    @property
    def eso_estimates(self) -> tuple[int, ...]:
        """The rows of the observer's estimates of the outputs' derivatives (no ``d_hat``)."""
        return tuple(row for rows in self.eso_rows for row in rows[:-1])

    @property
    def observed_states(self) -> tuple[int, ...]:
        """The plant states some input acts on (a row of ``G`` not structurally zero).

        The observer keeps its residual, and the last state and motion it is formed
        from, on these rows alone: on the others ``G d`` has no component, and their
        residual would reach no estimate.
        """
        return tuple(sorted({k for rows in self.observer_rows for k in rows}))

    def gram_rows(self, i: int, j: int) -> tuple[int, ...]:
        """The rows that add to ``(G^T G)[i, j]``: nonzero in both columns."""
        return tuple(k for k in self.observer_rows[i] if k in self.observer_rows[j])

    @property
    def limited(self) -> bool:
        """Whether any input has a limit or a rate."""
        return any(math.isfinite(v) for v in (*self.low, *self.high, *self.rate))

    @property
    def active(self) -> bool:
        """Whether the controller does anything beyond the nominal law at a step."""
        return (
            self.limited
            or self.observer is not None
            or bool(self.integral_chains)
            or self.eso is not None
        )


def robustness(
    model: Model,
    law: Law,
    extension: Extension,
    state_names: Sequence[str],
    integral_states: Sequence[str],
    bumpless: tuple[float, ...],
    rejection: Rejection | None,
) -> Robustness:
    """The :class:`Robustness` of a spec's ``[robust]`` and ``[limits]``: a stage record.

    The derivation computes it once (:attr:`Derivation.robustness`); the templates, the
    report, lowering and the sweep read it there.
    """
    settings, inputs = model.settings, model.input_names
    limits = {limit.input: limit for limit in settings.limits}
    inf = math.inf
    low = tuple(limits[u].low if u in limits else -inf for u in inputs)
    high = tuple(limits[u].high if u in limits else inf for u in inputs)
    rate = tuple(limits[u].rate if u in limits else inf for u in inputs)
    extended = [name for name, _ in extension.counts]
    input_chains = tuple(extended.index(u) if u in extended else -1 for u in inputs)
    chains = law.chains
    count = len(integral_states)
    integral_chains = tuple(range(len(chains) - count, len(chains)))
    first = len(model.x)
    rows: tuple[tuple[int, ...], ...] = ()
    if settings.robust.observer is not None:
        n, m = model.G.shape
        rows = tuple(tuple(k for k in range(n) if model.G[k, i] != 0) for i in range(m))
    return Robustness(
        low,
        high,
        rate,
        settings.robust.observer,
        integral_chains,
        input_chains,
        bumpless,
        tuple(state_names.index(name) - first for name in integral_states),
        rows,
        _blocks(rows),
        rejection,
        ()
        if rejection is None
        else tuple(
            tuple(state_names.index(name) - first for name in chain) for chain in rejection.states
        ),
    )


def _blocks(rows: tuple[tuple[int, ...], ...]) -> tuple[tuple[int, ...], ...]:
    """The inputs grouped by shared rows of ``G`` (connected components), ascending."""
    block = list(range(len(rows)))

    def root(i: int) -> int:
        while block[i] != i:
            i = block[i]
        return i

    for i in range(len(rows)):
        for j in range(i):
            if set(rows[i]) & set(rows[j]):
                block[root(i)] = root(j)
    groups: dict[int, list[int]] = {}
    for i in range(len(rows)):
        groups.setdefault(root(i), []).append(i)
    return tuple(sorted(tuple(group) for group in groups.values()))
