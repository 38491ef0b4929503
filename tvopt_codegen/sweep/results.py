"""What a sweep yields: statistics, the summary's text, the table and trajectories.

The Clopper-Pearson bound, quantiles and worst samples; the Parquet table and the Zarr
store's blocks.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    pass
from tvopt_codegen.sweep.options import SweepOptions
from tvopt_codegen.sweep.program import TAIL, SweepProgram, tail
from tvopt_codegen.sweep.sample import SampleResult
from tvopt_codegen.sweep.table import SUMMARY_COLUMNS, pyarrow, to_numpy


def clopper_pearson_upper(failures: int, runs: int, confidence: float = 0.95) -> float:
    """One-sided upper confidence bound on a failure probability (exact binomial).

    With no failure it is ``1 - (1 - confidence)^(1/runs)``: 0 in 299 runs gives 0.99%.
    The quantile of Beta(failures + 1, runs - failures), from ``scipy.special`` (what
    ``scipy.stats.beta.ppf`` calls, to the bit): importing ``scipy.stats`` took 1.2 s
    of a 6 s sweep command.
    """
    from scipy.special import betaincinv  # noqa: PLC0415

    if runs == 0:
        return 1.0
    if failures >= runs:
        return 1.0
    return float(betaincinv(failures + 1, runs - failures, confidence))


@dataclass(frozen=True)
class Summary:
    """The sweep's statistics (``summary.md`` and the terminal)."""

    runs: int
    requested: int
    outcomes: dict[str, int]
    failure_rate: float
    failure_upper: float
    final_error: dict[str, float]
    settling: dict[str, float]
    worst: list[tuple[int, float]]
    nominal: int
    nominal_certified: int
    interrupted: bool
    constrained: bool = False
    violating: int = 0
    ended_outside: int = 0
    final_equality: dict[str, float] = field(default_factory=dict)
    #: Time with an input clipped, quantiles over the ok samples (empty: never clipped).
    saturated: dict[str, float] = field(default_factory=dict)
    #: The first sample whose run raised, and what it raised ("" when none did).
    first_error: str = ""


def _quantiles(values: np.ndarray) -> dict[str, float]:
    """Median, p95, p99 and max of the finite values, and how many were not finite."""
    if not len(values):
        return {}
    finite = values[np.isfinite(values)]
    out = {"never": float(len(values) - len(finite))}
    if len(finite):
        for label, q in (("median", 50), ("p95", 95), ("p99", 99)):
            out[label] = float(np.percentile(finite, q))
        out["max"] = float(finite.max())
    return out


