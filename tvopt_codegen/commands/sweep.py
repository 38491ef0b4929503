"""``tvopt-codegen sweep``: check everything, run on Dask, write the outcome (through emit).

Every check that can fail on the user's input (options, names, distributions, the
output folder, the compiler, the scheduler) runs before the first file is written; a
sweep stopped by Ctrl-C stops its workers and still writes the samples that finished.
"""

from __future__ import annotations

import argparse
import math
import signal
import sys
import time
from pathlib import Path
from typing import Any

from tvopt_codegen.commands import common, plant, run_options
from tvopt_codegen.errors import (
    EXIT_INTERRUPTED,
    EXIT_TERMINATED,
    OutputError,
    SpecError,
    Terminated,
    signal_raised,
)
from tvopt_codegen.limits import RUN_OPTIONS

HELP = "Monte-Carlo closed loops with model mismatch, saturation and noise, on Dask"

#: In a log, seconds to the first progress line, then between lines.
LOG_FIRST = 10.0
LOG_EVERY = 60.0

#: The worst samples drawn in ``sweep_worst`` (rerun locally with their trajectories).
WORST = 5


def build(parser: argparse.ArgumentParser) -> None:
    """The ``sweep`` command's options."""
    parser.description = (
        "Run SPEC's closed loop for many drawn initial states and parameters "
        "(DIST: a number, normal(mean, sd), uniform(lo, hi) or lognormal(mu, sigma)), in "
        "compiled C on a Dask cluster; write summary.parquet, summary.md and figures to "
        "--out. `sweep --replay DIR SAMPLE_ID --out DIR2` reruns one sample of the sweep "
        "in DIR and writes its whole trajectory; `sweep --resume DIR` runs the samples an "
        "interrupted sweep lacks."
    )
    parser.add_argument("spec", nargs="?", help="spec file, or the name of a bundled example")
    parser.add_argument(
        "--replay",
        nargs=2,
        metavar=("DIR", "SAMPLE_ID"),
        help="rerun sample SAMPLE_ID of the sweep written to DIR (no SPEC)",
    )
    parser.add_argument(
        "--resume",
        metavar="DIR",
        help="complete the interrupted sweep in DIR: run only its missing samples (no SPEC)",
    )
    parser.add_argument("--samples", type=int, help="number of runs")
    run_options.add(parser, "seed")
    parser.add_argument("--out", help="output folder (not with --resume: DIR is the folder)")
    plant.plant_options(parser)
    run_options.add(parser, "precision")
    plant.cluster_options(parser)
    parser.add_argument(
        "--chunk-size", type=int, help="samples per Dask task (default: about 8 tasks a worker)"
    )
    parser.add_argument(
        "--trajectories",
        action="store_true",
        help="also store every run in trajectories.zarr (xarray-readable), as runs finish",
    )
    run_options.add(parser, "checkpoint_seconds")
    plant.job_options(parser, "sweep")


def run(args: argparse.Namespace) -> int:
    """A new sweep, ``--resume DIR`` or ``--replay DIR SAMPLE_ID``."""
    if args.replay and args.resume is not None:
        raise SpecError("command line", "--resume", "cannot be combined with --replay")
    if args.resume is not None:
        if not args.resume.strip():
            raise SpecError("command line", "--resume", "DIR is empty")
        if args.out is not None:
            raise SpecError("command line", "--out", "is DIR itself with --resume")
        return resume(args)
    if args.out is None:
        raise SpecError("command line", "--out", "is required")
    return replay(args) if args.replay else sweep(args)


class _Progress:
    """Samples done, failures and the rate on stderr.

    On a terminal one updating line; in a log (a batch job's, ``--progress auto``) a line
    a minute, the first after :data:`LOG_FIRST` seconds, so that a long job shows it runs
    from its first minute and a short one stays quiet.
    """

    def __init__(self, mode: str, total: int) -> None:
        self.tty = sys.stderr.isatty()
        self.enabled = mode != "never"
        self.log = mode == "auto" and not self.tty
        self.every = LOG_EVERY if self.log else (0.2 if self.tty else 2.0)
        self.total = total
        # The first line at once, or in a log LOG_FIRST seconds after the start.
        self.last = time.perf_counter() - LOG_EVERY + LOG_FIRST if self.log else -math.inf

    def __call__(self, done: int, failed: int, rate: float) -> None:
        now = time.perf_counter()
        finished = done >= self.total
        if not self.enabled or (finished and self.log):
            return  # a log gets the summary next
        if not finished and now - self.last < self.every:
            return
        self.last = now
        line = f"  sweep: {done}/{self.total} samples, {failed} failed, {rate:.1f} samples/s"
        print(line, end="\r" if self.tty else "\n", file=sys.stderr, flush=True)

    def close(self) -> None:
        if self.enabled and self.tty:
            print(file=sys.stderr, flush=True)


