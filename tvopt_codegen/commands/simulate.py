"""``tvopt-codegen simulate SPEC``: the closed loop and the theorem's certificate.

The continuous loop, or with ``--sample-time`` also the stateful controller sampled
every H seconds beside it; with ``--reference-file`` the references estimated online
from samples.
"""

from __future__ import annotations

import argparse
import contextlib
import math
import sys
from typing import TYPE_CHECKING

from tvopt_codegen.commands import common, run_options
from tvopt_codegen.errors import EXIT_CERTIFICATE, SpecError
from tvopt_codegen.limits import METHODS

if TYPE_CHECKING:
    from collections.abc import Mapping

    from tvopt_codegen.derivation import Derivation
    from tvopt_codegen.runs.drawing import Painter
    from tvopt_codegen.runs.side import Side
    from tvopt_codegen.simulation import Result
    from tvopt_codegen.simulation.result import Trajectories

HELP = "simulate the closed loop and check the theorem along the run"


def build(parser: argparse.ArgumentParser) -> None:
    """The ``simulate`` command's options."""
    common.spec_argument(parser)
    common.backend_option(parser, "controller backend to simulate")
    parser.add_argument(
        "--initial",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="initial value of a state (repeatable)",
    )
    parser.add_argument(
        "--param",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="parameter override (repeatable)",
    )
    parser.add_argument(
        "--plant-param",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="with --sample-time: the true plant's parameter, where it is not the model's "
        "(repeatable)",
    )
    parser.add_argument(
        "--method",
        default="RK45",
        choices=METHODS,
        help="solve_ivp method (default: RK45, Dormand-Prince, as in the paper)",
    )
    run_options.add(parser, "t_final", "rtol", "atol", "points", "seed", "sample_time")
    parser.add_argument(
        "--tolerance",
        type=float,
        default=1e-6,
        help="largest accepted relative deviation of E from expm(Ht) E(0)",
    )
    parser.add_argument(
        "--reference-file",
        metavar="FILE.csv",
        help="for a spec with [references]: samples t, <reference>, ... estimated online "
        "into jets by the spec's differentiator (default: the nominal closed forms)",
    )
    run_options.add(parser, "reference_noise")
    run_options.renamed(
        parser, "--noise", "--reference-noise (Gaussian noise on the reference samples)"
    )
    parser.add_argument(
        "--allow-gaps",
        action="store_true",
        help="with --reference-file: accept samples the estimator cannot follow (a gap of "
        "more than 10 median intervals, or samples slower than 1/bandwidth)",
    )
    parser.add_argument(
        "--convergence-order",
        action="store_true",
        help="with --sample-time: also run at H/2 (and at H/4, H/8 while the order is below "
        "0.75, not yet asymptotic) and report the observed order in H",
    )
    common.output_options(parser)
    common.derivation_options(parser)


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


class _Early:
    """Sends a run's figures of the run alone to the painter before it is certified."""

    def __init__(self, derivation: Derivation, painter: Painter) -> None:
        self._derivation, self._painter = derivation, painter
        self._runs: dict[str, Trajectories] = {}

    def __call__(self, run: Trajectories) -> None:
        from tvopt_codegen.runs.artifacts import submit_early  # noqa: PLC0415

        for stem in submit_early(self._derivation, run, self._painter):
            self._runs[stem] = run

    def stems(self, result: Result) -> set[str]:
        """The stems sent from ``result``'s run (not from one a failed check replaced)."""
        return {stem for stem, run in self._runs.items() if run.outputs is result.outputs}


def run(args: argparse.Namespace) -> int:
    """Simulate the closed loop (and the sampled one), check the certificate, write."""
    # First: the drawing process imports matplotlib while this one loads sympy and derives.
    from tvopt_codegen.runs.drawing import Painter  # noqa: PLC0415

    with Painter() as painter, contextlib.ExitStack() as stack:
        return _simulate_with(args, painter, stack)


