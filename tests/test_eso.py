"""The extended-state observer ([robust.eso]): the lumped disturbance, in the law's coordinates.

Checked with numbers: the discrete gains place every pole of the estimation error; on
the model the observer changes nothing (the plain law's input, its certificate); Python
and C step to the bit; a mismatch outside the span of G (the drag vehicle's) and a
mass-matrix plant's are rejected, the latter as in its [system.dynamics] twin.
"""

from __future__ import annotations

import math
import tomllib
from types import ModuleType
from typing import Any

import numpy as np
import pytest

from tvopt_codegen.derivation import derive
from tvopt_codegen.derivation.rejection import continuous_gains, discrete_gains
from tvopt_codegen.errors import SpecError
from tvopt_codegen.lowering.ir import lower
from tvopt_codegen.simulation import load_controller, resolve_options, simulate
from tvopt_codegen.simulation.direct import plant_function
from tvopt_codegen.simulation.sampled import hold
from tvopt_codegen.spec import spec_from_dict

from .conftest import ROOT, SPECS

ESO = {"eso": {"bandwidth": 20.0}}
#: The true vehicle: 10% heavier, 10% more drag and inertia than the model.
HEAVIER = {"m": 1.1, "c": 0.44, "J": 0.11, "cr": 0.11}

_CACHE: dict[tuple[str, bool], tuple[Any, ModuleType, ModuleType]] = {}


def _data(name: str, robust: dict[str, Any] | None) -> dict[str, Any]:
    folder = ROOT / "tvopt_codegen" / "examples"
    path = folder / f"{name}.toml" if (folder / f"{name}.toml").exists() else SPECS / name
    with path.open("rb") as stream:
        data = tomllib.load(stream)
    if robust is not None:
        data["robust"] = robust
    return data


def _both(name: str, eso: bool = True) -> tuple[Any, ModuleType, ModuleType]:
    """(derivation, Python module, C module) of a spec, with or without the observer."""
    key = (name, eso)
    if key not in _CACHE:
        d = derive(spec_from_dict(_data(name, ESO if eso else None)))
        kernels = lower(d)
        _CACHE[key] = (d, load_controller(kernels, "python"), load_controller(kernels, "c"))
    return _CACHE[key]


@pytest.mark.parametrize("order", [1, 2, 3])
def test_the_discrete_gains_are_sympys_exact_solution(order: int) -> None:
    # discrete_gains solves in Fractions; SymPy's solve of the same equations (the way
    # it was computed before, 10 s at order 5) is the reference, float for float.
    import sympy as sp

    n = order + 1
    gamma, lam = sp.Symbol("gamma"), sp.Symbol("lambda")
    chain = sp.Matrix(n, n, lambda i, j: sp.Rational(1, math.factorial(j - i)) if j >= i else 0)
    unknowns = sp.symbols(f"c0:{n}")
    error = chain - sp.Matrix(unknowns) * chain[0, :]
    polynomial = sp.Poly((lam * sp.eye(n) - error).det(method="berkowitz"), lam)
    target = sp.Poly((lam - (1 - gamma)) ** n, lam)
    equations = [
        sp.expand(a - b)
        for a, b in zip(polynomial.all_coeffs()[1:], target.all_coeffs()[1:], strict=True)
    ]
    solution = sp.solve(equations, unknowns, dict=True)[0]
    want = tuple(
        tuple(
            float(sp.Poly(sp.expand(solution[c]), gamma).coeff_monomial(gamma**m))
            for m in range(1, n + 1)
        )
        for c in unknowns
    )
    assert discrete_gains(order) == want


