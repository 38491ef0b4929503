"""Where a simulation's reference jets come from: the nominal closed form, or samples.

A spec with ``[references]`` generates a controller that takes the references' jets with
every call. ``simulate`` feeds it either the exact jets of the nominal closed forms
(:func:`nominal_source`) or jets estimated online from samples, as a robot would
(:func:`sampled_source`): the generated :class:`ReferenceEstimator` runs over the samples
in time order, and between two samples the jet is the last estimate's Taylor polynomial,
so the jets at time t use the samples up to t only.
"""

from __future__ import annotations

import bisect
import csv
import math
import os
import re
import stat
import types
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from tvopt_codegen import symbolic as sx
from tvopt_codegen.derivation import Derivation, calculus
from tvopt_codegen.errors import SpecError, clip

#: Most samples a reference file may hold.
MAX_SAMPLES = 2_000_000
#: Largest reference file read: MAX_SAMPLES rows of a few numbers each, with room.
MAX_FILE_BYTES = 256 * 2**20
#: Longest line of a reference file (a row of a few numbers, with room for comments).
MAX_LINE_CHARACTERS = 1 << 20
#: Rows parsed into one block of numbers at a time.
_BLOCK_ROWS = 65_536


@dataclass(frozen=True)
class ReferenceSource:
    """The reference jets of a simulation.

    Attributes
    ----------
    jets : callable
        ``jets(t)``: what the controller gets at ``t``, shape (n_refs, q + 1).
    exact : callable or None
        ``exact(t)``: the true jets (the nominal closed forms), when they are known.
    estimated : bool
        Whether ``jets`` are estimated from samples.
    times, samples : numpy.ndarray or None
        The sample times (T,) and the samples as the controller saw them, noise included
        (n_refs, T), for figures.
    noise : float
        Standard deviation of the noise added to the samples.
    flat : callable or None
        ``flat(t)``: the same numbers as ``jets(t)``, row after row in a new list of
        floats (what a generated module's one-point kernel takes), when the source has
        them so; None: ``jets(t).ravel().tolist()``.
    """

    jets: Callable[[float], np.ndarray]
    exact: Callable[[float], np.ndarray] | None
    estimated: bool = False
    times: np.ndarray | None = None
    samples: np.ndarray | None = None
    noise: float = 0.0
    flat: Callable[[float], list[float]] | None = None

    def flat_jets(self, t: float) -> list[float]:
        """The jets at ``t`` row after row, as floats (see ``flat``)."""
        if self.flat is not None:
            return self.flat(t)
        values: list[float] = self.jets(t).ravel().tolist()
        return values


def _taylor(xi: list[list[float]], h: float) -> list[list[float]]:
    """Jets (n_refs rows of q + 1) ``h`` seconds on along their Taylor polynomials.

    On Python floats, not arrays: a run on the sample grid asks for four jets of a few
    numbers per RK4 step, and NumPy's cost per call was most of their time. The same
    IEEE operations in the same order as a column at a time on arrays, so the same bits.
    """
    order = len(xi[0]) if xi else 0
    terms = _terms(order, h)
    unrolled = _UNROLLED.get(order)
    if unrolled is not None:
        return unrolled(xi, terms)
    return _shifted(xi, terms)


def _terms(order: int, h: float) -> list[float]:
    """``h^i / i!`` for ``i < order``, each from the one before (the shifts' weights)."""
    terms = [1.0] * order
    for index in range(1, order):
        terms[index] = terms[index - 1] * (h / index)
    return terms


def _shifted(xi: list[list[float]], terms: list[float]) -> list[list[float]]:
    """The general shift, any jet length: entry j of a row is ``sum xi[j + i] terms[i]``.

    ``terms[i]`` is ``h^i / i!``; the written-out forms of :data:`_UNROLLED` are held to
    this loop's bits (tests/test_simulate.py).
    """
    order = len(terms)
    out = []
    for row in xi:
        shifted = []
        # Entry j: 0.0 + xi[j] h^0/0! + xi[j + 1] h^1/1! + ..., summed in that order.
        for j in range(order):
            total = 0.0
            for index in range(order - j):
                total += row[j + index] * terms[index]
            shifted.append(total)
        out.append(shifted)
    return out


# _taylor's loops written out for the usual jet lengths (q + 1 = 2 to 5): a run on the
# sample grid shifts a jet at every other call of the field, and the loops' bookkeeping
# cost three times their arithmetic. Each entry is the loop's sum in the loop's order,
# ``0.0 + a + b t1 + ...`` (``a * 1.0`` is ``a`` for every float), so the same bits.


