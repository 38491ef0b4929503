"""Monte-Carlo robustness sweeps: thousands of closed loops, each with its own plant.

A sweep draws, for every sample, an initial state, the controller's (model's)
parameters and the true plant's parameters from the distributions the user names; runs
the closed loop in compiled C (``templates/c/sweep.c.jinja``: the true plant under the
law, inputs clipped to their limits, optionally sampled every ``H`` seconds with noisy
measurements, integrated by Dormand-Prince RK45 with scipy's error control, then
``y*(t)`` by the Newton method of :mod:`tvopt_codegen.simulation`); and tabulates each
run's outcome. Samples are spread over a Dask cluster in chunks; a worker builds (or
finds in its cache) the compiled loop from the sources' hash and never receives a
ctypes handle.

Sample ``i`` draws from ``numpy.random.default_rng(seed_i)``, where ``seed_i`` is the
first 64-bit word of ``SeedSequence(seed, spawn_key=(i,))`` (the sweep's ``i``-th
child) shifted right by one bit; ``seed_i`` is stored with the sample, so any sample
can be rerun alone, and the table is the same bit for bit whatever the number of
workers or the chunk size.

Nothing here writes files: :mod:`tvopt_codegen.emit` does.
"""

from __future__ import annotations

import ctypes
import enum
import hashlib
import math
import re
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from tvopt_codegen.contract import Status
from tvopt_codegen.errors import MissingExtraError, SpecError
from tvopt_codegen.limits import START_ITERATIONS

if TYPE_CHECKING:
    from tvopt_codegen.ir import KernelSet

#: Largest number of output times of one sample (the C loop keeps its grid on the stack).
MAX_POINTS = 10_001
#: Largest number of samples of one sweep.
MAX_SAMPLES = 100_000_000
#: A state this many times larger than the initial one (at least 1) has diverged.
DIVERGENCE_FACTOR = 1e6
#: The settling thresholds: |y - y*| stays below this fraction of its initial value.
SETTLING = (0.01, 0.001)
#: Seconds to wait for a scheduler named by ``--scheduler``.
SCHEDULER_TIMEOUT = 10.0
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


# ------------------------------------------------------------------ distributions


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


# ------------------------------------------------------------------ what a sweep is


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
    rtol: float = 1e-8
    atol: float = 1e-10
    points: int = 201
    max_steps: int = 1_000_000

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
        )


@dataclass(frozen=True)
class SweepProgram:
    """What a worker needs to run samples: the C sources and the spec's names and numbers.

    Attributes
    ----------
    name : str
        The spec's module name (the C functions' prefix).
    key : str
        SHA-256 of the sources: the compiled library's cache key.
    sources : tuple of (str, str)
        File name and text: ``<name>.h``, ``<name>.c`` and ``<name>_sweep.c``.
    state_names, plant_state_names, input_names, output_names, param_names : tuple of str
        The closed loop's names, in the C arrays' order.
    defaults : tuple of float
        The parameters' spec values.
    initial_state : tuple of float
        The spec's closed-loop initial state.
    coefficients : tuple of float
        The Hurwitz coefficients of H.
    alpha, c : float
        The certificate's constants: ``|expm(H t)| <= c e^(-alpha t)``.
    constraints : tuple of str
        The names of the spec's inequalities (their values are measured on the run).
    equalities : tuple of str
        The names of its equality constraints (``|a|`` is measured on the run, and y* is
        the KKT point).
    n_kkt : int
        Entries of a row of the optimality error: the outputs, then the multipliers.
    """

    name: str
    key: str
    sources: tuple[tuple[str, str], ...]
    state_names: tuple[str, ...]
    plant_state_names: tuple[str, ...]
    input_names: tuple[str, ...]
    output_names: tuple[str, ...]
    param_names: tuple[str, ...]
    defaults: tuple[float, ...]
    initial_state: tuple[float, ...]
    coefficients: tuple[float, ...]
    alpha: float
    c: float
    constraints: tuple[str, ...] = ()
    equalities: tuple[str, ...] = ()
    n_kkt: int = 0

    @property
    def columns(self) -> int:
        """Width of a trajectory row: t, s, y, y*, u, then the :data:`TAIL` columns."""
        n, m, nu = len(self.state_names), len(self.output_names), len(self.input_names)
        return 1 + n + 2 * m + nu + len(TAIL)


#: A trajectory row's last columns, after t, s, y, y* and u: log|det R|, the certificate's
#: m_f (with equalities, the KKT matrix's sigma_min), the barrier's margin
#: min_i (s - g_i), max_i g_i, and max_j |a_j| (NaN where the spec has none of them).
TAIL = ("log_det_R", "m_f", "margin", "max_constraint", "max_equality")


def tail(rows: np.ndarray, name: str) -> np.ndarray:
    """The :data:`TAIL` column ``name`` of trajectory rows (any leading dimensions)."""
    column: np.ndarray = rows[..., TAIL.index(name) - len(TAIL)]
    return column


