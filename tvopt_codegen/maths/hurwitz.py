"""The error dynamics ``E' = H E``: companion matrices, poles and coefficients.

The paper writes ``H = companion(a_0, ..., a_{k-1}) kron I_m`` with last row
``a_0 ... a_{k-1}`` (its equation for H), so the characteristic polynomial is
``s^k - a_{k-1} s^{k-1} - ... - a_0`` and ``a_i = -c_i`` for the monic polynomial
``prod (s - lambda)`` = ``s^k + c_{k-1} s^{k-1} + ... + c_0``.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from fractions import Fraction

import numpy as np


def coefficients_from_poles(poles: Sequence[complex]) -> tuple[float, ...]:
    """Return ``a_0 .. a_{k-1}`` whose companion matrix has the given eigenvalues.

    The product is expanded in exact rational arithmetic (conjugate pairs as real
    quadratics) and rounded once, so the coefficients are deterministic and exact to
    the last digit for poles written as decimals.

    Parameters
    ----------
    poles : sequence of complex
        Eigenvalues; complex ones must come with their conjugates.

    Returns
    -------
    tuple of float
        ``(a_0, ..., a_{k-1})``.
    """
    poly = [Fraction(1)]  # coefficients, highest power first
    pending = sorted((p for p in poles if p.imag != 0), key=lambda p: (p.real, p.imag))
    positive = [p for p in pending if p.imag > 0]
    negative = [p for p in pending if p.imag < 0]
    if len(positive) != len(negative):
        raise ValueError("complex poles must come in conjugate pairs")
    factors: list[list[Fraction]] = []
    for p in poles:
        if p.imag == 0:
            factors.append([Fraction(1), -Fraction(p.real)])
    for p in positive:
        re, im = Fraction(p.real), Fraction(p.imag)
        factors.append([Fraction(1), -2 * re, re * re + im * im])
    for factor in factors:
        product = [Fraction(0)] * (len(poly) + len(factor) - 1)
        for i, a in enumerate(poly):
            for j, b in enumerate(factor):
                product[i + j] += a * b
        poly = product
    monic_low_first = list(reversed(poly[1:]))  # c_0 .. c_{k-1}
    return tuple(float(-c) for c in monic_low_first)


def companion(coefficients: Sequence[float]) -> np.ndarray:
    """The paper's k x k companion matrix with last row ``a_0 .. a_{k-1}``."""
    k = len(coefficients)
    matrix = np.zeros((k, k))
    matrix[np.arange(k - 1), np.arange(1, k)] = 1.0
    matrix[k - 1, :] = coefficients
    return matrix


def error_matrix(coefficients: Sequence[float], m: int) -> np.ndarray:
    """``H = companion(a) kron I_m``, acting on ``E = col(grad f0, ..., grad^(k-1) f0)``."""
    return np.kron(companion(coefficients), np.eye(m))


def eigenvalues(coefficients: Sequence[float]) -> np.ndarray:
    """Eigenvalues of the companion matrix, sorted by real then imaginary part."""
    values = np.linalg.eigvals(companion(coefficients))
    return np.array(sorted(values, key=lambda v: (v.real, v.imag)))


def decay_rate(coefficients: Sequence[float]) -> float:
    """``alpha = -max Re(lambda)``; positive exactly when H is Hurwitz."""
    return float(-np.max(eigenvalues(coefficients).real))


def certified_rate(coefficients: Sequence[float]) -> tuple[float, bool]:
    """The rate alpha of the bound ``|expm(H t)| <= c e^{-alpha t}``, and whether it is exact.

    For distinct eigenvalues (diagonalizable H) ``alpha = -max Re(lambda)`` exactly. With
    repeated eigenvalues a Jordan block adds a polynomial factor, so the paper's
    Theorem takes ``-alpha = max Re(lambda) + epsilon``; here epsilon is 10% of the rate,
    which keeps c moderate (a 1% margin makes c grow like 100^(k-1)). Eigenvalues closer
    than 1e-3 of their magnitude count as repeated: a repeated root of the companion
    polynomial is computed only to about the k-th root of machine precision.

    Returns
    -------
    tuple of (float, bool)
        ``alpha`` and ``True`` when it equals the slowest eigenvalue's decay.
    """
    values = eigenvalues(coefficients)
    rate = float(-np.max(values.real))
    gaps = np.abs(values[:, None] - values[None, :]) + np.eye(len(values))
    distinct = bool(np.all(gaps > 1e-3 * max(1.0, float(np.max(np.abs(values))))))
    return (rate, True) if distinct else (0.9 * rate, False)


