"""python-control: the controller and the plant as nlsys, connected by signal names."""

from __future__ import annotations

import builtins
import sys
from typing import Any

import numpy as np
import pytest

from tvopt_codegen.errors import MissingExtraError
from tvopt_codegen.interop import plant_nlsys, to_nlsys
from tvopt_codegen.simulation import Options, simulate

from .conftest import derivation, module

control = pytest.importorskip("control")


@pytest.mark.parametrize("spec", ["unicycle_switch", "pvtol"])
def test_the_interconnection_reproduces_simulate(spec: str) -> None:
    mod, d = module(spec), derivation(spec)
    closed = control.interconnect(
        [plant_nlsys(mod), to_nlsys(mod)], inplist=[], outlist=list(mod.OUTPUT_NAMES)
    )
    # Connected by name alone: every input of each system is an output of the other.
    assert closed.ninputs == 0 and closed.noutputs == len(mod.OUTPUT_NAMES)
    _reproduces_simulate(closed, mod, d)


def _reproduces_simulate(closed: Any, mod: Any, d: Any) -> None:
    """The interconnection's outputs and states are simulate's, over 6 s."""
    options = Options(t_final=6.0, initial_state=tuple(mod.DEFAULT_STATE), points=61)
    reference = simulate(d, mod, options)
    response = control.input_output_response(
        closed,
        reference.t,
        0,
        X0=np.array(mod.DEFAULT_STATE),
        solve_ivp_kwargs={"rtol": 1e-10, "atol": 1e-12},
    )
    np.testing.assert_allclose(response.outputs, reference.outputs, rtol=0, atol=1e-6)
    np.testing.assert_allclose(response.states, reference.states, rtol=0, atol=1e-6)


def test_a_static_controller_and_parameters_by_name() -> None:
    mod = module("integrator")
    controller = to_nlsys(mod)
    assert controller.nstates == 0
    x = np.array(mod.DEFAULT_STATE)
    np.testing.assert_allclose(controller.output(0.5, [], x), mod.control(0.5, x))
    switch = module("unicycle_switch")
    plant = plant_nlsys(switch)
    state = np.array(switch.DEFAULT_STATE[:3])
    out = plant.output(0.0, state, [1.0, 0.1])
    np.testing.assert_allclose(out[:3], state)
    np.testing.assert_allclose(out[3:], switch.outputs(0.0, state))
    np.testing.assert_allclose(
        plant.dynamics(0.0, state, [1.0, 0.1]), switch.plant(0.0, state, [1.0, 0.1])
    )
    # An interconnection hands every parameter to every system: each keeps its own.
    ours = to_nlsys(switch)
    s = np.array(switch.DEFAULT_STATE)
    np.testing.assert_allclose(
        ours.output(0.0, s[3:], s[:3], params={"b": 2.0, "somebody_else": 1.0}),
        switch.control(0.0, s, {"b": 2.0}),
    )


