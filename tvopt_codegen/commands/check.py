"""``tvopt-codegen check SPEC``: the derivation's summary; writes nothing."""

from __future__ import annotations

import argparse

from tvopt_codegen.commands import common, run_options
from tvopt_codegen.errors import one_line

HELP = "print the derivation summary; writes nothing"


def build(parser: argparse.ArgumentParser) -> None:
    """The ``check`` command's options."""
    common.spec_argument(parser)
    run_options.add(parser, "precision")
    common.derivation_options(parser)


def run(args: argparse.Namespace) -> int:
    """Print the summary, and the targets that refuse this spec (docs/features.md)."""
    with common.without_collector():  # sympy's and numpy's imports build objects by the million
        from tvopt_codegen.runs.summary import format_summary  # noqa: PLC0415

    derivation, kernels = common.derive(args)
    print(format_summary(derivation, kernels))
    from tvopt_codegen.spec.features import target_notes  # noqa: PLC0415

    for note in target_notes(derivation):
        print(one_line(note))
    if args.precision != "double":
        # Asked for: the matrices the single-precision C may not resolve at the start.
        from tvopt_codegen.backends.c.precision import PRECISIONS  # noqa: PLC0415
        from tvopt_codegen.backends.c.resolution import resolution_notes  # noqa: PLC0415

        for note in resolution_notes(derivation, PRECISIONS[args.precision]):
            common.warn(note)
    return 0