def _side_process(
    args: argparse.Namespace,
    derivation: Derivation,
    params: Mapping[str, float],
    stack: contextlib.ExitStack[bool | None],
) -> Side | None:
    """For a continuous run with constraints, their SLSQP check's process, started now.

    It imports scipy.optimize and gets the problem ready while this process loads the
    controller and integrates; ``stack`` stops it.
    """
    model = derivation.model
    if args.sample_time is not None or not (model.constraints or model.equalities):
        return None
    from tvopt_codegen.simulation.constraints import minimiser_process  # noqa: PLC0415

    return stack.enter_context(minimiser_process(model, params))


def _simulate_with(
    args: argparse.Namespace, painter: Painter, stack: contextlib.ExitStack[bool | None]
) -> int:
    from tvopt_codegen.emit import write_files  # noqa: PLC0415
    from tvopt_codegen.runs.artifacts import result_files  # noqa: PLC0415 - matplotlib on use
    from tvopt_codegen.simulation import (  # noqa: PLC0415
        format_certificate,
        load_controller,
        resolve_options,
        simulate,
    )

    # The shared run options' bounds are checked already (commands.run_options.check).
    if not 0 < args.tolerance < math.inf:
        raise SpecError("command line", "--tolerance", "must be positive and finite")
    if args.reference_noise and args.reference_file is None:
        raise SpecError("command line", "--reference-noise", "needs --reference-file")
    if args.allow_gaps and args.reference_file is None:
        raise SpecError("command line", "--allow-gaps", "needs --reference-file")
    if args.convergence_order and args.sample_time is None:
        raise SpecError("command line", "--convergence-order", "needs --sample-time")
    if args.plant_param and args.sample_time is None:
        raise SpecError(
            "command line",
            "--plant-param",
            "needs --sample-time (the continuous run is the nominal theorem's; the sampled "
            "controller runs on the mismatched plant)",
        )
    common.check_out(args.out)
    derivation, kernels = common.derive(args)
    plant_params = common.assignments(args.plant_param, "--plant-param")
    unknown = sorted(set(plant_params) - {name for name, _ in derivation.spec.parameters})
    if unknown:
        raise SpecError("command line", "--plant-param", f"{unknown[0]!r} is not a parameter")
    options = resolve_options(
        derivation,
        args.t_final,
        common.assignments(args.initial, "--initial"),
        common.assignments(args.param, "--param"),
        method=args.method,
        rtol=args.rtol,
        atol=args.atol,
        points=args.points,
        tolerance=args.tolerance,
    )
    side = _side_process(args, derivation, options.params, stack)
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
            warn=common.warn,
        )
    controller = load_controller(kernels, args.backend)
    references = None
    if samples is not None:
        from tvopt_codegen.simulation.references import sampled_source  # noqa: PLC0415

        references = sampled_source(
            derivation, controller, dict(options.params), *samples, args.reference_noise, args.seed
        )
    progress, early = _Progress(), _Early(derivation, painter)
    try:
        if args.sample_time is None:
            result = simulate(derivation, controller, options, progress, references, side, early)
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
    files = result_files(derivation, result, painter, early.stems(result))
    text = format_certificate(derivation, result)
    passed = result.passed
    if sampled is not None:
        from tvopt_codegen.runs.artifacts import sampled_files  # noqa: PLC0415
        from tvopt_codegen.simulation.sampled import format_sampled  # noqa: PLC0415

        files.update(sampled_files(derivation, sampled))
        text += "\n" + format_sampled(derivation, sampled)
        files[f"{derivation.spec.name}_certificate.txt"] = (text + "\n").encode("utf-8")
        passed = sampled.passed
    write_files(files, args.out, force=args.force, warn=common.warn)
    print(text)
    for name in files:
        print(f"  wrote {args.out.rstrip('/')}/{name}")
    return 0 if passed else EXIT_CERTIFICATE
