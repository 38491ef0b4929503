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


def test_messages_name_values_in_words_not_python_reprs(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    text = (ROOT / "tvopt_codegen" / "examples" / "unicycle_switch.toml").read_text()
    spec = tmp_path / "no_extension.toml"
    spec.write_text(text.replace("[extension]\nintegrate = { v = 1 }\n", ""))
    assert main(["check", str(spec)]) == 3
    err = capsys.readouterr().err
    assert "relative degrees y1 = 1, y2 = 1" in err, err
    assert "{" not in err.split("prolong")[0], err


def test_the_examples_listing_is_aligned_whole_sentences_without_internal_labels() -> None:
    done = subprocess.run(
        [sys.executable, "-m", "tvopt_codegen", "examples"],
        capture_output=True,
        text=True,
        check=True,
    )
    lines = done.stdout.splitlines()
    names = [line.split()[0] for line in lines]
    assert "two_unicycles_barrier_refs" in names and len(lines) == len(names)
    starts = {
        len(line) - len(line[len(name) :].lstrip()) for line, name in zip(lines, names, strict=True)
    }
    assert len(starts) == 1  # one column of summaries, past the longest name
    for line in lines:
        assert line.endswith("."), line  # a whole sentence, not a cut line
        assert "issue" not in line and "{" not in line, line


def test_a_summary_is_the_first_sentence_whatever_its_abbreviations() -> None:
    from tvopt_codegen.spec.files import first_sentence

    assert (
        first_sentence("Two robots (paper, Sec. V-B). f0 = ...") == "Two robots (paper, Sec. V-B)."
    )
    assert first_sentence("The team of Fig. 3 kept\nin a corridor. More.") == (
        "The team of Fig. 3 kept in a corridor."
    )
    assert first_sentence("No full stop at all") == "No full stop at all"


def test_the_report_keeps_phi_for_the_coordinates_and_b_for_the_barrier_objective(
    tmp_path: Path,
) -> None:
    assert main(["report", "two_unicycles_corridor", "--out", str(tmp_path)]) == 0
    text = (tmp_path / "two_unicycles_corridor_report.md").read_text()
    assert "minimiser of B = f0 - mu(t)" in text
    assert "Phi = f0" not in text and "Coordinates Phi" in text
