"""A sweep's options: distributions, spreads, limits and their checks.

Also how a sample can end: the contract's statuses and the loop's own outcomes.
"""

from __future__ import annotations

import enum
import math
import re
import sys
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from tvopt_codegen.contract import Status
from tvopt_codegen.errors import SpecError
from tvopt_codegen.limits import DEFAULT_ATOL, DEFAULT_POINTS, DEFAULT_RTOL

#: Largest number of samples of one sweep.
MAX_SAMPLES = 100_000_000


#: A state this many times larger than the initial one (at least 1) has diverged.
DIVERGENCE_FACTOR = 1e6


#: The settling thresholds: |y - y*| stays below this fraction of its initial value.
SETTLING = (0.01, 0.001)


#: Standard deviations within which every draw of a normal (or lognormal) stays finite.
DRAW_REACH = 40.0


#: Column options of the command line, and what each distribution's parameters are.
DISTRIBUTIONS = {"normal": ("mean", "sd"), "uniform": ("lo", "hi"), "lognormal": ("mu", "sigma")}


class LoopOutcome(enum.IntEnum):
    """How the sweep's loop ends a sample beyond the law's statuses (:class:`Status`)."""

    #: A state left the divergence bound (or an output became non-finite).
    DIVERGED = 16
    #: RK45's step fell below ten units in the last place of t (scipy's "too small").
    STEP_SIZE_COLLAPSE = 17
    #: More RK steps than the sweep allows one sample.
    TOO_MANY_STEPS = 18
    #: Newton's method found no minimiser of f0 along the run.
    NO_MINIMIZER = 19

    @property
    def label(self) -> str:
        """The name in tables: ``diverged``, ``step_size_collapse``, ..."""
        return self.name.lower()


#: How a sample ended: one of the contract's statuses, or one of the loop's own.
Outcome = Status | LoopOutcome


def outcome_of(value: int) -> Outcome:
    """The outcome whose code the compiled loop returned.

    Every status of the contract (:func:`~tvopt_codegen.contract.statuses`) is one, so a
    status added there is recorded by every sweep without a change here.
    """
    if value in LoopOutcome._value2member_map_:
        return LoopOutcome(value)
    return Status.of(value)


@dataclass(frozen=True)
class Distribution:
    """A number, or one of :data:`DISTRIBUTIONS` with its two parameters.

    Attributes
    ----------
    kind : str
        ``fixed``, ``normal``, ``uniform`` or ``lognormal``.
    args : tuple of float
        The value (fixed) or the two parameters.
    """

    kind: str
    args: tuple[float, ...]

    def draw(self, rng: np.random.Generator) -> float:
        """One value (a fixed value draws nothing, so it does not shift later draws)."""
        if self.kind == "fixed":
            return self.args[0]
        a, b = self.args
        if self.kind == "normal":
            return float(rng.normal(a, b))
        if self.kind == "uniform":
            return float(rng.uniform(a, b))
        return float(rng.lognormal(a, b))

    @property
    def centre(self) -> float:
        """The nominal value: the number, the mean, the midpoint or the median."""
        if self.kind == "fixed":
            return self.args[0]
        a, b = self.args
        if self.kind == "normal":
            return a
        if self.kind == "uniform":
            return 0.5 * (a + b)
        return math.exp(a)

    def __str__(self) -> str:
        if self.kind == "fixed":
            return repr(self.args[0])
        return f"{self.kind}({self.args[0]!r}, {self.args[1]!r})"


_CALL = re.compile(r"^\s*([A-Za-z_]\w*)\s*\((.*)\)\s*$")


