"""Command-line interface: the parser's frame, the table of commands, the exit codes.

Each command is a module of :mod:`tvopt_codegen.commands` (its options and its ``run``);
this module builds the parser from :data:`COMMANDS`, runs the command named and maps
every outcome to one line on stderr and an exit code (:data:`tvopt_codegen.errors.EXIT_CODES`).
Set TVOPT_CODEGEN_DEBUG=1 for tracebacks of internal errors.
"""

from __future__ import annotations

import argparse
import contextlib
import gc
import os
import signal
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any, NoReturn, cast

from tvopt_codegen import __version__
from tvopt_codegen.commands import Command, run_options
from tvopt_codegen.errors import (
    EXIT_BAD_SPEC,
    EXIT_BROKEN_PIPE,
    EXIT_BUDGET,
    EXIT_INTERNAL,
    EXIT_INTERRUPTED,
    EXIT_TERMINATED,
    Terminated,
    TvoptError,
    exit_codes_text,
    forget_signals,
    one_line,
    signal_raised,
)
from tvopt_codegen.limits import ENGINE_VARIABLE, ENGINES


class _Deferred:
    """A command module of this package, imported when first asked for its help, options or run.

    A process runs one command: importing the other eight (``tune``'s hashlib and json,
    ``sweep``'s, ...) only to build parsers it never uses cost every command's start-up.
    """

    def __init__(self, module: str) -> None:
        self._name = f"tvopt_codegen.commands.{module}"

    def _module(self) -> Command:
        # __import__ rather than importlib.import_module: -X importtime lists it.
        return cast(Command, __import__(self._name, fromlist=["run"]))

    @property
    def HELP(self) -> str:  # noqa: N802 - the module's attribute, by its name
        """The module's line in ``--help``."""
        return self._module().HELP

    def build(self, parser: argparse.ArgumentParser) -> None:
        """The module's ``build``."""
        self._module().build(parser)

    def run(self, args: argparse.Namespace) -> int:
        """The module's ``run``."""
        return self._module().run(args)


#: The commands, in ``--help``'s order: a new command is a module and a line here.
COMMANDS: dict[str, Command] = {
    "generate": _Deferred("generate"),
    "check": _Deferred("check"),
    "examples": _Deferred("examples"),
    "import-urdf": _Deferred("import_urdf"),
    "report": _Deferred("report"),
    "export": _Deferred("export"),
    "simulate": _Deferred("simulate"),
    "sweep": _Deferred("sweep"),
    "tune": _Deferred("tune"),
}


class _Commands(argparse._SubParsersAction):  # type: ignore[type-arg]
    """The commands' parsers, each given its options when its command is the one named.

    ``--help`` reads every command's line; a command line builds the options of the
    command it names only (argparse hands a command's words to its parser here, after
    the options before it were read), so the other commands' modules stay unimported.
    """

    def __call__(
        self,
        parser: argparse.ArgumentParser,
        namespace: argparse.Namespace,
        values: Any,
        option_string: str | None = None,
    ) -> None:
        name = values[0]
        if name in self._name_parser_map and name not in self.built:
            self.built.add(name)
            COMMANDS[name].build(self._name_parser_map[name])
        super().__call__(parser, namespace, values, option_string)

    built: set[str]

    def describe(self) -> None:
        """Give each command its line of ``--help`` (importing every command's module)."""
        for choice in self._choices_actions:
            if choice.help is None:
                choice.help = COMMANDS[choice.dest].HELP


class _Parser(argparse.ArgumentParser):
    """argparse, with a usage error in one line (the seven-line usage is --help's)."""

    def error(self, message: str) -> NoReturn:
        sys.stderr.write(f"{self.prog}: error: {one_line(message)} (see {self.prog} --help)\n")
        raise SystemExit(EXIT_BAD_SPEC)

    def format_help(self) -> str:
        """The help, with each command's line read from its module first."""
        for action in self._actions:
            if isinstance(action, _Commands):
                action.describe()
        return super().format_help()


def _parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="tvopt-codegen",
        description="Generate implicit trajectory planning controllers from a spec file.",
        epilog=exit_codes_text(),
    )
    parser.add_argument("--version", action="version", version=f"tvopt-codegen {__version__}")
    parser.add_argument(
        "--engine",
        choices=ENGINES,
        default=None,
        help=f"the symbolic engine that derives the law (default: ${ENGINE_VARIABLE}, else "
        f"{ENGINES[0]}); SymPy is the reference, SymEngine the fast one",
    )
    parser.register("action", "parsers", _Commands)
    subparsers = cast(
        _Commands,
        parser.add_subparsers(dest="command", required=True, metavar="COMMAND"),
    )
    subparsers.built = set()
    for name in COMMANDS:
        subparsers.add_parser(name, help=None)  # its line: describe, for --help alone
    return parser


