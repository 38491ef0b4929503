"""The wheel carries the templates and bundled examples, so an installed user can run."""

from __future__ import annotations

import os
import subprocess
import sys
import zipfile
from pathlib import Path

from .conftest import ROOT


def test_installed_wheel_generates_a_bundled_example(tmp_path: Path) -> None:
    wheels = tmp_path / "wheels"
    subprocess.run(
        [
            sys.executable,
            "-m",
            "pip",
            "wheel",
            "--quiet",
            "--no-deps",
            "-w",
            str(wheels),
            str(ROOT),
        ],
        check=True,
        capture_output=True,
    )
    (wheel,) = wheels.glob("tvopt_codegen-*.whl")
    names = set(zipfile.ZipFile(wheel).namelist())
    assert "tvopt_codegen/templates/python/controller.py.jinja" in names
    assert "tvopt_codegen/examples/unicycle_switch.toml" in names
    assert "tvopt_codegen/templates/c/controller.c.jinja" in names
    assert "tvopt_codegen/templates/report/report.html.jinja" in names
    # Every template of every backend, found by glob (pyproject names no folder).
    shipped = {
        f"tvopt_codegen/templates/{p.relative_to(ROOT / 'templates').as_posix()}"
        for p in (ROOT / "templates").rglob("*.jinja")
    }
    assert shipped <= names
    target = tmp_path / "site"
    subprocess.run(
        [
            sys.executable,
            "-m",
            "pip",
            "install",
            "--quiet",
            "--no-deps",
            "--target",
            str(target),
            str(wheel),
        ],
        check=True,
        capture_output=True,
    )
    env = dict(os.environ, PYTHONPATH=str(target))
    where = subprocess.run(
        [sys.executable, "-c", "import tvopt_codegen; print(tvopt_codegen.__file__)"],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        check=True,
    )
    assert where.stdout.startswith(str(target))  # the wheel, not the checkout
    out = tmp_path / "out"
    subprocess.run(
        [
            sys.executable,
            "-m",
            "tvopt_codegen",
            "generate",
            "unicycle_switch",
            "--out",
            str(out),
            "--quiet",
        ],
        cwd=tmp_path,
        env=env,
        check=True,
    )
    assert (out / "unicycle_switch.py").read_bytes() == (
        ROOT / "generated" / "unicycle_switch.py"
    ).read_bytes()
