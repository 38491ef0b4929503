"""Plants in mass-matrix form: the spec section, spec_from_sympy, M factored at run time.

The law of a mass-matrix plant is checked against the oracle's independent path (numpy's
dense solves of M) for every spec in ``ALL_SPECS`` (the two-link arm) and, here, for
planar arms of 3 and 6 links built with SymPy mechanics, in both backends.
"""

from __future__ import annotations

import copy
import functools
import tomllib
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import sympy as sp
import sympy.physics.mechanics as me

from tvopt_codegen import contract
from tvopt_codegen.cli import main
from tvopt_codegen.derivation import derive
from tvopt_codegen.emit import write_files
from tvopt_codegen.errors import (
    EXIT_ASSUMPTION,
    EXIT_BAD_SPEC,
    AssumptionError,
    SpecError,
)
from tvopt_codegen.lowering.ir import lower
from tvopt_codegen.mechanics import spec_from_sympy, spec_toml
from tvopt_codegen.renderer.rendering import render
from tvopt_codegen.spec import load_spec, spec_from_dict

from .arms import planar_arm as _planar_arm
from .conftest import SPECS, derivation, import_file, module
from .oracle import Oracle, assert_matches_oracle

ARM2 = str(SPECS / "arm2_mass.toml")


@functools.cache
def _kane(links: int) -> tuple[me.KanesMethod, list[sp.Expr], dict[sp.Symbol, float]]:
    # Kane's method once per arm in a process: several tests read the same equations
    # (nothing here changes a KanesMethod), and forming them is most of what they cost.
    return _planar_arm(links)


def planar_arm(links: int) -> tuple[me.KanesMethod, list[sp.Expr], dict[sp.Symbol, float]]:
    """tests.arms.planar_arm, its equations formed once (the values a fresh dict)."""
    kane, q, values = _kane(links)
    return kane, list(q), dict(values)


@functools.cache
def _default_arm_spec(links: int) -> dict[str, Any]:
    kane, q, values = planar_arm(links)
    outputs = {f"y{i + 1}": q[i] for i in range(links)}
    f0 = " + ".join(f"(y{i + 1} - 0.3*sin(t + {i}))**2" for i in range(links))
    start = {f"q{i + 1}": 0.1 * (i + 1) for i in range(links)}
    return spec_from_sympy(kane, outputs, f0, values, name=f"planar{links}", initial_state=start)


def _arm_spec(links: int) -> dict[str, Any]:
    """The planar arm's spec (spec_from_sympy once per arm; each caller its own copy)."""
    return copy.deepcopy(_default_arm_spec(links))


def _plain(expr: sp.Expr) -> sp.Expr:
    """A SymPy mechanics expression in the spec's plain real symbols."""
    t = me.dynamicsymbols._t
    table: dict[sp.Basic, sp.Basic] = {}
    for node in sp.preorder_traversal(expr):
        if isinstance(node, sp.Derivative):
            table[node] = sp.Symbol("d" + node.args[0].func.__name__, real=True)
    out = sp.sympify(expr).xreplace(table)
    table = {}
    for node in sp.preorder_traversal(out):
        if isinstance(node, sp.core.function.AppliedUndef) and node.args == (t,):
            table[node] = sp.Symbol(node.func.__name__, real=True)
        elif isinstance(node, sp.Symbol) and node != t:
            table[node] = sp.Symbol(node.name, real=True)
    return out.xreplace(table)


@pytest.mark.parametrize("links", [2, 3])
def test_spec_from_sympy_round_trips(links: int, tmp_path: Path) -> None:
    """The TOML it writes, loaded back, holds the same M, F and B, symbolically."""
    kane, q, values = planar_arm(links)
    spec = _arm_spec(links)
    path = tmp_path / "arm.toml"
    path.write_text(spec_toml(spec), encoding="utf-8")
    assert tomllib.loads(path.read_text(encoding="utf-8")) == spec
    mech = load_spec(path).mechanics
    assert mech is not None
    assert mech.coordinates == tuple(f"q{i + 1}" for i in range(links))
    assert mech.rates == tuple(f"dq{i + 1}" for i in range(links))
    mass = kane.mass_matrix
    forcing = kane.forcing
    tau = [sp.Symbol(f"tau{i + 1}", real=True) for i in range(links)]
    for i in range(links):
        for j in range(links):
            assert sp.simplify(mech.mass_matrix[i][j] - _plain(mass[i, j])) == 0
        force = _plain(forcing[i])
        loaded = mech.forces[i] + sum(mech.input_matrix[i][j] * tau[j] for j in range(links))
        assert sp.simplify(loaded - force) == 0
    # The parameters are named, with their values, so that sweeps can perturb them.
    assert spec["parameters"] == {str(k): v for k, v in values.items()}