def decoupling_kernel(kernels: KernelSet) -> Any:
    """The sweep's own kernel: the whole decoupling matrix R(s), row-major (for det R)."""
    from tvopt_codegen.cse import make_kernel  # noqa: PLC0415 - sympy only when building
    from tvopt_codegen.ir import _arguments  # noqa: PLC0415

    d = kernels.derivation
    args = _arguments(d)
    m = d.R.rows
    entries = [d.R[i, j] for i in range(m) for j in range(m)]
    return make_kernel(
        "sweep_decoupling",
        "The decoupling matrix R(s), row-major",
        [args.t, args.s, args.p],
        [],
        [("r", (m * m,), entries, "decoupling matrix R")],
        args.subs,
        odd={},
    )


def constraint_kernel(kernels: KernelSet) -> Any:
    """The slack ``s(t)`` and each ``g_i(y, t)`` at the outputs (None without constraints)."""
    import sympy as sp  # noqa: PLC0415 - a worker never needs sympy

    from tvopt_codegen.cse import make_kernel  # noqa: PLC0415
    from tvopt_codegen.ir import _arguments  # noqa: PLC0415

    d = kernels.derivation
    model = d.model
    if not model.constraints:
        return None
    args = _arguments(d)
    values = [model.slack, *(sp.sympify(c.g) for c in model.constraints)]
    return make_kernel(
        "sweep_constraints",
        "The barrier's slack s(t), then each constraint g_i(y, t) (<= 0 when kept)",
        [args.t, args.y, args.p],
        list(model.signals),
        [("g", (len(values),), values, "slack and constraint values")],
        args.y_subs,
        odd={},
    )


def equality_kernel(kernels: KernelSet) -> Any:
    """``a(y, t)``, ``J_a`` and ``sum_j nu_j grad_yy a_j`` (None without equalities)."""
    import sympy as sp  # noqa: PLC0415 - a worker never needs sympy

    from tvopt_codegen.cse import make_kernel  # noqa: PLC0415
    from tvopt_codegen.ir import _arguments  # noqa: PLC0415
    from tvopt_codegen.kernel import Arg  # noqa: PLC0415
    from tvopt_codegen.law import symbols  # noqa: PLC0415

    d = kernels.derivation
    model = d.model
    if not model.equalities:
        return None
    args = _arguments(d)
    slots = symbols("nu", len(model.multipliers))
    arg_nu = Arg("nu", slots, tuple(nu.name for nu in model.multipliers), "multipliers")
    a = [sp.sympify(c.g) for c in model.equalities]
    curvature = [
        sp.Add(*(nu * sp.diff(e, yi, yj) for nu, e in zip(model.multipliers, a, strict=True)))
        for yi in model.y
        for yj in model.y
    ]
    m, q = len(model.y), len(a)
    return make_kernel(
        "sweep_equalities",
        "The equalities a_j(y, t), their Jacobian in y and sum_j nu_j grad_yy a_j",
        [args.t, args.y, args.p, arg_nu],
        list(model.signals),
        [
            ("a", (q,), a, "equality values (0 when kept)"),
            ("jac", (q, m), [sp.diff(e, y) for e in a for y in model.y], "J_a"),
            ("curv", (m, m), curvature, "the multipliers' curvature"),
        ],
        args.y_subs | dict(zip(model.multipliers, slots, strict=True)),
        odd={},
    )