def exponential(matrix: np.ndarray) -> np.ndarray:
    """``expm(matrix)`` of a small matrix, computed with 40 digits and rounded to floats.

    Here rather than ``scipy.linalg.expm``: every command computes the transient
    constant, and importing scipy for one exponential of a k x k matrix took a fifth of
    a small command's time. mpmath comes with sympy; its extra digits absorb the
    cancellation that a stiff companion matrix (entries up to ``a_0``, far above its
    spectral radius) causes in a double-precision series.

    Parameters
    ----------
    matrix : numpy.ndarray, shape (k, k)

    Returns
    -------
    numpy.ndarray, shape (k, k)
    """
    matrix = np.ascontiguousarray(matrix, dtype=float)
    return np.array(_exponential(matrix.shape, matrix.tobytes()))


@functools.lru_cache(maxsize=256)
def _exponential(shape: tuple[int, ...], data: bytes) -> tuple[tuple[float, ...], ...]:
    """:func:`exponential` of the matrix whose floats are ``data``, once per process.

    A run's grid has a handful of distinct steps, 5-9 ms each with mpmath, and a process
    that simulates again (a sweep's worker, a notebook, the test suite) meets the same
    ones; the answer is a pure function of the bits, so it is kept.
    """
    import mpmath  # noqa: PLC0415 - loaded with sympy; named here, where it is used

    values = np.frombuffer(data, dtype=float).reshape(shape)
    with mpmath.workdps(40):
        exact = mpmath.expm(mpmath.matrix(values.tolist()))
        return tuple(
            tuple(float(exact[i, j]) for j in range(exact.cols)) for i in range(exact.rows)
        )


def flow(coefficients: Sequence[float], m: int, start: np.ndarray, times: np.ndarray) -> np.ndarray:
    """``expm(H t) start`` at each of the increasing ``times``, row by row.

    ``H = companion(a) kron I_m`` (:func:`error_matrix`), so ``expm(H t) start`` is
    ``expm(companion(a) t)`` applied to ``start`` read as k rows of m: only the k x k
    exponential is needed, from :func:`exponential`, whatever the team's size.

    Stepped from one time to the next, ``x(t_{i+1}) = expm(H (t_{i+1} - t_i)) x(t_i)``,
    with one exponential per distinct step: an output grid (a linspace) has a handful of
    distinct steps, so a run of 401 times costs a few exponentials, not 401. Each step
    rounds at about ``eps`` of the state, and every later step carries that error along
    with a gain at most ``c`` (:func:`transient_constant`): over ``n`` steps the error
    stays below about ``n c^2 eps |start|``, far under any tolerance the certificate uses.
    """
    small = companion(coefficients)
    out = np.empty((len(times), len(start)))
    if not len(times):
        return out
    rows = np.asarray(start, dtype=float).reshape(len(small), m)
    if times[0]:
        rows = exponential(small * times[0]) @ rows
    out[0] = rows.ravel()
    steps: dict[float, np.ndarray] = {}
    for i in range(1, len(times)):
        h = float(times[i] - times[i - 1])
        if h not in steps:
            steps[h] = exponential(small * h)
        rows = steps[h] @ rows
        out[i] = rows.ravel()
    return out


def transient_constant(coefficients: Sequence[float], alpha: float) -> float:
    """``c = sup_t |expm(H t)|_2 e^{alpha t}`` (the paper's Theorem on Hurwitz matrices).

    ``H = companion(a) kron I_m`` has the norm of ``companion(a)``, so the supremum is
    taken for the companion matrix, on a grid fine against every time scale of H and
    long enough for the product to have decayed from its peak (it tends to a constant
    or to zero).

    Parameters
    ----------
    coefficients : sequence of float
        ``a_0 .. a_{k-1}``.
    alpha : float
        A rate no larger than the decay rate of H.

    Returns
    -------
    float
        The constant c (at least 1, the value at t = 0).
    """
    return _transient_constant(tuple(float(a) for a in coefficients), float(alpha))


