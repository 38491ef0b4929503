"""What the commands that derive share: their options, the derivation and its clock.

``derive`` loads, derives and lowers the spec a command names, within the time budget
(a real-time timer that stops even a single long SymPy call) and with its progress on
stderr; it runs without the cyclic garbage collector, whose scans of the live
expressions were a tenth of a large derivation for no garbage.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import gc
import math
import signal
import sys
import threading
import time
from collections.abc import Iterator, Sequence
from typing import TYPE_CHECKING

from tvopt_codegen.commands import run_options
from tvopt_codegen.errors import BudgetError, SpecError, one_line
from tvopt_codegen.limits import Budget

if TYPE_CHECKING:
    from tvopt_codegen.derivation import Derivation
    from tvopt_codegen.lowering.ir import KernelSet


def spec_argument(command: argparse.ArgumentParser) -> None:
    """The spec every deriving command starts from."""
    command.add_argument("spec", help="spec file, or the name of a bundled example")


def backend_option(command: argparse.ArgumentParser, what: str) -> None:
    """``--backend``: one of the registered backends, Python by default.

    Parameters
    ----------
    command
        The command's parser.
    what
        What the backend is for this command, for ``--help``.
    """
    option = command.add_argument("--backend", default="python", help=f"{what} (default: python)")
    # Set after add_argument, which lists choices to check a metavar: the registry is
    # read when the option is given or shown, not whenever the parser is built.
    option.choices = _BackendNames()


class _BackendNames:
    """The registered backends' names, sorted, read from the registry when asked.

    The registry finds the backends other packages declare as it is first read (an
    entry-point scan): a command that names no backend and prints no help never reads it.
    """

    def _names(self) -> list[str]:
        from tvopt_codegen import backends  # noqa: PLC0415 - the registry, not a backend

        return sorted(backends.BACKENDS)

    def __contains__(self, name: object) -> bool:
        return name in self._names()

    def __iter__(self) -> Iterator[str]:
        return iter(self._names())


def output_options(
    command: argparse.ArgumentParser,
    out_help: str = "output folder (default: current folder)",
) -> None:
    """``--out`` (a folder, the current one by default) and ``--force``."""
    command.add_argument("--out", default=".", help=out_help)
    command.add_argument(
        "--force",
        action="store_true",
        help="replace files that were edited by hand or not written here",
    )


def derivation_options(command: argparse.ArgumentParser) -> None:
    """The options of every command that derives the law (all but examples and sweep)."""
    command.add_argument(
        "--extension",
        choices=("spec", "auto"),
        default="spec",
        help="take the dynamic extension from the spec (default), or "
        "search the smallest one that makes the plant linearizable",
    )
    command.add_argument(
        "--progress",
        choices=("auto", "always", "never"),
        default="auto",
        help="show the derivation's progress on stderr: on a terminal after 2 s "
        "(auto, the default), always, or never",
    )
    run_options.add(command, "max_seconds", "max_size")


def derive(args: argparse.Namespace) -> tuple[Derivation, KernelSet]:
    """Load, derive and lower the spec named on the command line, within its budget."""
    # From the command's start: --timings counts the imports the stages need in "load".
    clock = [getattr(args, "started", time.perf_counter())]
    from tvopt_codegen.derivation import derive  # noqa: PLC0415
    from tvopt_codegen.lowering.ir import lower  # noqa: PLC0415
    from tvopt_codegen.spec import load_spec  # noqa: PLC0415

    progress = DeriveProgress(args.progress)
    source = [str(args.spec)]
    stages: dict[str, float] = {}

    def lap(stage: str) -> None:
        now = time.perf_counter()
        stages[stage] = now - clock[0]
        clock[0] = now

    try:
        with without_collector(), time_limit(args.max_seconds, source, progress):
            spec = load_spec(args.spec)
            source[0] = spec.source
            if args.extension == "auto":
                spec = dataclasses.replace(spec, extension=(), extension_auto=True)
            lap("load")
            derivation = derive(
                spec, progress=progress, budget=Budget(args.max_seconds, args.max_size)
            )
            lap("derive")
            progress.lowering()
            kernels = lower(derivation)
            lap("lower")
    finally:
        progress.close()
    args.stage_seconds = stages
    for warning in derivation.warnings:
        warn(f"{spec.source}: {warning}")
    return derivation, kernels


def warn(text: str) -> None:
    """Print one of the command line's warnings: one line on stderr.

    Stages do not print; what they want a person to know short of an error they return,
    or tell a ``warn`` callable the command passes (this one).
    """
    print(one_line(f"tvopt-codegen: warning: {text}"), file=sys.stderr)


@contextlib.contextmanager
def without_collector() -> Iterator[None]:
    """Run without Python's cyclic garbage collector, and turn it back on after.

    The derivation's and the printers' walks leave no reference cycles (jet.release):
    what they drop, reference counting frees at once. The collector would only scan the
    live expressions, again and again: a tenth of a large team's run, for no garbage
    (the peak memory is the same with it or without).

    On the way out the objects made so far are frozen (``gc.freeze``): they are the
    imported modules and the derivation, alive until the command ends, and the first
    collection after this block would otherwise scan every one of them (0.4 s at 128
    agents). :func:`tvopt_codegen.cli.main` unfreezes them when the command returns.
    """
    collecting = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        gc.freeze()
        if collecting:
            gc.enable()


class Overrun(BaseException):
    """The time budget ran out.

    A BaseException, so that no ``except Exception`` in a library the derivation calls
    can swallow it.
    """


@contextlib.contextmanager
def time_limit(seconds: float, source: list[str], progress: DeriveProgress) -> Iterator[None]:
    """Stop loading, deriving and lowering after ``seconds``, wherever they are.

    The derivation checks its budget as it builds expressions, but a single SymPy
    call (a simplification, an exact power) can run far past it between two checks:
    a timer signal interrupts it within the budget. Only in the main thread, where
    Python delivers signals, and only between Python's own steps: a single SymEngine
    call, which is C++, is interrupted when it returns (an ``expand`` of 0.7 s fired
    at 0.2 s stops at 0.7 s).
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    fired = False

    def expire(_signum: int, _frame: object) -> None:
        # Once: a budget far below the set-up's own time (1e-9 s) must not fire again
        # in the clean-up below, where nothing would turn it into one line.
        nonlocal fired
        if not fired:
            fired = True
            raise Overrun

    previous = signal.signal(signal.SIGALRM, expire)
    try:
        # Armed inside the try: the timer can fire before setitimer returns.
        signal.setitimer(signal.ITIMER_REAL, seconds)
        yield
        if fired:
            # The signal landed where an exception cannot propagate (a garbage
            # collector's callback, a __del__: Python prints it and goes on): the
            # budget still ran out, and what the block made must not be written.
            raise Overrun
    except Overrun:
        raise BudgetError(
            source[0], progress.stage, f"the derivation took longer than {seconds:g} s"
        ) from None
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)


