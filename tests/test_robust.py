"""On a plant that is not the model: integral action, the disturbance observer, limits.

Every claim is checked with numbers: the augmented certificate on every bundled example,
a constant matched disturbance rejected exactly, anti-windup on a saturated step, the
limits and slew rates the controller applies, and Python and C to the bit.
"""

from __future__ import annotations

import math
import shutil
import tomllib
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np
import pytest

from tvopt_codegen.derivation import derive
from tvopt_codegen.lowering.ir import lower
from tvopt_codegen.simulation import load_controller, resolve_options, simulate
from tvopt_codegen.simulation.direct import plant_function
from tvopt_codegen.simulation.sampled import hold
from tvopt_codegen.spec import bundled_examples, spec_from_dict

from .conftest import ROOT, SPECS, run_main


def _example(name: str) -> dict[str, Any]:
    path = ROOT / "tvopt_codegen" / "examples" / f"{name}.toml"
    with path.open("rb") as stream:
        return tomllib.load(stream)


def _with_integral(data: dict[str, Any]) -> dict[str, Any]:
    """The spec with integral action: one more pole, left of the spec's own."""
    data = dict(data)
    dynamics = dict(data["error_dynamics"])
    if "poles" in dynamics:
        poles = list(dynamics["poles"])
        leftmost = min(p if isinstance(p, float | int) else p[0] for p in poles)
        dynamics["poles"] = [*poles, float(leftmost) - 0.5]
    else:
        raise AssertionError("the bundled examples give poles")
    data["error_dynamics"] = dynamics
    data["robust"] = {"integral": True}
    return data


def _module(data: dict[str, Any]) -> ModuleType:
    """A fresh Python controller of the spec ``data`` (each call its own module)."""
    return load_controller(lower(derive(spec_from_dict(data))), "python")


@pytest.mark.parametrize("name", bundled_examples())
def test_the_nominal_certificate_holds_with_integral_action(name: str) -> None:
    """col(z_I, E) follows expm(H_I t) col(z_I, E)(0) on every bundled example."""
    data = _with_integral(_example(name))
    d = derive(spec_from_dict(data))
    assert d.closed_loop.integral_states
    assert len(d.dynamics.coefficients) == d.dynamics.k + 1
    kernels = lower(d)
    controller = load_controller(kernels, "python")
    result = simulate(d, controller, resolve_options(d, points=101))
    assert result.passed, result.failures
    assert result.deviation < 1e-6


#: A planar integrator whose inputs carry a constant disturbance (d1, d2): zero in the
#: model, not in the plant. The target is still, so the only offset is the disturbance's.
_DISTURBED = """
name = "disturbed"
[system]
states = ["x1", "x2"]
inputs = ["u1", "u2"]
[system.dynamics]
x1 = "u1 + d1"
x2 = "(1 + 0.5*x1**2)*(u2 + d2)"
[system.outputs]
y1 = "x1"
y2 = "x2"
[parameters]
d1 = 0.0
d2 = 0.0
[objective]
f0 = "(y1 - 1)**2 + (y2 + 0.5)**2"
[error_dynamics]
poles = [-2.0]
[simulation]
t_final = 10.0
initial_state = { x1 = 0.0, x2 = 0.0 }
"""


def _disturbed(robust: dict[str, Any]) -> ModuleType:
    data = tomllib.loads(_DISTURBED)
    if robust.get("integral"):
        data["error_dynamics"] = {"poles": [-2.0, -3.0]}
    data["robust"] = robust
    return _module(data)


def _sampled(
    mod: ModuleType, plant: dict[str, float], h: float, steps: int
) -> tuple[Any, np.ndarray]:
    """The Controller stepped every h on the true plant (RK4 under the held input)."""
    n = len(mod.PLANT_STATE_NAMES)
    x = np.array(mod.DEFAULT_STATE[:n], dtype=float)
    controller = mod.Controller(x)
    f = plant_function(mod, plant)
    for k in range(1, steps + 1):
        with np.errstate(all="ignore"):
            x = hold(f, (k - 1) * h, k * h, x, controller.u)
        controller.step(k * h, x)
    return controller, x


