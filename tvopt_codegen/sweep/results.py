"""What a sweep yields: statistics, the summary's text, the table and trajectories.

The Clopper-Pearson bound, quantiles and worst samples; the Parquet table and the Zarr
store's blocks.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from tvopt_codegen.errors import MissingExtraError

if TYPE_CHECKING:
    pass
from tvopt_codegen.sweep.options import SweepOptions
from tvopt_codegen.sweep.program import TAIL, SweepProgram, tail
from tvopt_codegen.sweep.sample import SampleResult


def clopper_pearson_upper(failures: int, runs: int, confidence: float = 0.95) -> float:
    """One-sided upper confidence bound on a failure probability (exact binomial).

    With no failure it is ``1 - (1 - confidence)^(1/runs)``: 0 in 299 runs gives 0.99%.
    """
    from scipy.stats import beta  # noqa: PLC0415

    if runs == 0:
        return 1.0
    if failures >= runs:
        return 1.0
    return float(beta.ppf(confidence, failures + 1, runs - failures))


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


def summarize(
    results: Sequence[SampleResult], requested: int, interrupted: bool, worst: int = 5
) -> Summary:
    """Outcomes, failure probability (Clopper-Pearson 95%), error quantiles, worst samples."""
    rows = [r.row for r in results]
    outcomes: dict[str, int] = {}
    for row in rows:
        outcomes[row["status"]] = outcomes.get(row["status"], 0) + 1
    failures = sum(count for status, count in outcomes.items() if status != "ok")
    ok = [row for row in rows if row["status"] == "ok"]
    finals = np.array([row["final_error"] for row in ok])
    settle = np.array([row["settling_1pct"] for row in ok])
    clipped = np.array([row["time_saturated"] for row in ok])

    def quantiles(values: np.ndarray) -> dict[str, float]:
        if not len(values):
            return {}
        finite = values[np.isfinite(values)]
        out = {"never": float(len(values) - len(finite))}
        if len(finite):
            for label, q in (("median", 50), ("p95", 95), ("p99", 99)):
                out[label] = float(np.percentile(finite, q))
            out["max"] = float(finite.max())
        return out

    ranked = sorted(ok, key=lambda row: (-row["final_error"], row["sample"]))[:worst]
    nominal = [row for row in ok if row["nominal"]]
    return Summary(
        runs=len(rows),
        requested=requested,
        outcomes=dict(sorted(outcomes.items(), key=lambda item: (item[0] != "ok", item[0]))),
        failure_rate=failures / len(rows) if rows else math.nan,
        failure_upper=clopper_pearson_upper(failures, len(rows)),
        final_error=quantiles(finals),
        settling={k: v for k, v in quantiles(settle).items()},
        worst=[(int(row["sample"]), float(row["final_error"])) for row in ranked],
        nominal=len(nominal),
        nominal_certified=sum(bool(row["certificate_holds"]) for row in nominal),
        interrupted=interrupted,
        constrained=bool(rows) and "violations" in rows[0],
        violating=sum(int(row.get("violations", 0)) > 0 for row in rows),
        ended_outside=sum(row.get("final_constraint", -1.0) > 0 for row in ok),
        final_equality=quantiles(np.array([row["final_equality"] for row in ok]))
        if ok and "final_equality" in ok[0]
        else {},
        saturated=quantiles(clipped) if np.any(clipped > 0) else {},
    )


def format_summary(name: str, options: SweepOptions, summary: Summary) -> str:
    """The summary as Markdown (also what the terminal shows)."""
    s = summary
    failures = s.runs - s.outcomes.get("ok", 0)
    lines = [f"# Sweep of {name}: {s.runs} samples", ""]
    if s.interrupted:
        lines += [f"Interrupted: {s.runs} of {s.requested} samples finished.", ""]
    spread = [f"`--initial {n}={d}`" for n, d in options.initial]
    spread += [f"`--param {n}={d}`" for n, d in options.params]
    spread += [f"`--plant-param {n}={d}`" for n, d in options.plant_params]
    spread += [f"`--saturation {n}={lo:g}:{hi:g}`" for n, lo, hi in options.limits]
    if options.noise:
        spread.append(f"`--noise {options.noise:g}`")
    loop = (
        f"sampled every {options.sample_time:g} s (zero-order hold)"
        if options.sample_time
        else "continuous"
    )
    lines += [
        f"Seed {options.seed}; horizon {options.t_final:g} s; loop {loop}; RK45 rtol "
        f"{options.rtol:g}, atol {options.atol:g}; {options.points} output times.",
        "",
        "Spread: " + (", ".join(spread) if spread else "none (every sample is the spec's run)"),
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


def parquet_bytes(rows: Sequence[Mapping[str, Any]]) -> bytes:
    """The summary table as Parquet (one row per sample, in sample order)."""
    try:
        import pyarrow as pa  # noqa: PLC0415
        import pyarrow.parquet as pq  # noqa: PLC0415
    except ImportError:
        raise MissingExtraError(
            "sweep writes Parquet with pyarrow: pip install 'tvopt-codegen[sweep]'"
        ) from None
    table = pa.Table.from_pylist(list(rows))
    sink = pa.BufferOutputStream()
    pq.write_table(table, sink)
    return bytes(sink.getvalue().to_pybytes())


def read_summary(path: str) -> list[dict[str, Any]]:
    """The rows of a ``summary.parquet``."""
    try:
        import pyarrow.parquet as pq  # noqa: PLC0415
    except ImportError:
        raise MissingExtraError(
            "reading a sweep needs pyarrow: pip install 'tvopt-codegen[sweep]'"
        ) from None
    rows: list[dict[str, Any]] = pq.read_table(path).to_pylist()
    return rows


#: The record of a sweep beside its table: what ``--replay`` reads.
RECORD = "sweep.json"
