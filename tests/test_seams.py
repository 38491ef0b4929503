"""Features that work alone and failed together (issue 46), one test per kind of seam.

- the disturbance observer on a plant in mass-matrix form: the jet kernel's outputs were
  bound to the plan's values in another order, the observer's f(x) read as the mass
  matrix, and the law was undefined at every state;
- the observer on the URDF arm: a template indexed a sparse output's result by the
  element's loop, and ``generate`` stopped;
- hostile step sequences: Python and C raise the same error class for the same input;
- no generated routine returns a value that is not finite with status OK (the reference
  estimator's jets far ahead, the observer at an extreme bandwidth).
"""

from __future__ import annotations

import ctypes
import dataclasses
import math
import shutil
import tomllib
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np
import pytest

from tvopt_codegen.cli import main
from tvopt_codegen.contract import Status
from tvopt_codegen.derivation import derive
from tvopt_codegen.lowering.ir import check_binding, lower
from tvopt_codegen.simulation import load_controller
from tvopt_codegen.simulation.sampled import hold
from tvopt_codegen.spec import spec_from_dict

from .conftest import ROOT, SPECS, import_file
from .conftest import kernels as shared_kernels

pytestmark = pytest.mark.skipif(
    not any(shutil.which(cc) for cc in ("gcc", "cc", "clang")), reason="no C compiler"
)

EXAMPLES = ROOT / "tvopt_codegen" / "examples"


def _table(path: Path, robust: dict[str, Any] | None = None) -> dict[str, Any]:
    with path.open("rb") as stream:
        data = tomllib.load(stream)
    if robust is not None:
        data["robust"] = robust
    return data


_CACHE: dict[str, tuple[Any, ModuleType, ModuleType]] = {}


def _both(path: Path, robust: dict[str, Any] | None = None) -> tuple[Any, ModuleType, ModuleType]:
    """(kernels, Python module, C module) of the spec at ``path`` with ``[robust]``.

    The spec as its file has it (``robust`` None) is conftest's, derived and lowered once
    per worker for every test that asks, and its C library (which differs only in the
    stamp's file name) is compiled once per run for them all.
    """
    key = f"{path}|{robust!r}"
    if key not in _CACHE:
        if robust is None:
            kernels = shared_kernels(path.stem if path.parent == EXAMPLES else str(path))
        else:
            kernels = lower(derive(spec_from_dict(_table(path, robust))))
        _CACHE[key] = (
            kernels,
            load_controller(kernels, "python"),
            load_controller(kernels, "c"),
        )
    return _CACHE[key]


# ------------------------------------------------- the observer on a mass-matrix plant

ARM2 = SPECS / "arm2_mass.toml"
OBSERVER = {"observer": {"bandwidth": 20.0}}
#: The true arm: heavier links than the model (a1, a3 are inertias, a2 their coupling).
HEAVIER = {"a1": 3.4, "a2": 0.55, "a3": 0.46}


def test_the_plan_binds_every_kernel_output_by_name() -> None:
    kernels, _, _ = _both(ARM2, OBSERVER)
    plan = kernels.plan
    jet = next(step for step in plan.steps if step.kernel == "jet")
    # Mass matrix and observer together: the jet returns both, in the plan's order.
    assert jet.results[-4:] == ("mass", "mass_pivot", "drift", "g")
    assert [out.name for out in kernels["jet"].outputs][-4:] == list(jet.results[-4:])
    # The old order (the observer's f and G before M) is refused at generation time.
    swapped = dataclasses.replace(
        jet, results=(*jet.results[:-4], "drift", "g", "mass", "mass_pivot")
    )
    steps = tuple(swapped if step is jet else step for step in plan.steps)
    with pytest.raises(RuntimeError, match="binds kernel jet's outputs"):
        check_binding(kernels.kernels, dataclasses.replace(plan, steps=steps))