class DeriveProgress:
    """The derivation's stage, expressions built and elapsed time, on stderr.

    ``auto`` shows it on a terminal only, once the derivation has taken 2 s (one
    updating line); ``always`` prints a line per report (for logs); ``never`` nothing.
    Errors stay one line: an updating line is cleared before anything else is printed.
    """

    def __init__(self, mode: str) -> None:
        self.terminal = sys.stderr.isatty()
        self.mode = mode
        self.stage = "reading the spec"
        self.shown = False
        self.start = time.perf_counter()
        self.last = (0, 0)

    def __call__(self, stage: str, expressions: int, nodes: int, seconds: float) -> None:
        """Report ``stage`` and the expressions built so far, ``seconds`` in."""
        self.stage = stage
        self.last = (expressions, nodes)
        if self.mode == "never" or (self.mode == "auto" and (not self.terminal or seconds < 2)):
            return
        text = (
            f"  deriving: {stage}, {expressions} expressions ({nodes} nodes) built, {seconds:.1f} s"
        )
        if self.terminal:
            print(f"{text:<80}", end="\r", file=sys.stderr, flush=True)
        else:
            print(text, file=sys.stderr, flush=True)
        self.shown = True

    def lowering(self) -> None:
        """The last step: kernels and their CSE (seconds for a large team)."""
        self("kernels and CSE", *self.last, time.perf_counter() - self.start)

    def close(self) -> None:
        """Clear the updating line, so that what follows starts on a clean one."""
        if self.shown and self.terminal:
            print(" " * 80, end="\r", file=sys.stderr, flush=True)


def assignments(items: Sequence[str], option: str) -> dict[str, float]:
    """Parse NAME=VALUE options into a mapping, one clear error per bad item."""
    values: dict[str, float] = {}
    for item in items:
        name, sep, text = item.partition("=")
        try:
            if not sep or not name:
                raise ValueError
            value = float(text)
        except ValueError:
            raise SpecError("command line", option, f"expected NAME=VALUE, got {item!r}") from None
        if not math.isfinite(value):
            raise SpecError("command line", option, f"{name}: value must be finite")
        values[name.strip()] = value
    return values


def check_out(out: str) -> None:
    """Refuse an unusable output folder before deriving, not after (creating nothing)."""
    from tvopt_codegen.emit import prepare_folder  # noqa: PLC0415

    prepare_folder(out, create=False)