def parse_distribution(text: str, option: str, name: str) -> Distribution:
    """Parse ``DIST``: a number, ``normal(mean, sd)``, ``uniform(lo, hi)``, ``lognormal(mu, s)``.

    Raises
    ------
    SpecError
        A one-line error naming the option, the name and the problem.
    """

    def number(part: str) -> float:
        try:
            value = float(part)
        except ValueError:
            raise SpecError(
                "command line", option, f"{name}: {part.strip()!r} is not a number"
            ) from None
        if not math.isfinite(value):
            raise SpecError("command line", option, f"{name}: values must be finite")
        return value

    call = _CALL.match(text)
    if call is None:
        if "(" in text or ")" in text:
            raise SpecError(
                "command line",
                option,
                f"{name}: malformed distribution {text!r} (expected a number, "
                "normal(mean, sd), uniform(lo, hi) or lognormal(mu, sigma))",
            )
        return Distribution("fixed", (number(text),))
    kind, inside = call.group(1), call.group(2)
    if kind not in DISTRIBUTIONS:
        raise SpecError(
            "command line",
            option,
            f"{name}: unknown distribution {kind!r} (known: {', '.join(DISTRIBUTIONS)})",
        )
    parts = inside.split(",")
    if len(parts) != 2:
        raise SpecError(
            "command line",
            option,
            f"{name}: {kind} takes two numbers ({', '.join(DISTRIBUTIONS[kind])}), got {text!r}",
        )
    a, b = number(parts[0]), number(parts[1])
    if kind in ("normal", "lognormal") and not b >= 0:
        raise SpecError(
            "command line", option, f"{name}: {kind}'s {DISTRIBUTIONS[kind][1]} must be >= 0"
        )
    if kind == "uniform" and not a <= b:
        raise SpecError("command line", option, f"{name}: uniform needs lo <= hi, got {text!r}")
    # numpy raises for a uniform width beyond the largest float, and the other two give
    # infinity: such a draw would fail every sample, so it is refused here, once.
    if kind == "uniform":
        reach = b - a
    elif kind == "normal":
        reach = abs(a) + DRAW_REACH * b
    else:
        reach = math.inf if a + DRAW_REACH * b > math.log(sys.float_info.max) else 1.0
    if not math.isfinite(reach):
        raise SpecError(
            "command line",
            option,
            f"{name}: {text.strip()!r} draws numbers beyond the largest float (about 1.8e308)",
        )
    return Distribution(kind, (a, b))


def parse_assignments(
    items: Sequence[str], option: str, known: Sequence[str], what: str
) -> tuple[tuple[str, Distribution], ...]:
    """``NAME=DIST`` options, each name one of ``known`` and given once."""
    out: dict[str, Distribution] = {}
    for item in items:
        name, sep, text = item.partition("=")
        name = name.strip()
        if not sep or not name or not text.strip():
            raise SpecError("command line", option, f"expected NAME=DIST, got {item!r}")
        if name not in known:
            raise SpecError(
                "command line",
                option,
                f"unknown {what} {name!r} ({what}s: {', '.join(known) or 'none'})",
            )
        if name in out:
            raise SpecError("command line", option, f"{name} is given twice")
        out[name] = parse_distribution(text, option, name)
    return tuple(out.items())


def parse_limits(
    items: Sequence[str], inputs: Sequence[str]
) -> tuple[tuple[str, float, float], ...]:
    """``INPUT=LIMIT`` (``|u| <= LIMIT``) or ``INPUT=LO:HI``."""
    out: dict[str, tuple[float, float]] = {}
    for item in items:
        name, sep, text = item.partition("=")
        name = name.strip()
        if not sep or not name:
            raise SpecError("command line", "--saturation", f"expected INPUT=LIMIT, got {item!r}")
        if name not in inputs:
            raise SpecError(
                "command line",
                "--saturation",
                f"unknown input {name!r} (inputs: {', '.join(inputs)})",
            )
        try:
            if ":" in text:
                lo_text, hi_text = text.split(":", 1)
                lo, hi = float(lo_text), float(hi_text)
            else:
                hi = float(text)
                lo = -hi
        except ValueError:
            raise SpecError(
                "command line", "--saturation", f"{name}: expected LIMIT or LO:HI, got {text!r}"
            ) from None
        if math.isnan(lo) or math.isnan(hi) or not lo < hi:
            raise SpecError(
                "command line", "--saturation", f"{name}: the limits must satisfy lo < hi"
            )
        out[name] = (lo, hi)
    return tuple((name, lo, hi) for name, (lo, hi) in out.items())