def test_without_python_control_one_line_says_what_to_install(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    real_import = builtins.__import__

    def no_control(name: str, *args: Any, **kwargs: Any) -> Any:
        if name == "control" or name.startswith("control."):
            raise ImportError("No module named 'control'")
        return real_import(name, *args, **kwargs)

    monkeypatch.delitem(sys.modules, "control", raising=False)
    monkeypatch.setattr(builtins, "__import__", no_control)
    with pytest.raises(MissingExtraError) as info:
        to_nlsys(module("integrator"))
    assert str(info.value) == (
        "python-control is not installed: pip install 'tvopt-codegen[control]'"
    )


def test_the_robust_controller_holds_a_mismatched_plant_in_python_control() -> None:
    """Limits, integral action and the observer's continuous form, against a wrong plant."""
    from .conftest import SPECS

    mod = module(str(SPECS / "robust_pvtol.toml"))
    d = derivation(str(SPECS / "robust_pvtol.toml"))
    controller = to_nlsys(mod)
    nx, nz = len(mod.PLANT_STATE_NAMES), len(mod.CONTROLLER_STATE_NAMES)
    assert controller.nstates == nz + nx  # the observer's states follow z
    plant = plant_nlsys(mod)
    closed = control.interconnect([plant, controller], inplist=[], outlist=list(mod.OUTPUT_NAMES))
    x0 = np.array(mod.DEFAULT_STATE[:nx])
    z0 = np.array(mod.DEFAULT_STATE[nx:])
    # The integrals start bumplessly, the observer at sigma = 0.
    s0 = np.concatenate([x0, z0])
    error = mod.optimality_error(0.0, s0)
    for name, value in zip(mod.INTEGRAL_NAMES, np.array(d.dynamics.bumpless) @ error, strict=True):
        z0[mod.CONTROLLER_STATE_NAMES.index(name)] = value
    beta = mod.OBSERVER_BANDWIDTH
    start = np.concatenate([x0, z0, beta * x0])
    times = np.linspace(0.0, 12.0, 121)
    # The plant is 15% heavier than the model (an interconnection hands its parameters
    # to every system, so the true mass is fixed inside this one).
    true = {"m": 1.15}
    heavy_plant = control.nlsys(
        lambda t, x, u, params: mod.plant(t, x, u, true),
        lambda t, x, u, params: np.concatenate([x, mod.outputs(t, x, true)]),
        inputs=list(mod.INPUT_NAMES),
        outputs=[*mod.PLANT_STATE_NAMES, *mod.OUTPUT_NAMES],
        states=list(mod.PLANT_STATE_NAMES),
        name="plant",
    )
    target = np.array([1.5 * np.sin(0.4 * 12.0), 2 + 0.8 * np.sin(0.3 * 12.0) - 0.5 * np.cos(2.4)])
    finals = {}
    for key, system in (("robust", controller), ("plain", to_nlsys(module("pvtol")))):
        heavy = control.interconnect(
            [heavy_plant, system], inplist=[], outlist=list(mod.OUTPUT_NAMES)
        )
        x_start = start if key == "robust" else np.array(module("pvtol").DEFAULT_STATE)
        # The solver at rtol 1e-6: the robust run ends 3.5014e-5 off the target against
        # 3.5043e-5 at rtol 1e-8 (the plain one 3.4753 at both), a change a millionth of
        # the bound it is held to (1% of the plain one's), in a third of the steps through
        # python-control (3.3 s -> 1.2 s CPU).
        response = control.input_output_response(
            heavy, times, 0, X0=x_start, solve_ivp_kwargs={"rtol": 1e-6, "atol": 1e-8}
        )
        finals[key] = float(np.linalg.norm(response.outputs[:, -1] - target))
        if key == "robust":
            robust = response
    # The plain law is off by the mismatch; the robust one holds the target.
    assert finals["plain"] > 0.3
    assert finals["robust"] < 0.01 * finals["plain"]
    response = robust
    # Every output of the controller is within the limits.
    u = np.array([controller.output(t, response.states[nx:, k], response.states[:nx, k])
                  for k, t in enumerate(times)])  # fmt: skip
    assert np.all(u >= np.array(mod.INPUT_LOW) - 1e-12)
    assert np.all(u <= np.array(mod.INPUT_HIGH) + 1e-12)
    assert closed.nstates == nx + nz + nx


def test_a_spec_with_references_takes_their_jets_as_inputs() -> None:
    from tvopt_codegen.interop import reference_inputs
    from tvopt_codegen.simulation.references import exact_jets

    spec = "unicycle_switch_refs"
    mod, d = module(spec), derivation(spec)
    controller = to_nlsys(mod)
    names = reference_inputs(mod)
    assert names[:3] == ["reference_o1x_d0", "reference_o1x_d1", "reference_o1x_d2"]
    assert controller.input_labels == [*mod.PLANT_STATE_NAMES, *names]
    jets = exact_jets(d, {})
    # A system that plays the nominal references as jets, named as the controller reads them.
    source = control.nlsys(
        None, lambda t, x, u, p: jets(t).ravel(), inputs=0, outputs=names, name="references"
    )
    closed = control.interconnect(
        [plant_nlsys(mod), controller, source], inplist=[], outlist=list(mod.OUTPUT_NAMES)
    )
    assert closed.ninputs == 0
    _reproduces_simulate(closed, mod, d)  # simulate: the nominal closed forms' exact jets


_STATIC_UNICYCLE = """
name = "static_unicycle"
[system]
states = ["px", "py", "theta", "v"]
inputs = ["a", "omega"]
[system.dynamics]
px = "v*cos(theta)"
py = "v*sin(theta)"
theta = "omega"
v = "a"
[system.outputs]
y1 = "px"
y2 = "py"
[objective]
f0 = "(y1 - 2*cos(0.3*t))**2 + (y2 - 2*sin(0.3*t))**2"
[error_dynamics]
poles = [-1.0, -2.0]
[simulation]
t_final = 6.0
initial_state = { px = 0.0, py = 0.0, theta = 0.0, v = 1.0 }
"""


def test_a_static_law_undefined_at_zero_inputs_runs_and_fails_only_at_a_real_zero_state(
    tmp_path: Any,
) -> None:
    """python-control's first pass hands a static controller all-zero inputs (v = 0 here,
    where det R = v vanishes): the interconnection still reproduces simulate from v = 1,
    and a plant state that really is all zero raises the law's error, never a number."""
    path = tmp_path / "static_unicycle.toml"
    path.write_text(_STATIC_UNICYCLE, encoding="utf-8")
    mod, d = module(str(path)), derivation(str(path))
    assert to_nlsys(mod).nstates == 0
    closed = control.interconnect(
        [plant_nlsys(mod), to_nlsys(mod)], inplist=[], outlist=list(mod.OUTPUT_NAMES)
    )
    _reproduces_simulate(closed, mod, d)
    with pytest.raises(ArithmeticError, match="singular"):
        control.input_output_response(closed, [0.0, 0.1], 0, X0=np.zeros(4))
    # The controller's own output at zero inputs, asked twice in a row, is the error too.
    alone = to_nlsys(mod)
    with pytest.raises(ArithmeticError):
        alone.output(0.0, [], np.zeros(4))
        alone.output(0.0, [], np.zeros(4))
