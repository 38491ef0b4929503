"""Spec validation: each bad spec gives one line naming file, field and problem."""

from __future__ import annotations

from pathlib import Path

import pytest

from tvopt_codegen.derivation import derive
from tvopt_codegen.errors import AssumptionError, SpecError
from tvopt_codegen.spec import bundled_examples, load_spec

from .conftest import write_spec


def _mutate(text: str, old: str, new: str) -> str:
    assert old in text, old
    return text.replace(old, new, 1)


BAD = [
    # (old, new, field, message)
    ('name = "unicycle_switch"', 'name = "os"', "name", "shadows the Python standard module"),
    ('name = "unicycle_switch"', 'name = "Unicycle"', "name", "must be lower case"),
    (
        'states = ["x1", "x2", "theta"]',
        'states = ["x1", "x2", "theta", "x1"]',
        "system.states.x1",
        "already declared",
    ),
    (
        'states = ["x1", "x2", "theta"]',
        'states = ["x1", "x2", "_theta"]',
        "system.states[2]",
        "underscore",
    ),
    (
        'states = ["x1", "x2", "theta"]',
        'states = ["x1", "x2", "lambda"]',
        "system.states[2]",
        "Python keyword",
    ),
    ('inputs = ["v", "omega"]', 'inputs = ["v", "double"]', "system.inputs[1]", "C keyword"),
    ('inputs = ["v", "omega"]', 'inputs = ["v", "sqrt"]', "system.inputs[1]", "built-in function"),
    (
        'x1 = "v*cos(theta)"',
        'x1 = "v*cos(thetta)"',
        "system.dynamics.x1",
        "column 7: unknown name 'thetta'",
    ),
    ('theta = "omega"', 'theta = "omega**2"', "system.dynamics.theta", "not affine in the inputs"),
    ('x1 = "v*cos(theta)"', 'x1 = "v*omega"', "system.dynamics.x1", "not affine in the inputs"),
    ('x1 = "v*cos(theta)"\n', "", "system.dynamics.x1", "missing right-hand side"),
    ('y1 = "x1"', 'y1 = "v"', "system.outputs.y1", "input 'v' may not appear here"),
    ("b = 1.5", 'b = "1.5"', "parameters.b", "expected a number"),
    ("a = 10.0", "a = nan", "parameters.a", "finite"),
    ('S = "0.5', 'S = "0.5 + x1*0', "signals.S", "state 'x1' may not appear here"),
    ('f0 = "S*', 'f0 = "theta + S*', "objective.f0", "state 'theta' may not appear here"),
    (
        "integrate = { v = 1 }",
        "integrate = { speed = 1 }",
        "extension.integrate.speed",
        "not a declared input",
    ),
    ("integrate = { v = 1 }", "integrate = { v = 1.5 }", "extension.integrate.v", "whole number"),
    (
        "poles = [-1.0, -1.5]",
        "poles = [[-1.0, 0.0]]",
        "error_dynamics.poles[0]",
        "must be positive",
    ),
    (
        "poles = [-1.0, -1.5]",
        "poles = [-1.0]\ncoefficients = [1.0]",
        "error_dynamics",
        "exactly one",
    ),
    ("t_final = 20.0", "t_final = -1.0", "simulation.t_final", "must be positive"),
    ("t_final = 20.0", "t_final = 20.0\nsolver = 'rk4'", "simulation.solver", "unknown key"),
    ("[objective]", "[objektive]", "objektive", "unknown key"),
    (
        "theta = 0.0, ",
        "theta = 0.0, phi = 1.0, ",
        "simulation.initial_state.phi",
        "not a state of the closed loop",
    ),
    ("theta = 0.0, ", "", "simulation.initial_state.theta", "missing"),
]


@pytest.mark.parametrize(("old", "new", "field", "message"), BAD)
def test_bad_spec_names_field_and_problem(
    tmp_path: Path, unicycle_text: str, old: str, new: str, field: str, message: str
) -> None:
    path = write_spec(tmp_path, _mutate(unicycle_text, old, new))
    with pytest.raises(SpecError) as info:
        derive(load_spec(path))
    text = str(info.value)
    assert text.startswith(f"{path}: {field}: "), text
    assert message in text, text
    assert "\n" not in text


@pytest.mark.parametrize(
    ("content", "message"),
    [
        (b"", "missing required key"),
        (b"\x00\x01\x02", "binary file"),
        (b"\xff\xfe bad", "not UTF-8"),
        (b"name = [", "TOML syntax error"),
        (b'name = "a"\nname = "b"', "TOML syntax error"),
    ],
)
def test_unreadable_files(tmp_path: Path, content: bytes, message: str) -> None:
    path = tmp_path / "broken.toml"
    path.write_bytes(content)
    with pytest.raises(SpecError, match=message):
        load_spec(path)


