"""The command layer: the table of commands, the shared run options, the exit codes."""

from __future__ import annotations

import pytest

from tvopt_codegen.cli import main
from tvopt_codegen.errors import EXIT_BAD_SPEC
from tvopt_codegen.limits import RUN_OPTIONS


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
    with pytest.raises(SystemExit):
        main([command[0], "--help"])
    shown = capsys.readouterr().out
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
    with pytest.raises(SystemExit):
        main([command, "--help"])
    shown = " ".join(capsys.readouterr().out.split())
    assert " ".join(f"{option.help} (default {option.default:g})".split()) in shown
    extra = ["--samples", "1"] if command == "sweep" else []
    assert main([command, "integrator", flag, "-1", "--out", "nowhere", *extra]) == EXIT_BAD_SPEC
    err = capsys.readouterr().err
    assert err == f"tvopt-codegen: error: command line: {flag}: {option.bounds}\n"
