"""Failures the differential fuzzer found (tests/fuzzing.py), each shrunk to a named case.

A failure in another part of the tool is ``xfail(strict=True)`` with what fails as the
reason, until its owner fixes it (then the strict xfail turns into a failure: remove the
mark). Failures of the fuzzer's own harness are ordinary tests.
"""

from __future__ import annotations

import functools
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from .conftest import ROOT
from .fuzzing import (
    Case,
    DisagreementError,
    build_spec,
    cases_strategy,
    drawn_cases,
    run_case,
    urdf_text,
)
from .fuzzing import main as fuzz_main

#: ``system:2:-:1`` of the first generator: two strict-feedback chains of length 2 whose
#: gains are ``c0 + c1 cos(s)`` and ``c0 + c1 tanh(s)``, in coordinates with one
#: ``x = s + c sin(s')``. det R is a product of those gains; nothing is hard about it.
TRIG_GAINS = {
    "name": "fz_trig_gains",
    "system": {
        "states": ["x1", "x2", "x3", "x4"],
        "inputs": ["u1", "u2"],
        "dynamics": {
            "x1": "(x2 - 3*sin(x1)/10)*(513*cos(x1)/1250 + 57/50) + 9*sin(x1)/20",
            "x2": "u1*(9*tanh(x2 - 3*sin(x1)/10)/100 + 141/100) + 51*u2*sin(x1)/100"
            " + 3*((x2 - 3*sin(x1)/10)*(513*cos(x1)/1250 + 57/50) + 9*sin(x1)/20)*cos(x1)/10"
            " - 19*sin(x2 - 3*sin(x1)/10)/100 + 33*cos(x2 - 3*sin(x1)/10)/100",
            "x3": "(x4 + sin(x3)/50)*(3059*cos(x3)/10000 + 133/100) + sin(x3)/25",
            "x4": "u2*(7/5 - 53*tanh(x4 + sin(x3)/50)/100)"
            " - ((x4 + sin(x3)/50)*(3059*cos(x3)/10000 + 133/100) + sin(x3)/25)*cos(x3)/50"
            " - sin(x3)/5 - 37*cos(x2 - 3*sin(x1)/10)/100",
        },
        "outputs": {"y1": "x1", "y2": "x3"},
    },
    "signals": {"o1": "0.5*sin(0.5*t)", "o2": "0.3*cos(0.4*t)"},
    "objective": {"f0": "(y1 - o1)**2 + (y2 - o2)**2"},
    "error_dynamics": {"poles": [-1.0, -2.0]},
    "simulation": {"initial_state": {"x1": 0.1, "x2": 0.0, "x3": -0.2, "x4": 0.0}},
}

_DERIVE = """
import json, sys, time
from tvopt_codegen.derivation import derive
from tvopt_codegen.limits import Budget
from tvopt_codegen.errors import BudgetError
start = time.perf_counter()
try:
    derive(json.loads(sys.argv[1]), budget=Budget(seconds=float(sys.argv[2])))
    print("derived")
except BudgetError as exc:
    print("budget", str(exc))
print(round(time.perf_counter() - start, 1))
"""


def _derive_within(spec: dict[str, object], budget: float, timeout: float) -> str:
    """Derive ``spec`` in a child process; its output, or ``timeout`` when it ran over."""
    return _children(json.dumps(spec), timeout)[budget]


@functools.cache
def _children(spec: str, timeout: float) -> dict[float, str]:
    """Both budgets' children at once: the two tests wait ``timeout`` together, not twice."""
    started = {
        budget: subprocess.Popen(
            [sys.executable, "-c", _DERIVE, spec, str(budget)],
            stdout=subprocess.PIPE,
            stderr=subprocess.DEVNULL,
            text=True,
            cwd=ROOT,
        )  # fmt: skip
        for budget in (2.0, 120.0)
    }
    deadline = time.monotonic() + timeout
    out = {}
    for budget, child in started.items():
        try:
            out[budget] = child.communicate(timeout=max(deadline - time.monotonic(), 0.1))[0]
        except subprocess.TimeoutExpired:
            child.kill()
            child.communicate()
            out[budget] = "timeout"
    return out


@pytest.mark.slow
def test_a_det_r_with_trigonometric_gains_derives_in_seconds() -> None:
    """simplify ran 487 s on this det R; past 5 s its exact short form stands."""
    out = _derive_within(TRIG_GAINS, budget=120.0, timeout=40.0)
    assert out.startswith("derived"), out


