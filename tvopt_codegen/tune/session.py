"""The search: generations of candidates asked of the optimiser, swept, scored, told back.

Pure of files and of Dask: it is handed a function that sweeps a generation, and it
hands back each evaluation as it completes, so that the command can record it at once
(Ctrl-C keeps every candidate already scored). A search resumed from its record replays
the recorded evaluations into a new optimiser of the same seed: the optimiser asks the
same points again (checked), is told the recorded values, and the search continues
exactly where it stopped, re-running only the candidates of the generation that was
cut short.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from tvopt_codegen.tune.requirements import Requirements, Score, score
from tvopt_codegen.tune.search import Optimizer
from tvopt_codegen.tune.space import Candidate, Space

#: Asked points must equal the recorded ones to this (the record stores them as JSON
#: floats, which round-trip exactly; the margin only absorbs nothing).
REPLAY_TOLERANCE = 1e-12

#: The generation of the spec's own gains (evaluated first, outside the optimiser).
ORIGINAL = -1


class ReplayError(ValueError):
    """A recorded evaluation is not where this search puts it: the record is another's."""


@dataclass(frozen=True)
class Evaluation:
    """One candidate swept and scored.

    Attributes
    ----------
    index : int
        Its place in the search (0: the spec's own gains).
    generation, position : int
        The optimiser's generation and the candidate's place in it (:data:`ORIGINAL`
        and 0 for the spec's gains).
    x : tuple of float
        The point in the search box ``[0, 1]^d`` the optimiser asked.
    candidate : Candidate
        The gains.
    score : Score
        The requirements' objective and constraints on the tuning samples.
    failures, runs : int
        Samples that failed, and samples run.
    saturation : float
        The mean fraction of the horizon during which an input was clipped.
    effort : float
        The 95th percentile, over the samples that ran to the end, of the largest
        ``|u|`` any input reached (NaN when none did): the trade-off's other axis.
    """

    index: int
    generation: int
    position: int
    x: tuple[float, ...]
    candidate: Candidate
    score: Score
    failures: int
    runs: int
    saturation: float
    effort: float

    def as_dict(self) -> dict[str, Any]:
        """A JSON-ready record (``tune.json``): floats exactly as computed."""
        return {
            "index": self.index,
            "generation": self.generation,
            "position": self.position,
            "x": list(self.x),
            "poles": [[p.real, p.imag] for p in self.candidate.poles],
            "bandwidth": self.candidate.bandwidth,
            "objective": _json_float(self.score.objective),
            "constraints": [
                [label, _json_float(value), bound] for label, value, bound in self.score.constraints
            ],
            "feasible": self.score.feasible,
            "value": _json_float(self.score.value),
            "failures": self.failures,
            "runs": self.runs,
            "saturation": _json_float(self.saturation),
            "effort": _json_float(self.effort),
        }

    @classmethod
    def from_dict(cls, record: Mapping[str, Any]) -> Evaluation:
        """The inverse of :meth:`as_dict`."""
        candidate = Candidate(
            poles=tuple(complex(float(re), float(im)) for re, im in record["poles"]),
            bandwidth=None if record["bandwidth"] is None else float(record["bandwidth"]),
        )
        result = Score(
            objective=_from_json_float(record["objective"]),
            constraints=tuple(
                (str(label), _from_json_float(value), float(bound))
                for label, value, bound in record["constraints"]
            ),
            feasible=bool(record["feasible"]),
            value=_from_json_float(record["value"]),
        )
        return cls(
            index=int(record["index"]),
            generation=int(record["generation"]),
            position=int(record["position"]),
            x=tuple(float(v) for v in record["x"]),
            candidate=candidate,
            score=result,
            failures=int(record["failures"]),
            runs=int(record["runs"]),
            saturation=_from_json_float(record["saturation"]),
            effort=_from_json_float(record["effort"]),
        )


def _json_float(value: float) -> float | str:
    """JSON has no infinity or NaN: those are written as text."""
    return value if np.isfinite(value) else repr(float(value))


