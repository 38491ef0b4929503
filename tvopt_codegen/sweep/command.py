"""The ``sweep`` command: check everything, run on Dask, write the outcome (through emit).

Every check that can fail on the user's input (options, names, distributions, the
output folder, the compiler, the scheduler) runs before the first file is written; a
sweep stopped by Ctrl-C stops its workers and still writes the samples that finished.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

from tvopt_codegen.errors import EXIT_INTERRUPTED, OutputError, SpecError

if TYPE_CHECKING:
    from tvopt_codegen.derivation import Derivation
    from tvopt_codegen.ir import KernelSet

#: The worst samples drawn in ``sweep_worst`` (rerun locally with their trajectories).
WORST = 5


class _Progress:
    """Samples done, failures and the rate on stderr: one updating line on a terminal."""

    def __init__(self, mode: str, total: int) -> None:
        tty = sys.stderr.isatty()
        self.enabled = mode == "always" or (mode == "auto" and tty)
        self.tty = tty
        self.total = total
        self.last = 0.0

    def __call__(self, done: int, failed: int, rate: float) -> None:
        now = time.perf_counter()
        if not self.enabled or (done < self.total and now - self.last < (0.2 if self.tty else 2)):
            return
        self.last = now
        line = f"  sweep: {done}/{self.total} samples, {failed} failed, {rate:.1f} samples/s"
        print(line, end="\r" if self.tty else "\n", file=sys.stderr, flush=True)

    def close(self) -> None:
        if self.enabled and self.tty:
            print(file=sys.stderr, flush=True)


def _options(args: argparse.Namespace, program: Any, horizon: float) -> Any:
    from tvopt_codegen.sweep import (  # noqa: PLC0415
        SweepOptions,
        check_options,
        parse_assignments,
        parse_limits,
    )

    options = SweepOptions(
        samples=args.samples,
        seed=args.seed,
        t_final=horizon if args.t_final is None else args.t_final,
        initial=parse_assignments(args.initial, "--initial", program.state_names, "state"),
        params=parse_assignments(args.param, "--param", program.param_names, "parameter"),
        plant_params=parse_assignments(
            args.plant_param, "--plant-param", program.param_names, "parameter"
        ),
        # The plant's actuators: --saturation, else the spec's [limits].
        limits=parse_limits(args.saturation, program.input_names) or program.limits,
        noise=args.noise,
        sample_time=args.sample_time,
        rtol=args.rtol,
        atol=args.atol,
        points=args.points,
    )
    check_options(program, options)
    if args.chunk_size is not None and not 1 <= args.chunk_size <= options.samples:
        raise SpecError("command line", "--chunk-size", "must be between 1 and --samples")
    return options


def _check_folder(args: argparse.Namespace) -> Path:
    """The output folder may be used: no earlier sweep in it unless --force; never a store."""
    from tvopt_codegen.emit import prepare_folder  # noqa: PLC0415
    from tvopt_codegen.sweep import RECORD  # noqa: PLC0415

    folder = prepare_folder(args.out, create=False)
    if (folder / RECORD).exists() and not args.force:
        raise OutputError(
            f"{folder}: already holds a sweep ({RECORD}); choose another --out, or --force "
            "to replace its files"
        )
    if args.trajectories and (folder / "trajectories.zarr").exists():
        raise OutputError(
            f"{folder / 'trajectories.zarr'}: already exists; move it away or choose another --out"
        )
    return folder


def sweep(
    args: argparse.Namespace,
    derive: Callable[[argparse.Namespace], tuple[Derivation, KernelSet]],
) -> int:
    """Run ``tvopt-codegen sweep SPEC ...``; returns the exit code."""
    from tvopt_codegen.emit import TrajectoryStore, prepare_folder, write_files  # noqa: PLC0415
    from tvopt_codegen.spec import read_spec_bytes  # noqa: PLC0415
    from tvopt_codegen.sweep import (  # noqa: PLC0415
        connect,
        default_chunk,
        loop_for,
        run_sample,
        run_sweep,
        summarize,
        sweep_program,
        trajectory_block,
        trajectory_layout,
    )

    if args.spec is None:
        raise SpecError("command line", "SPEC", "sweep needs a spec (or --replay DIR SAMPLE_ID)")
    if args.samples is None:
        raise SpecError("command line", "--samples", "is required")
    if args.samples < 1:
        raise SpecError("command line", "--samples", f"must be positive, got {args.samples}")
    if args.workers is not None and not 1 <= args.workers <= 1024:
        raise SpecError("command line", "--workers", "must be between 1 and 1024")
    _source, raw = read_spec_bytes(args.spec)
    derivation, kernels = derive(args)
    program = sweep_program(kernels)
    options = _options(args, program, derivation.spec.t_final)
    folder = _check_folder(args)
    loop_for(program)  # a compiler error stops here, before any worker starts
    client, cluster = connect(args.workers, args.scheduler)
    try:
        workers = len(client.scheduler_info().get("workers", {})) or 1
        chunk = args.chunk_size or default_chunk(options.samples, workers)
        prepare_folder(folder)
        store = None
        if args.trajectories:
            variables, coords, attrs = trajectory_layout(program, options, chunk)
            store = TrajectoryStore(folder / "trajectories.zarr", variables, coords, attrs)
        dashboard = getattr(client, "dashboard_link", "")
        print(
            f"sweep: {options.samples} samples of {program.name} on {workers} worker"
            f"{'s' if workers != 1 else ''}" + (f"; dashboard {dashboard}" if dashboard else ""),
            file=sys.stderr,
            flush=True,
        )

        def keep(results: list[Any]) -> None:
            if store is not None and results:
                store.write(int(results[0].row["sample"]), trajectory_block(program, results))

        progress = _Progress(args.progress, options.samples)
        try:
            run = run_sweep(
                client,
                program,
                options,
                chunk=chunk,
                keep=store is not None,
                on_results=keep,
                progress=progress,
            )
        finally:
            progress.close()
    finally:
        client.close()
        if cluster is not None:
            cluster.close()
    summary = summarize(run.results, options.samples, run.interrupted, WORST)
    worst = {
        index: run_sample(program, options, index, keep=True).trajectory
        for index, _ in summary.worst
    }
    from tvopt_codegen.artifacts import sweep_files  # noqa: PLC0415 - matplotlib on use

    files = sweep_files(
        program,
        options,
        f"{derivation.spec.name}.toml",
        raw.decode("utf-8"),
        args.extension,
        run,
        summary,
        {i: t for i, t in worst.items() if t is not None},
    )
    write_files(files, folder, force=True)
    print(files["summary.md"].decode().rstrip())
    print(
        f"\n{len(run.results)} samples in {run.seconds:.2f} s "
        f"({len(run.results) / max(run.seconds, 1e-9):.1f} samples/s on {run.workers} workers)"
    )
    for name in sorted(files) + (["trajectories.zarr"] if args.trajectories else []):
        print(f"  wrote {str(folder).rstrip('/')}/{name}")
    if run.interrupted:
        print(
            f"tvopt-codegen: interrupted; kept the {len(run.results)} samples that finished",
            file=sys.stderr,
        )
        return EXIT_INTERRUPTED
    return 0


def _same(a: Any, b: Any) -> bool:
    """Equal, NaN equal to NaN (a failed sample's errors)."""
    if isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b):
        return True
    return bool(a == b)