def sweep_program(kernels: KernelSet) -> SweepProgram:
    """Render the C closed loop of a lowered controller.

    Raises
    ------
    SpecError
        For a spec with ``[references]`` (the compiled loop has no reference source yet).
    """
    import scipy  # noqa: PLC0415
    from scipy.integrate._ivp.rk import RK45  # noqa: PLC0415

    from tvopt_codegen.backends import BACKENDS  # noqa: PLC0415
    from tvopt_codegen.rendering import (  # noqa: PLC0415
        print_kernel,
        render,
        render_template,
        template_context,
    )

    d = kernels.derivation
    if d.model.references:
        raise SpecError(
            d.spec.source,
            "references",
            "sweep does not run specs with [references] yet: sweep the spec without them "
            "(the nominal closed forms as signals)",
        )
    backend = BACKENDS["c"]
    files = render(kernels, backend)
    name = d.spec.name
    context = template_context(kernels, backend)
    constraints = constraint_kernel(kernels)
    equalities = equality_kernel(kernels)
    context |= {
        "equalities": None if equalities is None else print_kernel(equalities, backend.printer()),
        "equality_count": len(d.model.equalities),
        "multiplier_rows": [d.state_names.index(chain[0]) for chain in d.multiplier_states],
        "tail": TAIL,
        "decoupling": print_kernel(decoupling_kernel(kernels), backend.printer()),
        "constraints": None
        if constraints is None
        else print_kernel(constraints, backend.printer()),
        "constraint_count": len(d.model.constraints),
        "rk": {
            "A": RK45.A[:, :5].tolist(),
            "B": RK45.B.tolist(),
            "C": RK45.C.tolist(),
            "E": RK45.E.tolist(),
            "P": RK45.P.tolist(),
        },
        "scipy_version": scipy.__version__,
        "sweep_statuses": list(LoopOutcome),
        "max_points": MAX_POINTS,
        "start_iterations": START_ITERATIONS,
    }
    sources = (
        (f"{name}.h", files[f"{name}.h"]),
        (f"{name}.c", files[f"{name}.c"]),
        (f"{name}_sweep.c", render_template("c/sweep.c.jinja", context)),
    )
    digest = hashlib.sha256()
    for file_name, text in sources:
        digest.update(hashlib.sha256(f"{file_name}\0{text}".encode()).digest())
    return SweepProgram(
        name=name,
        key=digest.hexdigest(),
        sources=sources,
        state_names=tuple(d.state_names),
        plant_state_names=tuple(d.spec.states),
        input_names=tuple(d.spec.inputs),
        output_names=tuple(d.spec.outputs),
        param_names=tuple(n for n, _ in d.spec.parameters),
        defaults=tuple(float(v) for _, v in d.spec.parameters),
        initial_state=tuple(float(v) for v in d.initial_state),
        coefficients=tuple(float(a) for a in d.coefficients),
        alpha=float(d.certified_rate),
        c=float(d.transient_constant),
        constraints=tuple(c.name for c in d.model.constraints),
        equalities=tuple(c.name for c in d.model.equalities),
        n_kkt=d.n_kkt,
    )


def check_options(program: SweepProgram, options: SweepOptions) -> None:
    """Refuse what the loop cannot run, naming the option (all before anything runs)."""
    if not 1 <= options.samples <= MAX_SAMPLES:
        raise SpecError("command line", "--samples", f"must be between 1 and {MAX_SAMPLES}")
    if not 0 <= options.seed < 2**63:
        raise SpecError("command line", "--seed", "must be between 0 and 2**63 - 1")
    if not 0 < options.t_final <= 1e6:
        raise SpecError("command line", "--t-final", "must be positive and at most 1e6")
    if not 2 <= options.points <= MAX_POINTS:
        raise SpecError("command line", "--points", f"must be between 2 and {MAX_POINTS}")
    for option, value in (("--rtol", options.rtol), ("--atol", options.atol)):
        if not 0 < value < math.inf:
            raise SpecError("command line", option, "must be positive and finite")
    if not 0 <= options.noise < math.inf:
        raise SpecError("command line", "--noise", "must be zero or positive and finite")
    if options.sample_time is not None:
        if not 0 < options.sample_time < math.inf:
            raise SpecError("command line", "--sample-time", "must be positive and finite")
        if options.t_final / options.sample_time > 10_000_000:
            raise SpecError(
                "command line", "--sample-time", "more than 10^7 samples of the controller per run"
            )
    elif options.noise:
        raise SpecError(
            "command line",
            "--noise",
            "needs --sample-time (the noise is drawn once per measurement)",
        )


# ------------------------------------------------------------------ one sample


@dataclass(frozen=True)
class Draw:
    """What sample ``index`` drew."""

    index: int
    seed: int
    values: dict[str, float]
    s0: np.ndarray
    cp: np.ndarray
    pp: np.ndarray
    noise: np.ndarray | None


def sample_seed(root: int, index: int) -> int:
    """The seed of sample ``index``: the sweep's ``index``-th child's first word, 63 bits.

    63 bits, so that the seed is a signed 64-bit integer in every table format.
    """
    child = np.random.SeedSequence(root, spawn_key=(index,))
    return int(child.generate_state(1, np.uint64)[0]) >> 1


def draw(program: SweepProgram, options: SweepOptions, index: int) -> Draw:
    """Sample ``index``'s initial state, parameters and noise (in that order)."""
    seed = sample_seed(options.seed, index)
    rng = np.random.default_rng(seed)
    values: dict[str, float] = {}
    s0 = np.array(program.initial_state, dtype=float)
    for name, dist in options.initial:
        value = dist.draw(rng)
        values[f"initial.{name}"] = value
        s0[program.state_names.index(name)] = value
    cp = np.array(program.defaults, dtype=float)
    for name, dist in options.params:
        value = dist.draw(rng)
        values[f"param.{name}"] = value
        cp[program.param_names.index(name)] = value
    pp = np.array(program.defaults, dtype=float)
    for name, dist in options.plant_params:
        value = dist.draw(rng)
        values[f"plant.{name}"] = value
        pp[program.param_names.index(name)] = value
    noise = None
    if options.noise and options.sample_time is not None:
        count = math.ceil(options.t_final / options.sample_time - 1e-9) + 1
        noise = options.noise * rng.standard_normal((count, len(program.plant_state_names)))
    return Draw(index, seed, values, s0, cp, pp, noise)


