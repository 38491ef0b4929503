"""A tune's problem and its outcome in memory: what the command searches and writes.

:class:`Problem` gathers what the command line and the spec decided (the compiled loop,
its samples, the space, the requirements, the spec's own gains); the rest of this module
makes the optimiser it asks, the failure bound the spec's gains set by default, and the
files of an outcome (the tuned spec's text, the tables and the figure), as bytes for
:mod:`tvopt_codegen.emit` to write.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Any

from tvopt_codegen.sweep.results import clopper_pearson_upper
from tvopt_codegen.tune.requirements import Requirements, parse_constraint
from tvopt_codegen.tune.search import Optimizer
from tvopt_codegen.tune.session import Evaluation, Search
from tvopt_codegen.tune.settings import Settings
from tvopt_codegen.tune.space import REAL_TOLERANCE, Candidate, Space

if TYPE_CHECKING:
    from tvopt_codegen.derivation import Derivation
    from tvopt_codegen.sweep import SweepOptions, SweepProgram

#: The searches ``--method`` names, as ``tune.md`` names them.
METHODS = {"cma": "CMA-ES", "tpe": "optuna's TPE", "random": "uniform random points"}


@dataclass
class Problem:
    """A tune's problem, ready to search: the loop, its samples, the space, the requirements.

    Attributes
    ----------
    name, source, raw : str, str, bytes
        The spec's name, where it was read and its exact bytes (the tuned spec is this
        text with the tuned values replaced).
    program : SweepProgram
        The compiled loop with the spec's gains; every candidate is it with others.
    options, check : SweepOptions
        The tuning samples, and the fresh ones of the final check.
    space : Space
        The box the optimiser searches, and its map to candidates.
    requirements : Requirements
        The objective and constraints (the default failure bound added once the spec's
        own gains are scored, :func:`with_default_failure_bound`).
    original : Candidate
        The spec's own gains.
    settings : Settings
        The command line's settings (``tune.json``'s ``settings``).
    default_bound : str or None
        The label of the failure bound taken from the spec's gains, if one was added.
    """

    name: str
    source: str
    raw: bytes
    program: SweepProgram
    options: SweepOptions
    check: SweepOptions
    space: Space
    requirements: Requirements
    original: Candidate
    settings: Settings
    default_bound: str | None = None

    def search(self, history: Sequence[Evaluation] = ()) -> Search:
        """A search of this problem by a new optimiser, after ``history`` (``--resume``)."""
        return Search(
            self.space,
            self.requirements,
            optimizer_for(self),
            self.settings.evaluations,
            self.options.t_final,
            self.program.input_names,
            history,
        )

    def program_for(self, candidate: Candidate) -> SweepProgram:
        """The compiled loop with ``candidate``'s gains.

        The spec's own gains run the spec's loop unchanged: a spec that gave coefficients
        is measured with them, not with its poles recomputed in floating point.
        """
        if candidate == self.original:
            return self.program
        return self.program.with_gains(
            candidate.coefficients, candidate.bandwidth, poles=candidate.poles
        )


def spec_poles(derivation: Derivation) -> tuple[complex, ...]:
    """The spec's poles as it wrote them (exact); from coefficients, H's eigenvalues.

    Eigenvalues computed from coefficients are cleaned as the spec would write them: a
    root within :data:`~tvopt_codegen.tune.space.REAL_TOLERANCE` of its size of the real
    axis is real, and a pair's members are exact conjugates.
    """
    if derivation.spec.poles is not None:
        return tuple(complex(p) for p in derivation.spec.poles)
    cleaned: list[complex] = []
    for value in sorted(derivation.dynamics.eigenvalues, key=lambda p: (p.real, -p.imag)):
        if abs(value.imag) <= REAL_TOLERANCE * max(1.0, abs(value)):
            cleaned.append(complex(value.real, 0.0))
        elif value.imag > 0:
            cleaned += [complex(value.real, value.imag), complex(value.real, -value.imag)]
    return tuple(cleaned)


def default_population(dimension: int) -> int:
    """CMA-ES's default population, so that the other searches run the same batches."""
    return 4 + int(3 * math.log(dimension))


def optimizer_for(problem: Problem) -> Optimizer:
    """A new optimiser of the problem's method and seed, started at the spec's gains."""
    from tvopt_codegen.tune.search import (  # noqa: PLC0415 - cma and optuna on use
        cma_optimizer,
        random_optimizer,
        tpe_optimizer,
    )

    settings, space = problem.settings, problem.space
    population = settings.population or default_population(space.dimension)
    if settings.method == "random":
        return random_optimizer(space.dimension, settings.seed, population)
    start = space.encode(problem.original)
    if settings.method == "tpe":
        return tpe_optimizer(start, settings.seed, population)
    return cma_optimizer(start, settings.seed, settings.population)


