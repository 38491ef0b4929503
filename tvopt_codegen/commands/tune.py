"""``tvopt-codegen tune``: the poles and observer gains searched against sweeps (through emit).

Every check that can fail on the user's input (options, requirements, the search's
bounds, the output folder, the compiler, the nominal start) runs before the first file
is written. The search's record (``tune.json``) is rewritten after every generation; a
tune stopped by Ctrl-C or SIGTERM writes the best candidate so far and its record, and
``tune --resume DIR`` continues it to the same end as an uninterrupted run.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

from tvopt_codegen.commands import common, plant, run_options
from tvopt_codegen.errors import (
    EXIT_INTERRUPTED,
    EXIT_TERMINATED,
    OutputError,
    SpecError,
    Terminated,
)

if TYPE_CHECKING:
    from tvopt_codegen.sweep import SweepOptions, SweepProgram
    from tvopt_codegen.tune.requirements import Requirements
    from tvopt_codegen.tune.settings import Settings
    from tvopt_codegen.tune.space import Candidate, Space

HELP = "choose the poles and observer gains against sweeps of the mismatched plant"

#: The searches ``--method`` names, as ``tune.md`` names them.
METHODS = {"cma": "CMA-ES", "tpe": "optuna's TPE", "random": "uniform random points"}

#: In a log, seconds between progress lines.
LOG_EVERY = 60.0

#: The search's record in its folder.
RECORD = "tune.json"
#: What a tune writes beside its record (the tuned spec's name is ``<name>_tuned.toml``).
FILES = ("tune.md", "evaluations.csv", "tune_tradeoff.png", "tune_tradeoff.svg")
#: The most candidates, and samples per candidate, a tune takes.
MAX_EVALUATIONS = 100_000
#: Largest record read back by ``--resume`` (a long tune's history), and spec copy.
_MAX_RECORD = 1 << 26
_MAX_SPEC = 1 << 22


def build(parser: argparse.ArgumentParser) -> None:
    """The ``tune`` command's options."""
    parser.description = (
        "Search SPEC's error-dynamics poles (and its observer's bandwidth, its integral "
        "pole) for the gains that best meet the requirements on a sweep of the uncertain "
        "plant (the sweep's options; every candidate runs the same samples), with CMA-ES; "
        "then check the best and the spec's own gains on fresh samples, and write the tuned "
        "spec as a new file. `tune --resume DIR` continues an interrupted tune."
    )
    parser.add_argument("spec", nargs="?", help="spec file, or the name of a bundled example")
    parser.add_argument(
        "--resume", metavar="DIR", help="continue the interrupted tune in DIR (no SPEC)"
    )
    parser.add_argument("--out", help="output folder (not with --resume: DIR is the folder)")
    parser.add_argument(
        "--evaluations", type=int, help="candidates to sweep, the spec's own gains not counted"
    )
    parser.add_argument("--samples", type=int, help="samples each candidate runs (the same ones)")
    run_options.add(parser, "seed")
    plant.plant_options(parser)
    parser.add_argument(
        "--objective",
        metavar="STAT(METRIC)",
        help="what to minimise: STAT one of mean, median, p90, p95, p99, max; METRIC one of "
        "final_error, integrated_error, max_error (default p95(final_error), or the spec's "
        "[tune] objective)",
    )
    parser.add_argument(
        "--constraint",
        action="append",
        default=[],
        metavar="REQUIREMENT",
        help="a bound the tuned gains must keep, e.g. 'failure_bound <= 0.02', "
        "'mean(saturation) <= 0.05', 'max(peak_torque) <= 4' (repeatable; default: the "
        "failure bound of the spec's own gains)",
    )
    parser.add_argument(
        "--after",
        type=float,
        metavar="T",
        help="measure integrated_error and max_error from time T on (a settling time)",
    )
    parser.add_argument(
        "--pole-range",
        metavar="LO:HI",
        help="every pole's magnitude in [LO, HI] rad/s (default: a fifth of the spec's "
        "slowest to five times its fastest)",
    )
    parser.add_argument(
        "--min-damping",
        type=float,
        metavar="ZETA",
        help="complex pairs' least damping ratio (1: real poles only; default 0.3)",
    )
    parser.add_argument(
        "--bandwidth-range",
        metavar="LO:HI",
        help="the observer's bandwidth in [LO, HI] rad/s (default: a tenth to ten times "
        "the spec's)",
    )
    parser.add_argument(
        "--complex-pairs",
        type=int,
        metavar="N",
        help="how many of the poles are complex pairs (default: as many as the spec's)",
    )
    parser.add_argument(
        "--method",
        choices=tuple(METHODS),
        default="cma",
        help="the search: CMA-ES, optuna's TPE (the tpe extra), or uniform random points "
        "(the baseline) (default: cma)",
    )
    parser.add_argument(
        "--population", type=int, help="candidates per generation (default: CMA-ES's, 4 + 3 ln d)"
    )
    parser.add_argument(
        "--check-samples",
        type=int,
        default=1000,
        help="fresh samples the best and the spec's gains are checked on (default 1000)",
    )
    parser.add_argument(
        "--check-seed", type=int, help="their seed (default: --seed + 1, never the search's)"
    )
    plant.cluster_options(parser)
    parser.add_argument(
        "--force", action="store_true", help="replace an earlier tune's files in --out"
    )
    parser.add_argument(
        "--progress",
        choices=("auto", "always", "never"),
        default="auto",
        help="show progress on stderr (auto: on a terminal)",
    )
    run_options.add(parser, "max_seconds", "max_size", hidden=True)
    parser.add_argument(
        "--extension", choices=("spec", "auto"), default="spec", help=argparse.SUPPRESS
    )


