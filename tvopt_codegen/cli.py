"""Command-line interface: parse arguments, call the stages, map errors to exit codes.

Exit codes (``tvopt_codegen.errors``): 0 success; 2 bad spec or command line; 3 the
system violates the method's assumptions; 4 output could not be written; 5 the
simulation's certificate failed; 6 a derivation budget was exceeded; 7 a controller
could not be built; 70 internal error; 130 interrupted (Ctrl-C); 143 terminated (SIGTERM).
Every error is one line on stderr; set TVOPT_CODEGEN_DEBUG=1 for tracebacks of internal
errors.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import gc
import math
import os
import shutil
import signal
import sys
import textwrap
import threading
import time
import traceback
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, NoReturn

from tvopt_codegen import __version__
from tvopt_codegen.backends import BACKENDS
from tvopt_codegen.errors import (
    EXIT_BAD_SPEC,
    EXIT_BROKEN_PIPE,
    EXIT_BUDGET,
    EXIT_CERTIFICATE,
    EXIT_INTERNAL,
    EXIT_INTERRUPTED,
    EXIT_TERMINATED,
    BudgetError,
    SpecError,
    Terminated,
    TvoptError,
    one_line,
)
from tvopt_codegen.limits import MAX_POINTS, MAX_T_FINAL, METHODS, Budget

# The stages (sympy, numpy, scipy, jinja2; matplotlib for figures) are imported by the
# commands that use them: --help and --version answer without them.
if TYPE_CHECKING:
    from typing import TypeAlias

    from tvopt_codegen.derivation import Derivation
    from tvopt_codegen.drawing import Painter
    from tvopt_codegen.ir import KernelSet

    #: The subcommand table each ``_add_<command>`` adds its command to.
    _Commands: TypeAlias = argparse._SubParsersAction["_Parser"]


class _Parser(argparse.ArgumentParser):
    """argparse, with a usage error in one line (the seven-line usage is --help's)."""

    def error(self, message: str) -> NoReturn:
        sys.stderr.write(f"{self.prog}: error: {one_line(message)} (see {self.prog} --help)\n")
        raise SystemExit(EXIT_BAD_SPEC)


def _add_generate(commands: _Commands) -> argparse.ArgumentParser:
    """The ``generate`` command and its options."""
    generate = commands.add_parser("generate", help="derive the law and write the controller")
    generate.add_argument("spec", help="spec file, or the name of a bundled example")
    generate.add_argument("--out", default=".", help="output folder (default: current folder)")
    generate.add_argument(
        "--backend",
        default="python",
        choices=sorted(BACKENDS),
        help="target language (default: python)",
    )
    generate.add_argument(
        "--force",
        action="store_true",
        help="replace files that were edited by hand or not generated here",
    )
    generate.add_argument("--quiet", action="store_true", help="print nothing on success")
    generate.add_argument(
        "--timings",
        action="store_true",
        help="also print one JSON line of stage seconds and law operations on stderr "
        "(for benchmarks/bench_derive.py)",
    )
    return generate


def _add_check(commands: _Commands) -> argparse.ArgumentParser:
    """The ``check`` command and its options."""
    check = commands.add_parser("check", help="print the derivation summary; writes nothing")
    check.add_argument("spec", help="spec file, or the name of a bundled example")
    return check


def _add_import_urdf(commands: _Commands) -> None:
    """The ``import-urdf`` command and its options."""
    imp = commands.add_parser(
        "import-urdf", help="write a spec in mass-matrix form from a robot's URDF file"
    )
    imp.add_argument("urdf", help="the URDF file: a fixed-base serial chain")
    imp.add_argument("--out", required=True, help="the spec file to write (.toml)")
    imp.add_argument(
        "--tip",
        help="a link whose position (px, py, pz) the objective tracks; the outputs then "
        "replace the first three joints' by it",
    )
    imp.add_argument(
        "--gravity",
        default="0,0,-9.81",
        help="the gravity vector in the base frame, x,y,z (default: 0,0,-9.81)",
    )
    imp.add_argument("--name", help="the spec's name (default: the robot's)")
    imp.add_argument(
        "--initial",
        default="",
        help="initial joint positions, NAME=VALUE,... (default: the middle of each joint's "
        "limits); the targets move about this pose",
    )
    imp.add_argument(
        "--force",
        action="store_true",
        help="replace a spec file edited by hand or not written here",
    )
    imp.add_argument(
        "--max-seconds",
        type=float,
        default=Budget.seconds,
        help=f"time budget of the import (default {Budget.seconds:g})",
    )


def _import_urdf(args: argparse.Namespace) -> int:
    import tomllib  # noqa: PLC0415

    from tvopt_codegen.emit import write_files  # noqa: PLC0415
    from tvopt_codegen.mechanics import spec_toml  # noqa: PLC0415
    from tvopt_codegen.model import build_model  # noqa: PLC0415
    from tvopt_codegen.spec import spec_from_dict  # noqa: PLC0415
    from tvopt_codegen.urdf import spec_from_urdf  # noqa: PLC0415

    out = Path(args.out)
    if out.suffix != ".toml" or not out.stem:
        raise SpecError("command line", "--out", f"{args.out!r}: a spec file name ends in .toml")
    _check_out(str(out.parent))
    try:
        gravity = [float(v) for v in args.gravity.split(",")]
    except ValueError:
        gravity = []
    if len(gravity) != 3 or not all(math.isfinite(v) for v in gravity):
        raise SpecError("command line", "--gravity", f"{args.gravity!r}: expected x,y,z numbers")
    initial: dict[str, float] = {}
    for item in filter(None, (part.strip() for part in args.initial.split(","))):
        key, _, value = item.partition("=")
        try:
            initial[key.strip()] = float(value)
        except ValueError:
            raise SpecError("command line", "--initial", f"{item!r}: expected NAME=VALUE") from None
    if not args.max_seconds > 0:
        raise SpecError("command line", "--max-seconds", "must be positive")
    # The import runs the same clock as a derivation: a chain too long for it ends with
    # exit 6 naming the stage, never runs on (spec_from_urdf refuses the longest at once).
    progress = _DeriveProgress("never")
    notes: list[str] = []

    def stage(name: str) -> None:
        progress.stage = f"import-urdf: {name}"

    with _time_limit(args.max_seconds, [str(args.urdf)], progress):
        spec = spec_from_urdf(
            args.urdf,
            tip=args.tip,
            gravity=gravity,
            name=args.name,
            initial=initial,
            notes=notes,
            stage=stage,
        )
        stage("writing the spec text")
        text = spec_toml(spec)
        # What is written must read back and build: M symmetric, positive definite at the
        # start.
        stage("reading the spec back")
        build_model(spec_from_dict(tomllib.loads(text), source=str(out)))
    write_files({out.name: text}, out.parent, force=args.force)
    joints = len(spec["system"]["coordinates"])
    print(
        f"wrote {out} ({joints} joints, {len(spec['system']['mechanics']['definitions'])} "
        "definitions; edit its objective and initial state)"
    )
    for note in notes:
        print(one_line(f"note: {note}"))
    return 0


def _add_examples(commands: _Commands) -> None:
    """The ``examples`` command and its options."""
    commands.add_parser("examples", help="list the bundled example specs")


def _add_report(commands: _Commands) -> argparse.ArgumentParser:
    """The ``report`` command and its options."""
    rep = commands.add_parser("report", help="write the derivation report (HTML and Markdown)")
    rep.add_argument("spec", help="spec file, or the name of a bundled example")
    rep.add_argument(
        "--out",
        default=".",
        help="output folder (default: current folder); "
        "simulation results already there are included",
    )
    rep.add_argument(
        "--format",
        default="both",
        choices=("html", "md", "both"),
        help="report format (default: both)",
    )
    rep.add_argument(
        "--force",
        action="store_true",
        help="replace files that were edited by hand or not written here",
    )
    return rep


def _add_export(commands: _Commands) -> argparse.ArgumentParser:
    """The ``export`` command and its options."""
    export = commands.add_parser(
        "export", help="export the stateful controller for other tools (an FMU)"
    )
    export.add_argument("spec", help="spec file, or the name of a bundled example")
    export.add_argument(
        "--fmu",
        action="store_true",
        help="write <name>.fmu: a co-simulation FMU built from the generated C",
    )
    export.add_argument(
        "--fmi", type=int, default=2, choices=(2, 3), help="FMI version (default: 2)"
    )
    export.add_argument("--out", default=".", help="output folder (default: current folder)")
    export.add_argument(
        "--force",
        action="store_true",
        help="replace files that were edited by hand or not written here",
    )
    return export


def _add_simulate(commands: _Commands) -> argparse.ArgumentParser:
    """The ``simulate`` command and its options."""
    sim = commands.add_parser(
        "simulate", help="simulate the closed loop and check the theorem along the run"
    )
    sim.add_argument("spec", help="spec file, or the name of a bundled example")
    sim.add_argument(
        "--backend",
        default="python",
        choices=sorted(BACKENDS),
        help="controller backend to simulate (default: python)",
    )
    sim.add_argument("--t-final", type=float, help="horizon (default: the spec's t_final)")
    sim.add_argument(
        "--initial",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="initial value of a state (repeatable)",
    )
    sim.add_argument(
        "--param",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="parameter override (repeatable)",
    )
    sim.add_argument(
        "--plant-param",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="with --sample-time: the true plant's parameter, where it is not the model's "
        "(repeatable)",
    )
    sim.add_argument(
        "--method",
        default="RK45",
        choices=METHODS,
        help="solve_ivp method (default: RK45, Dormand-Prince, as in the paper)",
    )
    sim.add_argument("--rtol", type=float, default=1e-10, help="relative tolerance (1e-10)")
    sim.add_argument("--atol", type=float, default=1e-12, help="absolute tolerance (1e-12)")
    sim.add_argument("--points", type=int, default=401, help="output times (401)")
    sim.add_argument(
        "--tolerance",
        type=float,
        default=1e-6,
        help="largest accepted relative deviation of E from expm(Ht) E(0)",
    )
    sim.add_argument(
        "--reference-file",
        metavar="FILE.csv",
        help="for a spec with [references]: samples t, <reference>, ... estimated online "
        "into jets by the spec's differentiator (default: the nominal closed forms)",
    )
    sim.add_argument(
        "--noise",
        type=float,
        default=0.0,
        metavar="SIGMA",
        help="with --reference-file: Gaussian noise of this standard deviation on every sample",
    )
    sim.add_argument(
        "--allow-gaps",
        action="store_true",
        help="with --reference-file: accept samples the estimator cannot follow (a gap of "
        "more than 10 median intervals, or samples slower than 1/bandwidth)",
    )
    sim.add_argument("--seed", type=int, default=0, help="seed of the noise (default 0)")
    sim.add_argument(
        "--sample-time",
        type=float,
        metavar="H",
        help="also run the stateful controller sampled every H seconds (zero-order hold) "
        "against the continuous loop",
    )
    sim.add_argument(
        "--convergence-order",
        action="store_true",
        help="with --sample-time: also run at H/2 (and at H/4, H/8 while the order is below "
        "0.75, not yet asymptotic) and report the observed order in H",
    )
    sim.add_argument("--out", default=".", help="output folder (default: current folder)")
    sim.add_argument(
        "--force",
        action="store_true",
        help="replace files that were edited by hand or not written here",
    )
    return sim


def _add_sweep(commands: _Commands) -> argparse.ArgumentParser:
    """The ``sweep`` command and its options."""
    sw = commands.add_parser(
        "sweep",
        help="Monte-Carlo closed loops with model mismatch, saturation and noise, on Dask",
        description="Run SPEC's closed loop for many drawn initial states and parameters "
        "(DIST: a number, normal(mean, sd), uniform(lo, hi) or lognormal(mu, sigma)), in "
        "compiled C on a Dask cluster; write summary.parquet, summary.md and figures to "
        "--out. `sweep --replay DIR SAMPLE_ID --out DIR2` reruns one sample of the sweep "
        "in DIR and writes its whole trajectory; `sweep --resume DIR` runs the samples an "
        "interrupted sweep lacks.",
    )
    sw.add_argument("spec", nargs="?", help="spec file, or the name of a bundled example")
    sw.add_argument(
        "--replay",
        nargs=2,
        metavar=("DIR", "SAMPLE_ID"),
        help="rerun sample SAMPLE_ID of the sweep written to DIR (no SPEC)",
    )
    sw.add_argument(
        "--resume",
        metavar="DIR",
        help="complete the interrupted sweep in DIR: run only its missing samples (no SPEC)",
    )
    sw.add_argument("--samples", type=int, help="number of runs")
    sw.add_argument("--seed", type=int, default=0, help="root seed (default 0)")
    sw.add_argument("--out", help="output folder (not with --resume: DIR is the folder)")
    for option, what in (
        ("--initial", "spread of an initial closed-loop state"),
        ("--param", "the controller's (model's) parameter"),
        ("--plant-param", "the true plant's parameter (model mismatch)"),
    ):
        sw.add_argument(
            option, action="append", default=[], metavar="NAME=DIST", help=f"{what} (repeatable)"
        )
    sw.add_argument(
        "--saturation",
        action="append",
        default=[],
        metavar="INPUT=LIMIT",
        help=(
            "clip a plant input to |u| <= LIMIT, or to LO:HI "
            "(repeatable; default: the spec's [limits])"
        ),
    )
    sw.add_argument(
        "--noise",
        type=float,
        default=0.0,
        metavar="SIGMA",
        help="with --sample-time: Gaussian noise on every measured plant state",
    )
    sw.add_argument(
        "--sample-time",
        type=float,
        metavar="H",
        help="run the stateful controller every H seconds (zero-order hold)",
    )
    sw.add_argument("--t-final", type=float, help="horizon (default: the spec's t_final)")
    sw.add_argument("--rtol", type=float, default=1e-8, help="RK45 relative tolerance (1e-8)")
    sw.add_argument("--atol", type=float, default=1e-10, help="RK45 absolute tolerance (1e-10)")
    sw.add_argument("--points", type=int, default=201, help="output times per run (201)")
    where = sw.add_mutually_exclusive_group()
    where.add_argument(
        "--workers", type=int, help="workers of a new local Dask cluster (default: one per core)"
    )
    where.add_argument(
        "--scheduler", metavar="ADDRESS", help="an existing Dask scheduler, e.g. tcp://host:8786"
    )
    sw.add_argument(
        "--chunk-size", type=int, help="samples per Dask task (default: about 8 tasks a worker)"
    )
    sw.add_argument(
        "--trajectories",
        action="store_true",
        help="also store every run in trajectories.zarr (xarray-readable), as runs finish",
    )
    sw.add_argument(
        "--checkpoint-seconds",
        type=float,
        default=20.0,
        metavar="S",
        help="save the finished samples to DIR/parts at least every S seconds (20): a sweep "
        "killed outright (SIGKILL, a node lost) loses at most the last S seconds",
    )
    sw.add_argument(
        "--force", action="store_true", help="replace an earlier sweep's files in --out"
    )
    sw.add_argument(
        "--progress",
        choices=("auto", "always", "never"),
        default="auto",
        help="show progress on stderr (auto: on a terminal)",
    )
    for option, default in (("--max-seconds", Budget.seconds), ("--max-size", Budget.size)):
        sw.add_argument(option, type=type(default), default=default, help=argparse.SUPPRESS)
    sw.add_argument("--extension", choices=("spec", "auto"), default="spec", help=argparse.SUPPRESS)
    return sw


def _derivation_options(command: argparse.ArgumentParser) -> None:
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
    command.add_argument(
        "--max-seconds",
        type=float,
        default=Budget.seconds,
        help=f"time budget of the derivation (default {Budget.seconds:g})",
    )
    command.add_argument(
        "--max-size",
        type=int,
        default=Budget.size,
        help=f"largest expression tree a derivation stage may build (default {Budget.size})",
    )


def _parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="tvopt-codegen",
        description="Generate implicit trajectory planning controllers from a spec file.",
        epilog="Exit codes: 0 ok, 2 bad spec or usage, 3 assumptions violated, 4 output not "
        "written, 5 certificate failed, 6 budget exceeded, 7 build failed, 70 internal error, "
        "130 interrupted, 143 terminated.",
    )
    parser.add_argument("--version", action="version", version=f"tvopt-codegen {__version__}")
    commands = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    for add in (_add_generate, _add_check):
        _derivation_options(add(commands))
    _add_examples(commands)
    _add_import_urdf(commands)
    for add in (_add_report, _add_export, _add_simulate):
        _derivation_options(add(commands))
    _add_sweep(commands)
    return parser