class Loop:
    """The compiled closed loop of one program, loaded in this process.

    Parameters
    ----------
    program : SweepProgram
        Its sources; compiled once per machine into the cache (``TVOPT_CODEGEN_CACHE``).
    """

    def __init__(self, program: SweepProgram) -> None:
        from tvopt_codegen.emit import cached_library  # noqa: PLC0415

        self.program = program
        path = cached_library(dict(program.sources), f"{program.name}_sweep.c")
        library = ctypes.CDLL(str(path))
        pointer = ctypes.POINTER(ctypes.c_double)
        self._run = getattr(library, f"{program.name}_sweep_run")
        self._run.restype = ctypes.c_int
        self._run.argtypes = [pointer] * 8
        self._error = getattr(library, f"{program.name}_optimality_error")
        self._error.restype = ctypes.c_int
        self._error.argtypes = [ctypes.c_double, pointer, pointer, pointer]

    @staticmethod
    def _ptr(array: np.ndarray | None) -> Any:
        if array is None:
            return None
        return array.ctypes.data_as(ctypes.POINTER(ctypes.c_double))

    def run(self, options: SweepOptions, sample: Draw) -> tuple[Outcome, np.ndarray, np.ndarray]:
        """Integrate one sample: its outcome, the rows written and the run's counters."""
        p = self.program
        bound = DIVERGENCE_FACTOR * max(1.0, float(np.max(np.abs(sample.s0), initial=0.0)))
        settings = np.array(
            [
                options.t_final,
                options.rtol,
                options.atol,
                options.sample_time or 0.0,
                options.points,
                options.max_steps,
                bound,
            ]
        )
        lower = np.full(len(p.input_names), -np.inf)
        upper = np.full(len(p.input_names), np.inf)
        for name, lo, hi in options.limits:
            lower[p.input_names.index(name)] = lo
            upper[p.input_names.index(name)] = hi
        limits = np.concatenate([lower, upper])
        rows = np.full((options.points, p.columns), np.nan)
        info = np.zeros(4)
        noise = None if sample.noise is None else np.ascontiguousarray(sample.noise)
        cp, pp = np.ascontiguousarray(sample.cp), np.ascontiguousarray(sample.pp)
        # The C reads a pointer even for an empty parameter vector.
        if not len(cp):
            cp, pp = np.zeros(1), np.zeros(1)
        status = self._run(
            self._ptr(settings),
            self._ptr(np.ascontiguousarray(sample.s0)),
            self._ptr(cp),
            self._ptr(pp),
            self._ptr(limits),
            self._ptr(noise),
            self._ptr(rows),
            self._ptr(info),
        )
        written = int(info[1])
        return outcome_of(status), rows[:written], info

    def optimality_error(self, s: np.ndarray, params: np.ndarray) -> np.ndarray:
        """E at t = 0 (K rows of the gradient jet, or of the KKT map with equalities)."""
        width = self.program.n_kkt or len(self.program.output_names)
        out = np.empty(len(self.program.coefficients) * width)
        self._error(0.0, self._ptr(np.ascontiguousarray(s)), self._ptr(params), self._ptr(out))
        return out


_LOOPS: dict[str, Loop] = {}


def loop_for(program: SweepProgram) -> Loop:
    """The loaded loop of ``program`` (built or loaded from the cache once)."""
    if program.key not in _LOOPS:
        _LOOPS[program.key] = Loop(program)
    return _LOOPS[program.key]


@dataclass(frozen=True)
class SampleResult:
    """One row of the summary and, when kept, the run's trajectory.

    Attributes
    ----------
    row : dict
        The summary's columns for this sample.
    trajectory : numpy.ndarray or None
        ``points x columns`` (NaN after a failure); see :attr:`SweepProgram.columns`.
    """

    row: dict[str, Any]
    trajectory: np.ndarray | None


def _settling(t: np.ndarray, error: np.ndarray, fraction: float) -> float:
    """The first time after which ``error`` stays at or below ``fraction`` of its start."""
    above = np.nonzero(error > fraction * error[0])[0]
    if not len(above):
        return 0.0
    last = int(above[-1])
    return float(t[last + 1]) if last + 1 < len(t) else math.nan


def _certificate(
    loop: Loop, sample: Draw, t: np.ndarray, convexity: np.ndarray, error: np.ndarray
) -> bool:
    """Whether ``|y - y*| <= c |E(0)| / m_f e^(-alpha t)`` held (the nominal theorem).

    ``m_f`` is the least eigenvalue of f0's Hessian at y, y* and their midpoint along
    the run (the C loop's last column), as :mod:`tvopt_codegen.simulation` estimates it.
    """
    p = loop.program
    cp = sample.cp if len(sample.cp) else np.zeros(1)
    norm0 = float(np.linalg.norm(loop.optimality_error(sample.s0, cp)))
    smallest = float(np.min(convexity))
    if not smallest > 0:
        return False
    bound = p.c * norm0 / smallest * np.exp(-p.alpha * t)
    meaningful = bound > 1e-10
    return bool(np.all(error[meaningful] - 1e-8 <= bound[meaningful]))