def run(args: argparse.Namespace) -> int:
    """A new tune, or ``--resume DIR``."""
    if args.resume is not None:
        if not args.resume.strip():
            raise SpecError("command line", "--resume", "DIR is empty")
        if args.out is not None:
            raise SpecError("command line", "--out", "is DIR itself with --resume")
        if args.spec is not None:
            raise SpecError("command line", "--resume", "takes no SPEC (the tune's copy is used)")
        _refuse_tune_options(args)
        return _resume(args)
    if args.spec is None:
        raise SpecError("command line", "SPEC", "tune needs a spec (or --resume DIR)")
    if args.out is None:
        raise SpecError("command line", "--out", "is required")
    return _new(args)


# ------------------------------------------------------------------ the tune's settings


def _count(value: int | None, option: str, default: int, high: int) -> int:
    if value is None:
        return default
    if not 1 <= value <= high:
        raise SpecError("command line", option, f"must be between 1 and {high}")
    return value


def _settings(args: argparse.Namespace) -> Settings:
    """The command line's settings, each checked (the requirements' grammar comes later)."""
    from tvopt_codegen.sweep import MAX_SAMPLES  # noqa: PLC0415
    from tvopt_codegen.tune.settings import Settings  # noqa: PLC0415
    from tvopt_codegen.tune.space import parse_range  # noqa: PLC0415

    run_options.check(args)
    if args.population is not None and not 2 <= args.population <= 1000:
        raise SpecError("command line", "--population", "must be between 2 and 1000")
    if args.after is not None and not (math.isfinite(args.after) and args.after >= 0):
        raise SpecError("command line", "--after", "must be zero or positive and finite")
    if args.check_seed is not None and not 0 <= args.check_seed <= 2**63 - 1:
        raise SpecError("command line", "--check-seed", "must be between 0 and 2**63 - 1")
    if args.complex_pairs is not None and args.complex_pairs < 0:
        raise SpecError("command line", "--complex-pairs", "must be zero or positive")
    return Settings(
        evaluations=_count(args.evaluations, "--evaluations", 100, MAX_EVALUATIONS),
        samples=_count(args.samples, "--samples", 100, MAX_SAMPLES),
        seed=args.seed,
        check_samples=_count(args.check_samples, "--check-samples", 1000, MAX_SAMPLES),
        check_seed=(args.seed + 1) % 2**63 if args.check_seed is None else args.check_seed,
        method=args.method,
        population=args.population,
        objective=args.objective,
        constraints=tuple(args.constraint),
        after=args.after,
        pole_range=None
        if args.pole_range is None
        else parse_range(args.pole_range, "--pole-range"),
        min_damping=args.min_damping,
        bandwidth_range=None
        if args.bandwidth_range is None
        else parse_range(args.bandwidth_range, "--bandwidth-range"),
        complex_pairs=args.complex_pairs,
    )


#: What defines a tune, with the value that means "not given": a resume continues the
#: recorded tune, and a different value would silently not apply.
_DEFINING: dict[str, object] = {
    "evaluations": None,
    "samples": None,
    "seed": 0,
    "initial": [],
    "param": [],
    "plant_param": [],
    "saturation": [],
    "measurement_noise": 0.0,
    "sample_time": None,
    "t_final": None,
    "objective": None,
    "constraint": [],
    "after": None,
    "pole_range": None,
    "min_damping": None,
    "bandwidth_range": None,
    "complex_pairs": None,
    "method": "cma",
    "population": None,
    "check_samples": 1000,
    "check_seed": None,
}


def _refuse_tune_options(args: argparse.Namespace) -> None:
    """A resume takes the tune's own options from its record: refuse any given here."""
    from tvopt_codegen.limits import RUN_OPTIONS  # noqa: PLC0415

    defaults = {name: option.default for name, option in RUN_OPTIONS.items()}
    for name, unset in _DEFINING.items():
        if getattr(args, name) != defaults.get(name, unset):
            raise SpecError(
                "command line",
                "--" + name.replace("_", "-"),
                "not with --resume: the tune keeps the options it was started with",
            )
    for name in ("rtol", "atol", "points"):
        if getattr(args, name) != defaults[name]:
            raise SpecError(
                "command line",
                "--" + name,
                "not with --resume: the tune keeps the options it was started with",
            )


