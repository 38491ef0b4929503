"""``python -m tvopt_codegen`` and the ``tvopt-codegen`` console script.

The command line imports sympy, numpy and scipy, which takes a second or two; Ctrl-C
or SIGTERM arriving then still ends with one line and the documented exit code.
"""

from __future__ import annotations

import atexit
import contextlib
import os
import signal
import sys
import threading

from tvopt_codegen.errors import EXIT_INTERRUPTED, EXIT_TERMINATED


def _terminated_while_loading(_signum: int, _frame: object) -> None:
    print("tvopt-codegen: terminated; nothing was written", file=sys.stderr)
    raise SystemExit(EXIT_TERMINATED)


def entry() -> int:
    """Load the command line and run it."""
    previous = signal.signal(signal.SIGTERM, _terminated_while_loading)
    try:
        from tvopt_codegen.cli import main  # noqa: PLC0415 - signals are handled around it
    except KeyboardInterrupt:
        print("tvopt-codegen: interrupted; nothing was written", file=sys.stderr)
        return EXIT_INTERRUPTED
    finally:
        signal.signal(signal.SIGTERM, previous)
    code = main()
    _exit_now(code)
    return code


def _exit_now(code: int) -> None:
    """End the process without tearing down its objects, when nothing else runs.

    A derivation leaves millions of sympy objects; freeing them one by one as the
    interpreter shuts down took 0.25 s of a two-second command and 0.75 s of a ten-second
    one, after the work was done. The exit handlers still run and the streams are
    flushed; with another thread alive (a sweep's Dask workers), Python exits as usual.
    """
    if threading.active_count() != 1:
        return
    atexit._run_exitfuncs()
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(OSError, ValueError):
            stream.flush()
    os._exit(code)


if __name__ == "__main__":
    sys.exit(entry())
