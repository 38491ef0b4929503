"""The contributor's test loop: the skip line at the end of a run (issue 48)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from .conftest import skip_summary
from .coverage_check import unexercised


def test_skips_are_counted_with_the_command_that_runs_them() -> None:
    reasons = [
        "chromium is not installed (`.ci/run` installs Debian's chromium as root)",
        "chromium is not installed (`.ci/run` installs Debian's chromium as root)",
        "could not import 'fmpy': No module named 'fmpy'",
        "a fragment the page marks as such",
        "no C compiler",
    ]
    line = skip_summary(reasons)
    assert "\n" not in line
    assert line.startswith("skipped 5: ")
    assert "2 need `apt-get install chromium" in line
    assert "1 need `make .venv/.installed" in line
    assert "1 need `apt-get install gcc`" in line
    assert line.endswith("1 by design")


def test_a_run_without_skips_prints_nothing() -> None:
    assert skip_summary([]) == ""


def test_a_module_of_which_no_line_ran_fails_the_coverage_check() -> None:
    def summary(covered: int, statements: int) -> dict[str, dict[str, int]]:
        return {"summary": {"covered_lines": covered, "num_statements": statements}}

    report = {
        "tvopt_codegen/maths/lie.py": summary(40, 50),
        "tvopt_codegen/never.py": summary(0, 12),
        "tvopt_codegen/empty.py": summary(0, 0),
        "tvopt_codegen/__main__.py": summary(0, 20),
    }
    assert unexercised(report) == ["tvopt_codegen/never.py"]


def test_what_a_test_leaves_alive_is_frozen_out_of_the_collectors_passes() -> None:
    """conftest freezes the survivors after collection and after each test's teardown
    (gc.freeze): the collector no longer rescans the run's caches; a new object is
    scanned until the hook freezes it."""
    import gc  # noqa: PLC0415

    from .conftest import pytest_runtest_teardown  # noqa: PLC0415

    assert gc.isenabled() and gc.get_freeze_count() > 0
    survivor = [object()]  # a container: the collector tracks it

    def scanned() -> bool:
        return any(found is survivor for found in gc.get_objects())

    assert scanned()
    frozen = gc.get_freeze_count()
    pytest_runtest_teardown(None, None)  # type: ignore[arg-type]
    assert not scanned() and gc.get_freeze_count() > frozen


def test_the_dearest_modules_run_first_each_in_its_own_order(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    """conftest orders the modules by their recorded seconds, dearest first, and keeps
    each module's tests together in their order (their fixtures are set up once)."""
    from . import conftest  # noqa: PLC0415

    class Item:
        def __init__(self, module: str, name: str) -> None:
            self.path, self.name, self.nodeid = Path(module), name, f"{module}::{name}"
            self.markers: list[object] = []

        def add_marker(self, marker: object) -> None:
            self.markers.append(marker)

    items = [
        Item("tests/test_a.py", "one"),
        Item("tests/test_a.py", "two"),
        Item("tests/test_b.py", "one"),
        Item("tests/test_c.py", "one"),
        Item("tests/test_c.py", "two"),
    ]
    recorded = {"tests/test_a.py::two": 0.5, "tests/test_b.py::one": 3.0}
    recorded |= {"tests/test_c.py::one": 0.4, "tests/test_c.py::two": 0.4}
    durations = tmp_path / "durations.json"
    durations.write_text(json.dumps(recorded), encoding="utf-8")
    monkeypatch.setattr(conftest, "DURATIONS", durations)
    conftest.pytest_collection_modifyitems(None, items)  # type: ignore[arg-type]
    assert [i.nodeid for i in items] == [
        "tests/test_b.py::one",
        "tests/test_c.py::one",
        "tests/test_c.py::two",
        "tests/test_a.py::one",
        "tests/test_a.py::two",
    ]
    assert [bool(i.markers) for i in items] == [True, True, True, False, True]  # slow