def _from_json_float(value: float | str) -> float:
    return float(value)


@dataclass(frozen=True)
class Measured:
    """What a candidate's rows say: its score and the trade-off's numbers."""

    score: Score
    failures: int
    saturation: float
    effort: float


def measure(
    requirements: Requirements,
    rows: Sequence[Mapping[str, Any]],
    t_final: float,
    inputs: Sequence[str],
) -> Measured:
    """Score one candidate's rows, and measure its saturation and input effort."""
    failures = sum(row["status"] != "ok" for row in rows)
    saturation = float(np.mean([float(row["time_saturated"]) / t_final for row in rows]))
    peaks = [
        max(float(row[f"max_abs_{name}"]) for name in inputs)
        for row in rows
        if row["status"] == "ok"
    ]
    effort = float(np.quantile(peaks, 0.95, method="inverted_cdf")) if peaks else math.nan
    return Measured(score(requirements, rows, t_final, inputs), failures, saturation, effort)


def best(evaluations: Sequence[Evaluation]) -> Evaluation:
    """The evaluation of least value (feasible before infeasible); the earliest on a tie."""
    return min(evaluations, key=lambda e: (e.score.value, e.index))


#: Sweeps a generation: the candidates, then ``done(position, rows)`` as each completes.
Sweeper = Callable[[Sequence[Candidate], Callable[[int, list[dict[str, Any]]], None]], None]