# A constant matched disturbance: the plain law keeps an offset, integral action and the
# observer reject it exactly. Three tests, one per law, where one of 10 s was among the
# last to end on two workers; marked slow by hand (tests/durations.json has the one test's
# time only). Sampled at 100 Hz: what is checked is where the sampled loop settles (the
# held input constant, the plant still), which the step does not move; at 1 kHz the same
# 16 s took ten times the steps for the same settled state (|x - target| ~ 1e-14 at both).
_PLANT = {"d1": 0.4, "d2": -0.3}
_TARGET = np.array([1.0, -0.5])
_H = 1e-2


@pytest.mark.slow
def test_a_constant_matched_disturbance_leaves_the_plain_law_an_offset() -> None:
    _, x = _sampled(_disturbed({}), _PLANT, _H, 1000)
    # The plain law settles where grad f0 = -d / a_0-ish: an offset of the disturbance's size.
    assert np.linalg.norm(x - _TARGET) > 0.05


@pytest.mark.slow
def test_a_constant_matched_disturbance_is_rejected_exactly_by_integral_action() -> None:
    _, x = _sampled(_disturbed({"integral": True}), _PLANT, _H, 1600)
    assert np.linalg.norm(x - _TARGET) < 1e-9


@pytest.mark.slow
def test_a_constant_matched_disturbance_is_rejected_exactly_by_the_observer() -> None:
    observer = _disturbed({"observer": {"bandwidth": 20.0}})
    controller, x = _sampled(observer, _PLANT, _H, 1600)
    assert np.linalg.norm(x - _TARGET) < 1e-9
    # The observer's estimate is the disturbance itself.
    np.testing.assert_allclose(controller.disturbance, [0.4, -0.3], atol=1e-9)
    # Without a disturbance the observer estimates nothing: the nominal law.
    controller, _ = _sampled(observer, {"d1": 0.0, "d2": 0.0}, _H, 200)
    assert np.max(np.abs(controller.disturbance)) < 1e-6


#: A double integrator whose force is limited: the 5 m step of the docs.
_STEP = """
name = "cart"
[system]
states = ["p", "v"]
inputs = ["force"]
[system.dynamics]
p = "v"
v = "force/m"
[system.outputs]
y = "p"
[parameters]
m = 1.0
[objective]
f0 = "(y - 5)**2"
[error_dynamics]
poles = [-1.0, -1.5, -2.0]
[robust]
integral = true
[limits]
force = 2.0
[simulation]
t_final = 20.0
initial_state = { p = 0.0, v = 0.0 }
"""


def _step(mod: ModuleType) -> np.ndarray:
    h, n = 1e-3, 20_000
    path = []
    state = np.array([0.0, 0.0])
    controller = mod.Controller(state)
    for k in range(1, n + 1):
        u = controller.u
        # Exact under a held force.
        state = np.array([state[0] + state[1] * h + u[0] * h * h / 2, state[1] + u[0] * h])
        path.append(state[0])
        controller.step(k * h, state)
    return np.array(path)


def test_anti_windup_keeps_a_saturated_step_from_overshooting() -> None:
    mod = _module(tomllib.loads(_STEP))
    assert tuple(mod.INPUT_LOW) == (-2.0,) and tuple(mod.INPUT_HIGH) == (2.0,)
    with_aw = _step(mod)
    overshoot = (with_aw.max() - 5.0) / 5.0
    assert overshoot <= 0.05
    assert abs(with_aw[-1] - 5.0) < 1e-3
    # The same controller with its anti-windup switched off winds up and overshoots.
    mod._ANTI_WINDUP = False
    try:
        without = _step(mod)
    finally:
        mod._ANTI_WINDUP = True
    assert (without.max() - 5.0) / 5.0 > 3 * max(overshoot, 0.05)


def test_limits_and_slew_rates_are_what_the_controller_applies() -> None:
    data = tomllib.loads(_STEP)
    data["limits"] = {"force": [-1.0, 1.5], "rate": {"force": 10.0}}
    mod = _module(data)
    controller = mod.Controller(np.array([0.0, 0.0]))
    # At the start the law asks for more than 1.5: clipped, and said so.
    assert controller.u[0] == 1.5 and controller.saturated.tolist() == [True]
    previous, h = controller.u[0], 0.01
    rates = []
    state = np.array([0.0, 0.0])
    for k in range(1, 2000):
        u = controller.u[0]
        state = np.array([state[0] + state[1] * h + u * h * h / 2, state[1] + u * h])
        applied = controller.step(k * h, state)[0]
        assert -1.0 <= applied <= 1.5
        rates.append(abs(applied - previous) / h)
        previous = applied
    assert max(rates) <= 10.0 * (1 + 1e-12)
    # The rate limit was reached (the law asks for faster changes on the way in).
    assert max(rates) > 9.99


