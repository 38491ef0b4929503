"""``tvopt-codegen export SPEC --fmu``: the stateful controller for other tools."""

from __future__ import annotations

import argparse

from tvopt_codegen.commands import common, run_options
from tvopt_codegen.errors import SpecError

HELP = "export the stateful controller for other tools (an FMU)"


def build(parser: argparse.ArgumentParser) -> None:
    """The ``export`` command's options."""
    common.spec_argument(parser)
    parser.add_argument(
        "--fmu",
        action="store_true",
        help="write <name>.fmu: a co-simulation FMU built from the generated C",
    )
    parser.add_argument(
        "--fmi", type=int, default=2, choices=(2, 3), help="FMI version (default: 2)"
    )
    run_options.add(parser, "precision")
    common.output_options(parser)
    common.derivation_options(parser)


def run(args: argparse.Namespace) -> int:
    """Derive, build the FMU from the generated C, write it."""
    from tvopt_codegen.emit import write_files  # noqa: PLC0415
    from tvopt_codegen.runs.fmu import build_fmu  # noqa: PLC0415

    if not args.fmu:
        raise SpecError("command line", "export", "nothing to export: give --fmu")
    if args.precision != "double":
        # The FMU's interface is FMI's, whose reals are doubles, and its glue calls the
        # controller with them: single precision is for generate --backend c.
        raise SpecError(
            "command line",
            "--precision",
            f"the FMU keeps double precision (FMI's reals are doubles); for {args.precision} "
            "precision C use generate --backend c --precision " + args.precision,
        )
    common.check_out(args.out)
    derivation, kernels = common.derive(args)
    name = f"{derivation.spec.name}.fmu"
    write_files({name: build_fmu(kernels, args.fmi)}, args.out, force=args.force, warn=common.warn)
    print(f"wrote {args.out.rstrip('/')}/{name} (FMI {args.fmi}.0 co-simulation)")
    return 0
