"""The C run-time library: routines on request, each once, callees first; one Newton rule."""

from __future__ import annotations

import re
import shutil

import numpy as np
import pytest

from tests.conftest import ROOT, kernels, module
from tvopt_codegen.renderer import runtime
from tvopt_codegen.simulation.target import _newton
from tvopt_codegen.sweep import sweep_program


def test_closure_emits_callees_first_and_each_once() -> None:
    order = [r.macro for r in runtime.closure(["kkt_path", "kkt_newton", "rk45"])]
    assert len(order) == len(set(order))
    position = {name: i for i, name in enumerate(order)}
    for name, routine in runtime.ROUTINES.items():
        if routine.macro in position:
            for callee in routine.calls:
                assert position[runtime.ROUTINES[callee].macro] < position[routine.macro], name
    assert {"kkt", "lu_det", "dot", "kkt_newton", "kkt_convexity", "rk45"} <= {
        name for name, r in runtime.ROUTINES.items() if r.macro in position
    }
    # What the translation unit has already is not emitted again.
    left = [r.macro for r in runtime.closure(["newton"], emitted=["lu_det", "dot"])]
    assert left == ["newton"]
    with pytest.raises(KeyError):
        runtime.closure(["no_such_routine"])


def test_every_routine_is_a_macro_of_its_template() -> None:
    for name, routine in runtime.ROUTINES.items():
        text = (ROOT / "templates" / routine.template).read_text()
        assert re.search(r"\{% macro " + routine.macro + r"\(\) %\}", text), name
        for callee in routine.calls:
            assert callee in runtime.ROUTINES, (name, callee)


@pytest.mark.parametrize("spec", ["unicycle_switch", "arm_on_line"])
def test_the_sweep_emits_each_routine_once(spec: str) -> None:
    source = dict(sweep_program(kernels(spec)).sources)[f"{spec}_sweep.c"]
    for name in ("sweep_rk_step", "sweep_lu", "sweep_dot", "sweep_minimizer_path"):
        assert len(re.findall(r"^static \w+ " + name + r"\(", source, re.M)) == 1, name
    # Only what the loop asks for: no KKT routines without equalities, and the reverse.
    assert ("sweep_kkt_newton(" in source) == (spec == "arm_on_line")
    assert ("sweep_newton(" in source) == (spec != "arm_on_line")


def test_one_newton_rule_for_python_and_c(monkeypatch: pytest.MonkeyPatch) -> None:
    rule = runtime.NewtonRule(step_cap=0.0375, iterations=3)
    monkeypatch.setattr(runtime, "NEWTON", rule)
    source = dict(sweep_program(kernels("unicycle_switch")).sources)["unicycle_switch_sweep.c"]
    assert "if (size > 0.0375) {" in source
    assert "row < count - 1 ? 3 :" in source
    # The Python Newton reads the same table: three capped steps move y by 3 * 0.0375.
    from tvopt_codegen.simulation import target

    monkeypatch.setattr(target, "NEWTON", rule)
    controller = module("unicycle_switch")
    y0 = np.array([10.0, 10.0])
    moved = _newton(controller, 0.0, y0, {}, iterations=rule.iterations)
    assert np.linalg.norm(moved - y0) == pytest.approx(3 * 0.0375, rel=1e-9)


COUPLED = str(ROOT / "tests" / "specs" / "coupled3.toml")


def _coupled_oracle(t: float, x: np.ndarray, c: float) -> np.ndarray:
    """u of coupled3 by hand: y' = Hess^-1 (-2 grad f0 - grad_t f0), then R u = y'."""
    grad = np.array([2 * (x[0] - np.cos(t)), 2 * (x[1] - np.sin(t)), 4 * (x[2] - 0.5 * t)])
    grad_t = np.array([2 * np.sin(t), -2 * np.cos(t), -2.0])
    rate = (-2.0 * grad - grad_t) / np.array([2.0, 2.0, 4.0])
    R = np.array(
        [
            [2.0, 0.5, 0.3 * np.cos(x[1])],
            [0.4, 1.5, 0.2],
            [0.1 * np.sin(x[0]), 0.6, c],
        ]
    )
    return np.linalg.solve(R, rate)


def test_a_full_three_by_three_block_is_solved_by_the_library_lu(
    tmp_path_factory: pytest.TempPathFactory,
) -> None:
    """R is one 3 x 3 block: the C solves it with the run-time library's general LU."""
    assert kernels(COUPLED).plan.runtime == ("lu",)
    py = module(COUPLED)
    rng = np.random.default_rng(7)
    states = rng.uniform(-2, 2, size=(3, 40))
    expected = np.column_stack([_coupled_oracle(0.7, states[:, i], 1.8) for i in range(40)])
    np.testing.assert_allclose(py.control(0.7, states), expected, rtol=1e-12, atol=1e-12)
    backends = [py]
    if shutil.which("cc") or shutil.which("gcc"):
        from tests.test_c_backend import c_module

        c = c_module(COUPLED, tmp_path_factory)
        # The same operations in the same order: the same bits as the NumPy mirror.
        assert np.array_equal(c.control(0.7, states), py.control(0.7, states))
        backends.append(c)
    # Where R is singular (c = 0.06 at x1 = x2 = 0), both backends refuse.
    for backend in backends:
        with pytest.raises(backend.SingularDecouplingError):
            backend.control(0.0, [0.0, 0.0, 0.3], {"c": 0.06})


def test_one_tracking_bound_for_simulate_and_the_sweep() -> None:
    from tvopt_codegen.maths import hurwitz
    from tvopt_codegen.simulation import certificate
    from tvopt_codegen.sweep import sample

    t = np.array([0.0, 1.0, 30.0])
    constant, bound = hurwitz.tracking_bound(t, c=2.0, alpha=1.0, e0=3.0, m_f=0.5)
    assert constant == 12.0
    np.testing.assert_allclose(bound, 12.0 * np.exp(-t))
    # At t = 30 the bound is below the noise floor and is not judged.
    error = np.array([6.0, 12.0 * np.exp(-1.0) + 1e-8, 1.0])
    assert hurwitz.bound_ratio(error, bound) == pytest.approx(1.0)
    assert hurwitz.bound_ratio(error * 2, bound) > 1.0
    assert hurwitz.bound_ratio(error, np.zeros(3)) == 0.0
    # Both certificates state it through these two functions, not a copy of them.
    for verifier in (certificate, sample):
        source = verifier.__file__
        text = open(source, encoding="utf-8").read()
        assert "tracking_bound(" in text and "bound_ratio(" in text
        assert "1e-10" not in text