def _both_backends(
    kernels: Any, plant: dict[str, float], steps: int, h: float = 1e-3
) -> tuple[ModuleType, list[Any], list[np.ndarray], int]:
    """Python and C controllers stepped along the same sampled run of a mismatched plant,
    checked equal to the bit at every step: the Python module, both controllers, both
    plant states, and the steps at which the limits clipped an input."""
    if not any(shutil.which(cc) for cc in ("gcc", "cc", "clang")):
        pytest.skip("no C compiler")
    py = load_controller(kernels, "python")
    c = load_controller(kernels, "c")
    x0 = np.array(py.DEFAULT_STATE[: len(py.PLANT_STATE_NAMES)])
    controllers = [py.Controller(x0), c.Controller(x0)]
    states = [x0.copy(), x0.copy()]
    clipped = 0
    f = plant_function(py, plant)
    for k in range(1, steps + 1):
        for j in (0, 1):
            with np.errstate(all="ignore"):
                states[j] = hold(f, (k - 1) * h, k * h, states[j], controllers[j].u)
            controllers[j].step(k * h, states[j])
        a, b = controllers
        assert a.u.tobytes() == b.u.tobytes()
        assert a.state.tobytes() == b.state.tobytes()
        assert a.disturbance.tobytes() == b.disturbance.tobytes()
        assert a.saturated.tolist() == b.saturated.tolist()
        clipped += bool(a.saturated.any())
    return py, controllers, states, clipped


def test_the_sampled_python_and_c_controllers_agree_to_the_bit_on_a_mismatched_plant() -> None:
    spec = str(SPECS / "robust_pvtol.toml")
    kernels = lower(derive(spec_from_dict(_toml(spec))))
    # 3 s at 200 Hz: the limits clip 48 steps and the observer settles as at 1 kHz (its
    # estimate within 0.1% of the model error either way), in a fifth of the steps.
    _, controllers, _, clipped = _both_backends(kernels, {"m": 1.12, "J": 0.9}, 600, h=5e-3)
    assert clipped > 0  # the limits acted
    # The thrust's matched disturbance under a 12% heavier plant: T (m0 / m - 1).
    thrust = controllers[0].u[0]
    assert controllers[0].disturbance[0] == pytest.approx(thrust * (1 / 1.12 - 1), rel=0.05)


def _toml(path: str) -> dict[str, Any]:
    with open(path, "rb") as stream:
        return tomllib.load(stream)


@pytest.mark.parametrize(
    ("table", "field", "problem"),
    [
        ({"robust": {"integral": True}}, "error_dynamics.poles", "give 5 poles, not 4"),
        ({"limits": {"rotor": 1.0}}, "limits.rotor", "'rotor' is not a plant input"),
        ({"limits": {"thrust": [5.0, 1.0]}}, "limits.thrust", "low 5 must be below high 1"),
        ({"limits": {"torque": -1.0}}, "limits.torque", "L must be positive"),
        ({"limits": {"rate": {"thrust": -3.0}}}, "limits.rate.thrust", "must be positive"),
        ({"robust": {"observer": {"bandwidth": -2.0}}}, "robust.observer.bandwidth", "positive"),
        ({"robust": {"integral": "yes"}}, "robust.integral", "expected true or false"),
        ({"robust": {"observer": {}}}, "robust.observer.bandwidth", "missing required key"),
    ],
)
def test_bad_robust_tables_are_one_line_errors_that_write_nothing(
    tmp_path: Path, table: dict[str, Any], field: str, problem: str
) -> None:
    data = _example("pvtol") | table
    path = tmp_path / "bad.toml"
    path.write_text(_dump(data), encoding="utf-8")
    out = tmp_path / "out"
    done = run_main("generate", str(path), "--out", str(out))
    assert done.returncode == 2
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1, done.stderr
    assert field in lines[0] and problem in lines[0], lines[0]
    assert str(path) in lines[0]
    assert not out.exists()


