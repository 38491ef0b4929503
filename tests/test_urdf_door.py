"""import-urdf at the door (issue 45): hostile robot files refused in one line with
nothing written, what real robot files hold accepted, the robots of example-robot-data
against Pinocchio, and a default objective that keeps clear of singularities.
"""

from __future__ import annotations

import codecs
import json
import os
import shutil
import subprocess
import sys
import time
import tomllib
from importlib import metadata
from pathlib import Path

import numpy as np
import pytest

from tvopt_codegen.cli import main
from tvopt_codegen.errors import EXIT_BAD_SPEC, EXIT_BUDGET
from tvopt_codegen.spec import spec_from_dict
from tvopt_codegen.urdf import MAX_JOINTS, MAX_LINKS, spec_from_urdf

from .conftest import ROOT, Ran, run_main, shared
from .pinocchio_check import both_at

pytest.importorskip("yourdfpy", reason="import-urdf needs the urdf extra (yourdfpy)")

SCARA = ROOT / "tests" / "robots" / "scara_bent.urdf"

_UNIT = '<inertia ixx="0.01" ixy="0" ixz="0" iyy="0.01" iyz="0" izz="0.01"/>'


def _link(name: str, inertial: str | None = None) -> str:
    body = inertial if inertial is not None else f'<mass value="1"/>{_UNIT}'
    return f'<link name="{name}"><inertial><origin xyz="0 0 0.05" rpy="0 0 0"/>{body}</inertial></link>'  # noqa: E501


def _joint(name: str, parent: str, child: str, extra: str = "", kind: str = "revolute") -> str:
    limit = '<limit lower="-1" upper="1" effort="10" velocity="1"/>' if kind == "revolute" else ""
    return (
        f'<joint name="{name}" type="{kind}"><parent link="{parent}"/><child link="{child}"/>'
        f'<origin xyz="0 0 0.1" rpy="0 0 0"/><axis xyz="0 0 1"/>{limit}{extra}</joint>'
    )


def _robot(*parts: str) -> str:
    return '<?xml version="1.0"?>\n<robot name="door">\n' + "\n".join(parts) + "\n</robot>\n"


def _two(
    a: str = "a", b: str = "b", inertial: str | None = None, joint: str = "", kind: str = "revolute"
) -> str:
    """A base link ``a`` and one link ``b`` on one joint (``joint`` replaces the joint)."""
    return _robot(
        _link(a), _link(b, inertial), joint or _joint("j", a, b, kind=kind)
    )  # fmt: skip


def _refused(
    path: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], *extra: str
) -> tuple[int, str]:
    out = tmp_path / "out" / "robot.toml"
    out.parent.mkdir(exist_ok=True)
    code = main(["import-urdf", str(path), "--out", str(out), *extra])
    err = capsys.readouterr().err
    assert list(out.parent.iterdir()) == [], "a refused import wrote a file"
    assert err.count("\n") == 1 and "Traceback" not in err, err
    return code, err


_MASSLESS_WITH_INERTIA = '<mass value="0"/>' + _UNIT.replace('ixx="0.01"', 'ixx="0.5"')