@pytest.mark.parametrize("order", [1, 2, 3, 4, 5])
@pytest.mark.parametrize("h", [1e-3, 0.01, 0.2])
def test_the_discrete_gains_put_every_pole_of_the_error_at_exp_minus_omega_h(
    order: int, h: float
) -> None:
    omega = 20.0
    n = order + 1
    gamma = -math.expm1(-omega * h)
    gains = []
    for j, coefficients in enumerate(discrete_gains(order)):
        value = sum(c * gamma ** (m + 1) for m, c in enumerate(coefficients))
        gains.append(value / h**j)
    chain = np.array(
        [
            [h ** (j - i) / math.factorial(j - i) if j >= i else 0.0 for j in range(n)]
            for i in range(n)
        ]
    )
    error = (np.eye(n) - np.outer(gains, np.eye(n)[0])) @ chain
    beta = math.exp(-omega * h)
    # The characteristic polynomial, not the eigenvalues: an n-fold root moves by eps^(1/n).
    np.testing.assert_allclose(np.poly(error), np.poly([beta] * n), atol=1e-9)
    # Sampled fast, gain j is l_(j+1) h, the continuous gain (C(n, j+1) omega^(j+1)) over a step.
    if h == 1e-3:
        for j, (value, continuous) in enumerate(
            zip(gains, continuous_gains(order, omega), strict=True)
        ):
            assert value == pytest.approx(continuous * h, rel=0.2), j


def test_on_the_model_the_observer_is_the_plain_law_and_its_certificate_holds() -> None:
    d, py, c = _both("drag_vehicle")
    _, plain, _ = _both("drag_vehicle", eso=False)
    assert d.rejection is not None and d.rejection.orders == (4, 4)
    names = d.closed_loop.state_names
    start = dict(zip(names, d.closed_loop.initial_state, strict=True))
    # The default state starts the estimates at Phi(x0): y, y' of each output as measured.
    assert start["eso_x_0"] == start["px"] and start["eso_y_1"] == start["vy"]
    assert start["eso_x_d"] == 0.0 and start["eso_y_d"] == 0.0
    # At any state where the estimates are Phi(x) and d_hat = 0, the plain law's input.
    rng = np.random.default_rng(7)
    eta = py._eso_start_1
    for _ in range(5):
        s = np.array(py.DEFAULT_STATE) + 0.2 * rng.standard_normal(len(names))
        s[6] = 1.0 + abs(s[6])
        rows = [names.index(n) for chain in d.rejection.states for n in chain]
        s[[r for r in rows if not names[r].endswith("_d")]] = eta(
            0.5, s.tolist(), list(py.PARAMETERS.values())
        )
        s[[r for r in rows if names[r].endswith("_d")]] = 0.0
        reduced = s[[i for i in range(len(names)) if i not in rows]]
        np.testing.assert_allclose(py.control(0.5, s), plain.control(0.5, reduced), rtol=1e-12)
        np.testing.assert_allclose(c.control(0.5, s), plain.control(0.5, reduced), rtol=1e-12)
    # The continuous closed loop on the model: E' = H E along the run (the certificate).
    result = simulate(d, py, resolve_options(d, points=201))
    assert result.passed, result.failures
    assert result.deviation < 1e-6


def _run(
    module: ModuleType, h: float, steps: int, params: dict[str, float], plant: ModuleType
) -> np.ndarray:
    """The sampled loop of ``module``'s controller on ``plant``'s plant (a module of the same
    system: the C controller's runs take the Python module's plant, the same model)."""
    x = np.array(module.DEFAULT_STATE[: len(module.PLANT_STATE_NAMES)])
    controller = module.Controller(x)
    field = plant_function(plant, params)
    with np.errstate(all="ignore"):
        for k in range(1, steps + 1):
            x = hold(field, (k - 1) * h, k * h, x, controller.u)
            controller.step(k * h, x)
    return x


def test_python_and_c_step_to_the_bit_on_a_mismatched_plant() -> None:
    _, py, c = _both("drag_vehicle")
    x = np.array(py.DEFAULT_STATE[:6])
    a, b = py.Controller(x), c.Controller(x)
    assert np.array_equal(a.state, b.state)
    h = 1e-3
    field = plant_function(py, HEAVIER)
    for k in range(1, 801):
        with np.errstate(all="ignore"):
            x = hold(field, (k - 1) * h, k * h, x, a.u)
        ua, ub = a.step(k * h, x), b.step(k * h, x)
        assert np.array_equal(ua, ub), k
        assert np.array_equal(a.state, b.state), k
    # The lumped disturbance it has found: the heavier, draggier plant's, not zero.
    names = py.CONTROLLER_STATE_NAMES
    lumped = a.state[[names.index("eso_x_d"), names.index("eso_y_d")]]
    assert np.all(np.abs(lumped) > 1e-3)
    # A step that is not the sample time before it: the gains again, still to the bit.
    for t in (0.8015, 0.8040, 0.8041):
        assert np.array_equal(a.step(t, x), b.step(t, x))
        assert np.array_equal(a.state, b.state)


