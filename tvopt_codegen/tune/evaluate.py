"""Candidates' sweeps: every sample of every candidate of a generation, on Dask at once.

A candidate is the spec's compiled loop with other gains
(:meth:`~tvopt_codegen.sweep.program.SweepProgram.with_gains`): the same C library, the
same samples (common random numbers: sample ``i`` draws the same plant, initial state
and noise for every candidate), so that two candidates differ by their gains alone.
The generation's chunks go to the cluster together, a few ahead per worker; a worker
receives the loop's sources once (scattered) and, per chunk, only the gains' fields.
"""

from __future__ import annotations

import dataclasses
import math
import weakref
from collections.abc import Callable, Iterator, Mapping, Sequence
from typing import TYPE_CHECKING, Any

from tvopt_codegen.sweep.driver import (
    LOOKAHEAD_PER_WORKER,
    InlineClient,
    chunks,
    distributed_module,
)
from tvopt_codegen.sweep.options import SweepOptions
from tvopt_codegen.sweep.program import SweepProgram
from tvopt_codegen.sweep.sample import run_chunk
from tvopt_codegen.tune.requirements import failure_bound, statistic
from tvopt_codegen.tune.session import Evaluation, measure

if TYPE_CHECKING:
    from tvopt_codegen.tune.problem import Problem

#: The columns of a sample's row the tuner keeps (the rest stay on the worker).
KEPT = (
    "sample",
    "status",
    "final_error",
    "max_error",
    "integrated_error",
    "max_error_after",
    "time_saturated",
)

#: The program's fields that carry no gain: the loop's sources and their hash.
_SHARED = frozenset({"sources", "key"})


def gain_fields(program: SweepProgram) -> dict[str, Any]:
    """Every field of ``program`` but its sources: what a worker needs beside them."""
    return {
        f.name: getattr(program, f.name)
        for f in dataclasses.fields(program)
        if f.name not in _SHARED
    }


def _kept(row: Mapping[str, Any], inputs: Sequence[str]) -> dict[str, Any]:
    keep = (*KEPT, *(f"max_abs_{name}" for name in inputs))
    return {name: row.get(name) for name in keep}


def candidate_chunk(
    base: SweepProgram,
    fields: Mapping[str, Any],
    options: SweepOptions,
    indices: Sequence[int],
) -> list[dict[str, Any]]:
    """Run samples ``indices`` of the candidate ``base`` with ``fields`` (a Dask task).

    Returns only the columns the requirements read (:data:`KEPT` and each input's peak),
    so that a generation's results cost the client little.
    """
    program = dataclasses.replace(base, **fields)
    results = run_chunk(program, options, list(indices), keep=False)
    return [_kept(r.row, program.input_names) for r in results]


def chunk_size(samples: int, candidates: int, workers: int) -> int:
    """Samples per task: whole candidates when they alone keep the workers busy.

    A generation of fewer candidates than twice the workers splits each candidate's
    samples so that no worker idles for lack of a task while the last ones finish.
    """
    pieces = max(1, math.ceil(2 * workers / max(1, candidates)))
    return max(1, math.ceil(samples / pieces))


def evaluate(
    client: Any,
    programs: Sequence[SweepProgram],
    options: SweepOptions,
    on_candidate: Callable[[int, list[dict[str, Any]]], None],
) -> None:
    """Run every sample of every program; ``on_candidate(i, rows)`` as each completes.

    Parameters
    ----------
    client : distributed.Client or InlineClient
        Where to run (the sweep's :func:`~tvopt_codegen.sweep.driver.connect`).
    programs : sequence of SweepProgram
        The candidates: one base program with other gains (the same ``key``).
    options : SweepOptions
        The samples (every candidate runs all of them).
    on_candidate : callable
        Told each candidate's rows, in sample order, as soon as its last chunk is in
        (so that an interruption keeps every candidate already complete).
    """
    if not programs:
        return
    workers = len(client.scheduler_info().get("workers", {})) or 1
    size = chunk_size(options.samples, len(programs), workers)
    pieces = [(i, piece) for i in range(len(programs)) for piece in chunks(options.samples, size)]
    expected = {i: 0 for i in range(len(programs))}
    for i, piece in pieces:
        expected[i] += len(piece)
    rows: dict[int, list[dict[str, Any]]] = {i: [] for i in range(len(programs))}
    for i, found in _finished(client, programs, options, pieces, workers):
        rows[i].extend(found)
        if len(rows[i]) == expected[i]:
            ordered = sorted(rows.pop(i), key=lambda row: int(row["sample"]))
            on_candidate(i, ordered)