@functools.lru_cache(maxsize=256)
def _transient_constant(coefficients: tuple[float, ...], alpha: float) -> float:
    """:func:`transient_constant`, once per gains and rate in a process.

    It takes 10-90 ms (up to 20,000 grid points), and every derivation asks it: a
    process that derives again specs with the same poles (the test suite, a notebook,
    a tune's candidates) gets the value already computed, a pure function of the bits.
    """
    matrix = companion(coefficients)
    fastest = float(np.max(np.abs(eigenvalues(coefficients))))
    horizon = 40.0 / alpha
    steps = int(min(20000, max(2000, 40 * fastest * horizon)))
    grid = np.linspace(0.0, horizon, steps)
    step = exponential(matrix * grid[1])
    # The powers of the step one after another, their 2-norms (largest singular values)
    # in one batched call: one SVD call per grid point was most of this function's time,
    # itself a tenth of a small command.
    powers = np.empty((len(grid) - 1, len(coefficients), len(coefficients)))
    current = np.eye(len(coefficients))
    for i in range(len(powers)):
        current = powers[i] = current @ step
    norms = np.linalg.svd(powers, compute_uv=False)[:, 0]
    return max(1.0, float(np.max(norms * np.exp(alpha * grid[1:]))))


#: |y - y*| is compared with the bound only where the bound exceeds this: below it the
#: bound is at the integration's and the minimiser's noise.
MEANINGFUL_BOUND = 1e-10
#: The minimiser's absolute accuracy on y*, granted to |y - y*| against the bound.
TARGET_ACCURACY = 1e-8


def tracking_bound(
    t: np.ndarray, c: float, alpha: float, e0: float, m_f: float
) -> tuple[float, np.ndarray]:
    """The theorem's bound on ``|y - y*|``: ``C e^(-alpha t)`` with ``C = c |E(0)| / m_f``.

    Parameters
    ----------
    t : numpy.ndarray
        Times.
    c, alpha : float
        ``|expm(H t)| <= c e^(-alpha t)`` (:func:`transient_constant`, :func:`certified_rate`).
    e0 : float
        ``|E(0)|``.
    m_f : float
        f0's strong convexity modulus along the run (with equalities, the KKT matrix's
        smallest singular value).

    Returns
    -------
    C : float
        The bound's constant.
    bound : numpy.ndarray
        ``C e^(-alpha t)``.
    """
    constant = c * e0 / m_f
    return constant, constant * np.exp(-alpha * np.asarray(t, dtype=float))


def bound_ratio(error: np.ndarray, bound: np.ndarray) -> float:
    """The largest ``(|y - y*| - TARGET_ACCURACY) / bound`` where the bound is meaningful.

    At most 1 when the run keeps to the bound; 0 where no bound is meaningful. The
    certificate of ``simulate`` and the sweep's both ask this function.
    """
    meaningful = bound > MEANINGFUL_BOUND
    if not meaningful.any():
        return 0.0
    return float(np.max((error[meaningful] - TARGET_ACCURACY) / bound[meaningful]))


def integral_split(
    coefficients: Sequence[float], poles: Sequence[complex] | None = None
) -> tuple[float, tuple[float, ...], tuple[float, ...]] | None:
    """Integral action's pole, the nominal law's coefficients, and the bumpless start.

    With integral action ``col(z_I, E)' = H_I col(z_I, E)`` and ``H_I`` has k + 1
    coefficients ``c``. Factor its polynomial as ``(s - lambda) p(s)`` with ``lambda``
    the real eigenvalue closest to zero, ``p`` with coefficients ``a`` (k of them). Then
    the integral states on ``z_I = z*(E) = sum_j b_j E_j``, ``b_j = (a_j - c_{j+1}) / c_0``,
    stay there, and E then moves exactly as under the law without integral action and
    poles ``p``'s; ``delta = z_I - z*(E)`` obeys ``delta' = lambda delta``: it is where a
    disturbance's compensation lives. A controller that starts with ``z_I = z*(E(0))`` and
    holds ``delta`` while an input is clipped does not overshoot for the integral's sake.

    Parameters
    ----------
    coefficients : sequence of float
        ``c_0 .. c_k`` of ``H_I``.
    poles : sequence of complex, optional
        Its eigenvalues as the spec wrote them (exact); default: computed.

    Returns
    -------
    tuple or None
        ``(lambda, (a_0 .. a_{k-1}), (b_0 .. b_{k-1}))``; None when no eigenvalue is real.
    """
    values = list(poles) if poles is not None else list(eigenvalues(coefficients))
    real = [v.real for v in values if abs(v.imag) <= 1e-12 * max(1.0, abs(v))]
    if not real:
        return None
    pole = float(max(real))
    c = [float(v) for v in coefficients]
    k = len(c) - 1
    a = [0.0] * k
    a[k - 1] = c[k] - pole
    for j in range(k - 1, 0, -1):
        a[j - 1] = c[j] + pole * a[j]
    b = tuple(float((a[j] - c[j + 1]) / c[0]) for j in range(k))
    return pole, tuple(a), b