def test_a_mismatch_outside_the_span_of_g_is_rejected() -> None:
    _, py, c = _both("drag_vehicle")
    _, _, plain = _both("drag_vehicle", eso=False)
    h, t_final = 1e-3, 12.0
    steps = round(t_final / h)
    target = np.array([3 * math.cos(0.3 * t_final), 3 * math.sin(0.3 * t_final)])
    error = np.linalg.norm(_run(c, h, steps, HEAVIER, py)[:2] - target)
    baseline = np.linalg.norm(_run(plain, h, steps, HEAVIER, py)[:2] - target)
    # The plain law ends ~8 cm off the circle; the observer within 1% of that.
    assert baseline > 0.05
    assert error < 0.01 * baseline


MASS = """
name = "arm2_dynamics"
[system]
states = ["q1", "q2", "dq1", "dq2"]
inputs = ["tau1", "tau2"]
[system.dynamics]
q1 = "dq1"
q2 = "dq2"
[system.outputs]
y1 = "q1"
y2 = "q2"
[parameters]
a1 = 3.0
a2 = 0.5
a3 = 0.4
g1 = 9.0
g2 = 2.0
"""


def test_a_mass_matrix_plant_gets_what_its_dynamics_twin_gets() -> None:
    mass_data = _data("arm2_mass.toml", ESO)
    twin = tomllib.loads(MASS)
    forces = (
        "a2*sin(q2)*dq2*(2*dq1 + dq2) - g1*cos(q1) - g2*cos(q1 + q2)",
        "-a2*sin(q2)*dq1**2 - g2*cos(q1 + q2)",
    )
    m11, m12, m22 = "(a1 + 2*a2*cos(q2))", "(a3 + a2*cos(q2))", "a3"
    det = f"({m11}*{m22} - {m12}**2)"
    f1, f2 = (f"({force} + {tau})" for force, tau in zip(forces, ("tau1", "tau2"), strict=True))
    dynamics = twin["system"]["dynamics"]
    dynamics["dq1"] = f"({m22}*{f1} - {m12}*{f2})/{det}"
    dynamics["dq2"] = f"({m11}*{f2} - {m12}*{f1})/{det}"
    for key in ("objective", "error_dynamics", "simulation"):
        twin[key] = mass_data[key]
    twin["robust"] = ESO
    lowered = [lower(derive(spec_from_dict(data))) for data in (mass_data, twin)]
    modules = [load_controller(kernels, "c") for kernels in lowered]
    # Each arm's own plant (M factored at run time, and the twin's explicit dynamics), by
    # its Python module's kernel: the same model as the C module's plant, a tenth the cost.
    twins = [load_controller(kernels, "python") for kernels in lowered]
    heavier = {"a1": 3.3, "a2": 0.55, "a3": 0.44}
    fields = [plant_function(twin_module, heavier) for twin_module in twins]
    h = 1e-3
    x = [np.array(m.DEFAULT_STATE[:4]) for m in modules]
    controllers = [m.Controller(xi) for m, xi in zip(modules, x, strict=True)]
    assert np.allclose(controllers[0].state, controllers[1].state, rtol=1e-13, atol=1e-13)
    inputs: list[list[np.ndarray]] = [[], []]
    for k in range(1, 6001):
        for i, (field, ctrl) in enumerate(zip(fields, controllers, strict=True)):
            with np.errstate(all="ignore"):
                x[i] = hold(field, (k - 1) * h, k * h, x[i], ctrl.u)
            ctrl.step(k * h, x[i])
            inputs[i].append(np.array(ctrl.u))
    # Every step's inputs agree, compared at once (6,000 assert_allclose calls took seconds).
    np.testing.assert_allclose(inputs[0], inputs[1], rtol=1e-7, atol=1e-9)
    # And both track the target better than the plain law on the heavier arm.
    plain = load_controller(lower(derive(spec_from_dict(_data("arm2_mass.toml", None)))), "c")
    target = np.array([math.sin(6.0), 0.5 * math.cos(6.0)])
    baseline = np.linalg.norm(_run(plain, h, 6000, heavier, twins[0])[:2] - target)
    # 2.0e-3 against 1.1e-2 at 6 s: the arm's lumped term moves with the target, and
    # the observer's estimate lags it (docs/robust.md).
    assert np.linalg.norm(x[0][:2] - target) < 0.25 * baseline