#: (id, URDF text, what the one line must hold): each names the link or joint, the field
#: and the value.
HOSTILE = [
    ("duplicate-link", _robot(_link("a"), _link("b"), _link("b"), _joint("j", "a", "b")),
     "link 'b': two links are named 'b'"),
    ("duplicate-joint", _robot(_link("a"), _link("b"), _link("c"), _joint("j", "a", "b"),
                               _joint("j", "b", "c")),
     "joint 'j': two joints are named 'j'"),
    ("dash-underscore", _robot(_link("base"), _link("link-1"), _link("link_1"),
                               _joint("j1", "base", "link-1"), _joint("j2", "link-1", "link_1")),
     "link 'link_1': links 'link-1' and 'link_1' both become 'link_1'"),
    ("non-ascii", _robot(_link("base"), _link("l\u00efnk"), _link("l\u00f6nk"),
                         _joint("j1", "base", "l\u00efnk"), _joint("j2", "l\u00efnk", "l\u00f6nk")),
     "links 'l\u00efnk' and 'l\u00f6nk' both become 'l_nk'"),
    ("truncation", _robot(_link("base"), _link("x" * 48 + "one"), _link("x" * 48 + "two"),
                          _joint("j1", "base", "x" * 48 + "one"),
                          _joint("j2", "x" * 48 + "one", "x" * 48 + "two")),
     "both become 'xxxxxxxx"),
    ("case", _robot(_link("base"), _link("arm"), _link("c"), _joint("Elbow", "base", "arm"),
                    _joint("elbow", "arm", "c")),
     "joints 'Elbow' and 'elbow' both become 'elbow'"),
    ("joint-vs-mass", _robot(_link("base"), _link("arm"), _joint("m_arm", "base", "arm")),
     "link 'arm': its spec name 'm_arm' is also made by joint 'm_arm'"),
    ("joint-vs-definition", _robot(_link("a"), _link("b"), _link("c"), _joint("j", "a", "b"),
                                   _joint("cos_j", "b", "c")),
     "joint 'cos_j': its spec name is 'cos_j', which the import also gives one of its definitions"),
    ("mass-negative", _two(inertial=f'<mass value="-1.5"/>{_UNIT}'),
     "link 'b': inertial mass = -1.5 is negative"),
    ("mass-nan", _two(inertial=f'<mass value="nan"/>{_UNIT}'),
     "link 'b': inertial mass = 'nan' is not finite"),
    ("mass-inf", _two(inertial=f'<mass value="1e999"/>{_UNIT}'),
     "link 'b': inertial mass = '1e999' is not finite"),
    ("mass-text", _two(inertial=f'<mass value="heavy"/>{_UNIT}'),
     "link 'b': inertial mass = 'heavy': expected 1 number"),
    ("mass-zero-inertia", _two(inertial=_MASSLESS_WITH_INERTIA),
     "link 'b': inertia ixx = 0.5 on a link of mass 0"),
    ("moves-no-mass", _two(inertial='<mass value="0"/>' + _UNIT.replace("0.01", "0")),
     "joint 'j': moves no mass (every link beyond it has mass 0): M would be singular"),
    ("inertia-nan", _two(inertial='<mass value="1"/>' + _UNIT.replace('iyy="0.01"', 'iyy="NaN"')),
     "link 'b': inertia iyy = 'NaN' is not finite"),
    ("inertia-negative", _two(inertial='<mass value="1"/>' + _UNIT.replace('ixx="0.01"', 'ixx="-0.01"')),  # noqa: E501
     "link 'b': inertia (ixx=-0.01, ixy=0.0, ixz=0.0, iyy=0.01, iyz=0.0, izz=0.01) is not positive definite"),  # noqa: E501
    ("inertia-indefinite", _two(inertial='<mass value="1"/>' + _UNIT.replace('ixy="0"', 'ixy="0.02"')),  # noqa: E501
     "ixy=0.02, ixz=0.0, iyy=0.01, iyz=0.0, izz=0.01) is not positive definite"),
    ("triangle", _two(inertial='<mass value="1"/>' + _UNIT.replace('izz="0.01"', 'izz="0.03"')),
     "link 'b': inertia (ixx=0.01, ixy=0.0, ixz=0.0, iyy=0.01, iyz=0.0, izz=0.03) breaks the "
     "triangle inequality: principal moments 0.01 + 0.01 < 0.03"),
    ("inertia-missing", _two(inertial='<mass value="1"/><inertia ixx="0.01" iyy="0.01"/>'),
     "link 'b': inertia ixy: missing"),
    ("inertial-rpy-nan", _two(inertial=f'<origin xyz="0 0 0" rpy="0 nan 0"/><mass value="1"/>{_UNIT}'),  # noqa: E501
     "link 'b': inertial origin rpy = '0 nan 0' is not finite"),
    ("joint-xyz-inf", _two(joint='<joint name="j" type="revolute"><parent link="a"/><child link="b"/>'  # noqa: E501
                                  '<origin xyz="0 inf 0"/><axis xyz="0 0 1"/></joint>'),
     "joint 'j': origin xyz = '0 inf 0' is not finite"),
    ("joint-rpy-short", _two(joint='<joint name="j" type="revolute"><parent link="a"/><child link="b"/>'  # noqa: E501
                                    '<origin rpy="0 1"/><axis xyz="0 0 1"/></joint>'),
     "joint 'j': origin rpy = '0 1': expected 3 numbers"),
    ("axis-zero", _two(joint='<joint name="j" type="revolute"><parent link="a"/><child link="b"/>'
                              '<axis xyz="0 0 0"/></joint>'),
     "joint 'j': axis xyz = '0 0 0' is zero"),
    ("axis-nan", _two(joint='<joint name="j" type="prismatic"><parent link="a"/><child link="b"/>'
                             '<axis xyz="0 nan 1"/></joint>'),
     "joint 'j': axis xyz = '0 nan 1' is not finite"),
    ("limit-nan", _two(joint='<joint name="j" type="revolute"><parent link="a"/><child link="b"/>'
                              '<axis xyz="0 0 1"/><limit lower="nan" upper="1" effort="1" '
                              'velocity="1"/></joint>'),
     "joint 'j': limit lower = 'nan' is not finite"),
    ("limit-effort-inf", _two(joint='<joint name="j" type="revolute"><parent link="a"/>'
                                     '<child link="b"/><axis xyz="0 0 1"/><limit lower="-1" '
                                     'upper="1" effort="inf" velocity="1"/></joint>'),
     "joint 'j': limit effort = 'inf' is not finite"),
    ("limit-crossed", _two(joint='<joint name="j" type="revolute"><parent link="a"/>'
                                  '<child link="b"/><axis xyz="0 0 1"/><limit lower="1" '
                                  'upper="-1" effort="1" velocity="1"/></joint>'),
     "joint 'j': limit lower = 1.0 is above upper = -1.0"),
]  # fmt: skip


