"""Long sweeps that never lose work: signals, resume, the folder's rules, failures, scale."""

from __future__ import annotations

import contextlib
import errno
import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from tests.conftest import kernels, shared
from tvopt_codegen import sweep
from tvopt_codegen.cli import main
from tvopt_codegen.errors import (
    EXIT_BAD_SPEC,
    EXIT_INTERRUPTED,
    EXIT_OUTPUT,
    EXIT_TERMINATED,
    OutputError,
)
from tvopt_codegen.sweep import SweepOptions, sweep_program

pq = pytest.importorskip("pyarrow.parquet")
distributed = pytest.importorskip("distributed")

ROOT = Path(__file__).resolve().parents[1]
#: A sweep long enough to stop in the middle, short enough for the suite (about 2 s).
SAMPLES = 2000
COMMON = ["--samples", str(SAMPLES), "--t-final", "3", "--chunk-size", "40"]
COMMON += ["--initial", "x1=normal(-5, 0.3)", "--plant-param", "b=uniform(1, 2)"]


def _command(*args: str) -> list[str]:
    return [sys.executable, "-m", "tvopt_codegen", "sweep", *args]


@pytest.fixture(scope="module")
def reference() -> bytes:
    """The uninterrupted sweep's table (one worker), swept once per run for every worker."""

    def sweep_once(folder: Path) -> None:
        # In this process: the table is the subject, not a cold interpreter.
        out = folder / "out"
        assert main(["sweep", "unicycle_switch", *COMMON, "--workers", "1", "--out", str(out)]) == 0

    return (shared("sweep-jobs-reference", sweep_once) / "out" / "summary.parquet").read_bytes()


def _start(out: Path, workers: int, *extra: str) -> subprocess.Popen[str]:
    return subprocess.Popen(
        _command(
            "unicycle_switch",
            *COMMON,
            "--workers",
            str(workers),
            "--progress",
            "always",
            "--out",
            str(out),
            *extra,
        ),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,  # a process group of its own: the test signals all of it
    )


def _wait_for_progress(process: subprocess.Popen[str]) -> None:
    assert process.stderr is not None
    for line in process.stderr:
        if "samples/s" in line:
            return
    raise AssertionError("the sweep ended before it showed progress")


# Each signal on a local cluster and on the in-process worker (one worker), each resumed
# on the other (two workers: a scheduler's, in this process).
@pytest.mark.parametrize(
    ("how", "workers", "again"), [("SIGTERM", 2, 1), ("SIGTERM", 1, 2), ("SIGKILL", 2, 1)]
)
def test_a_killed_sweep_resumes_to_the_uninterrupted_table_bit_for_bit(
    tmp_path: Path,
    reference: bytes,
    how: str,
    workers: int,
    again: int,
    capsys: pytest.CaptureFixture[str],
) -> None:
    out = tmp_path / "out"
    process = _start(out, workers, "--checkpoint-seconds", "0.2")
    _wait_for_progress(process)
    if how == "SIGKILL":
        # A node lost: the whole job dies at once, after at least one checkpoint.
        deadline = time.monotonic() + 60
        while not list((out / "parts").glob("part-*.parquet")) and time.monotonic() < deadline:
            time.sleep(0.05)
        os.killpg(process.pid, signal.SIGKILL)
        process.communicate(timeout=60)
        assert process.returncode == -signal.SIGKILL
        assert not (out / "summary.parquet").exists()
        kept = sum(pq.ParquetFile(p).metadata.num_rows for p in (out / "parts").iterdir())
        assert 0 < kept < SAMPLES
    else:
        running = _descendants(process.pid)
        process.send_signal(signal.SIGTERM)  # what timeout, SLURM and systemd send
        _, stderr = process.communicate(timeout=120)
        assert process.returncode == EXIT_TERMINATED, stderr
        _no_worker_outlives(running)  # the command, signalled alone, stops its workers
        last = stderr.strip().splitlines()[-1]
        assert last.startswith("tvopt-codegen: terminated; kept the") and "--resume" in last
        rows = pq.read_table(out / "summary.parquet").num_rows
        assert 0 < rows < SAMPLES
        record = json.loads((out / "sweep.json").read_text())
        assert record["state"] == "interrupted" and record["missing"] == SAMPLES - rows
        assert f"{SAMPLES - rows} missing" in (out / "summary.md").read_text()
    # The resumes run in this process: what they read is the folder the killed process
    # left, and no state of it (a cold interpreter each would add its imports only).
    # Two workers are threads of this process behind a scheduler (--scheduler): rows from
    # worker processes are the killed local cluster's parts (the SIGTERM-2-1 and SIGKILL
    # cases), and a local cluster here was two more cold interpreters.
    capsys.readouterr()
    with contextlib.ExitStack() as stack:
        where = ["--workers", "1"]
        if again > 1:
            cluster = stack.enter_context(
                distributed.LocalCluster(
                    n_workers=again, threads_per_worker=1, processes=False, dashboard_address=":0"
                )
            )
            where = ["--scheduler", str(cluster.scheduler_address)]
        assert main(["sweep", "--resume", str(out), *where]) == 0, capsys.readouterr().err
    assert (out / "summary.parquet").read_bytes() == reference
    assert not (out / "parts").exists()
    assert json.loads((out / "sweep.json").read_text())["state"] == "complete"
    # Nothing left to do: a second resume says so and changes nothing.
    before = _folder_hash(out)
    capsys.readouterr()
    assert main(["sweep", "--resume", str(out)]) == 0
    assert "nothing to resume" in capsys.readouterr().err
    assert _folder_hash(out) == before