@dataclass(frozen=True)
class SweepOptions:
    """Everything that decides a sweep's table (not where or how fast it runs).

    Attributes
    ----------
    samples : int
        Number of closed-loop runs.
    seed : int
        The root of every sample's ``SeedSequence``.
    t_final : float
        Horizon of each run.
    initial, params, plant_params : tuple of (str, Distribution)
        Spread of the closed-loop initial state (by state name), of the controller's
        parameters and of the true plant's parameters (each unnamed one: the spec's).
    limits : tuple of (str, float, float)
        Input limits (lower, upper): the plant receives the law's input clipped.
    noise : float
        Standard deviation of Gaussian noise on every measured plant state (sampled
        loops only: one draw per state and sample).
    sample_time : float or None
        Sampled-data loop (the stateful controller, zero-order hold) every this many
        seconds; None: the continuous loop.
    rtol, atol : float
        RK45's tolerances.
    points : int
        Output times per run (where ``y*``, the errors and the inputs are measured).
    max_steps : int
        RK steps one run may take (accepted and rejected).
    window : float
        Where ``integrated_error`` and ``max_error_after`` start (seconds, at most
        ``t_final``): the tuner's measures of the error after the transient it allows.
        ``sweep`` keeps 0.
    """

    samples: int
    seed: int
    t_final: float
    initial: tuple[tuple[str, Distribution], ...] = ()
    params: tuple[tuple[str, Distribution], ...] = ()
    plant_params: tuple[tuple[str, Distribution], ...] = ()
    limits: tuple[tuple[str, float, float], ...] = ()
    noise: float = 0.0
    sample_time: float | None = None
    rtol: float = DEFAULT_RTOL
    atol: float = DEFAULT_ATOL
    points: int = DEFAULT_POINTS
    max_steps: int = 1_000_000
    window: float = 0.0

    def as_dict(self) -> dict[str, Any]:
        """A JSON-ready record (``sweep.json``)."""
        return {
            "samples": self.samples,
            "seed": self.seed,
            "t_final": self.t_final,
            "initial": {n: str(d) for n, d in self.initial},
            "params": {n: str(d) for n, d in self.params},
            "plant_params": {n: str(d) for n, d in self.plant_params},
            "limits": {n: [lo, hi] for n, lo, hi in self.limits},
            "noise": self.noise,
            "sample_time": self.sample_time,
            "rtol": self.rtol,
            "atol": self.atol,
            "points": self.points,
            "max_steps": self.max_steps,
            "window": self.window,
        }

    @classmethod
    def from_dict(cls, record: Mapping[str, Any]) -> SweepOptions:
        """The inverse of :meth:`as_dict`."""

        def dists(key: str) -> tuple[tuple[str, Distribution], ...]:
            return tuple(
                (name, parse_distribution(text, key, name)) for name, text in record[key].items()
            )

        return cls(
            samples=int(record["samples"]),
            seed=int(record["seed"]),
            t_final=float(record["t_final"]),
            initial=dists("initial"),
            params=dists("params"),
            plant_params=dists("plant_params"),
            limits=tuple((n, float(lo), float(hi)) for n, (lo, hi) in record["limits"].items()),
            noise=float(record["noise"]),
            sample_time=None if record["sample_time"] is None else float(record["sample_time"]),
            rtol=float(record["rtol"]),
            atol=float(record["atol"]),
            points=int(record["points"]),
            max_steps=int(record["max_steps"]),
            # Records written before the window existed: 0, as their sweeps measured.
            window=float(record.get("window", 0.0)),
        )
