"""The extended-state observer (``[robust.eso]``): the lumped disturbance, in the law's coordinates.

The law works in the outputs' Brunovsky coordinates: output ``i`` of relative degree
``r_i`` obeys ``y_i^(r_i) = p_i(x) + (R(x) w)_i`` on the model. On a plant that is not
the model, and whatever row of ``x' = f + G u`` the mismatch enters, the *true*
derivatives of ``y_i`` still form a chain of ``r_i`` integrators whose top is

    y_i^(r_i) = p_i(x) + (R(x) w)_i + d_i,

with one lumped term ``d_i``. The model's ``Phi(x)`` is not that chain (under mismatch
``L_f^j h`` is not ``y^(j)``), so the observer estimates the chain from the measured
output ``y_i = h_i(x)`` alone, with ``d_i`` as one more state (Han's extended-state
observer, Gao's bandwidth parametrisation: every pole at ``-omega``):

    eta_j' = eta_{j+1} + l_{j+1} e         (j < r_i - 1),
    eta_{r_i-1}' = v_i + l_{r_i} e,        d_hat' = l_{r_i+1} e,
    e = y_i - eta_0,  l_j = C(r_i + 1, j) omega^j.

The law reads ``eta_j`` where it read ``L_f^j h_i(x)`` (``y_i^(j)`` for
``1 <= j < r_i``; ``y_i`` itself is measured, and padding states stand above ``r_i``)
and commands ``R w = v - p - d_hat``, so that ``y^(r) = v`` again up to the estimation
error. On the model, started at ``eta = Phi(x)`` and ``d_hat = 0``, the
observer's error is zero and stays zero: the closed loop is the plain law's, and so is
its certificate (``E' = H E``).

These rows are the continuous closed loop's (``simulate``, the sweep's continuous runs,
python-control). The sampled controller runs the exact discrete twin at each step: the
chain ``eta`` moves over the step with ``v`` held (a Taylor polynomial, exact), then
the newest measured output corrects it with gains :func:`discrete_gains` chosen so that
the estimation error's poles are all at ``exp(-omega h)``: the continuous design's
poles, sampled.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from fractions import Fraction

import numpy as np

from tvopt_codegen import symbolic as sx
from tvopt_codegen.derivation.model import start_evaluator
from tvopt_codegen.spec import Mechanics


@dataclass(frozen=True)
class Rejection:
    """The extended-state observer of one spec, as the generated controllers run it.

    Attributes
    ----------
    bandwidth : float
        ``omega``, rad/s: every pole of the observer's error at ``-omega``.
    orders : tuple of int
        Per output, its relative degree ``r_i``: the observer estimates
        ``y_i .. y_i^(r_i - 1)`` and ``d_i``.
    states : tuple of tuple of str
        Per output, the controller states ``eso_<output>_0 .. eso_<output>_<r_i - 1>``
        (the estimates of the output's derivatives), then ``eso_<output>_d`` (``d_hat``).
    continuous : tuple of tuple of float
        Per output, ``l_1 .. l_{r_i + 1}``, ``l_j = C(r_i + 1, j) omega^j``.
    discrete : tuple of tuple of tuple of float
        Per output, per gain ``j = 0 .. r_i``: the coefficients of ``gamma^1 ..
        gamma^(r_i + 1)`` of the scaled discrete gain, ``gamma = 1 - exp(-omega h)``;
        the gain on ``eta_j`` (``d_hat`` for ``j = r_i``) is that polynomial over
        ``h^j``.
    """

    bandwidth: float
    orders: tuple[int, ...]
    states: tuple[tuple[str, ...], ...]
    continuous: tuple[tuple[float, ...], ...]
    discrete: tuple[tuple[tuple[float, ...], ...], ...]

    @property
    def names(self) -> tuple[str, ...]:
        """Every observer state, output by output."""
        return tuple(name for chain in self.states for name in chain)

    def recovery(self, i: int) -> float:
        """``l_{r_i} / l_{r_i + 1} = (r_i + 1) / omega``.

        The sampled controller holds ``v_i`` over a step; it reads it from the closed
        loop's rates as ``eta_{r_i-1}' - (l_{r_i} / l_{r_i+1}) d_hat'``.
        """
        return (self.orders[i] + 1) / self.bandwidth


def state_names(outputs: Sequence[str], degrees: Sequence[int]) -> tuple[tuple[str, ...], ...]:
    """The observer's states, per output: ``eso_<output>_<j>`` then ``eso_<output>_d``."""
    return tuple(
        (*(f"eso_{name}_{j}" for j in range(r)), f"eso_{name}_d")
        for name, r in zip(outputs, degrees, strict=True)
    )


def continuous_gains(order: int, bandwidth: float) -> tuple[float, ...]:
    """``l_1 .. l_{r+1}`` of the bandwidth parametrisation, ``(s + omega)^(r + 1)``."""
    n = order + 1
    return tuple(float(math.comb(n, j)) * bandwidth**j for j in range(1, n + 1))


@functools.cache
def discrete_gains(order: int) -> tuple[tuple[float, ...], ...]:
    """The discrete observer's scaled gains as polynomials in ``gamma = 1 - beta``.

    The chain ``(eta_0 .. eta_{r-1}, d)`` moves over a step ``h`` by ``A_d = exp(N h)``
    (``A_d[i][j] = h^(j-i) / (j-i)!``); the newest output corrects it,
    ``x+ = x- + L (y - x-_0)``. The error moves by ``(I - L e_0^T) A_d``; its
    characteristic polynomial is affine in ``L``, and equating it to
    ``(lambda - beta)^(r+1)``, ``beta = exp(-omega h)``, fixes ``L``. With
    ``L_j = c_j(gamma) / h^j`` the equations no longer involve ``h``: ``c_j`` is solved
    for once per order, exactly, here. In ``gamma`` (not ``beta``) the polynomials have
    no cancellation near ``beta = 1``, where a fast sampled loop lives.

    Solved in exact rationals (:class:`fractions.Fraction`): the characteristic
    polynomial is affine in ``c``, so its coefficients at ``c = 0`` and at each unit
    vector give a constant linear system, whose right-hand side is the target's
    coefficients, polynomials in ``gamma``. SymPy's ``solve`` of the same equations took
    5-23 s at order 5 and loaded SymPy into an observer's SymEngine derivation; the
    floats are the same (each an exact rational, correctly rounded).

    Returns
    -------
    tuple of tuple of float
        Per gain ``j = 0 .. r``, the coefficients of ``gamma^1 .. gamma^(r+1)``.
    """
    n = order + 1
    chain = [
        [Fraction(1, math.factorial(j - i)) if j >= i else Fraction(0) for j in range(n)]
        for i in range(n)
    ]

    def characteristic(c: Sequence[Fraction]) -> list[Fraction]:
        """``lambda^(n-1) .. lambda^0``'s coefficients of ``det(lambda I - (A - c A[0]))``."""
        error = [[chain[i][j] - c[i] * chain[0][j] for j in range(n)] for i in range(n)]
        return _characteristic(error)[1:]

    zero = [Fraction(0)] * n
    base = characteristic(zero)
    columns = [
        [
            a - b
            for a, b in zip(
                characteristic([Fraction(int(i == j)) for i in range(n)]), base, strict=True
            )
        ]
        for j in range(n)
    ]
    # (lambda - 1 + gamma)^n: lambda^(n-k)'s coefficient is C(n, k) (gamma - 1)^k, whose
    # gamma^m coefficient is C(n, k) C(k, m) (-1)^(k-m).
    target = [
        [Fraction(math.comb(n, k) * math.comb(k, m) * (-1) ** (k - m)) for m in range(n + 1)]
        for k in range(1, n + 1)
    ]
    rhs = [[t - (base[k] if m == 0 else 0) for m, t in enumerate(target[k])] for k in range(n)]
    solution = _solve([[columns[j][k] for j in range(n)] for k in range(n)], rhs)
    return tuple(tuple(float(x) for x in row[1:]) for row in solution)


def _characteristic(matrix: list[list[Fraction]]) -> list[Fraction]:
    """``det(lambda I - matrix)``'s coefficients, ``lambda^n`` first (Faddeev-LeVerrier)."""
    n = len(matrix)
    coefficients = [Fraction(1)]
    power = [[Fraction(int(i == j)) for j in range(n)] for i in range(n)]  # M_0 = I
    for k in range(1, n + 1):
        product = [
            [sum((matrix[i][m] * power[m][j] for m in range(n)), Fraction(0)) for j in range(n)]
            for i in range(n)
        ]
        c = -sum((product[i][i] for i in range(n)), Fraction(0)) / k
        coefficients.append(c)
        power = [[product[i][j] + (c if i == j else 0) for j in range(n)] for i in range(n)]
    return coefficients


def _solve(matrix: list[list[Fraction]], rhs: list[list[Fraction]]) -> list[list[Fraction]]:
    """``X`` with ``matrix X = rhs``, by Gauss-Jordan elimination in exact rationals."""
    n = len(matrix)
    rows = [list(matrix[i]) + list(rhs[i]) for i in range(n)]
    for col in range(n):
        pivot = next(r for r in range(col, n) if rows[r][col] != 0)
        rows[col], rows[pivot] = rows[pivot], rows[col]
        lead = rows[col][col]
        rows[col] = [x / lead for x in rows[col]]
        for r in range(n):
            if r != col and rows[r][col] != 0:
                factor = rows[r][col]
                rows[r] = [x - factor * y for x, y in zip(rows[r], rows[col], strict=True)]
    return [row[n:] for row in rows]


def rejection(bandwidth: float, degrees: Sequence[int], outputs: Sequence[str]) -> Rejection:
    """The :class:`Rejection` of outputs of these relative degrees."""
    return Rejection(
        bandwidth,
        tuple(degrees),
        state_names(outputs, degrees),
        tuple(continuous_gains(r, bandwidth) for r in degrees),
        tuple(discrete_gains(r) for r in degrees),
    )


def observer_field(
    rejection: Rejection,
    estimates: Sequence[Sequence[sx.Expr]],
    outputs: Sequence[sx.Expr],
    v: Sequence[sx.Expr],
) -> list[sx.Expr]:
    """The observer's rows of the closed-loop field, output by output.

    ``estimates[i]`` are output ``i``'s observer states (the last is ``d_hat``),
    ``outputs[i]`` is ``h_i(x)``, ``v[i]`` the law's new input.
    """
    field: list[sx.Expr] = []
    for i, chain in enumerate(estimates):
        r = rejection.orders[i]
        gains = rejection.continuous[i]
        error = outputs[i] - chain[0]
        for j in range(r):
            above = chain[j + 1] if j + 1 < r else v[i]
            field.append(above + sx.real(gains[j]) * error)
        field.append(sx.real(gains[r]) * error)
    return field


def initial_estimates(
    phi: Sequence[Sequence[sx.Expr]],
    states: Sequence[sx.Expr],
    initial: Sequence[float],
    defaults: Mapping[sx.Expr, float],
    mechanics: Mechanics | None,
) -> tuple[float, ...]:
    """``Phi(x0)`` and a zero ``d_hat`` per output: where the observer's error is zero.

    A value that cannot be evaluated there (the law is undefined at the start, which
    the derivation warns about) starts at 0.
    """
    evaluate = start_evaluator(states, initial, defaults, mechanics)
    out: list[float] = []
    for rows in phi:
        for entry in rows:
            with np.errstate(all="ignore"):
                value = complex(evaluate(entry))
            out.append(value.real if np.isfinite(value) and value.imag == 0 else 0.0)
        out.append(0.0)
    return tuple(out)
