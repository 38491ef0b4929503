"""The derivation's shortcuts give the numbers of the computations they replace, to the bit.

The convexity check's fading probe decides most points by Gershgorin's bounds or a
Cholesky factorization instead of an eigenvalue decomposition (issue 49): its verdicts,
and the eigenvalue its warning quotes, are those of LAPACK's eigenvalues.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
import pytest

from tvopt_codegen import symbolic as sx
from tvopt_codegen.derivation import convexity
from tvopt_codegen.derivation.convexity import _PROBE_DISTANCES, _probe_directions
from tvopt_codegen.derivation.hessians import (
    _BAND_LIMIT,
    _fading_dense,
    _Gershgorin,
    _SparseHessians,
)
from tvopt_codegen.derivation.pipeline import derive
from tvopt_codegen.maths.numeric import Tape

EPS = float(np.finfo(float).eps)


def _ring(m: int) -> list[tuple[int, int]]:
    """A ring's lower pattern: each output coupled to the next, the last to the first."""
    return [(i, i) for i in range(m)] + [
        (max(i, (i + 1) % m), min(i, (i + 1) % m)) for i in range(m)
    ]


def _star(m: int) -> list[tuple[int, int]]:
    """Every output coupled to the first: no narrow band in any order."""
    return [(i, i) for i in range(m)] + [(i, 0) for i in range(1, m)]


def _dense_of(entries: list[tuple[int, int]], m: int) -> Callable[[np.ndarray], np.ndarray]:
    def dense(values: np.ndarray) -> np.ndarray:
        out = np.zeros((values.shape[1], m, m))
        for (i, j), v in zip(entries, values, strict=True):
            out[:, i, j] = out[:, j, i] = v
        return out

    return dense


def _batch(entries: list[tuple[int, int]], m: int, rng: np.random.Generator) -> np.ndarray:
    """Entries (E, P) of matrices of every kind the probe meets: diagonally dominant,
    definite but not dominant, indefinite, with a negative diagonal, nearly singular,
    huge and tiny, indefinite with a positive diagonal."""
    diagonal = np.array([i == j for i, j in entries])
    columns = []
    for scale, spread, shift in [
        (1.0, 0.05, 2.0),  # dominant: Gershgorin settles it
        (1.0, 0.6, 1.0),  # definite, not dominant: Cholesky settles it
        (1.0, 1.0, 0.0),  # indefinite
        (1.0, 1.0, -3.0),  # a negative diagonal
        (1e12, 0.3, 1.0),  # huge
        (1e-9, 0.3, 1.0),  # tiny, near the threshold
    ]:
        for _ in range(12):
            values = rng.normal(0.0, spread, size=len(entries))
            values[diagonal] += shift
            columns.append(scale * values)
    # A positive diagonal, indefinite through a coupling: a 2 x 2 submatrix shows it.
    for _ in range(12):
        values = np.where(diagonal, 1.0, 3.0) + rng.normal(0.0, 0.1, size=len(entries))
        columns.append(values)
    return np.array(columns).T


