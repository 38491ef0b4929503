"""``tvopt-codegen generate SPEC``: derive the law and write the controller."""

from __future__ import annotations

import argparse
import sys
import time
from typing import TYPE_CHECKING

from tvopt_codegen.commands import common, run_options
from tvopt_codegen.errors import SpecError

if TYPE_CHECKING:
    from tvopt_codegen.backends import Backend

HELP = "derive the law and write the controller"


def build(parser: argparse.ArgumentParser) -> None:
    """The ``generate`` command's options."""
    common.spec_argument(parser)
    common.backend_option(parser, "target language")
    run_options.add(parser, "precision")
    common.output_options(parser)
    parser.add_argument("--quiet", action="store_true", help="print nothing on success")
    parser.add_argument(
        "--timings",
        action="store_true",
        help="also print one JSON line of stage seconds and law operations on stderr "
        "(for benchmarks/bench_derive.py)",
    )
    common.derivation_options(parser)


def run(args: argparse.Namespace) -> int:
    """Derive, render and write; print the summary and each file's state."""
    with common.without_collector():  # sympy's and numpy's imports build objects by the million
        from tvopt_codegen.runs.summary import format_summary  # noqa: PLC0415

    backend = c_backend(args.backend, args.precision)
    common.check_out(args.out)
    derivation, kernels = common.derive(args)
    started = time.perf_counter()
    from tvopt_codegen.emit import write_files  # noqa: PLC0415
    from tvopt_codegen.renderer.rendering import render  # noqa: PLC0415

    with common.without_collector():
        files = render(kernels, backend)
    rendered = time.perf_counter()
    written = write_files(files, args.out, force=args.force, warn=common.warn)
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


def c_backend(backend: str, precision: str) -> str | Backend:
    """The backend to render with: ``backend`` itself, or the C one in ``precision``.

    Raises
    ------
    SpecError
        Single precision asked of another backend than C (before any work).
    """
    if precision == "double":
        return backend
    if backend != "c":
        raise SpecError(
            "command line",
            "--precision",
            f"{precision} precision is the C backend's (the {backend} backend computes in "
            "double): give --backend c",
        )
    from tvopt_codegen.backends.c import with_precision  # noqa: PLC0415

    return with_precision(precision)
