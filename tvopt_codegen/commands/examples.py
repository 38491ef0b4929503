"""``tvopt-codegen examples``: the bundled example specs, a line each."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Mapping

HELP = "list the bundled example specs"


def build(parser: argparse.ArgumentParser) -> None:
    """The ``examples`` command takes no options."""


def run(args: argparse.Namespace) -> int:
    """Print every bundled example with its summary."""
    from tvopt_codegen.spec import bundled_examples  # noqa: PLC0415

    print_examples(bundled_examples())
    return 0


def print_examples(examples: Mapping[str, str]) -> None:
    """Each example's name and summary: one column of names, summaries beside it.

    On a terminal the summaries wrap to its width under their column; into a pipe each
    example stays one line, for ``grep``.
    """
    import shutil  # noqa: PLC0415 - with bz2 and lzma: loaded by this command alone
    import textwrap  # noqa: PLC0415 - --help reads this module's HELP

    column = max(map(len, examples), default=0) + 2
    width = max(shutil.get_terminal_size().columns, column + 30)
    for name, summary in examples.items():
        if sys.stdout.isatty():
            lines = textwrap.wrap(summary, width - column) or [""]
        else:
            lines = [summary]
        print(f"{name:<{column}}{lines[0]}")
        for line in lines[1:]:
            print(" " * column + line)
