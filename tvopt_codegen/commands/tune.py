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
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

from tvopt_codegen.commands import common, plant, run_options
from tvopt_codegen.errors import (
    EXIT_INTERRUPTED,
    EXIT_TERMINATED,
    OutputError,
    SpecError,
    Terminated,
    forget_signals,
)

if TYPE_CHECKING:
    from tvopt_codegen.tune.problem import Problem
    from tvopt_codegen.tune.session import Evaluation, Search
    from tvopt_codegen.tune.settings import Settings

HELP = "choose the poles and observer gains against sweeps of the mismatched plant"

#: In a log, seconds between progress lines.
LOG_EVERY = 60.0

#: What a tune writes beside its record (the tuned spec's name is ``<name>_tuned.toml``).
FILES = ("tune.md", "evaluations.csv", "tune_tradeoff.png", "tune_tradeoff.svg")
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
        choices=("cma", "tpe", "random"),
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
    plant.job_options(parser, "tune")


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
    from tvopt_codegen.tune.record import MAX_EVALUATIONS  # noqa: PLC0415
    from tvopt_codegen.tune.settings import Settings  # noqa: PLC0415
    from tvopt_codegen.tune.space import parse_range  # noqa: PLC0415

    run_options.check(args)
    if args.population is not None and not 2 <= args.population <= 1000:
        raise SpecError("command line", "--population", "must be between 2 and 1000")
    if args.after is not None and not (math.isfinite(args.after) and args.after >= 0):
        raise SpecError("command line", "--after", "must be zero or positive and finite")
    if args.check_seed is not None and not 0 <= args.check_seed <= 2**63 - 1:
        raise SpecError("command line", "--check-seed", "must be between 0 and 2**63 - 1")
    if args.check_seed is not None and args.check_seed == args.seed:
        raise SpecError(
            "command line", "--check-seed", "is --seed: the check's samples would not be fresh"
        )
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


def _problem(
    args: argparse.Namespace,
    settings: Settings,
    derivation: Any,
    kernels: Any,
    raw: bytes,
    source: str,
) -> Problem:
    """The loop, the samples and the search's space and requirements, all checked."""
    import dataclasses  # noqa: PLC0415

    from tvopt_codegen.sweep import sweep_program  # noqa: PLC0415
    from tvopt_codegen.tune.problem import Problem, spec_poles  # noqa: PLC0415
    from tvopt_codegen.tune.requirements import requirements_from  # noqa: PLC0415
    from tvopt_codegen.tune.space import Candidate, space_for  # noqa: PLC0415
    from tvopt_codegen.tune.spec_text import tuned_text  # noqa: PLC0415

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
        spec_poles(derivation),
        bandwidth,
        integral=bool(program.integral_rows),
        magnitude=magnitude,
        min_damping=min_damping,
        bandwidth_range=bandwidth_range,
        pairs=settings.complex_pairs,
        field_prefix="tune." if only_table else "--",
        source=source if only_table else "command line",
    )
    original = Candidate(poles=spec_poles(derivation), bandwidth=bandwidth)
    # The tuned spec is the user's text rewritten: a layout the writer cannot follow is
    # refused now, not after the search.
    tuned_text(raw.decode("utf-8"), source, poles=original.poles, bandwidth=original.bandwidth)
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
    )


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
    from tvopt_codegen.tune.problem import tuned_name  # noqa: PLC0415

    settings = _settings(args)
    if args.scheduler is None:
        check_workers(args.workers)
    source, raw = read_spec_bytes(args.spec)
    derivation, kernels = common.derive(args)
    problem = _problem(args, settings, derivation, kernels, raw, derivation.spec.source)
    tuned = tuned_name(problem.name)
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


