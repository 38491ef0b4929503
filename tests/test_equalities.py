"""Equality constraints: the KKT law, its multiplier chains and its certificate."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from scipy.linalg import expm

from tvopt_codegen.cli import main
from tvopt_codegen.derivation import derive
from tvopt_codegen.errors import EXIT_ASSUMPTION, EXIT_BAD_SPEC
from tvopt_codegen.lowering.ir import lower
from tvopt_codegen.maths import hurwitz
from tvopt_codegen.simulation import kkt_path, load_controller, resolve_options, simulate
from tvopt_codegen.simulation.constraints import equalities
from tvopt_codegen.spec import load_spec
from tvopt_codegen.sweep import SweepOptions, run_sample, tail

from .conftest import ROOT, derivation, module, write_spec
from .test_controller import _both
from .test_sweep import _columns, program

ARM = "arm_on_line"
UNICYCLE = (ROOT / "tvopt_codegen" / "examples" / "unicycle_switch.toml").read_text()


def _normal(t: np.ndarray) -> np.ndarray:
    """The arm's line cos(0.1 t) px + sin(0.1 t) py = 1: its unit normal, (2, T)."""
    return np.array([np.cos(0.1 * t), np.sin(0.1 * t)])


def _projection(t: np.ndarray) -> np.ndarray:
    """The arm's constrained minimiser in closed form: the target projected on the line."""
    target = np.array([0.9 + 0.3 * np.cos(0.5 * t), 0.7 + 0.3 * np.sin(0.5 * t)])
    normal = _normal(t)
    return target - (np.sum(normal * target, axis=0) - 1.0) * normal


def _with_constraints(tmp_path: Path, table: str, name: str = "spec.toml") -> Path:
    text = UNICYCLE.replace('name = "unicycle_switch"', 'name = "equal"')
    return write_spec(tmp_path, text + "\n[constraints]\n" + table + "\n", name)


@pytest.mark.parametrize("backend", ["python", "c"])
def test_the_arm_stays_on_its_turning_line_and_is_certified(backend: str) -> None:
    d = derivation(ARM)
    result = simulate(d, load_controller(lower(d), backend), resolve_options(d))
    assert result.passed, result.failures
    assert result.deviation < 1e-8
    # y* is the target's projection on the line, found here in closed form.
    assert np.max(np.abs(result.target - _projection(result.t))) < 1e-9
    # K = [[2 I, n], [n^T, 0]] has eigenvalues 2 and 1 +- sqrt(2) for a unit normal n:
    # the certificate's sigma_min is sqrt(2) - 1 at every point.
    assert result.m_f == pytest.approx(math.sqrt(2) - 1, rel=1e-9)
    check = result.constraints
    assert check is not None and check.margins.shape == (0, len(result.t))
    a = np.sum(_normal(result.t) * result.outputs, axis=0) - 1.0
    np.testing.assert_allclose(check.equality[0], a, rtol=0, atol=1e-12)
    assert abs(dict(check.final)["on_line"]) < 1e-6
    # |a| under c e^(-alpha t) |E(0)|, and the independent SLSQP minimiser where the
    # theorem puts y*.
    envelope = result.c * np.linalg.norm(result.E[0]) * np.exp(-result.alpha * result.t)
    assert np.all(np.abs(a) <= envelope)
    assert np.all(check.distance <= check.bound + 1e-6), (check.distance, check.bound)
    assert check.distance[-1] < 1e-5