def run(argv: Sequence[str] | None = None) -> int:
    """Run the CLI and return the exit code (errors are reported on stderr)."""
    args = _parser().parse_args(argv)
    args.started = time.perf_counter()
    run_options.check(args)
    if args.engine is None:
        return COMMANDS[args.command].run(args)
    # Imported here: the symbolic API binds the environment's engine when first imported.
    from tvopt_codegen import symbolic  # noqa: PLC0415

    with symbolic.using(args.engine):
        return COMMANDS[args.command].run(args)


def _on_sigterm(_signum: int, _frame: object) -> None:
    signal_raised(Terminated)


def _on_sigint(_signum: int, _frame: object) -> None:
    signal_raised(KeyboardInterrupt)


#: The cyclic garbage collector's thresholds while a command runs (Python's: 700, 10, 10).
#: A derivation allocates millions of sympy objects that live to its end; with Python's
#: thresholds the collector scans them nine thousand times for a ring of 128 agents, a
#: fifth of the run (6.0 s of 31), for next to no garbage. At these, 613 collections
#: take 2.8 s and the peak memory is the same (272 MB).
GC_THRESHOLDS = (10000, 10, 10)


def main(argv: Sequence[str] | None = None) -> int:
    """Console-script entry point: run, and map every outcome to one line and an exit code."""
    forget_signals()
    previous = signal.signal(signal.SIGTERM, _on_sigterm)
    # Python's own handler, remembering: a Ctrl-C swallowed by compiled code is raised
    # again at the next check (errors.raise_pending_signal). Left alone where SIGINT is
    # ignored (a job started with nohup) or handled by the caller.
    interrupt = signal.getsignal(signal.SIGINT)
    if interrupt is signal.default_int_handler:
        signal.signal(signal.SIGINT, _on_sigint)
    collector = gc.get_threshold()
    gc.set_threshold(*GC_THRESHOLDS)
    try:
        code = run(argv)
        sys.stdout.flush()  # here, where a closed pipe is caught below, not at exit
        return code
    except TvoptError as exc:
        print(f"tvopt-codegen: error: {one_line(str(exc))}", file=sys.stderr)
        return exc.exit_code
    except BrokenPipeError:
        # The reader went away (`check SPEC | head -1`): stop quietly, like a Unix tool,
        # and keep Python from complaining as it flushes stdout at exit.
        with contextlib.suppress(OSError):
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return EXIT_BROKEN_PIPE
    except KeyboardInterrupt:
        print("tvopt-codegen: interrupted; no file was left half-written", file=sys.stderr)
        return EXIT_INTERRUPTED
    except Terminated:
        print("tvopt-codegen: terminated; no file was left half-written", file=sys.stderr)
        return EXIT_TERMINATED
    except (RecursionError, MemoryError) as exc:
        print(
            f"tvopt-codegen: error: the derivation ran out of "
            f"{'stack' if isinstance(exc, RecursionError) else 'memory'}; the expressions are "
            "too large",
            file=sys.stderr,
        )
        return EXIT_BUDGET
    except Exception as exc:
        if os.environ.get("TVOPT_CODEGEN_DEBUG"):
            raise
        import traceback  # noqa: PLC0415 - with linecache and tokenize: for this line alone

        where = traceback.extract_tb(exc.__traceback__)[-1]
        print(
            f"tvopt-codegen: internal error: {type(exc).__name__}: {one_line(str(exc))} (at "
            f"{Path(where.filename).name}:{where.lineno}; please report it; "
            "TVOPT_CODEGEN_DEBUG=1 shows the traceback)",
            file=sys.stderr,
        )
        return EXIT_INTERNAL
    finally:
        signal.signal(signal.SIGTERM, previous)
        if interrupt is signal.default_int_handler:
            signal.signal(signal.SIGINT, interrupt)
        forget_signals()
        gc.set_threshold(*collector)
        # What common.without_collector froze becomes collectable again for a caller that goes on.
        gc.unfreeze()


if __name__ == "__main__":
    sys.exit(main())
