"""Time-varying inequality constraints: the barrier homotopy and its certificate."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from tvopt_codegen.cli import main
from tvopt_codegen.derivation import derive
from tvopt_codegen.errors import EXIT_ASSUMPTION, EXIT_BAD_SPEC
from tvopt_codegen.lowering.ir import lower
from tvopt_codegen.simulation import load_controller, resolve_options, simulate
from tvopt_codegen.spec import load_spec

from .conftest import ROOT, derivation, module, write_spec

UNICYCLE = (ROOT / "tvopt_codegen" / "examples" / "unicycle_switch.toml").read_text()


def _with_constraints(tmp_path: Path, table: str, name: str = "spec.toml") -> Path:
    text = UNICYCLE.replace('name = "unicycle_switch"', 'name = "constrained"')
    return write_spec(tmp_path, text + "\n[constraints]\n" + table + "\n", name)


def test_the_corridor_team_is_certified() -> None:
    d = derivation("two_unicycles_corridor")
    result = simulate(d, module("two_unicycles_corridor"), resolve_options(d))
    assert result.passed, result.failures
    check = result.constraints
    assert check is not None
    # No instant on or past a barrier, and the ceilings are active at the end.
    assert float(check.margins.min()) > 0
    finals = dict(check.final)
    assert -0.05 < finals["ceiling_b"] <= 0 and finals["floor_a"] < -2
    # The distance to the independent constrained minimiser within the derived bound,
    # at every checked time.
    assert np.all(check.distance <= check.bound + 1e-6), (check.distance, check.bound)
    # The objects climb out of the corridor: tracking them is not what the law does.
    assert result.outputs[1, -1] <= -2 + 0.05 * 20 + 1e-12


def test_far_away_constraints_change_the_law_by_the_barriers_influence_alone(
    tmp_path: Path,
) -> None:
    """A ceiling 100 away: the law differs from the unconstrained one by O(mu / 100)."""
    spec = load_spec(_with_constraints(tmp_path, 'far = "y1 <= 100"'))
    constrained = load_controller(lower(derive(spec)), "python")
    free = module("unicycle_switch")
    state = np.array(free.DEFAULT_STATE)
    for t in (0.0, 2.0, 8.0, 20.0):
        mu = 1e-4 + (1.0 - 1e-4) * np.exp(-t)
        gap = np.abs(constrained.control(t, state) - free.control(t, state))
        scale = 1.0 + np.abs(free.control(t, state))
        # grad of the barrier mu/(100 - y1) ~ mu/105 and its derivatives: far below mu.
        assert np.all(gap <= 0.05 * mu * scale), (t, gap, mu)


@pytest.mark.parametrize(
    ("table", "message"),
    [
        ('c = "y1 <= 1 <= 2"', "a chained comparison"),
        ('c = "y1 != 2"', "!= is not a constraint"),
        ('c = "y1 < 2"', "a strict < is not supported: use <="),
        ('c = "x1 <= 2"', "state 'x1' may not appear here: constraints are functions of"),
        ('c = "v <= 2"', "input 'v' may not appear here"),
        ('c = "y1 + 2"', "expected a comparison"),
    ],
)
def test_bad_constraints_are_one_line_errors(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], table: str, message: str
) -> None:
    spec = _with_constraints(tmp_path, table)
    assert main(["check", str(spec)]) == EXIT_BAD_SPEC
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and message in lines[0] and "constraints.c" in lines[0], lines


def test_a_comparison_outside_constraints_says_where_they_belong(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    spec = write_spec(tmp_path, UNICYCLE.replace('f0 = "S*(', 'f0 = "(y1 <= 2) + S*('))
    assert main(["check", str(spec)]) == EXIT_BAD_SPEC
    err = capsys.readouterr().err
    assert "comparisons are not allowed in expressions (a constraint goes in [constraints])" in err


def test_nonconvex_and_infeasible_constraints_are_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # Outside a disc: not convex in y. Refused, unless allowed (then a warning).
    outside = _with_constraints(tmp_path, 'away = "y1**2 + y2**2 >= 1"', "disc.toml")
    assert main(["check", str(outside)]) == EXIT_ASSUMPTION
    assert "constraints.away: not convex in the outputs" in capsys.readouterr().err
    allowed = _with_constraints(
        tmp_path, 'allow_nonconvex = true\naway = "y1**2 + y2**2 >= 1"', "allowed.toml"
    )
    assert main(["check", str(allowed)]) == 0
    assert "the certificate is local only" in capsys.readouterr().err
    # A ceiling below a floor at the end of the horizon: nothing satisfies both.
    squeeze = _with_constraints(
        tmp_path, 'low = "y1 <= 10 - t"\nhigh = "y1 >= -5 + t"', "squeeze.toml"
    )
    assert main(["check", str(squeeze)]) == EXIT_ASSUMPTION
    err = capsys.readouterr().err
    assert "constraints: infeasible from t = 7.5 to the horizon's end t = 20" in err, err


def test_an_infeasible_start_is_allowed_by_the_slack(tmp_path: Path) -> None:
    # y1 starts at -5, above the ceiling -6 + t/4 at t = 0: the slack starts above the
    # violation and decays, and the run never touches s - g = 0.
    spec = load_spec(
        _with_constraints(
            tmp_path, 'ceiling = "y1 <= -6 + 0.25*t"\n[constraints.barrier]\nrate = 0.5'
        )
    )
    d = derive(spec)
    assert float(d.model.slack.subs(d.model.t, 0)) == pytest.approx(2.0 * 1.0 + 0.1)
    result = simulate(d, load_controller(lower(d), "python"), resolve_options(d))
    assert result.passed, result.failures
    assert float(result.constraints.margins.min()) > 0


def test_check_and_report_show_the_constrained_problem(
    capsys: pytest.CaptureFixture[str],
) -> None:
    from tvopt_codegen.report import render_report

    assert main(["check", "two_unicycles_corridor"]) == 0
    out = capsys.readouterr().out
    assert "constraints: ceiling_a: qa <= -2 + 0.05*t;" in out
    assert "kept by the barrier objective B = f0 - mu(t) sum log(s(t) - g_i)" in out
    d = derivation("two_unicycles_corridor")
    text = render_report(d, lower(d), None, ("md",))["two_unicycles_corridor_report.md"]
    assert "Constraints g_i(y, t) &lt;= 0, kept by an interior-point homotopy" in text
    assert "| floor_b | qb &gt;= -4.5 + 0.05*t |" in text
