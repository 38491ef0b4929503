"""The wheel: built without a packaging warning, with every template inside it."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

from .conftest import ROOT, shared


def _build_wheel(folder: Path) -> None:
    """The wheel of a clean copy of the checkout, built once per run for both wheel tests.

    A copy without the checkout's ignored build/ folder, whose stale copies of moved
    modules setuptools would ship. Built by the declared backend in this environment
    (pip's ``--no-build-isolation`` calls the same hook, a second build that pip's own
    start-up made twice as dear), with every warning shown, as pip's isolated build shows
    them to a user: the folder keeps the wheel, the build's output and its exit status.
    """
    source = folder / "source"
    ignore = shutil.ignore_patterns("__pycache__", "*.pyc")
    for name in ("tvopt_codegen", "templates"):
        shutil.copytree(ROOT / name, source / name, ignore=ignore)
    for name in ("pyproject.toml", "README.md", "LICENSE"):
        if (ROOT / name).exists():
            shutil.copy2(ROOT / name, source / name)
    out = folder / "wheel"
    out.mkdir()
    build = subprocess.run(
        [
            sys.executable,
            "-W",
            "always",
            "-c",
            f"from setuptools import build_meta; print(build_meta.build_wheel({str(out)!r}))",
        ],
        cwd=source,
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )
    (folder / "build.json").write_text(
        json.dumps({"returncode": build.returncode, "log": build.stdout + build.stderr})
    )


def built_wheel() -> tuple[Path, str]:
    """The run's wheel of the checkout and its build's output (it must have built)."""
    folder = shared("wheel-of-the-checkout", _build_wheel)
    build = json.loads((folder / "build.json").read_text())
    assert build["returncode"] == 0, build["log"][-2000:]
    (wheel,) = (folder / "wheel").glob("tvopt_codegen-*.whl")
    return wheel, build["log"]


def test_the_wheel_builds_without_warnings_and_ships_every_template() -> None:
    pytest.importorskip("setuptools", minversion="77")
    wheel, log = built_wheel()
    assert "BuildBackendWarning" not in log and "absent from" not in log, log[-3000:]
    members = set(zipfile.ZipFile(wheel).namelist())
    templates = {
        "tvopt_codegen/templates/" + p.relative_to(ROOT / "templates").as_posix()
        for p in (ROOT / "templates").rglob("*.jinja")
    }
    assert templates and templates <= members, sorted(templates - members)
    assert {
        f"tvopt_codegen/examples/{p.name}"
        for p in (ROOT / "tvopt_codegen" / "examples").glob("*.toml")
    } <= members
