"""import-urdf: a URDF robot's M(q) and bias forces against Pinocchio, its law against the
oracle in both backends, the bundled ur5_tip through every command, and bad files refused.
"""

from __future__ import annotations

import os
import shutil
import tomllib
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from tvopt_codegen import symbolic as sx
from tvopt_codegen.cli import main
from tvopt_codegen.emit import write_files
from tvopt_codegen.errors import EXIT_BAD_SPEC, EXIT_OUTPUT, Terminated
from tvopt_codegen.mechanics import spec_toml
from tvopt_codegen.renderer.rendering import render
from tvopt_codegen.spec import load_spec, spec_from_dict
from tvopt_codegen.spec.implicit import implicit_values, mass_matrix_at
from tvopt_codegen.urdf import spec_from_urdf

from .conftest import ROOT, Ran, derivation, import_file, run_main
from .conftest import kernels as lowered
from .oracle import Oracle, assert_matches_oracle
from .pinocchio_check import both_at

pytest.importorskip("yourdfpy", reason="import-urdf needs the urdf extra (yourdfpy)")

UR5 = ROOT / "tests" / "robots" / "ur5_like.urdf"
INITIAL = {"shoulder_lift": -1.2, "elbow": 1.6, "wrist_1": -1.97, "wrist_2": -1.57}

#: A smaller chain with what the UR5 lacks: a prismatic joint, an axis not along z, a
#: joint placement with roll, pitch and yaw, a rotated inertia frame, and a fixed side
#: branch (a sensor) whose mass the chain carries.
SLIDER = """<?xml version="1.0"?>
<robot name="slider">
  <link name="base"/>
  <joint name="yaw" type="revolute">
    <parent link="base"/><child link="post"/>
    <origin xyz="0 0 0.3" rpy="0 0 0"/><axis xyz="0 0 1"/>
    <limit lower="-2" upper="2" effort="10" velocity="1"/>
  </joint>
  <link name="post">
    <inertial><origin xyz="0 0 0.1" rpy="0.1 0.2 0.3"/><mass value="2.0"/>
      <inertia ixx="0.02" ixy="0.001" ixz="0.002" iyy="0.03" iyz="0.003" izz="0.025"/></inertial>
  </link>
  <joint name="slide" type="prismatic">
    <parent link="post"/><child link="carriage"/>
    <origin xyz="0.1 0 0.2" rpy="0.3 -0.2 0.5"/><axis xyz="0.6 0 0.8"/>
    <limit lower="0" upper="0.5" effort="50" velocity="1"/>
  </joint>
  <link name="carriage">
    <inertial><origin xyz="0.05 0.02 0" rpy="0 0 0"/><mass value="1.2"/>
      <inertia ixx="0.004" ixy="0" ixz="0" iyy="0.005" iyz="0" izz="0.006"/></inertial>
  </link>
  <joint name="camera_mount" type="fixed">
    <parent link="carriage"/><child link="camera"/>
    <origin xyz="0 0.1 0" rpy="0 0 1.2"/>
  </joint>
  <link name="camera">
    <inertial><origin xyz="0.01 0 0.01" rpy="0 0 0"/><mass value="0.3"/>
      <inertia ixx="0.0003" ixy="0" ixz="0" iyy="0.0003" iyz="0" izz="0.0002"/></inertial>
  </link>
  <joint name="wrist" type="continuous">
    <parent link="carriage"/><child link="hand"/>
    <origin xyz="0.2 0 0" rpy="0 1.5707963267948966 0"/><axis xyz="0 1 0"/>
  </joint>
  <link name="hand">
    <inertial><origin xyz="0 0 0.05" rpy="0 0 0"/><mass value="0.5"/>
      <inertia ixx="0.001" ixy="0" ixz="0" iyy="0.001" iyz="0" izz="0.0005"/></inertial>
  </link>
</robot>
"""