def run_sample(
    program: SweepProgram, options: SweepOptions, index: int, keep: bool = False
) -> SampleResult:
    """Run sample ``index`` and measure it; keep its trajectory when asked."""
    loop = loop_for(program)
    sample = draw(program, options, index)
    outcome, rows, info = loop.run(options, sample)
    n, m = len(program.state_names), len(program.output_names)
    nu = len(program.input_names)
    t = rows[:, 0]
    y = rows[:, 1 + n : 1 + n + m]
    target = rows[:, 1 + n + m : 1 + n + 2 * m]
    u = rows[:, 1 + n + 2 * m : 1 + n + 2 * m + nu]
    logdet, convexity = tail(rows, "log_det_R"), tail(rows, "m_f")
    margin, largest = tail(rows, "margin"), tail(rows, "max_constraint")
    error = np.linalg.norm(y - target, axis=1) if len(rows) else np.zeros(0)
    ok = outcome == Status.OK
    limits = {name: (lo, hi) for name, lo, hi in options.limits}
    saturated = np.zeros(len(rows), dtype=bool)
    for j, name in enumerate(program.input_names):
        if name in limits:
            lo, hi = limits[name]
            saturated |= (u[:, j] < lo) | (u[:, j] > hi)
    spacing = options.t_final / (options.points - 1)
    mismatch = bool(np.any(sample.cp != sample.pp))
    nominal = (
        ok
        and not mismatch
        and not saturated.any()
        and options.sample_time is None
        and not options.noise
    )
    row: dict[str, Any] = {
        "sample": index,
        "seed": sample.seed,
        "status": outcome.label,
        "t_end": float(info[0]),
        "final_error": float(error[-1]) if ok else math.nan,
        "max_error": float(error.max()) if ok else math.nan,
        "settling_1pct": _settling(t, error, SETTLING[0]) if ok else math.nan,
        "settling_01pct": _settling(t, error, SETTLING[1]) if ok else math.nan,
    }
    for j, name in enumerate(program.input_names):
        row[f"max_abs_{name}"] = float(np.abs(u[:, j]).max()) if len(rows) else math.nan
    row["time_saturated"] = float(saturated[:-1].sum() * spacing) if len(rows) else 0.0
    # log|det R| is -inf where R is singular: the ratio is then 0.
    if not len(rows):
        row["min_det_ratio"] = math.nan
    elif np.isfinite(logdet[0]):
        row["min_det_ratio"] = float(np.exp(np.min(logdet) - logdet[0]))
    else:
        row["min_det_ratio"] = 0.0
    if program.constraints:
        # The barrier keeps g_i < s(t) (the certificate's claim); g_i > 0 alone is allowed
        # while the slack is still open.
        row["min_margin"] = float(np.min(margin)) if len(rows) else math.nan
        row["violations"] = int(np.sum(margin <= 0.0))
        row["time_outside"] = float(np.sum(largest[:-1] > 0.0) * spacing) if len(rows) else 0.0
        row["final_constraint"] = float(largest[-1]) if ok else math.nan
    if program.equalities:
        # max_j |a_j| along the run: the KKT law drives it to 0 like E.
        drift = tail(rows, "max_equality")
        row["max_equality"] = float(np.max(drift)) if len(rows) else math.nan
        row["final_equality"] = float(drift[-1]) if ok else math.nan
    row["steps"] = int(info[2])
    row["rejected_steps"] = int(info[3])
    row["nominal"] = nominal
    row["certificate_holds"] = _certificate(loop, sample, t, convexity, error) if nominal else None
    row |= sample.values
    return SampleResult(row, rows if keep else None)


def run_chunk(
    program: SweepProgram, options: SweepOptions, indices: Sequence[int], keep: bool
) -> list[SampleResult]:
    """Samples ``indices`` in this process (what one Dask task runs)."""
    return [run_sample(program, options, i, keep) for i in indices]


# ------------------------------------------------------------------ on Dask


def chunks(samples: int, size: int) -> Iterator[range]:
    """Consecutive ranges of sample indices, ``size`` at a time."""
    for start in range(0, samples, size):
        yield range(start, min(start + size, samples))


def default_chunk(samples: int, workers: int) -> int:
    """Small enough to keep every worker busy to the end, large enough to amortise a task."""
    return max(1, min(256, math.ceil(samples / (8 * max(1, workers)))))


