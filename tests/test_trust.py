"""What a user trusts: errors that stay one line and say what to fix (issue 31)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from tvopt_codegen.cli import main
from tvopt_codegen.errors import EXIT_BAD_SPEC, EXIT_BUDGET, one_line

from .conftest import ROOT

BARRIER_SPEC = """name = "walled"
[system]
states = ["px", "py"]
inputs = ["ux", "uy"]
[system.dynamics]
px = "ux"
py = "uy"
[system.outputs]
x_out = "px"
y_out = "py"
[objective]
f0 = "(x_out - 1)**2 + (y_out - 2)**2"
[constraints]
wall = "x_out <= 3"
[constraints.{table}]
{key} = 1e-3
[error_dynamics]
poles = [-1.0]
"""


@pytest.mark.parametrize(
    ("table", "key", "field", "message"),
    [
        ("barier", "final_weight", "constraints.barier", "did you mean 'barrier'?"),
        (
            "barrier",
            "final_wieght",
            "constraints.barrier.final_wieght",
            "did you mean 'final_weight'?",
        ),
        (
            "walls",
            "final_weight",
            "constraints.walls",
            "a table, where a constraint is a comparison",
        ),
    ],
)
def test_a_misspelt_key_gets_the_key_it_was_meant_to_be(
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    table: str,
    key: str,
    field: str,
    message: str,
) -> None:
    spec = tmp_path / "walled.toml"
    spec.write_text(BARRIER_SPEC.format(table=table, key=key))
    assert main(["check", str(spec)]) == EXIT_BAD_SPEC
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) == 1
    assert f"{spec}: {field}: " in lines[0] and message in lines[0], lines[0]
    if table == "walls":
        assert "did you mean" not in lines[0]  # nothing close: no guess


@pytest.mark.parametrize("seconds", ["1e-9", "1e-6", "1e-4", "3e-3"])
def test_any_budget_however_small_ends_in_one_line(seconds: str) -> None:
    # In a process of its own: the budget's timer is a real signal.
    for _ in range(3):
        done = subprocess.run(
            [
                sys.executable,
                "-m",
                "tvopt_codegen",
                "check",
                "unicycle_switch",
                "--max-seconds",
                seconds,
            ],
            capture_output=True,
            text=True,
            check=False,
        )
        assert done.returncode == EXIT_BUDGET, done.stderr
        assert len(done.stderr.splitlines()) == 1, done.stderr
        assert "took longer than" in done.stderr


def test_a_path_with_a_newline_is_printed_escaped(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    folder = tmp_path / "a\nb"
    folder.mkdir()
    spec = folder / "tab\there.toml"
    spec.write_text('name = "bad"\n[system]\nstates = ["x"]\n')
    assert main(["check", str(spec)]) == EXIT_BAD_SPEC
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "a\\nb/tab\\there.toml" in err, err
    blocker = tmp_path / "a\nb" / "file"
    blocker.write_text("")
    code = main(
        [
            "generate",
            str(ROOT / "tvopt_codegen" / "examples" / "integrator.toml"),
            "--out",
            str(blocker / "sub"),
        ]
    )
    err = capsys.readouterr().err
    assert code != 0 and err.count("\n") == 1 and "a\\nb/file" in err, err


def test_one_line_escapes_what_would_break_a_line_and_keeps_the_rest() -> None:
    assert one_line("a\nb\rc\td\x00e\x1bf\u2028g") == "a\\nb\\rc\\td\\x00e\\x1bf\\u2028g"
    assert one_line("café → ok 'quoted'") == "café → ok 'quoted'"