def test_the_bundled_arm_is_kanes_model() -> None:
    """planar_arm3.toml (trigsimp'd) equals Kane's equations at random states."""
    kane, _, values = planar_arm(3)
    mech = load_spec("planar_arm3").mechanics
    assert mech is not None
    rng = np.random.default_rng(4)
    names = [*mech.coordinates, *mech.rates]
    for _ in range(5):
        point = {
            sp.Symbol(n, real=True): v for n, v in zip(names, rng.uniform(-2, 2, 6), strict=True)
        }
        point |= {sp.Symbol(str(k), real=True): v for k, v in values.items()}
        for i in range(3):
            for j in range(3):
                ours = float(mech.mass_matrix[i][j].xreplace(point))
                theirs = float(_plain(kane.mass_matrix[i, j]).xreplace(point))
                assert ours == pytest.approx(theirs, rel=1e-13, abs=1e-13)
            taus = {sp.Symbol(f"tau{k + 1}", real=True): 0.0 for k in range(3)}
            ours = float(mech.forces[i].xreplace(point))
            theirs = float(_plain(kane.forcing[i]).xreplace(point | taus))
            assert ours == pytest.approx(theirs, rel=1e-12, abs=1e-12)


def test_lagranges_method_and_system() -> None:
    """A LagrangesMethod and a System give the spec a KanesMethod gives (one pendulum)."""
    q = me.dynamicsymbols("theta")
    torque = me.dynamicsymbols("torque")
    m, length, g = sp.symbols("m l g", positive=True)
    frame = me.ReferenceFrame("N")
    pivot = me.Point("O")
    pivot.set_vel(frame, 0)
    arm = frame.orientnew("A", "Axis", [q, frame.z])
    arm.set_ang_vel(frame, q.diff() * frame.z)
    bob = pivot.locatenew("P", length * arm.x)
    bob.v2pt_theory(pivot, frame, arm)
    particle = me.Particle("bob", bob, m)
    particle.potential_energy = -m * g * length * sp.cos(q)
    loads = [(arm, torque * frame.z)]
    lagrange = me.LagrangesMethod(me.Lagrangian(frame, particle), [q], forcelist=loads, frame=frame)
    lagrange.form_lagranges_equations()
    values = {m: 1.0, length: 0.5, g: 9.81}
    spec = spec_from_sympy(lagrange, {"y": q}, "(y - sin(t))**2", values, name="pendulum")
    mech = spec["system"]["mechanics"]
    assert spec["system"]["coordinates"] == ["theta"] and mech["rates"] == ["dtheta"]
    assert spec["system"]["inputs"] == ["torque"]
    assert sp.sympify(mech["mass_matrix"][0][0]) == sp.sympify("l**2*m")
    assert sp.simplify(sp.sympify(mech["forces"][0]) + sp.sympify("g*l*m*sin(theta)")) == 0
    assert mech["input_matrix"] == [[1]]

    system = me.System(frame, pivot)
    system.q_ind = [q]
    speed = me.dynamicsymbols("omega")
    system.u_ind = [speed]
    system.kdes = [q.diff() - speed]
    arm2 = frame.orientnew("A2", "Axis", [q, frame.z])
    arm2.set_ang_vel(frame, speed * frame.z)
    bob2 = pivot.locatenew("P2", length * arm2.x)
    bob2.v2pt_theory(pivot, frame, arm2)
    system.add_bodies(me.Particle("bob2", bob2, m))
    system.add_loads(me.Force(bob2, m * g * frame.x), me.Torque(arm2, torque * frame.z))
    system.form_eoms()
    from_system = spec_from_sympy(system, {"y": q}, "(y - sin(t))**2", values, name="pendulum")
    assert from_system["system"]["mechanics"]["rates"] == ["omega"]
    derive(spec_from_dict(from_system))


