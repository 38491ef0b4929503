"""The test loop: the whole suite on one core and on every core, and ``make test-fast``.

Run: ``make bench-tests``. Each figure is the wall time of one fresh ``pytest`` process
on this checkout, the three run one after another (``--rounds`` alternates them again),
so that a slow phase of the machine reaches all of them; the table gives each and its
ratio to the whole suite on one core.

``make bench-tests BASELINE=REV`` measures issue 48's done-when instead: ``make test`` of
commit REV and ``make test`` of this tree, alternated run for run (old, new, old, new,
...), and ``make test-fast`` of this tree after each pair. REV is checked out in a clean
``git worktree`` beside the checkout (in the temporary folder) and set up with its own
``make .venv/.compiled``, so it runs the suite and the tools it had, in a venv of its
own. ``TREE=REV`` measures a clean worktree of REV in place of the checkout (built the
same way), for when the checkout holds someone's unfinished edits. Each run's line gives
the load average before it: a figure taken while the machine did other work says so.

With ``--write FILE`` the table is written as Markdown with the command that made it.
"""

from __future__ import annotations

import argparse
import os
import platform
import re
import statistics
import subprocess
import sys
import tempfile
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


def _counts(stdout: str, returncode: int) -> str:
    """The counts pytest printed last (``1859 passed, 4 skipped in ...``), or the exit code."""
    lines = [line for line in stdout.splitlines() if re.search(r"\d+ (passed|failed)", line)]
    return lines[-1].strip("= ") if lines else f"exit {returncode}"


def _load() -> str:
    """The 1-minute load average now: 2 cores, so above about 0.5 means someone else works."""
    return f"{os.getloadavg()[0]:.2f}"


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
    return seconds, _counts(done.stdout, done.returncode)


def run_make(tree: Path, target: str, cold: bool = False) -> tuple[float, str]:
    """Wall seconds of ``make -C tree target`` (the tree's own venv), and its counts.

    ``cold``: with nothing kept from earlier runs, as on a fresh clone (CI): the compiled
    libraries in an empty folder (``TVOPT_CODEGEN_CACHE``, where the baseline kept them in
    ~/.cache across its runs) and, for a tree that keeps compiler runs (``.test-cache/``),
    ``TVOPT_TEST_CACHE=off``.
    """
    env = {k: v for k, v in os.environ.items() if k not in ("VIRTUAL_ENV", "PYTHONPATH")}
    if cold:
        with tempfile.TemporaryDirectory(prefix="tvopt-bench-cold-") as empty:
            env.update(TVOPT_CODEGEN_CACHE=empty, TVOPT_TEST_CACHE="off")
            return _timed_make(tree, target, env)
    return _timed_make(tree, target, env)


def _timed_make(tree: Path, target: str, env: dict[str, str]) -> tuple[float, str]:
    start = time.perf_counter()
    done = subprocess.run(
        ["make", "-C", str(tree), target],
        capture_output=True,
        text=True,
        check=False,
        env=env,
    )
    seconds = time.perf_counter() - start
    return seconds, _counts(done.stdout, done.returncode)


def worktree(rev: str) -> Path:
    """A clean worktree of ``rev`` with its own venv, made by its own Makefile.

    Kept between runs (``git worktree remove`` deletes it): its venv takes minutes to
    install. An existing worktree is moved to ``rev`` first (edits in it dropped: the
    folder is this script's), so a new commit of the same branch is measured, not the one
    it was made at.
    """
    sha = subprocess.run(
        ["git", "-C", str(ROOT), "rev-parse", "--verify", f"{rev}^{{commit}}"],
        check=True,
        capture_output=True,
        text=True,
    ).stdout.strip()
    folder = Path(tempfile.gettempdir()) / f"tvopt-bench-tests-{rev.replace('/', '-')}"
    if not folder.exists():
        subprocess.run(
            ["git", "-C", str(ROOT), "worktree", "add", "--detach", str(folder), sha],
            check=True,
            capture_output=True,
        )
    else:
        subprocess.run(
            ["git", "-C", str(folder), "checkout", "-q", "--force", "--detach", sha], check=True
        )
    # Its own setup target: the venv, the dev and optional extras, the bytecode.
    subprocess.run(["make", "-C", str(folder), ".venv/.compiled"], check=True)
    return folder


def describe(rev: str) -> str:
    """``rev`` as its short commit and date."""
    return subprocess.run(
        ["git", "-C", str(ROOT), "log", "-1", "--format=%h (%ad)", "--date=short", rev],
        check=True,
        capture_output=True,
        text=True,
    ).stdout.strip()