class Tally:
    """A table's statistics, fed a block of rows at a time.

    Counts, the nominal and constraint tallies and the worst samples are running totals;
    only the ok samples' final errors, settling times, clipped times and final equality
    residuals are kept (their exact quantiles need them): four numbers a sample, so that
    a table of 10^6 rows is summarised in 32 MB, whatever its other columns.

    Parameters
    ----------
    worst : int
        How many of the worst samples (by final ``|y - y*|``) to keep.
    """

    KEPT = ("final_error", "settling_1pct", "time_saturated", "final_equality")

    def __init__(self, worst: int = 5) -> None:
        self.count = worst
        self.outcomes: dict[str, int] = {}
        self.runs = self.nominal = self.certified = self.violating = self.outside = 0
        self.constrained = False
        self.kept: dict[str, list[np.ndarray]] = {name: [] for name in self.KEPT}
        self.worst: list[tuple[float, int]] = []
        self.first_error = ""

    def add(
        self,
        labels: Sequence[str],
        codes: np.ndarray,
        columns: Mapping[str, np.ndarray],
        first_error: str = "",
    ) -> None:
        """Count a block: its statuses (``labels[codes]``) and its numeric columns."""
        counts = np.bincount(codes, minlength=len(labels)) if len(codes) else ()
        for label, n in zip(labels, counts, strict=False):
            if n:
                self.outcomes[label] = self.outcomes.get(label, 0) + int(n)
        self.runs += len(codes)
        ok = codes == labels.index("ok") if "ok" in labels else np.zeros(len(codes), bool)
        for name in self.KEPT:
            if name in columns:
                self.kept[name].append(np.asarray(columns[name], dtype=float)[ok])
        nominal = np.asarray(columns["nominal"], dtype=bool) & ok
        self.nominal += int(nominal.sum())
        self.certified += int(
            (np.asarray(columns["certificate_holds"], dtype=bool) & nominal).sum()
        )
        if "violations" in columns:
            self.constrained = True
            self.violating += int((columns["violations"] > 0).sum())
            self.outside += int((columns["final_constraint"][ok] > 0).sum())
        finals, samples = columns["final_error"][ok], columns["sample"][ok]
        order = np.lexsort((samples, -finals))[: self.count]
        ranked = self.worst + [(-float(finals[i]), int(samples[i])) for i in order]
        self.worst = sorted(ranked, key=lambda r: (math.isnan(r[0]), r))[: self.count]
        if first_error and not self.first_error:
            self.first_error = first_error

    def values(self, name: str) -> np.ndarray:
        """The ok samples' ``name`` (one of :attr:`KEPT`), in table order."""
        return np.concatenate(self.kept[name]) if self.kept[name] else np.zeros(0)

    def summary(self, requested: int, interrupted: bool) -> Summary:
        """Outcomes, failure probability (Clopper-Pearson 95%), quantiles, worst samples."""
        failures = self.runs - self.outcomes.get("ok", 0)
        clipped = self.values("time_saturated")
        return Summary(
            runs=self.runs,
            requested=requested,
            outcomes=dict(
                sorted(self.outcomes.items(), key=lambda item: (item[0] != "ok", item[0]))
            ),
            failure_rate=failures / self.runs if self.runs else math.nan,
            failure_upper=clopper_pearson_upper(failures, self.runs),
            final_error=_quantiles(self.values("final_error")),
            settling=_quantiles(self.values("settling_1pct")),
            worst=[(index, -negative) for negative, index in self.worst],
            nominal=self.nominal,
            nominal_certified=self.certified,
            interrupted=interrupted,
            constrained=self.constrained and self.runs > 0,
            violating=self.violating,
            ended_outside=self.outside,
            final_equality=_quantiles(self.values("final_equality"))
            if self.kept["final_equality"]
            else {},
            saturated=_quantiles(clipped) if np.any(clipped > 0) else {},
            first_error=self.first_error,
        )


def summarize(
    results: Sequence[SampleResult], requested: int, interrupted: bool, worst: int = 5
) -> Summary:
    """The statistics of results held in memory (a file's: :func:`tally_table`)."""
    return tally_rows([r.row for r in results], worst).summary(requested, interrupted)


def tally_rows(rows: Sequence[Mapping[str, Any]], worst: int = 5) -> Tally:
    """A :class:`Tally` of rows held in memory."""
    tally = Tally(worst)
    labels: dict[str, int] = {}
    codes = np.array([labels.setdefault(str(r["status"]), len(labels)) for r in rows], np.int64)
    present = rows[0].keys() if rows else ()
    columns = {
        name: np.array([bool(r[name]) if name == "certificate_holds" else r[name] for r in rows])
        for name in SUMMARY_COLUMNS
        if name in present and name not in ("status", "error")
    }
    if not rows:
        columns = {name: np.zeros(0) for name in ("sample", "final_error", "nominal")}
        columns["certificate_holds"] = np.zeros(0)
    errors = [f"sample {r['sample']}: {r['error']}" for r in rows if r.get("error")]
    tally.add(list(labels), codes, columns, errors[0] if errors else "")
    return tally


def describe_options(options: SweepOptions) -> list[str]:
    """The samples' loop and spread, as Markdown lines (a sweep's summary, a tune's)."""
    spread = [f"`--initial {n}={d}`" for n, d in options.initial]
    spread += [f"`--param {n}={d}`" for n, d in options.params]
    spread += [f"`--plant-param {n}={d}`" for n, d in options.plant_params]
    spread += [f"`--saturation {n}={lo:g}:{hi:g}`" for n, lo, hi in options.limits]
    if options.noise:
        spread.append(f"`--measurement-noise {options.noise:g}`")
    loop = (
        f"sampled every {options.sample_time:g} s (zero-order hold)"
        if options.sample_time
        else "continuous"
    )
    return [
        f"Seed {options.seed}; horizon {options.t_final:g} s; loop {loop}; RK45 rtol "
        f"{options.rtol:g}, atol {options.atol:g}; {options.points} output times.",
        "",
        "Spread: " + (", ".join(spread) if spread else "none (every sample is the spec's run)"),
    ]


