"""Error types of tvopt-codegen and the CLI exit codes they map to.

Every error a user can cause is one of these; the CLI prints ``str(error)`` on one
line and exits with :attr:`TvoptError.exit_code`.
"""

from __future__ import annotations

import re
from typing import NoReturn

#: Exit code of a successful run.
EXIT_OK = 0
#: Exit code for a spec file that cannot be read or is invalid.
EXIT_BAD_SPEC = 2
#: Exit code for a well-formed spec whose system violates the paper's assumptions.
EXIT_ASSUMPTION = 3
#: Exit code for output that could not be written (or would overwrite a user's file).
EXIT_OUTPUT = 4
#: Exit code of a simulation whose certificate fails.
EXIT_CERTIFICATE = 5
#: Exit code for a derivation that exceeded its time or size budget.
EXIT_BUDGET = 6
#: Exit code for a controller that could not be built (no C compiler, compiler error).
EXIT_BUILD = 7
#: Exit code for a bug in tvopt-codegen itself.
EXIT_INTERNAL = 70
#: Exit code when the reader of stdout went away (as a process killed by SIGPIPE).
EXIT_BROKEN_PIPE = 141
#: Exit code after Ctrl-C.
EXIT_INTERRUPTED = 130
#: Exit code after SIGTERM.
EXIT_TERMINATED = 143

#: Every exit code of ``tvopt-codegen`` and what it means, in one line each: the command
#: line's ``--help`` prints it, and the README's table is checked against it.
EXIT_CODES: dict[int, str] = {
    EXIT_OK: "ok",
    EXIT_BAD_SPEC: "bad spec or usage",
    EXIT_ASSUMPTION: "assumptions violated",
    EXIT_OUTPUT: "output not written",
    EXIT_CERTIFICATE: "certificate failed",
    EXIT_BUDGET: "budget exceeded",
    EXIT_BUILD: "build failed",
    EXIT_INTERNAL: "internal error",
    EXIT_INTERRUPTED: "interrupted",
    EXIT_BROKEN_PIPE: "stdout closed by its reader",
    EXIT_TERMINATED: "terminated",
}


def exit_codes_text() -> str:
    """The exit codes in one sentence (``tvopt-codegen --help``'s epilog)."""
    return "Exit codes: " + ", ".join(f"{c} {m}" for c, m in EXIT_CODES.items()) + "."


class Terminated(BaseException):  # noqa: N818 - a signal, like KeyboardInterrupt
    """SIGTERM, raised where the process is so that it unwinds like Ctrl-C.

    What ``timeout``, SLURM, systemd and Kubernetes send to stop a job: a command that
    keeps finished work on Ctrl-C (a sweep) keeps it on SIGTERM too.
    """


#: Ctrl-C's or SIGTERM's exception raised by the command line's handlers and not yet
#: known to have ended the command or been handled (:func:`raise_pending_signal`).
_PENDING: list[type[BaseException]] = []


def signal_raised(kind: type[BaseException]) -> NoReturn:
    """Remember and raise ``kind`` (``KeyboardInterrupt``, :class:`Terminated`): a handler's.

    Compiled code that catches every exception (NumPy's random module as it first loads,
    SymEngine's matrix iterator) can swallow the exception the handler raises inside it,
    and the command would run on to its end and write its files: remembered, it is
    raised again at the next :func:`raise_pending_signal`.
    """
    _PENDING.append(kind)
    raise kind


def raise_pending_signal() -> None:
    """Raise again a signal's exception that was raised and then swallowed, if any.

    Called where the work is checked (the derivation's meter, the integrator's progress)
    and before anything is written.
    """
    if _PENDING:
        kind = _PENDING[0]
        _PENDING.clear()
        raise kind


def forget_signals() -> None:
    """The signal's exception reached code that handles it: nothing is pending."""
    _PENDING.clear()


#: Longest name or value an error message quotes in full.
MAX_QUOTED = 60

_LONG = MAX_QUOTED + 1
# A quote opens after a non-word character and closes before one: the apostrophe of
# "library's" neither opens nor closes a quoted span (it once clipped the prose between).
_QUOTED = re.compile(rf"(?<!\w)'([^'\n]{{{_LONG},}})'(?!\w)|(?<!\w)\"([^\"\n]{{{_LONG},}})\"(?!\w)")