def with_default_failure_bound(
    problem: Problem, original: Evaluation
) -> tuple[Requirements, str | None, Evaluation]:
    """Without a failure-bound constraint, the tuned gains may fail no more than the spec's.

    The bound is the spec's gains' own Clopper-Pearson bound on the tuning samples (a
    resumed tune takes it again from the recorded evaluation of the spec's gains).

    Returns
    -------
    requirements : Requirements
        The problem's, with the bound added (unchanged when the user gave one).
    label : str or None
        The added constraint's label.
    original : Evaluation
        The spec's gains' evaluation with the new constraint in its score (it meets it).
    """
    requirements = problem.requirements
    if any(c.metric == "failure_bound" for c in requirements.constraints):
        return requirements, None, original
    bound = clopper_pearson_upper(original.failures, original.runs)
    added = parse_constraint(f"failure_bound <= {bound!r}", "--constraint", samples=original.runs)
    requirements = replace(requirements, constraints=(*requirements.constraints, added))
    if any(label == added.label for label, _, _ in original.score.constraints):
        return requirements, added.label, original
    score = replace(
        original.score, constraints=(*original.score.constraints, (added.label, bound, bound))
    )
    return requirements, added.label, replace(original, score=score)


def on_bound(space: Space, candidate: Candidate) -> list[str]:
    """Which of ``candidate``'s numbers sit on the edge of the search's box (to 4 digits)."""
    edges = []
    lo, hi = space.magnitude
    for pole in candidate.poles:
        size = abs(pole)
        if math.isclose(size, lo, rel_tol=1e-3) or math.isclose(size, hi, rel_tol=1e-3):
            edges.append(f"a pole of magnitude {size:.4g} (the range is [{lo:.4g}, {hi:.4g}])")
            break
    if space.bandwidth is not None and candidate.bandwidth is not None:
        low, high = space.bandwidth
        if any(math.isclose(candidate.bandwidth, b, rel_tol=1e-3) for b in (low, high)):
            edges.append(
                f"the bandwidth {candidate.bandwidth:.4g} (the range is [{low:.4g}, {high:.4g}])"
            )
    return edges


def header(
    problem: Problem,
    chosen: Evaluation,
    original: Evaluation,
    fresh: dict[str, Any] | None,
) -> list[str]:
    """The tuned spec's first comment lines: how it was tuned, and what it is worth."""
    settings = problem.settings
    label = problem.requirements.objective.label
    lines = [
        f"Tuned by tvopt-codegen tune ({settings.method}, {settings.evaluations} candidates "
        f"of {settings.samples} samples, seed {settings.seed}):",
        f"  {label} = {chosen.score.objective:.6g} on the tuning samples (the spec's gains: "
        f"{original.score.objective:.6g}).",
    ]
    if not chosen.score.feasible:
        lines.append(
            "  No candidate met every requirement on the tuning samples: these gains are "
            "the least violating (see tune.md)."
        )
    if fresh is not None:
        lines.append(
            f"  On {fresh['samples']} fresh samples (seed {fresh['seed']}): "
            f"{fresh['tuned']['objective']:.6g} (the spec's gains: "
            f"{fresh['original']['objective']:.6g})."
        )
    else:
        lines.append("  Interrupted: the best candidate so far, not checked on fresh samples.")
    return lines


def result_files(
    problem: Problem,
    evaluations: Sequence[Evaluation],
    chosen: Evaluation,
    original: Evaluation,
    fresh: dict[str, Any] | None,
) -> dict[str, bytes | str]:
    """The tuned spec, the tables and the figure, in memory (the record is the caller's)."""
    from tvopt_codegen.runs.artifacts import tune_files  # noqa: PLC0415 - matplotlib on use
    from tvopt_codegen.tune.spec_text import tuned_text  # noqa: PLC0415
    from tvopt_codegen.tune.tables import (  # noqa: PLC0415
        evaluations_csv,
        space_text,
        tune_markdown,
    )

    # The spec's own gains chosen: its [error_dynamics] stays as the user wrote it
    # (coefficients, say), only the header is new.
    keep = chosen.candidate == problem.original
    text = tuned_text(
        problem.raw.decode("utf-8"),
        problem.source,
        poles=None if keep else chosen.candidate.poles,
        bandwidth=None if keep else chosen.candidate.bandwidth,
        header=header(problem, chosen, original, fresh),
    )
    requirements = [problem.requirements.objective.label] + [
        c.label + (" (the spec's gains' own bound)" if c.label == problem.default_bound else "")
        for c in problem.requirements.constraints
    ]
    method = f"{METHODS[problem.settings.method]}, seed {problem.settings.seed}"
    markdown = tune_markdown(
        problem.name,
        method,
        requirements,
        space_text(problem.space),
        problem.options,
        evaluations,
        chosen,
        fresh,
        on_bound(problem.space, chosen.candidate),
    )
    files: dict[str, bytes | str] = {tuned_name(problem.name): text}
    files |= tune_files(
        problem.name,
        markdown,
        evaluations_csv(evaluations),
        problem.requirements.objective.label,
        evaluations,
        chosen,
        original,
    )
    return files


def tuned_name(name: str) -> str:
    """The tuned spec's file name: never the spec's own (``<name>.toml`` is its copy)."""
    return f"{name}_tuned.toml"