def _options(args: argparse.Namespace, program: Any, horizon: float) -> Any:
    options = plant.plant_sweep(args, program, horizon, args.samples, args.seed)
    if args.chunk_size is not None and not 1 <= args.chunk_size <= options.samples:
        raise SpecError("command line", "--chunk-size", "must be between 1 and --samples")
    return options


#: The figures a sweep draws (each as PNG and SVG).
FIGURES = ("sweep_histograms", "sweep_worst")


def _names(spec_name: str) -> list[str]:
    """Every file a sweep writes into its folder (checked before the first sample)."""
    names = ["summary.parquet", "summary.md", "sweep.json", spec_name]
    return names + [f"{stem}.{kind}" for stem in FIGURES for kind in ("png", "svg")]


def _check_earlier(args: argparse.Namespace) -> None:
    """No earlier sweep in --out unless --force (nothing written yet: only looked at)."""
    from tvopt_codegen.emit import SweepFolder, prepare_folder  # noqa: PLC0415
    from tvopt_codegen.sweep import RECORD  # noqa: PLC0415

    folder = prepare_folder(args.out, create=False)
    if (folder / RECORD).exists() and not args.force:
        raise OutputError(
            f"{folder}: already holds a sweep ({RECORD}); `tvopt-codegen sweep --resume "
            f"{folder}` completes an interrupted one; choose another --out, or --force to "
            "replace its files"
        )
    parts = folder / SweepFolder.PARTS
    if parts.exists() and not args.force:
        raise OutputError(
            f"{parts}: already exists (the parts of an interrupted sweep?); choose another "
            "--out, or --force to replace them"
        )
    if args.trajectories and (folder / "trajectories.zarr").exists():
        raise OutputError(
            f"{folder / 'trajectories.zarr'}: already exists; move it away or choose another --out"
        )


class _Parts:
    """The client's buffer of finished chunks, written as a part every few seconds."""

    def __init__(self, folder: Any, schema: Any, store: Any, program: Any, every: float) -> None:
        self.folder, self.schema, self.store, self.program = folder, schema, store, program
        self.every = every
        self.batches: list[Any] = []
        self.rows = 0
        self.last = time.monotonic()

    def add(self, results: list[Any]) -> None:
        from tvopt_codegen.sweep import PART_ROWS, record_batch, trajectory_block  # noqa: PLC0415

        if not results:
            return
        if self.store is not None:
            self.store.write(int(results[0].row["sample"]), trajectory_block(self.program, results))
        self.batches.append(record_batch([r.row for r in results], self.schema))
        self.rows += len(results)
        if self.rows >= PART_ROWS or time.monotonic() - self.last >= self.every:
            self.flush()

    def flush(self) -> None:
        from tvopt_codegen.sweep import write_part  # noqa: PLC0415

        if self.batches:
            batches, schema = self.batches, self.schema
            self.folder.write_part(lambda handle: write_part(handle, batches, schema))
        self.batches, self.rows, self.last = [], 0, time.monotonic()


