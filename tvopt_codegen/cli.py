"""Command-line interface: parse arguments, call the stages, map errors to exit codes.

Exit codes: 0 success; 2 bad spec; 3 the system violates the method's assumptions;
4 output could not be written; 130 interrupted.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

from tvopt_codegen import __version__
from tvopt_codegen.backends import BACKENDS
from tvopt_codegen.derivation import derive
from tvopt_codegen.emit import write_files
from tvopt_codegen.errors import TvoptError
from tvopt_codegen.ir import lower
from tvopt_codegen.render import render
from tvopt_codegen.spec import bundled_examples, load_spec
from tvopt_codegen.summary import format_summary

EXIT_INTERRUPTED = 130


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="tvopt-codegen",
        description="Generate implicit trajectory planning controllers from a spec file.",
        epilog="Exit codes: 0 ok, 2 bad spec, 3 assumptions violated, 4 output not written.",
    )
    parser.add_argument("--version", action="version", version=f"tvopt-codegen {__version__}")
    commands = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

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

    check = commands.add_parser("check", help="print the derivation summary; writes nothing")
    check.add_argument("spec", help="spec file, or the name of a bundled example")

    commands.add_parser("examples", help="list the bundled example specs")
    return parser


def run(argv: Sequence[str] | None = None) -> int:
    """Run the CLI and return the exit code (errors are reported on stderr)."""
    args = _parser().parse_args(argv)
    if args.command == "examples":
        for name, summary in bundled_examples().items():
            print(f"{name:24s} {summary}")
        return 0
    derivation = derive(load_spec(args.spec))
    kernels = lower(derivation)
    if args.command == "check":
        print(format_summary(derivation, kernels))
        return 0
    files = render(kernels, args.backend)
    written = write_files(files, args.out, force=args.force)
    if not args.quiet:
        print(format_summary(derivation, kernels))
        for name in files:
            path = f"{args.out.rstrip('/')}/{name}"
            state = "written" if any(p.name == name for p in written) else "unchanged"
            print(f"  {state}: {path}")
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """Console-script entry point."""
    try:
        return run(argv)
    except TvoptError as exc:
        print(f"tvopt-codegen: error: {exc}", file=sys.stderr)
        return exc.exit_code
    except KeyboardInterrupt:
        print("tvopt-codegen: interrupted; nothing was written", file=sys.stderr)
        return EXIT_INTERRUPTED


if __name__ == "__main__":
    sys.exit(main())
