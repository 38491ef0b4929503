"""``tvopt-codegen report SPEC``: the derivation report, in HTML and Markdown."""

from __future__ import annotations

import argparse

from tvopt_codegen.commands import common

HELP = "write the derivation report (HTML and Markdown)"


def build(parser: argparse.ArgumentParser) -> None:
    """The ``report`` command's options."""
    common.spec_argument(parser)
    common.output_options(
        parser,
        "output folder (default: current folder); simulation results already there are included",
    )
    parser.add_argument(
        "--format",
        default="both",
        choices=("html", "md", "both"),
        help="report format (default: both)",
    )
    common.derivation_options(parser)


def run(args: argparse.Namespace) -> int:
    """Derive, read the simulation results in --out, write the report."""
    # Without the collector, as generate and check: the imports (the derivation's, the
    # printers', jinja2's) and the printers' walks make objects by the hundred thousand and
    # no garbage; its scans of them were 20 ms of a 0.27 s report of the integrator.
    with common.without_collector():
        from tvopt_codegen.emit import write_files  # noqa: PLC0415
        from tvopt_codegen.report import read_results, render_report  # noqa: PLC0415

    common.check_out(args.out)
    derivation, kernels = common.derive(args)
    results = read_results(args.out, derivation.spec.name)
    formats = ("html", "md") if args.format == "both" else (args.format,)
    with common.without_collector():
        files = render_report(derivation, kernels, results, formats)
    write_files(files, args.out, force=args.force, warn=common.warn)
    for name in files:
        print(f"wrote {args.out.rstrip('/')}/{name}")
    if results:
        print(f"  with the simulation results found in {args.out}")
    return 0
