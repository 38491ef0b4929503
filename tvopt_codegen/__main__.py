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

from tvopt_codegen.errors import EXIT_INTERRUPTED, EXIT_TERMINATED, TvoptError, one_line
from tvopt_codegen.limits import ENGINE_VARIABLE as VARIABLE
from tvopt_codegen.limits import ENGINES


def _terminated_while_loading(_signum: int, _frame: object) -> None:
    print("tvopt-codegen: terminated; nothing was written", file=sys.stderr)
    raise SystemExit(EXIT_TERMINATED)


def _engine_from_argv(argv: list[str]) -> None:
    """Name the engine of ``--engine X`` (before the command) in the environment, early.

    The symbolic API binds its engine when first imported, which loading the command
    line does: set first, a ``--engine symengine`` process never imports SymPy for a
    spec that needs no border. The parser still checks the value and the option's place.
    """
    for index, word in enumerate(argv):
        if not word.startswith("-"):
            return  # the command: options after it are the command's
        value = None
        if word == "--engine" and index + 1 < len(argv):
            value = argv[index + 1]
        elif word.startswith("--engine="):
            value = word.partition("=")[2]
        if value is not None:
            if value in ENGINES:  # else the parser refuses it, naming --engine
                os.environ[VARIABLE] = value
            return


#: The BLAS libraries' variables for their thread count: OpenBLAS (NumPy's and SciPy's
#: wheels) and MKL (conda's NumPy).
BLAS_THREADS = ("OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


def one_blas_thread() -> None:
    """Ask NumPy's BLAS for one thread, unless the user chose a number, before it loads.

    Every matrix the commands factor is small (a Hessian of 64 outputs, a 12 x 12 H):
    a second BLAS thread only waits on the first, and on a busy machine the two fight
    for the cores the command already uses (1,200 eigenvalue problems of 64 x 64 took
    10.8 s with OpenBLAS's threads under load, 0.5 s with one). A sweep's worker
    processes inherit it, one BLAS thread per worker. The numbers stay the same:
    ``simulate`` of five examples wrote the same bytes with one thread and with two.
    """
    for variable in BLAS_THREADS:
        os.environ.setdefault(variable, "1")


def entry() -> int:
    """Load the command line and run it."""
    _engine_from_argv(sys.argv[1:])
    one_blas_thread()
    previous = signal.signal(signal.SIGTERM, _terminated_while_loading)
    try:
        from tvopt_codegen.cli import main  # noqa: PLC0415 - signals are handled around it
    except TvoptError as exc:  # an unknown engine in the environment, met as the API loads
        print(f"tvopt-codegen: error: {one_line(str(exc))}", file=sys.stderr)
        return exc.exit_code
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