def _derive(args: argparse.Namespace) -> tuple[Derivation, KernelSet]:
    """Load, derive and lower the spec named on the command line, within its budget."""
    # From the command's start: --timings counts the imports the stages need in "load".
    clock = [getattr(args, "started", time.perf_counter())]
    from tvopt_codegen.derivation import derive  # noqa: PLC0415
    from tvopt_codegen.ir import lower  # noqa: PLC0415
    from tvopt_codegen.spec import load_spec  # noqa: PLC0415

    if not args.max_seconds > 0:
        raise SpecError("command line", "--max-seconds", "must be positive")
    if not args.max_size > 0:
        raise SpecError("command line", "--max-size", "must be positive")
    progress = _DeriveProgress(args.progress)
    source = [str(args.spec)]
    stages: dict[str, float] = {}

    def lap(stage: str) -> None:
        now = time.perf_counter()
        stages[stage] = now - clock[0]
        clock[0] = now

    try:
        with _without_collector(), _time_limit(args.max_seconds, source, progress):
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
        print(one_line(f"tvopt-codegen: warning: {spec.source}: {warning}"), file=sys.stderr)
    return derivation, kernels


@contextlib.contextmanager
def _without_collector() -> Iterator[None]:
    """Run without Python's cyclic garbage collector, and turn it back on after.

    The derivation's and the printers' walks leave no reference cycles (jet.release):
    what they drop, reference counting frees at once. The collector would only scan the
    live expressions, again and again: a tenth of a large team's run, for no garbage
    (the peak memory is the same with it or without).

    On the way out the objects made so far are frozen (``gc.freeze``): they are the
    imported modules and the derivation, alive until the command ends, and the first
    collection after this block would otherwise scan every one of them (0.4 s at 128
    agents). :func:`main` unfreezes them when the command returns.
    """
    collecting = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        gc.freeze()
        if collecting:
            gc.enable()


