"""Faults: signals, kills mid-write, full or read-only disks, missing compilers, races.

The output folder must hold the old files or the new ones (never a mix, never half a
file, no temporary litter), and every failure is one clear line with its exit code.
"""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tvopt_codegen import emit
from tvopt_codegen.cli import main
from tvopt_codegen.errors import EXIT_BUILD, EXIT_OUTPUT

from .conftest import ROOT, run_main

RING = (ROOT / "tvopt_codegen" / "examples" / "unicycle_ring.toml").read_text()


def _snapshot(folder: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir())}


def _cli(
    *args: str, env: dict[str, str] | None = None, cwd: Path | None = None
) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, "-m", "tvopt_codegen", *args],
        cwd=cwd,
        env={**os.environ, **(env or {})},
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def _into_the_derivation(pid: int, cpu_seconds: float = 0.5) -> None:
    """Wait until process ``pid`` has run ``cpu_seconds`` of CPU: past its imports (the
    command loads lazily: ``generate`` and ``simulate`` call ``derive`` after 0.17-0.22 s
    of CPU here, measured 2026-12-05, the painter already started), inside the ring's
    derivation (8 s here). Twice that and more is margin enough: every CPU second waited
    beyond it is a second of derivation each of these tests' processes spent for nothing.

    Counted in the process's own CPU time (Linux's /proc), not on the wall: a loaded
    machine neither signals it still importing nor waits longer than needed on an idle
    one. Without /proc, the wall: 4 s.
    """
    stat = Path(f"/proc/{pid}/stat")
    if not stat.exists():
        time.sleep(4.0)
        return
    tick = os.sysconf("SC_CLK_TCK")
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except (FileNotFoundError, ProcessLookupError):
            return  # it ended: the test's own check says how
        if (int(fields[11]) + int(fields[12])) / tick >= cpu_seconds:
            return
        time.sleep(0.05)


def _slow_spec(tmp_path: Path) -> Path:
    """A spec whose derivation takes many seconds: the ring of 64 unicycles."""
    text, count = re.subn(r"(?m)^i = \d+", "i = 64", RING)
    assert count == 1
    path = tmp_path / "slow.toml"
    path.write_text(text)
    return path


@pytest.mark.parametrize(
    ("sig", "code", "word"),
    [(signal.SIGINT, 130, "interrupted"), (signal.SIGTERM, 143, "terminated")],
)
def test_signal_during_derivation_writes_nothing(
    sig: int, code: int, word: str, tmp_path: Path
) -> None:
    out = tmp_path / "out"
    out.mkdir()
    (out / "keep.txt").write_text("mine")
    before = _snapshot(out)
    proc = _cli("generate", str(_slow_spec(tmp_path)), "--out", str(out), "--max-size", "100000000")
    _into_the_derivation(proc.pid)  # past the imports, inside the derivation
    assert proc.poll() is None, proc.communicate()
    proc.send_signal(sig)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == code, err
    assert err.strip().count("\n") == 0 and word in err and "Traceback" not in err
    assert _snapshot(out) == before


def _children(pid: int) -> list[int]:
    """The processes ``pid`` started (Linux's /proc)."""
    found = []
    for task in Path(f"/proc/{pid}/task").iterdir():
        found += [int(c) for c in (task / "children").read_text().split()]
    return found


def _gone(pid: int, within: float) -> bool:
    """Whether ``pid`` has ended (or is a zombie nobody needs) within ``within`` seconds."""
    deadline = time.monotonic() + within
    while time.monotonic() < deadline:
        try:
            state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
        except (FileNotFoundError, ProcessLookupError):
            return True
        if state == "Z":
            return True
        time.sleep(0.05)
    return False


def _signalled(proc: subprocess.Popen[str], sig: int, group: bool) -> str:
    """Send ``sig`` to the command (or to its whole group, as a terminal's Ctrl-C does);
    its stderr once it has ended."""
    if group:
        os.killpg(proc.pid, sig)
    else:
        proc.send_signal(sig)
    _, err = proc.communicate(timeout=60)
    return err


