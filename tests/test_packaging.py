"""The wheel: built without a packaging warning, with every template inside it."""

from __future__ import annotations

import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

from .conftest import ROOT


def test_the_wheel_builds_without_warnings_and_ships_every_template(tmp_path: Path) -> None:
    pytest.importorskip("setuptools", minversion="77")
    source = tmp_path / "source"
    source.mkdir()
    for name in ("pyproject.toml", "README.md"):
        shutil.copy(ROOT / name, source / name)
    ignore = shutil.ignore_patterns("__pycache__", "*.pyc")
    for folder in ("tvopt_codegen", "templates"):
        shutil.copytree(ROOT / folder, source / folder, ignore=ignore)
    out = tmp_path / "wheel"
    out.mkdir()
    # Every warning shown, as pip's isolated build shows them to a user.
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
    assert build.returncode == 0, build.stderr[-2000:]
    log = build.stdout + build.stderr
    assert "BuildBackendWarning" not in log and "absent from" not in log, log[-3000:]
    (wheel,) = out.glob("*.whl")
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