def _dump(data: dict[str, Any], prefix: str = "") -> str:
    """A small TOML writer for the tests' specs (tables, strings, numbers, lists)."""

    def value(v: Any) -> str:
        if isinstance(v, bool):
            return "true" if v else "false"
        if isinstance(v, str):
            return '"""' + v + '"""' if "\n" in v else repr(v).replace("'", '"')
        if isinstance(v, list):
            return "[" + ", ".join(value(x) for x in v) + "]"
        if isinstance(v, dict):
            return "{ " + ", ".join(f"{k} = {value(x)}" for k, x in v.items()) + " }"
        return repr(v) if not (isinstance(v, float) and math.isinf(v)) else "inf"

    lines, tables = [], []
    for key, v in data.items():
        if isinstance(v, dict) and (not prefix or any(isinstance(x, dict) for x in v.values())):
            tables.append((key, v))
        else:
            lines.append(f"{key} = {value(v)}")
    for key, v in tables:
        lines.append(f"\n[{prefix}{key}]")
        lines.append(_dump(v, f"{prefix}{key}."))
    return "\n".join(lines)


def _sweep_program(spec: str) -> Any:
    from tvopt_codegen.sweep import sweep_program  # noqa: PLC0415

    return sweep_program(lower(derive(spec_from_dict(_toml(spec)))))


def test_a_sampled_sweep_runs_the_robust_controller_on_mismatched_plants() -> None:
    pytest.importorskip("pyarrow")
    from tvopt_codegen.sweep import (  # noqa: PLC0415
        Distribution,
        SweepOptions,
        format_summary,
        run_sample,
        summarize,
    )

    program = _sweep_program(str(SPECS / "robust_pvtol.toml"))
    # The spec's [limits] are the plant's actuators by default.
    assert ("thrust", 0.0, 14.715) in program.limits and program.observer
    options = SweepOptions(
        samples=4,
        seed=7,
        t_final=12.0,
        plant_params=(
            ("m", Distribution("normal", (1.0, 0.1))),
            ("J", Distribution("normal", (1.0, 0.1))),
        ),
        limits=program.limits,
        sample_time=0.002,
        points=121,
    )
    results = [run_sample(program, options, i) for i in range(4)]
    rows = [result.row for result in results]
    assert all(row["status"] == "ok" for row in rows)
    # The summary says how long the inputs were clipped.
    text = format_summary("robust_pvtol", options, summarize(results, 4, False))
    assert "| time an input was clipped (s) |" in text
    # Both options hold the target on a 10% wrong model: millimetres where the plain
    # law is off by metres (docs/robust.md).
    assert max(row["final_error"] for row in rows) < 5e-3
    assert any(row["time_saturated"] > 0 for row in rows)


def test_a_continuous_sweep_of_an_observer_spec_is_refused(tmp_path: Path) -> None:
    done = run_main(
        "sweep", str(SPECS / "robust_pvtol.toml"), "--samples", "2", "--out", str(tmp_path / "out")
    )
    assert done.returncode == 2
    assert done.stderr.count("\n") == 1
    assert "--sample-time" in done.stderr and "[robust.observer]" in done.stderr
    assert not (tmp_path / "out").exists()


def test_the_continuous_loop_holds_the_integrals_while_an_input_is_clipped() -> None:
    """With integral action and limits, the continuous sweep's integrals stop while clipped."""
    from tvopt_codegen.sweep import SweepOptions, draw, loop_for  # noqa: PLC0415

    data = tomllib.loads(_STEP)
    path_spec = spec_from_dict(data)
    from tvopt_codegen.sweep import sweep_program  # noqa: PLC0415

    program = sweep_program(lower(derive(path_spec)))
    options = SweepOptions(samples=1, seed=0, t_final=20.0, limits=program.limits, points=401)
    sample = draw(program, options, 0)
    outcome, rows, _ = loop_for(program).run(options, sample)
    assert outcome == 0
    n = len(program.state_names)
    integral = rows[:, 1 + program.integral_rows[0]]
    clipped = rows[:, -1] > 0.5
    assert clipped[:20].all() and not clipped[-20:].any()
    # Held while clipped (between output rows inside the clipped stretch).
    stretch = np.nonzero(clipped[:-1] & clipped[1:])[0]
    assert np.all(integral[stretch + 1] == integral[stretch])
    # It settles on the target (the stateful controller also holds the integrals' offset
    # from z*(E), which the continuous loop cannot: test_anti_windup_... above).
    position = rows[:, 1]
    assert abs(position[-1] - 5.0) < 1e-3
    assert n == 3