def _shift2(xi: list[list[float]], terms: list[float]) -> list[list[float]]:
    t1 = terms[1]
    return [[0.0 + a + b * t1, 0.0 + b] for a, b in xi]


def _shift3(xi: list[list[float]], terms: list[float]) -> list[list[float]]:
    _, t1, t2 = terms
    return [[0.0 + a + b * t1 + c * t2, 0.0 + b + c * t1, 0.0 + c] for a, b, c in xi]


def _shift4(xi: list[list[float]], terms: list[float]) -> list[list[float]]:
    _, t1, t2, t3 = terms
    return [
        [
            0.0 + a + b * t1 + c * t2 + d * t3,
            0.0 + b + c * t1 + d * t2,
            0.0 + c + d * t1,
            0.0 + d,
        ]
        for a, b, c, d in xi
    ]


def _shift5(xi: list[list[float]], terms: list[float]) -> list[list[float]]:
    _, t1, t2, t3, t4 = terms
    return [
        [
            0.0 + a + b * t1 + c * t2 + d * t3 + e * t4,
            0.0 + b + c * t1 + d * t2 + e * t3,
            0.0 + c + d * t1 + e * t2,
            0.0 + d + e * t1,
            0.0 + e,
        ]
        for a, b, c, d, e in xi
    ]


_UNROLLED: dict[int, Callable[[list[list[float]], list[float]], list[list[float]]]] = {
    2: _shift2,
    3: _shift3,
    4: _shift4,
    5: _shift5,
}


def exact_jets(derivation: Derivation, params: dict[str, float]) -> Callable[[float], np.ndarray]:
    """The jets of the nominal closed forms, or a SpecError naming those without one."""
    d, model = derivation, derivation.model
    nominal = dict(model.nominal)
    missing = [r.name for r in model.references if r not in nominal]
    if missing:
        raise SpecError(
            d.spec.source,
            "references.nominal",
            f"{', '.join(missing)} have no nominal closed form: give --reference-file",
        )
    values = {q: params.get(q.name, v) for q, v in zip(model.params, model.defaults, strict=True)}
    fixed = {q: sx.real(v) for q, v in values.items()}
    rows = [
        [term.xreplace(fixed) for term in row]
        for row in calculus.nominal_jets(model, d.jet.reference_order)
    ]
    function = sx.lambdify(model.t, rows, "math")

    def jets(t: float) -> np.ndarray:
        return np.array(function(float(t)), dtype=float)

    return jets


def nominal_source(derivation: Derivation, params: dict[str, float]) -> ReferenceSource:
    """Exact jets from the nominal closed forms: the controller is the closed-form one."""
    jets = exact_jets(derivation, params)
    return ReferenceSource(jets=jets, exact=jets)


#: A gap: a sample interval this many times the file's median one.
GAP_FACTOR = 10.0

#: The sampling the linear differentiator needs: at least one sample per time constant
#: ``1 / bandwidth`` of its poles (the median interval times the bandwidth at most this).
RATE_LIMIT = 1.0

#: The separators a reference file may use, tried on its header: comma, semicolon (a
#: spreadsheet in a locale whose decimal mark is a comma), tab.
_DELIMITERS = (",", ";", "\t")


