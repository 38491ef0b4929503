"""The strict C profile (issue 50 item 4): every bundled example's C, in both precisions.

Each controller compiles without a warning under gcc and clang with :data:`STRICT`
(``-Werror``), and clang's static analyser and cppcheck find nothing in it. So are the
template paths no bundled example takes (:data:`VARIANTS`). The files are rendered once
per test run and precision (``conftest.shared``) and shared with ``test_precision``. A
tool that is missing skips with the command that installs it, except in CI (``CI`` set),
where ``.ci/run`` installs it and its absence is a failure.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import tomllib
from pathlib import Path

import pytest

from tvopt_codegen.backends.c import with_precision
from tvopt_codegen.derivation import derive
from tvopt_codegen.lowering.ir import KernelSet, lower
from tvopt_codegen.renderer.rendering import render
from tvopt_codegen.spec import spec_from_dict

from .conftest import ROOT, SPECS, kernels, shared

#: Every bundled example.
BUNDLED = tuple(sorted(path.stem for path in (ROOT / "tvopt_codegen" / "examples").glob("*.toml")))

#: The template paths no bundled example takes, held to the same profile: integral action,
#: the disturbance observer, limits and a slew rate (robust_pvtol), a 3 x 3 block of R (the
#: general LU: coupled3), the extended-state observer, Levant's differentiator.
VARIANTS: dict[str, tuple[Path, dict[str, object]]] = {
    "robust_pvtol": (SPECS / "robust_pvtol.toml", {}),
    "coupled3": (SPECS / "coupled3.toml", {}),
    "drag_vehicle_eso": (
        ROOT / "tvopt_codegen" / "examples" / "drag_vehicle.toml",
        {"robust": {"eso": {"bandwidth": 20.0}}},
    ),
    "unicycle_switch_levant": (
        ROOT / "tvopt_codegen" / "examples" / "unicycle_switch_refs.toml",
        {"references": {"estimator": {"kind": "levant", "lipschitz": 10.0}}},
    ),
}


def _kernels(spec: str) -> KernelSet:
    """A bundled example's kernels, or a variant's (:data:`VARIANTS`)."""
    if spec not in VARIANTS:
        return kernels(spec)
    path, changes = VARIANTS[spec]
    with path.open("rb") as stream:
        data = tomllib.load(stream)
    for section, value in changes.items():
        merged = dict(data.get(section, {}))
        merged.update(value)  # type: ignore[call-overload]
        data[section] = merged
    return lower(derive(spec_from_dict(data)))


#: The strict profile: C99, every warning the issue names, and none allowed.
STRICT = (
    "-std=c99",
    "-O2",
    "-Wall",
    "-Wextra",
    "-Wpedantic",
    "-Wshadow",
    "-Wcast-qual",
    "-Wconversion",
    "-Wundef",
    "-Wstrict-prototypes",
    "-Wdouble-promotion",
    "-Wfloat-conversion",
    "-Werror",
)

#: cppcheck's checks (its errors are always on): nothing it reports is accepted.
CPPCHECK = (
    "--enable=warning,style,performance,portability",
    "--std=c99",
    "--error-exitcode=1",
    "--quiet",
    "--inline-suppr",
)


def generated(spec: str, precision: str) -> Path:
    """The C backend's files for ``spec`` in ``precision``, rendered once per test run."""

    def build(folder: Path) -> None:
        for name, text in render(_kernels(spec), with_precision(precision)).items():
            (folder / name).write_text(text, encoding="utf-8")

    return shared(f"c-{precision}-{Path(spec).stem}", build)


def _tool(name: str, install: str) -> str:
    """The path of ``name``; skip outside CI (saying what installs it), fail in CI."""
    found = shutil.which(name)
    if found is None:
        message = f"{name} is not installed: {install}"
        if os.environ.get("CI"):
            pytest.fail(message)
        pytest.skip(message)
    return found


def _clean(command: list[str], folder: Path) -> None:
    """Run ``command`` in ``folder``; it must succeed and print nothing."""
    done = subprocess.run(command, cwd=folder, capture_output=True, text=True, check=False)
    report = (done.stdout + done.stderr).strip()
    assert done.returncode == 0 and not report, report[:3000]


@pytest.mark.parametrize("precision", ["double", "single"])
@pytest.mark.parametrize("example", [*BUNDLED, *VARIANTS])
def test_the_controller_compiles_warning_free_under_gcc_and_clang(
    example: str, precision: str, tmp_path: Path
) -> None:
    folder = generated(example, precision)
    (source,) = (p.name for p in folder.glob("*.c") if not p.name.endswith(".ext.c"))
    for compiler, install in (("gcc", "apt-get install gcc"), ("clang", "apt-get install clang")):
        cc = _tool(compiler, install)
        _clean([cc, *STRICT, "-c", source, "-o", str(tmp_path / "controller.o")], folder)


@pytest.mark.parametrize("precision", ["double", "single"])
@pytest.mark.parametrize("example", [*BUNDLED, *VARIANTS])
def test_the_static_analysers_find_nothing(example: str, precision: str, tmp_path: Path) -> None:
    folder = generated(example, precision)
    (source,) = (p.name for p in folder.glob("*.c") if not p.name.endswith(".ext.c"))
    clang = _tool("clang", "apt-get install clang")
    _clean([clang, "--analyze", "-std=c99", source, "-o", str(tmp_path / "plist")], folder)
    cppcheck = _tool("cppcheck", "apt-get install cppcheck")
    _clean([cppcheck, *CPPCHECK, source], folder)