def test_the_sampled_run_states_its_input_to_state_bound_on_a_wrong_plant() -> None:
    """w_k of E_(k+1) = expm(H h) E_k + w_k, and |E| within the bound it gives."""
    from tvopt_codegen.simulation.sampled import format_sampled, simulate_sampled

    spec = str(SPECS / "robust_pvtol.toml")
    d = derive(spec_from_dict(_toml(spec)))
    controller = load_controller(lower(d), "python")
    options = resolve_options(d, t_final=6.0, points=61)
    nominal = simulate_sampled(d, controller, options, 0.005)
    wrong = simulate_sampled(d, controller, options, 0.005, plant_params={"m": 1.2, "J": 0.8})
    for result in (nominal, wrong):
        run = result.runs[0]
        assert result.passed, result.failures
        assert 0.0 < run.iss_ratio <= 1.0
        # The limits act at the start (torque within 1 N m): a disturbance of the error
        # dynamics, as sampling and the wrong plant are.
        assert 0.0 < run.disturbance < math.inf and run.saturated_time > 0
    text = format_sampled(d, wrong)
    assert "input-to-state: col(z_I, E)_(k+1) = expm(H h) col(z_I, E)_k + w_k" in text
    assert "on a plant that is not the model (m = 1.2, J = 0.8)" in text


@pytest.mark.parametrize("backend", ["python", "c"])
def test_a_failed_robust_step_leaves_the_controller_as_it_was(backend: str) -> None:
    """The observer's and the integrals' updates commit with the law's, or not at all."""
    if backend == "c" and not any(shutil.which(cc) for cc in ("gcc", "cc", "clang")):
        pytest.skip("no C compiler")
    spec = str(SPECS / "robust_pvtol.toml")
    mod = load_controller(lower(derive(spec_from_dict(_toml(spec)))), backend)
    x = np.array(mod.DEFAULT_STATE[:6])
    controller = mod.Controller(x)
    for k in range(1, 50):
        x = x + 1e-3 * np.array([0.1, 0.05, 0.02, 0.0, 0.0, 0.0])
        controller.step(k * 1e-3, x)

    def snapshot() -> tuple[Any, ...]:
        return (
            controller.t,
            controller.u.tobytes(),
            controller.state.tobytes(),
            controller.disturbance.tobytes(),
            controller.saturated.tolist(),
        )

    before = snapshot()
    bad = x.copy()
    bad[2] = np.nan
    with pytest.raises(mod.NonFiniteInputError):
        controller.step(0.06, bad)
    assert snapshot() == before
    with pytest.raises(mod.DecreasingTimeError):
        controller.step(0.01, x)
    assert snapshot() == before
    # The next good step is the one it would have been.
    again = mod.Controller(np.array(mod.DEFAULT_STATE[:6]))
    y = np.array(mod.DEFAULT_STATE[:6])
    for k in range(1, 50):
        y = y + 1e-3 * np.array([0.1, 0.05, 0.02, 0.0, 0.0, 0.0])
        again.step(k * 1e-3, y)
    assert controller.step(0.06, x).tobytes() == again.step(0.06, y).tobytes()


def test_the_observer_keeps_its_estimate_where_g_loses_rank() -> None:
    spec = str(SPECS / "robust_pvtol.toml")
    mod = load_controller(lower(derive(spec_from_dict(_toml(spec)))), "python")
    # The observer's residual lives on the rows G acts on: vx, vz and omega.
    assert mod._OBSERVED == (3, 4, 5)
    sigma = [1.0, 2.0, 3.0]
    # G = 0: nothing to solve; the last estimate stays.
    assert mod._estimate([0.0] * 12, sigma, [0.3, 0.4]) == [0.3, 0.4]
    # A G of full rank: the least-squares solution (here exact: sigma = G d).
    g = [0.0] * 12
    g[3 * 2 + 0], g[4 * 2 + 0], g[5 * 2 + 1] = 0.0, 1.0, 2.0
    np.testing.assert_allclose(mod._estimate(g, sigma, [0.3, 0.4]), [2.0, 1.5], rtol=1e-15)