def against_baseline(args: argparse.Namespace) -> str:
    """``make test`` of the baseline and of this tree alternated, and ``make test-fast``."""
    old = worktree(args.baseline)
    new = worktree(args.tree) if args.tree else ROOT
    runs: dict[str, list[tuple[float, str, str]]] = {"old": [], "new": [], "fast": []}
    plan = [("old", old, "test", False), ("new", new, "test", False),
            ("fast", new, "test-fast", False)]  # fmt: skip
    if args.cold:
        runs.update({"old cold": [], "new cold": []})
        plan += [("old cold", old, "test", True), ("new cold", new, "test", True)]
    for _ in range(args.rounds):
        for key, tree, target, cold in plan:
            load = _load()
            seconds, counts = run_make(tree, target, cold)
            print(f"{seconds:7.0f} s  {key} make {target} (load {load}): {counts}", flush=True)
            runs[key].append((seconds, load, counts))

    def median(key: str) -> float:
        return statistics.median(s for s, _, _ in runs[key])

    this = f"this tree at {describe(args.tree)}" if args.tree else "this checkout"
    labels = {
        "old": f"`make test` of {describe(args.baseline)}",
        "new": f"`make test` of {this}",
        "fast": f"`make test-fast` of {this}",
        "old cold": f"`make test` of {describe(args.baseline)}, nothing kept from earlier runs",
        "new cold": f"`make test` of {this}, nothing kept from earlier runs",
    }
    rows = []
    for key, measured in runs.items():
        each = ", ".join(f"{s:.0f} s (load {load})" for s, load, _ in measured)
        rows.append(f"| {labels[key]} | {median(key):.0f} | {each} | {measured[-1][2]} |")
    ratio = median("new") / median("old")
    fifth = median("fast") / median("new")
    return "\n".join(
        [
            "| run | median wall s | each round (load average before it) | result |",
            "|---|---:|---|---|",
            *rows,
            "",
            f"- the whole suite against the baseline: **{ratio:.2f}** (issue 48 asks at most 0.5)",
            f"- `make test-fast` against `make test`: **{fifth:.2f}** (at most 0.2)",
            *(
                [
                    "- nothing kept from earlier runs (a fresh clone, as CI runs it), against "
                    f"the baseline alike: **{median('new cold') / median('old cold'):.2f}**"
                ]
                if args.cold
                else []
            ),
        ]
    )


def on_this_tree(args: argparse.Namespace) -> str:
    """The three runs of :data:`RUNS` on the checkout, best of the rounds."""
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
    return "\n".join(["| run | wall s | of one core | result |", "|---|---:|---:|---|", *rows])


def main() -> int:
    """Measure, print and optionally write the table."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--rounds", type=int, default=1)
    parser.add_argument("--baseline", help="a commit whose make test this tree's is set against")
    parser.add_argument("--tree", help="measure a clean worktree of this commit, not the checkout")
    parser.add_argument(
        "--cold", action="store_true", help="also run both with nothing kept from earlier runs"
    )
    parser.add_argument("--write", type=Path)
    args = parser.parse_args()
    if args.tree and not args.baseline:
        parser.error("--tree goes with --baseline")
    table = against_baseline(args) if args.baseline else on_this_tree(args)
    print(table)
    if args.write:
        machine = (
            f"{platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}"
        )
        if args.baseline:
            extra = (
                f" --baseline {args.baseline}"
                + (f" --tree {args.tree}" if args.tree else "")
                + (" --cold" if args.cold else "")
            )
            make = (
                f"make bench-tests BASELINE={args.baseline}"
                + (f" TREE={args.tree}" if args.tree else "")
                + (" COLD=1" if args.cold else "")
            )
            how = f"Median of {args.rounds} round(s), old and new alternated run for run"
        else:
            extra, make = "", "make bench-tests"
            how = f"Best of {args.rounds} round(s), the runs alternated"
        rounds = f" --rounds {args.rounds}" if args.rounds != 1 else ""
        args.write.write_text(
            "# The test loop\n\n"
            f"{how}. Machine: {machine}. Produced by `{make}"
            f"{f' ROUNDS={args.rounds}' if rounds else ''}` (`python benchmarks/bench_tests.py"
            f"{extra}{rounds} --write {args.write}`).\n\n" + table + "\n",
            encoding="utf-8",
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