@pytest.mark.parametrize("which", [0, 1])
def test_the_law_puts_dE_dt_on_H_E_at_any_state(
    which: int, tmp_path_factory: pytest.TempPathFactory
) -> None:
    """dE/dt = H E off the run too, at random arm states and multipliers, where K is
    factored at run time (its J_a turns with t); both backends."""
    mod = _both(ARM, tmp_path_factory)[which]
    H = hurwitz.error_matrix(mod.HURWITZ_COEFFICIENTS, 3)
    rng = np.random.default_rng(18)
    step = 1e-5
    for _ in range(6):
        t = float(rng.uniform(0.0, 12.0))
        s = np.array([*rng.uniform([-1, 0.5, -1, -1], [1, 2.5, 1, 1]), *rng.normal(size=2)])
        rate = mod.rhs(t, s)
        ahead = mod.optimality_error(t + step, s + step * rate).reshape(-1)
        behind = mod.optimality_error(t - step, s - step * rate).reshape(-1)
        derivative = (ahead - behind) / (2 * step)
        expected = H @ mod.optimality_error(t, s).reshape(-1)
        np.testing.assert_allclose(derivative, expected, rtol=1e-6, atol=1e-6)


def test_the_multipliers_are_controller_states_started_by_least_squares(tmp_path: Path) -> None:
    mod = module(ARM)
    assert mod.MULTIPLIER_NAMES == ("nu_on_line",)
    assert mod.STATE_NAMES[-2:] == ("nu_on_line_0", "nu_on_line_1")
    assert mod.CONTROLLER_STATE_NAMES == ("nu_on_line_0", "nu_on_line_1")
    # nu(0) minimises |grad f0 + J_a^T nu| at the start: J_a = n(0) = (1, 0) there, so
    # nu(0) = -d f0 / d px = -2 (px(0) - ox(0)); its derivative starts at 0.
    q1, q2 = mod.DEFAULT_STATE[:2]
    px = math.cos(q1) + 0.8 * math.cos(q1 + q2)
    assert mod.DEFAULT_STATE[-2] == pytest.approx(-2.0 * (px - 1.2), rel=1e-12)
    assert mod.DEFAULT_STATE[-1] == 0.0
    # A value the spec gives is kept.
    text = (ROOT / "tvopt_codegen" / "examples" / f"{ARM}.toml").read_text()
    given = text.replace("w2 = 0.0 }", "w2 = 0.0, nu_on_line_0 = 0.25 }")
    d = derive(load_spec(write_spec(tmp_path, given)))
    assert d.closed_loop.initial_state[-2:] == (0.25, 0.0)


def test_too_many_dependent_or_curved_equalities_are_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    def check(table: str, name: str) -> tuple[int, list[str]]:
        code = main(["check", str(_with_constraints(tmp_path, table, name))])
        return code, capsys.readouterr().err.strip().splitlines()

    code, err = check('a = "y1 + y2 == 1"\nb = "2*y1 + 2*y2 == 3"', "parallel.toml")
    assert code == EXIT_ASSUMPTION and len(err) == 1
    assert "the equality constraints a, b are dependent" in err[0] and "everywhere" in err[0]
    code, err = check('a = "y1 == 1"\nb = "y2 == 1"\nc = "y1 + y2 == 3"', "three.toml")
    assert code == EXIT_ASSUMPTION and "at most 2 can be independent" in err[0]
    code, err = check('circle = "y1**2 + y2**2 == 4"', "circle.toml")
    assert code == EXIT_ASSUMPTION and len(err) == 1
    assert "constraints.circle: not affine in the outputs" in err[0]
    code, err = check('allow_nonconvex = true\ncircle = "y1**2 + y2**2 == 4"', "allowed.toml")
    assert code == 0 and "the certificate is local only" in "\n".join(err)
    code, err = check('line = "y1 == 2"\n[constraints.barrier]\nrate = 2.0', "barrier.toml")
    assert code == EXIT_BAD_SPEC and len(err) == 1
    assert "constraints.barrier: only meaningful with inequalities" in err[0]
    # On the line y1 = 2 the ceiling y1 <= 1 holds nowhere.
    code, err = check('line = "y1 == 2"\nceiling = "y1 <= 1"', "infeasible.toml")
    assert code == EXIT_ASSUMPTION and len(err) == 1
    assert "infeasible from t = 0 to the horizon's end t = 20" in err[0], err[0]
    clash = UNICYCLE.replace("[parameters]", "[parameters]\nnu_c = 1.0")
    path = write_spec(tmp_path, clash + '\n[constraints]\nc = "y1 == 2"\n', "clash.toml")
    assert main(["check", str(path)]) == EXIT_BAD_SPEC
    assert "multiplier name 'nu_c' collides with a declared name" in capsys.readouterr().err