def _run_and_publish(
    args: argparse.Namespace,
    folder: Any,
    program: Any,
    options: Any,
    record: dict[str, Any],
    ranges: list[range],
    client: Any,
    cluster: Any,
) -> int:
    """Run ``ranges`` (every part flushed, whatever stops it), then publish the outcome."""
    from tvopt_codegen.emit import TrajectoryStore  # noqa: PLC0415
    from tvopt_codegen.sweep import (  # noqa: PLC0415
        default_chunk,
        run_sweep,
        trajectory_layout,
    )

    schema = _schema(program, options, record)
    run = None
    try:
        workers = len(client.scheduler_info().get("workers", {})) or 1
        chunk = args.chunk_size or default_chunk(options.samples, workers)
        store = None
        if record["trajectories"]:
            variables, coords, attrs = trajectory_layout(program, options, chunk)
            store = TrajectoryStore(
                folder.folder / "trajectories.zarr",
                variables,
                coords,
                attrs,
                resume=bool(record.get("resumed")),
            )
        todo = sum(len(r) for r in ranges)
        dashboard = getattr(client, "dashboard_link", "")
        print(
            f"sweep: {todo} samples of {program.name} on {workers} worker"
            f"{'s' if workers != 1 else ''}" + (f"; dashboard {dashboard}" if dashboard else ""),
            file=sys.stderr,
            flush=True,
        )
        parts = _Parts(folder, schema, store, program, args.checkpoint_seconds)
        progress = _Progress(args.progress, todo)
        with _Finishing() as finishing:
            try:
                run = run_sweep(
                    client,
                    program,
                    options,
                    ranges=ranges,
                    chunk=chunk,
                    keep=store is not None,
                    collect=False,
                    on_results=parts.add,
                    progress=progress,
                )
            finally:
                finishing.begin()
                progress.close()
                parts.flush()
                plant.disconnect(client, cluster)
                client = None
            code = _publish(args, folder, program, options, record, schema, run)
    finally:
        if client is not None:
            plant.disconnect(client, cluster)
    if finishing.signal and code == 0:
        stopped = "interrupted" if finishing.signal == signal.SIGINT else "terminated"
        print(
            f"tvopt-codegen: {stopped} while writing the sweep's files; they were finished "
            "first and are complete",
            file=sys.stderr,
        )
        return EXIT_INTERRUPTED if finishing.signal == signal.SIGINT else EXIT_TERMINATED
    return code


class _Finishing:
    """Ctrl-C and SIGTERM stop the samples at once, but not the writing of what finished.

    While the samples run, a signal raises (``run_sweep`` keeps what finished). From
    :meth:`begin` on (the last part, the table, the summary) the first signal is noted
    and the files are finished: a batch system's SIGTERM at the very end of a run would
    otherwise leave the table without its summary. A second signal stops at once (the
    parts stay, for ``--resume``).
    """

    def __init__(self) -> None:
        self.signal = 0
        self.finishing = False
        self.previous: dict[int, Any] = {}

    def __enter__(self) -> _Finishing:
        import threading  # noqa: PLC0415

        if threading.current_thread() is threading.main_thread():
            for number in (signal.SIGINT, signal.SIGTERM):
                self.previous[number] = signal.signal(number, self._handle)
        return self

    def __exit__(self, *exc: object) -> None:
        for number, handler in self.previous.items():
            signal.signal(number, handler)

    def begin(self) -> None:
        """From here on, the first signal is noted rather than raised."""
        self.finishing = True

    def _handle(self, number: int, _frame: object) -> None:
        if self.finishing and not self.signal:
            self.signal = number
            print(
                "tvopt-codegen: finishing the sweep's files (a second signal stops at once)",
                file=sys.stderr,
                flush=True,
            )
            return
        # Remembered, as the command line's own handlers do: compiled code that swallows
        # it does not let the sweep run on (errors.raise_pending_signal).
        signal_raised(KeyboardInterrupt if number == signal.SIGINT else Terminated)


def _publish(
    args: argparse.Namespace,
    folder: Any,
    program: Any,
    options: Any,
    record: dict[str, Any],
    schema: Any,
    run: Any,
) -> int:
    """The table from the parts, its summary and figures; the parts go once all are in."""
    from tvopt_codegen.emit import write_files, write_stream  # noqa: PLC0415
    from tvopt_codegen.sweep import (  # noqa: PLC0415
        index_parts,
        missing,
        run_sample,
        tally_table,
        write_table,
    )

    pieces = index_parts(folder.parts(), schema, options.samples)
    gaps = missing(pieces, options.samples)
    absent = sum(len(g) for g in gaps)
    table = write_stream(
        folder.folder,
        "summary.parquet",
        lambda handle: write_table(handle, pieces, schema),
        force=args.force,
    )
    tally = tally_table(table, WORST)
    summary = tally.summary(options.samples, bool(absent))
    worst = {
        index: run_sample(program, options, index, keep=True).trajectory
        for index, _ in summary.worst
    }
    from tvopt_codegen.runs.artifacts import sweep_files  # noqa: PLC0415 - matplotlib on use

    interrupted = run is not None and run.interrupted
    record |= {
        "state": "interrupted" if absent else "complete",
        "finished": summary.runs,
        "missing": absent,
        "interrupted": bool(absent),
    }
    files = sweep_files(
        program,
        options,
        record,
        summary,
        (tally.values("final_error"), tally.values("settling_1pct")),
        {i: t for i, t in worst.items() if t is not None},
    )
    write_files(files, folder.folder, force=args.force, warn=common.warn)
    if not absent:
        folder.clear_parts()
    print(files["summary.md"].decode().rstrip())
    if run is not None:
        print(
            f"\n{run.done} samples in {run.seconds:.2f} s "
            f"({run.done / max(run.seconds, 1e-9):.1f} samples/s on {run.workers} worker"
            f"{'s' if run.workers != 1 else ''})"
        )
    where = str(folder.folder).rstrip("/")
    for name in sorted([*files, "summary.parquet", record["spec"]]) + (
        ["trajectories.zarr"] if record["trajectories"] else []
    ):
        print(f"  wrote {where}/{name}")
    if absent:
        if interrupted:
            print(
                f"tvopt-codegen: {'terminated' if run.signal == 'SIGTERM' else 'interrupted'}; "
                f"kept the {summary.runs} samples that finished, {absent} missing: "
                f"`tvopt-codegen sweep --resume {where}` runs them",
                file=sys.stderr,
            )
            return EXIT_TERMINATED if run.signal == "SIGTERM" else EXIT_INTERRUPTED
        raise OutputError(f"{where}: {absent} samples are missing after the run")
    return 0


