"""The compiled loop: the sweep's C program beside the controller, and the draws.

Its loader, and the draws of one sample (one ``SeedSequence`` child per sample).
"""

from __future__ import annotations

import ctypes
import dataclasses
import functools
import hashlib
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from tvopt_codegen.errors import SpecError
from tvopt_codegen.limits import MAX_POINTS, RUN_OPTIONS, START_ITERATIONS
from tvopt_codegen.maths import dopri

if TYPE_CHECKING:
    from tvopt_codegen.lowering.ir import KernelSet
from tvopt_codegen.sweep.options import (
    DIVERGENCE_FACTOR,
    MAX_SAMPLES,
    LoopOutcome,
    Outcome,
    SweepOptions,
    outcome_of,
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
        File name and text: ``<name>.h``, ``<name>.c`` (with ``--precision single``
        then ``<name>_f32.h`` and ``<name>_f32.c``) and ``<name>_sweep.c``.
    state_names, plant_state_names, input_names, output_names, param_names : tuple of str
        The closed loop's names, in the C arrays' order.
    defaults : tuple of float
        The parameters' spec values.
    initial_state : tuple of float
        The spec's closed-loop initial state.
    coefficients : tuple of float
        The Hurwitz coefficients of H.
    alpha : float
        The certificate's rate: ``|expm(H t)| <= c e^(-alpha t)``.
    c : float or None
        The certificate's constant; None for a candidate's gains (:meth:`with_gains`)
        until a nominal sample's certificate asks it (:meth:`transient`).
    constraints : tuple of str
        The names of the spec's inequalities (their values are measured on the run).
    equalities : tuple of str
        The names of its equality constraints (``|a|`` is measured on the run, and y* is
        the KKT point).
    n_kkt : int
        Entries of a row of the optimality error: the outputs, then the multipliers.
    limits : tuple of (str, float, float)
        The spec's ``[limits]`` ranges: the plant's limits unless ``--saturation`` says
        otherwise.
    observer : bool
        Whether the controller has a disturbance observer (it runs in the sampled loop).
    integral_rows : tuple of int
        Where the integral states are in the closed-loop state (integral action).
    bumpless : tuple of float
        ``b_j`` of the integrals' bumpless start ``z*(E) = sum_j b_j E_j``.
    observer_bandwidth : float or None
        The disturbance observer's bandwidth, rad/s (None without an observer).

    The gains (``coefficients``, ``bumpless``, ``observer_bandwidth``) are run-time values
    of the compiled loop (:meth:`gains`): :meth:`with_gains` gives another candidate's
    program on the same library (same ``key``).
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
    c: float | None
    constraints: tuple[str, ...] = ()
    equalities: tuple[str, ...] = ()
    n_kkt: int = 0
    limits: tuple[tuple[str, float, float], ...] = ()
    observer: bool = False
    integral_rows: tuple[int, ...] = ()
    bumpless: tuple[float, ...] = ()
    observer_bandwidth: float | None = None

    @property
    def k(self) -> int:
        """The order of the error dynamics: the rows of E (integral action adds a coefficient)."""
        return len(self.coefficients) - (1 if self.integral_rows else 0)

    @property
    def columns(self) -> int:
        """Width of a trajectory row: t, s, y, y*, u, then the :data:`TAIL` columns."""
        n, m, nu = len(self.state_names), len(self.output_names), len(self.input_names)
        return 1 + n + 2 * m + nu + len(TAIL)

    def transient(self) -> float:
        """The certificate's constant c: the spec's, or computed now for a candidate's gains.

        Only a nominal sample's certificate reads it, and a tune's samples are seldom
        nominal (mismatch, noise, a sample time): computed for every candidate, it was
        about half of a small tune's CPU (:func:`transient_constant`, 50-90 ms each).
        """
        if self.c is not None:
            return self.c
        return transient_constant(self.coefficients, self.alpha)

    def gains(self) -> np.ndarray:
        """The gains the compiled loop runs with, in the C's order (``<name>_set_gains``).

        The Hurwitz coefficients ``a_0 ..`` (k, or k + 1 with integral action), then with
        integral action the bumpless ``b_0 .. b_(k-1)``, then with a disturbance observer
        its bandwidth.
        """
        observer = () if self.observer_bandwidth is None else (self.observer_bandwidth,)
        return np.array((*self.coefficients, *self.bumpless, *observer), dtype=float)

    def with_gains(
        self,
        coefficients: Sequence[float],
        bandwidth: float | None,
        poles: Sequence[complex] | None = None,
    ) -> SweepProgram:
        """The same program with other gains: its sources and ``key`` (the same library).

        Parameters
        ----------
        coefficients : sequence of float
            H's coefficients ``a_0 ..``
            (:func:`~tvopt_codegen.maths.hurwitz.coefficients_from_poles`), as many as
            the spec's (k + 1 with integral action).
        bandwidth : float or None
            The disturbance observer's bandwidth, rad/s; None exactly when the spec has
            no observer.
        poles : sequence of complex, optional
            The poles ``coefficients`` came from: then the integral's pole is split off
            them exactly, as the derivation does for a spec's poles (rows identical to
            that spec's); default: from the coefficients' computed eigenvalues.

        Returns
        -------
        SweepProgram
            With ``coefficients`` and ``alpha``
            (:func:`~tvopt_codegen.maths.hurwitz.certified_rate`), ``c`` None (computed
            when asked: :meth:`transient`), ``bumpless``
            (:func:`~tvopt_codegen.maths.hurwitz.integral_split`) and
            ``observer_bandwidth`` replaced.

        Raises
        ------
        SpecError
            When the count is not the spec's, H is not Hurwitz, integral action finds no
            real pole, or the bandwidth is missing, extra or not a positive number.
        """
        from tvopt_codegen.maths import hurwitz  # noqa: PLC0415

        values = tuple(float(a) for a in coefficients)
        if len(values) != len(self.coefficients):
            extra = " (k + 1: integral action adds one)" if self.integral_rows else ""
            raise SpecError(
                "command line",
                "gains",
                f"give {len(self.coefficients)} coefficients{extra}, not {len(values)}",
            )
        if not all(math.isfinite(a) for a in values):
            raise SpecError("command line", "gains", "the coefficients must be finite")
        if poles is not None:
            poles = tuple(complex(p) for p in poles)
            if hurwitz.coefficients_from_poles(poles) != values:
                raise SpecError(
                    "command line", "gains", "the poles are not those of the coefficients"
                )
        rate = hurwitz.decay_rate(values) if poles is None else -max(p.real for p in poles)
        if not rate > 0:
            raise SpecError(
                "command line",
                "gains",
                f"H is not Hurwitz: its slowest eigenvalue has real part {-rate:.6g} >= 0",
            )
        bumpless: tuple[float, ...] = ()
        if self.integral_rows:
            split = hurwitz.integral_split(values, poles)
            if split is None:
                raise SpecError(
                    "command line",
                    "gains",
                    "integral action takes a real pole (its own) and every eigenvalue of H "
                    "is complex",
                )
            bumpless = split[2]
        if (bandwidth is None) != (self.observer_bandwidth is None):
            raise SpecError(
                "command line",
                "gains",
                "the observer's bandwidth is needed"
                if bandwidth is None
                else "the spec has no disturbance observer ([robust.observer]): no bandwidth",
            )
        if bandwidth is not None and not (math.isfinite(bandwidth) and bandwidth > 0):
            raise SpecError(
                "command line", "gains", f"the observer's bandwidth must be > 0, not {bandwidth!r}"
            )
        alpha, _ = hurwitz.certified_rate(values)
        return dataclasses.replace(
            self,
            coefficients=values,
            alpha=alpha,
            c=None,
            bumpless=bumpless,
            observer_bandwidth=None if bandwidth is None else float(bandwidth),
        )


@functools.lru_cache(maxsize=1024)
def transient_constant(coefficients: tuple[float, ...], alpha: float) -> float:
    """:func:`~tvopt_codegen.maths.hurwitz.transient_constant`, once per gains in a process.

    It takes 50-90 ms for a candidate of a 4-pole spec (up to 20,000 grid points), and
    is asked only by a nominal sample's certificate (:meth:`SweepProgram.transient`): a
    candidate met again (its fresh check, a notebook or a test process that tunes the
    same candidates with the same seed) gets the value already computed, the same float.
    """
    from tvopt_codegen.maths import hurwitz  # noqa: PLC0415

    return hurwitz.transient_constant(coefficients, alpha)


#: A trajectory row's last columns, after t, s, y, y* and u: log|det R|, the certificate's
#: m_f (with equalities, the KKT matrix's sigma_min), the barrier's margin
#: min_i (s - g_i), max_i g_i, and max_j |a_j| (NaN where the spec has none of them), and
#: 1 where an input was clipped (by the controller's [limits] or the plant's --saturation).
TAIL = ("log_det_R", "m_f", "margin", "max_constraint", "max_equality", "saturated")


def tail(rows: np.ndarray, name: str) -> np.ndarray:
    """The :data:`TAIL` column ``name`` of trajectory rows (any leading dimensions)."""
    column: np.ndarray = rows[..., TAIL.index(name) - len(TAIL)]
    return column


def sweep_program(kernels: KernelSet, precision: str = "double") -> SweepProgram:
    """Render the C closed loop of a lowered controller.

    ``precision`` ``"single"`` steps the single-precision controller (every real a
    float, ``generate --precision single``'s C, included under the prefix
    ``<name>_f32``) against the true plant, the integrator and the certificate in
    double; it needs a sampled loop (the sweep's command checks ``--sample-time``).

    Raises
    ------
    SpecError
        For a spec with ``[references]`` (the compiled loop has no reference source yet).
    """
    from tvopt_codegen.backends import BACKENDS  # noqa: PLC0415
    from tvopt_codegen.lowering.ir import check_kernels  # noqa: PLC0415
    from tvopt_codegen.renderer.rendering import (  # noqa: PLC0415
        print_kernel,
        render_template,
        template_context,
    )
    from tvopt_codegen.renderer.runtime import NEWTON, closure, controller_routines  # noqa: PLC0415

    d = kernels.derivation
    if d.model.references:
        raise SpecError(
            d.spec.source,
            "references",
            "the compiled loop of sweep and tune does not run specs with [references] yet: "
            "sweep or tune the spec without them "
            "(the nominal closed forms as signals)",
        )
    backend = BACKENDS["c"]
    name = d.spec.name
    context = template_context(kernels, backend)
    files = _tunable(context, backend, name)
    single = f"{name}_f32" if precision == "single" else None
    extra: tuple[tuple[str, str], ...] = ()
    if single is not None:
        from tvopt_codegen.backends.c import with_precision  # noqa: PLC0415

        floating = with_precision(precision, prefix=single)
        floats = _tunable(template_context(kernels, floating), floating, name)
        extra = ((f"{single}.h", floats[f"{name}.h"]), (f"{single}.c", floats[f"{name}.c"]))
    checks = check_kernels(d)
    constraints, equalities = checks.constraints, checks.equalities
    context |= {
        "equalities": None if equalities is None else print_kernel(equalities, backend.printer()),
        "equality_count": len(d.model.equalities),
        "multiplier_rows": [
            d.closed_loop.state_names.index(chain[0]) for chain in d.closed_loop.multiplier_states
        ],
        "tail": TAIL,
        "decoupling": print_kernel(checks.decoupling, backend.printer()),
        "constraints": None
        if constraints is None
        else print_kernel(constraints, backend.printer()),
        "constraint_count": len(d.model.constraints),
        "rk": {name: getattr(dopri, name).tolist() for name in "ABCEP"},
        "sweep_statuses": list(LoopOutcome),
        # The run-time library's routines this loop calls, beyond the controller's own.
        "runtime_routines": closure(
            (
                "rk45",
                "lu_det",
                "dot",
                "kkt_path" if equalities else "minimizer_path",
            ),
            # The controller's C file, which the loop includes, has its plan's routines.
            emitted=(*kernels.plan.runtime, *controller_routines(bool(d.spec.references))),
        ),
        "newton_rule": NEWTON,
        "max_points": MAX_POINTS,
        "start_iterations": START_ITERATIONS,
        # The single-precision controller's prefix, or None: the loop steps the double one.
        "single": single,
    }
    sources = (
        (f"{name}.h", files[f"{name}.h"]),
        (f"{name}.c", files[f"{name}.c"]),
        *extra,
        (f"{name}_sweep.c", render_template("c/sweep.c.jinja", context)),
    )
    digest = hashlib.sha256()
    for file_name, text in sources:
        digest.update(hashlib.sha256(f"{file_name}\0{text}".encode()).digest())
    return SweepProgram(
        name=name,
        key=digest.hexdigest(),
        sources=sources,
        state_names=tuple(d.closed_loop.state_names),
        plant_state_names=tuple(d.spec.states),
        input_names=tuple(d.spec.inputs),
        output_names=tuple(d.spec.outputs),
        param_names=tuple(n for n, _ in d.spec.parameters),
        defaults=tuple(float(v) for _, v in d.spec.parameters),
        initial_state=tuple(float(v) for v in d.closed_loop.initial_state),
        coefficients=tuple(float(a) for a in d.dynamics.coefficients),
        alpha=float(d.dynamics.certified_rate),
        c=float(d.dynamics.transient_constant),
        constraints=tuple(c.name for c in d.model.constraints),
        equalities=tuple(c.name for c in d.model.equalities),
        n_kkt=d.jet.n_kkt,
        limits=tuple(
            (limit.input, limit.low, limit.high)
            for limit in d.spec.limits
            if math.isfinite(limit.low) or math.isfinite(limit.high)
        ),
        observer=d.robustness.observer is not None,
        integral_rows=tuple(
            d.closed_loop.state_names.index(name) for name in d.closed_loop.integral_states
        ),
        bumpless=tuple(float(b) for b in d.dynamics.bumpless),
        observer_bandwidth=None if d.robustness.observer is None else float(d.robustness.observer),
    )


def _tunable(context: dict[str, Any], backend: Any, name: str) -> dict[str, str]:
    """The controller's header and C as the sweep includes them: its gains run-time values.

    The templates' ``tunable`` switch: the Hurwitz coefficients, the bumpless ``b_j`` and
    the observer's bandwidth are per-thread storage that ``<name>_set_gains`` sets (the
    user's ``generate`` output, without the switch, keeps them constants).
    """
    from tvopt_codegen.renderer.rendering import render_template  # noqa: PLC0415

    context = context | {"tunable": True}
    wanted = (f"{name}.h", f"{name}.c")
    return {
        pattern.format(name=name): render_template(template, context, backend.template_root)
        for template, pattern in backend.templates
        if pattern.format(name=name) in wanted
    }


def check_options(program: SweepProgram, options: SweepOptions) -> None:
    """Refuse what the loop cannot run, naming the option (all before anything runs)."""
    if not 1 <= options.samples <= MAX_SAMPLES:
        raise SpecError("command line", "--samples", f"must be between 1 and {MAX_SAMPLES}")
    # The bounds the command line checks (one table: tvopt_codegen.limits.RUN_OPTIONS),
    # here too for options that come from a sweep's record or the library.
    for name in ("seed", "t_final", "points", "rtol", "atol", "sample_time"):
        value = getattr(options, name)
        problem = None if value is None else RUN_OPTIONS[name].problem(value)
        if problem is not None:
            raise SpecError("command line", RUN_OPTIONS[name].flag, problem)
    if not 0.0 <= options.window <= options.t_final:
        raise SpecError(
            "command line",
            "--after",
            f"must be between 0 and the horizon {options.t_final!r}, not {options.window!r}",
        )
    noise = RUN_OPTIONS["measurement_noise"]
    if noise.problem(options.noise) is not None:
        raise SpecError("command line", noise.flag, noise.bounds)
    if options.sample_time is not None:
        if options.t_final / options.sample_time > 10_000_000:
            raise SpecError(
                "command line", "--sample-time", "more than 10^7 samples of the controller per run"
            )
    elif options.noise:
        raise SpecError(
            "command line",
            noise.flag,
            "needs --sample-time (the noise is drawn once per measurement)",
        )
    elif program.observer:
        raise SpecError(
            "command line",
            "--sample-time",
            "is required: the spec's disturbance observer ([robust.observer]) runs in the "
            "sampled controller",
        )


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


#: The first line of a generated C file's stamp, and its last (``templates/c/_macros.jinja``;
#: the ``comment`` filter keeps ``*/`` out of the lines between).
_STAMP, _STAMP_END = "/* Generated by tvopt-codegen ", "\n */\n"


def compiled_sources(program: SweepProgram) -> dict[str, str]:
    """``program``'s sources as they are compiled: each file without its stamp.

    The stamp is a comment naming the spec's file and hashing its text and the file's: a
    spec copied under another name, or with another ``[tune]`` table or comment, compiles
    to the same library, which the cache (keyed on what is compiled) already holds. The
    program's ``key`` (the sweep's identity) still hashes the sources whole.
    """
    compiled = {}
    for name, text in program.sources:
        end = text.find(_STAMP_END) if text.startswith(_STAMP) else -1
        compiled[name] = text[end + len(_STAMP_END) :] if end >= 0 else text
    return compiled


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
        path = cached_library(compiled_sources(program), f"{program.name}_sweep.c")
        library = ctypes.CDLL(str(path))
        pointer = ctypes.POINTER(ctypes.c_double)
        self._run = getattr(library, f"{program.name}_sweep_run")
        self._run.restype = ctypes.c_int
        self._run.argtypes = [pointer] * 9
        self._error = getattr(library, f"{program.name}_optimality_error")
        self._error.restype = ctypes.c_int
        self._error.argtypes = [ctypes.c_double, pointer, pointer, pointer]

    @staticmethod
    def _ptr(array: np.ndarray | None) -> Any:
        if array is None:
            return None
        return array.ctypes.data_as(ctypes.POINTER(ctypes.c_double))

    def run(
        self, options: SweepOptions, sample: Draw, program: SweepProgram | None = None
    ) -> tuple[Outcome, np.ndarray, np.ndarray]:
        """Integrate one sample: its outcome, the rows written and the run's counters.

        ``program`` is the candidate whose gains the run takes (:meth:`SweepProgram.gains`;
        it must share this loop's ``key``); default: the loop's own.
        """
        p = self.program if program is None else program
        if p.key != self.program.key:
            raise ValueError(f"program {p.name!r} is not this loop's (another compiled key)")
        gains = np.ascontiguousarray(p.gains())
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
            self._ptr(gains),
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
        out = np.empty(self.program.k * width)
        self._error(0.0, self._ptr(np.ascontiguousarray(s)), self._ptr(params), self._ptr(out))
        return out


_LOOPS: dict[str, Loop] = {}


def loop_for(program: SweepProgram) -> Loop:
    """The loaded loop of ``program`` (built or loaded from the cache once)."""
    if program.key not in _LOOPS:
        _LOOPS[program.key] = Loop(program)
    return _LOOPS[program.key]