def read_reference_file(
    path: str | Path,
    derivation: Derivation,
    horizon: float,
    *,
    allow_gaps: bool = False,
    warn: Callable[[str], None] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Samples ``t, <reference>...`` from a CSV file, checked.

    The file is UTF-8, with or without a byte-order mark (a spreadsheet's "CSV UTF-8");
    lines whose first character is ``#`` and blank lines are comments; the header's
    separator, a comma, a semicolon or a tab, is the file's.

    Parameters
    ----------
    path : str or pathlib.Path
        The file.
    derivation : Derivation
        The spec's derivation: its references name the columns.
    horizon : float
        The run's end: the samples must cover ``[0, horizon]``.
    allow_gaps : bool, optional
        Accept samples the estimator cannot follow: a gap of more than
        :data:`GAP_FACTOR` median intervals, or (linear estimator) a median interval
        above ``RATE_LIMIT / bandwidth``.
    warn : callable, optional
        Called with a sentence for what is accepted but likely a mistake: a column that
        is no reference of the spec.

    Returns
    -------
    times : numpy.ndarray, shape (T,)
    values : numpy.ndarray, shape (n_refs, T)
        In ``REFERENCE_NAMES`` order.

    Raises
    ------
    SpecError
        Naming the file and the problem: unreadable, a missing column, a value that is not
        a finite number, times that do not increase, samples that do not cover
        ``[0, horizon]``, a gap or a sampling too slow for the estimator (unless
        ``allow_gaps``).
    """
    source = str(path)
    names = [r.name for r in derivation.model.references]
    expected = "a header t, " + ", ".join(names)
    try:
        # A regular file, read a line at a time within bounds: a FIFO would block, and
        # /dev/zero or a huge file would fill the memory before any line is checked.
        info = os.stat(path)
        if not stat.S_ISREG(info.st_mode):
            raise SpecError(source, "(file)", "not a regular file")
        if info.st_size > MAX_FILE_BYTES:
            raise SpecError(source, "(file)", f"larger than {MAX_FILE_BYTES // 2**20} MiB")
        with open(path, encoding="utf-8-sig", newline="") as handle:
            return _parse_reference_lines(
                source,
                derivation,
                horizon,
                _content_lines(source, handle),
                expected,
                allow_gaps=allow_gaps,
                warn=warn,
            )
    except (OSError, UnicodeDecodeError) as exc:
        raise SpecError(source, "(file)", f"cannot read the reference file: {exc}") from None


def _content_lines(source: str, handle: Any) -> Iterator[tuple[int, str]]:
    """The file's numbered lines but comments and blank ones, each within a bound."""
    number = 0
    while True:
        line = handle.readline(MAX_LINE_CHARACTERS + 1)
        if not line:
            return
        number += 1
        if len(line) > MAX_LINE_CHARACTERS:
            raise SpecError(
                source, f"line {number}", f"longer than {MAX_LINE_CHARACTERS} characters"
            )
        text = line.rstrip("\r\n")
        if text.strip() and not text.lstrip().startswith("#"):
            yield number, text


def _parse_reference_lines(
    source: str,
    derivation: Derivation,
    horizon: float,
    lines: Iterator[tuple[int, str]],
    expected: str,
    *,
    allow_gaps: bool,
    warn: Callable[[str], None] | None,
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`read_reference_file` on the file's content lines, one at a time."""
    names = [r.name for r in derivation.model.references]
    first = next(lines, None)
    if first is None:
        raise SpecError(source, "(header)", f"empty file: expected {expected}")
    delimiter = max(_DELIMITERS, key=first[1].count)

    def cells(number: int, text: str) -> list[str]:
        try:
            return next(csv.reader([text], delimiter=delimiter), [])
        except csv.Error as exc:  # a field beyond the csv module's size limit, say
            raise SpecError(source, f"line {number}", f"not a CSV row: {exc}") from None

    header = [cell.strip() for cell in cells(*first)]
    twice = sorted({cell for cell in header if header.count(cell) > 1})
    if twice:
        raise SpecError(source, "(header)", f"column {clip(twice[0])!r} appears more than once")
    for name in ("t", *names):
        if name not in header:
            found = ", ".join(clip(cell) for cell in header[:8]) + (
                ", ..." if len(header) > 8 else ""
            )
            raise SpecError(
                source,
                "(header)",
                f"missing column {name!r}: expected {expected}, separated by commas, "
                f"semicolons or tabs; found the columns {found}",
            )
    extra = [cell for cell in header if cell not in ("t", *names)]
    if extra and warn is not None:
        warn(
            f"{source}: column{'s' if len(extra) > 1 else ''} "
            f"{', '.join(repr(clip(c)) for c in extra)} ignored: not a reference of the spec "
            f"({', '.join(names)})"
        )
    columns = [header.index(name) for name in ("t", *names)]
    # Blocks of rows as they come: the memory is the samples' numbers, not the file's text.
    blocks: list[np.ndarray] = []
    block = np.empty((_BLOCK_ROWS, len(columns)))
    filled = count = 0
    previous = -math.inf
    for line, text in lines:
        if count == MAX_SAMPLES:
            raise SpecError(source, "(file)", f"more than {MAX_SAMPLES} samples")
        row = cells(line, text)
        for k, column in enumerate(columns):
            try:
                value = float(row[column])
            except (IndexError, ValueError):
                cell = row[column].strip() if column < len(row) else ""
                hint = (
                    " (a decimal comma? write a point)"
                    if re.fullmatch(r"[-+]?\d+,\d+", cell)
                    else ""
                )
                raise SpecError(
                    source,
                    f"line {line}",
                    f"{header[column]}: expected a number, got {clip(cell)!r}{hint}",
                ) from None
            if not math.isfinite(value):
                raise SpecError(
                    source, f"line {line}", f"{header[column]} = {value!r} is not finite"
                )
            block[filled, k] = value
        if not block[filled, 0] > previous:
            raise SpecError(source, f"line {line}", "t must increase from one sample to the next")
        previous = block[filled, 0]
        filled += 1
        count += 1
        if filled == _BLOCK_ROWS:
            blocks.append(block)
            block = np.empty((_BLOCK_ROWS, len(columns)))
            filled = 0
    blocks.append(block[:filled])
    data = np.concatenate(blocks)
    times = data[:, 0]
    if len(times) < 2:
        raise SpecError(source, "(file)", "expected at least two samples")
    steps = np.diff(times)
    if times[0] > 0.0 or times[-1] < horizon:
        raise SpecError(
            source,
            "t",
            f"the samples cover [{times[0]:g}, {times[-1]:g}]; the run needs [0, {horizon:g}]",
        )
    if not allow_gaps:
        _check_sampling(source, derivation, times, steps)
    return times, data[:, 1:].T


def _check_sampling(
    source: str, derivation: Derivation, times: np.ndarray, steps: np.ndarray
) -> None:
    """Refuse samples the estimator cannot follow: a gap, or too slow a rate."""
    median = float(np.median(steps))
    widest = int(np.argmax(steps))
    if steps[widest] > GAP_FACTOR * median:
        raise SpecError(
            source,
            "t",
            f"the samples leave a gap of {steps[widest]:g} s (t = {times[widest]:g} to "
            f"{times[widest + 1]:g}), {steps[widest] / median:.3g} times their median interval "
            f"{median:g} s: the estimator would extrapolate across it "
            "(--allow-gaps runs anyway)",
        )
    estimator = derivation.spec.estimator
    if estimator is not None and estimator.kind == "linear":
        if median * estimator.bandwidth > RATE_LIMIT:
            raise SpecError(
                source,
                "t",
                f"samples every {median:g} s (median) are too slow for the estimator's "
                f"bandwidth {estimator.bandwidth:g} rad/s: it needs one at least every "
                f"{RATE_LIMIT / estimator.bandwidth:g} s (--allow-gaps runs anyway)",
            )


def sampled_source(
    derivation: Derivation,
    controller: types.ModuleType,
    params: dict[str, float],
    times: np.ndarray,
    values: np.ndarray,
    noise: float = 0.0,
    seed: int = 0,
) -> ReferenceSource:
    """Jets estimated online from samples by the controller's own estimator.

    ``noise`` adds Gaussian noise of that standard deviation to every sample (seeded).
    The estimate at a sample uses the samples up to it; between samples the jets follow
    its Taylor polynomial; before the first sample, the first estimate's.
    """
    samples = values + noise * np.random.default_rng(seed).standard_normal(values.shape)
    estimator = controller.ReferenceEstimator(samples[:, 0], float(times[0]))
    estimates = [estimator.jets(float(times[0]))]
    for index in range(1, len(times)):
        estimates.append(estimator.update(float(times[index]), samples[:, index]))
    # Python lists: each call reads one estimate and returns a few numbers (see _taylor).
    grid: list[float] = np.asarray(times, dtype=float).tolist()
    stack: list[list[list[float]]] = np.array(estimates, dtype=float).tolist()
    # RK4 asks twice at each step's midpoint (and a step's end is often the next one's
    # start): the last answer, again. Kept as rows and flat, the two forms asked for.
    last: list[Any] = [None, None, None]

    def at(t: float) -> None:
        if t != last[0]:
            index = max(bisect.bisect_right(grid, t) - 1, 0)
            rows = _taylor(stack[index], float(t) - grid[index])
            last[0], last[1], last[2] = t, rows, [value for row in rows for value in row]

    def jets(t: float) -> np.ndarray:
        at(t)
        return np.array(last[1], dtype=float)

    def flat(t: float) -> list[float]:
        at(t)
        return list(last[2])

    try:
        exact: Callable[[float], np.ndarray] | None = exact_jets(derivation, params)
    except SpecError:
        exact = None
    return ReferenceSource(
        jets=jets,
        exact=exact,
        estimated=True,
        times=times,
        samples=samples,
        noise=noise,
        flat=flat,
    )