def test_inputs_whose_columns_of_g_share_rows_are_solved_together() -> None:
    from tvopt_codegen.derivation.robust import _blocks

    # Inputs 0 and 2 share row 0, input 3 reaches them through row 2; input 1 is alone.
    assert _blocks(((0,), (1,), (0, 2), (2, 4), (5,))) == ((0, 2, 3), (1,), (4,))
    assert _blocks(((3, 4), (5,))) == ((0,), (1,))
    assert _blocks(()) == ()


def _arm_with_observer() -> tuple[Any, Any]:
    table = _toml(str(ROOT / "tvopt_codegen" / "examples" / "arm_on_line.toml"))
    table["robust"] = {"observer": {"bandwidth": 20.0}}
    d = derive(spec_from_dict(table))
    return d, lower(d)


def test_the_observer_solves_a_coupled_g_by_least_squares() -> None:
    d, kernels = _arm_with_observer()
    robust = d.robustness
    # Both torques reach both joint accelerations through M^-1: one block of two.
    assert robust.observed_states == (2, 3)
    assert robust.observer_blocks == ((0, 1),)
    mod = load_controller(kernels, "python")
    rng = np.random.default_rng(7)
    for _ in range(20):
        g = [0.0] * 8
        g[4:] = rng.normal(size=4).tolist()
        sigma = rng.normal(size=2).tolist()
        block = np.array(g).reshape(4, 2)[[2, 3]]
        expected = np.linalg.lstsq(block, np.array(sigma), rcond=None)[0]
        np.testing.assert_allclose(mod._estimate(g, sigma, [9.0, 9.0]), expected, rtol=1e-12)
    # Columns that are parallel: G has lost rank, and the last estimate stays.
    g = [0.0, 0.0, 0.0, 0.0, 1.0, 2.0, 3.0, 6.0]
    assert mod._estimate(g, [1.0, 1.0], [0.3, 0.4]) == [0.3, 0.4]


def test_the_python_and_c_observers_agree_to_the_bit_on_a_coupled_g() -> None:
    _, kernels = _arm_with_observer()
    plant = {"m1": 1.1, "m2": 0.45}
    # 2 s at 200 Hz: the estimate at the end is the 1 kHz run's to 0.1%.
    py, controllers, states, _ = _both_backends(kernels, plant, 400, h=5e-3)
    # The estimate is the matched disturbance of the heavier and lighter links: not zero,
    # and what the plant's own G says the model error is, to the filter's lag.
    d_hat = controllers[0].disturbance
    assert np.all(np.abs(d_hat) > 1e-3)
    x, u = states[0], controllers[0].u
    error = np.asarray(py.plant(2.0, x, u, plant)) - np.asarray(py.plant(2.0, x, u))
    g = np.column_stack(
        [np.asarray(py.plant(2.0, x, e)) - np.asarray(py.plant(2.0, x, 0 * e)) for e in np.eye(2)]
    )
    truth = np.linalg.lstsq(g[2:], error[2:], rcond=None)[0]
    np.testing.assert_allclose(d_hat, truth, rtol=0.05, atol=5e-3)


def test_the_law_returns_the_observers_f_and_g_on_both_of_its_paths() -> None:
    # The jet kernel returns f(x) and G(x) beside the law: the one-point path and the
    # array path (the one-point path's fallback) give the same, and the plant's.
    spec = str(SPECS / "robust_pvtol.toml")
    mod = load_controller(lower(derive(spec_from_dict(_toml(spec)))), "python")
    s = np.array(mod.DEFAULT_STATE, dtype=float) + 0.1
    p = np.array(list(mod.PARAMETERS.values()), dtype=float)
    one = mod._law_1(0.3, s.tolist(), p.tolist(), True)
    ds, u, drift, g = mod._law(0.3, s[:, None], p)
    assert np.array(one[2]).tobytes() == drift[:, 0].tobytes()
    assert np.array(one[3]).tobytes() == g[:, 0].tobytes()
    x, e = s[:6], np.eye(2)
    np.testing.assert_allclose(drift[:, 0], mod.plant(0.3, x, [0.0, 0.0]), rtol=1e-15)
    for i in range(2):
        column = np.asarray(mod.plant(0.3, x, e[i])) - np.asarray(mod.plant(0.3, x, 0 * e[i]))
        np.testing.assert_allclose(g[:, 0].reshape(6, 2)[:, i], column, rtol=1e-14, atol=1e-15)