@pytest.mark.parametrize("robot", ["ur5", "slider"])
def test_mass_matrix_and_bias_forces_equal_pinocchios(robot: str, tmp_path: Path) -> None:
    """M(q) and -F(q, q') = C q' + g at random states, to 1e-10 relative."""
    pin = pytest.importorskip("pinocchio", reason="the check needs Pinocchio (pin)")
    path = UR5
    if robot == "slider":
        path = tmp_path / "slider.urdf"
        path.write_text(SLIDER, encoding="utf-8")
    spec = spec_from_dict(spec_from_urdf(path, gravity=(0.3, -0.2, -9.81)))
    mech = spec.mechanics
    assert mech is not None
    model = pin.buildModelFromUrdf(str(path))
    model.gravity.linear = np.array([0.3, -0.2, -9.81])
    data = model.createData()
    assert model.nv == len(mech.coordinates)
    rng = np.random.default_rng(7)
    # By name, as the spec holds them: the product keys them by its engine's symbols.
    params = dict(spec.parameters)
    for _ in range(25):
        q = rng.uniform(-np.pi, np.pi, model.nv)
        v = rng.uniform(-2.0, 2.0, model.nv)
        ours, theirs, our_bias, bias = both_at(mech, params, model, data, q, v)
        np.testing.assert_allclose(ours, theirs, rtol=0, atol=1e-10 * np.abs(theirs).max())
        np.testing.assert_allclose(our_bias, bias, rtol=0, atol=1e-10 * np.abs(bias).max())


@pytest.mark.parametrize("engine", ["symengine", "sympy"])
def test_the_doors_values_are_taken_by_name_or_by_either_engines_symbol(
    engine: str, tmp_path: Path
) -> None:
    """M and M^-1 F of the URDF door's spec at the door's own parameter mapping.

    Its parameters are a name-to-value mapping; a SymPy user keys values by SymPy's
    symbols while the spec's expressions are SymEngine's (the default engine), and the
    other way round. Each keying gives the numbers the engine's own symbols give, never
    "no value for the symbol Ixx_..." for a symbol the caller did give.
    """
    import symengine
    import sympy

    path = tmp_path / "slider.urdf"
    path.write_text(SLIDER, encoding="utf-8")
    with sx.using(engine):
        door = spec_from_urdf(path, gravity=(0.3, -0.2, -9.81))
        mech = spec_from_dict(door).mechanics
        assert mech is not None
        rng = np.random.default_rng(3)
        by_name: dict[str, object] = dict(door["parameters"])
        by_name |= {s: rng.uniform(-2.0, 2.0, 4) for s in (*mech.coordinates, *mech.rates)}
        keyings: dict[str, dict[Any, object]] = {
            "engine": {sx.symbol(k): v for k, v in by_name.items()},
            "name": by_name,
            "sympy": {sympy.Symbol(k, real=True): v for k, v in by_name.items()},
            "symengine": {symengine.Symbol(k): v for k, v in by_name.items()},
        }
        mass = {how: mass_matrix_at(mech, values, 4) for how, values in keyings.items()}
        accel = {how: implicit_values(mech, values, 4) for how, values in keyings.items()}
        with pytest.raises(TypeError, match="a name or a symbol"):
            mass_matrix_at(mech, {**by_name, 1.5: 2.0}, 4)
    # Real numbers: a positive definite M, finite accelerations that move.
    assert np.all(np.linalg.eigvalsh(mass["engine"]) > 0)
    assert any(np.all(np.isfinite(a)) and np.ptp(a) > 0 for a in accel["engine"].values())
    for how in keyings:
        np.testing.assert_array_equal(mass[how], mass["engine"], err_msg=how)
        assert accel[how].keys() == accel["engine"].keys()
        for symbol, value in accel["engine"].items():
            np.testing.assert_array_equal(accel[how][symbol], value, err_msg=how)


