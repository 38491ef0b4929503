"""Cold ``generate`` of large specs, this checkout against a baseline commit, run for run.

Run: ``make bench-baseline BASELINE=REV``. ``make bench-derive`` compares with CasADi in
the same minute, but this machine's slow phases stretch sympy's work and CasADi's C++
differently, so its ratios drift between runs by as much as a change gains. Here the
same specs run with both trees, alternating (``bench_commands.export`` and its runner),
and the ratio of the best runs is the change's own: the rings of 32 and 128 agents and
the k = 12 chain by default.

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

from bench_commands import ROOT, Setup, export, once  # noqa: E402
from bench_derive import ring_spec  # noqa: E402


def main() -> None:
    """Time each spec with both trees; print (and write) the table."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--baseline", required=True, help="the commit to compare with")
    parser.add_argument("--specs", default="ring32,ring128,chain12")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--write", help="write the Markdown table here")
    args = parser.parse_args()
    started = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        (folder / "tree").mkdir()
        # Each on the command line's default engine (bench_commands' setups).
        trees: list[Setup] = [(ROOT, None), (export(args.baseline, folder / "tree"), None)]
        for name in args.specs.split(","):
            if name == "chain12":
                spec = ROOT / "benchmarks" / "chain12.toml"
            else:
                spec = ring_spec(int(name.removeprefix("ring")), folder)
            runs: list[list[float]] = [[], []]
            for _ in range(args.repeats):
                for mine, tree in zip(runs, trees, strict=True):
                    mine.append(once(tree, "generate", str(spec))[0])
            rows.append((name, runs))
            print(name, [f"{min(r):.2f}" for r in runs], flush=True)
    lines = [
        "# Cold generate against a baseline commit",
        "",
        f"Best of {args.repeats} cold `tvopt-codegen generate` processes per tree, the trees "
        f"alternating run for run. Machine: {platform.machine()}, {os.cpu_count()} cores, "
        f"Python {platform.python_version()}; run at {started}. Produced by `make "
        f"bench-baseline BASELINE={args.baseline}` (`python benchmarks/bench_baseline.py "
        f"--baseline {args.baseline} --write benchmarks/BASELINE.md`).",
        "",
        f"| spec | this checkout s | {args.baseline} s | ratio | runs now | runs then |",
        "|---|---:|---:|---:|---|---|",
    ]
    for name, (now, then) in rows:
        lines.append(
            f"| {name} | {min(now):.2f} | {min(then):.2f} | {min(now) / min(then):.2f} | "
            + ", ".join(f"{x:.2f}" for x in now)
            + " | "
            + ", ".join(f"{x:.2f}" for x in then)
            + " |"
        )
    text = "\n".join([*lines, ""])
    print(text)
    if args.write:
        Path(args.write).write_text(text, encoding="utf-8")


if __name__ == "__main__":
    main()
