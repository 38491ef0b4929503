"""The search space of ``tune``: the unit box [0, 1]^d and the candidates it decodes to.

A point of the box is a controller's tunable numbers: the error dynamics' poles (real
ones by magnitude; complex pairs by natural frequency and damping), the integral pole
among them when the spec has integral action, and the observer's bandwidth. The
parametrisation makes every point a Hurwitz H: a real pole is ``-r`` with ``r`` in the
magnitude bounds, a pair is ``-zeta w +- j w sqrt(1 - zeta^2)`` with ``zeta >= min
damping > 0``. The count of poles is the derivation's (k, or k + 1 with integral
action) and the number of pairs is fixed: the optimiser moves the numbers, never the
structure.

Decoding rounds each real and imaginary part and the bandwidth to
:data:`SIGNIFICANT_DIGITS` significant digits: the candidate the sweep evaluates is the
one the tuned spec writes, digit for digit.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from tvopt_codegen.errors import SpecError
from tvopt_codegen.maths.hurwitz import coefficients_from_poles

#: Digits kept of every tuned number: what the tuned spec prints and what was evaluated.
SIGNIFICANT_DIGITS = 4

#: Default magnitude bounds: the spec's slowest pole over this factor, its fastest times it.
MAGNITUDE_FACTOR = 5.0
#: Default smallest damping ratio of a complex pair.
DEFAULT_MIN_DAMPING = 0.3
#: Largest damping ratio of a pair. At ``zeta = 1`` the pair is a double real pole (its
#: imaginary part 0, which the spec's ``[re, im]`` refuses); below this, ``im >= 0.04 w``.
MAX_PAIR_DAMPING = 0.999
#: Default bandwidth bounds: the spec's bandwidth over and times this factor.
BANDWIDTH_FACTOR = 10.0

#: Every magnitude and bandwidth bound lies here, rad/s: beyond, no controller's time
#: scale, and a product ``zeta w`` or a rounding could leave the doubles (an underflow to
#: 0 would put a pole on the imaginary axis, an overflow make it infinite).
RATE_LIMITS = (1e-9, 1e9)
#: Smallest damping bound accepted (below, ``zeta w`` could leave the normal doubles).
MIN_DAMPING_LIMIT = 1e-9

#: A pole whose imaginary part is at most this fraction of its magnitude counts as real.
#: A spec given by coefficients has its poles from a companion matrix, where a repeated
#: real root comes out only to the m-th root of machine precision, as a "pair" with an
#: imaginary part near 1e-8 |p| (double) or 1e-5 |p| (triple); no pair the space decodes
#: comes near (its imaginary part is at least 0.04 |p|).
REAL_TOLERANCE = 1e-4


def rounded(value: float, digits: int = SIGNIFICANT_DIGITS) -> float:
    """``value`` rounded to ``digits`` significant digits (the decimal's nearest double).

    Through the decimal text, as the spec will carry it: ``float(f"{v:.4g}")`` is the
    double a TOML reader makes of the printed number, so no second rounding happens on
    the way to the spec.
    """
    return float(f"{value:.{digits}g}")


def _is_real(pole: complex) -> bool:
    return abs(pole.imag) <= REAL_TOLERANCE * max(1.0, abs(pole))


def _order(pole: complex) -> tuple[float, float, float]:
    """Slowest first; at equal real parts a real pole before a pair, ``+j`` before ``-j``."""
    return (-pole.real, abs(pole.imag), -pole.imag)


@dataclass(frozen=True)
class Candidate:
    """One point of the search: the poles of H and the observer's bandwidth.

    Attributes
    ----------
    poles : tuple of complex
        Every eigenvalue, conjugates included, in canonical order (slowest first, a
        pair's ``+j`` member before its ``-j`` one).
    bandwidth : float or None
        The observer's (or extended-state observer's) bandwidth in rad/s; None when the
        spec has none.
    """

    poles: tuple[complex, ...]
    bandwidth: float | None

    @property
    def coefficients(self) -> tuple[float, ...]:
        """``a_0 .. a_{n-1}`` of H's companion matrix (:func:`coefficients_from_poles`)."""
        return coefficients_from_poles(self.poles)


@dataclass(frozen=True)
class Space:
    """The box [0, 1]^d and how its points become candidates.

    Coordinates, in order: one per real pole (its magnitude), two per complex pair
    (natural frequency, then damping), and one for the bandwidth when there is one.
    Magnitudes and the bandwidth are log-uniform in their bounds; damping is uniform in
    ``[min_damping, MAX_PAIR_DAMPING]``.

    Attributes
    ----------
    count : int
        Number of poles, conjugates counted (fixed by the derivation).
    pairs : int
        Number of complex conjugate pairs among them.
    magnitude : tuple of float
        ``(lo, hi)``: bounds on every pole's magnitude, rad/s.
    min_damping : float
        Smallest damping ratio of a pair, in (0, 1].
    bandwidth : tuple of float or None
        ``(lo, hi)`` of the observer's bandwidth, rad/s; None when it is not tuned.
    integral : bool
        Integral action: one real pole at least must remain (it becomes the integral's).
    """

    count: int
    pairs: int
    magnitude: tuple[float, float]
    min_damping: float
    bandwidth: tuple[float, float] | None = None
    integral: bool = False

    def __post_init__(self) -> None:
        # The checks with the user's words are in space_for; a Space built by hand that
        # breaks them is a programming error.
        lo, hi = self.magnitude
        if not (self.count >= 1 and 0 <= 2 * self.pairs <= self.count - int(self.integral)):
            raise ValueError(f"no space of {self.count} poles with {self.pairs} pairs")
        if not (_valid_range(lo, hi) and MIN_DAMPING_LIMIT <= self.min_damping <= 1):
            raise ValueError("magnitude bounds or damping out of range")
        if self.pairs and self.min_damping > MAX_PAIR_DAMPING:
            raise ValueError("no complex pair has that damping")
        if self.bandwidth is not None and not _valid_range(*self.bandwidth):
            raise ValueError("bandwidth bounds out of range")

    @property
    def reals(self) -> int:
        """How many real poles."""
        return self.count - 2 * self.pairs

    @property
    def dimension(self) -> int:
        """d, the number of coordinates."""
        return self.reals + 2 * self.pairs + int(self.bandwidth is not None)

    def decode(self, x: Sequence[float] | np.ndarray) -> Candidate:
        """The candidate at ``x`` (clipped to the box), rounded and in canonical order.

        Parameters
        ----------
        x : array_like, shape (d,)
            A point of [0, 1]^d.

        Returns
        -------
        Candidate
            Hurwitz, with :attr:`count` poles of which :attr:`pairs` pairs; each real
            and imaginary part and the bandwidth rounded to :data:`SIGNIFICANT_DIGITS`
            significant digits (so a bound is kept up to that rounding).
        """
        point = np.clip(np.asarray(x, dtype=float), 0.0, 1.0)
        if point.shape != (self.dimension,):
            raise ValueError(f"expected a point of {self.dimension} coordinates, got {point.shape}")
        if not np.all(np.isfinite(point)):
            raise ValueError("a point of the box must be finite")
        lo, hi = self.magnitude
        poles: list[complex] = []
        for value in point[: self.reals]:
            poles.append(complex(-rounded(_log_uniform(lo, hi, value)), 0.0))
        for j in range(self.pairs):
            w = _log_uniform(lo, hi, point[self.reals + 2 * j])
            zeta = self.min_damping + (MAX_PAIR_DAMPING - self.min_damping) * float(
                point[self.reals + 2 * j + 1]
            )
            re, im = rounded(-zeta * w), rounded(w * math.sqrt(1.0 - zeta * zeta))
            poles += [complex(re, im), complex(re, -im)]
        bandwidth = None
        if self.bandwidth is not None:
            bandwidth = rounded(_log_uniform(*self.bandwidth, point[-1]))
        return Candidate(tuple(sorted(poles, key=_order)), bandwidth)

    def encode(self, candidate: Candidate) -> np.ndarray:
        """The point of the box nearest to ``candidate`` (the inverse of :meth:`decode`).

        A candidate of this space's structure maps back to the point it was decoded from
        (up to the rounding). One of another structure, e.g. the spec's all-real poles
        in a space with a pair, is fitted to this one: two real poles ``-a, -b`` become
        the pair of the same ``w^2 = a b`` (its damping clipped), a surplus pair two real
        poles at ``-w``. Values outside the bounds are clipped to the box.

        Parameters
        ----------
        candidate : Candidate
            Poles (as many as :attr:`count`) and a bandwidth (ignored when the space
            tunes none; when it tunes one and the candidate has none, the middle).

        Returns
        -------
        numpy.ndarray, shape (d,)
        """
        if len(candidate.poles) != self.count:
            raise ValueError(f"expected {self.count} poles, got {len(candidate.poles)}")
        reals = sorted(-p.real for p in candidate.poles if _is_real(p))  # magnitudes
        pairs = [
            (abs(p), -p.real / abs(p)) for p in candidate.poles if not _is_real(p) and p.imag > 0
        ]
        while len(pairs) > self.pairs:  # the fastest pair splits first
            w, _ = max(pairs)
            pairs.remove(max(pairs))
            reals += [w, w]
        reals.sort()
        while len(pairs) < self.pairs:  # the two fastest real poles join; the slow one stays
            a, b = reals.pop(), reals.pop()
            w = math.sqrt(a * b)
            pairs.append((w, (a + b) / (2.0 * w)))
        lo, hi = self.magnitude
        coordinates = [_inverse_log_uniform(lo, hi, r) for r in reals]
        span = MAX_PAIR_DAMPING - self.min_damping
        for w, zeta in sorted(pairs):
            coordinates.append(_inverse_log_uniform(lo, hi, w))
            coordinates.append((zeta - self.min_damping) / span if span > 0 else 0.0)
        if self.bandwidth is not None:
            if candidate.bandwidth is None:
                coordinates.append(0.5)
            else:
                coordinates.append(_inverse_log_uniform(*self.bandwidth, candidate.bandwidth))
        point: np.ndarray = np.clip(np.array(coordinates, dtype=float), 0.0, 1.0)
        return point


def _valid_range(lo: float, hi: float) -> bool:
    """Increasing and within :data:`RATE_LIMITS` (so finite and positive)."""
    return RATE_LIMITS[0] <= lo < hi <= RATE_LIMITS[1]


def _within_limits(lo: float, hi: float) -> tuple[float, float]:
    """A default range cut to :data:`RATE_LIMITS` (the user's own ranges are checked)."""
    return max(lo, RATE_LIMITS[0]), min(hi, RATE_LIMITS[1])


def _checked_range(
    bounds: tuple[float, float], fail: Callable[[str], SpecError]
) -> tuple[float, float]:
    """``bounds`` as floats, or the one-line reason they leave no choice."""
    lo, hi = (float(v) for v in bounds)
    if not (math.isfinite(lo) and math.isfinite(hi)):
        raise fail(f"bounds must be finite, got {lo:g}:{hi:g}")
    if lo <= 0:
        raise fail(f"LO must be positive, got {lo:g}")
    if lo >= hi:
        raise fail(f"LO must be below HI, got {lo:g}:{hi:g}")
    if not _valid_range(lo, hi):
        low, high = RATE_LIMITS
        raise fail(f"bounds must lie within {low:g}:{high:g} rad/s, got {lo:g}:{hi:g}")
    return lo, hi


def _log_uniform(lo: float, hi: float, u: float) -> float:
    # The ends exactly: lo * (hi / lo) ** 1 may differ from hi in the last place.
    if u <= 0.0:
        return lo
    if u >= 1.0:
        return hi
    return float(lo * math.exp(u * math.log(hi / lo)))


def _inverse_log_uniform(lo: float, hi: float, value: float) -> float:
    """Where ``value`` sits in ``[lo, hi]`` on a log scale; beyond it (or 0, inf) clipped later."""
    if not value > 0:
        return 0.0
    if math.isinf(value):
        return 1.0
    return math.log(value / lo) / math.log(hi / lo)


def parse_range(text: str, option: str, source: str = "command line") -> tuple[float, float]:
    """Read ``"LO:HI"`` (two finite numbers) as ``(lo, hi)``.

    Whether the range makes sense for its option is :func:`space_for`'s to say.

    Raises
    ------
    SpecError
        One line naming ``option`` when the text is not two finite numbers.
    """
    parts = text.split(":")
    try:
        if len(parts) != 2:
            raise ValueError
        lo, hi = float(parts[0]), float(parts[1])
    except ValueError:
        raise SpecError(source, option, f"expected LO:HI (two numbers), got {text!r}") from None
    if not (math.isfinite(lo) and math.isfinite(hi)):
        raise SpecError(source, option, f"expected finite numbers, got {text!r}")
    return lo, hi


def space_for(
    poles: Sequence[complex],
    bandwidth: float | None,
    *,
    integral: bool,
    magnitude: tuple[float, float] | None = None,
    min_damping: float | None = None,
    bandwidth_range: tuple[float, float] | None = None,
    pairs: int | None = None,
    field_prefix: str = "--",
    source: str = "command line",
) -> Space:
    """The space around a spec's poles, with the user's bounds checked.

    Parameters
    ----------
    poles : sequence of complex
        The spec's poles (conjugates included), e.g. from ``[error_dynamics] poles`` or
        the eigenvalues of its coefficients; their count is the space's.
    bandwidth : float or None
        The spec's observer bandwidth; None when it has no observer.
    integral : bool
        Whether the spec has integral action (one real pole must remain).
    magnitude : tuple of float, optional
        ``(lo, hi)`` of every pole's magnitude; default ``(min|p| / 5, max|p| * 5)``.
    min_damping : float, optional
        Smallest damping ratio of a pair, in (0, 1]; default 0.3. Above
        :data:`MAX_PAIR_DAMPING` (1: real poles only) no pair is possible, and ``pairs``
        defaults to 0.
    bandwidth_range : tuple of float, optional
        ``(lo, hi)`` of the bandwidth; default ``(bandwidth / 10, bandwidth * 10)``.
    pairs : int, optional
        Number of complex pairs; default: the spec's (0 when ``min_damping`` allows none).
    field_prefix : str
        How the options are named in errors: ``"--"`` gives ``--pole-range``,
        ``"tune."`` gives ``tune.pole_range``.
    source : str
        Where the bounds came from, for errors (``"command line"`` or the spec file).

    Returns
    -------
    Space

    Raises
    ------
    SpecError
        One line, naming the option, when the bounds leave no Hurwitz choice of the
        fixed structure: a magnitude bound not positive, not finite or not increasing;
        a damping outside (0, 1] (or above the largest a pair can have); more pairs than
        the count holds; no real pole left for integral action; a bandwidth range not
        positive and increasing, or one given to a spec without an observer.
    """

    def name(option: str) -> str:
        if field_prefix.startswith("-"):
            return field_prefix + option
        return field_prefix + option.replace("-", "_")

    def fail(option: str, problem: str) -> SpecError:
        return SpecError(source, name(option), problem)

    count = len(poles)
    if not count:
        raise fail("pole-range", "the spec has no poles to tune")
    magnitudes = [abs(complex(p)) for p in poles]
    if magnitude is None:
        if min(magnitudes) <= 0 or not all(math.isfinite(m) for m in magnitudes):
            raise fail("pole-range", "the spec's poles must be nonzero and finite")
        magnitude = _within_limits(
            min(magnitudes) / MAGNITUDE_FACTOR, max(magnitudes) * MAGNITUDE_FACTOR
        )
    lo, hi = _checked_range(magnitude, lambda problem: fail("pole-range", problem))

    if min_damping is None:
        min_damping = DEFAULT_MIN_DAMPING
    if pairs is None:
        # A damping bound no pair can meet asks for real poles only ([tune]'s documented
        # meaning of min_damping = 1); given explicitly, the pairs are refused below.
        spec_pairs = sum(1 for p in poles if not _is_real(complex(p)) and complex(p).imag > 0)
        pairs = 0 if min_damping > MAX_PAIR_DAMPING else spec_pairs
    if pairs < 0:
        raise fail("complex-pairs", f"the number of pairs cannot be negative, got {pairs}")
    if 2 * pairs > count:
        raise fail("complex-pairs", f"{pairs} complex pairs need {2 * pairs} poles; H has {count}")
    if integral and 2 * pairs > count - 1:
        raise fail(
            "complex-pairs",
            f"{pairs} pairs of {count} poles leave no real pole for integral action "
            f"(at most {(count - 1) // 2})",
        )

    if not (math.isfinite(min_damping) and 0 < min_damping <= 1):
        raise fail("min-damping", f"must be in (0, 1], got {min_damping:g}")
    if min_damping < MIN_DAMPING_LIMIT:
        raise fail("min-damping", f"must be at least {MIN_DAMPING_LIMIT:g}, got {min_damping:g}")
    if pairs and min_damping > MAX_PAIR_DAMPING:
        raise fail(
            "min-damping",
            f"{min_damping:g} leaves no complex pair (a pair's damping is below "
            f"{MAX_PAIR_DAMPING:g}; at 1 it is a double real pole): "
            "lower it or use 0 complex pairs",
        )

    box: tuple[float, float] | None = None
    if bandwidth_range is not None and bandwidth is None:
        raise fail("bandwidth-range", "the spec has no observer bandwidth to tune")
    if bandwidth is not None:
        if bandwidth_range is None:
            bandwidth_range = _within_limits(
                bandwidth / BANDWIDTH_FACTOR, bandwidth * BANDWIDTH_FACTOR
            )
        blo, bhi = _checked_range(bandwidth_range, lambda problem: fail("bandwidth-range", problem))
        box = (blo, bhi)
    return Space(count, pairs, (lo, hi), float(min_damping), box, integral)