def format_summary(name: str, options: SweepOptions, summary: Summary) -> str:
    """The summary as Markdown (also what the terminal shows)."""
    s = summary
    failures = s.runs - s.outcomes.get("ok", 0)
    lines = [f"# Sweep of {name}: {s.runs} samples", ""]
    if s.runs and not s.outcomes.get("ok"):
        # Not an ordinary outcome: no run of the sweep is a closed loop to measure.
        kinds = ", ".join(f"`{status}`" for status in s.outcomes)
        lines += [
            f"**Every sample failed** ({kinds}): the statistics below describe no closed "
            "loop; the nominal plant started well (a sweep whose nominal start fails is "
            "refused), so the spread or the run itself drives the law out of its domain.",
            "",
        ]
    if s.interrupted:
        lines += [
            f"Interrupted: {s.runs} of {s.requested} samples finished, "
            f"{s.requested - s.runs} missing (`tvopt-codegen sweep --resume` on this folder "
            "runs them).",
            "",
        ]
    lines += [
        *describe_options(options),
        "",
        "| outcome | samples | share |",
        "|---|---:|---:|",
    ]
    for status, count in s.outcomes.items():
        lines.append(f"| {status} | {count} | {100 * count / max(s.runs, 1):.2f}% |")
    lines += [
        "",
        f"Failure probability: {failures}/{s.runs} = {100 * s.failure_rate:.3g}%; "
        f"Clopper-Pearson 95% upper bound {100 * s.failure_upper:.3g}%.",
        "",
    ]
    if s.final_error:
        lines += [
            "| ok samples | median | p95 | p99 | max | never settled |",
            "|---|---:|---:|---:|---:|---:|",
        ]
        for label, q in (
            ("final \\|y - y*\\|", s.final_error),
            ("settling time to 1% (s)", s.settling),
            *(
                (("final max_j \\|a_j\\| (equalities)", s.final_equality),)
                if s.final_equality
                else ()
            ),
            *((("time an input was clipped (s)", s.saturated),) if s.saturated else ()),
        ):
            cells = [f"{q[k]:.3g}" if k in q else "-" for k in ("median", "p95", "p99", "max")]
            lines.append(f"| {label} | {' | '.join(cells)} | {int(q.get('never', 0))} |")
        lines.append("")
    if s.constrained:
        lines += [
            f"Constraints: {s.violating} of {s.runs} samples crossed the barrier (g_i >= s(t) at "
            f"some output time; the barrier claims never); {s.ended_outside} ok samples end "
            "outside a constraint (g_i > 0 at the horizon).",
            "",
        ]
    if s.first_error:
        lines += [
            f"Samples whose run raised are recorded with status `error`; the first: "
            f"{s.first_error}.",
            "",
        ]
    if s.nominal:
        lines += [
            f"Nominal samples (no mismatch, no saturation, no noise, continuous): {s.nominal}; "
            f"the theorem's bound |y - y*| <= C e^(-alpha t) held on {s.nominal_certified}.",
            "",
        ]
    if s.worst:
        lines += [
            "Worst samples by final |y - y*| (rerun one: `tvopt-codegen sweep --replay DIR ID`):",
            "",
        ]
        lines += [f"- sample {i}: {e:.3g}" for i, e in s.worst]
        lines.append("")
    return "\n".join(lines)


