"""``make coverage-fast``'s verdict: every module of the package runs in ``make test-fast``.

Reads the coverage data ``coverage run`` left and exits 1 naming each module of which no
line ran (a module ``make test-fast`` never imports or never calls), with the share of
lines run overall.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import coverage

#: Modules that only ever run in a process of their own, which ``coverage run`` does not
#: follow: the console script's entry (the suite runs it as a subprocess).
OWN_PROCESS = ("tvopt_codegen/__main__.py",)


def unexercised(report: dict[str, dict[str, dict[str, int]]]) -> list[str]:
    """The modules of a coverage JSON report none of whose statements ran.

    Parameters
    ----------
    report
        ``files`` of ``coverage json``: path to its ``summary``.

    Returns
    -------
    list of str
        Their paths, sorted; empty modules (no statements) and :data:`OWN_PROCESS` aside.
    """
    return sorted(
        path
        for path, entry in report.items()
        if entry["summary"]["num_statements"] > 0
        and entry["summary"]["covered_lines"] == 0
        and not path.endswith(OWN_PROCESS)
    )


def main(argv: list[str] | None = None) -> int:
    """Print the verdict; 1 if a module did not run."""
    parser = argparse.ArgumentParser(prog="python -m tests.coverage_check")
    parser.add_argument("--data-file", default=".coverage")
    args = parser.parse_args(argv)
    cov = coverage.Coverage(data_file=args.data_file, source=["tvopt_codegen"])
    cov.load()
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "coverage.json"
        total = cov.json_report(outfile=str(out))
        files = json.loads(out.read_text(encoding="utf-8"))["files"]
    missing = unexercised(files)
    print(f"coverage-fast: {len(files)} modules, {total:.0f}% of lines run", end="")
    if missing:
        print(f"; {len(missing)} never ran: " + ", ".join(missing))
        return 1
    print("; every module ran")
    return 0


if __name__ == "__main__":
    sys.exit(main())
