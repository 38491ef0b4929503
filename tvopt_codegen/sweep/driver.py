"""The Dask driver: chunks of samples on a ``LocalCluster``, any scheduler, or in-process.

Results are gathered as they finish; an interruption keeps the finished samples. A sweep
that one worker serves (``--workers 1``, or a few samples and no ``--workers``) runs its
chunks in the command's own process: a local cluster costs about a second of wall time and
a few CPU seconds of worker start-up, more than a small sweep's samples.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Generator, Iterator, Sequence
from dataclasses import dataclass, field
from typing import Any

from tvopt_codegen.errors import MissingExtraError, SpecError, Terminated, forget_signals
from tvopt_codegen.sweep.options import SweepOptions
from tvopt_codegen.sweep.program import SweepProgram
from tvopt_codegen.sweep.sample import SampleResult, run_chunk

#: Seconds to wait for a scheduler named by ``--scheduler``.
SCHEDULER_TIMEOUT = 10.0


def chunks(samples: int | range, size: int) -> Iterator[range]:
    """Consecutive ranges of sample indices, ``size`` at a time.

    Of ``range(samples)``, or of the range given (``--resume`` splits each run of missing
    samples).
    """
    span = range(samples) if isinstance(samples, int) else samples
    for start in range(span.start, span.stop, size):
        yield range(start, min(start + size, span.stop))


def default_chunk(samples: int, workers: int) -> int:
    """Small enough to keep every worker busy to the end, large enough to amortise a task."""
    return max(1, min(256, math.ceil(samples / (8 * max(1, workers)))))


def distributed_module() -> Any:
    """Dask's ``distributed``, or one line saying which extra installs it."""
    try:
        import distributed  # noqa: PLC0415
    except ImportError:
        raise MissingExtraError(
            "sweep needs Dask: pip install 'tvopt-codegen[sweep]' (dask[distributed], "
            "pyarrow, zarr, xarray)"
        ) from None
    return distributed


@dataclass
class SweepRun:
    """A sweep as it ran.

    Attributes
    ----------
    results : list of SampleResult
        Every finished sample, in sample order (empty when the caller streams them away:
        ``collect=False``).
    done, failed : int
        Samples finished, and those of them not ``ok``.
    interrupted : bool
        Ctrl-C or SIGTERM stopped it: what finished was handed over.
    signal : str
        ``"SIGINT"`` or ``"SIGTERM"`` when interrupted, else "".
    seconds : float
        Wall time from the first task sent to the last result.
    first_result : float
        Seconds from the first task sent to the first chunk's result (NaN if none).
    workers : int
        Workers of the cluster.
    dashboard : str
        The Dask dashboard's address (empty when there is none).
    """

    results: list[SampleResult] = field(default_factory=list)
    done: int = 0
    failed: int = 0
    interrupted: bool = False
    signal: str = ""
    seconds: float = 0.0
    first_result: float = math.nan
    workers: int = 0
    dashboard: str = ""


#: Largest ``--workers`` per core of the machine.
WORKERS_PER_CORE = 4
#: Memory one local worker process takes (Python, numpy, Dask, the compiled loop).
WORKER_BYTES = 250 * 2**20