class _Overrun(BaseException):
    """The time budget ran out.

    A BaseException, so that no ``except Exception`` in a library the derivation calls
    can swallow it.
    """


@contextlib.contextmanager
def _time_limit(seconds: float, source: list[str], progress: _DeriveProgress) -> Iterator[None]:
    """Stop loading, deriving and lowering after ``seconds``, wherever they are.

    The derivation checks its budget as it builds expressions, but a single sympy
    call (a simplification, an exact power) can run far past it between two checks:
    a timer signal interrupts it within the budget. Only in the main thread, where
    Python delivers signals.
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
            raise _Overrun

    previous = signal.signal(signal.SIGALRM, expire)
    try:
        # Armed inside the try: the timer can fire before setitimer returns.
        signal.setitimer(signal.ITIMER_REAL, seconds)
        yield
    except _Overrun:
        raise BudgetError(
            source[0], progress.stage, f"the derivation took longer than {seconds:g} s"
        ) from None
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)


class _DeriveProgress:
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
        if self.shown and self.terminal:
            print(" " * 80, end="\r", file=sys.stderr, flush=True)


def _assignments(items: Sequence[str], option: str) -> dict[str, float]:
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


class _Progress:
    """Simulated time on stderr: one updating line on a terminal, else one line each."""

    def __init__(self) -> None:
        self.shown = False

    def __call__(self, t: float, t_final: float) -> None:
        end = "\r" if sys.stderr.isatty() else "\n"
        print(f"  simulated t = {t:.3f} of {t_final:g}", end=end, file=sys.stderr, flush=True)
        self.shown = True

    def close(self) -> None:
        if self.shown and sys.stderr.isatty():
            print(" " * 40, end="\r", file=sys.stderr, flush=True)


def _report(args: argparse.Namespace) -> int:
    from tvopt_codegen.emit import write_files  # noqa: PLC0415
    from tvopt_codegen.report import read_results, render_report  # noqa: PLC0415

    _check_out(args.out)
    derivation, kernels = _derive(args)
    results = read_results(args.out, derivation.spec.name)
    formats = ("html", "md") if args.format == "both" else (args.format,)
    files = render_report(derivation, kernels, results, formats)
    write_files(files, args.out, force=args.force)
    for name in files:
        print(f"wrote {args.out.rstrip('/')}/{name}")
    if results:
        print(f"  with the simulation results found in {args.out}")
    return 0


def _export(args: argparse.Namespace) -> int:
    from tvopt_codegen.emit import write_files  # noqa: PLC0415
    from tvopt_codegen.fmu import build_fmu  # noqa: PLC0415

    if not args.fmu:
        raise SpecError("command line", "export", "nothing to export: give --fmu")
    _check_out(args.out)
    derivation, kernels = _derive(args)
    name = f"{derivation.spec.name}.fmu"
    write_files({name: build_fmu(kernels, args.fmi)}, args.out, force=args.force)
    print(f"wrote {args.out.rstrip('/')}/{name} (FMI {args.fmi}.0 co-simulation)")
    return 0


def _simulate(args: argparse.Namespace) -> int:
    # First: the drawing process imports matplotlib while this one loads sympy and derives.
    from tvopt_codegen.drawing import Painter  # noqa: PLC0415

    with Painter() as painter:
        return _simulate_with(args, painter)


def _simulate_with(args: argparse.Namespace, painter: Painter) -> int:
    from tvopt_codegen.artifacts import result_files  # noqa: PLC0415 - matplotlib on use
    from tvopt_codegen.emit import write_files  # noqa: PLC0415
    from tvopt_codegen.simulation import (  # noqa: PLC0415
        format_certificate,
        load_controller,
        resolve_options,
        simulate,
    )

    for option, value in (
        ("--rtol", args.rtol),
        ("--atol", args.atol),
        ("--tolerance", args.tolerance),
    ):
        if not 0 < value < math.inf:
            raise SpecError("command line", option, "must be positive and finite")
    if not 3 <= args.points <= MAX_POINTS:
        raise SpecError("command line", "--points", f"must be between 3 and {MAX_POINTS}")
    if args.t_final is not None and not 0 < args.t_final <= MAX_T_FINAL:
        raise SpecError(
            "command line", "--t-final", f"must be positive and at most {MAX_T_FINAL:g}"
        )
    if not 0 <= args.noise < math.inf:
        raise SpecError("command line", "--noise", "must be zero or positive and finite")
    if args.noise and args.reference_file is None:
        raise SpecError("command line", "--noise", "needs --reference-file")
    if args.allow_gaps and args.reference_file is None:
        raise SpecError("command line", "--allow-gaps", "needs --reference-file")
    if not 0 <= args.seed < 2**63:
        raise SpecError("command line", "--seed", "must be between 0 and 2**63 - 1")
    if args.convergence_order and args.sample_time is None:
        raise SpecError("command line", "--convergence-order", "needs --sample-time")
    if args.sample_time is not None and not 0 < args.sample_time < math.inf:
        raise SpecError("command line", "--sample-time", "must be positive and finite")
    if args.plant_param and args.sample_time is None:
        raise SpecError(
            "command line",
            "--plant-param",
            "needs --sample-time (the continuous run is the nominal theorem's; the sampled "
            "controller runs on the mismatched plant)",
        )
    _check_out(args.out)
    derivation, kernels = _derive(args)
    plant_params = _assignments(args.plant_param, "--plant-param")
    unknown = sorted(set(plant_params) - {name for name, _ in derivation.spec.parameters})
    if unknown:
        raise SpecError("command line", "--plant-param", f"{unknown[0]!r} is not a parameter")
    options = resolve_options(
        derivation,
        args.t_final,
        _assignments(args.initial, "--initial"),
        _assignments(args.param, "--param"),
        method=args.method,
        rtol=args.rtol,
        atol=args.atol,
        points=args.points,
        tolerance=args.tolerance,
    )
    if args.sample_time is not None:
        from tvopt_codegen.simulation.sampled import check_sample_time  # noqa: PLC0415

        check_sample_time(
            args.sample_time / 2 if args.convergence_order else args.sample_time,
            options.t_final,
        )
    if args.reference_file is not None and not derivation.model.references:
        raise SpecError("command line", "--reference-file", "the spec has no [references]")
    if args.reference_file is not None and args.sample_time is not None:
        raise SpecError(
            "command line", "--reference-file", "not with --sample-time (one at a time, for now)"
        )
    samples = None
    if args.reference_file is not None:
        from tvopt_codegen.simulation.references import read_reference_file  # noqa: PLC0415

        samples = read_reference_file(
            args.reference_file,
            derivation,
            options.t_final,
            allow_gaps=args.allow_gaps,
            warn=lambda text: print(one_line(f"tvopt-codegen: warning: {text}"), file=sys.stderr),
        )
    controller = load_controller(kernels, args.backend)
    references = None
    if samples is not None:
        from tvopt_codegen.simulation.references import sampled_source  # noqa: PLC0415

        references = sampled_source(
            derivation, controller, dict(options.params), *samples, args.noise, args.seed
        )
    progress = _Progress()
    try:
        if args.sample_time is None:
            result = simulate(
                derivation, controller, options, progress=progress, references=references
            )
            sampled = None
        else:
            from tvopt_codegen.simulation.sampled import simulate_sampled  # noqa: PLC0415

            sampled = simulate_sampled(
                derivation,
                controller,
                options,
                args.sample_time,
                convergence_order=args.convergence_order,
                progress=progress,
                plant_params=dict(options.params) | plant_params,
            )
            result = sampled.continuous
    finally:
        progress.close()
    files = result_files(derivation, result, painter)
    text = format_certificate(derivation, result)
    passed = result.passed
    if sampled is not None:
        from tvopt_codegen.artifacts import sampled_files  # noqa: PLC0415
        from tvopt_codegen.simulation.sampled import format_sampled  # noqa: PLC0415

        files.update(sampled_files(derivation, sampled))
        text += "\n" + format_sampled(derivation, sampled)
        files[f"{derivation.spec.name}_certificate.txt"] = (text + "\n").encode("utf-8")
        passed = sampled.passed
    write_files(files, args.out, force=args.force)
    print(text)
    for name in files:
        print(f"  wrote {args.out.rstrip('/')}/{name}")
    return 0 if passed else EXIT_CERTIFICATE


def _print_examples(examples: Mapping[str, str]) -> None:
    """Each example's name and summary: one column of names, summaries beside it.

    On a terminal the summaries wrap to its width under their column; into a pipe each
    example stays one line, for ``grep``.
    """
    column = max(map(len, examples), default=0) + 2
    width = max(shutil.get_terminal_size().columns, column + 30)
    for name, summary in examples.items():
        if sys.stdout.isatty():
            lines = textwrap.wrap(summary, width - column) or [""]
        else:
            lines = [summary]
        print(f"{name:<{column}}{lines[0]}")
        for line in lines[1:]:
            print(" " * column + line)


def _check_out(out: str) -> None:
    """Refuse an unusable output folder before deriving, not after (creating nothing)."""
    from tvopt_codegen.emit import prepare_folder  # noqa: PLC0415

    prepare_folder(out, create=False)


def run(argv: Sequence[str] | None = None) -> int:
    """Run the CLI and return the exit code (errors are reported on stderr)."""
    args = _parser().parse_args(argv)
    args.started = time.perf_counter()
    if args.command == "examples":
        from tvopt_codegen.spec import bundled_examples  # noqa: PLC0415

        _print_examples(bundled_examples())
        return 0
    if args.command == "import-urdf":
        return _import_urdf(args)
    if args.command == "simulate":
        return _simulate(args)
    if args.command == "sweep":
        from tvopt_codegen.sweep.command import replay, resume, sweep  # noqa: PLC0415

        if args.replay and args.resume is not None:
            raise SpecError("command line", "--resume", "cannot be combined with --replay")
        if args.resume is not None:
            if not args.resume.strip():
                raise SpecError("command line", "--resume", "DIR is empty")
            if args.out is not None:
                raise SpecError("command line", "--out", "is DIR itself with --resume")
            return resume(args)
        if args.out is None:
            raise SpecError("command line", "--out", "is required")
        return replay(args) if args.replay else sweep(args, _derive)
    if args.command == "report":
        return _report(args)
    if args.command == "export":
        return _export(args)
    with _without_collector():  # sympy's and numpy's imports build objects by the million
        from tvopt_codegen.summary import format_summary  # noqa: PLC0415

    if args.command == "generate":
        _check_out(args.out)
    derivation, kernels = _derive(args)
    if args.command == "check":
        print(format_summary(derivation, kernels))
        from tvopt_codegen.features import target_notes  # noqa: PLC0415

        for note in target_notes(derivation):  # targets that refuse this spec (docs/features.md)
            print(one_line(note))
        return 0
    started = time.perf_counter()
    from tvopt_codegen.emit import write_files  # noqa: PLC0415
    from tvopt_codegen.rendering import render  # noqa: PLC0415

    with _without_collector():
        files = render(kernels, args.backend)
    rendered = time.perf_counter()
    written = write_files(files, args.out, force=args.force)
    if args.timings:
        import json  # noqa: PLC0415

        law = ("jet_time", "jet", "cholesky", "decoupling", "closed_loop")
        names = {k.name for k in kernels.kernels}
        record = dict(args.stage_seconds)
        record |= {"render": rendered - started, "write": time.perf_counter() - rendered}
        record["ops"] = sum(kernels[n].ops for n in law if n in names) + kernels.lu_ops
        print(f"timings: {json.dumps(record)}", file=sys.stderr)
    if not args.quiet:
        print(format_summary(derivation, kernels))
        for name in files:
            path = f"{args.out.rstrip('/')}/{name}"
            state = "written" if any(p.name == name for p in written) else "unchanged"
            print(f"  {state}: {path}")
    return 0


def _on_sigterm(_signum: int, _frame: object) -> None:
    raise Terminated


#: The cyclic garbage collector's thresholds while a command runs (Python's: 700, 10, 10).
#: A derivation allocates millions of sympy objects that live to its end; with Python's
#: thresholds the collector scans them nine thousand times for a ring of 128 agents, a
#: fifth of the run (6.0 s of 31), for next to no garbage. At these, 613 collections
#: take 2.8 s and the peak memory is the same (272 MB).
GC_THRESHOLDS = (10000, 10, 10)


def main(argv: Sequence[str] | None = None) -> int:
    """Console-script entry point: run, and map every outcome to one line and an exit code."""
    previous = signal.signal(signal.SIGTERM, _on_sigterm)
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
        gc.set_threshold(*collector)
        # What _without_collector froze becomes collectable again for a caller that goes on.
        gc.unfreeze()


if __name__ == "__main__":
    sys.exit(main())