def _distributed() -> Any:
    try:
        import distributed  # noqa: PLC0415
    except ImportError:
        raise MissingExtraError(
            "sweep needs Dask: pip install 'tvopt-codegen[sweep]' (dask[distributed], "
            "pyarrow, zarr, xarray)"
        ) from None
    return distributed


@dataclass
class SweepRun:
    """A sweep as it ran.

    Attributes
    ----------
    results : list of SampleResult
        Every finished sample, in sample order.
    interrupted : bool
        Ctrl-C stopped it: ``results`` holds what finished.
    seconds : float
        Wall time from the first task sent to the last result.
    workers : int
        Workers of the cluster.
    dashboard : str
        The Dask dashboard's address (empty when there is none).
    """

    results: list[SampleResult] = field(default_factory=list)
    interrupted: bool = False
    seconds: float = 0.0
    workers: int = 0
    dashboard: str = ""


def connect(workers: int | None, scheduler: str | None) -> tuple[Any, Any]:
    """A Dask client: on ``scheduler`` unchanged, else on a new ``LocalCluster``.

    Raises
    ------
    SpecError
        An unreachable scheduler (``--scheduler``, within :data:`SCHEDULER_TIMEOUT`), or a
        bad ``--workers``.
    """
    distributed = _distributed()
    import logging  # noqa: PLC0415

    if scheduler is not None:
        try:
            client = distributed.Client(scheduler, timeout=f"{SCHEDULER_TIMEOUT}s")
        except (OSError, TimeoutError) as exc:
            raise SpecError(
                "command line", "--scheduler", f"cannot reach {scheduler}: {exc}"
            ) from None
        return client, None
    if workers is not None and not 1 <= workers <= 1024:
        raise SpecError("command line", "--workers", "must be between 1 and 1024")
    import os  # noqa: PLC0415

    count = workers or os.cpu_count() or 1
    cluster = distributed.LocalCluster(
        n_workers=count,
        threads_per_worker=1,
        processes=True,
        dashboard_address=":0",
        silence_logs=logging.ERROR,
    )
    return distributed.Client(cluster), cluster


def run_sweep(
    client: Any,
    program: SweepProgram,
    options: SweepOptions,
    *,
    chunk: int | None = None,
    keep: bool = False,
    on_results: Callable[[list[SampleResult]], None] | None = None,
    progress: Callable[[int, int, float], None] | None = None,
) -> SweepRun:
    """Run every sample on ``client``'s cluster, chunk by chunk.

    Parameters
    ----------
    client : distributed.Client
        The cluster to run on.
    program, options : SweepProgram, SweepOptions
        What to run.
    chunk : int, optional
        Samples per task (default :func:`default_chunk`).
    keep : bool
        Return every sample's trajectory.
    on_results : callable, optional
        Called in the client with each finished chunk (to store it as it arrives).
    progress : callable, optional
        ``progress(done, failed, rate)`` after each chunk.

    Returns
    -------
    SweepRun
        The results in sample order; ``interrupted`` after Ctrl-C (the workers are
        stopped, the finished chunks kept).
    """
    distributed = _distributed()
    workers = len(client.scheduler_info().get("workers", {})) or 1
    size = chunk or default_chunk(options.samples, workers)
    # A fresh key per sweep: a key shared with an earlier sweep on the same client could
    # still be in release when this one needs it ("lost dependencies").
    scattered = client.scatter(program, broadcast=True, hash=False)
    started = time.perf_counter()
    futures = [
        client.submit(run_chunk, scattered, options, list(r), keep, pure=False)
        for r in chunks(options.samples, size)
    ]
    run = SweepRun(workers=workers, dashboard=str(getattr(client, "dashboard_link", "") or ""))
    done = failed = 0
    try:
        for future in distributed.as_completed(futures):
            results = future.result()
            run.results.extend(results)
            done += len(results)
            failed += sum(r.row["status"] != "ok" for r in results)
            if on_results is not None:
                on_results(results)
            if progress is not None:
                progress(done, failed, done / max(time.perf_counter() - started, 1e-9))
    except KeyboardInterrupt:
        run.interrupted = True
        client.cancel(futures)
    run.seconds = time.perf_counter() - started
    run.results.sort(key=lambda r: int(r.row["sample"]))
    return run


# ------------------------------------------------------------------ what it says


def clopper_pearson_upper(failures: int, runs: int, confidence: float = 0.95) -> float:
    """One-sided upper confidence bound on a failure probability (exact binomial).

    With no failure it is ``1 - (1 - confidence)^(1/runs)``: 0 in 299 runs gives 0.99%.
    """
    from scipy.stats import beta  # noqa: PLC0415

    if runs == 0:
        return 1.0
    if failures >= runs:
        return 1.0
    return float(beta.ppf(confidence, failures + 1, runs - failures))