@pytest.mark.parametrize("backend", ["python", "c"])
def test_dependence_at_run_time_is_a_status(tmp_path: Path, backend: str) -> None:
    """J_a = [[1, 0], [sin(t/10), cos(t/10)]] is singular at t = 5 pi only: derive accepts
    the spec, and the law reports the dependence there."""
    spec = load_spec(
        _with_constraints(tmp_path, 'a = "y1 == 1"\nb = "sin(0.1*t)*y1 + cos(0.1*t)*y2 == 0"')
    )
    mod = load_controller(lower(derive(spec)), backend)
    state = np.array(mod.DEFAULT_STATE)
    assert np.all(np.isfinite(mod.control(1.0, state)))
    with pytest.raises(mod.DependentConstraintsError, match="gradients are dependent") as info:
        mod.control(5 * math.pi, state)
    assert "it is where cos(t/10) = 0" in str(info.value)
    assert info.value.status == mod.STATUS_DEPENDENT_CONSTRAINTS == 6
    # A batch names the column.
    with pytest.raises(mod.DependentConstraintsError) as info:
        mod.rhs(5 * math.pi, np.stack([state, state], axis=1))
    assert info.value.index == 0


def test_inequalities_and_equalities_together(tmp_path: Path) -> None:
    """The barrier objective B under a moving line: the KKT law for B's Lagrangian,
    the barrier never reached, and y within the derived bound of SLSQP's minimiser."""
    table = (
        'line = "y1 - y2 == 1 + 0.05*t"\nceiling = "y2 <= -2.5"\n'
        "[constraints.barrier]\nfinal_weight = 1e-2"
    )
    d = derive(load_spec(_with_constraints(tmp_path, table)))
    result = simulate(d, load_controller(lower(d), "python"), resolve_options(d))
    assert result.passed, result.failures
    check = result.constraints
    assert float(check.margins.min()) > 0
    assert np.max(np.abs(check.equality[:, -1])) < 1e-6
    assert np.all(check.distance <= check.bound + 1e-6)
    # The E check covers the multiplier's rows: E has three entries per row.
    assert result.E.shape[1:] == (2, 3)
    H = hurwitz.error_matrix(d.dynamics.coefficients, 3)
    flat = result.E.reshape(len(result.t), -1)
    predicted = expm(H * result.t[-1]) @ flat[0]
    assert np.linalg.norm(flat[-1] - predicted) <= 1e-8 * np.linalg.norm(flat[0])


def test_the_sweep_follows_the_kkt_path() -> None:
    """The compiled loop's y* is the projection, its m_f sigma_min(K) and its last column
    max |a| at the outputs it recorded."""
    p = program(ARM)
    assert p.equalities == ("on_line",) and p.n_kkt == 3
    options = SweepOptions(samples=1, seed=0, t_final=12.0, rtol=1e-10, atol=1e-12, points=61)
    result = run_sample(p, options, 0, keep=True)
    rows = result.trajectory
    assert rows is not None and result.row["status"] == "ok"
    target = rows[:, _columns(p)["target"]].T
    assert np.max(np.abs(target - _projection(rows[:, 0]))) < 1e-12
    # The same path as the certificate's: its jumps and substeps, in Python.
    d = derivation(ARM)
    eq = equalities(d.model, dict(zip(d.model.params, d.model.defaults, strict=True)))
    states = [
        1 + d.closed_loop.state_names.index(chain[0]) for chain in d.closed_loop.multiplier_states
    ]
    start = np.concatenate([rows[-1, _columns(p)["y"]], rows[-1, states]])
    path = kkt_path(module(ARM), eq, rows[:, 0], start, {})
    assert np.max(np.abs(path[: len(d.spec.outputs)] - target)) < 1e-12
    np.testing.assert_allclose(tail(rows, "m_f"), math.sqrt(2) - 1, rtol=1e-9)
    y = rows[:, _columns(p)["y"]].T
    a = np.abs(np.sum(_normal(rows[:, 0]) * y, axis=0) - 1.0)
    np.testing.assert_allclose(tail(rows, "max_equality"), a, rtol=0, atol=1e-12)
    assert result.row["final_equality"] == pytest.approx(a[-1], abs=1e-15)
    assert result.row["max_equality"] == pytest.approx(a.max(), abs=1e-15)
    assert result.row["certificate_holds"] is True
    assert np.all(np.isnan(tail(rows, "margin")))