@pytest.mark.parametrize("pattern", ["ring", "star"])
@pytest.mark.parametrize("m", [6, 40])
def test_fading_verdicts_are_the_eigenvalues(pattern: str, m: int) -> None:
    """_fading_dense's verdict is ``|eigvalsh low| < threshold`` at every point, with
    thresholds on both sides of the smallest eigenvalue by a few ulps, at its negative,
    NaN and zero; non-candidates and non-finite matrices never fade; the eigenvalue it
    returns is eigvalsh's bits; and the screens do settle the easy points."""
    rng = np.random.default_rng(3 + m)
    entries = _ring(m) if pattern == "ring" else _star(m)
    dense = _dense_of(entries, m)
    bounds = _Gershgorin(entries, m)
    values = _batch(entries, m, rng)
    exact = np.linalg.eigvalsh(dense(values))[:, 0]
    thresholds: list[np.ndarray] = [np.abs(exact) * factor for factor in (0.5, 2.0, 1e-6)]
    for ulps in (-3, -1, 0, 1, 3):
        thresholds.append(np.abs(exact) * (1.0 + ulps * EPS))
        thresholds.append(np.nextafter(np.abs(exact), np.inf * ulps) if ulps else np.abs(exact))
    thresholds.append(np.full(len(exact), np.nan))
    thresholds.append(np.zeros(len(exact)))
    thresholds.append(rng.uniform(0.0, 3.0, size=len(exact)))
    candidates = rng.uniform(size=len(exact)) < 0.9
    broken = values.copy()
    broken[0, ::7] = np.nan
    broken[1, ::11] = np.inf
    for threshold in thresholds:
        for given in (values, broken):
            fading, low = _fading_dense(bounds, dense, given, threshold, candidates)
            finite = np.all(np.isfinite(given), axis=0)
            with np.errstate(invalid="ignore"):
                expected = candidates & finite & (np.abs(exact) < threshold)
            np.testing.assert_array_equal(fading, expected)
            computed = np.isfinite(low)
            # Bit for bit: the eigenvalue of each matrix alone is the batch's.
            np.testing.assert_array_equal(low[computed], exact[computed])
    # The dominant and the definite matrices are settled without eigenvalues: those
    # definite beyond rounding (smallest eigenvalue above 1e-6 of the largest).
    threshold = 1e-6 * np.abs(exact)
    _, low = _fading_dense(bounds, dense, values, threshold, np.ones(len(exact), dtype=bool))
    largest = np.abs(np.linalg.eigvalsh(dense(values))).max(axis=1)
    assert not np.isfinite(low[exact > 1e-6 * largest]).any()
    assert not np.isfinite(low[:12]).any()
    assert np.isfinite(low).sum() < len(low) / 2


@pytest.mark.parametrize("pattern", ["ring", "star"])
def test_the_screen_agrees_with_the_sparse_factorizations(pattern: str) -> None:
    """Past 64 outputs the probe factors sparse Hessians; where Gershgorin's screen
    settles a point first, the factorization it skips would have said the same
    (H - tau I definite where surely above; H + tau I not where surely below), and so
    would the eigenvalues."""
    m = 70  # the star too wide for a band (SuperLU factors it), the ring a narrow one
    rng = np.random.default_rng(21)
    entries = _ring(m) if pattern == "ring" else _star(m)
    sparse = _SparseHessians(entries, m)
    assert (sparse.band <= _BAND_LIMIT) is (pattern == "ring")
    values = _batch(entries, m, rng)
    exact = np.linalg.eigvalsh(_dense_of(entries, m)(values))[:, 0]
    thresholds = (
        1e-6 * np.abs(exact),
        np.abs(exact) * (1 - 4 * EPS),
        rng.uniform(size=len(exact)),
    )
    for threshold in thresholds:
        above, below, _ = _Gershgorin(entries, m).screen(values, threshold)
        assert not (above & below).any()
        if threshold is thresholds[0]:
            # Those with a negative diagonal are settled, and the dominant ones of the
            # ring (the star's first row sums 69 couplings: not dominant).
            assert below[36:48].all() and below[72:].all()
            assert bool(above[:12].all()) is (pattern == "ring")
        for point in np.flatnonzero(above):
            assert exact[point] > threshold[point]
            assert sparse.positive_definite(values[:, point], -threshold[point]) in (True, None)
        for point in np.flatnonzero(below):
            assert exact[point] < -threshold[point]
            assert sparse.positive_definite(values[:, point], threshold[point]) in (False, None)