def max_local_workers() -> tuple[int, str]:
    """The most worker processes this machine can run, and why (its cores and memory)."""
    import os  # noqa: PLC0415

    cores = os.cpu_count() or 1
    try:
        memory = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):
        memory = 0
    limit = WORKERS_PER_CORE * cores
    if memory:
        limit = max(1, min(limit, memory // WORKER_BYTES))
    why = f"{cores} core{'s' if cores != 1 else ''}"
    if memory:
        why += f" and {memory / 2**30:.1f} GB of memory"
    return limit, why


def check_workers(workers: int | None) -> None:
    """Refuse a ``--workers`` this machine cannot run (one line, naming the limit)."""
    if workers is None:
        return
    limit, why = max_local_workers()
    if not 1 <= workers <= limit:
        raise SpecError(
            "command line",
            "--workers",
            f"must be between 1 and {limit} on this machine ({why}; a worker is a process of "
            f"about {WORKER_BYTES // 2**20} MB), got {workers}; use --scheduler for more",
        )


def _scheduler_problem(scheduler: str, problem: str) -> SpecError:
    from tvopt_codegen.errors import clip  # noqa: PLC0415

    return SpecError("command line", "--scheduler", f"{clip(scheduler)!r}: {problem}")


def check_scheduler(scheduler: str, timeout: float) -> None:
    """Check ``--scheduler`` before Dask is asked to connect, within ``timeout`` seconds.

    Dask's client takes a malformed address apart with a traceback, waits without end for
    a server that accepts and never answers, and reads a server that is not Dask's as a
    huge message ("ran out of memory"). Here: the address is parsed, a TLS address needs
    Dask's TLS settings, and a TCP scheduler must greet within ``timeout`` as Dask's do
    (the first 8 bytes of a Dask message are its frame count).

    Raises
    ------
    SpecError
        One line naming the address and the problem.
    """
    import socket  # noqa: PLC0415
    import struct  # noqa: PLC0415

    if not scheduler.strip():
        raise _scheduler_problem(scheduler, "is empty (expected tcp://HOST:PORT)")
    distributed = distributed_module()
    from distributed.comm.addressing import parse_address, parse_host_port  # noqa: PLC0415
    from distributed.comm.registry import get_backend  # noqa: PLC0415

    try:
        scheme, location = parse_address(scheduler)
        get_backend(scheme)
    except ValueError:
        raise _scheduler_problem(
            scheduler, "unknown scheme (expected tcp://HOST:PORT or tls://HOST:PORT)"
        ) from None
    if scheme not in ("tcp", "tls"):
        return  # inproc, ws, ucx: Dask's own checks, within the client's timeout
    try:
        host, port = parse_host_port(location)
    except ValueError as exc:
        raise _scheduler_problem(scheduler, f"not HOST:PORT ({exc})") from None
    if scheme == "tls":
        import dask  # noqa: PLC0415

        tls = dask.config.get("distributed.comm.tls", {}) or {}
        if not (tls.get("ca-file") and (tls.get("client") or {}).get("cert")):
            raise _scheduler_problem(
                scheduler,
                "tls:// needs Dask's TLS settings (distributed.comm.tls.ca-file and "
                "distributed.comm.tls.client.cert/key in the Dask configuration)",
            )
    try:
        with socket.create_connection((host, port), timeout=timeout) as probe:
            if scheme == "tls":
                return  # the greeting is encrypted: the client's handshake checks it
            probe.settimeout(timeout)
            greeting = b""
            while len(greeting) < 8:
                block = probe.recv(8 - len(greeting))
                if not block:
                    raise _scheduler_problem(
                        scheduler, "closed the connection without a greeting: not a Dask scheduler"
                    )
                greeting += block
    except TimeoutError:
        raise _scheduler_problem(
            scheduler,
            f"no answer within {timeout:g} s (a server that is not a Dask scheduler, or a "
            "stalled one)",
        ) from None
    except OSError as exc:
        raise _scheduler_problem(scheduler, f"cannot reach it: {exc.strerror or exc}") from None
    (frames,) = struct.unpack("<Q", greeting)
    if not 1 <= frames <= 1024:
        raise _scheduler_problem(
            scheduler, "answers, but it is not a Dask scheduler (its greeting is not Dask's)"
        )
    del distributed


#: Samples that make a local worker process worth starting, when ``--workers`` is not
#: given: a bundled example's sample takes 10-200 ms, a worker's start 1-3 CPU seconds.
SAMPLES_PER_LOCAL_WORKER = 32


class InlineClient:
    """The cluster of one worker: the command's own process, no Dask.

    Answers the few questions the sweep command asks a Dask client (its workers, its
    dashboard) so that the command runs the same whichever it was given.
    """

    dashboard_link = ""

    def scheduler_info(self) -> dict[str, Any]:
        """One worker, this process."""
        return {"workers": {"inline": {}}}

    def close(self) -> None:
        """Nothing to stop."""


def local_workers(workers: int | None, samples: int | None) -> int:
    """Worker processes for a local sweep: ``--workers``, else one per core that has work.

    Without ``--workers``, a core gets a worker only for each
    :data:`SAMPLES_PER_LOCAL_WORKER` samples (at least one worker).
    """
    import os  # noqa: PLC0415

    if workers is not None:
        return workers
    cores = os.cpu_count() or 1
    if samples is None:
        return cores
    return max(1, min(cores, math.ceil(samples / SAMPLES_PER_LOCAL_WORKER)))


def connect(
    workers: int | None, scheduler: str | None, samples: int | None = None
) -> tuple[Any, Any]:
    """A client: on ``scheduler`` unchanged, on a new ``LocalCluster``, or in-process.

    One local worker (:func:`local_workers` of ``workers`` and ``samples``) is this
    process: an :class:`InlineClient`, no cluster. The local cluster's worker processes
    ignore SIGINT: Ctrl-C in a terminal reaches the whole process group, and it is the
    client's to stop them (one line, not a traceback from each worker).

    Raises
    ------
    SpecError
        A bad ``--scheduler`` (see :func:`check_scheduler`), one with no worker within
        :data:`SCHEDULER_TIMEOUT`, or a ``--workers`` the machine cannot run.
    """
    if scheduler is None:
        check_workers(workers)
        if local_workers(workers, samples) == 1:
            return InlineClient(), None
    distributed = distributed_module()
    import logging  # noqa: PLC0415

    if scheduler is not None:
        check_scheduler(scheduler, SCHEDULER_TIMEOUT)
        try:
            client = distributed.Client(scheduler, timeout=f"{SCHEDULER_TIMEOUT}s")
        except (OSError, TimeoutError, ValueError, TypeError) as exc:
            raise _scheduler_problem(scheduler, f"cannot connect: {exc}") from None
        try:
            client.wait_for_workers(1, timeout=SCHEDULER_TIMEOUT)
        except (TimeoutError, OSError):
            client.close()
            raise _scheduler_problem(
                scheduler,
                f"has no worker (waited {SCHEDULER_TIMEOUT:g} s); start some with "
                f"`dask worker {scheduler}`",
            ) from None
        return client, None
    import signal  # noqa: PLC0415
    import threading  # noqa: PLC0415

    count = local_workers(workers, samples)
    # The workers start while SIGINT is ignored, and keep it so (an ignored signal stays
    # ignored across exec, and Python then installs no handler of its own).
    # (Only the main thread may set a handler: from another, the workers keep SIGINT.)
    main = threading.current_thread() is threading.main_thread()
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN) if main else None
    try:
        cluster = distributed.LocalCluster(
            n_workers=count,
            threads_per_worker=1,
            processes=True,
            dashboard_address=":0",
            silence_logs=logging.CRITICAL,
        )
    finally:
        if main:
            signal.signal(signal.SIGINT, previous)
    return distributed.Client(cluster), cluster


#: Tasks in flight per worker: enough to keep each busy, few enough that a sweep of
#: 10^8 samples holds a few dozen futures, not hundreds of thousands.
LOOKAHEAD_PER_WORKER = 4


def run_sweep(
    client: Any,
    program: SweepProgram,
    options: SweepOptions,
    *,
    ranges: Sequence[range] | None = None,
    chunk: int | None = None,
    keep: bool = False,
    collect: bool = True,
    on_results: Callable[[list[SampleResult]], None] | None = None,
    progress: Callable[[int, int, float], None] | None = None,
) -> SweepRun:
    """Run the samples on ``client``'s cluster a few chunks ahead, or here chunk by chunk.

    Parameters
    ----------
    client : distributed.Client
        The cluster to run on.
    program, options : SweepProgram, SweepOptions
        What to run.
    ranges : sequence of range, optional
        The samples to run (default: all of ``options.samples``); ``--resume`` passes
        the missing ones.
    chunk : int, optional
        Samples per task (default :func:`default_chunk`).
    keep : bool
        Return every sample's trajectory.
    collect : bool
        Keep the results in :attr:`SweepRun.results`; without it they go only to
        ``on_results`` and the client's memory stays flat however many samples run.
    on_results : callable, optional
        Called in the client with each finished chunk (to store it as it arrives).
    progress : callable, optional
        ``progress(done, failed, rate)`` after each chunk.

    Returns
    -------
    SweepRun
        ``interrupted`` after Ctrl-C or SIGTERM (the tasks in flight are cancelled; what
        finished was handed to ``on_results``).
    """
    workers = len(client.scheduler_info().get("workers", {})) or 1
    todo = list(ranges) if ranges is not None else [range(options.samples)]
    size = chunk or default_chunk(sum(len(r) for r in todo), workers)
    pieces = (piece for span in todo for piece in chunks(span, size))
    run = SweepRun(workers=workers, dashboard=str(getattr(client, "dashboard_link", "") or ""))
    started = time.perf_counter()
    if isinstance(client, InlineClient):
        finished = (run_chunk(program, options, list(piece), keep) for piece in pieces)
    else:
        finished = _on_cluster(client, program, options, pieces, keep, workers)
    try:
        for results in finished:
            if math.isnan(run.first_result):
                run.first_result = time.perf_counter() - started
            if collect:
                run.results.extend(results)
            run.done += len(results)
            run.failed += sum(r.row["status"] != "ok" for r in results)
            if on_results is not None:
                on_results(results)
            if progress is not None:
                progress(run.done, run.failed, run.done / max(time.perf_counter() - started, 1e-9))
    except (KeyboardInterrupt, Terminated) as stop:
        forget_signals()  # handled here: the finished rows are kept and written
        run.interrupted = True
        run.signal = "SIGINT" if isinstance(stop, KeyboardInterrupt) else "SIGTERM"
    finally:
        # Cancels the chunks in flight, wherever the interruption arrived.
        finished.close()
    run.seconds = time.perf_counter() - started
    run.results.sort(key=lambda r: int(r.row["sample"]))
    return run


def _on_cluster(
    client: Any,
    program: SweepProgram,
    options: SweepOptions,
    pieces: Iterator[range],
    keep: bool,
    workers: int,
) -> Generator[list[SampleResult], None, None]:
    """Each chunk's results as it finishes on ``client``'s cluster, a few chunks ahead.

    Closing the generator (or an interruption while it waits) cancels the chunks in
    flight.
    """
    distributed = distributed_module()
    # A fresh key per sweep: a key shared with an earlier sweep on the same client could
    # still be in release when this one needs it ("lost dependencies").
    scattered = client.scatter(program, broadcast=True, hash=False)

    def submit() -> Any | None:
        piece = next(pieces, None)
        if piece is None:
            return None
        return client.submit(run_chunk, scattered, options, list(piece), keep, pure=False)

    first = [f for f in (submit() for _ in range(LOOKAHEAD_PER_WORKER * workers)) if f]
    flying = set(first)
    queue = distributed.as_completed(first)
    try:
        for future in queue:
            flying.discard(future)
            results = future.result()
            future.release()
            more = submit()
            if more is not None:
                flying.add(more)
                queue.add(more)
            yield results
    finally:
        if flying:
            client.cancel(list(flying))
