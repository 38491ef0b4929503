"""f0's gradient and Hessian in numbers, at many points at once, and the linear algebra on them.

:class:`_ObjectiveNumbers` evaluates f0, its gradient and the Hessian's stored entries
over (y, t) points; the Hessians' smallest eigenvalues come dense, or, for a team's
outputs (a sparse pattern), banded (:class:`_SparseHessians`: banded eigenvalues, LU and
Cholesky in the reverse Cuthill-McKee order, SuperLU for a wide band). Gershgorin's
bounds and 2 x 2 principal submatrices (:class:`_Gershgorin`) and Cholesky screens
settle the fading probe's verdicts beyond rounding (:func:`_fading_dense`,
:func:`_fading_sparse`), as LAPACK's eigenvalues would. Called by
:mod:`tvopt_codegen.derivation.convexity`: Newton along ``y*(t)``, the sampled check of
strong convexity and the fading probe.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np

from tvopt_codegen import symbolic as sx
from tvopt_codegen.derivation.model import Model
from tvopt_codegen.maths.jet import Program
from tvopt_codegen.maths.numeric import Tape
from tvopt_codegen.maths.sparse import reverse_cuthill_mckee

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
        rows, columns = self._places
        matrices = np.zeros((values.shape[1], m, m))
        # Two scatters of every entry at once (the lower entries' places are distinct),
        # where a loop over the entries cost a NumPy call each, per batch of points.
        matrices[:, rows, columns] = values.T
        matrices[:, columns, rows] = values.T
        return matrices

    @functools.cached_property
    def _places(self) -> tuple[np.ndarray, np.ndarray]:
        """The stored entries' rows and columns."""
        places = np.array([ij for ij, _ in self.entries], dtype=np.int64).reshape(-1, 2)
        return places[:, 0], places[:, 1]

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
        # The Hessian's tape alone: the same operations as the derivatives', so the
        # same bits, without the gradient's.
        values = self.hessian_entries(ys, ts)
        if self.sparse is None:
            return _smallest_eigenvalues(self._dense(values))
        return self.sparse.extremes(values, self._dense)

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
        below ``-threshold`` (asked only where it is not surely above: the two exclude
        each other), and the margin used (each (P,)). "Surely" beyond rounding:
        LAPACK's smallest eigenvalue and a Cholesky factorization of
        ``H - (threshold + margin) I`` agree with the verdict (NaN or infinite entries,
        or a norm that overflows, settle nothing).
        """
        points = values.shape[1]
        diagonal = np.zeros((self.m, points))
        diagonal[self.diagonal_rows] = values[self.diagonal]
        magnitude = np.abs(values[self.off])
        # Each row's sum of |h_ij| over its off-diagonal entries, in the entries' order
        # (first as the row, then as the column), as two np.add.at would add them: one
        # bincount over (row, point) cells visits the terms in that order, at a tenth of
        # add.at's cost.
        cells = (self.ends.T.reshape(-1)[:, None] * points + np.arange(points)).reshape(-1)
        terms = np.concatenate([magnitude, magnitude]).reshape(-1)
        radius = np.bincount(cells, weights=terms, minlength=self.m * points)
        radius = radius.reshape(self.m, points)
        with np.errstate(all="ignore"):
            # The largest row sum of |H| bounds its spectral norm (H symmetric).
            norm = (radius + np.abs(diagonal)).max(axis=0, initial=0.0)
            margin = _SCREEN_MARGIN * (self.m + 1) ** 2 * np.finfo(float).eps * (norm + threshold)
            above = (diagonal - radius).min(axis=0, initial=np.inf) > threshold + margin
            settled = np.isfinite(margin)
            above &= settled
            # The 2 x 2 submatrices' eigenvalues (a hypot per stored entry and point) only
            # at the points still open: where f0 is strongly convex, the common case,
            # Gershgorin's discs settle nearly all of them. Column by column the same
            # operations, so the same bits.
            open_ = np.flatnonzero(~above & settled)
            below = np.zeros(points, dtype=bool)
            if open_.size:
                near = diagonal[:, open_]
                first, second = near[self.ends[:, 0]], near[self.ends[:, 1]]
                off = values[self.off][:, open_]
                pairs = 0.5 * (first + second) - np.hypot(0.5 * (first - second), off)
                lowest = np.minimum(
                    near.min(axis=0, initial=np.inf), pairs.min(axis=0, initial=np.inf)
                )
                below[open_] = lowest < -threshold[open_] - margin[open_]
        return above, below, margin


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
