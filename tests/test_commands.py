"""The command layer: the table of commands, the shared run options, the exit codes."""

from __future__ import annotations

import argparse
import re
import types

import pytest

from tvopt_codegen import cli
from tvopt_codegen.cli import main
from tvopt_codegen.errors import EXIT_BAD_SPEC, EXIT_CODES, SpecError
from tvopt_codegen.limits import RUN_OPTIONS

from .conftest import ROOT


def _help(capsys: pytest.CaptureFixture[str], *argv: str) -> str:
    """What ``tvopt-codegen ARGV --help`` prints, on one line."""
    with pytest.raises(SystemExit) as stop:
        main([*argv, "--help"])
    assert stop.value.code == 0
    return " ".join(capsys.readouterr().out.split())


def _readme_exit_codes() -> dict[int, str]:
    """The README's table of exit codes: each code (``130 / 143``: two) and its meaning."""
    text = (ROOT / "README.md").read_text()
    section = text.split("\n## Exit codes\n", 1)[1].split("\n## ", 1)[0]
    codes: dict[int, str] = {}
    for line in section.splitlines():
        cells = [cell.strip() for cell in line.strip().strip("|").split("|")]
        if len(cells) >= 2 and re.fullmatch(r"\d+( / \d+)*", cells[0]):
            for code in cells[0].split(" / "):
                codes[int(code)] = cells[1]
    return codes


def test_the_readme_documents_every_exit_code_and_no_other() -> None:
    documented = _readme_exit_codes()
    assert sorted(documented) == sorted(EXIT_CODES)
    assert "success" in documented[0] and "budget" in documented[6]


def test_help_lists_every_command_and_every_exit_code(capsys: pytest.CaptureFixture[str]) -> None:
    shown = _help(capsys)
    for name, command in cli.COMMANDS.items():
        assert f"{name} {' '.join(command.HELP.split())}" in shown
    assert ", ".join(f"{code} {meaning}" for code, meaning in EXIT_CODES.items()) in shown


def test_a_new_command_is_one_module_and_one_table_line(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    toy = types.ModuleType("toy")
    toy.HELP = "say hello to a name"  # type: ignore[attr-defined]

    def build(parser: argparse.ArgumentParser) -> None:
        parser.add_argument("name")
        parser.add_argument("--shout", action="store_true")

    def run(args: argparse.Namespace) -> int:
        if not args.name:
            raise SpecError("command line", "NAME", "is empty")
        print(f"hello {args.name}{'!' if args.shout else ''}")
        return 0

    toy.build = build  # type: ignore[attr-defined]
    toy.run = run  # type: ignore[attr-defined]
    monkeypatch.setitem(cli.COMMANDS, "toy", toy)
    assert "toy say hello to a name" in _help(capsys)
    assert "--shout" in _help(capsys, "toy")
    assert main(["toy", "world", "--shout"]) == 0
    assert capsys.readouterr().out == "hello world!\n"
    # Its errors are mapped like any command's: one line, the documented code.
    assert main(["toy", ""]) == EXIT_BAD_SPEC
    assert capsys.readouterr().err == "tvopt-codegen: error: command line: NAME: is empty\n"


@pytest.mark.parametrize(
    ("command", "new"),
    [
        (["simulate", "integrator"], "--reference-noise"),
        (["sweep", "integrator"], "--measurement-noise"),
    ],
)
@pytest.mark.parametrize("spelling", [["--noise", "0.1"], ["--noise=0.1"], ["--noise"]])
def test_the_old_noise_option_is_refused_naming_the_new_one(
    command: list[str], new: str, spelling: list[str], capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(SystemExit) as stop:
        main([*command, *spelling, "--out", "nowhere"])
    assert stop.value.code == EXIT_BAD_SPEC
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"--noise is now {new} " in err
    # The old spelling is no option of --help's.
    shown = _help(capsys, command[0])
    assert new in shown and "--noise" not in shown.replace(new, "")


@pytest.mark.parametrize(
    ("name", "value", "problem"),
    [
        ("rtol", 0.0, "must be positive and finite"),
        ("atol", float("inf"), "must be positive and finite"),
        ("points", 2, "must be between 3 and 10001"),
        ("points", 10_002, "must be between 3 and 10001"),
        ("t_final", 1e7, "must be positive and at most 1e+06"),
        ("seed", 2**63, "must be between 0 and 2**63 - 1"),
        ("reference_noise", -1.0, "must be zero or positive and finite"),
        ("measurement_noise", float("nan"), "must be zero or positive and finite"),
        ("max_seconds", 0.0, "must be positive"),
        ("checkpoint_seconds", 86_401.0, "must be between 0 and 86400"),
    ],
)
def test_each_run_option_has_one_bound(name: str, value: float, problem: str) -> None:
    option = RUN_OPTIONS[name]
    assert option.problem(value) == problem
    assert option.default is None or option.problem(option.default) is None


@pytest.mark.parametrize("command", ["simulate", "sweep"])
@pytest.mark.parametrize("flag", ["--rtol", "--atol", "--points", "--seed"])
def test_a_shared_option_means_the_same_in_every_command(
    command: str, flag: str, capsys: pytest.CaptureFixture[str]
) -> None:
    """The same default and help in simulate and sweep, and the same one-line refusal."""
    option = next(o for o in RUN_OPTIONS.values() if o.flag == flag)
    shown = _help(capsys, command)
    assert " ".join(f"{option.help} (default {option.default:g})".split()) in shown
    extra = ["--samples", "1"] if command == "sweep" else []
    assert main([command, "integrator", flag, "-1", "--out", "nowhere", *extra]) == EXIT_BAD_SPEC
    err = capsys.readouterr().err
    assert err == f"tvopt-codegen: error: command line: {flag}: {option.bounds}\n"


def test_the_how_to_adds_a_command_that_runs(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    # docs/adding-a-command.md: its module, from the page's text, and its table line.
    page = (ROOT / "docs" / "adding-a-command.md").read_text(encoding="utf-8")
    module_text, table_line = re.findall(r"```python\n(.*?)```", page, re.S)
    degree = types.ModuleType("degree")
    exec(compile(module_text, "docs/adding-a-command.md", "exec"), degree.__dict__)  # noqa: S102
    namespace = {"COMMANDS": dict(cli.COMMANDS), "degree": degree}
    exec(table_line, namespace)  # noqa: S102
    monkeypatch.setattr(cli, "COMMANDS", namespace["COMMANDS"])
    assert "degree print each output's relative degree" in _help(capsys)
    assert main(["degree", "unicycle_switch", "--progress", "never"]) == 0
    assert capsys.readouterr().out == "y1: 2\ny2: 2\n"
    assert main(["degree", "no_such_example"]) == EXIT_BAD_SPEC
    assert capsys.readouterr().err.count("\n") == 1
