"""The commands of ``tvopt-codegen``: one module each, listed in ``cli.COMMANDS``.

A command module has :data:`HELP` (its line in ``tvopt-codegen --help``), ``build``
(its options, on the parser ``cli`` made for it) and ``run`` (the command itself,
returning the exit code). A new command is one module here and one line in the table.

The modules import the stages (sympy, numpy, scipy, Dask) inside ``run``: building the
parser, for ``--help`` and ``--version``, loads none of them.
"""

from __future__ import annotations

import argparse
from typing import Protocol


class Command(Protocol):
    """What ``cli`` needs of a command module."""

    @property
    def HELP(self) -> str:  # noqa: N802 - a module's constant
        """The command's line in ``tvopt-codegen --help``."""

    def build(self, parser: argparse.ArgumentParser) -> None:
        """Add the command's arguments (and its description) to its own parser."""

    def run(self, args: argparse.Namespace) -> int:
        """Run the command on its parsed arguments; return the exit code."""
