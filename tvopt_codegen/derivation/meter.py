"""The derivation's budgets: expression size and time, checked as it builds."""

from __future__ import annotations

import contextlib
import signal
import threading
import time
from collections.abc import Callable, Iterator

from tvopt_codegen import symbolic as sx
from tvopt_codegen.errors import BudgetError, raise_pending_signal
from tvopt_codegen.limits import Budget

#: det R is simplified and factored only up to this many expression nodes.
_DET_SIMPLIFY_NODES = 400


class TimeLimitError(Exception):
    """A block run under :func:`time_limited` took longer than its seconds."""


class _Expired(BaseException):
    """The timer's signal, raised where the interrupted call happens to be.

    A BaseException, so that sympy's ``except Exception`` fallbacks inside the call
    cannot swallow it and carry on.
    """


@contextlib.contextmanager
def time_limited(seconds: float) -> Iterator[None]:
    """Run the block for at most ``seconds``, then raise :class:`TimeLimitError`.

    A single SymPy call at the border (``simplify``) can run for minutes between two budget checks;
    the real-time timer's signal interrupts it. Only in the main thread of a POSIX
    process, where Python delivers signals; elsewhere the block runs unlimited. A timer
    already armed (the command line's budget) is kept: when it would fire first, it is
    left to fire; otherwise it is re-armed afterwards with what remains of it.
    """
    if not hasattr(signal, "setitimer") or threading.current_thread() is not (
        threading.main_thread()
    ):
        yield
        return
    outer_remaining = signal.getitimer(signal.ITIMER_REAL)[0]
    if 0.0 < outer_remaining <= seconds:
        yield
        return
    token = _Expired()

    def expire(_signum: int, _frame: object) -> None:
        raise token

    start = time.monotonic()
    outer_handler = signal.signal(signal.SIGALRM, expire)
    try:
        # Armed inside the try: the timer can fire before setitimer returns.
        signal.setitimer(signal.ITIMER_REAL, max(seconds, 1e-6))
        yield
    except _Expired as exc:
        if exc is not token:
            raise
        raise TimeLimitError(f"took longer than {seconds:g} s") from None
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, outer_handler)
        if outer_remaining > 0.0:
            left = outer_remaining - (time.monotonic() - start)
            signal.setitimer(signal.ITIMER_REAL, max(left, 1e-6))


#: The size of a tree, as the budget counts it (the API's: the border uses it too).
tree_size = sx.tree_size


class _Meter:
    """Checks the budget as expressions are built; knows the current stage's name."""

    def __init__(
        self,
        source: str,
        budget: Budget,
        progress: Callable[[str, int, int, float], None] | None = None,
    ) -> None:
        self.source = source
        self.budget = budget
        self.start = time.perf_counter()
        self.deadline = self.start + budget.seconds
        self.stage = "model"
        self.progress = progress
        self.expressions = 0
        self.nodes = 0
        self.last_report = self.start

    def report(self) -> None:
        """Tell the progress callback the stage, expressions and nodes so far, and time."""
        raise_pending_signal()
        now = time.perf_counter()
        # Kept without a callback too: check_time would otherwise call this at every
        # expression once the first half second is past.
        self.last_report = now
        if self.progress is not None:
            self.progress(self.stage, self.expressions, self.nodes, now - self.start)

    def check_time(self) -> None:
        """Report progress now and then; raise when the time budget is spent.

        Or a signal whose exception compiled code swallowed
        (:func:`~tvopt_codegen.errors.signal_raised`): it is raised again here.
        """
        raise_pending_signal()
        now = time.perf_counter()
        if now - self.last_report > 0.5:
            self.report()
        if now > self.deadline:
            raise BudgetError(
                self.source,
                self.stage,
                f"the derivation took longer than {self.budget.seconds:g} s",
            )

    @contextlib.contextmanager
    def interrupting(self) -> Iterator[None]:
        """Hold the time budget inside any one call too: a BudgetError naming the stage."""
        try:
            with time_limited(self.deadline - time.perf_counter()):
                yield
        except TimeLimitError:
            raise BudgetError(
                self.source,
                self.stage,
                f"the derivation took longer than {self.budget.seconds:g} s",
            ) from None

    def __call__(self, expr: sx.Expr) -> None:
        self.expressions += 1
        if isinstance(expr, sx.Basic):
            args = expr.args
            if not args:
                self.nodes += 1  # an atom: most entries of a team's matrices are zeros
                return
        else:  # a Python number from a caller's arithmetic
            expr = sx.as_expr(expr)
            args = expr.args
        self.check_time()
        # The arguments read above are walked, not read again.
        size = tree_size(expr, self.budget.size, args)
        self.nodes += size
        if size > self.budget.size:
            raise BudgetError(
                self.source,
                self.stage,
                f"an expression grew past {self.budget.size} nodes (the size budget); "
                "simplify the model or objective, or raise --max-size",
            )

    def matrix(self, matrix: sx.Expr) -> None:
        for entry in matrix:
            self(entry)


class _Clock:
    """Records how long each derivation step takes."""

    def __init__(self) -> None:
        self.marks: list[tuple[str, float]] = []
        self.last = time.perf_counter()

    def mark(self, stage: str) -> None:
        now = time.perf_counter()
        self.marks.append((stage, now - self.last))
        self.last = now