def test_spec_from_sympy_refuses_what_it_cannot_express() -> None:
    kane, q, values = planar_arm(2)
    with pytest.raises(SpecError, match="no value in parameters for l2"):
        spec_from_sympy(
            kane,
            {"y1": q[0], "y2": q[1]},
            "y1**2 + y2**2",
            {**{k: v for k, v in values.items() if str(k) != "l2"}},
        )
    with pytest.raises(SpecError, match="eoms: expected a KanesMethod"):
        spec_from_sympy(object(), {}, "0", {})
    unformed = me.KanesMethod(
        me.ReferenceFrame("N"), q_ind=q, u_ind=me.dynamicsymbols("w1:3"), kd_eqs=[]
    )
    with pytest.raises(SpecError, match="not formed yet"):
        spec_from_sympy(unformed, {"y1": q[0], "y2": q[1]}, "y1**2 + y2**2", values)
    # A speed twice the angle's rate: the spec's rates must be the derivatives themselves.
    angle, speed = me.dynamicsymbols("angle speed")
    frame = me.ReferenceFrame("N")
    body = frame.orientnew("A", "Axis", [angle, frame.z])
    body.set_ang_vel(frame, 2 * speed * frame.z)
    pivot = me.Point("O")
    pivot.set_vel(frame, 0)
    tip = pivot.locatenew("P", body.x)
    tip.v2pt_theory(pivot, frame, body)
    skewed = me.KanesMethod(frame, q_ind=[angle], u_ind=[speed], kd_eqs=[angle.diff() - 2 * speed])
    skewed.kanes_equations([me.Particle("p", tip, 1)], [(tip, frame.y)])
    with pytest.raises(SpecError, match="the speeds must be the coordinates' derivatives"):
        spec_from_sympy(skewed, {"y": angle}, "y**2", {})


