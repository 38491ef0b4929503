"""A tune's tables as text: ``tune.md`` and ``evaluations.csv``.

``tune.md`` holds the outcome, the fresh check side by side and the best candidates;
``evaluations.csv`` every candidate. Nothing here writes files.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

from tvopt_codegen.sweep.options import SweepOptions
from tvopt_codegen.sweep.results import describe_options
from tvopt_codegen.tune.session import ORIGINAL, Evaluation
from tvopt_codegen.tune.space import Space

#: Candidates listed in ``tune.md`` (all are in ``evaluations.csv``).
LISTED = 10


def _number(value: float) -> str:
    return "-" if value is None or math.isnan(value) else f"{value:.4g}"


def poles_label(poles: Sequence[complex]) -> str:
    """``-1, -1.5, -2 ± 1j``: each conjugate pair once."""
    parts = []
    for p in poles:
        if p.imag < 0:
            continue
        parts.append(f"{p.real:g}" if p.imag == 0 else f"{p.real:g} ± {p.imag:g}j")
    return ", ".join(parts)


def _gains(evaluation: Evaluation) -> str:
    text = poles_label(evaluation.candidate.poles)
    if evaluation.candidate.bandwidth is not None:
        text += f"; bandwidth {evaluation.candidate.bandwidth:g}"
    return text


def space_text(space: Space) -> str:
    """What was searched, in words: the poles' structure and bounds, the bandwidth's."""
    lo, hi = space.magnitude
    text = (
        f"{space.count} poles ({space.pairs} complex pair{'s' if space.pairs != 1 else ''}"
        f"{', one of them the integral' if space.integral else ''}) of magnitude in "
        f"[{lo:.4g}, {hi:.4g}] rad/s"
    )
    if space.pairs:
        text += f", pairs damped at least {space.min_damping:g}"
    if space.bandwidth is not None:
        text += (
            f"; the observer's bandwidth in [{space.bandwidth[0]:.4g}, "
            f"{space.bandwidth[1]:.4g}] rad/s"
        )
    return text


def _percent(value: float) -> str:
    return "-" if math.isnan(value) else f"{100 * value:.3g}%"


def tune_markdown(
    name: str,
    method: str,
    requirements: Sequence[str],
    space: str,
    options: SweepOptions,
    evaluations: Sequence[Evaluation],
    chosen: Evaluation,
    fresh: Mapping[str, Any] | None,
    edges: Sequence[str] = (),
) -> str:
    """``tune.md``: what was searched, the fresh check side by side, the best candidates.

    ``edges`` names the chosen numbers that sit on the edge of the search's box.
    """
    searched = [e for e in evaluations if e.generation != ORIGINAL]
    original = next(e for e in evaluations if e.generation == ORIGINAL)
    lines = [
        f"# Tuning of {name}: {len(searched)} candidates, {original.runs} samples each",
        "",
        f"Search: {method}; {space}.",
        "",
        "Requirements: minimise "
        + requirements[0]
        + ("; subject to " + ", ".join(requirements[1:]) if len(requirements) > 1 else "")
        + ".",
        "",
        "Every candidate ran the same samples (common random numbers):",
        "",
        *describe_options(options),
        "",
    ]
    if fresh is None:
        lines += [
            "**Interrupted**: the best candidate so far, not checked on fresh samples "
            "(`tvopt-codegen tune --resume` on this folder continues the search).",
            "",
        ]
    else:
        before, after = fresh["original"], fresh["tuned"]
        lines += [
            f"## On {fresh['samples']} fresh samples (seed {fresh['seed']})",
            "",
            "| | the spec's gains | tuned |",
            "|---|---:|---:|",
            f"| gains | {_gains(original)} | {_gains(chosen)} |",
            f"| {requirements[0]} (objective) | {_number(before['objective'])} | "
            f"{_number(after['objective'])} |",
            f"| p95 final \\|y - y*\\| | {_number(before['p95_final_error'])} | "
            f"{_number(after['p95_final_error'])} |",
            f"| median final \\|y - y*\\| | {_number(before['median_final_error'])} | "
            f"{_number(after['median_final_error'])} |",
            f"| failures | {before['failures']}/{fresh['samples']} | "
            f"{after['failures']}/{fresh['samples']} |",
            f"| failure bound (Clopper-Pearson 95%) | {_percent(before['failure_bound'])} | "
            f"{_percent(after['failure_bound'])} |",
            f"| mean time in saturation | {_percent(before['saturation'])} | "
            f"{_percent(after['saturation'])} |",
            f"| p95 of the peak \\|u\\| | {_number(before['effort'])} | "
            f"{_number(after['effort'])} |",
        ]
        for (label, value, _), (_, tuned, _) in zip(
            before["constraints"], after["constraints"], strict=True
        ):
            lines.append(f"| {label} | {_number(value)} | {_number(tuned)} |")
        lines += [
            "",
            f"Requirements on the fresh samples: the spec's gains "
            f"{'meet' if before['feasible'] else 'miss'} them, the tuned gains "
            f"{'meet' if after['feasible'] else 'miss'} them.",
            "",
        ]
    if not chosen.score.feasible:
        lines += [
            "**No candidate met every requirement** on the tuning samples: the chosen gains "
            "are the least violating. Loosen a constraint, or widen the search's ranges.",
            "",
        ]
    if edges:
        lines += [
            "The chosen gains sit on the edge of the searched box (" + "; ".join(edges) + "): "
            "better ones may lie beyond it (`--pole-range`, `--bandwidth-range`).",
            "",
        ]
    ranked = sorted(evaluations, key=lambda e: (e.score.value, e.index))[:LISTED]
    lines += [
        "## The search, on its own samples",
        "",
        f"The chosen candidate is #{chosen.index}"
        + (" (the spec's own gains: no candidate did better)" if chosen is original else "")
        + f"; the spec's gains scored {_number(original.score.objective)}.",
        "",
        "| # | generation | gains | objective | feasible | failures | saturation | "
        "p95 peak \\|u\\| |",
        "|---:|---:|---|---:|---|---:|---:|---:|",
    ]
    for e in ranked:
        generation = "spec" if e.generation == ORIGINAL else str(e.generation)
        lines.append(
            f"| {e.index} | {generation} | {_gains(e)} | {_number(e.score.objective)} | "
            f"{'yes' if e.score.feasible else 'no'} | {e.failures} | "
            f"{_percent(e.saturation)} | {_number(e.effort)} |"
        )
    return "\n".join(lines) + "\n"


def evaluations_csv(evaluations: Sequence[Evaluation]) -> str:
    """``evaluations.csv``: one row per candidate, floats exact (``repr``)."""
    labels = [label for label, _, _ in evaluations[0].score.constraints] if evaluations else []
    count = max((len(e.candidate.poles) for e in evaluations), default=0)
    header = [
        "index",
        "generation",
        "position",
        *(f"pole{i}_re,pole{i}_im" for i in range(count)),
        "bandwidth",
        "objective",
        *labels,
        "feasible",
        "value",
        "failures",
        "runs",
        "saturation",
        "effort",
    ]
    rows = [",".join(header)]
    for e in evaluations:
        poles = [f"{p.real!r},{p.imag!r}" for p in e.candidate.poles]
        values = {label: value for label, value, _ in e.score.constraints}
        rows.append(
            ",".join(
                [
                    str(e.index),
                    str(e.generation),
                    str(e.position),
                    *poles,
                    "" if e.candidate.bandwidth is None else repr(e.candidate.bandwidth),
                    repr(e.score.objective),
                    *(repr(values.get(label, math.nan)) for label in labels),
                    "1" if e.score.feasible else "0",
                    repr(e.score.value),
                    str(e.failures),
                    str(e.runs),
                    repr(e.saturation),
                    repr(e.effort),
                ]
            )
        )
    return "\n".join(rows) + "\n"