def sweep(args: argparse.Namespace) -> int:
    """Run ``tvopt-codegen sweep SPEC ...``; returns the exit code."""
    from tvopt_codegen.emit import SweepFolder, write_files  # noqa: PLC0415
    from tvopt_codegen.spec import read_spec_bytes  # noqa: PLC0415
    from tvopt_codegen.sweep import (  # noqa: PLC0415
        RECORD,
        check_workers,
        connect,
        loop_for,
        record_bytes,
        sweep_program,
    )

    if args.spec is None:
        raise SpecError(
            "command line",
            "SPEC",
            "sweep needs a spec (or --replay DIR SAMPLE_ID, or --resume DIR)",
        )
    if args.samples is None:
        raise SpecError("command line", "--samples", "is required")
    if args.samples < 1:
        raise SpecError("command line", "--samples", f"must be positive, got {args.samples}")
    if args.scheduler is None:
        check_workers(args.workers)
    if args.precision != "double" and args.sample_time is None:
        raise SpecError(
            "command line",
            "--precision",
            f"a {args.precision}-precision sweep steps the stateful controller: give "
            "--sample-time H (the continuous loop runs the law in double)",
        )
    _source, raw = read_spec_bytes(args.spec)
    derivation, kernels = common.derive(args)
    program = sweep_program(kernels, args.precision)
    options = _options(args, program, derivation.spec.t_final)
    _check_earlier(args)
    loop_for(program)  # a compiler error stops here, before any worker starts
    plant.check_nominal(derivation.spec.source, program, options)
    spec_name = f"{derivation.spec.name}.toml"
    record = _record(program, options, spec_name, args.extension, bool(args.trajectories), raw)
    if args.precision != "double":
        record["precision"] = args.precision  # the controller's; --resume builds it again
    folder = SweepFolder(args.out, _names(spec_name), args.force)
    try:
        # Again under the lock: a sweep that finished since the first look owns the folder.
        _check_earlier(args)
        client, cluster = connect(args.workers, args.scheduler, options.samples)
        try:
            if args.force:
                folder.clear_parts()  # an earlier sweep's: they are not this one's samples
            write_files(
                {RECORD: record_bytes(record), spec_name: raw.decode("utf-8")},
                folder.folder,
                force=args.force,
                warn=common.warn,
            )
        except BaseException:
            plant.disconnect(client, cluster)
            raise
        code = _run_and_publish(
            args, folder, program, options, record, [range(options.samples)], client, cluster
        )
    except BaseException:
        folder.close(failed=True)
        raise
    folder.close()
    return code


def _schema(program: Any, options: Any, record: dict[str, Any]) -> Any:
    """The table's schema carrying the sweep's identity (its parts must carry the same)."""
    from tvopt_codegen.sweep import row_schema, with_identity  # noqa: PLC0415

    return with_identity(row_schema(program, options), record["identity"])