def replay(args: argparse.Namespace) -> int:
    """Run ``tvopt-codegen sweep --replay DIR SAMPLE_ID --out DIR2``."""
    import json  # noqa: PLC0415

    from tvopt_codegen.derivation import derive  # noqa: PLC0415
    from tvopt_codegen.emit import prepare_folder, read_regular_file, write_files  # noqa: PLC0415
    from tvopt_codegen.ir import lower  # noqa: PLC0415
    from tvopt_codegen.spec import parse_spec  # noqa: PLC0415
    from tvopt_codegen.sweep import (  # noqa: PLC0415
        RECORD,
        SweepOptions,
        read_summary,
        run_sample,
        sweep_program,
    )

    if args.spec is not None:
        raise SpecError("command line", "--replay", "takes no SPEC (the sweep's copy is used)")
    where, text = args.replay
    folder = Path(where)
    try:
        index = int(text)
    except ValueError:
        raise SpecError(
            "command line", "--replay", f"SAMPLE_ID must be an integer, got {text!r}"
        ) from None
    raw = read_regular_file(folder / RECORD, 1 << 20)
    if raw is None:
        raise SpecError(str(folder), RECORD, "not found: DIR is not a sweep's output folder")
    try:
        record = json.loads(raw)
        options = SweepOptions.from_dict(record["options"])
        spec_name = str(record["spec"])
    except (ValueError, KeyError, TypeError) as exc:
        raise SpecError(str(folder / RECORD), "options", f"unreadable: {exc}") from None
    if not 0 <= index < options.samples:
        raise SpecError(
            "command line", "--replay", f"sample {index} is not in 0 .. {options.samples - 1}"
        )
    spec_bytes = read_regular_file(folder / spec_name, 1 << 22)
    if spec_bytes is None:
        raise SpecError(str(folder), spec_name, "the sweep's copy of its spec is missing")
    prepare_folder(args.out, create=False)
    spec = parse_spec(str(folder / spec_name), spec_bytes)
    if record.get("extension") == "auto":
        import dataclasses  # noqa: PLC0415

        spec = dataclasses.replace(spec, extension=(), extension_auto=True)
    program = sweep_program(lower(derive(spec)))
    if program.key != record.get("loop"):
        print(
            "tvopt-codegen: warning: this tvopt-codegen builds another loop than the sweep's "
            "(another version?); the replayed numbers may differ",
            file=sys.stderr,
        )
    result = run_sample(program, options, index, keep=True)
    from tvopt_codegen.artifacts import replay_files  # noqa: PLC0415 - matplotlib on use

    files = replay_files(program, result)
    write_files(files, args.out, force=args.force)
    rows = {int(r["sample"]): r for r in read_summary(str(folder / "summary.parquet"))}
    stored = rows.get(index)
    for key in ("status", "final_error", "max_error", "seed"):
        print(f"  {key}: {result.row[key]}")
    if stored is not None:
        same = all(_same(stored.get(key), value) for key, value in result.row.items())
        print(f"  the sweep's row {'matches' if same else 'DIFFERS from'} this run")
    for name in files:
        print(f"  wrote {args.out.rstrip('/')}/{name}")
    return 0