@pytest.mark.slow
def test_the_time_budget_stops_a_derivation_inside_a_stage() -> None:
    """Budget(seconds=2) holds inside one sympy call: BudgetError within about 2 s."""
    out = _derive_within(TRIG_GAINS, budget=2.0, timeout=40.0)
    assert out.startswith("budget") and "decoupling matrix" in out, out
    assert float(out.split()[-1]) < 6.0, out


# ----------------------------------------------------------------- the harness itself


def test_a_case_string_names_its_case() -> None:
    case = Case.parse("system:3:integral+c+unicycle:42")
    assert case == Case("system", 3, frozenset({"integral", "c", "unicycle"}), 42)
    assert Case.parse(str(case)) == case and str(Case("arm", 1, frozenset(), 7)) == "arm:1:-:7"
    with pytest.raises(ValueError, match="not a fuzz case"):
        Case.parse("robot:1:-:3")


def test_a_case_is_the_same_spec_on_every_build(tmp_path: Path) -> None:
    case = Case.parse("system:3:integral+limits+references+unicycle:5")
    first, extra = build_spec(case, tmp_path)
    again, _ = build_spec(case, tmp_path)
    assert first == again
    # 3 outputs: one chain of random length and the unicycle's two (2 once extended).
    assert len(first["system"]["outputs"]) == 3 and extra["relative_degree"][1:] == (2, 2)
    assert first["robust"]["integral"] is True and "references" in first


def test_a_random_inertia_is_positive_definite_with_the_triangle_inequality() -> None:
    # The first generator rotated the principal moments by two different rotations: an
    # indefinite tensor that spec_from_urdf (rightly) refused.
    text = urdf_text(Case("urdf", 3, frozenset(), 5), np.random.default_rng(5))
    for block in text.split("<inertia ")[1:]:
        values = dict(item.split("=") for item in block.split("/>")[0].split())
        get = {k: float(v.strip('"')) for k, v in values.items()}
        tensor = np.array(
            [
                [get["ixx"], get["ixy"], get["ixz"]],
                [get["ixy"], get["iyy"], get["iyz"]],
                [get["ixz"], get["iyz"], get["izz"]],
            ]
        )
        a, b, c = np.linalg.eigvalsh(tensor)
        assert a > 0 and c <= a + b + 1e-9


def test_the_cli_import_takes_a_negative_gravity(tmp_path: Path) -> None:
    # The harness once passed --gravity as three arguments; a first negative component
    # must also not read as an option.
    assert run_case(Case.parse("urdf:1:cli:0")) == "agrees"


def test_c_and_the_fmu_are_drawn_rarely_not_first() -> None:
    hypothesis = pytest.importorskip("hypothesis")
    draws = []

    @hypothesis.settings(max_examples=60, database=None, derandomize=True)
    @hypothesis.given(cases_strategy(c_rate=0.1, fmu_rate=0.0))
    def collect(case: Case) -> None:
        draws.append(case)

    collect()
    assert not any("fmu" in c.features for c in draws)
    assert "c" not in draws[0].features and sum("c" in c.features for c in draws) < 30


def test_a_law_off_by_a_millionth_is_a_disagreement(monkeypatch: pytest.MonkeyPatch) -> None:
    # The oracles must be able to fail: a module whose control is 1e-6 off is caught.
    import types

    from tvopt_codegen import simulation

    real = simulation.load_controller

    def skewed(kernels: object, backend: str = "python") -> types.ModuleType:
        mod = real(kernels, backend)  # type: ignore[arg-type]
        control = mod.control
        mod.control = lambda t, s, **kw: control(t, s, **kw) * (1 + 1e-6)
        return mod

    monkeypatch.setattr(simulation, "load_controller", skewed)
    with pytest.raises(DisagreementError, match="control at t="):
        run_case(Case.parse("arm:2:integral:3"))


def test_a_seed_draws_the_same_cases_again() -> None:
    # make fuzz SEED=S replays a run: hypothesis seeded, no database, generation only;
    # each case once.
    first = drawn_cases(30, 7, 0.05, 0.02)
    assert first == drawn_cases(30, 7, 0.05, 0.02) and first != drawn_cases(30, 8, 0.05, 0.02)
    assert len(first) == len(set(first)) == 30


