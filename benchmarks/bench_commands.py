"""The commands a user runs, cold: ``generate``, ``simulate`` and ``report`` per example.

Run: ``make bench-commands``. Each figure is the best of ``--repeats`` fresh
``tvopt-codegen`` processes (``benchmarks/cold.py``: wall time and the process's own peak
memory), into a new output folder each time, so that nothing is reused but what a user's
machine keeps between runs (the compiled-library and template caches). The targets are
issue 33's: ``generate`` at most 0.7 s, ``simulate`` at most 1.5 s (figures and
certificate included), ``report`` at most 1.0 s, for every bundled example.

With ``--baseline REV`` every figure is measured for that commit too (its tree exported
with ``git archive``), each baseline run right after the current one, and the table
gives both and their ratio: this machine has slow phases of minutes in which every
figure is up to twice as long, and a ratio of runs a few seconds apart cancels them.

With ``--engines A,B`` the checkout runs on each symbolic engine in turn (``--engine``
before the command), the first engine's figure first and the others' in parentheses
with their ratio, measured alternately as a baseline is.

With ``--write FILE`` the table is written as Markdown with the command that made it.
"""

from __future__ import annotations

import argparse
import os
import platform
import subprocess
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
    "planar_arm3",
    "drag_vehicle",
    "ur5_tip",
)
#: Issue 49's targets (issue 33's, with report at 1.5 s).
TARGETS = {"generate": 0.7, "simulate": 1.5, "report": 1.5}


#: Runs the command line of the tree given first, not the installed one: the editable
#: install's import hook, which would find the checkout's package whatever the path, is
#: removed first. Both trees run through it, so they start alike.
_TREE = """
import runpy, sys
tree = sys.argv[1]
sys.meta_path[:] = [f for f in sys.meta_path if "__editable__" not in repr(f)]
sys.path.insert(0, tree)
sys.argv = ["tvopt-codegen", *sys.argv[2:]]
runpy.run_module("tvopt_codegen", run_name="__main__", alter_sys=True)
"""

ROOT = Path(__file__).resolve().parent.parent


def export(rev: str, folder: Path) -> Path:
    """The tree of commit ``rev`` (its package and templates), written into ``folder``."""
    archive = subprocess.run(
        ["git", "-C", str(ROOT), "archive", rev, "tvopt_codegen", "templates"],
        check=True,
        capture_output=True,
    )
    subprocess.run(["tar", "-x", "-C", str(folder)], input=archive.stdout, check=True)
    # Its bytecode, as the checkout's setup compiles the checkout's: with
    # PYTHONDONTWRITEBYTECODE set, an uncompiled tree is compiled anew by every run
    # (0.1-0.3 s of a small command), which made the checkout look faster than it is.
    subprocess.run(
        [sys.executable, "-m", "compileall", "-q", str(folder / "tvopt_codegen")], check=True
    )
    return folder


#: A configuration: a package tree and the engine it runs on (None: the CLI's default).
Setup = tuple[Path, str | None]


def once(setup: Setup, command: str, example: str) -> tuple[float, float]:
    """One cold run of ``command`` on ``example`` with a tree and engine: (s, MB)."""
    tree, engine = setup
    with tempfile.TemporaryDirectory() as scratch:
        argv = [sys.executable, "-c", _TREE, str(tree)]
        argv += ([] if engine is None else ["--engine", engine]) + [command, example]
        argv += ["--out", str(Path(scratch) / "out")]
        if command == "generate":
            argv.append("--quiet")
        run = cold_run(argv, timeout=300)
    return run.wall, run.peak_mb


def best(trees: list[Setup], command: str, example: str, repeats: int) -> list[tuple[float, float]]:
    """Per tree, the best wall time (s) and its peak memory (MB) over ``repeats`` runs.

    The trees take turns, run after run, so that each figure's runs share the
    machine's phase.
    """
    runs: list[list[tuple[float, float]]] = [[] for _ in trees]
    for _ in range(repeats):
        for mine, tree in zip(runs, trees, strict=True):
            mine.append(once(tree, command, example))
    return [min(mine) for mine in runs]


def main() -> None:
    """Time every command on every example; print (and write) the table."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3, help="cold runs per figure (best)")
    parser.add_argument("--baseline", help="a commit to measure beside the checkout")
    parser.add_argument("--write", help="write the Markdown table here")
    parser.add_argument("--engines", help="symbolic engines to run the checkout on, first first")
    args = parser.parse_args()
    started = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())
    engines: list[str | None] = list(args.engines.split(",")) if args.engines else [None]
    with tempfile.TemporaryDirectory(prefix="baseline-") as tmp:
        trees: list[Setup] = [(ROOT, engine) for engine in engines]
        if args.baseline:
            trees.append((export(args.baseline, Path(tmp)), None))
        rows = []
        for example in EXAMPLES:
            cells = [best(trees, command, example, args.repeats) for command in TARGETS]
            rows.append((example, cells))
            print(example, " ".join(f"{c[0][0]:.2f}s" for c in cells), flush=True)
    met = {
        command: sum(cells[i][0][0] <= target for _, cells in rows)
        for i, (command, target) in enumerate(TARGETS.items())
    }
    compared = ""
    if args.engines:
        first, *others = engines
        compared += (
            f" Each cell: this checkout on {first}, then on {', '.join(map(str, others))} in "
            "parentheses (their runs alternating), each with the ratio first / other."
        )
    if args.baseline:
        revision = subprocess.run(
            ["git", "-C", str(ROOT), "rev-parse", "--short", args.baseline],
            check=True,
            capture_output=True,
            text=True,
        ).stdout.strip()
        compared = (
            f" Each cell: this checkout, then commit {revision} in parentheses (its runs "
            "alternating with this checkout's), then the ratio now / then, which the "
            "machine's phase cancels from."
        )
    lines = [
        "# Commands, cold",
        "",
        f"Best of {args.repeats} fresh `tvopt-codegen` processes per figure (wall time, and the "
        f"process's own peak memory), each into a new output folder; the compiled-library and "
        f"template caches warm, as on a user's machine after a first run. Machine: "
        f"{platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}; "
        f"run at {started}. Produced by `make bench-commands` (`python "
        "benchmarks/bench_commands.py"
        + (f" --baseline {args.baseline}" if args.baseline else "")
        + (f" --engines {args.engines}" if args.engines else "")
        + " --write benchmarks/COMMANDS.md`)."
        + compared,
        "",
        "| example | generate | simulate | report |",
        "|---|---:|---:|---:|",
    ]
    for example, cells in rows:
        texts = []
        for cell in cells:
            (wall, peak), *before = cell
            text = f"{wall:.2f} s ({peak:.0f} MB)"
            for other, _ in before:
                text += f" ({other:.2f} s) {wall / other:.2f}x"
            texts.append(text)
        lines.append(f"| {example} | " + " | ".join(texts) + " |")
    lines += [
        "",
        "Targets (issue 49), examples within them: "
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