# ------------------------------------------------------------------ the problem


@dataclass
class Problem:
    """A tune's problem, ready to search: the loop, its samples, the space, the requirements."""

    name: str
    source: str
    raw: bytes
    program: SweepProgram
    options: SweepOptions
    check: SweepOptions
    space: Space
    requirements: Requirements
    original: Candidate
    settings: Settings
    extension: str
    #: The label of the failure bound added for the spec's own gains, if one was.
    default_bound: str | None = None


def _problem(
    args: argparse.Namespace,
    settings: Settings,
    derivation: Any,
    kernels: Any,
    raw: bytes,
    extension: str,
    source: str,
) -> Problem:
    """The loop, the samples and the search's space and requirements, all checked."""
    import dataclasses  # noqa: PLC0415

    from tvopt_codegen.sweep import sweep_program  # noqa: PLC0415
    from tvopt_codegen.tune.requirements import requirements_from  # noqa: PLC0415
    from tvopt_codegen.tune.space import Candidate, space_for  # noqa: PLC0415

    spec = derivation.spec
    program = sweep_program(kernels)
    horizon = spec.t_final if args.t_final is None else args.t_final
    if settings.after is not None and not settings.after < horizon:
        raise SpecError("command line", "--after", f"must be before the horizon, {horizon:g} s")
    options = plant.plant_sweep(
        args, program, horizon, settings.samples, settings.seed, window=settings.after or 0.0
    )
    if options.sample_time is not None and options.t_final < options.sample_time:
        # The candidate's gains would act once, at t = 0: every candidate looks alike.
        raise SpecError(
            "command line" if args.t_final is not None else source,
            "--t-final" if args.t_final is not None else "simulation.t_final",
            f"the horizon {options.t_final:g} s is shorter than one controller period "
            f"(--sample-time {options.sample_time:g} s): the gains would act only once",
        )
    check = replace(options, samples=settings.check_samples, seed=settings.check_seed)
    table = getattr(spec, "tune", None)
    requirements = requirements_from(
        None if table is None else dataclasses.asdict(table),
        source,
        settings.objective,
        settings.constraints,
        settings.after,
        samples=settings.samples,
        t_final=options.t_final,
        inputs=program.input_names,
    )
    if requirements.after >= options.t_final:
        # Only the spec's [tune] table can say so here: --after was checked above.
        raise SpecError(source, "tune.after", f"must be before the horizon, {horizon:g} s")
    if requirements.after != options.window:
        options = replace(options, window=requirements.after)
        check = replace(check, window=requirements.after)
    bandwidth = program.observer_bandwidth
    given = (settings.pole_range, settings.min_damping, settings.bandwidth_range)
    # Each bound from the command line when given there, else from the spec's [tune]
    # table: an option overrides its own key, not the table's other keys.
    magnitude, min_damping, bandwidth_range = given
    if table is not None:
        magnitude = table.pole_range if magnitude is None else magnitude
        min_damping = table.min_damping if min_damping is None else min_damping
        bandwidth_range = table.bandwidth_range if bandwidth_range is None else bandwidth_range
    # A bound of the spec's [tune] table is named there, one of the command line's there;
    # the table's bounds were checked when the spec was read, so an error that both could
    # cause (too few poles for the pairs) is the command line's when it gave any.
    only_table = given == (None, None, None) and (magnitude, min_damping, bandwidth_range) != given
    space = space_for(
        _spec_poles(derivation),
        bandwidth,
        integral=bool(program.integral_rows),
        magnitude=magnitude,
        min_damping=min_damping,
        bandwidth_range=bandwidth_range,
        pairs=settings.complex_pairs,
        field_prefix="tune." if only_table else "--",
        source=source if only_table else "command line",
    )
    original = Candidate(poles=_spec_poles(derivation), bandwidth=bandwidth)
    return Problem(
        spec.name,
        source,
        raw,
        program,
        options,
        check,
        space,
        requirements,
        original,
        settings,
        extension,
    )


def _spec_poles(derivation: Any) -> tuple[complex, ...]:
    """The spec's poles as it wrote them (exact); from coefficients, H's eigenvalues.

    Eigenvalues computed from coefficients are cleaned as the spec would write them: a
    root within 1e-4 of its size of the real axis is real, and a pair's members are
    exact conjugates.
    """
    if derivation.spec.poles is not None:
        return tuple(complex(p) for p in derivation.spec.poles)
    cleaned: list[complex] = []
    for value in sorted(derivation.dynamics.eigenvalues, key=lambda p: (p.real, -p.imag)):
        if abs(value.imag) <= 1e-4 * abs(value):
            cleaned.append(complex(value.real, 0.0))
        elif value.imag > 0:
            cleaned += [complex(value.real, value.imag), complex(value.real, -value.imag)]
    return tuple(cleaned)