def test_workers_run_the_same_cases_with_the_same_ends(
    capsys: pytest.CaptureFixture[str],
) -> None:
    # --workers changes the order of the lines, never what a case does.
    cases = ["system:1:-:5", "arm:1:integral:6"]
    ends = []
    for workers in ("1", "2"):
        argv = [a for c in cases for a in ("--case", c)] + ["--workers", workers]
        assert fuzz_main(argv) == 0
        lines = [line.split() for line in capsys.readouterr().out.splitlines()]
        ends.append(sorted((w[3], w[0]) for w in lines if len(w) > 3 and w[3] in cases))
    assert ends[0] == ends[1] and len(ends[0]) == 2


@pytest.mark.slow
def test_a_drawn_chain_that_starts_singular_is_the_documented_refusal() -> None:
    """``urdf:3:-:11`` starts stretched out, where R is singular: the derivation warns
    (simulate's exit 3), and the case counts as that refusal, not as a failure of the
    Controller, which raises SingularDecouplingError at its first step there."""
    out = run_case(Case.parse("urdf:3:-:11"))
    assert out.startswith("refused: warning: simulation.initial_state: the law is undefined")


@pytest.mark.slow
def test_a_loop_that_leaves_the_domain_ends_in_the_same_error_in_python_and_c(
    tmp_path: Path,
) -> None:
    """``system:3:auto+inequality+integral+limits+observer+references+unicycle:3`` starts
    1.5 cm inside a barrier with ``u1`` limited to [-16.46, -6.6]. The harness first fed
    the controller a path that ignored its inputs (x0 + drift t), which wound the
    integrals and the observer up until the prolonged speed crossed v = 0: a finding of
    the harness, not the tool. On the plant's own closed loop, sampled at 10 ms, the loop
    still leaves the law's domain: it crosses the barrier at 0.04 s, where both backends
    stop with the documented OutsideBarrierError (before the margin check, the law went on
    past the barrier until the speed crossed v = 0 at 0.09 s), and the case counts as that
    run-time end."""
    from tvopt_codegen.derivation import derive
    from tvopt_codegen.lowering.ir import lower
    from tvopt_codegen.simulation import load_controller
    from tvopt_codegen.simulation.references import exact_jets
    from tvopt_codegen.spec import spec_from_dict

    from .fuzzing import _closed_loop, _controller_run

    case = Case.parse("system:3:auto+inequality+integral+limits+observer+references+unicycle:3")
    out = run_case(case)
    assert out.startswith("refused: run-time: the sampled closed loop left the law's domain")
    assert "OutsideBarrierError" in out and "t = 0.04 s" in out
    spec, _ = build_spec(case, tmp_path)
    d = derive(spec_from_dict(spec))
    kernels = lower(d)
    py, cmod = load_controller(kernels, "python"), load_controller(kernels, "c")
    jets = exact_jets(d, {})
    x0 = np.array(py.DEFAULT_STATE[: len(py.PLANT_STATE_NAMES)], dtype=float)
    times = np.round(np.arange(0, 11) * 0.01, 6)
    loop = _closed_loop(py, x0, times, np.zeros(len(x0)), jets)
    assert loop.stopped.startswith("OutsideBarrierError") and loop.at >= 2
    # The plant answered the controller: its path is not the straight line through x0.
    assert not np.allclose(loop.plants[:, 1], x0)
    rows, stopped = _controller_run(cmod, x0, loop.plants, loop.times, jets)
    assert stopped == "OutsideBarrierError"
    np.testing.assert_allclose(rows, loop.rows, rtol=1e-9, atol=1e-9)


#: ``system:1:equality+inequality+observer+references:23120940`` of the 2,000-case run
#: (seed 2030): a chain of three starting 4 cm inside the barrier of ``y1 >= o1 - 0.19``,
#: whose 10 ms sampled loop is unstable. The harness's plant overflowed at 0.1 s; on the
#: way the output crossed the constraint at 0.06 s, and the controller went on answering.
BARRIER_CASE = "system:1:equality+inequality+observer+references:23120940"


