"""The test loop: the whole suite on one core and on every core, and ``make test-fast``.

Run: ``make bench-tests``. Each figure is the wall time of one fresh ``pytest`` process
on this checkout, the three run one after another (``--rounds`` alternates them again),
so that a slow phase of the machine reaches all of them; the table gives each and its
ratio to the whole suite on one core.

With ``--write FILE`` the table is written as Markdown with the command that made it.
"""

from __future__ import annotations

import argparse
import os
import platform
import re
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent

#: (label, pytest arguments): what ``make test`` and ``make test-fast`` run, and the
#: suite as it ran before the loop used both cores.
RUNS = (
    ("whole suite, one core (`pytest -p no:xdist`)", ["-p", "no:xdist"]),
    ("whole suite, every core (`make test`)", ["-n", "auto", "--dist", "worksteal"]),
    ("quick part, every core (`make test-fast`)",
     ["-n", "auto", "--dist", "worksteal", "-m", "not slow"]),
)  # fmt: skip


def run_once(args: list[str]) -> tuple[float, str]:
    """Wall seconds of one pytest process, and its last line (the counts)."""
    start = time.perf_counter()
    done = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", *args],
        cwd=ROOT,
        capture_output=True,
        text=True,
        check=False,
    )
    seconds = time.perf_counter() - start
    lines = [line for line in done.stdout.splitlines() if re.search(r"\d+ passed", line)]
    return seconds, (lines[-1].strip("= ") if lines else f"exit {done.returncode}")


def main() -> int:
    """Measure, print and optionally write the table."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--rounds", type=int, default=1)
    parser.add_argument("--write", type=Path)
    args = parser.parse_args()
    best: dict[str, tuple[float, str]] = {}
    for _ in range(args.rounds):
        for label, pytest_args in RUNS:
            seconds, counts = run_once(pytest_args)
            print(f"{seconds:7.0f} s  {label}: {counts}", flush=True)
            if label not in best or seconds < best[label][0]:
                best[label] = (seconds, counts)
    whole = best[RUNS[0][0]][0]
    rows = [
        f"| {label} | {s:.0f} | {s / whole:.2f} | {counts} |" for label, (s, counts) in best.items()
    ]
    table = "\n".join(
        [
            "| run | wall s | of one core | result |",
            "|---|---:|---:|---|",
            *rows,
        ]
    )
    print(table)
    if args.write:
        python = platform.python_version()
        machine = f"{platform.machine()}, {os.cpu_count()} cores, Python {python}"
        args.write.write_text(
            "# The test loop\n\n"
            f"Best of {args.rounds} round(s), the runs alternated. Machine: {machine}. "
            "Produced by `make bench-tests` "
            f"(`python benchmarks/bench_tests.py --write {args.write}`).\n\n" + table + "\n",
            encoding="utf-8",
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