@pytest.mark.skipif(not Path("/proc/self/task").exists(), reason="needs Linux's /proc")
@pytest.mark.parametrize(
    ("sig", "code", "group"),
    [
        (signal.SIGINT, 130, True),  # Ctrl-C on a terminal: every process of the group
        (signal.SIGTERM, 143, False),
        (signal.SIGTERM, 143, True),
        (signal.SIGKILL, -9, False),  # nothing runs in the command: its pipe closes
    ],
)
def test_a_signal_during_simulate_leaves_no_drawing_process(
    sig: int, code: int, group: bool, tmp_path: Path
) -> None:
    """simulate's drawing process (drawing.Painter) ends with the command, however it ends."""
    out = tmp_path / "out"
    proc = subprocess.Popen(
        [sys.executable, "-m", "tvopt_codegen", "simulate", str(_slow_spec(tmp_path))]
        + ["--out", str(out), "--max-size", "100000000"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
    )
    _into_the_derivation(proc.pid)  # the drawing process waiting for figures
    assert proc.poll() is None, proc.communicate()
    drawing = _children(proc.pid)
    assert len(drawing) == 1
    err = _signalled(proc, sig, group)
    assert proc.returncode == code, err
    if sig != signal.SIGKILL:
        assert err.strip().count("\n") == 0 and "Traceback" not in err
    assert _gone(drawing[0], 10.0)
    assert not out.exists()


KILLER = """
import os, signal, sys
from tvopt_codegen import emit
real = os.replace
count = [0]
def replace(src, dst):
    real(src, dst)
    if str(dst).endswith(".c"):
        os.kill(os.getpid(), signal.SIGKILL)  # killed between two renames
emit.os.replace = replace
from tvopt_codegen.cli import main
sys.exit(main(sys.argv[1:]))
"""


def test_killed_between_renames_is_completed_by_the_next_run(tmp_path: Path) -> None:
    out = tmp_path / "out"
    assert main(["generate", "integrator", "--backend", "c", "--out", str(out), "--quiet"]) == 0
    old = _snapshot(out)
    spec = tmp_path / "integrator.toml"
    spec.write_text(
        (ROOT / "tvopt_codegen" / "examples" / "integrator.toml")
        .read_text()
        .replace("w = 2.0", "w = 3.0")
    )
    killed = subprocess.run(
        [
            sys.executable,
            "-c",
            KILLER,
            "generate",
            str(spec),
            "--backend",
            "c",
            "--out",
            str(out),
            "--quiet",
        ],
        capture_output=True,
        text=True,
        check=False,
    )
    assert killed.returncode == -signal.SIGKILL
    journals = list(out.glob(".tvopt-journal-*.json"))
    assert len(journals) == 1  # the interrupted transaction is on record
    for name in ("integrator.c", "integrator.h", "integrator_c.py"):
        text = (out / name).read_bytes()
        assert text.endswith(b"\n") and b"content sha256" in text  # whole files only
    emit.recover(out)  # what the next run into the folder does first
    new = _snapshot(out)
    assert sorted(new) == sorted(old)
    assert all(new[n] != old[n] for n in ("integrator.c", "integrator.h", "integrator_c.py"))
    assert b"3.0" in new["integrator.h"] + new["integrator.c"]
    assert not [p for p in out.iterdir() if p.name.startswith(".")]


def test_full_disk(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "out"
    assert main(["generate", "integrator", "--out", str(out), "--quiet"]) == 0
    before = _snapshot(out)
    real_fdopen = os.fdopen

    def full(fd: int, *args: object, **kwargs: object) -> object:
        os.close(fd)
        return real_fdopen(os.open("/dev/full", os.O_WRONLY), "wb")

    monkeypatch.setattr(emit.os, "fdopen", full)
    spec = tmp_path / "integrator.toml"
    spec.write_text(
        (ROOT / "tvopt_codegen" / "examples" / "integrator.toml")
        .read_text()
        .replace("w = 2.0", "w = 5.0")
    )
    assert main(["generate", str(spec), "--out", str(out)]) == EXIT_OUTPUT
    err = capsys.readouterr().err
    assert "No space left on device" in err and err.count("\n") == 1
    assert _snapshot(out) == before


def test_read_only_folder(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    mount = tmp_path / "ro"
    mount.mkdir()
    done = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", "ro,size=1m", "tmpfs", str(mount)],
        capture_output=True,
        check=False,
    )
    if done.returncode != 0:
        pytest.skip(f"cannot mount a read-only tmpfs here: {done.stderr.decode().strip()}")
    try:
        assert main(["generate", "integrator", "--out", str(mount)]) == EXIT_OUTPUT
        err = capsys.readouterr().err
        assert "Read-only file system" in err and err.count("\n") == 1
        assert list(mount.iterdir()) == []
    finally:
        subprocess.run(["umount", str(mount)], check=False)


def test_missing_output_parent(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    target = tmp_path / "no" / "such" / "folder"
    assert main(["generate", "integrator", "--out", str(target)]) == EXIT_OUTPUT
    assert "does not exist" in capsys.readouterr().err
    assert not (tmp_path / "no").exists()


def test_no_c_compiler(tmp_path: Path) -> None:
    empty = tmp_path / "bin"
    empty.mkdir()
    env = {"PATH": str(empty), "CC": "", "TVOPT_CODEGEN_CACHE": str(tmp_path / "c")}
    done = run_main(
        "simulate", "integrator", "--backend", "c", "--out", str(tmp_path / "o"), env=env
    )
    err = done.stderr
    assert done.returncode == EXIT_BUILD, err
    assert err.count("\n") == 1 and "no C compiler found" in err and "Traceback" not in err
    assert not (tmp_path / "o").exists()
    # The Python backend is unaffected.
    done = run_main(
        "simulate", "integrator", "--out", str(tmp_path / "py"), "--points", "21", env=env
    )
    assert done.returncode == 0, done.stderr
    assert "certificate: PASSED" in done.stdout


def test_compiler_error_is_one_line_and_nothing_cached(tmp_path: Path) -> None:
    cache = tmp_path / "cache"
    env = {"TVOPT_CODEGEN_CFLAGS": "-fno-such-flag", "TVOPT_CODEGEN_CACHE": str(cache)}
    done = run_main(
        "simulate", "integrator", "--backend", "c", "--out", str(tmp_path / "o"), env=env
    )
    assert done.returncode == EXIT_BUILD, done.stderr
    assert done.stderr.count("\n") == 1 and "failed" in done.stderr
    assert not list(cache.glob("*.so"))


def test_two_runs_at_once_on_the_same_output(tmp_path: Path) -> None:
    out = tmp_path / "out"
    reference = tmp_path / "ref"
    assert (
        main(
            [
                "generate",
                "two_unicycles_barrier",
                "--backend",
                "c",
                "--out",
                str(reference),
                "--quiet",
            ]
        )
        == 0
    )
    procs = [
        _cli("generate", "two_unicycles_barrier", "--backend", "c", "--out", str(out), "--quiet")
        for _ in range(2)
    ]
    results = [p.communicate(timeout=120) for p in procs]
    assert [p.returncode for p in procs] == [0, 0], results
    assert _snapshot(out) == _snapshot(reference)


def test_output_folder_created_by_another_run_in_between(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The window between "does it exist" and mkdir: the other run wins, we go on."""
    out = tmp_path / "out"
    real_mkdir = Path.mkdir

    def racing_mkdir(self: Path, *args: object, **kwargs: object) -> None:
        real_mkdir(self)  # the other run, just before us
        real_mkdir(self)  # ours: FileExistsError

    monkeypatch.setattr(Path, "mkdir", racing_mkdir)
    assert emit.prepare_folder(out) == out
    assert out.is_dir()


def test_output_path_created_as_a_file_in_between(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    out = tmp_path / "out"

    def racing_mkdir(self: Path, *args: object, **kwargs: object) -> None:
        self.write_text("not a folder")
        raise FileExistsError(17, "File exists", str(self))

    monkeypatch.setattr(Path, "mkdir", racing_mkdir)
    with pytest.raises(emit.OutputError, match="not a folder"):
        emit.prepare_folder(out)


def _dead_pid() -> int:
    """The pid of a process that has ended (``true``'s: an interpreter costs 20 ms more)."""
    child = subprocess.Popen(["true"])
    assert child.wait(timeout=60) == 0
    return child.pid


def _journal(folder: Path, renames: list[list[str]]) -> None:
    record = {"pid": _dead_pid(), "renames": renames}
    (folder / ".tvopt-journal-1-abcd.json").write_text(json.dumps(record))


def test_recovery_never_moves_or_replaces_a_users_file(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "out"
    assert main(["generate", "integrator", "--out", str(out), "--quiet"]) == 0
    victim = tmp_path / "victim.txt"
    victim.write_text("the user's notes\n")
    notes = out / "notes.txt"
    notes.write_text("edited by hand\n")
    legit_temp = f".notes.txt.{_dead_pid()}-x1y2z3.tvopt-tmp"
    (out / legit_temp).write_text("planted\n")
    _journal(
        out,
        [
            ["../victim.txt", "stolen.txt"],  # a path out of the folder
            [str(victim), "stolen2.txt"],  # an absolute path
            [legit_temp, "notes.txt"],  # the tool's name, but over an edited file
            [".x.1-abc.tvopt-tmp", "../escape.txt"],  # a target out of the folder
        ],
    )
    capsys.readouterr()
    assert main(["generate", "integrator", "--out", str(out), "--quiet"]) == 0
    err = capsys.readouterr().err
    assert victim.read_text() == "the user's notes\n"
    assert not (out / "stolen.txt").exists() and not (out / "stolen2.txt").exists()
    assert notes.read_text() == "edited by hand\n"
    assert not (tmp_path / "escape.txt").exists()
    assert err.count("left alone while finishing") == 4, err
    assert "'notes.txt' was changed since tvopt-codegen wrote it" in err
    assert not list(out.glob(".tvopt-journal-*"))


def test_a_library_caller_hears_of_what_recovery_left_alone_as_a_warning(
    tmp_path: Path,
) -> None:
    # The writer prints nothing: without a warn of the caller's, a journal entry left
    # alone is a RuntimeWarning, which the caller filters or records like any other.
    out = tmp_path / "out"
    emit.write_files({"a.txt": "one\n"}, out)
    victim = tmp_path / "victim.txt"
    victim.write_text("the user's notes\n")
    _journal(out, [["../victim.txt", "stolen.txt"]])
    with pytest.warns(RuntimeWarning, match="left alone while finishing"):
        emit.write_files({"a.txt": "two\n"}, out)
    heard: list[str] = []
    _journal(out, [["../victim.txt", "stolen.txt"]])
    emit.write_files({"a.txt": "three\n"}, out, warn=heard.append)
    assert len(heard) == 1 and "left alone while finishing" in heard[0]
    assert victim.read_text() == "the user's notes\n" and (out / "a.txt").read_text() == "three\n"


def test_a_fifo_named_like_the_manifest_or_a_journal_does_not_hang(tmp_path: Path) -> None:
    out = tmp_path / "out"
    out.mkdir()
    os.mkfifo(out / ".tvopt-manifest.json")
    os.mkfifo(out / ".tvopt-journal-1-abcd.json")
    proc = _cli("report", "integrator", "--out", str(out), "--format", "md")
    _, err = proc.communicate(timeout=60)
    # The manifest is not a regular file: the report cannot record itself, and says so.
    assert proc.returncode in (0, 4), err
    assert err.count("\n") <= 1


@pytest.mark.parametrize(
    ("env", "message"),
    [
        (
            {"TVOPT_CODEGEN_CACHE": "/dev/null/cache"},
            "the cache folder /dev/null/cache cannot be used",
        ),
        ({"TVOPT_CODEGEN_CFLAGS": "-ffast-math"}, "failed"),
        ({"TVOPT_CODEGEN_CFLAGS": "-fno-such-flag-at-all"}, "failed"),
    ],
)
def test_a_failing_c_build_writes_nothing(
    env: dict[str, str], message: str, tmp_path: Path
) -> None:
    env = {"TVOPT_CODEGEN_CACHE": str(tmp_path / "cache"), **env}
    out = tmp_path / "o"
    done = run_main("simulate", "integrator", "--backend", "c", "--out", str(out), env=env)
    err = done.stderr
    assert done.returncode == EXIT_BUILD, err
    assert err.count("\n") == 1 and message in err and "Traceback" not in err
    assert not out.exists()
    # An existing folder is left exactly as it was.
    out.mkdir()
    (out / "keep.txt").write_text("mine")
    done = run_main("simulate", "integrator", "--backend", "c", "--out", str(out), env=env)
    assert done.returncode == EXIT_BUILD
    assert [p.name for p in out.iterdir()] == ["keep.txt"]


@pytest.mark.parametrize(
    "command",
    [["generate"], ["report"], ["simulate"], ["export", "--fmu"]],
)
def test_a_missing_output_parent_is_refused_before_deriving(
    command: list[str],
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The folder is checked first: a typo in --out costs no derivation."""
    from tvopt_codegen.commands import common

    def derive(_args: object) -> object:
        raise AssertionError("derived before checking --out")

    monkeypatch.setattr(common, "derive", derive)
    target = tmp_path / "no" / "such" / "folder"
    name, *rest = command
    assert main([name, "integrator", *rest, "--out", str(target)]) == EXIT_OUTPUT
    err = capsys.readouterr().err
    assert "does not exist" in err and err.count("\n") == 1
    assert not (tmp_path / "no").exists()


@pytest.mark.skipif(not Path("/proc/self/task").exists(), reason="needs Linux's /proc")
@pytest.mark.parametrize(
    ("sig", "code", "group"),
    [(signal.SIGINT, 130, True), (signal.SIGTERM, 143, False)],
)
def test_a_signal_while_the_constraints_side_process_runs_ends_both_side_processes(
    sig: int, code: int, group: bool, tmp_path: Path
) -> None:
    """A constrained spec's simulate runs two side processes (the painter and the SLSQP
    solver, runs/side.py) while it integrates: a signal then ends the command in one line,
    both side processes with it, and nothing is written."""
    out = tmp_path / "out"
    proc = subprocess.Popen(
        [sys.executable, "-m", "tvopt_codegen", "simulate", "two_unicycles_corridor"]
        + ["--out", str(out), "--t-final", "300", "--rtol", "1e-12"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
    )
    deadline = time.monotonic() + 60
    side: list[int] = []
    while len(side) < 2 and proc.poll() is None and time.monotonic() < deadline:
        side = _children(proc.pid)
        time.sleep(0.01)
    assert len(side) == 2 and proc.poll() is None, proc.communicate()
    err = _signalled(proc, sig, group)
    assert proc.returncode == code, err
    last = [line for line in err.splitlines() if "simulated t =" not in line]
    assert len(last) == 1 and "Traceback" not in err, err
    assert all(_gone(pid, 10.0) for pid in side)
    assert not out.exists()


def _swallowing(function: object, sig: int) -> object:
    """``function``, run after a signal to this process that a blanket ``except`` eats.

    As compiled code does (NumPy's random module as it first loads, SymEngine's matrix
    iterator): the handler's exception is raised inside it and never leaves it.
    """

    def wrapper(*args: object, **kwargs: object) -> object:
        try:
            os.kill(os.getpid(), sig)
            time.sleep(0.5)  # the handler runs here, at the next bytecode
        except BaseException:  # noqa: BLE001, S110 - the point: a library that swallows
            pass
        return function(*args, **kwargs)  # type: ignore[operator]

    return wrapper


@pytest.mark.parametrize(
    ("sig", "code", "word"),
    [(signal.SIGINT, 130, "interrupted"), (signal.SIGTERM, 143, "terminated")],
)
@pytest.mark.parametrize("where", ["derivation", "simulation"])
def test_a_signal_swallowed_by_a_library_still_ends_the_command_writing_nothing(
    sig: int,
    code: int,
    word: str,
    where: str,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    from tvopt_codegen.maths import lie
    from tvopt_codegen.simulation import run as simulation

    if where == "derivation":
        monkeypatch.setattr(lie.Sampler, "__init__", _swallowing(lie.Sampler.__init__, sig))
    else:
        monkeypatch.setattr(
            simulation.dopri, "integrate", _swallowing(simulation.dopri.integrate, sig)
        )
    out = tmp_path / "out"
    assert main(["simulate", "integrator", "--out", str(out)]) == code
    err = capsys.readouterr().err
    assert err.strip().count("\n") == 0 and word in err, err
    assert not out.exists()
    # The next command in the same process is not interrupted by what was remembered.
    monkeypatch.undo()
    assert main(["generate", "integrator", "--out", str(out)]) == 0