def _record(
    program: Any,
    options: Any,
    spec_name: str,
    extension: str,
    trajectories: bool,
    spec: bytes,
) -> dict[str, Any]:
    """``sweep.json`` as the sweep starts: everything ``--resume`` and ``--replay`` need."""
    from tvopt_codegen.sweep import sweep_identity  # noqa: PLC0415

    return {
        "identity": sweep_identity(spec, options, program.key, str(extension)),
        "spec": spec_name,
        "extension": extension,
        "loop": program.key,
        "options": options.as_dict(),
        "trajectories": trajectories,
        "state": "running",
        "finished": 0,
        "missing": options.samples,
        "interrupted": False,
        "seed_rule": "sample i draws from numpy.random.default_rng(seed), seed = "
        "SeedSequence(options.seed, spawn_key=(i,)).generate_state(1, uint64)[0] >> 1",
    }


#: Largest ``sweep.json`` read, and largest spec copy.
_MAX_RECORD = 1 << 20
_MAX_SPEC = 1 << 22


def _from_record(folder: Path) -> tuple[dict[str, Any], Any, str, bytes, Any]:
    """A sweep's folder read back: its record, options, spec copy and re-derived program.

    Only files inside ``folder`` are read (the record names its spec by a plain file
    name), each within a bound, and the options pass the checks a new sweep's pass.
    """
    import dataclasses  # noqa: PLC0415
    import json  # noqa: PLC0415

    from tvopt_codegen.derivation import derive  # noqa: PLC0415
    from tvopt_codegen.emit import read_regular_file  # noqa: PLC0415
    from tvopt_codegen.lowering.ir import lower  # noqa: PLC0415
    from tvopt_codegen.spec import parse_spec  # noqa: PLC0415
    from tvopt_codegen.sweep import RECORD, SweepOptions, check_options, sweep_program  # noqa: PLC0415

    raw = read_regular_file(folder / RECORD, _MAX_RECORD)
    if raw is None:
        raise SpecError(str(folder), RECORD, "not found: DIR is not a sweep's output folder")
    try:
        record = json.loads(raw)
        options = SweepOptions.from_dict(record["options"])
        spec_name = str(record["spec"])
    except (ValueError, KeyError, TypeError, AttributeError, SpecError) as exc:
        raise SpecError(str(folder / RECORD), "options", f"unreadable: {exc}") from None
    if Path(spec_name).name != spec_name or not spec_name.endswith(".toml"):
        raise SpecError(
            str(folder / RECORD), "spec", f"{spec_name!r} is not a file name in the folder"
        )
    spec_bytes = read_regular_file(folder / spec_name, _MAX_SPEC)
    if spec_bytes is None:
        raise SpecError(str(folder), spec_name, "the sweep's copy of its spec is missing")
    spec = parse_spec(str(folder / spec_name), spec_bytes)
    if record.get("extension") == "auto":
        spec = dataclasses.replace(spec, extension=(), extension_auto=True)
    program = sweep_program(lower(derive(spec)), str(record.get("precision", "double")))
    try:
        check_options(program, options)
    except SpecError as exc:
        key = exc.field.lstrip("-").replace("-", "_")
        # The record's key of --measurement-noise is the options' own name, noise.
        where = "options." + ("noise" if key == "measurement_noise" else key)
        raise SpecError(str(folder / RECORD), where, exc.problem) from None
    return record, options, spec_name, spec_bytes, program


#: What defines a sweep, with the value that means "not given": a resume runs the
#: recorded sweep, and a different value would silently not apply.
_DEFINING: dict[str, object] = {
    "samples": None,
    "seed": RUN_OPTIONS["seed"].default,
    "initial": [],
    "param": [],
    "plant_param": [],
    "saturation": [],
    "measurement_noise": RUN_OPTIONS["measurement_noise"].default,
    "sample_time": None,
    "t_final": None,
    "rtol": RUN_OPTIONS["rtol"].default,
    "atol": RUN_OPTIONS["atol"].default,
    "points": RUN_OPTIONS["points"].default,
    "trajectories": False,
    "precision": RUN_OPTIONS["precision"].default,
}


def _refuse_sweep_options(args: argparse.Namespace) -> None:
    """A resume takes the sweep's own options from its record: refuse any given here."""
    for name, unset in _DEFINING.items():
        if getattr(args, name) != unset:
            option = "--" + name.replace("_", "-")
            raise SpecError(
                "command line",
                option,
                "not with --resume: the sweep keeps the options it was started with",
            )