def test_the_law_refuses_a_state_outside_the_barriers_domain(tmp_path: Path) -> None:
    """Past a barrier the law's 1/(s - g) is finite: before the margin check, control,
    rhs, optimality_error, the gradient and Hessian of B and Controller.step answered
    there with status OK. Now both backends raise the contract's OutsideBarrierError, in
    a batch at the column that is outside, on the one-point path as on the array path."""
    from tvopt_codegen.derivation import derive
    from tvopt_codegen.lowering.ir import lower
    from tvopt_codegen.simulation import load_controller
    from tvopt_codegen.simulation.references import exact_jets
    from tvopt_codegen.spec import spec_from_dict

    spec, _ = build_spec(Case.parse(BARRIER_CASE), tmp_path)
    d = derive(spec_from_dict(spec))
    kernels = lower(d)
    jets = exact_jets(d, {})
    refs = jets(0.0)
    # o1(0) = 0.42 sin(2.95) = 0.080: the constraint keeps y1 = x1 >= -0.110.
    inside = np.array([[-0.07], [0.3], [0.21]])
    outside = np.array([[-0.2], [0.3], [0.21]])
    batch = np.hstack([inside, outside, inside])
    for backend in ("python", "c"):
        mod = load_controller(kernels, backend)
        assert np.all(np.isfinite(mod.control(0.0, inside, refs=refs)))
        for function in (mod.objective, mod.gradient, mod.hessian):
            assert np.all(np.isfinite(function(0.0, inside[:1], refs=refs)))
            for y in (outside[:1], outside[:1, 0]):
                with pytest.raises(mod.OutsideBarrierError, match=r"barrier \(column 0\)"):
                    function(0.0, y, refs=refs)
        for function in (mod.control, mod.rhs, mod.optimality_error):
            for state in (outside, outside[:, 0]):
                with pytest.raises(mod.OutsideBarrierError, match=r"barrier \(column 0\)"):
                    function(0.0, state, refs=refs)
            with pytest.raises(mod.OutsideBarrierError, match=r"\(column 1\)") as caught:
                function(0.0, batch, refs=np.repeat(refs[..., None], 3, axis=-1))
            assert caught.value.status == mod.STATUS_OUTSIDE_BARRIER
        # The stateful controller, stepped across the barrier, stops there.
        controller = mod.Controller(inside[:, 0], refs=refs)
        with pytest.raises(mod.OutsideBarrierError):
            controller.step(0.01, outside[:, 0], refs=jets(0.01))


#: ``arm:3:equality+inequality+limits+observer:241`` of seed 2032: the arm starts 4.6 mm
#: inside the barrier of ``y3 >= o3 - 0.19``; the harness's constant disturbance (on every
#: state's rate) and tau2's limit, which holds the nominal input, push y3 out within 9 ms
#: whatever the sampling (10, 1 or 0.1 ms). The first step's OutsideBarrierError is then
#: the plant's, not a seam: the oracle's margin confirms it.
START_NEAR_A_BARRIER = "arm:3:equality+inequality+limits+observer:241"


def test_a_start_pushed_across_a_barrier_at_once_is_a_documented_end() -> None:
    out = run_case(Case.parse(START_NEAR_A_BARRIER))
    assert out.startswith("refused: run-time: the sampled closed loop left the law's domain")
    assert "t = 0.01 s: OutsideBarrierError" in out


def test_a_barrier_refusal_inside_every_barrier_is_a_disagreement(tmp_path: Path) -> None:
    """The harness believes OutsideBarrierError only where the oracle's margins agree."""
    from tvopt_codegen.derivation import derive
    from tvopt_codegen.spec import spec_from_dict

    from .fuzzing import ClosedLoop, _crossed_a_barrier
    from .oracle import Oracle

    spec, _ = build_spec(Case.parse(START_NEAR_A_BARRIER), tmp_path)
    d = derive(spec_from_dict(spec))
    x0 = np.array(d.closed_loop.initial_state[: len(d.model.x)], dtype=float)
    p = np.array([v for _, v in d.spec.parameters], dtype=float)
    times = np.array([0.0, 0.01])
    plants = np.stack([x0, x0], axis=1)  # still at the start, 4.6 mm inside
    stopped = ClosedLoop(plants, times, np.zeros((1, 1)), "OutsideBarrierError: (made up)", 1)
    oracle = Oracle(d)  # its functions are pure: one for both loops (each costs a second)
    with pytest.raises(DisagreementError, match="where the oracle's margins are"):
        _crossed_a_barrier(oracle, stopped, d, p)
    other = ClosedLoop(plants, times, np.zeros((1, 1)), "SingularDecouplingError: x", 1)
    assert not _crossed_a_barrier(oracle, other, d, p)