def test_the_imported_law_matches_the_oracle_in_both_backends(tmp_path: Path) -> None:
    """The UR5's tip-tracking law (its 340 definitions in the kernels) against numpy's.

    The law of the bundled ur5_tip, which is the import's output (the next test): its
    derivation is the one other tests share (conftest's cache), and its C module the
    one ``generate ur5_tip --backend c`` writes, compiled once in the run's cache.
    """
    d = derivation("ur5_tip")
    kernels = lowered("ur5_tip")
    oracle = Oracle(d)
    write_files(render(kernels, "python"), tmp_path)
    write_files(render(kernels, "c"), tmp_path)
    python = import_file(tmp_path / "ur5_tip.py", "_tvopt_ur5_py")
    compiled = import_file(tmp_path / "ur5_tip_c.py", "_tvopt_ur5_c")
    rng = np.random.default_rng(2)
    base = np.array(d.closed_loop.initial_state)[:, None]
    states = base + np.vstack([rng.uniform(-0.4, 0.4, (6, 300)), rng.uniform(-1, 1, (6, 300))])
    assert_matches_oracle(oracle, (python, compiled), states, (0.0, 2.1))


def test_the_bundled_example_is_what_import_urdf_writes() -> None:
    """ur5_tip.toml is the import's output with its description written for people."""
    fresh = spec_from_urdf(UR5, tip="tool0", name="ur5_tip", initial=INITIAL)
    bundled = tomllib.loads(
        (ROOT / "tvopt_codegen" / "examples" / "ur5_tip.toml").read_text(encoding="utf-8")
    )
    assert "import-urdf tests/robots/ur5_like.urdf" in bundled.pop("description")
    fresh.pop("description")
    assert tomllib.loads(spec_toml(fresh)) == bundled


def test_the_import_prints_every_expression_as_sstr_does(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The import's own printer (sstr's rules without its cost) writes what sp.sstr writes.

    Every definition, entry of M, force and tip coordinate of the slider (a prismatic
    joint, an axis off z, rolled placements, a rotated inertia, a fixed side branch), so
    that the bundled examples stay what sstr made them.
    """
    import sympy

    import tvopt_codegen.urdf.mapping
    import tvopt_codegen.urdf.objective
    from tvopt_codegen.urdf.dynamics import _text

    printed: list[tuple[sympy.Expr, str]] = []

    def recorded(expr: sympy.Expr) -> str:
        text = _text(expr)
        printed.append((expr, text))
        return text

    monkeypatch.setattr(tvopt_codegen.urdf.mapping, "_text", recorded)
    monkeypatch.setattr(tvopt_codegen.urdf.objective, "_text", recorded)
    path = tmp_path / "slider.urdf"
    path.write_text(SLIDER, encoding="utf-8")
    spec_from_urdf(path, tip="hand", gravity=(0.3, -0.2, -9.81))
    assert len(printed) > 100
    for expr, text in printed:
        assert text == sympy.sstr(expr), expr


def _cli(*args: str, cwd: Path) -> Ran:
    return run_main(*args, cwd=cwd)


# The bundled six-joint arm through every command: check, generate (both backends), the
# stateful controller of the C module, report, simulate (the certificate), the FMU and a
# sweep. Four tests, not one: each command derives the arm (seconds each), and one test
# of all of them (28 s) was the longest of the suite, the last to end on two workers.
# The commands run in the test's process (run_main): the cold process is tested
# elsewhere, and a subprocess each cost a second of imports. Marked slow by hand:
# tests/durations.json has only the one test's time.


@pytest.mark.slow
def test_ur5_tip_checks_and_generates_a_stepping_c_controller(tmp_path: Path) -> None:
    for args in (
        ("check", "ur5_tip"),
        ("generate", "ur5_tip", "--out", "py", "--quiet"),
        ("generate", "ur5_tip", "--backend", "c", "--out", "c", "--quiet"),
    ):
        run = _cli(*args, cwd=tmp_path)
        assert run.returncode == 0, run.stderr
    # The stateful controller of the C module, stepped at 1 kHz.
    os.environ.setdefault("TVOPT_CODEGEN_CACHE", str(tmp_path / "cache"))
    mod = import_file(tmp_path / "c" / "ur5_tip_c.py", "_tvopt_ur5_tip_c")
    x = np.array(mod.DEFAULT_STATE[:12])
    controller = mod.Controller(x)
    for k in range(1, 6):
        u = controller.step(1e-3 * k, x)
        assert u.shape == (6,) and np.all(np.isfinite(u))


@pytest.mark.slow
def test_ur5_tip_reports_and_simulates_with_a_passing_certificate(tmp_path: Path) -> None:
    run = _cli("report", "ur5_tip", "--out", "report", cwd=tmp_path)
    assert run.returncode == 0, run.stderr
    run = _cli("simulate", "ur5_tip", "--out", "sim", "--points", "101", cwd=tmp_path)
    assert run.returncode == 0 and "certificate: PASSED" in run.stdout, run.stdout + run.stderr
    report = (tmp_path / "report" / "ur5_tip_report.md").read_text(encoding="utf-8")
    assert "M is factored at run time, never inverted" in report
    assert "Definitions (340)" in report and "_let" not in report


@pytest.mark.slow
def test_ur5_tip_exports_a_valid_fmu(tmp_path: Path) -> None:
    if not (shutil.which("cc") or shutil.which("gcc")):
        pytest.skip("an FMU needs a C compiler (cc or gcc)")
    fmpy = pytest.importorskip("fmpy")
    run = _cli("export", "ur5_tip", "--fmu", "--out", "fmu", cwd=tmp_path)
    assert run.returncode == 0, run.stderr
    from fmpy.validation import validate_fmu

    assert validate_fmu(str(tmp_path / "fmu" / "ur5_tip.fmu")) == []
    assert fmpy.read_model_description(str(tmp_path / "fmu" / "ur5_tip.fmu"))


@pytest.mark.slow
def test_ur5_tip_sweeps(tmp_path: Path) -> None:
    pytest.importorskip("distributed")
    run = _cli(
        "sweep", "ur5_tip", "--samples", "8", "--plant-param", "m_forearm=normal(2.275, 0.2)",
        "--t-final", "2", "--out", "sweep", cwd=tmp_path,
    )  # fmt: skip
    assert run.returncode == 0, run.stderr
    summary = (tmp_path / "sweep" / "summary.md").read_text(encoding="utf-8")
    assert "# Sweep of ur5_tip: 8 samples" in summary and "Clopper-Pearson" in summary


def _robot(body: str) -> str:
    return f'<?xml version="1.0"?>\n<robot name="bad">\n{body}\n</robot>\n'


_TWO_LINKS = """
  <link name="a"><inertial><mass value="1"/><inertia ixx="1" ixy="0" ixz="0" iyy="1" iyz="0" izz="1"/></inertial></link>
  <link name="b"><inertial><mass value="1"/><inertia ixx="1" ixy="0" ixz="0" iyy="1" iyz="0" izz="1"/></inertial></link>
