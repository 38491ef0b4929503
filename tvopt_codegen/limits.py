"""Limits and choices the command line offers, importable without the heavy stages.

``tvopt-codegen --help`` and ``--version`` read these without loading sympy, numpy or
scipy; the stages that enforce them import them from here. :data:`RUN_OPTIONS` is the
one table of the run options several commands share: each declared once, with its
default, bounds and help, for the command line and for the library's own checks (a
sweep's record is checked against the same bounds as its command line).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

#: The symbolic engines (``tvopt_codegen.symbolic``), the default first, and the
#: environment variable that names one: here, below the API, so that the command line
#: can offer them without importing it (importing it binds an engine).
ENGINES = ("symengine", "sympy")
ENGINE_VARIABLE = "TVOPT_CODEGEN_ENGINE"

#: Longest simulation horizon: a run is integrated and sampled step by step, so a
#: horizon of 1e300 would never end.
MAX_T_FINAL = 1e6
#: Most output times of a run, simulated or swept (the sweep's C loop keeps its grid of
#: output times on the stack, and a simulation's are rows of its trajectory table).
MAX_POINTS = 10_001
#: Fewest output times of a run: its start, its end and one between.
MIN_POINTS = 3
#: The integrator's tolerances of every run. The tighter pair is right for both
#: commands: ``simulate`` checks the certificate to 1e-6 relative, and at 1e-8 a sweep's
#: final errors carry the integrator's (unicycle_switch's: 5.43e-8 against 5.36e-8).
DEFAULT_RTOL = 1e-10
DEFAULT_ATOL = 1e-12
#: Output times of a run: the certificate, the errors and settling are measured on them.
DEFAULT_POINTS = 401
#: Integration methods of solve_ivp offered on the command line.
METHODS = ("RK45", "DOP853", "RK23", "Radau", "BDF", "LSODA")
#: The precisions of the generated C (``--precision``): double, the default, and single
#: (every real a float, for a single-precision FPU; docs/precision.md).
PRECISIONS = ("double", "single")


@dataclass(frozen=True)
class Budget:
    """Limits one derivation may use before it is stopped with a :class:`BudgetError`.

    Attributes
    ----------
    seconds : float
        Wall time for the whole derivation.
    size : int
        Largest expression tree (nodes, shared subtrees counted each time they occur)
        any stage may build: Lie derivatives, gradient, Hessian, jet assignments.
    """

    seconds: float = 120.0
    size: int = 20_000


#: Newton iterations at the first point of a minimiser path (steps are capped at 0.02: up
#: to 2,000 units from y*); the warm-started points take at most 200.
START_ITERATIONS = 100_000


#: The largest seed: a sample's seed is a signed 64-bit integer in every table format.
MAX_SEED = 2**63 - 1


@dataclass(frozen=True)
class RunOption:
    """A run option: its flag, type, default, bounds and help, declared once.

    Attributes
    ----------
    flag : str
        The option on the command line (``--rtol``).
    kind : type
        ``int`` or ``float``; ``str`` for an option with :attr:`choices`.
    default : float, str or None
        Its value when not given (None: decided by the command, e.g. the spec's).
    help : str
        Its help text, without the default (appended where there is one).
    low, high : float
        Its bounds (``-inf``/``inf``: none).
    low_open, high_open : bool
        Whether ``low`` and ``high`` themselves are outside the bounds.
    metavar : str or None
        The value's name in the usage line.
    choices : tuple of str
        The values a word option takes (``--precision``); empty for a number.
    """

    flag: str
    kind: type[int] | type[float] | type[str]
    default: float | str | None
    help: str
    low: float = -math.inf
    high: float = math.inf
    low_open: bool = False
    high_open: bool = True
    metavar: str | None = None
    choices: tuple[str, ...] = ()

    @property
    def default_text(self) -> str:
        """The default as ``--help`` shows it (a number in ``%g``, a word as it is)."""
        return self.default if isinstance(self.default, str) else f"{self.default:g}"

    @property
    def dest(self) -> str:
        """The attribute argparse stores it in (``sample_time`` for ``--sample-time``)."""
        return self.flag.removeprefix("--").replace("-", "_")

    @property
    def bounds(self) -> str:
        """What the error says of a value out of bounds ("must be positive and finite")."""
        if self.high == MAX_SEED:
            return f"must be between {self.low:g} and 2**63 - 1"
        if self.low == 0 and self.high == math.inf:
            if self.low_open:
                return "must be positive and finite" if self.high_open else "must be positive"
            return "must be zero or positive and finite"
        if self.low == 0 and self.low_open:
            return f"must be positive and at most {self.high:g}"
        return f"must be between {self.low:g} and {self.high:g}"

    def problem(self, value: float | str) -> str | None:
        """Why ``value`` is refused (:attr:`bounds`), or None (NaN is always refused)."""
        if isinstance(value, str) or self.choices:
            return None if value in self.choices else f"must be one of {', '.join(self.choices)}"
        above = value > self.low if self.low_open else value >= self.low
        below = value < self.high if self.high_open else value <= self.high
        return None if above and below else self.bounds


#: The run options commands share (``cli`` adds each to every command that takes it).
RUN_OPTIONS: dict[str, RunOption] = {
    option.dest: option
    for option in (
        RunOption(
            "--rtol", float, DEFAULT_RTOL, "the integrator's relative tolerance", 0.0, low_open=True
        ),
        RunOption(
            "--atol", float, DEFAULT_ATOL, "the integrator's absolute tolerance", 0.0, low_open=True
        ),
        RunOption(
            "--points",
            int,
            DEFAULT_POINTS,
            "output times of a run (where the certificate and the errors are measured)",
            low=MIN_POINTS,
            high=MAX_POINTS,
            high_open=False,
        ),
        RunOption(
            "--t-final",
            float,
            None,
            "horizon (default: the spec's t_final)",
            low=0.0,
            high=MAX_T_FINAL,
            low_open=True,
            high_open=False,
        ),
        RunOption(
            "--sample-time",
            float,
            None,
            "run the stateful controller sampled every H seconds (zero-order hold); simulate "
            "runs it beside the continuous loop",
            0.0,
            low_open=True,
            metavar="H",
        ),
        RunOption(
            "--reference-noise",
            float,
            0.0,
            "simulate, with --reference-file: Gaussian noise of this standard deviation on "
            "every reference sample",
            low=0.0,
            metavar="SIGMA",
        ),
        RunOption(
            "--measurement-noise",
            float,
            0.0,
            "sweep, with --sample-time: Gaussian noise of this standard deviation on every "
            "measured plant state",
            low=0.0,
            metavar="SIGMA",
        ),
        RunOption(
            "--seed", int, 0, "seed of the random draws", low=0, high=MAX_SEED, high_open=False
        ),
        RunOption(
            "--workers",
            int,
            None,
            "workers of a new local Dask cluster (default: one per core, one per 32 samples at "
            "most; one worker runs in this process; at most what this machine's cores and "
            "memory run, checked by the sweep)",
        ),
        RunOption(
            "--checkpoint-seconds",
            float,
            20.0,
            "save the finished samples to DIR/parts at least every S seconds: a sweep killed "
            "outright (SIGKILL, a node lost) loses at most the last S seconds",
            low=0.0,
            high=86_400.0,
            high_open=False,
            metavar="S",
        ),
        RunOption(
            "--max-seconds",
            float,
            Budget.seconds,
            "time budget of the derivation (of import-urdf: of the import), in seconds",
            low=0.0,
            low_open=True,
            high_open=False,
        ),
        RunOption(
            "--precision",
            str,
            PRECISIONS[0],
            "the C controller's real numbers: single makes every one a float (literals with "
            "f, sinf, sqrtf, ...) for a single-precision FPU; C backend only (docs/precision.md)",
            choices=PRECISIONS,
        ),
        RunOption(
            "--max-size",
            int,
            Budget.size,
            "largest expression tree a derivation stage may build",
            low=0,
            low_open=True,
            high_open=False,
        ),
    )
}
