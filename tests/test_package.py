"""The wheel carries the templates and bundled examples, so an installed user can run."""

from __future__ import annotations

import importlib.metadata
import os
import shutil
import subprocess
import sys
import tomllib
import zipfile
from pathlib import Path

from packaging.requirements import Requirement

from tvopt_codegen import symbolic as sx
from tvopt_codegen.limits import ENGINE_VARIABLE

from .conftest import ROOT, run_main


def _clean_source(tmp_path: Path) -> Path:
    """What the wheel is built from, copied without the checkout's ignored build/ folder,
    whose stale copies of moved modules setuptools would ship."""
    source = tmp_path / "source"
    ignore = shutil.ignore_patterns("__pycache__", "*.pyc")
    for name in ("tvopt_codegen", "templates"):
        shutil.copytree(ROOT / name, source / name, ignore=ignore)
    for name in ("pyproject.toml", "README.md", "LICENSE"):
        if (ROOT / name).exists():
            shutil.copy2(ROOT / name, source / name)
    return source


def _build_requirements_are_installed() -> None:
    """Every requirement of pyproject's ``[build-system]`` is met by this environment's
    own packages, so the build below (without pip's isolated build environment) runs on
    the declared backend: an isolated build would install setuptools afresh from the
    index on every run, a download that took most of this test's time."""
    build = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))["build-system"]
    assert build["build-backend"] == "setuptools.build_meta"
    for line in build["requires"]:
        requirement = Requirement(line)
        installed = importlib.metadata.version(requirement.name)
        assert requirement.specifier.contains(installed, prereleases=True), (line, installed)


def test_installed_wheel_generates_a_bundled_example(tmp_path: Path) -> None:
    _build_requirements_are_installed()
    wheels = tmp_path / "wheels"
    subprocess.run(
        [
            sys.executable,
            "-m",
            "pip",
            "wheel",
            "--quiet",
            "--no-deps",
            "--no-build-isolation",
            "-w",
            str(wheels),
            str(_clean_source(tmp_path)),
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
    # Every module of the package, and no other: pyproject lists the packages one by one,
    # and a stale build/ folder would ship modules that no longer exist.
    package = ROOT / "tvopt_codegen"
    modules = {
        f"tvopt_codegen/{p.relative_to(package).as_posix()}"
        for p in package.rglob("*.py")
        if "__pycache__" not in p.parts
    }
    shipped_modules = {n for n in names if n.startswith("tvopt_codegen/") and n.endswith(".py")}
    assert modules - shipped_modules == set(), "modules missing from the wheel"
    assert shipped_modules - modules == set(), "modules in the wheel but not in the checkout"
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
    # Both generations below on this process's engine, named: the file stamp names it.
    env = dict(os.environ, PYTHONPATH=str(target), **{ENGINE_VARIABLE: sx.ENGINE})
    where = subprocess.run(
        [sys.executable, "-c", "import tvopt_codegen; print(tvopt_codegen.__file__)"],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        check=True,
    )
    assert where.stdout.startswith(str(target))  # the wheel, not the checkout
    # The installed wheel generates what this checkout generates, byte for byte. The
    # checkout's own run, not generated/: whether generated/ is current is
    # test_generated's question, and this one would fail on any stale file there. The
    # wheel's run is a process of its own (the installed package is the subject); the
    # checkout's is this process's, which imported the checkout already.
    wheel_out, checkout_out = tmp_path / "out-wheel", tmp_path / "out-checkout"
    subprocess.run(
        [
            sys.executable,
            "-m",
            "tvopt_codegen",
            "generate",
            "unicycle_switch",
            "--out",
            str(wheel_out),
            "--quiet",
        ],
        cwd=tmp_path,
        env=env,
        check=True,
    )
    ran = run_main("generate", "unicycle_switch", "--out", str(checkout_out), "--quiet")
    assert ran.returncode == 0, ran.stderr
    made = (wheel_out / "unicycle_switch.py").read_bytes()
    assert made.startswith(b"# Generated by tvopt-codegen")
    assert f"({sx.engine_version()})".encode() in made.splitlines()[0]
    assert made == (checkout_out / "unicycle_switch.py").read_bytes()