def test_check_and_report_show_the_kkt_system(capsys: pytest.CaptureFixture[str]) -> None:
    from tvopt_codegen.report import render_report

    assert main(["check", ARM]) == 0
    out = capsys.readouterr().out
    assert "closed-loop state: q1, q2, w1, w2, nu_on_line_0, nu_on_line_1" in out
    assert "equality constraints: on_line: cos(0.1*t)*px + sin(0.1*t)*py == 1; kept by" in out
    assert "KKT matrix singular (the equalities' gradients dependent) where: nowhere" in out
    d = derivation(ARM)
    text = render_report(d, lower(d), None, ("md",))[f"{ARM}_report.md"]
    assert "Equality constraints a_j(y, t) = 0, kept by the KKT system" in text
    assert "| on_line | cos(0.1*t)*px + sin(0.1*t)*py == 1 |" in text
    assert "the KKT matrix K = [[grad_yy L, J_a^T], [J_a, 0]]" in text
    assert "kron I_3" in text
    assert "K is singular (the constraints' gradients dependent) nowhere" in text


def test_constraints_on_signals_of_signals(tmp_path: Path) -> None:
    """A line that follows a signal defined by other signals: the certificate's
    independent problem (SLSQP, the equalities' numbers) inlines them all."""
    text = UNICYCLE.replace('name = "unicycle_switch"', 'name = "nested"').replace(
        'o2y = "-3 + 0.4*t', 'mid = "0.5*(o1x + o2x)"\nshift = "mid - 1"\no2y = "-3 + 0.4*t'
    )
    spec = write_spec(tmp_path, text + '\n[constraints]\nline = "y1 == shift"\n')
    d = derive(load_spec(spec))
    result = simulate(d, load_controller(lower(d), "python"), resolve_options(d))
    assert result.passed, result.failures
    t = result.t
    shift = 0.5 * ((-5 + 0.6 * t - 0.01 * t**2) + (5 - 0.3 * t - 0.01 * t**2)) - 1
    np.testing.assert_allclose(
        result.constraints.equality[0], result.outputs[0] - shift, atol=1e-12
    )
    assert abs(result.constraints.equality[0, -1]) < 1e-6
    assert np.all(result.constraints.distance <= result.constraints.bound + 1e-6)


def test_equalities_dependent_at_the_start_are_the_methods_assumption(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """J_a = [[1, 0], [cos(t/10), sin(t/10)]] is singular at t = 0 only: simulate is exit 3
    (the method's assumption, not a bad spec), one line, nothing written; and the C
    library (the FMU's log) names the status rather than "unknown status"."""
    import ctypes

    spec = _with_constraints(tmp_path, 'a = "y1 == 1"\nb = "cos(0.1*t)*y1 + sin(0.1*t)*y2 == 0"')
    out = tmp_path / "out"
    assert main(["simulate", str(spec), "--out", str(out)]) == EXIT_ASSUMPTION
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "dependent" in err and "t = 0" in err
    assert not out.exists()
    mod = load_controller(lower(derivation(ARM)), "c")
    message = mod._LIB.arm_on_line_status_message
    message.restype, message.argtypes = ctypes.c_char_p, (ctypes.c_int,)
    text = message(mod.STATUS_DEPENDENT_CONSTRAINTS).decode()
    assert text.startswith("the equality constraints' gradients are dependent")