def _old_fading_warning(
    numbers: Any, path: np.ndarray, ts: np.ndarray, path_low: np.ndarray, converged: np.ndarray
) -> list[str]:
    """The dense probe as it was: every probe point's eigenvalues, then the verdicts."""
    count, m = path.shape
    probes = [(d, direction) for d in _PROBE_DISTANCES for direction in _probe_directions(m)]
    points = np.concatenate([path + d * direction for d, direction in probes])
    times = np.tile(ts, len(probes))
    reference = np.tile(path_low, len(probes))
    candidates = np.tile(converged, len(probes))
    low, _ = numbers.extremes(points, times)
    fading = candidates & (np.abs(low) < 1e-6 * reference)
    if not fading.any():
        return []
    at = int(np.argmax(fading))
    distance, when = probes[at // count][0], ts[at % count]
    return [
        "objective.f0: f0 is strongly convex only near its minimiser: at distance "
        f"{distance:g} "
        f"from y*(t) (t = {when:.6g}) the Hessian's smallest eigenvalue is "
        f"{low[at]:.3g}, against {reference[at]:.3g} at y*; the certificate's "
        "bound holds only while the outputs stay where it is bounded below"
    ]


def _team(n: int, f0: str) -> dict[str, Any]:
    return {
        "name": "team",
        "system": {
            "states": [f"x{i}" for i in range(n)],
            "inputs": [f"u{i}" for i in range(n)],
            "dynamics": {f"x{i}": f"u{i}" for i in range(n)},
            "outputs": {f"y{i}": f"x{i}" for i in range(n)},
        },
        "objective": {"f0": f0},
        "error_dynamics": {"poles": [-1.0]},
        "simulation": {"t_final": 5.0},
    }


@pytest.mark.parametrize(
    ("n", "f0", "warned"),
    [
        # Fading: log cosh's curvature 1/cosh(10)^2 at distance 10.
        (20, " + ".join(f"log(cosh(y{i} - sin(t + {i})))" for i in range(20)), True),
        # Neighbours coupled by a tan barrier: indefinite at distance 100, never fading.
        (
            24,
            " + ".join(
                f"(y{i} - sin(t + {i}))**2 + 0.001*tan((y{i} - y{(i + 1) % 24})**2/20)**2"
                for i in range(24)
            ),
            False,
        ),
        # A curvature that fades only at some times and along some directions.
        (8, " + ".join(f"log(cosh(3*y{i} - t)) + 1e-7*y{i}**2" for i in range(8)), True),
    ],
)
def test_the_fading_warning_is_the_one_of_every_eigenvalue(
    n: int, f0: str, warned: bool, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Up to 64 outputs the probe's warning (or its absence) is the one the old probe,
    every point's eigenvalues, gives from the same minimiser path."""
    original = convexity._fading_convexity
    seen: list[tuple[list[str], list[str]]] = []

    def both(*args: Any) -> list[str]:
        new = original(*args)
        seen.append((new, _old_fading_warning(*args)))
        return new

    monkeypatch.setattr(convexity, "_fading_convexity", both)
    derivation = derive(_team(n, f0))
    ((new, old),) = seen
    assert new == old
    assert bool(new) is warned
    assert list(derivation.warnings) == new


def test_a_restricted_tape_gives_the_full_tapes_bits() -> None:
    """``Tape.only`` runs the operations its outputs need, the same ones in the same
    order: the convexity check's Hessian tape is its derivatives' tape restricted, one
    walk of the expressions instead of two."""
    x, y, t = (sx.symbol(name) for name in ("x", "y", "t"))
    a, b = sx.symbol("a"), sx.symbol("b")
    definitions = {a: sx.sin(x * y) + t, b: sx.exp(a) * sx.cos(y) - a**3}
    outputs = [a + x, b * y, sx.tan(b) / (1 + x**2), sx.Integer(2), y]
    full = Tape([x, y, t], outputs, definitions, {})
    rng = np.random.default_rng(2)
    point = [rng.normal(size=50) for _ in range(3)]
    every = full(*point)
    for indices in ([0], [1, 2], [2, 0], [3], [4, 1], []):
        part = full.only(indices)
        got = part(*point)
        assert len(got) == len(indices)
        for index, value in zip(indices, got, strict=True):
            np.testing.assert_array_equal(value, every[index])
        assert len(part._operations) <= len(full._operations)
    # Only what an output needs runs: x + a needs neither b nor tan.
    assert len(full.only([0])._operations) < len(full.only([2])._operations)
