"""``python -m tvopt_codegen`` and the ``tvopt-codegen`` console script.

The command line imports sympy, numpy and scipy, which takes a second or two; Ctrl-C
or SIGTERM arriving then still ends with one line and the documented exit code.
"""

from __future__ import annotations

import signal
import sys


def _terminated_while_loading(_signum: int, _frame: object) -> None:
    print("tvopt-codegen: terminated; nothing was written", file=sys.stderr)
    raise SystemExit(143)


def entry() -> int:
    """Load the command line and run it."""
    previous = signal.signal(signal.SIGTERM, _terminated_while_loading)
    try:
        from tvopt_codegen.cli import main  # noqa: PLC0415 - signals are handled around it
    except KeyboardInterrupt:
        print("tvopt-codegen: interrupted; nothing was written", file=sys.stderr)
        return 130
    finally:
        signal.signal(signal.SIGTERM, previous)
    return main()


if __name__ == "__main__":
    sys.exit(entry())
