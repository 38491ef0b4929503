"""One fresh process, timed from outside: its wall time and its own peak memory.

Linux hands a process the peak resident size of the process it was forked from
(``ru_maxrss`` survives ``exec``). A bench that imports sympy and CasADi, or has run
CasADi's pipeline for 256 agents, would see every process it starts report at least its
own size (538 MB for a one-agent ring). So each command is started from a small launcher
interpreter, which reads the command's ``wait4`` usage and reports it in a file.
"""

from __future__ import annotations

import json
import math
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

#: Starts the command, waits for it (killing it after the timeout) and writes its wall
#: time, peak resident size (kB), exit code and whether it was killed to the report.
_LAUNCHER = """
import json, os, subprocess, sys, time
report, timeout, command = sys.argv[1], float(sys.argv[2]), sys.argv[3:]
started = time.perf_counter()
child = subprocess.Popen(command)
killed = False
while True:
    pid, status, usage = os.wait4(child.pid, os.WNOHANG)
    if pid:
        break
    if time.perf_counter() > started + timeout:
        child.kill()
        killed = True
        pid, status, usage = os.wait4(child.pid, 0)
        break
    time.sleep(0.01)
wall = time.perf_counter() - started
with open(report, "w") as out:
    json.dump([wall, usage.ru_maxrss, os.waitstatus_to_exitcode(status), killed], out)
"""


@dataclass(frozen=True)
class ColdRun:
    """What one process took: wall seconds, its peak resident size (MB), its output."""

    wall: float
    peak_mb: float
    stdout: str
    stderr: str


def cold_run(command: list[str], timeout: float) -> ColdRun:
    """Run ``command`` in a fresh process started by the launcher; raise if it fails.

    Parameters
    ----------
    command : list of str
        The program and its arguments.
    timeout : float
        Seconds after which the command is killed (and this raises).

    Returns
    -------
    ColdRun
    """
    with tempfile.TemporaryDirectory(prefix="cold-") as tmp:
        report = Path(tmp) / "report.json"
        launcher = [sys.executable, "-c", _LAUNCHER, str(report), str(timeout), *command]
        done = subprocess.run(
            launcher, check=False, capture_output=True, text=True, timeout=timeout + 60
        )
        if done.returncode != 0 or not report.exists():
            raise RuntimeError(f"the launcher failed ({done.returncode}): {done.stderr[-500:]}")
        wall, peak_kb, code, killed = json.loads(report.read_text())
    what = " ".join(command[:4])
    if killed:
        raise RuntimeError(f"{what} timed out after {timeout:g} s")
    if code != 0:
        raise RuntimeError(f"{what} failed ({code}): {done.stderr[-500:]}")
    return ColdRun(wall, peak_kb / 1024, done.stdout, done.stderr)


def best_wall(command: list[str], runs: int) -> float:
    """Best wall time of ``runs`` fresh processes, in seconds, timed from here.

    For commands short enough that the launcher's own start would weigh (``--version``);
    :func:`cold_run` gives each process's own figures.
    """
    best = math.inf
    for _ in range(runs):
        start = time.perf_counter()
        subprocess.run(command, check=True, capture_output=True)
        best = min(best, time.perf_counter() - start)
    return best