def test_missing_file_lists_examples(tmp_path: Path) -> None:
    with pytest.raises(SpecError, match="no bundled example of that name") as info:
        load_spec(tmp_path / "nope.toml")
    assert "unicycle_switch" in str(info.value)


def test_bundled_examples_are_listed_and_load() -> None:
    examples = bundled_examples()
    assert set(examples) == {
        "integrator",
        "unicycle_switch",
        "two_unicycles_barrier",
        "pvtol",
        "flexible_joint",
        "unicycle_ring",
        # Their twins with the moving objects as references measured at run time.
        *(f"{name}_refs" for name in ("integrator", "unicycle_switch", "pvtol")),
        *(f"{name}_refs" for name in ("two_unicycles_barrier", "unicycle_ring")),
        # The paper's Fig. 3 team inside a moving corridor ([constraints]).
        "two_unicycles_corridor",
        # A two-link arm's end effector on a turning line (an equality constraint).
        "arm_on_line",
        # A three-link arm in mass-matrix form ([system.mechanics]).
        "planar_arm3",
        # A six-joint arm imported from a URDF file (import-urdf).
        "ur5_tip",
        # An underactuated vehicle with drag: the extended-state observer's example.
        "drag_vehicle",
    }
    for name in examples:
        spec = load_spec(name)
        assert spec.name == name
        assert spec.source == f"{name}.toml (bundled example)"


def test_decimals_stay_exact(unicycle_text: str, tmp_path: Path) -> None:
    spec = load_spec(write_spec(tmp_path, unicycle_text))
    signals = dict(spec.signals)
    assert str(signals["S"]) == "1/2 - tanh(t/b - a/b)/2" or "1/2" in str(signals["S"])
    assert spec.extension == (("v", 1),)
    assert spec.poles == (complex(-1, 0), complex(-1.5, 0))


def test_non_square_plant_is_an_assumption_error(tmp_path: Path, unicycle_text: str) -> None:
    text = _mutate(unicycle_text, 'y2 = "x2"', 'y2 = "x2"\ny3 = "theta"')
    with pytest.raises(AssumptionError, match="2 inputs but 3 outputs"):
        derive(load_spec(write_spec(tmp_path, text)))


# A value of the wrong type anywhere: TOML's 1 is not true, true is not 1 (Python says
# both are equal), and each message names the type and the value it got.
WRONG_TYPES = [
    # (old, new, field, message)
    ("[simulation]", "[robust]\nintegral = 1\n\n[simulation]", "robust.integral", "got integer 1"),
    ("[simulation]", "[robust]\nintegral = 0.0\n\n[simulation]", "robust.integral", "float 0.0"),
    (
        "[simulation]",
        '[robust]\nintegral = "yes"\n\n[simulation]',
        "robust.integral",
        "expected true or false, got string 'yes'",
    ),
    (
        "[simulation]",
        "[robust]\nintegral = [true]\n\n[simulation]",
        "robust.integral",
        "got array [true]",
    ),
    (
        "[simulation]",
        "[robust]\nintegral = 1979-05-27\n\n[simulation]",
        "robust.integral",
        "got date 1979-05-27",
    ),
    (
        "[simulation]",
        "[robust]\nobserver = 1\n\n[simulation]",
        "robust.observer",
        "table, got integer 1",
    ),
    (
        "[simulation]",
        "[robust.observer]\nbandwidth = true\n\n[simulation]",
        "robust.observer.bandwidth",
        "expected a number, got boolean true",
    ),
    (
        'name = "unicycle_switch"',
        'robust = 2\nname = "unicycle_switch"',
        "robust",
        "table, got integer 2",
    ),
    (
        "integrate = { v = 1 }",
        "integrate = { v = true }",
        "extension.integrate.v",
        "expected a whole number of integrators 0..8, got boolean true",
    ),
    (
        "integrate = { v = 1 }",
        "auto = 1",
        "extension.auto",
        "expected true or false, got integer 1",
    ),
    (
        "integrate = { v = 1 }",
        "auto = true\nmax_total = 2.0",
        "extension.max_total",
        "expected a whole number 1..24, got float 2.0",
    ),
    ("a = 10.0", "a = true", "parameters.a", "expected a number, got boolean true"),
    ("t_final = 20.0", "t_final = false", "simulation.t_final", "got boolean false"),
    ("poles = [-1.0, -1.5]", "poles = [-1.0, true]", "error_dynamics.poles[1]", "boolean true"),
    ('theta = "omega"', "theta = 1", "system.dynamics.theta", "expression string, got integer 1"),
    ('inputs = ["v", "omega"]', 'inputs = ["v", 2]', "system.inputs[1]", "name, got integer 2"),
    ('name = "unicycle_switch"', "name = 7", "name", "expected a string, got integer 7"),
    (
        'objects = [["o1x", "o1y"], ["o2x", "o2y"]]',
        'objects = [["o1x", 1], ["o2x", "o2y"]]',
        "simulation.objects[0]",
        "names, got integer 1",
    ),
    (
        "[simulation]",
        '[references]\nnames = ["r"]\n[references.estimator]\nkind = 1\n\n[simulation]',
        "references.estimator.kind",
        "got integer 1",
    ),
    (
        "[simulation]",
        '[constraints]\nnear = "y1 <= 10"\nallow_nonconvex = 1\n\n[simulation]',
        "constraints.allow_nonconvex",
        "expected true or false, got integer 1",
    ),
    (
        "[simulation]",
        '[constraints]\nnear = "y1 <= 10"\n[constraints.barrier]\nrate = true\n\n[simulation]',
        "constraints.barrier.rate",
        "expected a number, got boolean true",
    ),
    (
        "[simulation]",
        "[limits]\nomega = [false, 1.0]\n\n[simulation]",
        "limits.omega[0]",
        "expected a number, got boolean false",
    ),
]


