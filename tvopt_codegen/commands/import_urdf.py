"""``tvopt-codegen import-urdf URDF --out SPEC.toml``: a spec from a robot's URDF file."""

from __future__ import annotations

import argparse
import math
from pathlib import Path

from tvopt_codegen.commands import common, run_options
from tvopt_codegen.errors import SpecError, one_line

HELP = "write a spec in mass-matrix form from a robot's URDF file"


def build(parser: argparse.ArgumentParser) -> None:
    """The ``import-urdf`` command's options."""
    parser.add_argument("urdf", help="the URDF file: a fixed-base serial chain")
    parser.add_argument("--out", required=True, help="the spec file to write (.toml)")
    parser.add_argument(
        "--tip",
        help="a link whose position (px, py, pz) the objective tracks; the outputs then "
        "replace the first three joints' by it",
    )
    parser.add_argument(
        "--gravity",
        default="0,0,-9.81",
        help="the gravity vector in the base frame, x,y,z (default: 0,0,-9.81)",
    )
    parser.add_argument("--name", help="the spec's name (default: the robot's)")
    parser.add_argument(
        "--initial",
        default="",
        help="initial joint positions, NAME=VALUE,... (default: the middle of each joint's "
        "limits); the targets move about this pose",
    )
    parser.add_argument(
        "--force",
        action="store_true",
        help="replace a spec file edited by hand or not written here",
    )
    run_options.add(parser, "max_seconds")


def run(args: argparse.Namespace) -> int:
    """Read the URDF, write the spec (read back and built first)."""
    import tomllib  # noqa: PLC0415

    from tvopt_codegen.derivation.model import build_model  # noqa: PLC0415
    from tvopt_codegen.emit import write_files  # noqa: PLC0415
    from tvopt_codegen.mechanics import spec_toml  # noqa: PLC0415
    from tvopt_codegen.spec import spec_from_dict  # noqa: PLC0415
    from tvopt_codegen.urdf import spec_from_urdf  # noqa: PLC0415

    out = Path(args.out)
    if out.suffix != ".toml" or not out.stem:
        raise SpecError("command line", "--out", f"{args.out!r}: a spec file name ends in .toml")
    common.check_out(str(out.parent))
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
    # The import runs the same clock as a derivation: a chain too long for it ends with
    # exit 6 naming the stage, never runs on (spec_from_urdf refuses the longest at once).
    progress = common.DeriveProgress("never")
    notes: list[str] = []

    def stage(name: str) -> None:
        progress.stage = f"import-urdf: {name}"

    with common.time_limit(args.max_seconds, [str(args.urdf)], progress):
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
    write_files({out.name: text}, out.parent, force=args.force, warn=common.warn)
    joints = len(spec["system"]["coordinates"])
    print(
        f"wrote {out} ({joints} joints, {len(spec['system']['mechanics']['definitions'])} "
        "definitions; edit its objective and initial state)"
    )
    for note in notes:
        print(one_line(f"note: {note}"))
    return 0
