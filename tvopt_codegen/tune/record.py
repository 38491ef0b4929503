"""A tune's record, ``tune.json``: written after every generation, trusted by nothing.

What a tune writes of itself (:func:`record_bytes`: strict JSON, in the options' order)
and the checks ``--resume`` makes of what it reads back (:func:`check_recorded`,
:func:`check_history`), all before the folder is locked or written: a record edited by
hand, cut short or from another search is one line naming the record and its field.
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from tvopt_codegen.errors import SpecError
from tvopt_codegen.tune.problem import METHODS, Problem, optimizer_for
from tvopt_codegen.tune.session import ORIGINAL, Evaluation, ReplayError
from tvopt_codegen.tune.settings import Settings

#: The search's record in its folder.
RECORD = "tune.json"
#: The most candidates a tune takes.
MAX_EVALUATIONS = 100_000


def record_bytes(record: dict[str, Any]) -> bytes:
    """``tune.json``'s bytes."""
    # Not sorted: the order of --plant-param and the others is the order of the draws.
    # Strict JSON (no NaN or Infinity tokens, which other readers refuse): a fresh check
    # whose every sample failed has an infinite objective and no input effort.
    return (json.dumps(strict_json(record), indent=1, allow_nan=False) + "\n").encode()


def strict_json(value: Any) -> Any:
    """``value`` with every non-finite float written as its text (``"inf"``, ``"nan"``)."""
    if isinstance(value, float) and not math.isfinite(value):
        return repr(value)
    if isinstance(value, dict):
        return {k: strict_json(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [strict_json(v) for v in value]
    return value


def check_recorded(settings: Settings, where: str) -> None:
    """A recorded tune's settings within the bounds its command line had (``--resume``).

    A record edited by hand could otherwise ask for 10^12 candidates or a method that
    does not exist; the requirements' grammar and the space's bounds are checked when
    the problem is built, and their errors are turned into the record's.
    """
    from tvopt_codegen.sweep import MAX_SAMPLES  # noqa: PLC0415 - the sweep on use

    def fail(key: str, problem: str) -> SpecError:
        return SpecError(where, f"settings.{key}", problem)

    for key, high in (
        ("evaluations", MAX_EVALUATIONS),
        ("samples", MAX_SAMPLES),
        ("check_samples", MAX_SAMPLES),
    ):
        if not 1 <= getattr(settings, key) <= high:
            raise fail(key, f"must be between 1 and {high}")
    for key in ("seed", "check_seed"):
        if not 0 <= getattr(settings, key) <= 2**63 - 1:
            raise fail(key, "must be between 0 and 2**63 - 1")
    if settings.check_seed == settings.seed:
        raise fail("check_seed", "is the search's seed: the check's samples would not be fresh")
    if settings.method not in METHODS:
        raise fail("method", f"expected one of {', '.join(METHODS)}, got {settings.method!r}")
    if settings.population is not None and not 2 <= settings.population <= 1000:
        raise fail("population", "must be between 2 and 1000")
    if settings.complex_pairs is not None and settings.complex_pairs < 0:
        raise fail("complex_pairs", "must be zero or positive")
    if settings.after is not None and not (math.isfinite(settings.after) and settings.after >= 0):
        raise fail("after", "must be zero or positive and finite")
    if settings.min_damping is not None and not (
        math.isfinite(settings.min_damping) and 0 < settings.min_damping <= 1
    ):
        raise fail("min_damping", "must be in (0, 1]")
    for key in ("pole_range", "bandwidth_range"):
        bounds = getattr(settings, key)
        if bounds is not None and not (
            all(math.isfinite(b) for b in bounds) and 0 < bounds[0] < bounds[1]
        ):
            raise fail(key, "expected 0 < lo < hi, both finite")


def check_history(problem: Problem, history: Sequence[Evaluation], where: str) -> None:
    """The recorded evaluations are the ones this search made, in its order.

    Each is where the search put it (index, generation, position in the optimiser's
    batches), its candidate is the decoding of its point (so inside the Hurwitz region
    of the space, never poles typed into the record), its scores are numbers a sweep
    gives, and a dry replay of the optimiser asks the same points: a record that is
    not this search's is refused before anything runs or is written.
    """
    samples = problem.settings.samples
    population = optimizer_for(problem).population
    # Every generation before the last recorded one is whole; the last may have been cut
    # with any of its candidates done (a cluster finishes them out of order).
    last = max((e.generation for e in history), default=ORIGINAL)
    whole = 1 + population * max(last, 0) if last >= 0 else 1
    for i, e in enumerate(history):

        def fail(problem_text: str, i: int = i) -> SpecError:
            return SpecError(where, f"evaluations[{i}]", problem_text)

        if i < whole and e.index != i:
            raise fail(f"index {e.index}, expected {i} (the evaluations in order, no gaps)")
        if i >= whole and (e.generation != last or e.index <= history[i - 1].index):
            raise fail(
                f"index {e.index}: after the whole generations, only the last one's "
                "candidates, in increasing order"
            )
        if i == 0:
            if (e.generation, e.position) != (ORIGINAL, 0) or e.candidate != problem.original:
                raise fail("the first evaluation must be the spec's own gains")
        else:
            if e.generation < 0 or not 0 <= e.position < population:
                raise fail(f"generation {e.generation}, position {e.position}: not this search's")
            if e.index != 1 + e.generation * population + e.position:
                raise fail(
                    f"index {e.index} is not generation {e.generation}'s candidate "
                    f"{e.position} (population {population})"
                )
            point = np.asarray(e.x, dtype=float)
            if (
                point.shape != (problem.space.dimension,)
                or not np.all(np.isfinite(point))
                or np.any(point < 0)
                or np.any(point > 1)
            ):
                raise fail("its point is not in the search's box [0, 1]^d")
            if problem.space.decode(point) != e.candidate:
                raise fail("its poles and bandwidth are not its point's (edited by hand?)")
        if not (0 <= e.failures <= e.runs == samples):
            raise fail(f"failures {e.failures} of {e.runs} runs: expected runs = {samples}")
        numbers = (e.score.value, *(bound for _, _, bound in e.score.constraints))
        if not all(math.isfinite(v) for v in numbers) or math.isnan(e.score.objective):
            raise fail("its score is not a number a sweep gives")
    if len(history) - 1 > problem.settings.evaluations:
        raise SpecError(
            where, "evaluations", f"more than the tune's {problem.settings.evaluations} candidates"
        )

    class _RecordEndError(Exception):
        """The replay reached a candidate the record lacks: the rest is the resume's."""

    def no_sweep(candidates: Sequence[Any], _done: Any) -> None:
        if candidates:
            raise _RecordEndError

    search = problem.search(history)
    if not history:
        return
    try:
        search.run(problem.original, no_sweep, lambda _e: None)
    except _RecordEndError:
        pass
    except ReplayError as exc:
        raise SpecError(where, "evaluations", str(exc)) from None