def clip(text: str, limit: int = MAX_QUOTED) -> str:
    """``text``, or its first ``limit - 3`` characters and an ellipsis."""
    return text if len(text) <= limit else text[: limit - 3] + "..."


#: Characters that would break an error's one line: the C0 controls (a newline, a tab),
#: DEL, the C1 controls and Unicode's line and paragraph separators.
_LINE_BREAKERS = re.compile("[\x00-\x1f\x7f-\x9f\u2028\u2029]")


def one_line(text: str) -> str:
    r"""``text`` with every character that would end or garble a terminal line escaped.

    A path may hold a newline (a file name is any bytes but ``/`` and NUL); printed as
    is, it would split an error across lines, and a script reading the first line would
    lose the problem. ``\n``, ``\t`` and ``\xNN`` are what Python's ``repr`` writes.
    """

    def escape(match: re.Match[str]) -> str:
        return repr(match.group(0))[1:-1]

    return _LINE_BREAKERS.sub(escape, text)


def clip_quotes(message: str) -> str:
    """``message`` with every quoted name or value longer than :data:`MAX_QUOTED` clipped.

    A 10,000-character name must not make a 10,000-character error line.
    """

    def shorten(match: re.Match[str]) -> str:
        quote = "'" if match.group(1) is not None else '"'
        return quote + clip(match.group(1) or match.group(2)) + quote

    return _QUOTED.sub(shorten, message)


def _field(field: str) -> str:
    """A dotted field path, clipped part by part (a key may be a long name)."""
    return ".".join(clip(part) for part in field.split("."))


class TvoptError(Exception):
    """Base class of all errors reported to users.

    Attributes
    ----------
    exit_code : int
        The process exit code the CLI uses for this error.
    """

    exit_code = 1


class SpecError(TvoptError):
    """A spec file is unreadable, malformed, or refers to something undeclared.

    Parameters
    ----------
    source : str
        The spec file (path or bundled example name).
    field : str
        Dotted path of the offending field, e.g. ``system.dynamics.x1``.
    problem : str
        What is wrong, in one line.
    """

    exit_code = EXIT_BAD_SPEC

    def __init__(self, source: str, field: str, problem: str) -> None:
        self.source = source
        self.field = field
        self.problem = problem
        super().__init__(f"{source}: {_field(field)}: {clip_quotes(problem)}")


class AssumptionError(TvoptError):
    """The system or objective violates an assumption of the method.

    Raised for plants without a vector relative degree, decoupling matrices that are
    singular everywhere, non-Hurwitz error dynamics, Hessians that are not positive
    definite, and dimension mismatches found during derivation.

    Parameters
    ----------
    source : str
        The spec file the system came from.
    field : str
        The spec field the problem is best attributed to.
    problem : str
        What is wrong and, where possible, how to fix it.
    """

    exit_code = EXIT_ASSUMPTION

    def __init__(self, source: str, field: str, problem: str) -> None:
        self.source = source
        self.field = field
        self.problem = problem
        super().__init__(f"{source}: {_field(field)}: {clip_quotes(problem)}")


class OutputError(TvoptError):
    """Generated files could not be written, or writing them would lose a user's work."""

    exit_code = EXIT_OUTPUT


class BudgetError(TvoptError):
    """A derivation stage exceeded its time or size budget.

    Parameters
    ----------
    source : str
        The spec file.
    stage : str
        The derivation stage (``relative degree``, ``gradient jet``, ...).
    problem : str
        What was exceeded, and by how much.
    """

    exit_code = EXIT_BUDGET

    def __init__(self, source: str, stage: str, problem: str) -> None:
        self.source = source
        self.stage = stage
        super().__init__(f"{source}: derivation stage '{stage}': {clip_quotes(problem)}")


class BuildError(TvoptError):
    """A generated controller could not be built (no C compiler, or a compiler error)."""

    exit_code = EXIT_BUILD


class MissingExtraError(BuildError, ImportError):
    """An optional integration was used without its package: the message says what to install."""