@pytest.mark.parametrize("workers", [2, 1])
def test_ctrl_c_in_a_terminal_is_one_line(tmp_path: Path, workers: int) -> None:
    """A terminal sends SIGINT to the whole process group, the workers too (or to the one
    process that is the worker): one line, the finished samples kept, no worker left.

    (A signal to the command alone, with workers: the SIGTERM case of
    test_a_killed_sweep_resumes_to_the_uninterrupted_table_bit_for_bit.)
    """
    out = tmp_path / "out"
    process = _start(out, workers)
    _wait_for_progress(process)
    workers_running = _descendants(process.pid)
    if workers > 1:
        assert workers_running, "the local cluster runs its workers as child processes"
    os.killpg(process.pid, signal.SIGINT)
    _, stderr = process.communicate(timeout=120)
    assert process.returncode == EXIT_INTERRUPTED, stderr
    lines = [line for line in stderr.splitlines() if not line.startswith("  sweep:")]
    assert len(lines) == 1 and lines[0].startswith("tvopt-codegen: interrupted; kept the")
    rows = pq.read_table(out / "summary.parquet").column("status").to_pylist()
    assert 0 < len(rows) < SAMPLES and set(rows) == {"ok"}
    record = json.loads((out / "sweep.json").read_text())
    assert record["interrupted"] is True and record["finished"] == len(rows)
    assert "Interrupted:" in (out / "summary.md").read_text()
    _no_worker_outlives(workers_running)


def _descendants(pid: int) -> list[int]:
    """Every process ``pid`` started, and theirs (Linux's /proc)."""
    found: list[int] = []
    todo = [pid]
    while todo:
        parent = todo.pop()
        for task in Path(f"/proc/{parent}/task").glob("*"):
            with contextlib.suppress(OSError):
                children = [int(c) for c in (task / "children").read_text().split()]
                found += children
                todo += children
    return found


def _no_worker_outlives(pids: list[int]) -> None:
    """Each of ``pids`` ends (or is a zombie nobody needs) within 20 s of its command."""

    def alive(pid: int) -> bool:
        try:
            state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
        except OSError:
            return False
        return state != "Z"

    deadline = time.monotonic() + 20
    while time.monotonic() < deadline and any(alive(pid) for pid in pids):
        time.sleep(0.05)
    assert not [pid for pid in pids if alive(pid)]