@dataclass(frozen=True)
class Summary:
    """The sweep's statistics (``summary.md`` and the terminal)."""

    runs: int
    requested: int
    outcomes: dict[str, int]
    failure_rate: float
    failure_upper: float
    final_error: dict[str, float]
    settling: dict[str, float]
    worst: list[tuple[int, float]]
    nominal: int
    nominal_certified: int
    interrupted: bool
    constrained: bool = False
    violating: int = 0
    ended_outside: int = 0
    final_equality: dict[str, float] = field(default_factory=dict)


def summarize(
    results: Sequence[SampleResult], requested: int, interrupted: bool, worst: int = 5
) -> Summary:
    """Outcomes, failure probability (Clopper-Pearson 95%), error quantiles, worst samples."""
    rows = [r.row for r in results]
    outcomes: dict[str, int] = {}
    for row in rows:
        outcomes[row["status"]] = outcomes.get(row["status"], 0) + 1
    failures = sum(count for status, count in outcomes.items() if status != "ok")
    ok = [row for row in rows if row["status"] == "ok"]
    finals = np.array([row["final_error"] for row in ok])
    settle = np.array([row["settling_1pct"] for row in ok])

    def quantiles(values: np.ndarray) -> dict[str, float]:
        if not len(values):
            return {}
        finite = values[np.isfinite(values)]
        out = {"never": float(len(values) - len(finite))}
        if len(finite):
            for label, q in (("median", 50), ("p95", 95), ("p99", 99)):
                out[label] = float(np.percentile(finite, q))
            out["max"] = float(finite.max())
        return out

    ranked = sorted(ok, key=lambda row: (-row["final_error"], row["sample"]))[:worst]
    nominal = [row for row in ok if row["nominal"]]
    return Summary(
        runs=len(rows),
        requested=requested,
        outcomes=dict(sorted(outcomes.items(), key=lambda item: (item[0] != "ok", item[0]))),
        failure_rate=failures / len(rows) if rows else math.nan,
        failure_upper=clopper_pearson_upper(failures, len(rows)),
        final_error=quantiles(finals),
        settling={k: v for k, v in quantiles(settle).items()},
        worst=[(int(row["sample"]), float(row["final_error"])) for row in ranked],
        nominal=len(nominal),
        nominal_certified=sum(bool(row["certificate_holds"]) for row in nominal),
        interrupted=interrupted,
        constrained=bool(rows) and "violations" in rows[0],
        violating=sum(int(row.get("violations", 0)) > 0 for row in rows),
        ended_outside=sum(row.get("final_constraint", -1.0) > 0 for row in ok),
        final_equality=quantiles(np.array([row["final_equality"] for row in ok]))
        if ok and "final_equality" in ok[0]
        else {},
    )


def format_summary(name: str, options: SweepOptions, summary: Summary) -> str:
    """The summary as Markdown (also what the terminal shows)."""
    s = summary
    failures = s.runs - s.outcomes.get("ok", 0)
    lines = [f"# Sweep of {name}: {s.runs} samples", ""]
    if s.interrupted:
        lines += [f"Interrupted: {s.runs} of {s.requested} samples finished.", ""]
    spread = [f"`--initial {n}={d}`" for n, d in options.initial]
    spread += [f"`--param {n}={d}`" for n, d in options.params]
    spread += [f"`--plant-param {n}={d}`" for n, d in options.plant_params]
    spread += [f"`--saturation {n}={lo:g}:{hi:g}`" for n, lo, hi in options.limits]
    if options.noise:
        spread.append(f"`--noise {options.noise:g}`")
    loop = (
        f"sampled every {options.sample_time:g} s (zero-order hold)"
        if options.sample_time
        else "continuous"
    )
    lines += [
        f"Seed {options.seed}; horizon {options.t_final:g} s; loop {loop}; RK45 rtol "
        f"{options.rtol:g}, atol {options.atol:g}; {options.points} output times.",
        "",
        "Spread: " + (", ".join(spread) if spread else "none (every sample is the spec's run)"),
        "",
        "| outcome | samples | share |",
        "|---|---:|---:|",
    ]
    for status, count in s.outcomes.items():
        lines.append(f"| {status} | {count} | {100 * count / max(s.runs, 1):.2f}% |")
    lines += [
        "",
        f"Failure probability: {failures}/{s.runs} = {100 * s.failure_rate:.3g}%; "
        f"Clopper-Pearson 95% upper bound {100 * s.failure_upper:.3g}%.",
        "",
    ]
    if s.final_error:
        lines += [
            "| ok samples | median | p95 | p99 | max | never settled |",
            "|---|---:|---:|---:|---:|---:|",
        ]
        for label, q in (
            ("final \\|y - y*\\|", s.final_error),
            ("settling time to 1% (s)", s.settling),
            *(
                (("final max_j \\|a_j\\| (equalities)", s.final_equality),)
                if s.final_equality
                else ()
            ),
        ):
            cells = [f"{q[k]:.3g}" if k in q else "-" for k in ("median", "p95", "p99", "max")]
            lines.append(f"| {label} | {' | '.join(cells)} | {int(q.get('never', 0))} |")
        lines.append("")
    if s.constrained:
        lines += [
            f"Constraints: {s.violating} of {s.runs} samples crossed the barrier (g_i >= s(t) at "
            f"some output time; the barrier claims never); {s.ended_outside} ok samples end "
            "outside a constraint (g_i > 0 at the horizon).",
            "",
        ]
    if s.nominal:
        lines += [
            f"Nominal samples (no mismatch, no saturation, no noise, continuous): {s.nominal}; "
            f"the theorem's bound |y - y*| <= C e^(-alpha t) held on {s.nominal_certified}.",
            "",
        ]
    if s.worst:
        lines += [
            "Worst samples by final |y - y*| (rerun one: `tvopt-codegen sweep --replay DIR ID`):",
            "",
        ]
        lines += [f"- sample {i}: {e:.3g}" for i, e in s.worst]
        lines.append("")
    return "\n".join(lines)