# ------------------------------------------------------------------ running it


class _Progress:
    """Candidates done and the best so far on stderr (a line a generation; in a log, a minute)."""

    def __init__(self, mode: str, total: int, objective: str) -> None:
        self.tty = sys.stderr.isatty()
        self.enabled = mode == "always" or (mode == "auto" and self.tty)
        self.log = mode == "auto" and not self.tty
        self.total = total
        self.objective = objective
        self.started = time.perf_counter()
        self.last = self.started
        if self.log:
            self.enabled = True

    def __call__(self, done: int, best: Any) -> None:
        now = time.perf_counter()
        if not self.enabled or (self.log and now - self.last < LOG_EVERY):
            return
        self.last = now
        state = "feasible" if best.score.feasible else "no candidate feasible yet"
        line = (
            f"  tune: {done}/{self.total} candidates, best {self.objective} = "
            f"{best.score.objective:.4g} ({state}), {now - self.started:.0f} s"
        )
        print(line, end="\r" if self.tty else "\n", file=sys.stderr, flush=True)

    def close(self) -> None:
        if self.enabled and self.tty:
            print(file=sys.stderr, flush=True)


def _new(args: argparse.Namespace) -> int:
    """Run ``tvopt-codegen tune SPEC ...``."""
    from tvopt_codegen.spec import read_spec_bytes  # noqa: PLC0415
    from tvopt_codegen.sweep import check_workers  # noqa: PLC0415

    settings = _settings(args)
    if args.scheduler is None:
        check_workers(args.workers)
    source, raw = read_spec_bytes(args.spec)
    derivation, kernels = common.derive(args)
    problem = _problem(
        args, settings, derivation, kernels, raw, args.extension, derivation.spec.source
    )
    tuned = _tuned_name(problem.name)
    spec_path = Path(args.spec)
    if spec_path.is_file():
        # Neither the tuned spec nor the tune's copy may land on the user's spec (not even
        # with --force, which is for an earlier tune's files): the copy would claim it.
        for kept in (tuned, f"{problem.name}.toml"):
            if (Path(args.out) / kept).resolve() == spec_path.resolve():
                what = "tuned spec" if kept == tuned else "copy of the spec"
                raise OutputError(
                    f"{spec_path}: the tune's {what} ({kept}) would replace it; "
                    "choose another --out"
                )
    record = {
        "kind": "tune",
        "spec": f"{problem.name}.toml",
        "spec_sha256": hashlib.sha256(raw).hexdigest(),
        "extension": args.extension,
        "loop": problem.program.key,
        "options": problem.options.as_dict(),
        "settings": settings.as_dict(),
        "state": "running",
        "evaluations": [],
    }
    return _run(args, problem, record, history=[], force=args.force)


def _tuned_name(name: str) -> str:
    return f"{name}_tuned.toml"


def _names(name: str) -> list[str]:
    return [RECORD, f"{name}.toml", _tuned_name(name), *FILES]


def _run(
    args: argparse.Namespace,
    problem: Problem,
    record: dict[str, Any],
    history: Sequence[Any],
    force: bool,
    folder_path: str | None = None,
) -> int:
    """Lock the folder, search, check on fresh samples, write; keep the best on a signal."""
    from tvopt_codegen.emit import SweepFolder, write_files  # noqa: PLC0415
    from tvopt_codegen.sweep import connect, loop_for  # noqa: PLC0415

    out = folder_path or args.out
    if not history and not force:
        _refuse_earlier(out)
    folder = SweepFolder(out, _names(problem.name), force or bool(history), kind="tune")
    try:
        loop_for(problem.program)  # a compiler error stops here, before any worker starts
        plant.check_nominal(problem.source, problem.program, problem.options)
        write_files(
            {RECORD: _record_bytes(record), f"{problem.name}.toml": problem.raw.decode("utf-8")},
            folder.folder,
            force=True,
            warn=common.warn,
        )
        client, cluster = connect(args.workers, args.scheduler, problem.settings.samples * 8)
        try:
            code = _search_and_write(args, problem, record, history, folder.folder, client)
        finally:
            plant.disconnect(client, cluster)
    except BaseException:
        folder.close(failed=True)
        raise
    folder.close()
    return code


def _refuse_earlier(out: str) -> None:
    from tvopt_codegen.emit import prepare_folder  # noqa: PLC0415

    folder = prepare_folder(out, create=False)
    if (folder / RECORD).exists():
        raise OutputError(
            f"{folder}: already holds a tune ({RECORD}); `tvopt-codegen tune --resume "
            f"{folder}` continues an interrupted one; choose another --out, or --force to "
            "replace its files"
        )


