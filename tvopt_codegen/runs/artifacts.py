"""What the verification commands write: tables, records, certificates and figures.

The verification stages (:mod:`~tvopt_codegen.simulation`, :mod:`~tvopt_codegen.simulation.sampled`,
:mod:`~tvopt_codegen.sweep`) compute and return data; this module turns their results
into the files a command writes, in memory (the writer, :mod:`~tvopt_codegen.emit`,
puts them on disk). It is the only module that imports :mod:`~tvopt_codegen.runs.figures`
(what each figure shows) and :mod:`~tvopt_codegen.runs.drawing` (matplotlib, which draws
them): ``generate``, ``check`` and ``report`` never load either.
"""

from __future__ import annotations

import io
from collections.abc import Collection, Mapping, Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

from tvopt_codegen.derivation import Derivation
from tvopt_codegen.runs.drawing import Painter, draw, draw_all
from tvopt_codegen.runs.figures import (
    early_figures,
    figures,
    replay_figure,
    sampled_figure,
    sweep_figures,
    tune_figure,
)
from tvopt_codegen.simulation import Result, columns, format_certificate

if TYPE_CHECKING:
    from tvopt_codegen.simulation.result import Trajectories

    # Types only: the sampled run's module and the sweep's are loaded by the commands
    # that run them (``simulate`` has no use for the sweep's: 15 ms of its imports).
    from tvopt_codegen.simulation.sampled import SampledResult
    from tvopt_codegen.sweep import SampleResult, Summary, SweepOptions, SweepProgram
    from tvopt_codegen.tune.session import Evaluation


def submit_early(derivation: Derivation, run: Trajectories, painter: Painter) -> tuple[str, ...]:
    """Send ``painter`` the figures of ``run`` alone, before it is certified; their stems.

    Those of :func:`~tvopt_codegen.runs.figures.early_figures`: paths and inputs. Pass
    the stems to :func:`result_files` when the result is this run's.
    """
    plots = early_figures(derivation, run)
    painter.submit(plots)
    return tuple(plot.stem for plot in plots)


def result_files(
    derivation: Derivation,
    result: Result,
    painter: Painter | None = None,
    submitted: Collection[str] = (),
) -> dict[str, bytes]:
    """Trajectories (CSV, NPZ), the certificate text, and the figures, in memory.

    The figures go to ``painter`` first (its drawing process draws them while the
    tables are written here), but for those of stems ``submitted`` already, from this
    run (:func:`submit_early`); without a painter they are drawn in this process.
    """
    d, r = derivation, result
    name = d.spec.name
    plots = figures(d, r)
    if painter is not None:
        painter.submit([plot for plot in plots if plot.stem not in submitted])
    table = np.column_stack(
        [r.t, r.states.T, r.inputs.T, r.outputs.T, r.target.T, r.E.reshape(len(r.t), -1)]
    )
    text = io.StringIO()
    text.write(",".join(columns(d)) + "\n")
    for row in table:
        text.write(",".join(repr(float(v)) for v in row) + "\n")
    arrays = io.BytesIO()
    np.savez(
        arrays,
        t=r.t,
        states=r.states,
        inputs=r.inputs,
        y=r.outputs,
        y_star=r.target,
        E=r.E,
        bound=r.bound,
        state_names=np.array(d.closed_loop.state_names),
        input_names=np.array(d.spec.inputs),
        output_names=np.array(d.spec.outputs),
    )
    files = {
        f"{name}_trajectory.csv": text.getvalue().encode("utf-8"),
        f"{name}_trajectory.npz": arrays.getvalue(),
        f"{name}_certificate.txt": (format_certificate(d, r) + "\n").encode("utf-8"),
    }
    drawn = painter.collect() if painter is not None else draw_all(plots)
    files.update({each: drawn[each] for plot in plots for each in plot.file_names()})
    return files


def sampled_files(derivation: Derivation, result: SampledResult) -> dict[str, bytes]:
    """The sampled runs (CSV of the first, NPZ of all) and the overlay figure, in memory."""
    d = derivation
    name = d.spec.name
    run = result.runs[0]
    table = np.column_stack([run.t, run.states.T, run.inputs.T, run.outputs.T])
    header = ["t", *d.closed_loop.state_names, *(f"u_{n}" for n in d.spec.inputs)]
    header += [f"y_{n}" for n in d.spec.outputs]
    text = io.StringIO()
    text.write(",".join(header) + "\n")
    for row in table:
        text.write(",".join(repr(float(v)) for v in row) + "\n")
    arrays = io.BytesIO()
    saved: dict[str, Any] = {}
    for index, each in enumerate(result.runs):
        saved |= {
            f"h{index}": np.array(each.h),
            f"t{index}": each.t,
            f"states{index}": each.states,
            f"inputs{index}": each.inputs,
            f"y{index}": each.outputs,
        }
    np.savez(arrays, state_names=np.array(d.closed_loop.state_names), **saved)
    files = {
        f"{name}_sampled.csv": text.getvalue().encode("utf-8"),
        f"{name}_sampled.npz": arrays.getvalue(),
    }
    files.update(draw(sampled_figure(d, result)))
    return files


def sweep_files(
    program: SweepProgram,
    options: SweepOptions,
    record: Mapping[str, Any],
    summary: Summary,
    histograms: tuple[np.ndarray, np.ndarray],
    worst: Mapping[int, np.ndarray],
) -> dict[str, bytes]:
    """What a sweep writes at its end beside its table, in memory: record, summary, figures.

    ``histograms`` are the ok samples' final errors and settling times.
    """
    from tvopt_codegen.sweep import RECORD, format_summary, record_bytes  # noqa: PLC0415

    files = {
        "summary.md": (format_summary(program.name, options, summary) + "\n").encode(),
        RECORD: record_bytes(record),
    }
    files.update(draw_all(sweep_figures(program, summary.runs, *histograms, worst)))
    return files


def replay_files(program: SweepProgram, result: SampleResult) -> dict[str, bytes]:
    """One replayed sample: its trajectory as CSV, its row as Markdown, and a figure."""
    from tvopt_codegen.sweep import TAIL  # noqa: PLC0415

    assert result.trajectory is not None
    index = int(result.row["sample"])
    header = (
        ["t", *program.state_names]
        + list(program.output_names)
        + [f"{name}*" for name in program.output_names]
        + list(program.input_names)
        + list(TAIL)
    )
    lines = [",".join(header)]
    lines += [",".join(repr(float(v)) for v in row) for row in result.trajectory]
    table = ["| column | value |", "|---|---|"]
    table += [f"| {key} | {value} |" for key, value in result.row.items()]
    return {
        f"sample_{index}.csv": ("\n".join(lines) + "\n").encode(),
        f"sample_{index}.md": (
            f"# Sample {index} of a sweep of {program.name}\n\n" + "\n".join(table) + "\n"
        ).encode(),
        **draw(replay_figure(program, result.row, result.trajectory)),
    }


def tune_files(
    name: str,
    markdown: str,
    csv: str,
    objective: str,
    evaluations: Sequence[Evaluation],
    chosen: Evaluation,
    original: Evaluation,
) -> dict[str, bytes]:
    """What a tune writes beside its record and tuned spec: its tables and its figure."""

    def point(e: Evaluation) -> tuple[float, float, float]:
        return (e.score.objective, e.saturation, e.effort)

    figure = tune_figure(
        name,
        objective,
        [(*point(e), e.score.feasible) for e in evaluations],
        point(original),
        point(chosen),
    )
    return {"tune.md": markdown.encode(), "evaluations.csv": csv.encode(), **draw(figure)}
