"""The command line runs NumPy's BLAS on one thread unless the user chose a number."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

PROBE = """
import os, sys
from tvopt_codegen.__main__ import one_blas_thread
one_blas_thread()
import numpy as np
a = np.random.default_rng(0).random((400, 400))
a @ a  # OpenBLAS starts its threads at its first large product
print(os.environ["OPENBLAS_NUM_THREADS"], len(os.listdir("/proc/self/task")))
"""


@pytest.mark.parametrize(("chosen", "variable", "threads"), [(None, "1", 1), ("2", "2", 2)])
def test_one_blas_thread_unless_the_user_chose(
    chosen: str | None, variable: str, threads: int
) -> None:
    if not os.path.isdir("/proc/self/task") or (os.cpu_count() or 1) < 2:
        pytest.skip("needs Linux's /proc and two cores to tell one thread from two")
    env = {
        k: v for k, v in os.environ.items() if k not in ("OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")
    }
    if chosen is not None:
        env["OPENBLAS_NUM_THREADS"] = chosen
    done = subprocess.run(
        [sys.executable, "-c", PROBE], env=env, capture_output=True, text=True, check=True
    )
    assert done.stdout.split() == [variable, str(threads)]


def test_the_console_entry_asks_for_one_thread_before_the_command_runs() -> None:
    probe = (
        "import os, tvopt_codegen.cli as cli\n"
        "cli.main = lambda *a: print(os.environ.get('OPENBLAS_NUM_THREADS'),"
        " os.environ.get('MKL_NUM_THREADS')) or 0\n"
        "from tvopt_codegen.__main__ import entry\n"
        "entry()\n"
    )
    env = {
        k: v for k, v in os.environ.items() if k not in ("OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")
    }
    done = subprocess.run(
        [sys.executable, "-c", probe], env=env, capture_output=True, text=True, check=True
    )
    assert done.stdout.split() == ["1", "1"]
