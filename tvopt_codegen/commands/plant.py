"""What ``sweep`` and ``tune`` share: the uncertain plant's options, its samples, the cluster.

Both spell the plant that is not the model the same way (``--plant-param``,
``--saturation``, ``--measurement-noise``, ``--sample-time``, ...), refuse a spec whose
nominal plant fails at its start, and run on a local cluster or a scheduler.
"""

from __future__ import annotations

import argparse
from typing import TYPE_CHECKING, Any

from tvopt_codegen.commands import run_options

if TYPE_CHECKING:
    from tvopt_codegen.sweep import SweepOptions, SweepProgram


def plant_options(parser: argparse.ArgumentParser) -> None:
    """The uncertain plant and its loop, spelled alike by ``sweep`` and ``tune``."""
    for option, what in (
        ("--initial", "spread of an initial closed-loop state"),
        ("--param", "the controller's (model's) parameter"),
        ("--plant-param", "the true plant's parameter (model mismatch)"),
    ):
        parser.add_argument(
            option, action="append", default=[], metavar="NAME=DIST", help=f"{what} (repeatable)"
        )
    parser.add_argument(
        "--saturation",
        action="append",
        default=[],
        metavar="INPUT=LIMIT",
        help=(
            "clip a plant input to |u| <= LIMIT, or to LO:HI "
            "(repeatable; default: the spec's [limits])"
        ),
    )
    run_options.add(parser, "measurement_noise")
    run_options.renamed(
        parser, "--noise", "--measurement-noise (Gaussian noise on the measured plant states)"
    )
    run_options.add(parser, "sample_time", "t_final", "rtol", "atol", "points")


def cluster_options(parser: argparse.ArgumentParser) -> None:
    """Where the samples run: ``--workers`` of a local cluster or ``--scheduler``."""
    where = parser.add_mutually_exclusive_group()
    run_options.add(where, "workers")
    where.add_argument(
        "--scheduler", metavar="ADDRESS", help="an existing Dask scheduler, e.g. tcp://host:8786"
    )


def plant_sweep(
    args: argparse.Namespace,
    program: SweepProgram,
    horizon: float,
    samples: int,
    seed: int,
    window: float = 0.0,
) -> SweepOptions:
    """The :class:`~tvopt_codegen.sweep.SweepOptions` of :func:`plant_options`, checked.

    ``window``: where the errors measured after a settling time start (``tune --after``).
    """
    from tvopt_codegen.sweep import (  # noqa: PLC0415
        SweepOptions,
        check_options,
        parse_assignments,
        parse_limits,
    )

    options = SweepOptions(
        samples=samples,
        seed=seed,
        t_final=horizon if args.t_final is None else args.t_final,
        initial=parse_assignments(args.initial, "--initial", program.state_names, "state"),
        params=parse_assignments(args.param, "--param", program.param_names, "parameter"),
        plant_params=parse_assignments(
            args.plant_param, "--plant-param", program.param_names, "parameter"
        ),
        # The plant's actuators: --saturation, else the spec's [limits].
        limits=parse_limits(args.saturation, program.input_names) or program.limits,
        noise=args.measurement_noise,
        sample_time=args.sample_time,
        rtol=args.rtol,
        atol=args.atol,
        points=args.points,
        window=window,
    )
    check_options(program, options)
    return options


def check_nominal(source: str, program: SweepProgram, options: SweepOptions) -> None:
    """Refuse a sweep whose nominal plant fails at its start (nothing run, nothing written).

    Every sample would start there or near it and fail for that one reason of the
    model's: a table of 100% failures would hide it as an ordinary outcome.
    """
    from tvopt_codegen.contract import Status  # noqa: PLC0415
    from tvopt_codegen.errors import AssumptionError  # noqa: PLC0415
    from tvopt_codegen.sweep.sample import nominal_start  # noqa: PLC0415

    outcome = nominal_start(program, options)
    if not isinstance(outcome, Status) or outcome == Status.OK:
        return
    start = "the spec's initial state" + (
        " with each --initial at its centre" if options.initial else ""
    )
    why = outcome.text.replace("{result}", "a value of the law")
    raise AssumptionError(
        source,
        "sweep",
        f"the nominal plant fails at its start ({start}, the spec's parameters, t = 0): "
        f"{outcome.label} ({why}); every sample would start there or near it, so nothing "
        "was run: fix the spec (check SPEC names where the law is undefined)",
    )


def disconnect(client: Any, cluster: Any) -> None:
    """Close the client, and the local cluster with its worker processes."""
    client.close()
    if cluster is not None:
        cluster.close()


def job_options(parser: argparse.ArgumentParser, kind: str) -> None:
    """What a long job (``sweep``, ``tune``) takes beside its work: --force, --progress."""
    parser.add_argument(
        "--force", action="store_true", help=f"replace an earlier {kind}'s files in --out"
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
