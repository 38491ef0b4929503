"""The benches' cold-process measurement (benchmarks/cold.py): each process's own figures."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path
from types import ModuleType

import pytest

pytestmark = pytest.mark.skipif(sys.platform != "linux", reason="Linux's ru_maxrss semantics")


def _cold() -> ModuleType:
    path = Path(__file__).resolve().parents[1] / "benchmarks" / "cold.py"
    spec = importlib.util.spec_from_file_location("bench_cold", path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses looks its module up
    spec.loader.exec_module(module)
    return module


def _touched(megabytes: int) -> bytearray:
    block = bytearray(megabytes << 20)
    block[::4096] = b"\x01" * len(block[::4096])  # resident, not just reserved
    return block


def test_a_process_reports_its_own_peak_not_its_parents() -> None:
    """Forked from a 400 MB process, a bare interpreter still reports tens of MB; one
    that touches 200 MB reports at least that. Started by this process directly, Linux
    would report the bare one at 400 MB or more."""
    cold = _cold()
    big = _touched(400)
    bare = cold.cold_run([sys.executable, "-c", "pass"], timeout=60)
    grown = cold.cold_run(
        [sys.executable, "-c", "b = bytearray(200 << 20); b[::4096] = b'1' * len(b[::4096])"],
        timeout=60,
    )
    assert len(big) == 400 << 20
    assert bare.peak_mb < 100, bare
    assert 200 <= grown.peak_mb < 400, grown
    assert 0 < bare.wall < grown.wall


def test_output_failure_and_timeout() -> None:
    cold = _cold()
    said = cold.cold_run(
        [sys.executable, "-c", "import sys; print('out'); print('err', file=sys.stderr)"], 60
    )
    assert (said.stdout, said.stderr) == ("out\n", "err\n")
    with pytest.raises(RuntimeError, match=r"failed \(3\): .*boom"):
        cold.cold_run(
            [sys.executable, "-c", "import sys; print('boom', file=sys.stderr); sys.exit(3)"], 60
        )
    with pytest.raises(RuntimeError, match="timed out after 0.5 s"):
        cold.cold_run([sys.executable, "-c", "import time; time.sleep(30)"], 0.5)