class Search:
    """A search of ``budget`` candidates beyond the spec's own gains.

    Parameters
    ----------
    space : Space
        The box the optimiser searches and its map to gains.
    requirements : Requirements
        The objective and constraints that score a candidate.
    optimizer : Optimizer
        Asked for points, told their values (a new one, of the search's seed).
    budget : int
        Candidates to evaluate (``--evaluations``), the spec's gains not counted.
    t_final : float
        The horizon (the saturation's fraction is of it).
    inputs : sequence of str
        The plant's inputs (their peaks are columns of the rows).
    history : sequence of Evaluation
        The evaluations of an earlier, interrupted run (``--resume``), in index order.
    """

    def __init__(
        self,
        space: Space,
        requirements: Requirements,
        optimizer: Optimizer,
        budget: int,
        t_final: float,
        inputs: Sequence[str],
        history: Sequence[Evaluation] = (),
    ) -> None:
        self.space = space
        self.requirements = requirements
        self.optimizer = optimizer
        self.budget = budget
        self.t_final = t_final
        self.inputs = tuple(inputs)
        self.evaluations: list[Evaluation] = list(history)

    @property
    def searched(self) -> int:
        """Candidates of the optimiser evaluated so far."""
        return sum(e.generation != ORIGINAL for e in self.evaluations)

    @property
    def original(self) -> Evaluation | None:
        """The evaluation of the spec's own gains, once made."""
        return next((e for e in self.evaluations if e.generation == ORIGINAL), None)

    def evaluate_original(
        self, original: Candidate, sweep: Sweeper, on_evaluation: Callable[[Evaluation], None]
    ) -> Evaluation:
        """Sweep the spec's own gains (evaluation 0), unless the history has them."""
        if self.original is None:
            x0 = tuple(float(v) for v in self.space.encode(original))
            self._sweep(ORIGINAL, 0, [x0], [original], [0], sweep, on_evaluation)
        assert self.original is not None
        return self.original

    def with_requirements(self, requirements: Requirements) -> None:
        """Score by ``requirements`` from now on: a constraint added after the spec's gains.

        The caller keeps the recorded scores comparable: a new search adds the constraint
        before its first generation (the spec's own evaluation extended by hand, its
        gains meeting a bound taken from them), a resumed one adds it again as recorded.
        """
        self.requirements = requirements

    def run(
        self,
        original: Candidate,
        sweep: Sweeper,
        on_evaluation: Callable[[Evaluation], None],
        on_generation: Callable[[], None] | None = None,
    ) -> Evaluation:
        """Evaluate the spec's gains, then generations until the budget; the best.

        ``on_evaluation`` is told each evaluation as it completes (in completion order;
        :attr:`evaluations` keeps index order), ``on_generation`` after each generation.
        """
        self.evaluate_original(original, sweep, on_evaluation)
        recorded: dict[int, dict[int, Evaluation]] = {}
        for e in self.evaluations:
            if e.generation != ORIGINAL:
                recorded.setdefault(e.generation, {})[e.position] = e
        generation, offset = 0, 1
        while True:
            done = recorded.get(generation, {})
            left = self.budget - (self.searched - len(done))
            if left <= 0:
                break
            asked = [np.asarray(x, dtype=float) for x in self.optimizer.ask()]
            for position, e in done.items():
                if (
                    position >= len(asked)
                    or e.index != offset + position
                    or not np.allclose(asked[position], e.x, rtol=0.0, atol=REPLAY_TOLERANCE)
                ):
                    raise ReplayError(
                        f"the optimiser asked another point than the record's (generation "
                        f"{generation}, candidate {position}): the record is not this search's"
                    )
            positions = [p for p in range(min(len(asked), left)) if p not in done]
            xs = [tuple(float(v) for v in asked[p]) for p in positions]
            candidates = [self.space.decode(np.array(x)) for x in xs]
            self._sweep(generation, offset, xs, candidates, positions, sweep, on_evaluation)
            if len(asked) > left:
                break  # the budget ends within this generation: nothing more to tell
            values = {
                e.position: e.score.value for e in self.evaluations if e.generation == generation
            }
            self.optimizer.tell(asked, [values[p] for p in range(len(asked))])
            if on_generation is not None:
                on_generation()
            generation, offset = generation + 1, offset + len(asked)
        return best(self.evaluations)

    def _sweep(
        self,
        generation: int,
        offset: int,
        xs: Sequence[tuple[float, ...]],
        candidates: Sequence[Candidate],
        positions: Sequence[int],
        sweep: Sweeper,
        on_evaluation: Callable[[Evaluation], None],
    ) -> None:
        # Common random numbers make a candidate's sweep a function of its gains: one
        # asked again (CMA-ES's steps shrink below the 4 digits the gains are rounded to)
        # is scored from its first sweep, not run again.
        earlier = {e.candidate: e for e in self.evaluations}
        first: dict[Candidate, int] = {}
        for i, candidate in enumerate(candidates):
            first.setdefault(candidate, i)

        def record(i: int, source: Evaluation | None, rows: list[dict[str, Any]]) -> None:
            if source is None:
                found = measure(self.requirements, rows, self.t_final, self.inputs)
                fields: dict[str, Any] = {
                    "score": found.score,
                    "failures": found.failures,
                    "runs": len(rows),
                    "saturation": found.saturation,
                    "effort": found.effort,
                }
            else:
                fields = {
                    "score": source.score,
                    "failures": source.failures,
                    "runs": source.runs,
                    "saturation": source.saturation,
                    "effort": source.effort,
                }
            evaluation = Evaluation(
                index=offset + positions[i],
                generation=generation,
                position=positions[i],
                x=xs[i],
                candidate=candidates[i],
                **fields,
            )
            self.evaluations.append(evaluation)
            on_evaluation(evaluation)

        for i, candidate in enumerate(candidates):
            if candidate in earlier:
                record(i, earlier[candidate], [])
        new = [i for i, c in enumerate(candidates) if c not in earlier and first[c] == i]

        def done(j: int, rows: list[dict[str, Any]]) -> None:
            i = new[j]
            record(i, None, rows)
            swept = self.evaluations[-1]
            for twin in range(i + 1, len(candidates)):
                if candidates[twin] == candidates[i]:
                    record(twin, swept, [])

        sweep([candidates[i] for i in new], done)
        self.evaluations.sort(key=lambda e: e.index)
