"""The shared run options on a command's parser, and their bounds checked in one place.

Each option is declared once, in :data:`tvopt_codegen.limits.RUN_OPTIONS`; a command
adds the ones it takes by name, and :func:`check` refuses a value out of its bounds
with the same one line whichever command it was given to.
"""

from __future__ import annotations

import argparse
from typing import Any

from tvopt_codegen.errors import SpecError
from tvopt_codegen.limits import RUN_OPTIONS

#: Where a command's arguments go: its parser or a group of it.
Target = argparse.ArgumentParser | argparse._ActionsContainer


def add(target: Target, *names: str, hidden: bool = False) -> None:
    """Add the run options ``names`` (keys of ``RUN_OPTIONS``) to ``target``.

    ``hidden`` options are accepted but left out of ``--help``.
    """
    for name in names:
        option = RUN_OPTIONS[name]
        text = option.help
        if option.default is not None:
            text += f" (default {option.default_text})"
        target.add_argument(
            option.flag,
            type=option.kind,
            default=option.default,
            choices=option.choices or None,
            metavar=option.metavar,
            help=argparse.SUPPRESS if hidden else text,
        )


class _Renamed(argparse.Action):
    """An option's old spelling: refused at once, with a one-line hint naming the new one."""

    def __init__(self, option_strings: list[str], dest: str, new: str, **kwargs: Any) -> None:
        super().__init__(option_strings, dest, **kwargs)
        self.new = new

    def __call__(
        self,
        parser: argparse.ArgumentParser,
        namespace: argparse.Namespace,
        values: Any,
        option_string: str | None = None,
    ) -> None:
        parser.error(f"{option_string} is now {self.new}")


def renamed(target: Target, old: str, new: str) -> None:
    """Refuse ``old``, an option renamed: the error names ``new`` (neither in ``--help``)."""
    target.add_argument(
        old, nargs="?", action=_Renamed, new=new, help=argparse.SUPPRESS, dest=argparse.SUPPRESS
    )


def check(args: argparse.Namespace) -> None:
    """Refuse the first run option given out of its bounds, naming it."""
    for name, option in RUN_OPTIONS.items():
        value: Any = getattr(args, name, None)
        if value is not None:
            problem = option.problem(value)
            if problem is not None:
                raise SpecError("command line", option.flag, problem)
