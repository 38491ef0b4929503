"""The package's Python API: the stages by name, and the example of docs/api.md."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

import tvopt_codegen as tc
from tvopt_codegen.errors import SpecError

from .conftest import ROOT


def test_the_stages_are_public_and_load_lazily() -> None:
    for name in (
        "load_spec",
        "spec_from_dict",
        "build_model",
        "derive",
        "lower",
        "render",
        "write_files",
        "load_controller",
        "simulate",
        "render_report",
    ):
        assert name in tc.__all__ and callable(getattr(tc, name))
    with pytest.raises(AttributeError, match="no attribute 'nope'"):
        _ = tc.nope  # type: ignore[attr-defined]
    done = subprocess.run(
        [sys.executable, "-c", "import sys, tvopt_codegen; print('sympy' in sys.modules)"],
        check=True,
        capture_output=True,
        text=True,
    )
    assert done.stdout.strip() == "False"


def test_the_api_example_runs(tmp_path: Path) -> None:
    text = (ROOT / "docs" / "api.md").read_text()
    (code,) = re.findall(r"```python\n(.*?)```", text, re.S)
    done = subprocess.run(
        [sys.executable, "-c", code],
        cwd=tmp_path,
        check=False,
        capture_output=True,
        text=True,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
    )
    assert done.returncode == 0, done.stderr
    lines = done.stdout.splitlines()
    assert lines[0] == "(2, 2) 2"
    assert lines[2].startswith("True ")
    assert (tmp_path / "api-example" / "double_integrator.py").is_file()


def test_a_mapping_spec_is_checked_like_a_file() -> None:
    spec = tc.load_spec("integrator")
    assert tc.derive(spec).dynamics.k == 1
    with pytest.raises(SpecError, match=r"<python>: system.dynamics: missing required key"):
        tc.spec_from_dict(
            {"name": "x", "system": {"states": "x1"}, "objective": {}, "error_dynamics": {}}
        )
    with pytest.raises(SpecError, match="expected a mapping"):
        tc.spec_from_dict(["not", "a", "mapping"])  # type: ignore[arg-type]
    with pytest.raises(SpecError, match="not a plain mapping"):
        tc.derive({"name": "x", "system": {"states": [float("nan")]}})
