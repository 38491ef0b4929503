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