def trajectory_layout(
    program: SweepProgram, options: SweepOptions, chunk: int
) -> tuple[dict[str, Any], dict[str, np.ndarray], dict[str, Any]]:
    """The Zarr store's arrays (dimensions, shape, chunks), coordinates and attributes."""
    n, m, nu = len(program.state_names), len(program.output_names), len(program.input_names)
    count, points = options.samples, options.points

    def variable(
        *names: tuple[str, int],
    ) -> tuple[tuple[str, ...], tuple[int, ...], tuple[int, ...]]:
        dims = ("sample", "time", *(name for name, _ in names))
        shape = (count, points, *(size for _, size in names))
        return dims, shape, (chunk, points, *(size for _, size in names))

    variables = {
        "t": variable(),
        "state": variable(("state_name", n)),
        "output": variable(("output_name", m)),
        "target": variable(("output_name", m)),
        "input": variable(("input_name", nu)),
        **{name: variable() for name in TAIL},
    }
    coords = {
        "sample": np.arange(count, dtype=np.int64),
        "state_name": np.array(program.state_names, dtype=str),
        "output_name": np.array(program.output_names, dtype=str),
        "input_name": np.array(program.input_names, dtype=str),
    }
    attrs = {
        "spec": program.name,
        "description": "tvopt-codegen sweep trajectories: t, closed-loop state, outputs y, "
        "target y* (minimiser of f0), commanded input u, log|det R| and the least "
        "eigenvalue of f0's Hessian, at each output time; NaN after a failure",
        "options": options.as_dict(),
    }
    return variables, coords, attrs


def trajectory_block(
    program: SweepProgram, results: Sequence[SampleResult]
) -> dict[str, np.ndarray]:
    """The store's arrays for consecutive samples (their trajectories, NaN-padded)."""
    n, m, nu = len(program.state_names), len(program.output_names), len(program.input_names)
    points = max((len(r.trajectory) for r in results if r.trajectory is not None), default=0)
    width = program.columns
    block = np.full((len(results), points, width), np.nan)
    for i, result in enumerate(results):
        if result.trajectory is not None:
            block[i, : len(result.trajectory)] = result.trajectory
    return {
        "t": block[:, :, 0],
        "state": block[:, :, 1 : 1 + n],
        "output": block[:, :, 1 + n : 1 + n + m],
        "target": block[:, :, 1 + n + m : 1 + n + 2 * m],
        "input": block[:, :, 1 + n + 2 * m : 1 + n + 2 * m + nu],
        **{name: tail(block, name) for name in TAIL},
    }


def tally_table(path: Path, worst: int = 5) -> Tally:
    """The statistics of a ``summary.parquet``, read a row group and a few columns at a time.

    ``status`` is dictionary-encoded per row group, so a block costs its codes, not a
    Python string a row; the client's memory is that of :class:`Tally`.
    """
    _, pq = pyarrow()
    table = pq.ParquetFile(path)
    present = [c for c in SUMMARY_COLUMNS if c in table.schema_arrow.names]
    tally = Tally(worst)
    for group in range(table.metadata.num_row_groups):
        batch = table.read_row_group(group, columns=present)
        encoded = batch.column("status").combine_chunks().dictionary_encode()
        columns = {
            name: _null_as_false(to_numpy(batch.column(name)))
            if name == "certificate_holds"
            else to_numpy(batch.column(name))
            for name in present
            if name not in ("status", "error")
        }
        first = ""
        if "error" in present and batch.column("error").null_count < batch.num_rows:
            where = int(np.argmax(to_numpy(batch.column("error").is_valid())))
            message = batch.column("error")[where].as_py()
            first = f"sample {int(columns['sample'][where])}: {message}"
        tally.add(
            [str(v) for v in encoded.dictionary.to_pylist()],
            to_numpy(encoded.indices).astype(np.int64),
            columns,
            first,
        )
    return tally


def _null_as_false(values: np.ndarray) -> np.ndarray:
    """A boolean column's values, a null (``None`` in an object array) as False."""
    return values if values.dtype == bool else np.array([v is True for v in values], dtype=bool)


def record_bytes(record: Mapping[str, Any]) -> bytes:
    """``sweep.json``: what ``--replay`` and ``--resume`` read.

    Written as the sweep starts, and again at its end with what finished.
    """
    import json  # noqa: PLC0415

    return (json.dumps(dict(record), indent=2) + "\n").encode()


#: The record of a sweep beside its table: what ``--replay`` reads.
RECORD = "sweep.json"