# ------------------------------------------------------------------ what it writes


def trajectory_layout(
    program: SweepProgram, options: SweepOptions, chunk: int
) -> tuple[dict[str, Any], dict[str, np.ndarray], dict[str, Any]]:
    """The Zarr store's arrays (dimensions, shape, chunks), coordinates and attributes."""
    n, m, nu = len(program.state_names), len(program.output_names), len(program.input_names)
    count, points = options.samples, options.points

    def variable(
        *names: tuple[str, int],
    ) -> tuple[tuple[str, ...], tuple[int, ...], tuple[int, ...]]:
        dims = ("sample", "time", *(name for name, _ in names))
        shape = (count, points, *(size for _, size in names))
        return dims, shape, (chunk, points, *(size for _, size in names))

    variables = {
        "t": variable(),
        "state": variable(("state_name", n)),
        "output": variable(("output_name", m)),
        "target": variable(("output_name", m)),
        "input": variable(("input_name", nu)),
        **{name: variable() for name in TAIL},
    }
    coords = {
        "sample": np.arange(count, dtype=np.int64),
        "state_name": np.array(program.state_names, dtype=str),
        "output_name": np.array(program.output_names, dtype=str),
        "input_name": np.array(program.input_names, dtype=str),
    }
    attrs = {
        "spec": program.name,
        "description": "tvopt-codegen sweep trajectories: t, closed-loop state, outputs y, "
        "target y* (minimiser of f0), commanded input u, log|det R| and the least "
        "eigenvalue of f0's Hessian, at each output time; NaN after a failure",
        "options": options.as_dict(),
    }
    return variables, coords, attrs


def trajectory_block(
    program: SweepProgram, results: Sequence[SampleResult]
) -> dict[str, np.ndarray]:
    """The store's arrays for consecutive samples (their trajectories, NaN-padded)."""
    n, m, nu = len(program.state_names), len(program.output_names), len(program.input_names)
    points = max((len(r.trajectory) for r in results if r.trajectory is not None), default=0)
    width = program.columns
    block = np.full((len(results), points, width), np.nan)
    for i, result in enumerate(results):
        if result.trajectory is not None:
            block[i, : len(result.trajectory)] = result.trajectory
    return {
        "t": block[:, :, 0],
        "state": block[:, :, 1 : 1 + n],
        "output": block[:, :, 1 + n : 1 + n + m],
        "target": block[:, :, 1 + n + m : 1 + n + 2 * m],
        "input": block[:, :, 1 + n + 2 * m : 1 + n + 2 * m + nu],
        **{name: tail(block, name) for name in TAIL},
    }


def parquet_bytes(rows: Sequence[Mapping[str, Any]]) -> bytes:
    """The summary table as Parquet (one row per sample, in sample order)."""
    try:
        import pyarrow as pa  # noqa: PLC0415
        import pyarrow.parquet as pq  # noqa: PLC0415
    except ImportError:
        raise MissingExtraError(
            "sweep writes Parquet with pyarrow: pip install 'tvopt-codegen[sweep]'"
        ) from None
    table = pa.Table.from_pylist(list(rows))
    sink = pa.BufferOutputStream()
    pq.write_table(table, sink)
    return bytes(sink.getvalue().to_pybytes())


def read_summary(path: str) -> list[dict[str, Any]]:
    """The rows of a ``summary.parquet``."""
    try:
        import pyarrow.parquet as pq  # noqa: PLC0415
    except ImportError:
        raise MissingExtraError(
            "reading a sweep needs pyarrow: pip install 'tvopt-codegen[sweep]'"
        ) from None
    rows: list[dict[str, Any]] = pq.read_table(path).to_pylist()
    return rows


#: The record of a sweep beside its table: what ``--replay`` reads.
RECORD = "sweep.json"
