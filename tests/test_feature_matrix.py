"""Every pair of features works or is refused up front (issue 46, item 1).

The table is :mod:`tvopt_codegen.spec.features`. Its covering cases (a strength-2 covering
array: every working pair of feature values meets in one of them) are each built once as a
spec and run on their targets: the closed loop's certificate, the law against the
independent oracle of ``tests/oracle.py``, Python against C at random points and along the
loop, the stateful ``Controller`` stepped on a sampled loop, the FMU co-simulated with
FMPy, ``to_nlsys`` simulated with python-control, and a tiny sweep. The per-pair tests
then point at the case that holds their pair; every refused pair is refused by ``check``
with the table's line.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import io
import json
import tempfile
import traceback
from collections.abc import Callable
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from tvopt_codegen.cli import main
from tvopt_codegen.derivation import Derivation, derive
from tvopt_codegen.errors import EXIT_ASSUMPTION, AssumptionError
from tvopt_codegen.lowering.ir import KernelSet, lower
from tvopt_codegen.simulation import load_controller, resolve_options, simulate
from tvopt_codegen.simulation.references import exact_jets as reference_jets
from tvopt_codegen.spec import features, load_spec

from .conftest import ROOT, SPECS, derivation, shared
from .oracle import Oracle, assert_matches_oracle

FEATURES_DOC = ROOT / "docs" / "features.md"
CASES = features.covering_cases()
_FOLDER = Path(tempfile.mkdtemp(prefix="tvopt-feature-matrix-"))


# ------------------------------------------------------------------ specs from features


def _names(values: list[str]) -> str:
    return "[" + ", ".join(f'"{v}"' for v in values) + "]"


def spec_text(chosen: dict[str, str], name: str) -> str:
    """A spec that uses exactly the features ``chosen`` (axis to value; missing: default).

    ``[system.dynamics]``: a unicycle whose output is its position; without an extension
    its speed ``v`` is already a state (input: the acceleration ``a``), with one, ``v`` is
    the input and the extension integrates it (declared or found by the search). Padding:
    a third channel ``z' = uz`` of relative degree 1 beside the others' 2.
    ``[system.mechanics]``: the two-link arm of docs/spec.md, joint angles as outputs;
    with padding, a third link on a spring that no torque drives (relative degree 4).
    """
    value = {
        axis: chosen.get(axis, features.AXES[i].keys[0])
        for i, axis in enumerate(a.name for a in features.AXES)
    }
    mech = value["plant"] == "mechanics"
    ext, pad = value["extension"], value["padding"] == "yes"
    lines = [f'name = "{name}"', ""]
    if not mech:
        states = ["x", "y", "th"] + (["v"] if ext == "none" else [])
        inputs = ["a" if ext == "none" else "v", "om"]
        dynamics = {"x": "v*cos(th)", "y": "v*sin(th)", "th": "om"}
        if ext == "none":
            dynamics["v"] = "a"
        outputs = {"px": "x", "py": "y"}
        initial = {"x": 0.0, "y": 0.0, "th": 0.0, "v": 1.0}
        if pad:
            states.append("z")
            inputs.append("uz")
            dynamics["z"] = "uz"
            outputs["pz"] = "z"
            initial["z"] = 0.2
        lines += ["[system]", f"states = {_names(states)}", f"inputs = {_names(inputs)}"]
        lines += ["", "[system.dynamics]", *(f'{k} = "{v}"' for k, v in dynamics.items())]
        targets = {"ox": "1.0 + 0.4*t", "oy": "0.3*sin(0.5*t)"}
        if pad:
            targets["oz"] = "0.5*sin(0.8*t)"
        limited = inputs[1]
    else:
        coordinates = ["q1", "q2"] + (["q3"] if pad else [])
        lines += ["[system]", f"coordinates = {_names(coordinates)}", 'inputs = ["tau1", "tau2"]']
        lines += ["", "[system.mechanics]"]
        if pad:
            lines += [
                'mass_matrix = [["a1 + 2*a2*cos(q2)", "a3 + a2*cos(q2)", 0], '
                '["a3 + a2*cos(q2)", "a3", 0], [0, 0, 1]]',
                'forces = ["a2*sin(q2)*dq2*(2*dq1 + dq2) - g1*cos(q1)", '
                '"-a2*sin(q2)*dq1**2 - ks*(q2 - q3)", "ks*(q2 - q3)"]',
                "input_matrix = [[1, 0], [0, 1], [0, 0]]",
            ]
        else:
            lines += [
                'mass_matrix = [["a1 + 2*a2*cos(q2)", "a3 + a2*cos(q2)"], '
                '["a3 + a2*cos(q2)", "a3"]]',
                'forces = ["a2*sin(q2)*dq2*(2*dq1 + dq2) - g1*cos(q1)", "-a2*sin(q2)*dq1**2"]',
                "input_matrix = [[1, 0], [0, 1]]",
            ]
        outputs = {"px": "q1", "py": "q3" if pad else "q2"}
        initial = {"q1": 0.2, "q2": 1.0, "dq1": 0.0, "dq2": 0.0}
        if pad:
            initial |= {"q3": 1.0, "dq3": 0.0}
        targets = {"ox": "0.3 + 0.3*sin(0.5*t)", "oy": "1.0 + 0.3*cos(0.4*t)"}
        limited = "tau2"
    lines += ["", "[system.outputs]", *(f'{k} = "{v}"' for k, v in outputs.items())]
    if ext == "declared":
        lines += ["", "[extension]", f"integrate = {{ {'tau1' if mech else 'v'} = 1 }}"]
    elif ext == "auto":
        lines += ["", "[extension]", "auto = true"]
    lines += ["", "[parameters]", "w = 1.0"]
    if mech:
        lines += ["a1 = 3.0", "a2 = 0.5", "a3 = 0.4", "g1 = 9.0"] + (["ks = 5.0"] if pad else [])
    if value["references"] == "yes":
        lines += ["", "[references]", f"names = {_names(list(targets))}", ""]
        lines += ["[references.nominal]", *(f'{k} = "{v}"' for k, v in targets.items())]
    else:
        lines += ["", "[signals]", *(f'{k} = "{v}"' for k, v in targets.items())]
    f0 = "(px - ox)**2 + w*(py - oy)**2" + (" + (pz - oz)**2" if "oz" in targets else "")
    lines += ["", "[objective]", f'f0 = "{f0}"']
    constraints = []
    if value["inequality"] == "yes":
        constraints.append('ceiling = "py <= 1.5 + 0.05*t"' if mech else 'ceiling = "px <= 3.0"')
    if value["equality"] == "yes":
        constraints.append(
            'on_line = "px + py == 1.2 + 0.1*sin(t)"'
            if mech
            else 'on_line = "py - 0.2*px == 0.1*sin(0.3*t)"'
        )
    if constraints:
        lines += ["", "[constraints]", *constraints]
    k = 3 if mech and ext == "declared" else 2
    poles = [-1.0, -1.5, -2.0, -2.5][: k + (value["integral"] == "yes")]
    lines += ["", "[error_dynamics]", f"poles = {poles}"]
    if "yes" in (value["integral"], value["observer"], value["eso"]):
        lines += ["", "[robust]"]
        if value["integral"] == "yes":
            lines.append("integral = true")
        if value["observer"] == "yes":
            lines += ["", "[robust.observer]", "bandwidth = 20.0"]
        if value["eso"] == "yes":
            lines += ["", "[robust.eso]", "bandwidth = 20.0"]
    if value["limits"] == "yes":
        lines += ["", "[limits]", f"{limited} = 40.0", "", "[limits.rate]", f"{limited} = 1000.0"]
    start = ", ".join(f"{k} = {v}" for k, v in initial.items())
    lines += ["", "[simulation]", "t_final = 6.0", f"initial_state = {{ {start} }}"]
    return "\n".join(lines) + "\n"


def spec_file(chosen: dict[str, str], name: str) -> Path:
    path = _FOLDER / f"{name}.toml"
    path.write_text(spec_text(chosen, name), encoding="utf-8")
    return path


# ------------------------------------------------------------------ one covering case


class _WithJets:
    """A module with references, seen as one without: its jets are the nominal ones."""

    def __init__(self, mod: ModuleType, jets: Callable[[float], np.ndarray]) -> None:
        self.mod, self.jets = mod, jets
        self.PARAMETERS = mod.PARAMETERS
        self.OutsideBarrierError = mod.OutsideBarrierError

    def control(self, t: float, s: np.ndarray) -> np.ndarray:
        return self.mod.control(t, s, refs=self.jets(t))

    def rhs(self, t: float, s: np.ndarray) -> np.ndarray:
        return self.mod.rhs(t, s, refs=self.jets(t))


class CaseRun:
    """One covering case built and run on its targets; each target's failure is kept."""

    def __init__(self, index: int, case: features.Case | None = None) -> None:
        self.index = index
        self.case = CASES[index] if case is None else case
        self.chosen = dict(self.case.features)
        self.failures: dict[str, str] = {}
        self.passed: set[str] = set()
        self.numbers: dict[str, float] = {}
        self.name = f"fm_case{index}"
        self.d: Derivation | None = None

    def run(self, target: str, check: Callable[[], None]) -> None:
        try:
            check()
        except Exception:  # noqa: BLE001 - the per-pair tests report it
            self.failures[target] = traceback.format_exc(limit=6)
        else:
            self.passed.add(target)

    # The law and its certificate, on the Python module.
    def python(self) -> None:
        path = spec_file(self.chosen, self.name)
        d = derive(load_spec(path))
        self.d = d
        assert features.derivation_features(d) == self.chosen  # the spec is the case
        self.kernels: KernelSet = lower(d)
        self.mod = load_controller(self.kernels, "python")
        self.refs = bool(d.model.references)
        self.jets = reference_jets(d, {}) if self.refs else None
        result = simulate(d, self.mod, resolve_options(d, points=61))
        assert result.passed, result.failures
        self.result = result
        self.numbers["deviation"] = result.deviation
        # The oracle: with references, the twin spec with the same closed forms as signals.
        if self.refs:
            twin = derive(
                load_spec(spec_file({**self.chosen, "references": "no"}, self.name + "_twin"))
            )
            oracle, law = Oracle(twin), _WithJets(self.mod, self.jets)  # type: ignore[arg-type]
        else:
            oracle, law = Oracle(d), self.mod
        self.oracle = oracle
        states = self._points()
        assert_matches_oracle(oracle, [law], states, [0.0, 1.3, 4.0], tolerance=1e-8)

    def _points(self) -> np.ndarray:
        """Closed-loop states along the run and random points near them (20 columns)."""
        rng = np.random.default_rng(self.index)
        along = self.result.states[:, :: max(1, self.result.states.shape[1] // 10)][:, :10]
        near = along + 0.05 * rng.standard_normal(along.shape)
        return np.hstack([along, near])

    def kw(self, t: float) -> dict[str, Any]:
        return {"refs": self.jets(t)} if self.jets is not None else {}  # type: ignore[misc]

    def c(self) -> None:
        self.cmod = load_controller(self.kernels, "c")
        points = self._points()
        params = np.array(list(self.mod.PARAMETERS.values()))
        for t in (0.0, 0.7, 3.1):
            # Points past a barrier at t (the run has moved on) are refused alike.
            inside, outside = self.oracle.domain(t, points, params)
            if outside.any():
                for mod in (self.cmod, self.mod):
                    with pytest.raises(mod.OutsideBarrierError):
                        mod.control(t, points[:, outside], **self.kw(t))
            states = points[:, inside]
            np.testing.assert_allclose(
                self.cmod.control(t, states, **self.kw(t)),
                self.mod.control(t, states, **self.kw(t)),
                rtol=1e-11, atol=1e-11,
            )  # fmt: skip
            np.testing.assert_allclose(
                self.cmod.rhs(t, states, **self.kw(t)),
                self.mod.rhs(t, states, **self.kw(t)),
                rtol=1e-11, atol=1e-11,
            )  # fmt: skip
        for i, t in enumerate(self.result.t[::6]):
            s = self.result.states[:, i * 6]
            np.testing.assert_allclose(
                self.cmod.control(t, s, **self.kw(t)), self.mod.control(t, s, **self.kw(t)),
                rtol=1e-11, atol=1e-11,
            )  # fmt: skip

    def _sampled(self, mod: Any, h: float = 0.01, steps: int = 150) -> tuple[np.ndarray, ...]:
        """The stateful controller on the plant, zero-order hold, RK45 between samples."""
        d = self.d
        assert d is not None
        n = len(mod.PLANT_STATE_NAMES)
        x = np.array(self.result.states[:n, 0])
        ctl = mod.Controller(x, **self.kw(0.0))
        params = np.array(list(mod.PARAMETERS.values()))
        plant = _plant(d)
        inputs, xs = [], [x]
        for j in range(steps):
            t = j * h
            u = ctl.step(t, x, **self.kw(t))
            held = np.array(u)
            inputs.append(held)
            run = solve_ivp(
                lambda _t, z, w=held: plant(z, w, params),
                (t, t + h),
                x,
                rtol=1e-10,
                atol=1e-12,
            )
            x = run.y[:, -1]
            xs.append(x)
        return np.array(inputs), np.array(xs).T

    def controller(self) -> None:
        inputs, xs = self._sampled(self.mod)
        assert np.all(np.isfinite(inputs))
        # Sampled at 100 Hz, the loop stays near the continuous one (a zero-order hold
        # error of order h): outputs within 0.05 at t = 1.5 s.
        reference = self.result.dense(1.5)[: xs.shape[0]]
        gap = float(np.max(np.abs(xs[:, -1] - reference)))
        self.numbers["sampled_gap"] = gap
        assert gap < 0.05, gap
        if "c" in self.case.targets and hasattr(self, "cmod"):
            c_inputs, _ = self._sampled(self.cmod, steps=40)
            np.testing.assert_allclose(c_inputs, inputs[:40], rtol=1e-9, atol=1e-9)

    def nlsys(self) -> None:
        import control  # noqa: PLC0415

        from tvopt_codegen.interop import plant_nlsys, to_nlsys  # noqa: PLC0415

        mod = self.mod
        controller = to_nlsys(mod)
        ref_inputs = [n for n in controller.input_labels if n.startswith("reference_")]
        closed = control.interconnect(
            [plant_nlsys(mod), controller],
            inplist=ref_inputs,
            outlist=list(mod.OUTPUT_NAMES),
        )
        times = np.linspace(0.0, 0.4, 5)
        if self.jets is not None:
            u = np.array([self.jets(t).reshape(-1) for t in times]).T
        else:
            u = 0.0
        s0 = self.result.states[:, 0]
        # The observer's continuous form starts at sigma = 0: its states at bandwidth * x0.
        # (None, or no such name, without one.)
        beta = getattr(mod, "OBSERVER_BANDWIDTH", None) or 0.0
        observer = s0[: len(mod.PLANT_STATE_NAMES)] * beta
        x0 = np.concatenate([s0, observer[: closed.nstates - len(s0)]])
        response = control.input_output_response(
            closed, times, u, X0=x0, solve_ivp_kwargs={"rtol": 1e-9, "atol": 1e-11}
        )
        expected = self.result.dense(times)
        y = np.asarray(response.outputs)
        h = _outputs(self.d)
        want = h(expected)
        gap = float(np.max(np.abs(y - want)))
        self.numbers["nlsys_gap"] = gap
        # The observer's continuous form moves its estimate off 0 while the loop settles.
        assert gap < (1e-3 if self.chosen["observer"] == "yes" else 1e-6), gap

    def fmu(self) -> None:
        import fmpy  # noqa: PLC0415

        from tvopt_codegen.runs.fmu import build_fmu  # noqa: PLC0415

        mod = self.mod
        path = _FOLDER / f"{self.name}.fmu"
        path.write_bytes(build_fmu(self.kernels, 2))
        h = 0.01
        times = np.round(np.arange(0.0, 0.3 + h / 2, h), 12)
        n = len(mod.PLANT_STATE_NAMES)
        states = self.result.dense(times)[:n]
        columns = [(t, *states[:, k]) for k, t in enumerate(times)]
        names_in = list(mod.PLANT_STATE_NAMES)
        if self.jets is not None:
            jet_names = [
                f"reference.{r}.d{j}"
                for r in mod.REFERENCE_NAMES
                for j in range(mod.REFERENCE_ORDER + 1)
            ]
            columns = [(*row, *self.jets(row[0]).reshape(-1)) for row in columns]
            names_in += jet_names
        table = np.array(columns, dtype=[("time", float)] + [(m, float) for m in names_in])
        names = list(mod.INPUT_NAMES)
        result = fmpy.simulate_fmu(
            str(path), start_time=0.0, stop_time=float(times[-1]), output_interval=h,
            input=table, output=names, fmi_type="CoSimulation",
        )  # fmt: skip
        ctl = mod.Controller(states[:, 0], **self.kw(0.0))
        expected = [np.array(ctl.u)]
        for k in range(len(times) - 1):
            expected.append(np.array(ctl.step(float(times[k]), states[:, k], **self.kw(times[k]))))
        got = np.array([[row[m] for m in names] for row in result])
        np.testing.assert_allclose(got, np.array(expected), rtol=1e-9, atol=1e-9)

    def sweep(self) -> None:
        from tvopt_codegen.sweep import SweepOptions, run_sample, sweep_program  # noqa: PLC0415

        program = sweep_program(self.kernels)
        sampled = self.chosen["observer"] == "yes"  # the observer runs in the sampled loop
        options = SweepOptions(
            samples=2, seed=3, t_final=3.0, sample_time=0.01 if sampled else None
        )
        rows = [run_sample(program, options, i).row for i in range(2)]
        assert all(r["status"] == "ok" for r in rows), [r["status"] for r in rows]
        if not sampled:
            assert all(r["certificate_holds"] for r in rows), rows
        # The nominal sweep ends where simulate's loop does.
        final = float(rows[0]["final_error"])
        self.numbers["sweep_final_error"] = final
        # simulate's |y - y*| at the same time, from its own integrator and its own y*.
        expected = float(np.interp(3.0, self.result.t, self.result.error))
        self.numbers["sweep_vs_simulate"] = abs(final - expected)
        # The continuous loop is simulate's to 1e-10 (measured); the sampled one (100 Hz,
        # zero-order hold, the observer) is off by 4% at t = 3 s on the arm (measured).
        tolerance = 0.1 * expected if sampled else 1e-6 * (1.0 + expected)
        assert abs(final - expected) <= tolerance, (final, expected)


def _plant(d: Derivation) -> Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray]:
    """The plant's x' = f(x) + G(x) u (mass-matrix plants: M solved numerically)."""
    import sympy as sp  # noqa: PLC0415

    model = d.model
    u = sp.symbols(f"U0:{len(model.u)}", real=True)
    if model.mechanics is None:
        field = sp.lambdify(
            [model.x, u, model.params], list(model.f + model.G * sp.Matrix(u)), "numpy"
        )
        return lambda x, w, p: np.array(field(x, w, p), dtype=float)
    mech = model.mechanics
    args = [model.x, model.params]
    mass = sp.lambdify(args, [list(r) for r in mech.mass_matrix], "numpy")
    forces = sp.lambdify(args, list(mech.forces), "numpy")
    gain = sp.lambdify(args, [list(r) for r in mech.input_matrix], "numpy")
    nq = len(mech.coordinates)

    def field_mech(x: np.ndarray, w: np.ndarray, p: np.ndarray) -> np.ndarray:
        M = np.array(mass(x, p), dtype=float)
        F = np.array(forces(x, p), dtype=float)
        B = np.array(gain(x, p), dtype=float)
        return np.concatenate([x[nq:], np.linalg.solve(M, F + B @ w)])

    return field_mech


def _outputs(d: Derivation | None) -> Callable[[np.ndarray], np.ndarray]:
    import sympy as sp  # noqa: PLC0415

    assert d is not None
    h = sp.lambdify([d.closed_loop.states, d.model.params], list(d.model.h), "numpy")
    params = [value for _, value in d.spec.parameters]

    def outputs(states: np.ndarray) -> np.ndarray:
        values = h(states, params)
        return np.array([np.broadcast_to(np.asarray(v, float), states.shape[1:]) for v in values])

    return outputs


def _run_case(index: int) -> CaseRun:
    run = CaseRun(index)
    run.run("python", run.python)
    if "python" in run.failures:
        return run
    order = ("c", "controller", "nlsys", "fmu", "sweep")
    for target in order:
        if target in run.case.targets:
            run.run(target, getattr(run, target))
    return run


@dataclasses.dataclass(frozen=True)
class Verdict:
    """What one covering case's run found: each target's failure, the passed, its numbers."""

    failures: dict[str, str]
    passed: set[str]
    numbers: dict[str, float]


@functools.cache
def case_run(index: int) -> Verdict:
    """Covering case ``index`` run once per pytest run, whichever worker asks first.

    Its per-pair tests land on every xdist worker, and each ran the whole case (derive,
    simulate, the oracle, the targets) again: the first worker runs it under the run
    folder's lock and writes what it found, the others wait and read it (the run folder
    is this run's, so nothing outlives it).
    """

    def build(folder: Path) -> None:
        run = _run_case(index)
        found = {"failures": run.failures, "passed": sorted(run.passed), "numbers": run.numbers}
        (folder / "verdict.json").write_text(json.dumps(found), encoding="utf-8")

    found = json.loads((shared(f"feature-matrix-case{index}", build) / "verdict.json").read_text())
    return Verdict(found["failures"], set(found["passed"]), found["numbers"])


# ------------------------------------------------------------------ the table itself


def test_the_committed_doc_is_the_generated_table() -> None:
    assert FEATURES_DOC.read_text(encoding="utf-8") == features.markdown()


def test_the_covering_cases_hold_every_working_pair_and_no_other() -> None:
    every = features.pairs()
    # 274 pairs, and 50 more with the extended-state observer (each of its two values
    # against the 25 values of the other axes).
    assert len(every) == 324
    for a, b in every:
        holding = [i for i, case in enumerate(CASES) if case.holds(a, b)]
        if features.status(a, b) == "works":
            assert holding, (a, b)
        else:
            assert not holding, (a, b)
    assert features.covering_cases() == CASES  # deterministic


# ------------------------------------------------------------------ every pair

_PAIRS = features.pairs()


def _pair_id(pair: tuple[features.Feature, features.Feature]) -> str:
    (a, x), (b, y) = pair
    status = features.status(*pair)
    where = (
        f"case{features.case_of(*pair, CASES)}" if status == "works" else status.replace(" ", "_")
    )
    return f"{a}={x}-{b}={y}-{where}"


_WORKING = [p for p in _PAIRS if features.status(*p) == "works"]


@pytest.mark.slow
@pytest.mark.parametrize("pair", _WORKING, ids=[_pair_id(p) for p in _WORKING])
def test_a_working_pair_runs_its_covering_case(
    pair: tuple[features.Feature, features.Feature],
) -> None:
    run = case_run(features.case_of(*pair, CASES))
    targets = [f[1] for f in pair if f[0] == "target"] or ["python"]
    for target in {"python", *targets}:
        assert target not in run.failures, run.failures[target]
        assert target in run.passed


_REFUSED = [p for p in _PAIRS if features.status(*p) == "refused"]


def _check(path: Path, *extra: str) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main([extra[0], str(path), *extra[1:]])
    return code, out.getvalue(), err.getvalue()


_KNOWN = [p for p in _PAIRS if features.status(*p) == "known failure"]


@pytest.mark.parametrize(
    "pair",
    [
        pytest.param(
            p,
            marks=pytest.mark.xfail(
                strict=True, raises=ArithmeticError, reason=features.known_failure(*p).symptom
            ),
        )  # type: ignore[union-attr]
        for p in _KNOWN
    ],
    ids=[_pair_id(p) for p in _KNOWN],
)
def test_a_known_failure_fails_until_its_fix_lands(
    pair: tuple[features.Feature, features.Feature],
) -> None:
    """The pair alone, every other axis at its default: flips to XPASS (a failure) once fixed."""
    chosen = {axis: features.AXES[i].keys[0] for i, axis in enumerate(features.SPEC_AXES)}
    chosen |= {axis: value for axis, value in pair if axis != "target"}
    target = next((value for axis, value in pair if axis == "target"), None)
    case = features.Case(tuple(chosen.items()), ("python", *([target] if target else [])))
    run = CaseRun(100 + _KNOWN.index(pair), case)
    run.name = f"fm_known{_KNOWN.index(pair)}"
    run.run("python", run.python)
    assert not run.failures, run.failures
    if target is not None:
        getattr(run, target)()


@pytest.mark.parametrize("pair", _REFUSED, ids=[_pair_id(p) for p in _REFUSED])
def test_a_refused_pair_is_refused_by_check_in_one_line(
    pair: tuple[features.Feature, features.Feature], tmp_path: Path
) -> None:
    line = features.refusal(*pair).line  # type: ignore[union-attr]
    chosen = {axis: value for axis, value in pair if axis != "target"}
    path = spec_file(chosen, "fm_refused_" + "_".join(f"{a}_{v}" for a, v in pair))
    if any(axis == "target" for axis, _ in pair):
        # A target's refusal: check says which targets the spec is not for, and the target
        # itself refuses (the sweep: exit 2, one line, nothing written).
        code, out, err = _check(path, "check")
        assert code == 0, err
        assert f"not for {features.label(next(f for f in pair if f[0] == 'target'))}: {line}" in out
        out_dir = tmp_path / "sweep"
        code, out, err = _check(path, "sweep", "--samples", "1", "--out", str(out_dir))
        assert code == 2 and err.count("\n") == 1 and "[references]" in err, err
        assert not out_dir.exists()
        return
    code, out, err = _check(path, "check")
    assert code == EXIT_ASSUMPTION
    assert err.count("\n") == 1 and line in err, err
    assert out == ""
    # generate refuses the same way, and writes nothing.
    out_dir = tmp_path / "generated"
    code, _, err = _check(path, "generate", "--out", str(out_dir))
    assert code == EXIT_ASSUMPTION and line in err and not out_dir.exists()
    # So do simulate and sweep, which derive the same way.
    for command in (
        ["simulate", "--out", str(tmp_path / "run")],
        ["sweep", "--samples", "1", "--out", str(tmp_path / "sw")],
    ):
        code, _, err = _check(path, *command)
        assert code == EXIT_ASSUMPTION and err.count("\n") == 1 and line in err, err
    assert not (tmp_path / "run").exists() and not (tmp_path / "sw").exists()
    # So does the library.
    with pytest.raises(AssumptionError, match=r".*") as caught:
        derive(load_spec(path))
    assert line in str(caught.value)


@pytest.mark.parametrize(
    ("spec", "expected"),
    [
        ("integrator", {}),
        ("unicycle_switch", {"extension": "declared"}),
        ("pvtol", {"extension": "auto"}),
        ("arm_on_line", {"equality": "yes"}),
        ("two_unicycles_corridor", {"extension": "declared", "inequality": "yes"}),
        ("integrator_refs", {"references": "yes"}),
        ("planar_arm3", {"plant": "mechanics"}),
        (
            str(SPECS / "robust_pvtol.toml"),
            {"extension": "auto", "integral": "yes", "observer": "yes", "limits": "yes"},
        ),
        (str(SPECS / "nonuniform.toml"), {"padding": "yes"}),
    ],
)
def test_the_features_a_bundled_spec_uses(spec: str, expected: dict[str, str]) -> None:
    d = derivation(spec)
    defaults = {axis: features.AXES[i].keys[0] for i, axis in enumerate(features.SPEC_AXES)}
    assert features.derivation_features(d) == defaults | expected


def test_the_extension_search_on_a_mass_matrix_plant_that_needs_padding_says_why() -> None:
    """[extension] auto with [system.mechanics] works (the search takes "none"); with outputs
    that would need padding, the search has nothing to try, and the padding line says why.
    Before, it listed 28 prolongations it had tried in vain."""
    path = spec_file(
        {"plant": "mechanics", "extension": "auto", "padding": "yes"}, "fm_auto_mechanics_padding"
    )
    with pytest.raises(AssumptionError) as caught:
        derive(load_spec(path))
    line = features.refusal_line(("plant", "mechanics"), ("padding", "yes"))
    assert line in str(caught.value) and "system.outputs.py" in str(caught.value)
    assert "tried" not in str(caught.value)


def test_a_spec_without_refusals_gets_no_target_notes() -> None:
    d = derive(load_spec(spec_file({"integral": "yes"}, "fm_plain")))
    assert features.target_notes(d) == []
    assert features.refusals(features.derivation_features(d)) == []


def test_check_on_a_working_spec_prints_no_refusal() -> None:
    code, out, err = _check(spec_file({"observer": "yes"}, "fm_check_plain"), "check")
    assert code == 0, err
    assert "not for" not in out


# ------------------------------------------------------------------ the cases' numbers


@pytest.mark.slow
@pytest.mark.parametrize("index", range(len(CASES)), ids=[f"case{i}" for i in range(len(CASES))])
def test_each_covering_case_passes_on_all_its_targets(index: int) -> None:
    run = case_run(index)
    assert not run.failures, "\n".join(f"{k}: {v}" for k, v in run.failures.items())
    assert run.passed == set(CASES[index].targets)
    # The certificate is tight, not vacuous: E follows expm(H t) E(0).
    assert run.numbers["deviation"] < 1e-6