def _names(name: str) -> list[str]:
    from tvopt_codegen.tune.problem import tuned_name  # noqa: PLC0415
    from tvopt_codegen.tune.record import RECORD  # noqa: PLC0415

    return [RECORD, f"{name}.toml", tuned_name(name), *FILES]


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
    from tvopt_codegen.tune.record import RECORD, record_bytes  # noqa: PLC0415

    out = folder_path or args.out
    if not history and not force:
        _refuse_earlier(out)
    folder = SweepFolder(out, _names(problem.name), force or bool(history), kind="tune")
    try:
        loop_for(problem.program)  # a compiler error stops here, before any worker starts
        plant.check_nominal(problem.source, problem.program, problem.options)
        write_files(
            {RECORD: record_bytes(record), f"{problem.name}.toml": problem.raw.decode("utf-8")},
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
    from tvopt_codegen.tune.record import RECORD  # noqa: PLC0415

    folder = prepare_folder(out, create=False)
    if (folder / RECORD).exists():
        raise OutputError(
            f"{folder}: already holds a tune ({RECORD}); `tvopt-codegen tune --resume "
            f"{folder}` continues an interrupted one; choose another --out, or --force to "
            "replace its files"
        )


def _search_and_write(
    args: argparse.Namespace,
    problem: Problem,
    record: dict[str, Any],
    history: Sequence[Evaluation],
    folder: Path,
    client: Any,
) -> int:
    """The search (recorded after every generation), the fresh check, the files.

    Ctrl-C or SIGTERM anywhere before the files (in the search or the fresh check) keeps
    the best candidate so far (:func:`_interrupted`).
    """
    from tvopt_codegen.emit import write_files  # noqa: PLC0415
    from tvopt_codegen.tune.evaluate import evaluate, fresh_check  # noqa: PLC0415
    from tvopt_codegen.tune.problem import (  # noqa: PLC0415
        result_files,
        with_default_failure_bound,
    )
    from tvopt_codegen.tune.record import RECORD, record_bytes  # noqa: PLC0415
    from tvopt_codegen.tune.session import ORIGINAL, best  # noqa: PLC0415

    def sweep(candidates: Sequence[Any], done: Any) -> None:
        evaluate(client, [problem.program_for(c) for c in candidates], problem.options, done)

    search = problem.search(history)
    label = problem.requirements.objective.label
    progress = _Progress(args.progress, problem.settings.evaluations, label)

    def checkpoint() -> None:
        record["evaluations"] = [e.as_dict() for e in search.evaluations]
        write_files({RECORD: record_bytes(record)}, folder, force=True, warn=common.warn)

    def told(_evaluation: Evaluation) -> None:
        progress(search.searched, best(search.evaluations))

    print(
        f"tune: {problem.settings.evaluations} candidates of {problem.name}, "
        f"{problem.settings.samples} samples each, {problem.settings.method}",
        file=sys.stderr,
        flush=True,
    )
    try:
        original = search.evaluate_original(problem.original, sweep, told)
        requirements, problem.default_bound, scored = with_default_failure_bound(problem, original)
        problem.requirements = requirements
        search.with_requirements(requirements)
        search.evaluations[search.evaluations.index(original)] = scored
        checkpoint()
        chosen = search.run(problem.original, sweep, told, checkpoint)
        checkpoint()  # the last generation, cut by the budget, is told to no one
        progress.close()
        original = next(e for e in search.evaluations if e.generation == ORIGINAL)
        fresh = fresh_check(client, problem, original, chosen)
    except (KeyboardInterrupt, Terminated) as stop:
        forget_signals()  # handled here: the evaluations so far are kept and written
        progress.close()
        return _interrupted(problem, record, search, folder, stop)
    record["state"] = "complete"
    record["evaluations"] = [e.as_dict() for e in search.evaluations]
    record["best"] = chosen.index
    record["fresh"] = fresh
    files = result_files(problem, search.evaluations, chosen, original, fresh)
    files[RECORD] = record_bytes(record)
    write_files(files, folder, force=True, warn=common.warn)
    markdown = files["tune.md"]
    print((markdown if isinstance(markdown, str) else markdown.decode()).rstrip())
    where = str(folder).rstrip("/")
    for name in sorted(files):
        print(f"  wrote {where}/{name}")
    if not chosen.score.feasible:
        common.warn(
            f"no candidate met every requirement on the tuning samples; "
            f"{where}/{tuned_name_of(problem)} holds the least violating (see tune.md)"
        )
    return 0


def tuned_name_of(problem: Problem) -> str:
    """The tuned spec's file name for ``problem``."""
    from tvopt_codegen.tune.problem import tuned_name  # noqa: PLC0415

    return tuned_name(problem.name)


def _interrupted(
    problem: Problem, record: dict[str, Any], search: Search, folder: Path, stop: BaseException
) -> int:
    """Keep the best so far (its spec, the tables) and the record; say how to continue."""
    from tvopt_codegen.emit import write_files  # noqa: PLC0415
    from tvopt_codegen.tune.problem import result_files  # noqa: PLC0415
    from tvopt_codegen.tune.record import RECORD, record_bytes  # noqa: PLC0415
    from tvopt_codegen.tune.session import best  # noqa: PLC0415

    record["state"] = "interrupted"
    record["evaluations"] = [e.as_dict() for e in search.evaluations]
    files: dict[str, bytes | str] = {RECORD: record_bytes(record)}
    original = search.original
    if original is not None:
        chosen = best(search.evaluations)
        files |= result_files(problem, search.evaluations, chosen, original, None)
    # Held signals: a second one while the files are written does not cut them short.
    write_files(files, folder, force=True, warn=common.warn)
    terminated = isinstance(stop, Terminated)
    print(
        f"tvopt-codegen: {'terminated' if terminated else 'interrupted'} after "
        f"{search.searched} of {problem.settings.evaluations} candidates; kept the best so far "
        f"in {folder / tuned_name_of(problem)}: `tvopt-codegen tune --resume {folder}` "
        "continues",
        file=sys.stderr,
    )
    return EXIT_TERMINATED if terminated else EXIT_INTERRUPTED


# ------------------------------------------------------------------ --resume


def _resume(args: argparse.Namespace) -> int:
    """Run ``tvopt-codegen tune --resume DIR``."""
    import dataclasses  # noqa: PLC0415

    from tvopt_codegen.derivation import derive  # noqa: PLC0415
    from tvopt_codegen.emit import read_regular_file  # noqa: PLC0415
    from tvopt_codegen.lowering.ir import lower  # noqa: PLC0415
    from tvopt_codegen.spec import parse_spec  # noqa: PLC0415
    from tvopt_codegen.tune.record import RECORD, check_history, check_recorded  # noqa: PLC0415
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
    check_recorded(settings, where)
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
        problem = _problem(replayed, settings, derivation, kernels, raw, source)
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
    check_history(problem, history, where)
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
