"""The Dask driver: chunks of samples on a ``LocalCluster`` or any scheduler.

Results are gathered as they finish; an interruption keeps the finished samples.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from tvopt_codegen.errors import MissingExtraError, SpecError

if TYPE_CHECKING:
    pass
from tvopt_codegen.sweep.options import SweepOptions
from tvopt_codegen.sweep.program import SweepProgram
from tvopt_codegen.sweep.sample import SampleResult, run_chunk

#: Seconds to wait for a scheduler named by ``--scheduler``.
SCHEDULER_TIMEOUT = 10.0


def chunks(samples: int, size: int) -> Iterator[range]:
    """Consecutive ranges of sample indices, ``size`` at a time."""
    for start in range(0, samples, size):
        yield range(start, min(start + size, samples))


def default_chunk(samples: int, workers: int) -> int:
    """Small enough to keep every worker busy to the end, large enough to amortise a task."""
    return max(1, min(256, math.ceil(samples / (8 * max(1, workers)))))


def _distributed() -> Any:
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
        Every finished sample, in sample order.
    interrupted : bool
        Ctrl-C stopped it: ``results`` holds what finished.
    seconds : float
        Wall time from the first task sent to the last result.
    workers : int
        Workers of the cluster.
    dashboard : str
        The Dask dashboard's address (empty when there is none).
    """

    results: list[SampleResult] = field(default_factory=list)
    interrupted: bool = False
    seconds: float = 0.0
    workers: int = 0
    dashboard: str = ""


def connect(workers: int | None, scheduler: str | None) -> tuple[Any, Any]:
    """A Dask client: on ``scheduler`` unchanged, else on a new ``LocalCluster``.

    Raises
    ------
    SpecError
        An unreachable scheduler (``--scheduler``, within :data:`SCHEDULER_TIMEOUT`), or a
        bad ``--workers``.
    """
    distributed = _distributed()
    import logging  # noqa: PLC0415

    if scheduler is not None:
        try:
            client = distributed.Client(scheduler, timeout=f"{SCHEDULER_TIMEOUT}s")
        except (OSError, TimeoutError) as exc:
            raise SpecError(
                "command line", "--scheduler", f"cannot reach {scheduler}: {exc}"
            ) from None
        return client, None
    if workers is not None and not 1 <= workers <= 1024:
        raise SpecError("command line", "--workers", "must be between 1 and 1024")
    import os  # noqa: PLC0415

    count = workers or os.cpu_count() or 1
    cluster = distributed.LocalCluster(
        n_workers=count,
        threads_per_worker=1,
        processes=True,
        dashboard_address=":0",
        silence_logs=logging.ERROR,
    )
    return distributed.Client(cluster), cluster


def run_sweep(
    client: Any,
    program: SweepProgram,
    options: SweepOptions,
    *,
    chunk: int | None = None,
    keep: bool = False,
    on_results: Callable[[list[SampleResult]], None] | None = None,
    progress: Callable[[int, int, float], None] | None = None,
) -> SweepRun:
    """Run every sample on ``client``'s cluster, chunk by chunk.

    Parameters
    ----------
    client : distributed.Client
        The cluster to run on.
    program, options : SweepProgram, SweepOptions
        What to run.
    chunk : int, optional
        Samples per task (default :func:`default_chunk`).
    keep : bool
        Return every sample's trajectory.
    on_results : callable, optional
        Called in the client with each finished chunk (to store it as it arrives).
    progress : callable, optional
        ``progress(done, failed, rate)`` after each chunk.

    Returns
    -------
    SweepRun
        The results in sample order; ``interrupted`` after Ctrl-C (the workers are
        stopped, the finished chunks kept).
    """
    distributed = _distributed()
    workers = len(client.scheduler_info().get("workers", {})) or 1
    size = chunk or default_chunk(options.samples, workers)
    # A fresh key per sweep: a key shared with an earlier sweep on the same client could
    # still be in release when this one needs it ("lost dependencies").
    scattered = client.scatter(program, broadcast=True, hash=False)
    started = time.perf_counter()
    futures = [
        client.submit(run_chunk, scattered, options, list(r), keep, pure=False)
        for r in chunks(options.samples, size)
    ]
    run = SweepRun(workers=workers, dashboard=str(getattr(client, "dashboard_link", "") or ""))
    done = failed = 0
    try:
        for future in distributed.as_completed(futures):
            results = future.result()
            run.results.extend(results)
            done += len(results)
            failed += sum(r.row["status"] != "ok" for r in results)
            if on_results is not None:
                on_results(results)
            if progress is not None:
                progress(done, failed, done / max(time.perf_counter() - started, 1e-9))
    except KeyboardInterrupt:
        run.interrupted = True
        client.cancel(futures)
    run.seconds = time.perf_counter() - started
    run.results.sort(key=lambda r: int(r.row["sample"]))
    return run
