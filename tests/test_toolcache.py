"""The suite's kept tool runs (``tests/toolcache.py``): a kept verdict is the tool's verdict.

A run is given back only when the program, its arguments (paths by their role) and every
byte it reads are the same; what it printed and wrote comes back naming this run's
folders. A stand-in program that logs each of its runs shows which runs were real.
"""

from __future__ import annotations

import os
import shutil
import stat
from pathlib import Path

import pytest

from .toolcache import kept_run

#: A compiler's stand-in: logs that it ran, then prints a warning naming its input when
#: the input says WARN, and writes its output (which names the input too).
TOOL = """#!/bin/sh
echo ran >> "$LOG"
if grep -q WARN "$1"; then echo "$1:1: warning: said WARN" >&2; exit 1; fi
echo "compiled from $1" > "$2"
"""


@pytest.fixture
def tool(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> tuple[Path, Path]:
    """The stand-in on the PATH (as ``cc-standin``), and its log."""
    bin_folder = tmp_path / "bin"
    bin_folder.mkdir()
    program = bin_folder / "cc-standin"
    program.write_text(TOOL, encoding="utf-8")
    program.chmod(program.stat().st_mode | stat.S_IXUSR)
    log = tmp_path / "log"
    monkeypatch.setenv("PATH", f"{bin_folder}{os.pathsep}{os.environ['PATH']}")
    monkeypatch.setenv("LOG", str(log))
    return program, log


def _runs(log: Path) -> int:
    return len(log.read_text(encoding="utf-8").splitlines()) if log.exists() else 0


def _compile(folder: Path, text: str, cache: Path | None) -> tuple[int, str, str]:
    """Compile ``text`` in a new ``folder``: the exit code, the error text, the output."""
    folder.mkdir()
    source, out = folder / "x.c", folder / "x.s"
    source.write_text(text, encoding="utf-8")
    done = kept_run(
        ["cc-standin", str(source), str(out)], reads=[source], writes=[out], cache=cache
    )
    return done.returncode, done.stderr, out.read_text(encoding="utf-8") if out.exists() else ""


def test_the_same_bytes_run_once_and_come_back_naming_this_runs_folder(
    tool: tuple[Path, Path], tmp_path: Path
) -> None:
    _, log = tool
    cache = tmp_path / "cache"
    first = _compile(tmp_path / "run1", "int x;\n", cache)
    assert first == (0, "", f"compiled from {tmp_path / 'run1' / 'x.c'}\n")
    # Another run's folder, the same source: kept, and its output names the new folder.
    second = _compile(tmp_path / "run2", "int x;\n", cache)
    assert second == (0, "", f"compiled from {tmp_path / 'run2' / 'x.c'}\n")
    assert _runs(log) == 1
    # Without a cache folder the tool always runs.
    _compile(tmp_path / "run3", "int x;\n", None)
    assert _runs(log) == 2


def test_a_changed_byte_runs_the_tool_again_and_a_kept_failure_fails_alike(
    tool: tuple[Path, Path], tmp_path: Path
) -> None:
    _, log = tool
    cache = tmp_path / "cache"
    assert _compile(tmp_path / "run1", "int x;\n", cache)[0] == 0
    code, error, _ = _compile(tmp_path / "run2", "int x; /* WARN */\n", cache)
    assert code == 1 and error == f"{tmp_path / 'run2' / 'x.c'}:1: warning: said WARN\n"
    assert _runs(log) == 2
    code, error, out = _compile(tmp_path / "run3", "int x; /* WARN */\n", cache)
    assert (code, out) == (1, "")
    assert error == f"{tmp_path / 'run3' / 'x.c'}:1: warning: said WARN\n"
    assert _runs(log) == 2


def test_a_changed_program_or_argument_runs_again(tool: tuple[Path, Path], tmp_path: Path) -> None:
    program, log = tool
    cache = tmp_path / "cache"
    _compile(tmp_path / "run1", "int x;\n", cache)
    # An upgraded tool (its file rewritten): a new key.
    program.write_text(TOOL + "# 2\n", encoding="utf-8")
    _compile(tmp_path / "run2", "int x;\n", cache)
    assert _runs(log) == 2
    # One more argument: a new key.
    folder = tmp_path / "run3"
    folder.mkdir()
    source = folder / "x.c"
    source.write_text("int x;\n", encoding="utf-8")
    kept_run(
        ["cc-standin", str(source), str(folder / "x.s"), "-O3"],
        reads=[source],
        writes=[folder / "x.s"],
        cache=cache,
    )
    assert _runs(log) == 3


def test_real_gcc_warnings_are_kept_with_this_runs_paths(tmp_path: Path) -> None:
    gcc = shutil.which("gcc")
    if gcc is None:
        pytest.skip("gcc is not installed: apt-get install gcc")
    cache = tmp_path / "cache"
    printed = []
    for run in ("a", "b"):
        folder = tmp_path / run
        folder.mkdir()
        source = folder / "w.c"
        source.write_text("int f(int a) { int unused; return a; }\n", encoding="utf-8")
        assembly = folder / "w.s"
        done = kept_run(
            ["gcc", "-Wall", "-Werror", "-S", str(source), "-o", str(assembly)],
            reads=[source],
            writes=[assembly],
            cache=cache,
        )
        assert done.returncode != 0 and not assembly.exists()
        printed.append(done.stderr)
    assert str(tmp_path / "a" / "w.c") in printed[0] and str(tmp_path / "a") not in printed[1]
    assert printed[1] == printed[0].replace(str(tmp_path / "a"), str(tmp_path / "b"))
    assert len(list((cache / "tools").iterdir())) == 1


def test_an_unusable_cache_folder_only_costs_the_tools_time(
    tool: tuple[Path, Path], tmp_path: Path
) -> None:
    """A cache that cannot be written (a file where its folder should be: a read-only
    checkout, a full disk alike) runs the tool every time, with its own verdict."""
    _, log = tool
    cache = tmp_path / "cache"
    cache.write_text("not a folder", encoding="utf-8")
    for run in ("run1", "run2"):
        assert _compile(tmp_path / run, "int x;\n", cache)[::2] == (
            0,
            f"compiled from {tmp_path / run / 'x.c'}\n",
        )
    code, error, _ = _compile(tmp_path / "run3", "int x; /* WARN */\n", cache)
    assert code == 1 and "said WARN" in error
    assert _runs(log) == 3


def test_a_run_that_succeeds_without_writing_a_named_file_is_an_error(
    tool: tuple[Path, Path], tmp_path: Path
) -> None:
    """Nothing is kept for it: a caller would read a file the tool never made."""
    source, out, other = tmp_path / "x.c", tmp_path / "x.s", tmp_path / "x.ci"
    source.write_text("int x;\n", encoding="utf-8")
    cache = tmp_path / "cache"
    with pytest.raises(FileNotFoundError, match=r"succeeded without writing .*x\.ci"):
        kept_run(
            ["cc-standin", str(source), str(out)],
            reads=[source],
            writes=[out, other],
            cache=cache,
        )
    assert not (cache / "tools").exists()