def resume(args: argparse.Namespace) -> int:
    """Run ``tvopt-codegen sweep --resume DIR``: the samples an interrupted sweep lacks."""
    from tvopt_codegen.emit import SweepFolder  # noqa: PLC0415
    from tvopt_codegen.sweep import (  # noqa: PLC0415
        connect,
        index_parts,
        loop_for,
        missing,
        sweep_identity,
    )

    if args.spec is not None:
        raise SpecError("command line", "--resume", "takes no SPEC (the sweep's copy is used)")
    _refuse_sweep_options(args)
    folder_path = Path(args.resume)
    record, options, spec_name, spec_bytes, program = _from_record(folder_path)
    if program.key != record.get("loop"):
        raise SpecError(
            str(folder_path / "sweep.json"),
            "loop",
            "this tvopt-codegen builds another loop than the one that ran the sweep (another "
            "version?); its rows would not match: run the sweep anew",
        )
    if args.scheduler is None:
        from tvopt_codegen.sweep import check_workers  # noqa: PLC0415

        check_workers(args.workers)
    if args.chunk_size is not None and not 1 <= args.chunk_size <= options.samples:
        raise SpecError("command line", "--chunk-size", "must be between 1 and the sweep's samples")
    if record.get("state") == "complete":
        print(f"sweep: {folder_path} is complete; nothing to resume", file=sys.stderr)
        return 0
    # The identity is the folder's own (its spec copy and options), never the record's
    # word for it: every part must be of this sweep before anything is written.
    record["identity"] = sweep_identity(
        spec_bytes, options, program.key, str(record.get("extension", ""))
    )
    schema = _schema(program, options, record)
    index_parts(_listed_parts(folder_path), schema, options.samples)
    loop_for(program)
    folder = SweepFolder(folder_path, _names(spec_name), args.force)
    try:
        # Again under the lock (a part written since the first look is checked too).
        gaps = missing(index_parts(folder.parts(), schema, options.samples), options.samples)
        record["resumed"] = True
        if gaps:
            client, cluster = connect(args.workers, args.scheduler, sum(map(len, gaps)))
            code = _run_and_publish(args, folder, program, options, record, gaps, client, cluster)
        else:
            code = _publish(args, folder, program, options, record, schema, None)
    finally:
        folder.close()
    return code


def _listed_parts(folder: Path) -> list[Path]:
    """The parts in ``folder``, as :meth:`SweepFolder.parts` lists them, without the lock."""
    from tvopt_codegen.emit import SweepFolder  # noqa: PLC0415

    where = folder / SweepFolder.PARTS
    if where.is_symlink() or not where.is_dir():
        return []
    return sorted(p for p in where.iterdir() if SweepFolder._PART.fullmatch(p.name) and p.is_file())


def _same(a: Any, b: Any) -> bool:
    """Equal, NaN equal to NaN (a failed sample's errors)."""
    if isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b):
        return True
    return bool(a == b)


def replay(args: argparse.Namespace) -> int:
    """Run ``tvopt-codegen sweep --replay DIR SAMPLE_ID --out DIR2``."""
    from tvopt_codegen.emit import prepare_folder, write_files  # noqa: PLC0415
    from tvopt_codegen.sweep import read_row, run_sample  # noqa: PLC0415

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
    table = folder / "summary.parquet"
    if not table.is_file() or table.is_symlink():
        raise SpecError(str(folder), "summary.parquet", "not found: DIR holds no finished sweep")
    record, options, _name, _spec, program = _from_record(folder)
    if not 0 <= index < options.samples:
        raise SpecError(
            "command line", "--replay", f"sample {index} is not in 0 .. {options.samples - 1}"
        )
    prepare_folder(args.out, create=False)
    if program.key != record.get("loop"):
        print(
            "tvopt-codegen: warning: this tvopt-codegen builds another loop than the sweep's "
            "(another version?); the replayed numbers may differ",
            file=sys.stderr,
        )
    result = run_sample(program, options, index, keep=True)
    from tvopt_codegen.runs.artifacts import replay_files  # noqa: PLC0415 - matplotlib on use

    files = replay_files(program, result)
    write_files(files, args.out, force=args.force, warn=common.warn)
    stored = read_row(table, index)
    for key in ("status", "final_error", "max_error", "seed"):
        print(f"  {key}: {result.row[key]}")
    if stored is not None:
        same = all(_same(stored.get(key), value) for key, value in result.row.items())
        print(f"  the sweep's row {'matches' if same else 'DIFFERS from'} this run")
    else:
        print("  the sweep's table has no row for this sample (it was interrupted before it)")
    for name in files:
        print(f"  wrote {args.out.rstrip('/')}/{name}")
    return 0
