"""The rough edges a new user hits: usage errors, pipes, budgets, long specs, long names."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from tvopt_codegen.errors import clip_quotes

from .conftest import ROOT, module, write_spec

INTEGRATOR = (ROOT / "tvopt_codegen" / "examples" / "integrator.toml").read_text()


def _cli(*args: str, **kwargs: object) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "tvopt_codegen", *args],
        check=False,
        capture_output=True,
        text=True,
        **kwargs,  # type: ignore[call-overload]
    )


def _with_objective(tmp_path: Path, f0: str) -> Path:
    lines = [
        f'f0 = "{f0}"' if line.startswith("f0 = ") else line for line in INTEGRATOR.splitlines()
    ]
    return write_spec(tmp_path, "\n".join(lines) + "\n")


def test_usage_errors_are_one_line_with_a_pointer_to_help() -> None:
    for args, text in (
        (("simulate",), "the following arguments are required: spec"),
        (("generate", "integrator", "--backend", "fortran"), "invalid choice: 'fortran'"),
        (("frobnicate",), "invalid choice: 'frobnicate'"),
    ):
        done = _cli(*args)
        assert done.returncode == 2
        assert done.stderr.count("\n") == 1, done.stderr
        assert text in done.stderr and "(see tvopt-codegen" in done.stderr
        assert "--help)" in done.stderr


def test_a_closed_pipe_ends_quietly_like_a_unix_tool() -> None:
    read, write = os.pipe()
    os.close(read)
    try:
        done = subprocess.run(
            [sys.executable, "-m", "tvopt_codegen", "check", "unicycle_switch"],
            stdout=write,
            stderr=subprocess.PIPE,
            text=True,
            check=False,
        )
    finally:
        os.close(write)
    assert done.returncode == 141
    assert done.stderr == ""


def test_the_time_budget_interrupts_a_long_sympy_call(tmp_path: Path) -> None:
    # A product of 50 sums in f0: minutes of sympy work between two budget checks.
    product = "*".join(f"(y1 + {k}*y2 + {k})" for k in range(1, 51))
    spec = _with_objective(tmp_path, f"0.5*(y1 - o1)**2 + 0.5*(y2 - o2)**2 + 1e-30*{product}")
    start = time.perf_counter()
    done = _cli("check", str(spec), "--max-seconds", "2")
    elapsed = time.perf_counter() - start
    assert done.returncode == 6, done.stderr
    assert "derivation stage '" in done.stderr and "took longer than 2 s" in done.stderr
    assert done.stderr.count("\n") == 1
    assert elapsed < 2 + 6  # the budget, plus start-up, within a few seconds


def test_a_long_flat_objective_is_not_deep(tmp_path: Path) -> None:
    # 400 terms written out by a program: a sum is not nesting.
    terms = " + ".join(f"{k}e-4*(y1 - o1)**2 + {k}e-4*w*(y2 - o2)**2" for k in range(1, 201))
    spec = _with_objective(tmp_path, terms)
    done = _cli("check", str(spec))
    assert done.returncode == 0, done.stderr
    done = _cli("generate", str(spec), "--out", str(tmp_path / "out"), "--quiet")
    assert done.returncode == 0, done.stderr


def test_long_names_are_quoted_short(tmp_path: Path) -> None:
    name = "x" * 10_000
    spec = _with_objective(tmp_path, f"(y1 - {name})**2 + y2**2")
    done = _cli("check", str(spec))
    assert done.returncode == 2
    assert len(done.stderr) < 300, done.stderr
    assert f"unknown name '{'x' * 57}...'" in done.stderr
    assert clip_quotes("a 'short' name") == "a 'short' name"


def test_zero_columns_give_empty_results_in_the_numpy_backend() -> None:
    mod = module("unicycle_switch")
    n, m = len(mod.STATE_NAMES), len(mod.OUTPUT_NAMES)
    empty = np.zeros((n, 0))
    assert mod.control(0.5, empty).shape == (len(mod.INPUT_NAMES), 0)
    assert mod.rhs(0.5, empty).shape == (n, 0)
    assert mod.optimality_error(0.5, empty).shape == (mod.K, m, 0)
    assert mod.objective(0.5, np.zeros((m, 0))).shape == (0,)
    assert mod.gradient(0.5, np.zeros((m, 0))).shape == (m, 0)
    assert mod.hessian(0.5, np.zeros((m, 0))).shape == (m, m, 0)
