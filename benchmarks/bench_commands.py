"""The commands a user runs, cold: ``generate``, ``simulate`` and ``report`` per example.

Run: ``make bench-commands``. Each figure is the best of ``--repeats`` fresh
``tvopt-codegen`` processes (``benchmarks/cold.py``: wall time and the process's own peak
memory), into a new output folder each time, so that nothing is reused but what a user's
machine keeps between runs (the compiled-library and template caches). The targets are
issue 33's: ``generate`` at most 0.7 s, ``simulate`` at most 1.5 s (figures and
certificate included), ``report`` at most 1.0 s, for every bundled example.

With ``--write FILE`` the table is written as Markdown with the command that made it.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from cold import cold_run  # noqa: E402

#: Every bundled example without [references] (simulate runs those with exact jets too,
#: but their twins cost the same) and the targets of issue 33, in seconds.
EXAMPLES = (
    "integrator",
    "unicycle_switch",
    "two_unicycles_barrier",
    "two_unicycles_corridor",
    "pvtol",
    "flexible_joint",
    "unicycle_ring",
    "arm_on_line",
)
TARGETS = {"generate": 0.7, "simulate": 1.5, "report": 1.0}


def best(command: str, example: str, repeats: int) -> tuple[float, float]:
    """Best wall time (s) and its process's peak memory (MB) over ``repeats`` cold runs."""
    runs = []
    for _ in range(repeats):
        with tempfile.TemporaryDirectory() as scratch:
            argv = [sys.executable, "-m", "tvopt_codegen", command, example]
            argv += ["--out", str(Path(scratch) / "out")]
            if command == "generate":
                argv.append("--quiet")
            runs.append(cold_run(argv, timeout=300))
    fastest = min(runs, key=lambda r: r.wall)
    return fastest.wall, fastest.peak_mb


def main() -> None:
    """Time every command on every example; print (and write) the table."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3, help="cold runs per figure (best)")
    parser.add_argument("--write", help="write the Markdown table here")
    args = parser.parse_args()
    started = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())
    rows = []
    for example in EXAMPLES:
        cells = [best(command, example, args.repeats) for command in TARGETS]
        rows.append((example, cells))
        print(example, " ".join(f"{wall:.2f}s" for wall, _ in cells), flush=True)
    met = {
        command: sum(cells[i][0] <= target for _, cells in rows)
        for i, (command, target) in enumerate(TARGETS.items())
    }
    lines = [
        "# Commands, cold",
        "",
        f"Best of {args.repeats} fresh `tvopt-codegen` processes per figure (wall time, and the "
        f"process's own peak memory), each into a new output folder; the compiled-library and "
        f"template caches warm, as on a user's machine after a first run. Machine: "
        f"{platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}; "
        f"run at {started}. Produced by `make bench-commands` (`python "
        "benchmarks/bench_commands.py --write benchmarks/COMMANDS.md`).",
        "",
        "| example | generate | simulate | report |",
        "|---|---:|---:|---:|",
    ]
    for example, cells in rows:
        lines.append(
            f"| {example} | "
            + " | ".join(f"{wall:.2f} s ({peak:.0f} MB)" for wall, peak in cells)
            + " |"
        )
    lines += [
        "",
        "Targets (issue 33), examples within them: "
        + "; ".join(
            f"`{command}` at most {target:g} s: {met[command]} of {len(rows)}"
            for command, target in TARGETS.items()
        )
        + ".",
        "",
    ]
    text = "\n".join(lines)
    print(text)
    if args.write:
        Path(args.write).write_text(text, encoding="utf-8")


if __name__ == "__main__":
    main()