"""  # noqa: E501


@pytest.mark.parametrize(
    ("text", "problem"),
    [
        (
            _robot(
                _TWO_LINKS
                + '<joint name="j" type="floating"><parent link="a"/><child link="b"/></joint>'
            ),  # noqa: E501
            "joint 'j': a floating joint (a floating base) is not supported",
        ),
        (
            _robot(
                _TWO_LINKS
                + '<link name="c"/>'
                + '<joint name="j1" type="revolute"><parent link="a"/><child link="b"/>'
                '<axis xyz="0 0 1"/><limit lower="-1" upper="1" effort="1" velocity="1"/></joint>'
                + '<joint name="j2" type="revolute"><parent link="c"/><child link="b"/>'
                '<axis xyz="0 0 1"/><limit lower="-1" upper="1" effort="1" velocity="1"/></joint>'
            ),
            "joint 'j2': link 'b' has a second parent joint: a closed chain is not supported",
        ),
        (
            _robot(
                _TWO_LINKS
                + '<link name="c"/>'
                + '<joint name="j1" type="revolute"><parent link="a"/><child link="b"/>'
                '<axis xyz="0 0 1"/><limit lower="-1" upper="1" effort="1" velocity="1"/></joint>'
                + '<joint name="j2" type="revolute"><parent link="b"/><child link="c"/>'
                '<axis xyz="0 0 1"/><limit lower="-1" upper="1" effort="1" velocity="1"/>'
                '<mimic joint="j1"/></joint>'
            ),
            "joint 'j2': mimics 'j1': a mimic joint is not driven on its own",
        ),
        (_robot('<link name="a">'), "not well-formed XML"),
        ('<?xml version="1.0"?>\n<!DOCTYPE r [<!ENTITY x "y">]>\n<robot name="r"/>', "ENTITY"),
        ('<?xml version="1.0"?>\n<sdf/>', "the root element is <sdf>, not <robot>"),
        (_robot(_TWO_LINKS), "expected one root link, found 2"),
        (_robot("<a>" * 40 + "</a>" * 40), "elements nest 40 deep (at most 32)"),
    ],
    ids=[
        "floating",
        "closed",
        "mimic",
        "malformed",
        "dtd",
        "root",
        "roots",
        "deep",
    ],  # fmt: skip
)
def test_bad_urdf_is_one_line_and_writes_nothing(
    text: str, problem: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "robot.urdf"
    path.write_text(text, encoding="utf-8")
    out = tmp_path / "out" / "robot.toml"
    out.parent.mkdir()
    assert main(["import-urdf", str(path), "--out", str(out)]) == EXIT_BAD_SPEC
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and problem in err and str(path) in err, err
    assert list(out.parent.iterdir()) == []


@pytest.mark.parametrize(
    ("args", "problem"),
    [
        (("--tip", "nowhere"), "--tip: no link 'nowhere'"),
        (("--gravity", "0,0"), "--gravity: '0,0': expected x,y,z numbers"),
        (("--initial", "knee=1"), "--initial: 'knee' is not a joint"),
        (("--initial", "elbow"), "--initial: 'elbow': expected NAME=VALUE"),
        (("--initial", "elbow=nan"), "--initial: elbow = nan is not finite"),
        (("--gravity", "0,0,inf"), "--gravity: '0,0,inf': expected x,y,z numbers"),
    ],
)
def test_bad_options(
    args: tuple[str, ...], problem: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "robot.toml"
    assert main(["import-urdf", str(UR5), "--out", str(out), *args]) == EXIT_BAD_SPEC
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and problem in err, err
    assert not out.exists()


def test_a_second_import_never_overwrites_an_edited_spec(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # The three-joint slider, not the UR5: what is written over, or not, is the file,
    # whatever the robot (and each import of the UR5 takes a second or more).
    robot = tmp_path / "slider.urdf"
    robot.write_text(SLIDER, encoding="utf-8")
    out = tmp_path / "arm.toml"
    assert main(["import-urdf", str(robot), "--out", str(out)]) == 0
    first = out.read_text(encoding="utf-8")
    assert load_spec(out).mechanics is not None
    assert main(["import-urdf", str(robot), "--out", str(out)]) == 0  # its own file: same text
    assert out.read_text(encoding="utf-8") == first
    out.write_text(first.replace("t_final = 10.0", "t_final = 4.0"), encoding="utf-8")
    assert main(["import-urdf", str(robot), "--out", str(out)]) == EXIT_OUTPUT
    assert "t_final = 4.0" in out.read_text(encoding="utf-8")
    capsys.readouterr()
    assert main(["import-urdf", str(robot), "--out", str(out), "--force"]) == 0
    assert out.read_text(encoding="utf-8") == first


@pytest.mark.parametrize(
    ("fault", "code", "word"),
    [(KeyboardInterrupt, 130, "interrupted"), (Terminated, 143, "terminated")],
)
def test_ctrl_c_or_sigterm_during_the_import_writes_nothing(
    fault: type[BaseException],
    code: int,
    word: str,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    """Interrupted inside the Newton-Euler pass: one line, the signal's code, the folder
    (with a file of the user's in it) as it was."""
    (tmp_path / "keep.toml").write_text("mine", encoding="utf-8")

    def interrupted(*_args: object, **_kwargs: object) -> None:
        raise fault

    monkeypatch.setattr("tvopt_codegen.urdf._newton_euler", interrupted)
    assert main(["import-urdf", str(UR5), "--out", str(tmp_path / "arm.toml")]) == code
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and word in err and "Traceback" not in err, err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["keep.toml"]
    assert (tmp_path / "keep.toml").read_text(encoding="utf-8") == "mine"