def _record_bytes(record: dict[str, Any]) -> bytes:
    # Not sorted: the order of --plant-param and the others is the order of the draws.
    # Strict JSON (no NaN or Infinity tokens, which other readers refuse): a fresh check
    # whose every sample failed has an infinite objective and no input effort.
    return (json.dumps(_strict_json(record), indent=1, allow_nan=False) + "\n").encode()


def _strict_json(value: Any) -> Any:
    """``value`` with every non-finite float written as its text (``"inf"``, ``"nan"``)."""
    if isinstance(value, float) and not math.isfinite(value):
        return repr(value)
    if isinstance(value, dict):
        return {k: _strict_json(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_strict_json(v) for v in value]
    return value


def _optimizer(problem: Problem) -> Any:
    from tvopt_codegen.tune.search import (  # noqa: PLC0415
        cma_optimizer,
        random_optimizer,
        tpe_optimizer,
    )

    settings, space = problem.settings, problem.space
    population = settings.population or _default_population(space.dimension)
    if settings.method == "random":
        return random_optimizer(space.dimension, settings.seed, population)
    start = space.encode(problem.original)
    if settings.method == "tpe":
        return tpe_optimizer(start, settings.seed, population)
    return cma_optimizer(start, settings.seed, settings.population)


def _default_population(dimension: int) -> int:
    """CMA-ES's default population, so that the random baseline runs the same batches."""
    return 4 + int(3 * math.log(dimension))


def _search_and_write(
    args: argparse.Namespace,
    problem: Problem,
    record: dict[str, Any],
    history: Sequence[Any],
    folder: Path,
    client: Any,
) -> int:
    """The search (recorded after every generation), the fresh check, the files."""
    from tvopt_codegen.emit import write_files  # noqa: PLC0415
    from tvopt_codegen.tune.evaluate import evaluate, fresh_check  # noqa: PLC0415
    from tvopt_codegen.tune.session import ORIGINAL, Evaluation, Search, best  # noqa: PLC0415

    def sweep(candidates: Sequence[Any], done: Any) -> None:
        programs = [
            problem.program.with_gains(c.coefficients, c.bandwidth, poles=c.poles)
            for c in candidates
        ]
        evaluate(client, programs, problem.options, done)

    search = Search(
        problem.space,
        problem.requirements,
        _optimizer(problem),
        problem.settings.evaluations,
        problem.options.t_final,
        problem.program.input_names,
        history,
    )
    label = problem.requirements.objective.label
    progress = _Progress(args.progress, problem.settings.evaluations, label)

    def checkpoint() -> None:
        record["evaluations"] = [e.as_dict() for e in search.evaluations]
        write_files({RECORD: _record_bytes(record)}, folder, force=True, warn=common.warn)

    def told(_evaluation: Evaluation) -> None:
        progress(search.searched, best(search.evaluations))

    print(
        f"tune: {problem.settings.evaluations} candidates of {problem.name}, "
        f"{problem.settings.samples} samples each, {problem.settings.method}",
        file=sys.stderr,
        flush=True,
    )
    stop: BaseException | None = None
    try:
        original = search.evaluate_original(problem.original, sweep, told)
        _add_default_failure_bound(problem, search, original)
        checkpoint()
        search.run(problem.original, sweep, told, checkpoint)
    except (KeyboardInterrupt, Terminated) as exc:
        stop = exc
    finally:
        progress.close()
    if stop is not None:
        return _interrupted(problem, record, search, folder, stop)
    chosen = best(search.evaluations)
    original = next(e for e in search.evaluations if e.generation == ORIGINAL)
    fresh = fresh_check(
        client, problem.program, problem.requirements, problem.check, original, chosen
    )
    record["state"] = "complete"
    record["evaluations"] = [e.as_dict() for e in search.evaluations]
    record["best"] = chosen.index
    record["fresh"] = fresh
    files = _result_files(problem, search.evaluations, chosen, original, fresh, record)
    write_files(files, folder, force=True, warn=common.warn)
    print(files["tune.md"].decode().rstrip())
    where = str(folder).rstrip("/")
    for name in sorted(files):
        print(f"  wrote {where}/{name}")
    return 0


def _add_default_failure_bound(problem: Problem, search: Any, original: Any) -> None:
    """Without a failure-bound constraint, the tuned gains may fail no more than the spec's.

    The bound is the spec's gains' own Clopper-Pearson bound on the tuning samples; a
    resumed tune takes it again from the recorded evaluation of the spec's gains.
    """
    from tvopt_codegen.sweep.results import clopper_pearson_upper  # noqa: PLC0415
    from tvopt_codegen.tune.requirements import parse_constraint  # noqa: PLC0415

    if any(c.metric == "failure_bound" for c in problem.requirements.constraints):
        return
    bound = clopper_pearson_upper(original.failures, original.runs)
    added = parse_constraint(f"failure_bound <= {bound!r}", "--constraint", samples=original.runs)
    problem.requirements = replace(
        problem.requirements, constraints=(*problem.requirements.constraints, added)
    )
    problem.default_bound = added.label
    search.with_requirements(problem.requirements)
    if not any(label == added.label for label, _, _ in original.score.constraints):
        extended = replace(
            original.score, constraints=(*original.score.constraints, (added.label, bound, bound))
        )
        search.evaluations[search.evaluations.index(original)] = replace(original, score=extended)


def _interrupted(
    problem: Problem, record: dict[str, Any], search: Any, folder: Path, stop: BaseException
) -> int:
    """Keep the best so far (its spec, the tables) and the record; say how to continue."""
    from tvopt_codegen.emit import write_files  # noqa: PLC0415
    from tvopt_codegen.tune.session import ORIGINAL, best  # noqa: PLC0415

    record["state"] = "interrupted"
    record["evaluations"] = [e.as_dict() for e in search.evaluations]
    files: dict[str, Any] = {RECORD: _record_bytes(record)}
    originals = [e for e in search.evaluations if e.generation == ORIGINAL]
    if originals:
        chosen = best(search.evaluations)
        files |= _result_files(problem, search.evaluations, chosen, originals[0], None, record)
    # Held signals: a second one while the files are written does not cut them short.
    write_files(files, folder, force=True, warn=common.warn)
    terminated = isinstance(stop, Terminated)
    print(
        f"tvopt-codegen: {'terminated' if terminated else 'interrupted'} after "
        f"{search.searched} of {problem.settings.evaluations} candidates; kept the best so far "
        f"in {folder / _tuned_name(problem.name)}: `tvopt-codegen tune --resume {folder}` "
        "continues",
        file=sys.stderr,
    )
    return EXIT_TERMINATED if terminated else EXIT_INTERRUPTED


def _result_files(
    problem: Problem,
    evaluations: Sequence[Any],
    chosen: Any,
    original: Any,
    fresh: dict[str, Any] | None,
    record: dict[str, Any],
) -> dict[str, Any]:
    """The tuned spec, the tables, the figure and the record, in memory."""
    from tvopt_codegen.runs.artifacts import tune_files  # noqa: PLC0415
    from tvopt_codegen.tune.spec_text import tuned_text  # noqa: PLC0415
    from tvopt_codegen.tune.tables import evaluations_csv, space_text, tune_markdown  # noqa: PLC0415

    header = [
        f"Tuned by tvopt-codegen tune ({problem.settings.method}, {problem.settings.evaluations} "
        f"candidates of {problem.settings.samples} samples, seed {problem.settings.seed}):",
        f"  {problem.requirements.objective.label} = {chosen.score.objective:.6g} on the tuning "
        f"samples (the spec's gains: {original.score.objective:.6g}).",
    ]
    if fresh is not None:
        header.append(
            f"  On {fresh['samples']} fresh samples (seed {fresh['seed']}): "
            f"{fresh['tuned']['objective']:.6g} (the spec's gains: "
            f"{fresh['original']['objective']:.6g})."
        )
    else:
        header.append("  Interrupted: the best candidate so far, not checked on fresh samples.")
    text = tuned_text(
        problem.raw.decode("utf-8"),
        problem.source,
        poles=chosen.candidate.poles,
        bandwidth=chosen.candidate.bandwidth,
        header=header,
    )
    files: dict[str, Any] = {_tuned_name(problem.name): text, RECORD: _record_bytes(record)}
    requirements = [problem.requirements.objective.label] + [
        c.label + (" (the spec's gains' own bound)" if c.label == problem.default_bound else "")
        for c in problem.requirements.constraints
    ]
    method = f"{METHODS[problem.settings.method]}, seed {problem.settings.seed}"
    markdown = tune_markdown(
        problem.name,
        method,
        requirements,
        space_text(problem.space),
        problem.options,
        evaluations,
        chosen,
        fresh,
    )
    files |= tune_files(
        problem.name,
        markdown,
        evaluations_csv(evaluations),
        problem.requirements.objective.label,
        evaluations,
        chosen,
        original,
    )
    return files


# ------------------------------------------------------------------ --resume


def _resume(args: argparse.Namespace) -> int:
    """Run ``tvopt-codegen tune --resume DIR``."""
    import dataclasses  # noqa: PLC0415

    from tvopt_codegen.derivation import derive  # noqa: PLC0415
    from tvopt_codegen.emit import read_regular_file  # noqa: PLC0415
    from tvopt_codegen.lowering.ir import lower  # noqa: PLC0415
    from tvopt_codegen.spec import parse_spec  # noqa: PLC0415
    from tvopt_codegen.tune.session import Evaluation  # noqa: PLC0415
    from tvopt_codegen.tune.settings import Settings  # noqa: PLC0415

    folder = Path(args.resume)
    where = str(folder / RECORD)
    raw_record = read_regular_file(folder / RECORD, _MAX_RECORD)
    if raw_record is None:
        raise SpecError(str(folder), RECORD, "not found: DIR is not a tune's output folder")
    try:
        record = json.loads(raw_record)
    except ValueError as exc:
        raise SpecError(where, RECORD, f"not a tune's record (cut short?): {exc}") from None
    if not isinstance(record, dict) or record.get("kind") != "tune":
        raise SpecError(where, "kind", "not a tune's record: DIR is not a tune's output folder")
    state = record.get("state")
    if state == "complete":
        print(f"tvopt-codegen: {folder}: the tune is complete; nothing to resume", file=sys.stderr)
        return 0
    if state not in ("running", "interrupted"):
        raise SpecError(where, "state", f"expected running or interrupted, got {state!r}")
    try:
        settings = Settings.from_dict(record.get("settings"))
    except ValueError as exc:
        raise SpecError(where, "settings", str(exc)) from None
    _check_recorded(settings, where)
    evaluations = record.get("evaluations")
    if not isinstance(evaluations, list):
        raise SpecError(where, "evaluations", f"expected a list, got {type(evaluations).__name__}")
    history = []
    for i, entry in enumerate(evaluations):
        try:
            if not isinstance(entry, dict):
                raise TypeError(f"expected a table, got {type(entry).__name__}")
            history.append(Evaluation.from_dict(entry))
        except (ValueError, KeyError, TypeError, AttributeError, IndexError) as exc:
            raise SpecError(where, f"evaluations[{i}]", f"unreadable: {exc}") from None
    options_record = record.get("options")
    if not isinstance(options_record, dict):
        raise SpecError(where, "options", "missing, or not a table")
    spec_name = record.get("spec")
    if (
        not isinstance(spec_name, str)
        or Path(spec_name).name != spec_name
        or not spec_name.endswith(".toml")
    ):
        raise SpecError(where, "spec", f"{spec_name!r} is not a file name in DIR")
    raw = read_regular_file(folder / spec_name, _MAX_SPEC)
    if raw is None:
        raise SpecError(str(folder), spec_name, "the tune's copy of its spec is missing")
    if hashlib.sha256(raw).hexdigest() != record.get("spec_sha256"):
        raise SpecError(
            str(folder / spec_name),
            "spec_sha256",
            "the tune's copy of its spec was edited or replaced since the tune started; "
            "a resume runs the law the tune started with: restore it, or start a new tune",
        )
    source = str(folder / spec_name)
    spec = parse_spec(source, raw)
    if record.get("extension") == "auto":
        spec = dataclasses.replace(spec, extension=(), extension_auto=True)
    derivation = derive(spec)
    kernels = lower(derivation)
    try:
        # The recorded sweep's options, spelled back as the command line gave them.
        replayed = _args_from_options(args, options_record)
        problem = _problem(
            replayed, settings, derivation, kernels, raw, str(record.get("extension")), source
        )
    except SpecError as exc:
        # A recorded value the checks refuse: the record's fault, not the command line's.
        if exc.source != "command line":
            raise
        raise SpecError(where, f"settings ({exc.field})", exc.problem) from None
    except (ValueError, KeyError, TypeError, AttributeError) as exc:
        raise SpecError(where, "options", f"unreadable: {exc}") from None
    if problem.program.key != record.get("loop"):
        raise SpecError(
            where,
            "loop",
            "the compiled loop differs from the one the tune started with (another version?)",
        )
    # Compared as text: the draws follow the options' order, which dicts' == ignores.
    if json.dumps(problem.options.as_dict()) != json.dumps(options_record):
        raise SpecError(where, "options", "do not match the tune's samples")
    _check_history(problem, history, where)
    return _run(replayed, problem, record, history, force=True, folder_path=str(folder))


def _args_from_options(args: argparse.Namespace, options: dict[str, Any]) -> argparse.Namespace:
    """The command line that makes ``options`` again (the sweep's own spelling)."""
    values = vars(args) | {
        "initial": [f"{n}={d}" for n, d in options["initial"].items()],
        "param": [f"{n}={d}" for n, d in options["params"].items()],
        "plant_param": [f"{n}={d}" for n, d in options["plant_params"].items()],
        "saturation": [f"{n}={lo!r}:{hi!r}" for n, (lo, hi) in options["limits"].items()],
        "measurement_noise": options["noise"],
        "sample_time": options["sample_time"],
        "t_final": options["t_final"],
        "rtol": options["rtol"],
        "atol": options["atol"],
        "points": options["points"],
    }
    return argparse.Namespace(**values)


def _check_recorded(settings: Settings, where: str) -> None:
    """A recorded tune's settings within the bounds its command line had (``--resume``).

    A record edited by hand could otherwise ask for 10^12 candidates or a method that
    does not exist; the requirements' grammar and the space's bounds are checked when
    the problem is built, and their errors are turned into the record's.
    """
    from tvopt_codegen.sweep import MAX_SAMPLES  # noqa: PLC0415

    def fail(key: str, problem: str) -> SpecError:
        return SpecError(where, f"settings.{key}", problem)

    for key, high in (
        ("evaluations", MAX_EVALUATIONS),
        ("samples", MAX_SAMPLES),
        ("check_samples", MAX_SAMPLES),
    ):
        if not 1 <= getattr(settings, key) <= high:
            raise fail(key, f"must be between 1 and {high}")
    for key in ("seed", "check_seed"):
        if not 0 <= getattr(settings, key) <= 2**63 - 1:
            raise fail(key, "must be between 0 and 2**63 - 1")
    if settings.method not in METHODS:
        raise fail("method", f"expected one of {', '.join(METHODS)}, got {settings.method!r}")
    if settings.population is not None and not 2 <= settings.population <= 1000:
        raise fail("population", "must be between 2 and 1000")
    if settings.complex_pairs is not None and settings.complex_pairs < 0:
        raise fail("complex_pairs", "must be zero or positive")
    if settings.after is not None and not (math.isfinite(settings.after) and settings.after >= 0):
        raise fail("after", "must be zero or positive and finite")
    if settings.min_damping is not None and not (
        math.isfinite(settings.min_damping) and 0 < settings.min_damping <= 1
    ):
        raise fail("min_damping", "must be in (0, 1]")
    for key in ("pole_range", "bandwidth_range"):
        bounds = getattr(settings, key)
        if bounds is not None and not (
            all(math.isfinite(b) for b in bounds) and 0 < bounds[0] < bounds[1]
        ):
            raise fail(key, "expected 0 < lo < hi, both finite")


def _check_history(problem: Problem, history: Sequence[Any], where: str) -> None:
    """The recorded evaluations are the ones this search made, in its order.

    Each is where the search put it (index, generation, position in the optimiser's
    batches), its candidate is the decoding of its point (so inside the Hurwitz region
    of the space, never poles typed into the record), its scores are numbers a sweep
    gives, and a dry replay of the optimiser asks the same points: a record that is
    not this search's is refused before anything runs or is written.
    """
    import numpy as np  # noqa: PLC0415

    from tvopt_codegen.tune.session import ORIGINAL, ReplayError, Search  # noqa: PLC0415

    samples = problem.settings.samples
    population = _optimizer(problem).population
    for i, e in enumerate(history):

        def fail(problem_text: str, i: int = i) -> SpecError:
            return SpecError(where, f"evaluations[{i}]", problem_text)

        if e.index != i:
            raise fail(f"index {e.index}, expected {i} (the evaluations in order, no gaps)")
        if i == 0:
            if (e.generation, e.position) != (ORIGINAL, 0) or e.candidate != problem.original:
                raise fail("the first evaluation must be the spec's own gains")
        else:
            if e.generation < 0 or not 0 <= e.position < population:
                raise fail(f"generation {e.generation}, position {e.position}: not this search's")
            if e.index != 1 + e.generation * population + e.position:
                raise fail(
                    f"index {e.index} is not generation {e.generation}'s candidate "
                    f"{e.position} (population {population})"
                )
            point = np.asarray(e.x, dtype=float)
            if (
                point.shape != (problem.space.dimension,)
                or not np.all(np.isfinite(point))
                or np.any(point < 0)
                or np.any(point > 1)
            ):
                raise fail("its point is not in the search's box [0, 1]^d")
            if problem.space.decode(point) != e.candidate:
                raise fail("its poles and bandwidth are not its point's (edited by hand?)")
        if not (0 <= e.failures <= e.runs == samples):
            raise fail(f"failures {e.failures} of {e.runs} runs: expected runs = {samples}")
        numbers = (e.score.value, *(bound for _, _, bound in e.score.constraints))
        if not all(math.isfinite(v) for v in numbers) or math.isnan(e.score.objective):
            raise fail("its score is not a number a sweep gives")
    if len(history) - 1 > problem.settings.evaluations:
        raise SpecError(
            where, "evaluations", f"more than the tune's {problem.settings.evaluations} candidates"
        )

    class _RecordEndError(Exception):
        """The replay reached a candidate the record lacks: the rest is the resume's."""

    def no_sweep(candidates: Sequence[Any], _done: Any) -> None:
        if candidates:
            raise _RecordEndError

    search = Search(
        problem.space,
        problem.requirements,
        _optimizer(problem),
        problem.settings.evaluations,
        problem.options.t_final,
        problem.program.input_names,
        history,
    )
    if not history:
        return
    try:
        search.run(problem.original, no_sweep, lambda _e: None)
    except _RecordEndError:
        pass
    except ReplayError as exc:
        raise SpecError(where, "evaluations", str(exc)) from None