def test_a_bandwidth_that_is_not_positive_is_refused() -> None:
    data = _data("drag_vehicle", {"eso": {"bandwidth": -1.0}})
    with pytest.raises(SpecError, match=r"robust\.eso\.bandwidth: must be positive"):
        spec_from_dict(data)
    data = _data("drag_vehicle", {"eso": {"bandwith": 5.0}})
    with pytest.raises(SpecError, match=r"robust\.eso"):
        spec_from_dict(data)
    # Its gains are powers of the bandwidth up to r + 1: bounded where they stay doubles.
    for bandwidth in (1e300, 1e-300):
        data = _data("drag_vehicle", {"eso": {"bandwidth": bandwidth}})
        with pytest.raises(
            SpecError, match=r"robust\.eso\.bandwidth: .* is outside \[1e-06, 1e\+06\]"
        ):
            spec_from_dict(data)


def test_the_barriers_read_the_measured_output_not_its_estimate() -> None:
    """With the observer, y^(j) for j >= 1 are estimates but y is the plant's h(x).

    The fuzzer's case ``urdf:3:equality+eso+fmu+inequality:36935662`` stopped with
    OutsideBarrierError where the plant's outputs were 0.11 inside the barrier: the
    margins read the estimate eta_0, which a 10 ms loop had swung out. The barrier protects
    the plant's outputs, and the objective's first row is theirs.
    """
    data = _data("drag_vehicle", ESO)
    data["constraints"] = {"keep": "x <= 3.5"}
    module = load_controller(lower(derive(spec_from_dict(data))), "python")
    names = module.STATE_NAMES
    s = np.array(module.DEFAULT_STATE)
    assert s[names.index("px")] == 2.5 and s[names.index("eso_x_0")] == 2.5
    estimate_out = s.copy()
    estimate_out[names.index("eso_x_0")] = 4.0
    assert np.all(np.isfinite(module.control(0.0, estimate_out)))
    plant_out = s.copy()
    plant_out[names.index("px")] = 4.0
    with pytest.raises(module.OutsideBarrierError):
        module.control(0.0, plant_out)


def test_a_step_that_fails_changes_nothing_in_either_backend() -> None:
    """A step whose observer overflows (a step of 1e300 s) is an input error in Python and
    C alike, and leaves the controller, the observer's gains included, as it was: the next
    good step gives what it would have given without the failed one, to the bit."""
    _, py, c = _both("drag_vehicle")
    x = np.array(py.DEFAULT_STATE[:6])
    controllers = [py.Controller(x), c.Controller(x), py.Controller(x)]
    for k in range(1, 4):
        for controller in controllers:
            controller.step(k * 1e-3, x)
    for controller in controllers[:2]:
        before = controller.state.copy()
        with pytest.raises(
            py.NonFiniteInputError if controller is controllers[0] else c.NonFiniteInputError
        ):
            controller.step(1e300, x)
        assert np.array_equal(controller.state, before)
        assert controller.t == pytest.approx(3e-3)
    # The untouched third controller is the reference: a step of another length, after the
    # failed one, recomputes the gains in all three alike.
    results = [controller.step(0.0045, x) for controller in controllers]
    assert np.array_equal(results[0], results[2]) and np.array_equal(results[1], results[2])
    assert np.array_equal(controllers[0].state, controllers[2].state)
    assert np.array_equal(controllers[1].state, controllers[2].state)
    # A state at the edge of the doubles is refused before the observer sees it.
    for controller in controllers[:2]:
        with pytest.raises(ArithmeticError):
            controller.step(0.005, np.array([np.inf, *x[1:]]))