def test_the_observer_on_a_mass_matrix_plant_closes_the_loop_in_both_backends() -> None:
    _, py, c = _both(ARM2, OBSERVER)
    _, plain, _ = _both(ARM2)
    n = len(py.PLANT_STATE_NAMES)
    s = np.array(py.DEFAULT_STATE) + np.array([0.3, -0.2, 0.5, 0.1])
    # The observer leaves the law alone: the same input as without it, at any state.
    for t in (0.0, 1.3):
        np.testing.assert_allclose(py.control(t, s), plain.control(t, s), rtol=1e-14)
        np.testing.assert_allclose(c.control(t, s), plain.control(t, s), rtol=1e-13)
    # Its f(x) and G(x) are the plant's: a = M^-1 F and W = M^-1 B, solved by LDL^T.
    p = np.array(list(py.PARAMETERS.values()))
    ds, u, drift, g = py._law(0.4, s[:, None], p)
    np.testing.assert_allclose(drift[:, 0], py.plant(0.4, s[:n], [0.0, 0.0]), rtol=1e-14)
    for i, e in enumerate(np.eye(2)):
        column = np.asarray(py.plant(0.4, s[:n], e)) - np.asarray(py.plant(0.4, s[:n], 0 * e))
        np.testing.assert_allclose(g[:, 0].reshape(n, 2)[:, i], column, atol=1e-14)
    # A sampled closed loop on the heavier arm: every step OK, Python equal to C.
    x = np.array(py.DEFAULT_STATE[:n])
    a, b = py.Controller(x), c.Controller(x)
    h = 2e-3
    for k in range(1, 1501):
        x = hold(lambda t, x, u: np.asarray(py.plant(t, x, u, HEAVIER)), (k - 1) * h, k * h, x, a.u)
        ua, ub = a.step(k * h, x), b.step(k * h, x)
        np.testing.assert_allclose(ua, ub, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(a.disturbance, b.disturbance, rtol=1e-10, atol=1e-12)
    assert np.all(np.isfinite(x))
    # The estimate is the matched disturbance the heavier links make: not zero.
    assert np.all(np.abs(a.disturbance) > 1e-2)
    # Tracking f0's target (sin t, 0.5 cos t) to the filter's lag.
    target = np.array([math.sin(3.0), 0.5 * math.cos(3.0)])
    assert np.linalg.norm(x[:2] - target) < 5e-3


def test_a_sweep_of_the_observer_on_a_mismatched_mass_matrix_has_no_failures() -> None:
    pytest.importorskip("pyarrow")
    from tvopt_codegen.sweep import (  # noqa: PLC0415
        Distribution,
        SweepOptions,
        run_sample,
        summarize,
        sweep_program,
    )

    mismatch = (
        ("a1", Distribution("normal", (3.0, 0.3))),
        ("a3", Distribution("normal", (0.4, 0.04))),
    )
    options = SweepOptions(
        samples=4, seed=3, t_final=5.0, sample_time=2e-3, points=51, plant_params=mismatch
    )
    errors = {}
    for robust in (OBSERVER, None):
        kernels, _, _ = _both(ARM2, robust)
        program = sweep_program(kernels)
        results = [run_sample(program, options, i) for i in range(4)]
        rows = [result.row for result in results]
        assert [row["status"] for row in rows] == ["ok"] * 4
        summary = summarize(results, 4, False)
        assert summary.outcomes == {"ok": 4} and summary.failure_rate == 0.0
        errors[robust is not None] = [row["final_error"] for row in rows]
    # The observer rejects the mismatch: each sample tracks 5x closer than the plain law.
    assert all(o < p / 5 for o, p in zip(errors[True], errors[False], strict=True))


# ------------------------------------------------------- the observer on the URDF arm


def test_the_observer_on_the_urdf_arm_generates_and_steps_in_both_backends(
    tmp_path: Path,
) -> None:
    text = (EXAMPLES / "ur5_tip.toml").read_text(encoding="utf-8")
    spec = tmp_path / "ur5_observed.toml"
    spec.write_text(text + "\n[robust.observer]\nbandwidth = 20.0\n", encoding="utf-8")
    assert main(["generate", str(spec), "--out", str(tmp_path / "py"), "--quiet"]) == 0
    out = tmp_path / "c"
    assert main(["generate", str(spec), "--out", str(out), "--backend", "c", "--quiet"]) == 0
    py = import_file(tmp_path / "py" / "ur5_tip.py", "_tvopt_seams_ur5_py")
    c = import_file(out / "ur5_tip_c.py", "_tvopt_seams_ur5_c")
    # G = M^-1 B has 36 structural zeros: the sparse output the template mis-indexed.
    assert py._OBSERVED == tuple(range(6, 12))
    n = len(py.PLANT_STATE_NAMES)
    x = np.array(py.DEFAULT_STATE[:n])
    heavier = {name: 1.1 * value for name, value in py.PARAMETERS.items() if name[:2] == "m_"}
    a, b = py.Controller(x), c.Controller(x)
    h = 2e-3
    for k in range(1, 41):
        x = x + h * np.asarray(py.plant(k * h, x, a.u, heavier))
        ua, ub = a.step(k * h, x), b.step(k * h, x)
        np.testing.assert_allclose(ua, ub, rtol=1e-12, atol=1e-12)
    assert np.all(np.isfinite(a.disturbance)) and np.any(np.abs(a.disturbance) > 1e-3)
    np.testing.assert_allclose(a.disturbance, b.disturbance, rtol=1e-10, atol=1e-12)


# ------------------------------------------------------------ hostile step sequences

NAN, INF = math.nan, math.inf
#: (start time, then (time, offset of the plant state from its default) per step).
HOSTILE: dict[str, list[tuple[float, float]]] = {
    "t = 1e200": [(0.0, 0.0), (1e200, 0.0)],
    "start at 1e200": [(1e200, 0.0), (1e200 * (1 + 1e-15), 0.01)],
    "t = 1e308": [(0.0, 0.0), (1e308, 0.0)],
    "t = max": [(0.0, 0.0), (1.7976931348623157e308, 0.0)],
    "from -1e308": [(-1e308, 0.0), (0.0, 0.01)],
    "backwards": [(0.0, 0.0), (1.0, 0.01), (0.5, 0.01)],
    "tiny steps": [(0.0, 0.0), (1e-300, 0.01), (2e-300, 0.02)],
    "denormal step": [(0.0, 0.0), (5e-324, 0.01)],
    "nan state": [(0.0, 0.0), (0.1, NAN)],
    "inf state": [(0.0, 0.0), (0.1, INF)],
    "huge state": [(0.0, 0.0), (0.1, 1e300)],
    "state near the largest": [(0.0, 0.0), (0.1, 1e308)],
    "nan t": [(0.0, 0.0), (NAN, 0.0)],
    "inf t": [(0.0, 0.0), (INF, 0.0)],
    "huge step": [(0.0, 0.0), (0.01, 0.0), (1e15, 0.0)],
    "then a good step": [(0.0, 0.0), (1e200, 0.0), (0.01, 0.0), (0.02, 0.001)],
}

SEAM_SPECS = {
    "pvtol, observer at 1e300": (EXAMPLES / "pvtol.toml", {"observer": {"bandwidth": 1e300}}),
    "robust_pvtol": (SPECS / "robust_pvtol.toml", None),
    "robust_pvtol, bandwidth 1e-300": (
        SPECS / "robust_pvtol.toml",
        {"integral": True, "observer": {"bandwidth": 1e-300}},
    ),
    "arm2, observer at 1e12": (ARM2, {"observer": {"bandwidth": 1e12}}),
    "unicycle_switch": (EXAMPLES / "unicycle_switch.toml", None),
    # Fed with reference samples: the estimator steps with the controller.
    "pvtol_refs, Levant": (EXAMPLES / "pvtol_refs.toml", None),
    "integrator_refs, linear": (EXAMPLES / "integrator_refs.toml", None),
}


def _run(mod: ModuleType, sequence: list[tuple[float, float]]) -> list[str]:
    """Each call's outcome: ``ok`` or the exception's class; after an OK, every value the
    controller hands out is finite. A spec with references is fed samples (the offset's
    too, where it is finite)."""
    n = len(mod.PLANT_STATE_NAMES)
    x0 = np.array(mod.DEFAULT_STATE[:n], dtype=float)
    references = len(getattr(mod, "REFERENCE_NAMES", ()))
    outcomes, controller = [], None
    for t, offset in sequence:
        x = x0 + offset
        extra = {}
        if references:
            extra["samples"] = np.full(references, 0.5 + (offset if math.isfinite(offset) else 0))
        try:
            if controller is None:
                controller = mod.Controller(x, t0=t, **extra)
            else:
                controller.step(t, x, **extra)
        except Exception as error:  # noqa: BLE001 - the class is what is compared
            outcomes.append(type(error).__name__)
            if controller is None:
                return outcomes
            continue
        outcomes.append("ok")
        for value in (controller.u, controller.state, getattr(controller, "disturbance", [])):
            assert np.all(np.isfinite(value)), (mod.__name__, t, value)
    return outcomes


@pytest.mark.parametrize("case", list(SEAM_SPECS))
def test_python_and_c_raise_the_same_error_on_hostile_steps(case: str) -> None:
    path, robust = SEAM_SPECS[case]
    _, py, c = _both(path, robust)
    seen = set()
    for name, sequence in HOSTILE.items():
        outcome = _run(py, sequence)
        assert outcome == _run(c, sequence), (case, name)
        seen.update(outcome)
        if name == "backwards":
            assert outcome[-1] == "DecreasingTimeError"
        if name in ("nan state", "inf state", "nan t", "inf t"):
            assert outcome[-1] == "NonFiniteInputError"
    # The sequences reach past the happy path: errors of the contract, never another.
    errors = {Status[name].exception for name in Status.__members__ if name != "OK"}
    assert seen - {"ok"} <= errors and len(seen) >= 3


def test_states_that_overflow_over_a_long_step_are_an_input_error_in_both() -> None:
    """PVTOL's thrust chain over 1e200 s: the C refused the advanced states as an input,
    the Python tried the law on them and said its output was not finite."""
    _, py, c = _both(*SEAM_SPECS["pvtol, observer at 1e300"])
    for mod in (py, c):
        controller = mod.Controller(np.array(mod.DEFAULT_STATE[:6]))
        state = controller.state.copy()
        with pytest.raises(mod.NonFiniteInputError, match="the step is too long for them"):
            controller.step(1e200, np.array(mod.DEFAULT_STATE[:6]))
        np.testing.assert_array_equal(controller.state, state)
        assert controller.t == 0.0


def test_finite_values_whose_sum_overflows_are_finite_in_both() -> None:
    # Python's finiteness test summed the values: 1e308 + 1e308 is inf.
    _, py, c = _both(EXAMPLES / "unicycle_switch.toml")
    s = np.array([1e308, 1e308, 0.3, 1.0])
    assert py._finite(s.tolist()) and not py._finite([1e308, math.inf])
    for mod in (py, c):
        with pytest.raises(mod.NonFiniteOutputError):
            mod.control(0.0, s)


# ----------------------------------------- no routine returns a non-finite value as OK


@pytest.mark.parametrize("name", ["integrator_refs", "pvtol_refs"])
def test_the_c_estimators_jets_far_ahead_are_an_error_not_nan(name: str) -> None:
    _, py, c = _both(EXAMPLES / f"{name}.toml")
    count = len(py.REFERENCE_NAMES)
    size = count * (py.REFERENCE_ORDER + 1)
    for mod in (py, c):
        estimator = mod.ReferenceEstimator(np.zeros(count))
        jets = estimator.update(1.0, np.ones(count))
        np.testing.assert_allclose(estimator.jets(1.0), jets, rtol=0, atol=0)
        with pytest.raises(mod.NonFiniteOutputError, match="extrapolated to t = 1e\\+308"):
            estimator.jets(1e308)
    # The C routine itself: a status, and the jets it wrote are not to be read as values.
    estimator = c.ReferenceEstimator(np.zeros(count))
    estimator.update(1.0, np.ones(count))
    out = np.zeros(size)
    status = c._ESTIMATOR_JETS(
        estimator._memory.ctypes.data, ctypes.c_double(1e308), out.ctypes.data
    )
    assert status == Status.NONFINITE_OUTPUT
    assert not np.all(np.isfinite(out))
    assert c._ESTIMATOR_JETS(estimator._memory.ctypes.data, 1.5, out.ctypes.data) == Status.OK
    np.testing.assert_allclose(out, estimator.jets(1.5).ravel(), rtol=0, atol=0)
    assert np.all(np.isfinite(out))


def test_the_observer_at_an_extreme_bandwidth_fails_rather_than_return_nan() -> None:
    """A step of one denormal second: 1 / h is infinite, the residual NaN; both say so."""
    _, py, c = _both(*SEAM_SPECS["robust_pvtol, bandwidth 1e-300"])
    _, py_fast, c_fast = _both(
        SPECS / "robust_pvtol.toml", {"integral": True, "observer": {"bandwidth": 1e300}}
    )
    for mod in (py, c, py_fast, c_fast):
        x = np.array(mod.DEFAULT_STATE[:6])
        controller = mod.Controller(x)
        before = controller.disturbance.copy()
        with pytest.raises(mod.NonFiniteOutputError):
            controller.step(5e-324, x + 0.01)
        np.testing.assert_array_equal(controller.disturbance, before)
        # An ordinary step afterwards works and hands out finite values.
        u = controller.step(1e-3, x + 0.01)
        assert np.all(np.isfinite(u)) and np.all(np.isfinite(controller.disturbance))


@pytest.mark.parametrize(
    "case",
    [
        (EXAMPLES / "pvtol.toml", None),
        (ARM2, OBSERVER),
        (EXAMPLES / "pvtol_refs.toml", None),
    ],
    ids=["pvtol", "arm2 observer", "pvtol_refs"],
)
def test_no_public_function_returns_a_value_that_is_not_finite(
    case: tuple[Path, dict[str, Any] | None],
) -> None:
    """Every function of the contract at arguments whose results overflow: a finite
    value, or the same error class from both backends."""
    from tvopt_codegen.contract import FUNCTIONS  # noqa: PLC0415

    _, py, c = _both(*case)
    sizes = {
        "state": len(py.STATE_NAMES),
        "output": len(py.OUTPUT_NAMES),
        "plant": len(py.PLANT_STATE_NAMES),
        "plant_input": len(py.PLANT_STATE_NAMES),
    }
    refs = getattr(py, "REFERENCE_NAMES", ())
    errors = 0
    for function in FUNCTIONS:
        for big in (1e100, 1e155, 1e200, 1e300, -1e300):
            outcomes = []
            for mod in (py, c):
                args = [np.full(sizes[function.argument], big)]
                if function.argument == "plant_input":
                    args.append(np.full(len(py.INPUT_NAMES), big))
                keywords = {}
                if refs and function.batch:
                    keywords["refs"] = np.full((len(refs), py.REFERENCE_ORDER + 1), big)
                try:
                    value = getattr(mod, function.name)(0.5, *args, **keywords)
                except mod.ControllerError as error:
                    outcomes.append(type(error).__name__)
                    continue
                assert np.all(np.isfinite(value)), (function.name, big, mod.__name__)
                outcomes.append("ok")
            assert outcomes[0] == outcomes[1], (function.name, big)
            errors += outcomes[0] != "ok"
    assert errors > 5  # the arguments do reach past the domain