@pytest.mark.parametrize(("text", "problem"), [c[1:] for c in HOSTILE], ids=[c[0] for c in HOSTILE])
def test_a_hostile_robot_is_one_line_exit_2_and_writes_nothing(
    text: str, problem: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "robot.urdf"
    path.write_text(text, encoding="utf-8")
    code, err = _refused(path, tmp_path, capsys)
    assert code == EXIT_BAD_SPEC and problem in err and str(path) in err, err


def test_a_merged_model_never_passes_silently(tmp_path: Path) -> None:
    """The issue's case: 'link-1' and 'link_1' would share m_link_1 (M off by 35%)."""
    text = _robot(
        _link("base"),
        _link("link-1", f'<mass value="1"/>{_UNIT}'),
        _link("link_1", f'<mass value="3"/>{_UNIT}'),
        _joint("j1", "base", "link-1"),
        _joint("j2", "link-1", "link_1"),
    )
    path = tmp_path / "merged.urdf"
    path.write_text(text, encoding="utf-8")
    with pytest.raises(Exception, match="links 'link-1' and 'link_1' both become 'link_1'"):
        spec_from_urdf(path)


_ENTITY = (
    '<!DOCTYPE robot [<!ENTITY evil "INJECTED">]>\n<robot name="&evil;"><link name="a"/></robot>\n'
)


@pytest.mark.parametrize(
    ("encoding", "bom", "declared"),
    [
        ("utf-16-le", codecs.BOM_UTF16_LE, "UTF-16"),
        ("utf-16-be", codecs.BOM_UTF16_BE, "UTF-16"),
        ("utf-16-le", b"", "UTF-16"),
        ("utf-16-be", b"", "UTF-16"),
        ("utf-32-le", codecs.BOM_UTF32_LE, "UTF-32"),
        ("utf-32-be", codecs.BOM_UTF32_BE, "UTF-32"),
        ("utf-8", codecs.BOM_UTF8, "UTF-8"),
        ("utf-7", b"", "UTF-7"),
        ("cp500", b"", "cp500"),
    ],
)
def test_a_doctype_is_refused_in_any_encoding(
    encoding: str, bom: bytes, declared: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Decoded first, then checked: no encoding hides the entity (the issue's UTF-16 file
    passed and 'INJECTED' reached the spec)."""
    text = f'<?xml version="1.0" encoding="{declared}"?>\n{_ENTITY}'
    path = tmp_path / "robot.urdf"
    if encoding == "cp500":
        # EBCDIC: the declaration itself is not ASCII, so it cannot be read: refused too.
        path.write_bytes(text.encode("cp500"))
    else:
        path.write_bytes(bom + text.encode(encoding))
    code, err = _refused(path, tmp_path, capsys)
    assert code == EXIT_BAD_SPEC and "INJECTED" not in err, err
    assert "DOCTYPE" in err or "not well-formed" in err, err


def test_a_utf16_robot_without_a_doctype_imports(tmp_path: Path) -> None:
    """Decoding is no refusal: the same robot in UTF-16 imports as in UTF-8."""
    text = _robot(_link("a"), _link("b"), _joint("j", "a", "b")).replace(
        '<?xml version="1.0"?>', '<?xml version="1.0" encoding="UTF-16"?>'
    )
    wide, narrow = tmp_path / "wide.urdf", tmp_path / "narrow.urdf"
    wide.write_bytes(codecs.BOM_UTF16_LE + text.encode("utf-16-le"))
    narrow.write_text(text.replace("UTF-16", "UTF-8"), encoding="utf-8")
    first, second = spec_from_urdf(wide), spec_from_urdf(narrow)
    first.pop("description"), second.pop("description")
    assert first == second


def _cli(*args: str, cwd: Path, timeout: float = 120) -> subprocess.CompletedProcess[str]:
    env = dict(os.environ, TVOPT_CODEGEN_CACHE=str(cwd / "cache"))
    return subprocess.run(
        [sys.executable, "-m", "tvopt_codegen", *args],
        check=False, cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout,
    )  # fmt: skip


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="named pipes need POSIX")
def test_a_fifo_is_refused_at_once(tmp_path: Path) -> None:
    """A FIFO with no writer hung the import; it is refused before any read."""
    fifo = tmp_path / "robot.urdf"
    os.mkfifo(fifo)
    run = _cli("import-urdf", str(fifo), "--out", "out.toml", cwd=tmp_path, timeout=60)
    assert run.returncode == EXIT_BAD_SPEC, run.stderr
    assert (
        run.stderr.count("\n") == 1 and "is a FIFO (named pipe), not a regular file" in run.stderr
    )
    assert not (tmp_path / "out.toml").exists()


@pytest.mark.parametrize(
    ("target", "problem"),
    [("/dev/zero", "is a character device, not a regular file"), (".", "is a directory")],
)
def test_special_files_are_refused(
    target: str, problem: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = Path(target) if target.startswith("/") else tmp_path
    if not path.exists():
        pytest.skip(f"{target} is not on this system")
    code, err = _refused(path, tmp_path, capsys)
    assert code == EXIT_BAD_SPEC and problem in err and "memory" not in err, err


def test_an_oversized_file_is_refused_before_it_is_read(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "huge.urdf"
    with path.open("wb") as handle:  # sparse: no 5 MB written
        handle.truncate(5_000_000)
    code, err = _refused(path, tmp_path, capsys)
    assert code == EXIT_BAD_SPEC and "5000000 bytes, larger than 1000000 bytes" in err, err


def _chain(n: int) -> str:
    parts = [_link("base")]
    for i in range(n):
        parts.append(_link(f"l{i}"))
        axis = ("0 0 1", "0 1 0", "1 0 0")[i % 3]
        parts.append(
            _joint(f"j{i}", "base" if i == 0 else f"l{i - 1}", f"l{i}").replace(
                'axis xyz="0 0 1"', f'axis xyz="{axis}"'
            )
        )
    return _robot(*parts)


def test_a_long_chain_is_refused_within_the_budget(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The issue's 100-joint chain ran past two minutes; it ends at once with exit 6."""
    path = tmp_path / "chain.urdf"
    path.write_text(_chain(100), encoding="utf-8")
    started = time.perf_counter()
    code, err = _refused(path, tmp_path, capsys)
    assert code == EXIT_BUDGET and time.perf_counter() - started < 20, err
    assert f"stage 'chain size': 100 driven joints, more than the {MAX_JOINTS}" in err, err


def test_thousands_of_fixed_links_are_refused_at_once(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """One driven joint carrying 2,000 fixed links: no recursion limit, no minutes."""
    parts = [_link("base"), _link("l0"), _joint("j0", "base", "l0")]
    for i in range(1, 2000):
        parts.append(f'<link name="l{i}"/>')
        parts.append(
            f'<joint name="f{i}" type="fixed"><parent link="l{i - 1}"/><child link="l{i}"/>'
            '<origin xyz="0 0 0.01"/></joint>'
        )
    path = tmp_path / "long.urdf"
    path.write_text(_robot(*parts), encoding="utf-8")
    code, err = _refused(path, tmp_path, capsys)
    assert code == EXIT_BUDGET, err
    assert f"stage 'chain size': 2001 links, more than the {MAX_LINKS}" in err, err


def test_the_import_stops_at_its_time_budget_naming_the_stage(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A chain the cap allows still ends with exit 6 when the clock runs out."""
    path = tmp_path / "chain.urdf"
    path.write_text(_chain(MAX_JOINTS), encoding="utf-8")
    started = time.perf_counter()
    code, err = _refused(path, tmp_path, capsys, "--max-seconds", "0.5")
    assert code == EXIT_BUDGET and time.perf_counter() - started < 20, err
    assert "derivation stage 'import-urdf: " in err and "longer than 0.5 s" in err, err


#: A small arm with what real files hold beyond the dynamics: a continuous joint with
#: position limits, a transmission, Gazebo tags, meshes, a safety controller, a massless
#: frame, and a two-finger gripper beyond the tip whose second finger mimics the first.
REAL = """<?xml version="1.0"?>
<robot name="real" xmlns:xacro="http://www.ros.org/wiki/xacro">
  <link name="base"><visual><geometry><mesh filename="package://real/base.dae"/></geometry></visual></link>
  <joint name="turn" type="continuous">
    <parent link="base"/><child link="upper"/><origin xyz="0 0 0.3" rpy="0 0 0"/>
    <axis xyz="0 0 1"/><limit lower="-6.28" upper="6.28" effort="40" velocity="1"/>
    <safety_controller k_position="100" k_velocity="40" soft_lower_limit="-6" soft_upper_limit="6"/>
    <dynamics damping="0.1" friction="0"/>
  </joint>
  <link name="upper">
    <inertial><origin xyz="0 0 0.1" rpy="0.1 0 0"/><mass value="2"/>
      <inertia ixx="0.02" ixy="0.001" ixz="0" iyy="0.025" iyz="0" izz="0.01"/></inertial>
    <collision><geometry><mesh filename="package://real/upper.stl"/></geometry></collision>
  </link>
  <joint name="lift" type="revolute">
    <parent link="upper"/><child link="fore"/><origin xyz="0 0 0.2" rpy="0 0 0"/>
    <axis xyz="0 1 0"/><limit lower="-0.5" upper="1.5" effort="40" velocity="1"/>
  </joint>
  <link name="fore">
    <inertial><origin xyz="0.1 0 0" rpy="0 0 0"/><mass value="1.5"/>
      <inertia ixx="0.004" ixy="0" ixz="0" iyy="0.012" iyz="0" izz="0.012"/></inertial>
  </link>
  <joint name="bend" type="revolute">
    <parent link="fore"/><child link="hand"/><origin xyz="0.25 0 0" rpy="0 0 0"/>
    <axis xyz="0 1 0"/><limit lower="0.4" upper="2.0" effort="20" velocity="1"/>
  </joint>
  <link name="hand">
    <inertial><origin xyz="0.05 0 0" rpy="0 0 0"/><mass value="0.6"/>
      <inertia ixx="0.0006" ixy="0" ixz="0" iyy="0.0008" iyz="0" izz="0.0008"/></inertial>
  </link>
  <joint name="flange_joint" type="fixed">
    <parent link="hand"/><child link="flange"/><origin xyz="0.1 0 0" rpy="0 0 0"/>
  </joint>
  <link name="flange">
    <inertial><mass value="0"/><inertia ixx="0" ixy="0" ixz="0" iyy="0" iyz="0" izz="0"/></inertial>
  </link>
  <joint name="finger_left" type="prismatic">
    <parent link="flange"/><child link="left"/><origin xyz="0.02 0 0" rpy="0 0 0"/>
    <axis xyz="0 1 0"/><limit lower="0" upper="0.04" effort="10" velocity="0.1"/>
  </joint>
  <link name="left">
    <inertial><origin xyz="0.01 0 0"/><mass value="0.1"/>
      <inertia ixx="0.00002" ixy="0" ixz="0" iyy="0.00002" iyz="0" izz="0.00001"/></inertial>
  </link>
  <joint name="finger_right" type="prismatic">
    <parent link="flange"/><child link="right"/><origin xyz="0.02 0 0" rpy="0 0 0"/>
    <axis xyz="0 -1 0"/><limit lower="0" upper="0.04" effort="10" velocity="0.1"/>
    <mimic joint="finger_left" multiplier="1.5" offset="0.001"/>
  </joint>
  <link name="right">
    <inertial><origin xyz="0.01 0 0"/><mass value="0.1"/>
      <inertia ixx="0.00002" ixy="0" ixz="0" iyy="0.00002" iyz="0" izz="0.00001"/></inertial>
  </link>
  <transmission name="turn_trans"><type>transmission_interface/SimpleTransmission</type>
    <joint name="turn"><hardwareInterface>EffortJointInterface</hardwareInterface></joint>
    <actuator name="turn_motor"><mechanicalReduction>100</mechanicalReduction></actuator>
  </transmission>
  <gazebo reference="upper"><material>Gazebo/Orange</material></gazebo>
  <gazebo><plugin name="control" filename="libgazebo_ros_control.so"/></gazebo>
</robot>
"""


def _pinocchio_check(
    path: Path, spec: dict[str, object], held: dict[str, float], states: int, seed: int
) -> float:
    """The largest relative difference of M and the bias forces from Pinocchio's, at random
    states; the joints in ``held`` locked where the import holds them."""
    pin = pytest.importorskip("pinocchio", reason="the check needs Pinocchio (pin)")
    full = pin.buildModelFromUrdf(str(path))
    reference = pin.neutral(full)
    locked = []
    for name, value in held.items():
        joint = full.joints[full.getJointId(name)]
        locked.append(full.getJointId(name))
        if joint.nq == 2:
            reference[joint.idx_q : joint.idx_q + 2] = np.cos(value), np.sin(value)
        else:
            reference[joint.idx_q] = value
    model = pin.buildReducedModel(full, locked, reference) if locked else full
    data = model.createData()
    mech = spec_from_dict(spec).mechanics
    assert mech is not None and model.nv == len(mech.coordinates)
    # The door's parameter mapping as it is, by name: the product keys it by its symbols.
    params = dict(spec["parameters"])  # type: ignore[call-overload]
    rng = np.random.default_rng(seed)
    worst = 0.0
    for _ in range(states):
        q = rng.uniform(-np.pi, np.pi, model.nv)
        v = rng.uniform(-2.0, 2.0, model.nv)
        ours, theirs, bias, their_bias = both_at(mech, params, model, data, q, v)
        worst = max(
            worst,
            float(np.abs(ours - theirs).max() / np.abs(theirs).max()),
            float(np.abs(bias - their_bias).max() / np.abs(their_bias).max()),
        )
    return worst


def test_what_real_files_hold_is_read_past_and_the_gripper_is_held(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "real.urdf"
    path.write_text(REAL, encoding="utf-8")
    out = tmp_path / "real.toml"
    assert main(["import-urdf", str(path), "--out", str(out), "--tip", "flange"]) == 0
    captured = capsys.readouterr()
    assert captured.err == ""  # transmissions, Gazebo tags, meshes: not a word
    held = "held fixed beyond or beside the tip 'flange': finger_left = 0.02, finger_right = 0.031"
    assert f"note: {held}" in captured.out, captured.out
    # The file written, not a second import: it is what the user gets.
    spec = tomllib.loads(out.read_text(encoding="utf-8"))
    assert spec["system"]["coordinates"] == ["turn", "lift", "bend"]
    # The continuous joint's limits are ignored: it starts at 0, not at their middle.
    assert spec["simulation"]["initial_state"]["turn"] == 0.0
    assert spec["simulation"]["initial_state"]["bend"] == 1.2
    worst = _pinocchio_check(path, spec, {"finger_left": 0.02, "finger_right": 0.031}, 10, 3)
    assert worst < 1e-9, worst


def test_a_mimic_joint_the_tip_needs_is_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "real.urdf"
    path.write_text(REAL, encoding="utf-8")
    code, err = _refused(path, tmp_path, capsys, "--tip", "right")
    assert code == EXIT_BAD_SPEC
    assert "joint 'finger_right': mimics 'finger_left': a mimic joint is not driven" in err, err


# --------------------------------------------------------------------- example-robot-data


def _robots_folder() -> Path | None:
    try:
        found = metadata.distribution("example-robot-data")
    except metadata.PackageNotFoundError:
        return None
    folder = Path(str(found.locate_file("cmeel.prefix/share/example-robot-data/robots")))
    return folder if folder.is_dir() else None


ROBOTS = _robots_folder()
needs_robots = pytest.mark.skipif(
    ROBOTS is None, reason="example-robot-data is not installed (pip install -e '.[dev]')"
)

#: (id, URDF path in example-robot-data, --tip, the joints held fixed there).
REAL_ROBOTS = [
    ("ur3", "ur_description/urdf/ur3_robot.urdf", None, {}),
    ("ur5", "ur_description/urdf/ur5_robot.urdf", None, {}),
    ("ur10", "ur_description/urdf/ur10_robot.urdf", None, {}),
    ("z1", "z1_description/urdf/z1.urdf", None, {}),
    ("so100", "so_arm_description/urdf/so100.urdf", None, {}),
    ("xarm7", "xarm_description/urdf/xarm7.urdf", None, {}),
    ("double-pendulum", "double_pendulum_description/urdf/double_pendulum.urdf", None, {}),
    ("double-pendulum-continuous",
     "double_pendulum_description/urdf/double_pendulum_continuous.urdf", None, {}),
    ("panda", "panda_description/urdf/panda.urdf", "panda_link8",
     {"panda_finger_joint1": 0.02, "panda_finger_joint2": 0.02}),
    ("kinova", "kinova_description/robots/kinova.urdf", None, {}),
]  # fmt: skip


#: The robots that are simulated too, by (URDF path, --tip): imported once a run by the
#: command line (:func:`_imported`), whose file both tests read.
SIMULATED = [
    ("panda_description/urdf/panda.urdf", "panda_link8"),
    ("kinova_description/robots/kinova.urdf", None),
]


def _imported(relative: str, tip: str | None) -> tuple[Path, Ran]:
    """``import-urdf`` of an example-robot-data robot, once a run: the spec file it wrote
    and what it said (a second import of the same robot would make the same file)."""
    assert ROBOTS is not None
    robots = ROBOTS

    def build(folder: Path) -> None:
        tip_args = ("--tip", tip) if tip else ()
        run = run_main(
            "import-urdf", str(robots / relative), "--out", "arm.toml", *tip_args, cwd=folder
        )
        said = [run.returncode, run.stdout, run.stderr]
        (folder / "ran.json").write_text(json.dumps(said), encoding="utf-8")

    key = "urdf_door_" + Path(relative).stem + (f"_{tip}" if tip else "")
    folder = shared(key, build)
    code, out, err = json.loads((folder / "ran.json").read_text(encoding="utf-8"))
    return folder / "arm.toml", Ran(code, out, err)


@needs_robots
@pytest.mark.parametrize(
    ("relative", "tip", "held"), [r[1:] for r in REAL_ROBOTS], ids=[r[0] for r in REAL_ROBOTS]
)
def test_real_robots_equal_pinocchio(
    relative: str, tip: str | None, held: dict[str, float]
) -> None:
    """M and the bias forces at random states, to 1e-9 relative (joints beyond the tip
    locked in Pinocchio's reduced model where the import holds them)."""
    assert ROBOTS is not None
    path = ROBOTS / relative
    notes: list[str] = []
    if (relative, tip) in SIMULATED:
        # The file the command wrote, which the simulation test reads too: one import.
        written, run = _imported(relative, tip)
        assert run.returncode == 0 and run.stderr == "", run.stderr
        spec = tomllib.loads(written.read_text(encoding="utf-8"))
        notes = [
            n.removeprefix("note: ") for n in run.stdout.splitlines() if n.startswith("note: ")
        ]
    else:
        spec = spec_from_urdf(path, tip=tip, notes=notes)
    if held:
        listed = ", ".join(f"{k} = {v:g}" for k, v in held.items())
        assert f"held fixed beyond or beside the tip {tip!r}: {listed}" in notes
    worst = _pinocchio_check(path, spec, held, 4, 11)
    assert worst < 1e-9, worst


def _simulate(spec: Path) -> None:
    """The closed loop of the imported spec passes its certificate at 101 output times.

    Run in this process, as ``simulate SPEC --points 101`` runs it (its exit 0 is
    ``passed``; the command's files and figures are test_simulate's subject, not this).
    """
    from tvopt_codegen.derivation import derive
    from tvopt_codegen.lowering.ir import lower
    from tvopt_codegen.simulation import (
        format_certificate,
        load_controller,
        resolve_options,
        simulate,
    )
    from tvopt_codegen.spec import load_spec

    d = derive(load_spec(spec))
    result = simulate(d, load_controller(lower(d)), resolve_options(d, points=101))
    assert result.passed, format_certificate(d, result)


@pytest.mark.slow
@needs_robots
@pytest.mark.parametrize(("relative", "tip"), SIMULATED, ids=["panda", "kinova"])
def test_panda_and_kinova_simulate_with_a_passing_certificate(
    relative: str, tip: str | None, tmp_path: Path
) -> None:
    written, run = _imported(relative, tip)
    assert run.returncode == 0 and run.stderr == "", run.stderr
    if tip:
        # At the Panda's middle pose its shoulder and upper-arm roll axes are aligned:
        # the import lets the tip replace shoulder, shoulder pitch and elbow instead.
        assert "replacing panda_joint1, panda_joint2, panda_joint4 as outputs" in run.stdout
    shutil.copy(written, tmp_path / "arm.toml")
    _simulate(tmp_path / "arm.toml")


# ------------------------------------------------------------------ the default objective


def _scara(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> list[str]:
    out = tmp_path / "scara.toml"
    assert main(["import-urdf", str(SCARA), "--tip", "tool", "--out", str(out)]) == 0
    captured = capsys.readouterr()
    assert captured.err == "", captured.err
    return [line for line in captured.out.splitlines() if line.startswith("note: ")]


def test_a_bent_scara_gets_a_circle_clear_of_its_elbow_singularity(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The 0.1 m horizontal circle would stretch the elbow past straight; the import says
    so and picks a circle that stays clear."""
    notes = _scara(tmp_path, capsys)
    assert len(notes) == 1, notes
    assert "would bring the tip Jacobian's inverse condition number to 0 " in notes[0]
    assert "the tip follows a 0.1 m circle in the y-z plane about the start" in notes[0]
    margin = float(notes[0].split("(margin ")[1].split(",")[0])
    assert 0.05 <= margin < 0.2, notes[0]
    text = (tmp_path / "scara.toml").read_text(encoding="utf-8")
    assert 'ox = "0.559012"' in text and 'oy = "0.215207 + 0.1*cos(0.5*t)"' in text


@pytest.mark.slow
def test_the_bent_scara_simulates_with_a_passing_certificate(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Imported with the default objective (the import's own choice of circle)."""
    _scara(tmp_path, capsys)
    _simulate(tmp_path / "scara.toml")


def test_a_safe_default_keeps_its_circle_and_prints_its_margin(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "ur5.toml"
    initial = "shoulder_lift=-1.2,elbow=1.6,wrist_1=-1.97,wrist_2=-1.57"
    ur5 = ROOT / "tests" / "robots" / "ur5_like.urdf"
    assert main(["import-urdf", str(ur5), "--out", str(out), "--tip", "tool0",
                 "--initial", initial]) == 0  # fmt: skip
    printed = capsys.readouterr().out
    assert (
        "note: the default objective, the tip's 0.1 m circle in the x-y plane about the "
        "start, keeps the tip Jacobian's inverse condition number >= 0.288" in printed
    ), printed


def test_a_stretched_start_says_no_circle_is_safe(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The SCARA stretched straight: every circle about it leaves the reachable set."""
    out = tmp_path / "scara.toml"
    code = main(["import-urdf", str(SCARA), "--out", str(out), "--tip", "tool",
                 "--initial", "elbow=0"])  # fmt: skip
    assert code == 0
    notes = [n for n in capsys.readouterr().out.splitlines() if n.startswith("note: ")]
    assert len(notes) == 1 and notes[0].startswith(
        "note: no tip circle of 0.1, 0.05 or 0.02 m about the start keeps clear of a singularity"
    ), notes


def _random_arm(seed: int) -> str:
    """Five random joints in a chain (random axes, placements, rotated inertias), the last
    two beyond link ``l3``, the fifth mimicking the fourth."""
    rng = np.random.default_rng(seed)
    parts = [_link("base")]
    for i in range(5):
        matrix, _ = np.linalg.qr(rng.normal(size=(3, 3)))
        a, b = rng.uniform(0.005, 0.05, 2)
        c = rng.uniform(abs(a - b) + 1e-3, a + b)
        tensor = matrix @ np.diag([a, b, c]) @ matrix.T
        inertia = " ".join(
            f'{k}="{tensor[i_, j_]:.10f}"'
            for k, (i_, j_) in zip(
                ("ixx", "ixy", "ixz", "iyy", "iyz", "izz"),
                ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)),
                strict=True,
            )
        )
        com = " ".join(f"{x:.4f}" for x in rng.uniform(-0.1, 0.1, 3))
        rpy = " ".join(f"{x:.4f}" for x in rng.uniform(-1, 1, 3))
        parts.append(
            f'<link name="l{i}"><inertial><origin xyz="{com}" rpy="{rpy}"/>'
            f'<mass value="{rng.uniform(0.3, 3):.4f}"/><inertia {inertia}/></inertial></link>'
        )
        kind = ("revolute", "continuous", "prismatic", "revolute", "revolute")[i]
        axis = " ".join(f"{x:.5f}" for x in rng.normal(size=3))
        xyz = " ".join(f"{x:.4f}" for x in rng.uniform(-0.3, 0.3, 3))
        placement = " ".join(f"{x:.4f}" for x in rng.uniform(-1.5, 1.5, 3))
        limit = '<limit lower="-0.7" upper="1.1" effort="10" velocity="1"/>'
        mimic = '<mimic joint="j3" multiplier="-0.8" offset="0.05"/>' if i == 4 else ""
        parts.append(
            f'<joint name="j{i}" type="{kind}"><parent link="{"base" if i == 0 else f"l{i - 1}"}"/>'
            f'<child link="l{i}"/><origin xyz="{xyz}" rpy="{placement}"/><axis xyz="{axis}"/>'
            f"{limit}{mimic}</joint>"
        )
    return _robot(*parts)


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_random_arms_with_held_joints_equal_pinocchio(seed: int, tmp_path: Path) -> None:
    """Joints beyond the tip held (one mimicking the other, at multiplier * leader +
    offset), M and the bias forces against Pinocchio's reduced model to 1e-9."""
    path = tmp_path / "arm.urdf"
    path.write_text(_random_arm(seed), encoding="utf-8")
    notes: list[str] = []
    spec = spec_from_urdf(path, tip="l2", notes=notes, gravity=(0.0, 0.0, -9.81))
    held = {"j3": 0.2, "j4": -0.8 * 0.2 + 0.05}
    assert spec["system"]["coordinates"] == ["j0", "j1", "j2"]
    assert notes[0] == "held fixed beyond or beside the tip 'l2': j3 = 0.2, j4 = -0.11", notes
    worst = _pinocchio_check(path, spec, held, 6, seed)
    assert worst < 1e-9, worst


def test_initial_for_a_held_joint_is_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "real.urdf"
    path.write_text(REAL, encoding="utf-8")
    code, err = _refused(path, tmp_path, capsys, "--tip", "flange", "--initial", "finger_left=0")
    assert code == EXIT_BAD_SPEC
    assert "--initial: 'finger_left' is held fixed beyond or beside the tip" in err, err