def test_a_users_file_in_out_is_refused_before_the_first_sample(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "out"
    out.mkdir()
    (out / "summary.md").write_text("my notes\n")
    (out / "unicycle_switch.toml").write_text("# my edited spec\n")
    args = ["sweep", "unicycle_switch", "--samples", "4", "--workers", "1", "--out", str(out)]
    assert main(args) == EXIT_OUTPUT
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "edited by hand" in err and "--force" in err
    assert "sweep:" not in err  # no sample ran
    assert sorted(p.name for p in out.iterdir()) == ["summary.md", "unicycle_switch.toml"]
    assert (out / "summary.md").read_text() == "my notes\n"
    # --force replaces them, as for every other command.
    assert main([*args, "--force"]) == 0
    assert (out / "summary.md").read_text().startswith("# Sweep of unicycle_switch")


def test_two_sweeps_into_one_new_folder_one_is_refused(tmp_path: Path) -> None:
    out = tmp_path / "out"
    small = ["unicycle_switch", "--samples", "400", "--t-final", "3", "--workers", "1"]
    both = [
        subprocess.Popen(
            _command(*small, "--out", str(out)),
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        for _ in range(2)
    ]
    outcomes = sorted((p.wait(timeout=240), p.communicate()[1]) for p in both)
    assert [code for code, _ in outcomes] == [0, EXIT_OUTPUT], outcomes
    refusal = outcomes[1][1].strip()
    assert len(refusal.splitlines()) == 1
    assert "another sweep is writing" in refusal or "already holds a sweep" in refusal
    assert pq.read_table(out / "summary.parquet").num_rows == 400


def _read_only_folder(tmp_path: Path) -> Path:
    """A folder this process cannot write in (root writes anywhere chmod allows nothing)."""
    if os.geteuid() != 0:
        folder = tmp_path / "locked"
        folder.mkdir()
        folder.chmod(0o555)
        return folder
    for candidate in (Path("/sys/kernel"), Path("/proc/sys")):
        try:
            os.close(os.open(candidate / ".tvopt-probe", os.O_CREAT | os.O_WRONLY, 0o644))
        except OSError:
            return candidate
        (candidate / ".tvopt-probe").unlink()
    pytest.skip("no read-only folder for root on this machine")


def test_an_unwritable_out_is_refused_before_the_first_sample(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    for out in (_read_only_folder(tmp_path), Path("/proc/tvopt-sweep-out")):
        started = time.monotonic()
        code = main(["sweep", "unicycle_switch", "--samples", "4", "--out", str(out)])
        err = capsys.readouterr().err.strip()
        assert code == EXIT_OUTPUT and len(err.splitlines()) == 1, err
        assert "cannot" in err and str(out) in err
        assert time.monotonic() - started < 30
        assert not (out / "sweep.json").exists()


def test_a_full_disk_during_trajectories_is_exit_4_and_resumable(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    zarr = pytest.importorskip("zarr")
    out = tmp_path / "out"
    real = zarr.Array.__setitem__
    writes = {"n": 0}

    def full(self: object, key: object, value: object) -> None:
        writes["n"] += 1
        if writes["n"] > 12:  # the coordinates and a chunk's arrays fit; the next do not
            raise OSError(errno.ENOSPC, "No space left on device")
        real(self, key, value)  # type: ignore[arg-type]

    monkeypatch.setattr(zarr.Array, "__setitem__", full)
    args = ["sweep", "unicycle_switch", "--samples", "40", "--chunk-size", "4", "--t-final", "3"]
    args += ["--workers", "1", "--trajectories", "--out", str(out)]
    assert main(args) == EXIT_OUTPUT
    err = capsys.readouterr().err.strip().splitlines()
    assert "No space left on device" in err[-1] and "--resume" in err[-1]
    assert (out / "sweep.json").exists() and (out / "trajectories.zarr").is_dir()
    monkeypatch.setattr(zarr.Array, "__setitem__", real)  # space made
    assert main(["sweep", "--resume", str(out), "--workers", "1"]) == 0
    table = pq.read_table(out / "summary.parquet").to_pylist()
    assert [row["sample"] for row in table] == list(range(40))
    xr = pytest.importorskip("xarray")
    store = xr.open_zarr(out / "trajectories.zarr", consolidated=False)
    final = store.isel(time=-1)
    errors = np.linalg.norm(final.output.values - final.target.values, axis=1)
    assert np.array_equal(errors, [row["final_error"] for row in table])


# ------------------------------------------------------------ a sample never stops it


@pytest.mark.parametrize(
    "dist",
    ["x1=uniform(-1e308, 1e308)", "x1=normal(0, 1e307)", "x1=lognormal(700, 1)"],
)
def test_a_distribution_that_overflows_is_refused_when_parsed(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], dist: str
) -> None:
    out = tmp_path / "out"
    code = main(
        ["sweep", "unicycle_switch", "--samples", "4", "--initial", dist, "--out", str(out)]
    )
    err = capsys.readouterr().err.strip()
    assert code == EXIT_BAD_SPEC and len(err.splitlines()) == 1
    assert "--initial" in err and "beyond the largest float" in err
    assert not out.exists()


def test_a_sample_that_raises_is_a_row_with_its_message(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    program = sweep_program(kernels("unicycle_switch"))
    options = SweepOptions(samples=6, seed=3, t_final=2.0, points=21)
    real = sweep.sample.run_sample

    def flaky(p: object, o: SweepOptions, index: int, keep: bool = False) -> object:
        if index == 4:
            raise FloatingPointError("the draw met a wall")
        return real(p, o, index, keep)  # type: ignore[arg-type]

    monkeypatch.setattr(sweep.sample, "run_sample", flaky)
    results = sweep.run_chunk(program, options, range(6), False)
    assert [r.row["status"] for r in results] == ["ok"] * 4 + ["error", "ok"]
    failed = results[4].row
    assert failed["error"] == "FloatingPointError: the draw met a wall"
    assert failed["seed"] == sweep.sample_seed(3, 4) and np.isnan(failed["final_error"])
    schema = sweep.row_schema(program, options)
    batch = sweep.record_batch([r.row for r in results], schema)
    assert batch.num_rows == 6 and batch.schema.equals(schema)
    summary = sweep.summarize(results, 6, False)
    assert summary.outcomes == {"ok": 5, "error": 1}
    text = sweep.format_summary("unicycle_switch", options, summary)
    assert "sample 4: FloatingPointError: the draw met a wall" in text
    # The table on disk, read a row group at a time, gives the same statistics.
    table = tmp_path / "table.parquet"
    with table.open("wb") as handle:
        sweep.write_part(handle, [batch], schema)
    assert sweep.tally_table(table).summary(6, False) == summary


def test_a_dependent_constraints_status_is_recorded(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    text = (ROOT / "tvopt_codegen" / "examples" / "unicycle_switch.toml").read_text()
    text = text.replace('name = "unicycle_switch"', 'name = "dependent"')
    text = text.replace("[parameters]", "[parameters]\nq = 1.0")
    spec = tmp_path / "dependent.toml"
    spec.write_text(text + '\n[constraints]\na = "y1 == 1"\nb = "y1 + q*y2 == 0"\n')
    out = tmp_path / "out"
    code = main(
        [
            "sweep",
            str(spec),
            "--samples",
            "6",
            "--param",
            "q=0",
            "--workers",
            "1",
            "--out",
            str(out),
        ]
    )
    assert code == 0, capsys.readouterr().err
    statuses = pq.read_table(out / "summary.parquet").column("status").to_pylist()
    assert statuses == ["dependent_constraints"] * 6


# ------------------------------------------------------------------ the scheduler


@pytest.fixture
def silent_server() -> Iterator[str]:
    """A server that accepts connections and never says a word."""
    with socket.socket() as server:
        server.bind(("127.0.0.1", 0))
        server.listen()
        held: list[socket.socket] = []
        stop = threading.Event()

        def accept() -> None:
            server.settimeout(0.2)
            while not stop.is_set():
                try:
                    held.append(server.accept()[0])
                except TimeoutError:
                    continue

        thread = threading.Thread(target=accept, daemon=True)
        thread.start()
        yield f"tcp://127.0.0.1:{server.getsockname()[1]}"
        stop.set()
        thread.join()
        for connection in held:
            connection.close()


@pytest.fixture
def http_server() -> Iterator[str]:
    """A server that is not Dask's: it answers every connection with an HTTP error."""
    with socket.socket() as server:
        server.bind(("127.0.0.1", 0))
        server.listen()
        stop = threading.Event()

        def answer() -> None:
            server.settimeout(0.2)
            while not stop.is_set():
                try:
                    connection = server.accept()[0]
                except TimeoutError:
                    continue
                with connection:
                    connection.sendall(b"HTTP/1.1 400 Bad Request\r\nContent-Length: 0\r\n\r\n")

        thread = threading.Thread(target=answer, daemon=True)
        thread.start()
        yield f"tcp://127.0.0.1:{server.getsockname()[1]}"
        stop.set()
        thread.join()


@pytest.fixture
def idle_scheduler() -> Iterator[str]:
    """A real Dask scheduler with no worker."""
    with distributed.LocalCluster(n_workers=0, processes=False, dashboard_address=":0") as cluster:
        yield str(cluster.scheduler_address)


@pytest.mark.parametrize(
    ("address", "words"),
    [
        ("garbage://x", "unknown scheme"),
        ("", "is empty"),
        ("tcp://[::1", "not HOST:PORT"),
        ("tcp://127.0.0.1", "not HOST:PORT"),
        ("tls://127.0.0.1:8786", "needs Dask's TLS settings"),
        ("silent", "no answer within 0.5 s"),
        ("http", "not a Dask scheduler"),
        ("idle", "has no worker"),
    ],
)
def test_a_bad_scheduler_is_one_line_in_bounded_time(
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
    request: pytest.FixtureRequest,
    address: str,
    words: str,
) -> None:
    # The silent server's wait is the whole timeout: half a second shows it as well. A
    # real (idle) scheduler gets 2 s to be connected to, however loaded the machine.
    timeout = 0.5 if address == "silent" else 2.0
    monkeypatch.setattr(sweep.driver, "SCHEDULER_TIMEOUT", timeout)
    servers = {"silent": "silent_server", "http": "http_server", "idle": "idle_scheduler"}
    if address in servers:
        address = request.getfixturevalue(servers[address])
    out = tmp_path / "out"
    started = time.monotonic()
    code = main(
        ["sweep", "unicycle_switch", "--samples", "4", "--scheduler", address, "--out", str(out)]
    )
    elapsed = time.monotonic() - started
    err = capsys.readouterr().err.strip()
    assert code == EXIT_BAD_SPEC and len(err.splitlines()) == 1, err
    assert "--scheduler" in err and words in err, err
    assert elapsed < 30
    assert not out.exists()


def test_workers_beyond_the_machine_are_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    limit, _ = sweep.max_local_workers()
    out = tmp_path / "out"
    code = main(
        ["sweep", "unicycle_switch", "--samples", "4", "--workers", "1024", "--out", str(out)]
    )
    err = capsys.readouterr().err.strip()
    assert code == EXIT_BAD_SPEC and len(err.splitlines()) == 1
    assert f"must be between 1 and {limit} on this machine" in err and "core" in err
    assert limit <= sweep.driver.WORKERS_PER_CORE * (os.cpu_count() or 1)
    assert not out.exists()


# ------------------------------------------------------------------ scale


def test_progress_in_a_log_starts_within_the_first_minute(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """A batch job's log (stderr not a terminal, --progress auto): a first line after
    LOG_FIRST seconds, then one a minute; nothing for a sweep that ends sooner."""
    from tvopt_codegen.commands import sweep as command

    clock = {"now": 1000.0}
    monkeypatch.setattr(command.time, "perf_counter", lambda: clock["now"])
    monkeypatch.setattr(sys.stderr, "isatty", lambda: False)
    progress = command._Progress("auto", 100)
    for seconds, done in ((1.0, 5), (9.0, 10), (11.0, 20), (30.0, 40), (71.5, 80), (75.0, 100)):
        clock["now"] = 1000.0 + seconds
        progress(done, 0, done / seconds)
    progress.close()
    lines = capsys.readouterr().err.splitlines()
    assert [line.split(",")[0] for line in lines] == [
        "  sweep: 20/100 samples",
        "  sweep: 80/100 samples",
    ]


@contextlib.contextmanager
def _cluster_from_a_thread() -> Iterator[list[object]]:
    """``sweep.connect(2, None)`` called from another thread than the main one: the
    client of its two-worker local cluster, or what it raised (a list of one); closed
    on leaving (an idle cluster costs its workers' and scheduler's ticks, about 0.07 s of
    CPU a second: not kept to the module's end).
    """
    outcome: list[object] = []
    made: list[tuple[object, object]] = []

    def start() -> None:
        try:
            client, cluster = sweep.connect(2, None)
            made.append((client, cluster))
            outcome.append(client)
        except Exception as exc:  # noqa: BLE001 - reported by the tests' assertions
            outcome.append(exc)

    thread = threading.Thread(target=start)
    thread.start()
    thread.join(timeout=120)
    try:
        yield outcome
    finally:
        for client, cluster in made:
            client.close()  # type: ignore[attr-defined]
            cluster.close()  # type: ignore[attr-defined]


def test_a_local_cluster_from_another_thread_bounds_the_tasks_in_flight() -> None:
    """The workers ignore SIGINT when started from the main thread; from another (a
    notebook's worker thread, a GUI), where no handler may be set, the cluster still
    starts. On it (one start for both checks: two cold worker processes), the tasks in
    flight are bounded and rows are not kept."""
    program = sweep_program(kernels("unicycle_switch"))
    options = SweepOptions(samples=80, seed=1, t_final=1.0, points=11)
    seen: list[int] = []
    with _cluster_from_a_thread() as outcome:
        [client] = outcome
        assert isinstance(client, distributed.Client), client
        assert len(client.scheduler_info()["workers"]) == 2

        def count(results: list[sweep.SampleResult]) -> None:
            seen.append(len([f for f in client.futures if f.startswith("run_chunk")]))

        run = sweep.run_sweep(client, program, options, chunk=1, collect=False, on_results=count)
    assert run.done == 80 and run.results == [] and len(seen) == 80
    # At most the look-ahead of both workers, never all 80 chunks at once.
    # (the chunk just finished is still known to the client as its callback runs).
    assert max(seen) <= sweep.LOOKAHEAD_PER_WORKER * 2 + 1, seen


def test_parts_merge_in_sample_order_whatever_order_they_came_in(tmp_path: Path) -> None:
    program = sweep_program(kernels("unicycle_switch"))
    options = SweepOptions(samples=10, seed=2, t_final=1.0, points=11)
    schema = sweep.row_schema(program, options)
    rows = [r.row for r in sweep.run_chunk(program, options, range(10), False)]

    def part(name: str, *spans: range) -> Path:
        path = tmp_path / name
        with path.open("wb") as handle:
            sweep.write_part(
                handle, [sweep.record_batch([rows[i] for i in s], schema) for s in spans], schema
            )
        return path

    # Chunks out of order, 6..7 missing.
    pieces = sweep.index_parts(
        [part("a", range(8, 10), range(0, 3)), part("b", range(3, 6))], schema, 10
    )
    assert sweep.missing(pieces, 10) == [range(6, 8)]
    # A chunk kept twice: which copy holds the right rows is unknown, so neither is taken.
    with pytest.raises(OutputError, match=r"/c: holds samples 0\.\.2, which a holds too"):
        sweep.index_parts([part("a", range(8, 10), range(0, 3)), part("c", range(0, 3))], schema)
    with (tmp_path / "table").open("wb") as handle:
        assert sweep.write_table(handle, pieces, schema) == 8
    table = pq.read_table(tmp_path / "table").to_pylist()
    assert [r["sample"] for r in table] == [0, 1, 2, 3, 4, 5, 8, 9]
    assert {k: repr(v) for k, v in table[8 - 2].items()} == {k: repr(v) for k, v in rows[8].items()}


# ------------------------------------------------------------------ replay and resume


def _finished(tmp_path: Path) -> Path:
    out = tmp_path / "done"
    args = ["sweep", "unicycle_switch", "--samples", "4", "--t-final", "2", "--workers", "1"]
    assert main([*args, "--out", str(out)]) == 0
    return out


def test_replay_reads_only_inside_its_folder_and_checks_before_writing(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = _finished(tmp_path)
    capsys.readouterr()
    record = json.loads((out / "sweep.json").read_text())
    (tmp_path / "outside.toml").write_text((out / "unicycle_switch.toml").read_text())
    replay = ["sweep", "--replay", str(out), "1", "--out", str(tmp_path / "r")]
    for key, value, words in (
        ("spec", "../outside.toml", "is not a file name in the folder"),
        ("spec", str(tmp_path / "outside.toml"), "is not a file name in the folder"),
        ("options", record["options"] | {"points": 1_000_000_000}, "options.points"),
    ):
        (out / "sweep.json").write_text(json.dumps(record | {key: value}))
        assert main(replay) == EXIT_BAD_SPEC
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and words in err, err
        assert "outside" not in capsys.readouterr().out
    (out / "sweep.json").write_text(json.dumps(record))
    (out / "summary.parquet").unlink()
    assert main(replay) == EXIT_BAD_SPEC
    assert "holds no finished sweep" in capsys.readouterr().err
    assert not (tmp_path / "r").exists()


def test_resume_refuses_a_loop_it_cannot_rebuild(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = _finished(tmp_path)
    record = json.loads((out / "sweep.json").read_text())
    (out / "sweep.json").write_text(json.dumps(record | {"loop": "0" * 64, "state": "running"}))
    capsys.readouterr()
    assert main(["sweep", "--resume", str(out)]) == EXIT_BAD_SPEC
    assert "another loop" in capsys.readouterr().err
    assert main(["sweep", "--resume", str(out), "--out", "x"]) == EXIT_BAD_SPEC
    # What defines the sweep is its record's: an option that would silently not apply.
    capsys.readouterr()
    assert main(["sweep", "--resume", str(out), "--samples", "10"]) == EXIT_BAD_SPEC
    assert "--samples: not with --resume" in capsys.readouterr().err


def test_a_signal_while_the_files_are_written_lets_them_finish(
    capsys: pytest.CaptureFixture[str],
) -> None:
    """SIGTERM at the very end of a run (a batch job's wall time) is noted while the table
    and summary are written; before that it stops the samples, and a second one stops the
    writing too."""
    from tvopt_codegen.commands import sweep as command
    from tvopt_codegen.errors import Terminated

    def deliver(number: int) -> None:
        os.kill(os.getpid(), number)
        time.sleep(0.05)  # the handler runs between bytecodes of this thread

    with command._Finishing() as finishing:
        with pytest.raises(Terminated):
            deliver(signal.SIGTERM)  # the samples are running: stop them
        finishing.begin()
        deliver(signal.SIGTERM)  # writing: noted, not raised
        assert finishing.signal == signal.SIGTERM
        assert "a second signal stops at once" in capsys.readouterr().err
        with pytest.raises(KeyboardInterrupt):
            deliver(signal.SIGINT)
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler


# ------------------------------------------------------------------ parts that cannot mix

#: A small sweep whose parts are one chunk each (samples 0..2, 3..5, 6..8, 9..11).
MIXING = ["--samples", "12", "--chunk-size", "3", "--t-final", "1", "--points", "11"]
MIXING += ["--initial", "x1=normal(-1, 0.1)", "--checkpoint-seconds", "0", "--workers", "1"]


def _ranges_of(part: Path) -> list[list[int]]:
    metadata = pq.ParquetFile(part).schema_arrow.metadata
    return [list(r) for r in json.loads(metadata[b"tvopt.sweep.ranges"])]


def _part_holding(folder: Path, start: int) -> Path:
    """The part whose (only) chunk starts at sample ``start``."""
    found = [p for p in sorted((folder / "parts").iterdir()) if _ranges_of(p)[0][0] == start]
    assert len(found) == 1, found
    return found[0]


@pytest.fixture(scope="module")
def mixing() -> dict[str, Path]:
    """Three finished sweeps of one spec with their parts kept: seed 1, seed 2, t_final 2.

    ``seed1`` is then made an interrupted sweep whose last chunk (9..11) is missing. Made
    once per run for every worker (the tests copy what they change).
    """
    root = shared("sweep-jobs-mixing", _sweeps_to_mix)
    made = {name: root / name for name in ("seed1", "seed2", "longer")}
    return made | {"complete": root / "complete.parquet"}


def _sweeps_to_mix(root: Path) -> None:
    import shutil

    from tvopt_codegen.emit import SweepFolder, write_files

    made = {}
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(SweepFolder, "clear_parts", lambda self: None)
        for name, extra in (
            ("seed1", ["--seed", "1"]),
            ("seed2", ["--seed", "2"]),
            ("longer", ["--seed", "1", "--t-final", "2"]),
        ):
            out = root / name
            options = [*MIXING, *extra]
            if name == "longer":
                options.remove("1")  # the first --t-final's value: given again in extra
                options.remove("--t-final")
            assert main(["sweep", "integrator", *options, "--out", str(out)]) == 0
            assert sorted(_ranges_of(p)[0][0] for p in (out / "parts").iterdir()) == [0, 3, 6, 9]
            made[name] = out
    shutil.copyfile(made["seed1"] / "summary.parquet", root / "complete.parquet")
    _part_holding(made["seed1"], 9).unlink()
    # As an interrupted sweep leaves its record (written by the tool: its manifest knows it).
    record = json.loads((made["seed1"] / "sweep.json").read_text()) | {"state": "interrupted"}
    write_files({"sweep.json": sweep.record_bytes(record)}, made["seed1"])


def _folder_hash(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in folder.rglob("*") if p.is_file()}


def _copy(mixing: dict[str, Path], tmp_path: Path) -> Path:
    import shutil

    out = tmp_path / "sweep"
    shutil.copytree(mixing["seed1"], out)
    return out


def test_an_interrupted_sweep_with_its_own_parts_resumes_to_the_whole_table(
    mixing: dict[str, Path], tmp_path: Path
) -> None:
    out = _copy(mixing, tmp_path)
    assert main(["sweep", "--resume", str(out), "--workers", "1"]) == 0
    assert (out / "summary.parquet").read_bytes() == mixing["complete"].read_bytes()
    assert not (out / "parts").exists()
    metadata = pq.ParquetFile(out / "summary.parquet").schema_arrow.metadata
    assert metadata[b"tvopt.sweep.seed"] == b"1"


def _tamper_other_seed(out: Path, mixing: dict[str, Path]) -> tuple[str, str]:
    import shutil

    part = out / "parts" / "part-00000090-1.parquet"
    shutil.copyfile(_part_holding(mixing["seed2"], 9), part)
    return part.name, "it is a part of another sweep: seed 2, this sweep's is 1"


def _tamper_other_options(out: Path, mixing: dict[str, Path]) -> tuple[str, str]:
    import shutil

    part = out / "parts" / "part-00000090-1.parquet"
    shutil.copyfile(_part_holding(mixing["longer"], 9), part)
    return part.name, "it is a part of another sweep: other options"


def _rewrite(part: Path, table: object) -> None:
    # What a hand edit with pyarrow does: the schema's metadata (ranges too) is kept.
    pq.write_table(table, part)


def _tamper_duplicate(out: Path, mixing: dict[str, Path]) -> tuple[str, str]:
    import pyarrow as pa

    part = _part_holding(out, 3)
    table = pq.read_table(part)
    _rewrite(part, pa.concat_tables([table.slice(0, 2), table.slice(1, 1)]))
    assert pq.read_table(part).column("sample").to_pylist() == [3, 4, 4]
    return part.name, "its sample column holds sample 4 twice (row group 0; sample 5 is missing)"


def _tamper_dropped(out: Path, mixing: dict[str, Path]) -> tuple[str, str]:
    part = _part_holding(out, 6)
    _rewrite(part, pq.read_table(part).slice(0, 2))
    return part.name, "row group 0 holds 2 rows for samples 6..8 (3 samples)"


def _tamper_overlap(out: Path, mixing: dict[str, Path]) -> tuple[str, str]:
    import shutil

    first = _part_holding(out, 3)
    copy = out / "parts" / "part-00000090-1.parquet"
    shutil.copyfile(first, copy)
    return copy.name, f"holds samples 3..5, which {first.name} holds too (overlapping parts)"


def _tamper_anonymous(out: Path, mixing: dict[str, Path]) -> tuple[str, str]:
    # The right rows, written without the sweep's identity (by another tool).
    program = sweep_program(kernels("integrator"))
    record = json.loads((out / "sweep.json").read_text())
    options = SweepOptions.from_dict(record["options"])
    schema = sweep.row_schema(program, options)
    rows = [r.row for r in sweep.run_chunk(program, options, range(9, 12), False)]
    part = out / "parts" / "part-00000090-1.parquet"
    with part.open("wb") as handle:
        sweep.write_part(handle, [sweep.record_batch(rows, schema)], schema)
    return part.name, "it carries no sweep identity"


def _tamper_beyond(out: Path, mixing: dict[str, Path]) -> tuple[str, str]:
    # A part whose recorded range and rows agree, past the sweep's last sample.
    import pyarrow as pa

    part = _part_holding(out, 6)
    table = pq.read_table(part)
    shifted = table.set_column(0, "sample", pa.array([12, 13, 14], pa.int64()))
    metadata = dict(table.schema.metadata) | {b"tvopt.sweep.ranges": b"[[12,15]]"}
    _rewrite(part, shifted.replace_schema_metadata(metadata))
    return part.name, "row group 0's range 12..14 is not a range of 0..11"


@pytest.mark.parametrize(
    "tamper",
    [
        _tamper_other_seed,
        _tamper_other_options,
        _tamper_duplicate,
        _tamper_dropped,
        _tamper_overlap,
        _tamper_anonymous,
        _tamper_beyond,
    ],
    ids=lambda f: f.__name__.removeprefix("_tamper_"),
)
def test_resume_refuses_parts_that_would_mix_rows_and_changes_nothing(
    tamper: object,
    mixing: dict[str, Path],
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    out = _copy(mixing, tmp_path)
    name, words = tamper(out, mixing)  # type: ignore[operator]
    before = _folder_hash(out)
    capsys.readouterr()
    assert main(["sweep", "--resume", str(out), "--workers", "1"]) == EXIT_OUTPUT
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    assert f"parts/{name}: " in err[0] and words in err[0], err[0]
    assert err[0].endswith("nothing was changed")
    assert _folder_hash(out) == before