#: Each client's scattered loop, by its key: the sources reach the workers once a tune.
_SCATTERED: weakref.WeakKeyDictionary[Any, dict[str, Any]] = weakref.WeakKeyDictionary()


def _scattered(client: Any, program: SweepProgram) -> Any:
    """``program`` on every worker of ``client``'s cluster, scattered once per client."""
    held = _SCATTERED.setdefault(client, {})
    if program.key not in held:
        held[program.key] = client.scatter(program, broadcast=True, hash=False)
    return held[program.key]


def _finished(
    client: Any,
    programs: Sequence[SweepProgram],
    options: SweepOptions,
    pieces: Sequence[tuple[int, range]],
    workers: int,
) -> Iterator[tuple[int, list[dict[str, Any]]]]:
    """Each chunk's rows as it finishes, here or on the cluster (a few ahead per worker)."""
    if isinstance(client, InlineClient):
        for i, piece in pieces:
            yield i, candidate_chunk(programs[i], {}, options, piece)
        return
    cluster = distributed_module()
    base = _scattered(client, programs[0])
    fields = [gain_fields(p) for p in programs]
    todo = iter(pieces)
    owner: dict[Any, int] = {}

    def submit() -> Any | None:
        item = next(todo, None)
        if item is None:
            return None
        i, piece = item
        future = client.submit(candidate_chunk, base, fields[i], options, list(piece), pure=False)
        owner[future] = i
        return future

    first = [f for f in (submit() for _ in range(LOOKAHEAD_PER_WORKER * workers)) if f]
    queue = cluster.as_completed(first)
    try:
        for future in queue:
            found = future.result()
            i = owner.pop(future)
            future.release()
            more = submit()
            if more is not None:
                queue.add(more)
            yield i, found
    finally:
        if owner:
            client.cancel(list(owner))


def fresh_check(
    client: Any, problem: Problem, original: Evaluation, chosen: Evaluation
) -> dict[str, Any]:
    """The spec's gains and the chosen ones on fresh samples (another seed), side by side.

    The search chose among candidates by their scores on its own samples, so that the
    best of many is favoured by its samples' luck; these samples have never been seen
    (``--check-seed`` is never the search's seed).
    """
    options = problem.check
    programs = [problem.program_for(e.candidate) for e in (original, chosen)]
    rows: dict[int, list[dict[str, Any]]] = {}
    evaluate(client, programs, options, rows.__setitem__)
    inputs = problem.program.input_names
    result: dict[str, Any] = {"samples": options.samples, "seed": options.seed}
    for key, i in (("original", 0), ("tuned", 1)):
        found = measure(problem.requirements, rows[i], options.t_final, inputs)
        finals = [_measured(row["final_error"]) for row in rows[i]]
        result[key] = {
            "objective": found.score.objective,
            "constraints": [list(c) for c in found.score.constraints],
            "feasible": found.score.feasible,
            "failures": found.failures,
            "failure_bound": failure_bound(rows[i]),
            "saturation": found.saturation,
            "effort": found.effort,
            "p95_final_error": statistic(finals, "p95"),
            "median_final_error": statistic(finals, "median"),
        }
    return result


def _measured(value: Any) -> float:
    """A sample's final error; a failed sample's (NaN) counts as infinite."""
    return math.inf if value is None or math.isnan(value) else float(value)
