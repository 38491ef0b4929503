"""The stateful sampled-data controller: Controller in both backends, and its C struct."""

from __future__ import annotations

import math
from pathlib import Path
from types import ModuleType

import numpy as np
import pytest

from tvopt_codegen.spec.implicit import implicit_values
from tvopt_codegen.symbolic.border import to_sympy

from .conftest import ALL_SPECS, derivation, module
from .test_c_backend import _write_c, c_module, run_sanitized


def _both(spec: str, tmp_path_factory: pytest.TempPathFactory) -> tuple[ModuleType, ModuleType]:
    return module(spec), c_module(spec, tmp_path_factory)


def _plant_rates(mod: ModuleType, t: float, x: np.ndarray, z: np.ndarray) -> np.ndarray:
    """dx/dt of the plant under the law at (t, [x; z]): a stand-in for measured motion."""
    return np.asarray(mod.rhs(t, np.concatenate([x, z])))[: len(x)]


@pytest.mark.parametrize("spec", ALL_SPECS)
def test_python_and_c_controllers_agree_along_a_sampled_run(
    spec: str, tmp_path_factory: pytest.TempPathFactory
) -> None:
    py, c = _both(spec, tmp_path_factory)
    n = len(py.PLANT_STATE_NAMES)
    assert py.PLANT_STATE_NAMES + py.CONTROLLER_STATE_NAMES == py.STATE_NAMES
    assert c.PLANT_STATE_NAMES == py.PLANT_STATE_NAMES
    x = np.array(py.DEFAULT_STATE[:n])
    a, b = py.Controller(x), c.Controller(x)
    # The law's input, within the limits where the spec has [limits].
    low = getattr(py, "INPUT_LOW", -np.inf)
    high = getattr(py, "INPUT_HIGH", np.inf)
    expected = np.clip(py.control(0.0, np.array(py.DEFAULT_STATE)), low, high)
    np.testing.assert_array_equal(a.u, expected)
    h = 2e-3
    for k in range(1, 400):
        t = k * h
        ua, ub = a.step(t, x), b.step(t, x)
        np.testing.assert_allclose(ua, ub, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(a.state, b.state, rtol=1e-12, atol=1e-12)
        assert a.t == b.t == t
        x = x + h * _plant_rates(py, t, x, a.state)
    assert np.all(np.isfinite(x))


def test_the_chains_move_by_their_exact_taylor_polynomial(
    tmp_path_factory: pytest.TempPathFactory,
) -> None:
    """PVTOL's thrust is integrated twice: z = (thrust, thrust'), thrust'' = w held."""
    for mod in _both("pvtol", tmp_path_factory):
        x = np.array(mod.DEFAULT_STATE[:6])
        z0 = np.array([9.0, 0.3])
        controller = mod.Controller(x, t0=1.0, z0=z0)
        s = np.concatenate([x, z0])
        drive = mod.rhs(1.0, s)[-1]
        h = 0.25
        controller.step(1.0 + h, x)
        expected = [z0[0] + z0[1] * h + drive * h * h / 2, z0[1] + drive * h]
        np.testing.assert_allclose(controller.state, expected, rtol=1e-15, atol=1e-15)
        # The input it returns is the law's at the advanced state.
        np.testing.assert_allclose(
            controller.u, mod.control(1.0 + h, np.concatenate([x, expected])), rtol=1e-14
        )


def test_padding_states_are_driven_by_y_imp(tmp_path_factory: pytest.TempPathFactory) -> None:
    from .conftest import SPECS

    spec = str(SPECS / "nonuniform.toml")
    for mod in _both(spec, tmp_path_factory):
        assert mod.CONTROLLER_STATE_NAMES == ("xi_y1_1",)
        x = np.array(mod.DEFAULT_STATE[:3])
        controller = mod.Controller(x, z0=[0.5])
        drive = mod.rhs(0.0, np.concatenate([x, [0.5]]))[-1]
        controller.step(0.1, x)
        np.testing.assert_allclose(controller.state, [0.5 + 0.1 * drive], rtol=1e-15)


@pytest.mark.parametrize("spec", ["integrator", "flexible_joint"])
def test_a_controller_without_states(spec: str, tmp_path_factory: pytest.TempPathFactory) -> None:
    for mod in _both(spec, tmp_path_factory):
        assert mod.CONTROLLER_STATE_NAMES == ()
        x = np.array(mod.DEFAULT_STATE)
        controller = mod.Controller(x)
        assert controller.state.shape == (0,)
        np.testing.assert_allclose(controller.step(0.3, x), mod.control(0.3, x), rtol=1e-14)


@pytest.mark.parametrize("backend", ["python", "c"])
def test_bad_steps_are_errors_that_change_nothing(
    backend: str, tmp_path_factory: pytest.TempPathFactory
) -> None:
    py, c = _both("unicycle_switch", tmp_path_factory)
    mod = py if backend == "python" else c
    x = np.array(mod.DEFAULT_STATE[:3])
    controller = mod.Controller(x, params={"b": 2.0})
    # The parameters are the controller's own from then on.
    np.testing.assert_allclose(
        controller.step(0.5, x),
        mod.control(0.5, np.concatenate([x, controller.state]), {"b": 2.0}),
        rtol=1e-14,
    )
    before = (controller.t, controller.state, controller.u)

    def unchanged() -> None:
        assert controller.t == before[0]
        np.testing.assert_array_equal(controller.state, before[1])
        np.testing.assert_array_equal(controller.u, before[2])

    with pytest.raises(ValueError, match=r"t = 0.25 is before the last step's time 0.5"):
        controller.step(0.25, x)
    unchanged()
    with pytest.raises(ValueError, match=r"x must have shape \(3,\), got \(4,\)"):
        controller.step(0.6, np.append(x, 1.0))
    unchanged()
    bad = x.copy()
    bad[2] = math.nan
    with pytest.raises(mod.NonFiniteInputError, match="theta = nan is not finite") as info:
        controller.step(0.6, bad)
    assert info.value.index == 2
    unchanged()
    with pytest.raises(mod.NonFiniteInputError, match="t = inf is not finite"):
        controller.step(math.inf, x)
    unchanged()
    with pytest.raises(mod.NonFiniteInputError, match="v = inf is not finite"):
        mod.Controller(x, z0=[math.inf])
    # The law itself fails: v = 0 makes R singular; the controller stays where it was.
    stopped = mod.Controller(x, z0=[1.0])
    with pytest.raises(mod.SingularDecouplingError, match=r"singular \(column 0\)"):
        mod.Controller(x, z0=[0.0])
    assert stopped.t == 0.0
    # A step of zero length is allowed and changes nothing but the input's evaluation.
    u = controller.step(0.5, x)
    np.testing.assert_array_equal(u, before[2])
    unchanged()


def test_reset_starts_again(tmp_path_factory: pytest.TempPathFactory) -> None:
    for mod in _both("unicycle_switch", tmp_path_factory):
        x = np.array(mod.DEFAULT_STATE[:3])
        controller = mod.Controller(x)
        controller.step(1.0, x)
        controller.reset(x, t0=2.0, z0=[0.7])
        assert controller.t == 2.0
        np.testing.assert_array_equal(controller.state, [0.7])
        assert repr(controller).startswith("<unicycle_switch Controller")


C_DRIVER = """
#include "{name}.h"
#include <math.h>
#include <stdio.h>
#include <string.h>

int main(void)
{{
    {name}_controller_t c, copy;
    double x[{P}_N_PLANT_STATES], u[{P}_N_INPUTS];
    int i, k, status;
    for (i = 0; i < {P}_N_PLANT_STATES; ++i) x[i] = {name}_default_state[i];
    status = {name}_controller_init(&c, 0.0, x, NULL, NULL);
    if (status != {P}_OK) return 10 + status;
    for (k = 1; k <= 100; ++k) {{
        status = {name}_controller_step(&c, 1e-3 * k, x, u);
        if (status != {P}_OK) return 20 + status;
    }}
    copy = c;
    if ({name}_controller_step(&c, 0.05, x, u) != {P}_DECREASING_TIME) return 30;
    if (memcmp(&c, &copy, sizeof c) != 0) return 31;
    x[0] = NAN;
    if ({name}_controller_step(&c, 0.2, x, u) != {P}_NONFINITE_INPUT) return 32;
    if (memcmp(&c, &copy, sizeof c) != 0) return 33;
    if ({name}_controller_size() != sizeof c) return 34;
    printf("%.17g %.17g\\n", c.t, u[0]);
    return 0;
}}
"""


@pytest.mark.parametrize("spec", ["pvtol", "unicycle_ring", "integrator"])
def test_the_c_struct_under_sanitizers(spec: str, tmp_path: Path) -> None:
    source = _write_c(spec, tmp_path)
    name = derivation(spec).spec.name
    out = run_sanitized(C_DRIVER.format(name=name, P=name.upper()), source, tmp_path)
    t, u0 = map(float, out.split())
    assert t == pytest.approx(0.1) and math.isfinite(u0)


@pytest.mark.parametrize("spec", ALL_SPECS)
def test_plant_and_outputs_are_the_model(
    spec: str, tmp_path_factory: pytest.TempPathFactory
) -> None:
    """The generated plant against sympy's own evaluation of f + G u and h.

    The model crosses to SymPy (the identity on the SymPy engine): the printers and the
    CSE that wrote the plant walk the engine's trees, and SymPy's evaluation is not theirs.
    """
    import sympy as sp

    d = derivation(spec)
    model = d.model
    memo: dict[object, object] = {}
    f, G, h = (to_sympy(matrix, memo) for matrix in (model.f, model.G, model.h))
    inputs = sp.Matrix([to_sympy(u, memo) for u in model.u])
    rng = np.random.default_rng(5)
    defaults = dict(zip(model.params, model.defaults, strict=True))
    for mod in _both(spec, tmp_path_factory):
        x = np.array(mod.DEFAULT_STATE[: len(model.x)]) + 0.1 * rng.standard_normal(len(model.x))
        u = rng.uniform(0.5, 1.5, len(model.u))
        values = {**dict(zip(model.x, x, strict=True)), **dict(zip(model.u, u, strict=True))}
        values |= {q: v for q, v in defaults.items()}
        if model.mechanics is not None:
            # M^-1 F and M^-1 B by numpy's dense solve (the generated code: its LDL^T).
            solved = implicit_values(model.mechanics, values)
            values |= {sym: float(v[0]) for sym, v in solved.items()}
        at = {to_sympy(sym, memo): value for sym, value in values.items()}
        expected = (f + G * inputs).xreplace(at)
        np.testing.assert_allclose(
            mod.plant(0.3, x, u), np.array(expected, dtype=float).ravel(), rtol=1e-13, atol=1e-14
        )
        np.testing.assert_allclose(
            mod.outputs(0.3, x),
            np.array(h.xreplace(at), dtype=float).ravel(),
            rtol=1e-13,
            atol=1e-14,
        )
        batch = mod.plant(0.3, np.stack([x, x], 1), np.stack([u, u], 1))
        np.testing.assert_array_equal(batch[:, 1], mod.plant(0.3, x, u))
        with pytest.raises(ValueError, match="as many columns"):
            mod.plant(0.3, np.stack([x, x], 1), u)
        bad = u.copy()
        bad[0] = np.nan
        with pytest.raises(mod.NonFiniteInputError, match=r"the input is not finite \(column 0\)"):
            mod.plant(0.3, x, bad)