def _refusal_of(tmp_path: Path, text: str, old: str, new: str, field: str) -> str:
    """The SpecError of the unicycle spec with ``old`` replaced by ``new``; it names ``field``."""
    path = write_spec(tmp_path, _mutate(text, old, new))
    with pytest.raises(SpecError) as info:
        derive(load_spec(path))
    message = str(info.value)
    assert message.startswith(f"{path}: {field}: "), message
    return message


@pytest.mark.parametrize(("old", "new", "field", "message"), WRONG_TYPES)
def test_a_value_of_the_wrong_type_is_named_with_its_type(
    tmp_path: Path, unicycle_text: str, old: str, new: str, field: str, message: str
) -> None:
    text = _refusal_of(tmp_path, unicycle_text, old, new, field)
    assert message in text and "\n" not in text, text


# A misspelt key or name at any depth gets the nearest valid one.
MISSPELT = [
    # (old, new, field, suggestion)
    ("[objective]", "[objektive]", "objektive", "'objective'"),
    ("t_final = 20.0", "t_finl = 20.0", "simulation.t_finl", "'t_final'"),
    ("initial_state = {", "initial_stat = {", "simulation.initial_stat", "'initial_state'"),
    ("theta = 0.0, ", "thetaa = 0.0, ", "simulation.initial_state.thetaa", "'theta'"),
    ('theta = "omega"', 'thetta = "omega"', "system.dynamics.thetta", "'theta'"),
    ("integrate = { v = 1 }", "integrate = { omegq = 1 }", "extension.integrate.omegq", "'omega'"),
    ("integrate = { v = 1 }", "integrate = { v = 1 }\nauot = true", "extension.auot", "'auto'"),
    ('["o2x", "o2y"]]', '["o2x", "o2yy"]]', "simulation.objects[1]", "'o2y'"),
    (
        "[simulation]",
        "[robust.observer]\nbandwith = 20.0\n\n[simulation]",
        "robust.observer.bandwith",
        "'bandwidth'",
    ),
    (
        "[simulation]",
        "[robust]\nintegrall = true\n\n[simulation]",
        "robust.integrall",
        "'integral'",
    ),
    (
        "[simulation]",
        '[constraints]\nnear = "y1 <= 10"\n[constraints.barier]\nrate = 1.0\n\n[simulation]',
        "constraints.barier",
        "'barrier'",
    ),
    (
        "[simulation]",
        '[constraints]\nnear = "y1 <= 10"\n[constraints.barrier]\nrat = 1.0\n\n[simulation]',
        "constraints.barrier.rat",
        "'rate'",
    ),
    (
        "[simulation]",
        '[constraints]\nnear = "y1 <= 10"\nallow_nonconvx = true\n\n[simulation]',
        "constraints.allow_nonconvx",
        "'allow_nonconvex'",
    ),
    (
        "[simulation]",
        '[constraints]\nnear = "y1 <= 10"\nbarier = 1.0\n\n[simulation]',
        "constraints.barier",
        "'barrier'",
    ),
    ("[simulation]", "[limits]\nomgea = 1.0\n\n[simulation]", "limits.omgea", "'omega'"),
    ("[simulation]", "[limits.rate]\nomeg = 1.0\n\n[simulation]", "limits.rate.omeg", "'omega'"),
    (
        "[simulation]",
        '[references]\nnames = ["ref"]\n[references.nominal]\nreff = "t"\n\n[simulation]',
        "references.nominal.reff",
        "'ref'",
    ),
    (
        "[simulation]",
        '[references]\nnames = ["r"]\n[references.estimator]\nbandwdth = 5.0\n\n[simulation]',
        "references.estimator.bandwdth",
        "'bandwidth'",
    ),
]


@pytest.mark.parametrize(("old", "new", "field", "guess"), MISSPELT)
def test_a_misspelt_key_at_any_depth_gets_the_nearest_valid_one(
    tmp_path: Path, unicycle_text: str, old: str, new: str, field: str, guess: str
) -> None:
    text = _refusal_of(tmp_path, unicycle_text, old, new, field)
    assert f"did you mean {guess}?" in text, text
