"""The numerical checks of strong convexity.

Newton along ``y*(t)``, the probes of the Hessian (dense, or banded for large teams), and
the constraints' convexity and feasibility.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np

from tvopt_codegen import symbolic as sx
from tvopt_codegen.derivation.calculus import constraint_hessian_entries
from tvopt_codegen.derivation.model import Model
from tvopt_codegen.derivation.record import Convexity
from tvopt_codegen.errors import AssumptionError
from tvopt_codegen.maths.jet import Program
from tvopt_codegen.maths.numeric import Evaluator, Tape
from tvopt_codegen.maths.sparse import reverse_cuthill_mckee
from tvopt_codegen.spec import Constraint
from tvopt_codegen.spec.constraints import Violation

#: A Hessian whose smallest eigenvalue is below this fraction of its scale (the largest
#: eigenvalue met) is degenerate: f0 is not strongly convex there.
DEGENERATE_HESSIAN = 1e-8


#: Times along the horizon at which the minimiser y*(t) is found and checked.
_PATH_POINTS = 25


#: Times along the horizon at which the constraints' feasibility is checked, and the
#: least violation above which nothing satisfies them.
_FEASIBILITY_POINTS = 41
_INFEASIBLE = 1e-7


#: Distances from y*(t) probed for where f0 stops being strongly convex.
_PROBE_DISTANCES = (1.0, 10.0, 100.0)


#: Up to this many outputs the fading probe steps along every axis; beyond, along this
#: many fixed directions.
_PROBE_AXES = 16


#: Memory for the Hessians of the fading probe evaluated at once.
_PROBE_BYTES = 64 * 2**20


#: Sparse Hessians whose band (in the reverse Cuthill-McKee order) is at most this wide
#: are factored as bands; wider ones by SuperLU.
_BAND_LIMIT = 32


#: Beyond this many outputs the Hessian's samples are handled as sparse matrices (a
#: team's is almost all zeros): the fading probe factors them, the convexity check takes
#: their banded eigenvalues and the search for y*(t) their banded LU (:class:`_SparseHessians`).
_SPARSE_PROBE = 64


class _ObjectiveNumbers:
    """f0, its gradient and its Hessian at many (y, t) points at once."""

    def __init__(
        self,
        model: Model,
        program: Program,
        gradient: Sequence[sx.Expr],
        entries: Sequence[tuple[tuple[int, int], sx.Expr]],
        defaults: Mapping[sx.Expr, float],
    ) -> None:
        self.model, self.program, self.gradient = model, program, gradient
        self.entries, self.defaults = entries, defaults

    def _tape(self, outputs: Sequence[sx.Expr]) -> Tape:
        """``outputs`` compiled over (y_1 .. y_m, t): parameters at their defaults."""
        nominal = dict(self.model.nominal)
        definitions = nominal | dict(self.model.signals) | dict(self.program.assignments)
        # A reference without a nominal closed form is unknown here: taken at 0.
        constants: dict[sx.Expr, Any] = dict(self.defaults)
        constants |= {r: 0.0 for r in self.model.references if r not in nominal}
        return Tape([*self.model.y, self.model.t], outputs, definitions, constants)

    @functools.cached_property
    def _f0(self) -> Tape:
        return self._tape([self.model.f0])

    @functools.cached_property
    def _hessian(self) -> Tape:
        # The derivatives' tape, restricted: one walk of the expressions, not two.
        gradients = len(self.gradient)
        return self._derivatives.only(range(gradients, gradients + len(self.entries)))

    @functools.cached_property
    def _derivatives(self) -> Tape:
        return self._tape([*self.gradient, *(expr for _, expr in self.entries)])

    @staticmethod
    def _inputs(ys: np.ndarray, ts: np.ndarray) -> list[np.ndarray]:
        return [*(ys[:, i] for i in range(ys.shape[1])), ts]

    def value(self, ys: np.ndarray, ts: np.ndarray) -> np.ndarray:
        (out,) = self._f0(*self._inputs(ys, ts))
        return np.broadcast_to(np.asarray(np.real(out), dtype=float), ts.shape).copy()

    def hessian_entries(self, ys: np.ndarray, ts: np.ndarray) -> np.ndarray:
        """The Hessian's stored entries (E, P) at the points (NaN where undefined)."""
        values = np.empty((len(self.entries), len(ts)))
        for index, value in enumerate(self._hessian(*self._inputs(ys, ts))):
            values[index] = np.real(value)
        return values

    def derivatives(self, ys: np.ndarray, ts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Gradients (P, m) and Hessians (P, m, m) at the points (NaN where undefined)."""
        grads, values = self._gradients_and_entries(ys, ts)
        return grads, self._dense(values)

    def _gradients_and_entries(
        self, ys: np.ndarray, ts: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """Gradients (P, m) and the Hessian's stored entries (E, P) at the points."""
        points, m = ys.shape
        results = self._derivatives(*self._inputs(ys, ts))
        grads = np.empty((points, m))
        for i in range(m):
            grads[:, i] = np.real(results[i])
        values = np.empty((len(self.entries), points))
        for index, value in enumerate(results[m:]):
            values[index] = np.real(value)
        return grads, values

    def _dense(self, values: np.ndarray) -> np.ndarray:
        """The Hessians (P, m, m) of stored entries (E, P)."""
        m = len(self.model.y)
        matrices = np.zeros((values.shape[1], m, m))
        for ((i, j), _), value in zip(self.entries, values, strict=True):
            matrices[:, i, j] = matrices[:, j, i] = value
        return matrices

    @functools.cached_property
    def sparse(self) -> _SparseHessians | None:
        """The Hessian's pattern, for a team's outputs (beyond :data:`_SPARSE_PROBE`)."""
        m = len(self.model.y)
        return _SparseHessians([ij for ij, _ in self.entries], m) if m > _SPARSE_PROBE else None

    @functools.cached_property
    def gershgorin(self) -> _Gershgorin:
        """Bounds on the Hessian's smallest eigenvalue from its stored entries."""
        return _Gershgorin([ij for ij, _ in self.entries], len(self.model.y))

    def extremes(self, ys: np.ndarray, ts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The Hessian's smallest and largest |eigenvalue| at each point (NaN if not finite)."""
        if self.sparse is None:
            return _smallest_eigenvalues(self.derivatives(ys, ts)[1])
        return self.sparse.extremes(self.hessian_entries(ys, ts), self._dense)

    def newton(self, ys: np.ndarray, ts: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Gradients (P, m), Newton steps H^-1 grad, and where H was finite and nonsingular.

        Non-finite gradient entries are taken as 0; where H is not usable the step is
        the solve with the identity's place taken (the caller falls back to the gradient).
        """
        if self.sparse is None:
            grads, matrices = self.derivatives(ys, ts)
            grads = np.where(np.isfinite(grads), grads, 0.0)
            usable = np.all(np.isfinite(matrices), axis=(1, 2))
            usable &= np.abs(np.linalg.det(np.where(usable[:, None, None], matrices, 1.0))) > 0
            safe = np.where(usable[:, None, None], matrices, np.eye(matrices.shape[1]))
            return grads, np.linalg.solve(safe, grads[:, :, None])[:, :, 0], usable
        grads, values = self._gradients_and_entries(ys, ts)
        grads = np.where(np.isfinite(grads), grads, 0.0)
        steps, usable = self.sparse.solve(values, grads, self._dense)
        return grads, steps, usable


def _smallest_eigenvalues(matrices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Smallest and largest |eigenvalue| of each finite matrix (NaN for the others)."""
    low = np.full(len(matrices), np.nan)
    high = np.full(len(matrices), np.nan)
    finite = np.all(np.isfinite(matrices), axis=(1, 2))
    if finite.any():
        eig = np.linalg.eigvalsh(matrices[finite])
        low[finite] = eig[:, 0]
        high[finite] = np.max(np.abs(eig), axis=1)
    return low, high


#: The screens of the fading probe settle a verdict only this far beyond rounding: the
#: margin is this many times (m + 1)^2 eps ||H||, above Cholesky's backward error
#: ((m + 1)^2 u ||H||, Higham Thm 10.3 and Demmel's converse, Thm 10.7), LAPACK's symmetric
#: eigenvalues' (a modest p(m) eps ||H||) and a row sum's rounding (m eps ||H||) together.
_SCREEN_MARGIN = 8.0


class _Gershgorin:
    """Bounds on the smallest eigenvalue of one sparse symmetric pattern's matrices.

    Every eigenvalue lies in a Gershgorin disc, so the smallest is at least
    ``min_i (h_ii - sum_{j != i} |h_ij|)``; and it is at most every diagonal entry and
    the smallest eigenvalue of every 2 x 2 principal submatrix of a stored entry
    (Cauchy's interlacing). All come from the stored entries in O(entries), where an
    eigenvalue decomposition is O(m^3) a matrix.
    """

    def __init__(self, entries: Sequence[tuple[int, int]], m: int) -> None:
        lower = np.array(entries, dtype=np.int64).reshape(-1, 2)
        on = lower[:, 0] == lower[:, 1]
        self.m = m
        self.diagonal, self.diagonal_rows = np.flatnonzero(on), lower[on, 0]
        self.off, self.ends = np.flatnonzero(~on), lower[~on]

    def screen(self, values: np.ndarray, threshold: np.ndarray) -> tuple[np.ndarray, ...]:
        """Where the smallest eigenvalue is surely above or below a threshold, and the margin.

        ``values`` (E, P) are the points' stored entries, ``threshold`` (P) positive.
        Returns where the smallest eigenvalue is surely above ``threshold``, where surely
        below ``-threshold``, and the margin used (each (P,)). "Surely" beyond rounding:
        LAPACK's smallest eigenvalue and a Cholesky factorization of
        ``H - (threshold + margin) I`` agree with the verdict (NaN or infinite entries,
        or a norm that overflows, settle nothing).
        """
        points = values.shape[1]
        diagonal = np.zeros((self.m, points))
        diagonal[self.diagonal_rows] = values[self.diagonal]
        radius = np.zeros((self.m, points))
        magnitude = np.abs(values[self.off])
        np.add.at(radius, self.ends[:, 0], magnitude)
        np.add.at(radius, self.ends[:, 1], magnitude)
        with np.errstate(all="ignore"):
            # The largest row sum of |H| bounds its spectral norm (H symmetric).
            norm = (radius + np.abs(diagonal)).max(axis=0, initial=0.0)
            margin = _SCREEN_MARGIN * (self.m + 1) ** 2 * np.finfo(float).eps * (norm + threshold)
            above = (diagonal - radius).min(axis=0, initial=np.inf) > threshold + margin
            first, second = diagonal[self.ends[:, 0]], diagonal[self.ends[:, 1]]
            pairs = 0.5 * (first + second) - np.hypot(0.5 * (first - second), values[self.off])
            lowest = np.minimum(
                diagonal.min(axis=0, initial=np.inf), pairs.min(axis=0, initial=np.inf)
            )
            below = lowest < -threshold - margin
        settled = np.isfinite(margin)
        return above & settled, below & settled, margin


def _fading_dense(
    bounds: _Gershgorin,
    dense: Callable[[np.ndarray], np.ndarray],
    values: np.ndarray,
    threshold: np.ndarray,
    candidates: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Where the Hessian's smallest eigenvalue is in (-threshold, threshold), and its value.

    ``values`` (E, P) are the candidates' stored entries of ``bounds``' pattern, ``dense``
    builds their matrices; the eigenvalue is returned where it was computed (NaN
    elsewhere). The verdict is LAPACK's smallest eigenvalue's, ``|low| < threshold``,
    asked of it only where cheaper evidence leaves it open: Gershgorin's bounds
    (:class:`_Gershgorin`), then a Cholesky factorization of ``H - (threshold + margin)
    I``, which exists at every point where f0 is strongly convex, the common case. Each
    screen decides only beyond rounding, so the verdicts are the eigenvalues' to the bit.
    """
    points = values.shape[1]
    fading = np.zeros(points, dtype=bool)
    low = np.full(points, np.nan)
    # |NaN| < threshold is False: no threshold (a NaN at y*), no fading.
    open_ = candidates & np.all(np.isfinite(values), axis=0) & (threshold > 0)
    above, below, margin = bounds.screen(values, threshold)
    open_ &= ~above & ~below
    index = np.flatnonzero(open_ & np.isfinite(threshold + margin))
    if index.size:
        eye = np.eye(bounds.m)
        shifted = dense(values[:, index])
        shifted -= (threshold[index] + margin[index])[:, None, None] * eye
        for point, matrix in zip(index, shifted, strict=True):
            try:
                factor = np.linalg.cholesky(matrix)
            except np.linalg.LinAlgError:
                continue
            open_[point] = not np.all(np.isfinite(factor))
    if open_.any():
        low[open_], _ = _smallest_eigenvalues(dense(values[:, open_]))
        fading[open_] = np.abs(low[open_]) < threshold[open_]
    return fading, low


def _minimiser_path(
    numbers: _ObjectiveNumbers, starts: np.ndarray, ts: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """``y*(t)`` at every time by damped Newton (all times at once), and which converged.

    Time ``ts[k]`` starts from ``starts[k]``; steps are Newton's where the Hessian is
    positive definite, the gradient's elsewhere, halved until f0 decreases.
    """
    points = len(ts)
    ys = np.array(starts, dtype=float)
    converged = np.zeros(points, dtype=bool)
    with np.errstate(all="ignore"):
        # 40 steps: Newton converges in a few on a strongly convex f0; on a flat minimum
        # ((y - r)**4: linear, by 2/3 a step) they leave a Hessian ~1e-13 of its scale.
        first: np.ndarray | None = None
        value: np.ndarray | None = None
        for _ in range(40):
            grads, newton, usable = numbers.newton(ys, ts)
            norms = np.linalg.norm(grads, axis=1)
            if first is None:
                first = norms
            descent = usable & np.all(np.isfinite(newton), axis=1)
            descent &= np.einsum("pi,pi->p", grads, newton) > 0
            steps = np.where(descent[:, None], newton, grads)
            size = np.linalg.norm(steps, axis=1)
            converged = size <= 1e-10 * (1.0 + np.linalg.norm(ys, axis=1))
            # Located: the step vanished, or the gradient fell by eight orders.
            converged |= norms <= 1e-8 * first
            if converged.all():
                break
            if value is None:
                value = numbers.value(ys, ts)
            # The full steps, then all halvings (2^-1 .. 2^-29) of the points they did not
            # improve in one call: 30 calls where a point cannot improve (out of the domain).
            full = numbers.value(ys - steps, ts)
            scale, reached = np.ones(points), full
            accepted = converged | (full < value)
            todo = np.flatnonzero(~accepted)
            if todo.size:
                halvings = 0.5 ** np.arange(1, 30)[:, None, None]
                trial = (ys[todo] - halvings * steps[todo]).reshape(-1, ys.shape[1])
                values = numbers.value(trial, np.tile(ts[todo], 29)).reshape(29, -1)
                better = values < value[todo]
                level, accepted[todo] = better.argmax(axis=0), better.any(axis=0)
                scale[todo] = np.where(accepted[todo], halvings[level, 0, 0], 1.0)
                reached[todo] = values[level, np.arange(todo.size)]
            if not (accepted & ~converged).any():
                break  # no point moves any more
            ys = np.where(accepted[:, None], ys - scale[:, None] * steps, ys)
            value = np.where(accepted, reached, value)  # f0 there was met on the way
    return ys, converged


def _check_convexity(
    model: Model,
    polynomial: sx.Expr | None,
    program: Program,
    gradient: Sequence[sx.Expr],
    entries: Sequence[tuple[tuple[int, int], sx.Expr]],
    y0: Sequence[float],
    t_final: float,
    source: str,
) -> tuple[Convexity, tuple[str, ...]]:
    """Check the strong convexity of f0 where it matters; return the evidence and warnings.

    ``program`` computes ``gradient`` and the Hessian's lower triangle ``entries``;
    ``polynomial`` is the Hessian's symbolic form when f0 is polynomial in ``y`` (then a
    Hessian free of ``y``, t and the signals is checked exactly at the parameters'
    defaults). Otherwise the Hessian is sampled near the initial outputs and along the
    minimiser ``y*(t)`` over the horizon (found by Newton's method), where the
    theorem's bound lives: a Hessian that degenerates on ``y*`` (``(y - r)**4``) is
    refused, and one that fades away from ``y*`` (``log cosh``) gives a warning.
    """
    defaults = {q: float(v) for q, v in zip(model.params, model.defaults, strict=True)}
    m = len(model.y)
    warnings: list[str] = []
    if polynomial is not None and polynomial.free_symbols <= defaults.keys():
        fixed = Evaluator(defaults)
        matrix = np.array([[fixed(polynomial[i, j]) for j in range(m)] for i in range(m)])
        if not np.all(np.isfinite(matrix)):
            raise AssumptionError(
                source,
                "objective.f0",
                "the Hessian of f0 is not finite at the parameters' defaults (does a "
                "parameter divide by zero?)",
            )
        m_f = float(np.linalg.eigvalsh(np.real(matrix)).min())
        result = Convexity("constant Hessian", m_f, 1)
    else:
        numbers = _ObjectiveNumbers(model, program, gradient, entries, defaults)
        rng = np.random.default_rng(7)
        points = 24
        ys = np.asarray(y0) + rng.uniform(-0.1, 0.1, size=(points, m))
        ts = rng.uniform(0.0, t_final, size=points)
        if model.constraints:
            # The barrier objective lives on {g_i < s(t)}: outside it the log is undefined,
            # and the barrier term's curvature, still finite there, is negative. A sample
            # outside says nothing about the law, which never goes there.
            with np.errstate(all="ignore"):
                inside = np.isfinite(numbers.value(ys, ts))
            ys, ts = ys[inside], ts[inside]
        low, high = numbers.extremes(ys, ts) if len(ts) else (np.empty(0), np.empty(0))
        path_ts = np.linspace(0.0, t_final, _PATH_POINTS)
        path, converged = _continued_path(numbers, np.asarray(y0, dtype=float), path_ts)
        path_low, path_high = numbers.extremes(path, path_ts)
        path_low = np.where(converged, path_low, np.nan)
        finite = np.isfinite(low).sum() + np.isfinite(path_low).sum()
        if not finite:
            raise AssumptionError(
                source,
                "objective.f0",
                f"the Hessian of {_named(model)} is not finite at any of {points} points near "
                "the initial outputs (overflow or outside its domain), so strong convexity "
                "cannot be checked",
            )
        # Degenerate against the Hessian's scale. Without constraints, the largest
        # eigenvalue met anywhere: a minimum flat in every direction, (y - r)**4, has a
        # Hessian near 0 at y*(t) against 12 (y - r)**2 elsewhere. With them, against the
        # Hessian at the point itself: the barrier's curvature near the start, steep
        # without bound at the domain's edge, must not make a minimum with curvature 2
        # look flat (the barrier, positive where it acts, cannot hide a flat f0 there).
        if model.constraints:
            scales = np.maximum(path_high, 1e-300)
        else:
            scales = np.full(
                len(path_ts), float(np.nanmax(np.concatenate([high, path_high, [0.0]])))
            )
        ratio = np.where(converged, path_low / scales, np.nan)
        if converged.any() and np.nanmin(ratio) <= DEGENERATE_HESSIAN:
            worst = int(np.nanargmin(ratio))
            where = ", ".join(
                f"{y.name} = {value:.6g}" for y, value in zip(model.y, path[worst], strict=True)
            )
            field, cause = _culprit(model, path[worst], float(path_ts[worst]))
            if field == "objective.f0":
                flat = "a flat minimum such as (y - r)**4: the law divides by it"
                cause = flat if model.objective is None else f"{cause}; {flat}"
            raise AssumptionError(
                source,
                field,
                f"{_named(model)} is not strongly convex at its minimiser: at t = "
                f"{path_ts[worst]:.6g}, y*(t) = ({where}), the Hessian's smallest eigenvalue "
                f"is {path_low[worst]:.3g}, below {DEGENERATE_HESSIAN:g} of its scale "
                f"{scales[worst]:.3g} ({cause})",
            )
        warnings += _fading_convexity(numbers, path, path_ts, path_low, converged)
        all_low = np.concatenate([low, path_low])
        m_f = float(np.nanmin(all_low))
        result = Convexity("sampled near y(0) and along y*(t)", m_f, int(finite))
        if not m_f > 0:
            index = int(np.nanargmin(all_low))
            at_y = np.concatenate([ys, path])[index]
            at_t = float(np.concatenate([ts, path_ts])[index])
            field, cause = _culprit(model, at_y, at_t)
            where = ", ".join(f"{y.name} = {v:.6g}" for y, v in zip(model.y, at_y, strict=True))
            raise AssumptionError(
                source,
                field,
                f"{_named(model)} is not strongly convex in the outputs: at t = {at_t:.6g}, "
                f"y = ({where}), the Hessian has eigenvalue {m_f:.6g} <= 0 ({cause})",
            )
    if not result.m_f > 0:
        raise AssumptionError(
            source,
            "objective.f0",
            "f0 is not strongly convex in the outputs: the Hessian has eigenvalue "
            f"{result.m_f:.6g} <= 0 (the method needs grad_yy f0 positive definite)",
        )
    return result, tuple(warnings)


def _named(model: Model) -> str:
    """What the law's objective is called in a message: f0, or the barrier objective."""
    return "the barrier objective B = f0 - mu sum log(s - g_i)" if model.constraints else "f0"


def _culprit(model: Model, y: np.ndarray, t: float) -> tuple[str, str]:
    """The field to blame for a Hessian that is not positive at ``(y, t)``, and why.

    Without constraints, f0. With them, f0 alone is evaluated there: when its own Hessian
    is positive definite, the barrier's term is what fails, and the constraints are named.
    """
    if model.objective is None:
        return "objective.f0", "the method needs grad_yy f0 positive definite"
    hessian = _hessian(model.objective, model.y)
    evaluate = _evaluator_at(model, np.asarray(y, dtype=float)[None, :], np.array([t]))
    m = len(model.y)
    with np.errstate(all="ignore"):
        matrix = np.array(
            [[float(np.ravel(evaluate(hessian[i][j]))[0]) for j in range(m)] for i in range(m)]
        )
    if not np.all(np.isfinite(matrix)):
        return "objective.f0", "f0's own Hessian is not finite there"
    eigenvalues = np.linalg.eigvalsh(0.5 * (matrix + matrix.T))
    if eigenvalues[0] > DEGENERATE_HESSIAN * max(abs(eigenvalues[-1]), 1e-300):
        names = ", ".join(c.name for c in model.constraints)
        return (
            "constraints",
            f"f0 alone is strongly convex there, eigenvalue {eigenvalues[0]:.3g}: the "
            f"barrier term of the constraints {names} is what fails",
        )
    return "objective.f0", f"f0's own Hessian has eigenvalue {eigenvalues[0]:.3g} there"


def _hessian(f: sx.Expr, variables: Sequence[sx.Expr]) -> list[list[sx.Expr]]:
    """The Hessian of ``f``, rows of entries: ``f.diff(v_i).diff(v_j)``, as ``sympy.hessian``.

    The upper triangle is differentiated, in SymPy's order, and mirrored.
    """
    n = len(variables)
    out: list[list[sx.Expr]] = [[sx.ZERO] * n for _ in range(n)]
    for i in range(n):
        first = f.diff(variables[i])
        for j in range(i, n):
            out[i][j] = out[j][i] = first.diff(variables[j])
    return out


def _continued_path(
    numbers: _ObjectiveNumbers, y0: np.ndarray, ts: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """``y*(t)`` at every time from ``y0``; where that fails, from the nearest one found.

    A start outside the barrier's domain at a later time (the slack shrinks) leaves
    Newton nowhere to go; the minimiser found at a neighbouring time is inside.
    """
    path, converged = _minimiser_path(numbers, np.tile(y0, (len(ts), 1)), ts)
    for _ in range(len(ts)):
        if converged.all() or not converged.any():
            break
        done = np.flatnonzero(converged)
        todo = np.flatnonzero(~converged)
        nearest = done[np.abs(ts[done][None, :] - ts[todo][:, None]).argmin(axis=1)]
        again, ok = _minimiser_path(numbers, path[nearest], ts[todo])
        if not ok.any():
            break
        path[todo[ok]] = again[ok]
        converged[todo[ok]] = True
    return path, converged


def _probe_directions(m: int) -> np.ndarray:
    """The directions in which :func:`_fading_convexity` steps away from ``y*``.

    Each axis both ways while there are at most :data:`_PROBE_AXES` outputs; beyond,
    :data:`_PROBE_AXES` fixed directions of +-1 entries (all ones, alternating signs, and
    seeded random signs, each with its opposite), so that every output moves by the
    probe's distance in every direction: the cost stays that of :data:`_PROBE_AXES`
    Hessians per point however many outputs there are (per axis it grew as m^4).
    """
    if m <= _PROBE_AXES:
        return np.concatenate([np.eye(m), -np.eye(m)])
    rng = np.random.default_rng(14)
    half = [np.ones(m), np.resize([1.0, -1.0], m)]
    half += [rng.choice([-1.0, 1.0], size=m) for _ in range(_PROBE_AXES // 2 - 2)]
    return np.concatenate([np.array(half), -np.array(half)])


class _SparseHessians:
    """Definiteness of one sparse symmetric pattern's matrices, by sparse factorization.

    ``A + shift I`` is positive definite exactly when its Cholesky factor exists. In
    the reverse Cuthill-McKee order a team's Hessian (a few entries per row, neighbours
    coupled) is a narrow band, whose Cholesky factorization (LAPACK's ``pbtrf``) takes
    microseconds. A pattern whose band stays wide is factored by SuperLU instead, as an
    LDL^T without pivoting in a fill-reducing symmetric order: positive definite when
    every pivot is positive (Sylvester's law of inertia). Either costs well under a
    millisecond where a dense eigenvalue decomposition costs tens.
    """

    def __init__(self, entries: Sequence[tuple[int, int]], m: int) -> None:
        lower = np.array(entries, dtype=np.int64).reshape(-1, 2)
        self.off = lower[:, 0] != lower[:, 1]
        diagonal = np.arange(m)
        self.rows = np.concatenate([lower[:, 0], lower[self.off, 1], diagonal])
        self.cols = np.concatenate([lower[:, 1], lower[self.off, 0], diagonal])
        self.m = m
        # Each entry's place in LAPACK's upper band storage of the permuted matrix:
        # ab[band + i - j, j] = A[i, j] for i <= j.
        pattern = {(i, j) for i, j in entries} | {(j, i) for i, j in entries}
        # order[k]: the output at place k of the permuted matrix; position: its inverse.
        self.order = np.array(reverse_cuthill_mckee(pattern, m), dtype=np.int64)
        position = self.position = np.empty(m, dtype=np.int64)
        position[self.order] = np.arange(m)
        first, second = position[lower[:, 0]], position[lower[:, 1]]
        low, high = np.minimum(first, second), np.maximum(first, second)
        self.band = int((high - low).max(initial=0))
        self.band_rows = self.band + low - high
        self.band_cols = high

    def _upper_band(self, values: np.ndarray) -> np.ndarray:
        """LAPACK's upper band storage of the permuted matrix of ``values`` (one point)."""
        band = np.zeros((self.band + 1, self.m))
        band[self.band_rows, self.band_cols] = values
        return band

    def extremes(
        self, values: np.ndarray, dense: Callable[[np.ndarray], np.ndarray]
    ) -> tuple[np.ndarray, np.ndarray]:
        """Smallest and largest |eigenvalue| of each point's matrix (``values`` (E, P)).

        In a narrow band, LAPACK's banded symmetric eigenvalues (``sbevd``: a reduction
        to tridiagonal form in O(m band^2)) of the permuted matrix, a similarity that
        keeps them; otherwise the dense matrices (``dense`` builds them). NaN where an
        entry is not finite.
        """
        points = values.shape[1]
        finite = np.all(np.isfinite(values), axis=0)
        if self.band > _BAND_LIMIT:
            low, high = np.full(points, np.nan), np.full(points, np.nan)
            if finite.any():
                low[finite], high[finite] = _smallest_eigenvalues(dense(values[:, finite]))
            return low, high
        from scipy.linalg import eigvals_banded  # noqa: PLC0415 - only for large teams

        low, high = np.full(points, np.nan), np.full(points, np.nan)
        for point in np.nonzero(finite)[0]:
            band = self._upper_band(values[:, point])
            eig = eigvals_banded(band, lower=False, check_finite=False)
            low[point], high[point] = eig[0], max(abs(eig[0]), abs(eig[-1]))
        return low, high

    def solve(
        self, values: np.ndarray, grads: np.ndarray, dense: Callable[[np.ndarray], np.ndarray]
    ) -> tuple[np.ndarray, np.ndarray]:
        """``H^-1 g`` at each point, and where H is finite and nonsingular (else ``g``).

        In a narrow band, LAPACK's banded LU (``gbsv``) of the permuted matrix (a
        Newton step need not be on a definite matrix); otherwise dense LU.
        """
        steps = grads.copy()
        usable = np.all(np.isfinite(values), axis=0)
        if self.band > _BAND_LIMIT:
            for point in np.nonzero(usable)[0]:
                try:
                    steps[point] = np.linalg.solve(dense(values[:, point, None])[0], grads[point])
                except np.linalg.LinAlgError:
                    usable[point] = False
            return steps, usable
        from scipy.linalg import solve_banded  # noqa: PLC0415 - only for large teams

        b = self.band
        for point in np.nonzero(usable)[0]:
            upper = self._upper_band(values[:, point])
            general = np.zeros((2 * b + 1, self.m))
            general[: b + 1] = upper
            # Below the diagonal by symmetry: A[j + d, j] = A[j, j + d].
            for d in range(1, b + 1):
                general[b + d, : self.m - d] = upper[b - d, d:]
            try:
                permuted = solve_banded((b, b), general, grads[point, self.order])
            except np.linalg.LinAlgError:
                usable[point] = False
                continue
            steps[point] = permuted[self.position]
        return steps, usable

    def positive_definite(self, values: np.ndarray, shift: float) -> bool | None:
        """Whether the matrix of ``values`` (in the entries' order) + ``shift I`` is definite.

        None when SuperLU would not keep the order symmetric (the pivots then say
        nothing of the inertia).
        """
        if self.band <= _BAND_LIMIT:
            from scipy.linalg import cholesky_banded  # noqa: PLC0415 - only for large teams

            band = self._upper_band(values)
            band[self.band] += shift
            try:
                cholesky_banded(band, lower=False, check_finite=False)
            except np.linalg.LinAlgError:
                return False
            return True
        from scipy.sparse import csc_matrix  # noqa: PLC0415 - only for large teams
        from scipy.sparse.linalg import splu  # noqa: PLC0415

        data = np.concatenate([values, values[self.off], np.full(self.m, shift)])
        matrix = csc_matrix((data, (self.rows, self.cols)), shape=(self.m, self.m))
        try:
            factor = splu(
                matrix,
                permc_spec="MMD_AT_PLUS_A",
                diag_pivot_thresh=0.0,
                options={"SymmetricMode": True},
            )
        except RuntimeError:  # an exactly zero pivot: singular, so not definite
            return False
        if not np.array_equal(factor.perm_r, factor.perm_c):
            return None
        return bool(np.all(factor.U.diagonal() > 0.0))


def _fading_sparse(
    numbers: _ObjectiveNumbers,
    points: np.ndarray,
    times: np.ndarray,
    threshold: np.ndarray,
    candidates: np.ndarray,
) -> np.ndarray:
    """Which points have a Hessian whose smallest eigenvalue lies in (-threshold, threshold).

    Sparse factorizations per candidate point: ``H - threshold I`` not definite (one
    factorization where it is, at every point where f0 is strongly convex), then
    ``H + threshold I`` definite; a dense eigenvalue decomposition where SuperLU would
    not keep a symmetric order. Gershgorin's bounds settle most points first, beyond
    rounding (:class:`_Gershgorin`), as the factorizations would.
    """
    m = points.shape[1]
    sparse = _SparseHessians([ij for ij, _ in numbers.entries], m)
    fading = np.zeros(len(points), dtype=bool)
    chunk = max(1, _PROBE_BYTES // (8 * max(len(numbers.entries), 1)))
    for start in range(0, len(points), chunk):
        part = slice(start, start + chunk)
        values = numbers.hessian_entries(points[part], times[part])
        # Surely above: H - threshold I is definite. Surely below: a diagonal entry or a
        # 2 x 2 principal submatrix of H + threshold I is not, and neither is the whole.
        surely_above, surely_below, _ = numbers.gershgorin.screen(values, threshold[part])
        for offset in np.nonzero(candidates[part] & ~surely_above & ~surely_below)[0]:
            column, tau = values[:, offset], float(threshold[start + offset])
            if not np.all(np.isfinite(column)):
                continue
            below = sparse.positive_definite(column, -tau)
            if below:
                continue  # H - tau I > 0: strongly convex there, the common case
            above = sparse.positive_definite(column, tau)
            if above is None or below is None:
                low, _ = _smallest_eigenvalues(numbers._dense(column[:, None]))
                fading[start + offset] = bool(abs(low[0]) < tau)
            else:
                fading[start + offset] = above and not below
    return fading


def _fading_convexity(
    numbers: _ObjectiveNumbers,
    path: np.ndarray,
    ts: np.ndarray,
    path_low: np.ndarray,
    converged: np.ndarray,
) -> list[str]:
    """A warning when f0 is strongly convex near y*(t) only (its Hessian fades away)."""
    count, m = path.shape
    probes = [(d, direction) for d in _PROBE_DISTANCES for direction in _probe_directions(m)]
    # Every probe point in one array, evaluated in chunks of at most _PROBE_BYTES of
    # Hessians: the evaluator's cost is per expression, not per point.
    points = np.concatenate([path + d * direction for d, direction in probes])
    times = np.tile(ts, len(probes))
    reference = np.tile(path_low, len(probes))
    candidates = np.tile(converged, len(probes))
    # Fading, not turning negative: a barrier's periodic branches beyond its domain
    # (tan**2) are not where the outputs can go.
    if m > _SPARSE_PROBE:
        fading = _fading_sparse(numbers, points, times, 1e-6 * reference, candidates)
        if not fading.any():
            return []
        at = int(np.argmax(fading))
        low = np.full(len(points), np.nan)
        low[at] = numbers.extremes(points[None, at], times[None, at])[0][0]
    else:
        # The first fading point in the probes' order is the one named: the chunks are
        # taken in that order, and the search stops at the first chunk that has one.
        chunk = max(count, _PROBE_BYTES // (8 * m * m))
        for start in range(0, len(points), chunk):
            part = slice(start, start + chunk)
            values = numbers.hessian_entries(points[part], times[part])
            found, found_low = _fading_dense(
                numbers.gershgorin, numbers._dense, values, 1e-6 * reference[part], candidates[part]
            )
            if found.any():
                fading = np.zeros(len(points), dtype=bool)
                fading[part] = found
                low = np.full(len(points), np.nan)
                low[part] = found_low
                break
        else:
            return []
    at = int(np.argmax(fading))  # the first in the order distance, direction, time
    distance, when = probes[at // count][0], ts[at % count]
    return [
        "objective.f0: f0 is strongly convex only near its minimiser: at distance "
        f"{distance:g} "
        f"from y*(t) (t = {when:.6g}) the Hessian's smallest eigenvalue is "
        f"{low[at]:.3g}, against {reference[at]:.3g} at y*; the certificate's "
        "bound holds only while the outputs stay where it is bounded below"
    ]


def nonconvex(
    constraints: Sequence[Constraint],
    outputs: Sequence[sx.Expr],
    evaluate: Evaluator,
    points: int,
) -> list[tuple[str, float]]:
    """The constraints whose Hessian in ``y`` has a negative eigenvalue at a sample point.

    ``evaluate`` holds the sample points (arrays of ``points`` values for the outputs,
    ``t``, signals and references). Returns (name, smallest eigenvalue) of each.
    """
    found = []
    m = len(outputs)
    for constraint in constraints:
        matrices = np.zeros((points, m, m))
        for i, j, second in constraint_hessian_entries(sx.sympify(constraint.g), tuple(outputs)):
            value = np.broadcast_to(np.real(evaluate(second)), (points,))
            matrices[:, i, j] = matrices[:, j, i] = value
        finite = np.all(np.isfinite(matrices), axis=(1, 2))
        if not finite.any():
            continue
        eigenvalues = np.linalg.eigvalsh(matrices[finite])
        smallest = float(eigenvalues[:, 0].min())
        scale = max(1.0, float(np.abs(eigenvalues).max()))
        if smallest < -1e-9 * scale:
            found.append((constraint.name, smallest))
    return found


def _constraint_convexity(model: Model, y0: np.ndarray) -> tuple[str, ...]:
    """Refuse a constraint that is not convex in the outputs, unless the spec allows it.

    Each ``g_i``'s Hessian in ``y`` is sampled around the initial outputs over the
    horizon (signals and nominal references at their values there; references without
    one at 0).
    """
    if not model.constraints:
        return ()
    rng = np.random.default_rng(18)
    points = 64
    ys = y0[None, :] + rng.uniform(-2.0, 2.0, size=(points, len(y0)))
    settings = model.settings
    evaluate = _evaluator_at(model, ys, rng.uniform(0.0, settings.t_final, size=points))
    _feasible_over_the_horizon(model, y0)
    found = nonconvex(model.constraints, model.y, evaluate, points)
    if not found:
        return ()
    names = ", ".join(f"{name} (Hessian eigenvalue {value:.3g})" for name, value in found)
    if not settings.allow_nonconvex:
        raise AssumptionError(
            settings.source,
            f"constraints.{found[0][0]}",
            f"not convex in the outputs: {names}; the barrier method needs convex "
            "inequalities (set allow_nonconvex = true to accept a local certificate)",
        )
    return (f"constraints not convex in the outputs: {names}; the certificate is local only",)


def _evaluator_at(model: Model, ys: np.ndarray, ts: np.ndarray) -> Evaluator:
    """Numbers for expressions in the outputs and t at points (one row of ``ys`` each).

    Parameters at their defaults, signals and nominal references defined (references
    without one at 0).
    """
    values: dict[sx.Expr, Any] = {y: ys[:, i] for i, y in enumerate(model.y)}
    values[model.t] = ts
    values |= {q: float(v) for q, v in zip(model.params, model.defaults, strict=True)}
    nominal = dict(model.nominal)
    values |= {r: 0.0 for r in model.references if r not in nominal}
    evaluate = Evaluator(values)
    for symbol, expr in nominal.items():
        evaluate.define(symbol, expr)
    for symbol, expr in model.signals:
        evaluate.define(symbol, expr)
    return evaluate


def _feasible_over_the_horizon(model: Model, y0: np.ndarray) -> None:
    """Refuse constraints that no output satisfies at some time of the horizon.

    The least violation is found at :data:`_FEASIBILITY_POINTS` times (each search
    starting where the last one ended), the first infeasible stretch's edges refined by
    bisection, and the constraint named when it alone holds nowhere there.
    """
    violation = Violation(model)
    t_final = model.settings.t_final
    times = np.linspace(0.0, t_final, _FEASIBILITY_POINTS)
    worst = np.empty(len(times))
    point = np.asarray(y0, dtype=float)
    for k, t in enumerate(times):
        worst[k], point = violation.least(float(t), point)
    bad = worst > _INFEASIBLE
    if not bad.any():
        return
    first = int(np.argmax(bad))
    last = first
    while last + 1 < len(times) and bad[last + 1]:
        last += 1
    start = (
        float(times[first]) if first == 0 else _edge(violation, y0, times[first - 1], times[first])
    )
    end = (
        float(times[last])
        if last == len(times) - 1
        else _edge(violation, y0, times[last + 1], times[last])
    )
    peak = first + int(np.argmax(worst[first : last + 1]))
    alone = [
        name
        for i, name in enumerate(violation.names)
        if violation.least(float(times[peak]), np.asarray(y0, dtype=float), only=i)[0] > _INFEASIBLE
    ]
    if last == len(times) - 1:
        span = f"from t = {start:.4g} to the horizon's end t = {t_final:g}"
    else:
        span = f"for t in [{start:.4g}, {end:.4g}] of the horizon [0, {t_final:g}]"
    least = f"the least violation found is {worst[peak]:.3g}, at t = {times[peak]:.4g}"
    if len(alone) == 1:
        raise AssumptionError(
            model.source,
            f"constraints.{alone[0]}",
            f"infeasible {span}: no output satisfies it there ({least})",
        )
    raise AssumptionError(
        model.source,
        "constraints",
        f"infeasible {span}: every output violates a constraint there ({least})",
    )


def _edge(violation: Violation, y0: np.ndarray, feasible: float, infeasible: float) -> float:
    """Where feasibility ends between two times, by bisection (to 1e-4 of the interval)."""
    low, high = float(feasible), float(infeasible)
    point = np.asarray(y0, dtype=float)
    for _ in range(14):
        middle = 0.5 * (low + high)
        value, found = violation.least(middle, point)
        if value > _INFEASIBLE:
            high = middle
        else:
            low, point = middle, found
    return high
