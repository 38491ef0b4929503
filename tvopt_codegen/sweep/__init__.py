"""Monte-Carlo robustness sweeps: thousands of closed loops, each with its own plant.

A sweep draws, for every sample, an initial state, the controller's (model's)
parameters and the true plant's parameters from the distributions the user names; runs
the closed loop in compiled C (``templates/c/sweep.c.jinja``: the true plant under the
law, inputs clipped to their limits, optionally sampled every ``H`` seconds with noisy
measurements, integrated by Dormand-Prince RK45 with scipy's error control, then
``y*(t)`` by the Newton method of :mod:`tvopt_codegen.simulation`); and tabulates each
run's outcome. Samples are spread over a Dask cluster in chunks; a worker builds (or
finds in its cache) the compiled loop from the sources' hash and never receives a
ctypes handle.

Sample ``i`` draws from ``numpy.random.default_rng(seed_i)``, where ``seed_i`` is the
first 64-bit word of ``SeedSequence(seed, spawn_key=(i,))`` (the sweep's ``i``-th
child) shifted right by one bit; ``seed_i`` is stored with the sample, so any sample
can be rerun alone, and the table is the same bit for bit whatever the number of
workers or the chunk size.

Nothing here writes files: :mod:`tvopt_codegen.emit` does.
"""

from __future__ import annotations

from tvopt_codegen.limits import MAX_POINTS
from tvopt_codegen.sweep.driver import (
    LOOKAHEAD_PER_WORKER,
    SAMPLES_PER_LOCAL_WORKER,
    SCHEDULER_TIMEOUT,
    InlineClient,
    SweepRun,
    check_scheduler,
    check_workers,
    chunks,
    connect,
    default_chunk,
    local_workers,
    max_local_workers,
    run_sweep,
)
from tvopt_codegen.sweep.options import (
    DISTRIBUTIONS,
    DIVERGENCE_FACTOR,
    MAX_SAMPLES,
    SETTLING,
    Distribution,
    LoopOutcome,
    Outcome,
    SweepOptions,
    outcome_of,
    parse_assignments,
    parse_distribution,
    parse_limits,
)
from tvopt_codegen.sweep.program import (
    TAIL,
    Draw,
    Loop,
    SweepProgram,
    check_options,
    draw,
    loop_for,
    sample_seed,
    sweep_program,
    tail,
)
from tvopt_codegen.sweep.results import (
    RECORD,
    Summary,
    Tally,
    clopper_pearson_upper,
    format_summary,
    record_bytes,
    summarize,
    tally_rows,
    tally_table,
    trajectory_block,
    trajectory_layout,
)
from tvopt_codegen.sweep.sample import SampleResult, nominal_start, run_chunk, run_sample
from tvopt_codegen.sweep.table import (
    ERROR_STATUS,
    IDENTITY_KEYS,
    PART_ROWS,
    RANGES_KEY,
    TABLE_ROW_GROUP,
    Piece,
    failed_row,
    index_parts,
    missing,
    read_row,
    read_summary,
    record_batch,
    row_columns,
    row_schema,
    sweep_identity,
    with_identity,
    write_part,
    write_table,
)

__all__ = [
    "SampleResult",
    "nominal_start",
    "run_chunk",
    "run_sample",
    "DISTRIBUTIONS",
    "DIVERGENCE_FACTOR",
    "Distribution",
    "Draw",
    "ERROR_STATUS",
    "IDENTITY_KEYS",
    "LOOKAHEAD_PER_WORKER",
    "Loop",
    "LoopOutcome",
    "MAX_POINTS",
    "MAX_SAMPLES",
    "Outcome",
    "PART_ROWS",
    "RANGES_KEY",
    "Piece",
    "RECORD",
    "SAMPLES_PER_LOCAL_WORKER",
    "SCHEDULER_TIMEOUT",
    "SETTLING",
    "Summary",
    "SweepOptions",
    "SweepProgram",
    "InlineClient",
    "SweepRun",
    "TABLE_ROW_GROUP",
    "TAIL",
    "check_options",
    "check_scheduler",
    "check_workers",
    "chunks",
    "clopper_pearson_upper",
    "connect",
    "default_chunk",
    "draw",
    "failed_row",
    "format_summary",
    "index_parts",
    "loop_for",
    "local_workers",
    "max_local_workers",
    "missing",
    "outcome_of",
    "parse_assignments",
    "parse_distribution",
    "parse_limits",
    "read_row",
    "read_summary",
    "record_batch",
    "record_bytes",
    "row_columns",
    "row_schema",
    "run_sweep",
    "sample_seed",
    "summarize",
    "Tally",
    "tally_rows",
    "tally_table",
    "sweep_identity",
    "sweep_program",
    "with_identity",
    "tail",
    "trajectory_block",
    "trajectory_layout",
    "write_part",
    "write_table",
]