@pytest.mark.parametrize("links", [2, 3, 6])
def test_planar_arms_match_the_oracle_in_both_backends(
    links: int, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The law of 2-, 3- and 6-link arms equals the oracle's (M solved densely) to 1e-9."""
    d = derive(spec_from_dict(_arm_spec(links)))
    kernels = lower(d)
    oracle = Oracle(d)
    monkeypatch.setenv("TVOPT_CODEGEN_CACHE", str(tmp_path / "cache"))
    write_files(render(kernels, "python"), tmp_path)
    write_files(render(kernels, "c"), tmp_path)
    python = import_file(tmp_path / f"planar{links}.py", f"_tvopt_arm{links}_py")
    compiled = import_file(tmp_path / f"planar{links}_c.py", f"_tvopt_arm{links}_c")
    rng = np.random.default_rng(links)
    states = np.vstack([rng.uniform(-1.5, 1.5, (links, 200)), rng.uniform(-1.0, 1.0, (links, 200))])
    assert_matches_oracle(oracle, (python, compiled), states, (0.0, 1.3))


def _arm2() -> dict[str, Any]:
    return tomllib.loads(Path(ARM2).read_text(encoding="utf-8"))


def _refused(
    data: dict[str, Any], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> tuple[int, str]:
    path = tmp_path / "bad.toml"
    path.write_text(spec_toml(data), encoding="utf-8")
    out = tmp_path / "out"
    code = main(["generate", str(path), "--out", str(out)])
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err, err
    assert not out.exists()
    return code, err


def test_a_mass_matrix_that_is_not_symmetric(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    data = _arm2()
    data["system"]["mechanics"]["mass_matrix"][1][0] = "a3 + a2*sin(q2)"
    code, err = _refused(data, tmp_path, capsys)
    assert code == EXIT_BAD_SPEC
    assert "system.mechanics.mass_matrix[1][0]: M is not symmetric" in err


def test_a_mass_matrix_singular_at_the_start(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    data = _arm2()
    # a3 = a1 + 2 a2 cos(q2) - ... : with a3 = 0 the second pivot is 0 at every state.
    data["parameters"]["a3"] = 0.0
    code, err = _refused(data, tmp_path, capsys)
    assert code == EXIT_ASSUMPTION
    assert "system.mechanics.mass_matrix: M is not positive definite at the initial state" in err


def test_mechanics_together_with_dynamics(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    data = _arm2()
    data["system"]["states"] = ["q1", "q2", "dq1", "dq2"]
    data["system"]["dynamics"] = {"q1": "dq1", "q2": "dq2", "dq1": "tau1", "dq2": "tau2"}
    code, err = _refused(data, tmp_path, capsys)
    assert code == EXIT_BAD_SPEC
    assert "not both" in err


@pytest.mark.parametrize(
    ("where", "value", "problem"),
    [
        ("mass_matrix", [["1"]], "expected a list of 2 rows"),
        ("forces", ["0"], "expected a list of 2 entries"),
        ("input_matrix", [[1, 0], [0, "tau1"]], "'tau1'"),
        ("forces", ["dq1*tau1", "0"], None),
        ("rates", ["w1"], "1 rates for 2 coordinates"),
    ],
)
def test_malformed_mechanics(
    where: str,
    value: object,
    problem: str | None,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    data = _arm2()
    data["system"]["mechanics"][where] = copy.deepcopy(value)
    if problem is None:
        # Forces holding the inputs need no input matrix, but must be affine in them.
        del data["system"]["mechanics"]["input_matrix"]
        data["system"]["mechanics"]["forces"] = ["tau1*tau2", "tau2"]
        problem = "not affine in the inputs"
    code, err = _refused(data, tmp_path, capsys)
    assert code == EXIT_BAD_SPEC and f"system.mechanics.{where}" in err and problem in err, err


def test_forces_affine_in_the_inputs_give_b() -> None:
    data = _arm2()
    mech = data["system"]["mechanics"]
    mech["forces"] = [f"({mech['forces'][0]}) + tau1", f"({mech['forces'][1]}) + 2*tau2"]
    del mech["input_matrix"]
    spec = spec_from_dict(data)
    assert spec.mechanics is not None
    assert spec.mechanics.input_matrix == ((1, 0), (0, 2))


def test_an_output_that_needs_the_derivative_of_m_inverse() -> None:
    """Relative degree above 2 would differentiate M^-1 F: a one-line AssumptionError."""
    data = {
        "name": "chain",
        "system": {
            "coordinates": ["q1", "q2"],
            "inputs": ["tau"],
            "mechanics": {
                "mass_matrix": [["2", "0"], ["0", "1"]],
                "forces": ["0", "sin(q1)"],
                "input_matrix": [[1], [0]],
            },
            "outputs": {"y": "q2"},
        },
        "objective": {"f0": "(y - t)**2"},
        "error_dynamics": {"poles": [-1.0, -2.0, -3.0, -4.0]},
    }
    with pytest.raises(
        AssumptionError, match=r"system.outputs.y: output 'y' needs the derivative of M\^-1"
    ):
        derive(spec_from_dict(data))
    data["extension"] = {"integrate": {"tau": 1}}
    with pytest.raises((AssumptionError, SpecError)):
        derive(spec_from_dict(data))


def test_a_mass_matrix_that_loses_definiteness_at_run_time(
    tmp_path_factory: pytest.TempPathFactory,
) -> None:
    """Both backends stop with MASS_MATRIX_NOT_PD, naming the failing column."""
    from .test_c_backend import c_module

    states = np.array([[0.1, 0.3], [0.2, 0.1], [0.0, 0.5], [0.0, -0.2]])
    for mod in (module(ARM2), c_module(ARM2, tmp_path_factory)):
        assert mod.control(0.5, states).shape == (2, 2)
        with pytest.raises(mod.MassMatrixNotPositiveDefiniteError) as info:
            mod.control(0.5, states, {"a3": -0.4})
        assert info.value.status == contract.Status.MASS_MATRIX_NOT_PD
        assert "the mass matrix M(q) is not positive definite" in str(info.value)
        with pytest.raises(mod.MassMatrixNotPositiveDefiniteError):
            mod.rhs(0.5, states[:, 1], {"a3": -0.4})


@pytest.mark.parametrize("spec", ["planar_arm3", "ur5_tip"])
def test_casadis_own_law_agrees(spec: str) -> None:
    """CasADi's AD with its ldl and qr solvers (tests/casadi_oracle.py) gives our law."""
    pytest.importorskip("casadi", reason="the CasADi oracle needs casadi (the dev extra)")
    from .casadi_oracle import casadi_mechanics_law

    d = derivation(spec)  # the one module(spec) is generated from: derived once
    law, _ = casadi_mechanics_law(d)
    mod = module(spec)
    p = np.array(list(mod.PARAMETERS.values()))
    rng = np.random.default_rng(9)
    base = np.array(d.closed_loop.initial_state)
    n = len(base) // 2
    for t in (0.0, 1.7, 4.2):
        for _ in range(10):
            state = base + np.concatenate([rng.uniform(-0.3, 0.3, n), rng.uniform(-1, 1, n)])
            ours = mod.control(t, state)
            theirs = np.array(law(t, state, p)).ravel()
            np.testing.assert_allclose(ours, theirs, rtol=1e-9, atol=1e-9 * np.abs(theirs).max())


def test_a_sweep_of_the_bundled_arm_with_a_heavier_last_link(tmp_path: Path) -> None:
    """The compiled sweep loop factors M like the controller: 8 samples, a 10% mass spread."""
    pytest.importorskip("distributed")
    out = tmp_path / "sweep"
    args = ["sweep", "planar_arm3", "--samples", "8", "--t-final", "2", "--out", str(out)]
    assert main([*args, "--plant-param", "m3=normal(1.5, 0.15)"]) == 0
    summary = (out / "summary.md").read_text(encoding="utf-8")
    assert "# Sweep of planar_arm3: 8 samples" in summary and "Clopper-Pearson" in summary
