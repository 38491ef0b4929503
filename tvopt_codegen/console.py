"""The command line's warning line on the terminal, for stages that take a ``warn``.

A stage does not print: what it wants a person to know, short of an error, it tells a
``warn`` callable its caller passes (:func:`tvopt_codegen.emit.write_files`,
:func:`tvopt_codegen.emit.recover`). The command line passes nothing yet to the writer,
so the writer's ``warn`` defaults to :func:`warning`, which prints the line the writer
printed itself before it became a package (issue 48), byte for byte.
"""

from __future__ import annotations

import sys


def warning(message: str) -> None:
    """Print ``message`` on stderr as one of the command line's warnings.

    Parameters
    ----------
    message : str
        The warning, without the ``tvopt-codegen: warning:`` prefix this adds.
    """
    print(f"tvopt-codegen: warning: {message}", file=sys.stderr)
