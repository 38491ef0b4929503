"""The co-simulation FMU: valid for FMPy, and the same inputs as Controller.step."""

from __future__ import annotations

import functools
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from tvopt_codegen import symbolic as sx
from tvopt_codegen.cli import main
from tvopt_codegen.errors import EXIT_BAD_SPEC, MissingExtraError
from tvopt_codegen.runs.fmu import build_fmu, fmi_headers, fmu_sources

from .conftest import SPECS, kernels, module
from .test_c_backend import COMPILERS, STRICT

ROBUST = str(SPECS / "robust_pvtol.toml")

fmpy = pytest.importorskip("fmpy")
from fmpy.validation import validate_fmu  # noqa: E402


def _fmu(spec: str, fmi: int, folder: Path) -> Path:
    """``spec``'s FMU for FMI ``fmi``, written in ``folder`` (a file of the test's own)."""
    path = folder / f"{Path(spec).stem}_fmi{fmi}.fmu"
    path.write_bytes(_archive(spec, fmi, sx.ENGINE))
    return path


@functools.cache
def _archive(spec: str, fmi: int, engine: str) -> bytes:
    # Built (and its C compiled) once per engine: the archive is deterministic for given
    # sources and compiler (test_the_archive_is_deterministic_and_holds_sources_and_a_binary
    # builds one twice), so the tests that simulate the same FMU share its bytes.
    return build_fmu(kernels(spec), fmi)


def _measured(spec: str, horizon: float, h: float) -> tuple[np.ndarray, np.ndarray]:
    """Plant states along the continuous closed loop, at the communication points.

    Integrated once per engine (both FMI versions are fed the same loop); read-only.
    """
    return _integrated(spec, horizon, h, sx.ENGINE)


@functools.cache
def _integrated(spec: str, horizon: float, h: float, engine: str) -> tuple[np.ndarray, np.ndarray]:
    mod = module(spec)
    times = np.round(np.arange(0.0, horizon + h / 2, h), 12)
    run = solve_ivp(
        mod.rhs, (0.0, horizon), np.array(mod.DEFAULT_STATE), dense_output=True, rtol=1e-10,
        atol=1e-12,
    )  # fmt: skip
    states = run.sol(times)[: len(mod.PLANT_STATE_NAMES)]
    times.setflags(write=False)
    states.setflags(write=False)
    return times, states


@pytest.mark.parametrize("fmi", [2, 3])
# arm_on_line: the multipliers of its equality constraint are controller states too.
# robust_pvtol: limits, integral action and an observer; its saturation flags are outputs.
# planar_arm3: M factored at run time inside the FMU's controller.
@pytest.mark.parametrize("spec", ["pvtol", "unicycle_switch", "arm_on_line", ROBUST, "planar_arm3"])
def test_fmpy_validates_and_cosimulates_it_like_controller_step(
    spec: str, fmi: int, tmp_path: Path
) -> None:
    mod = module(spec)
    path = _fmu(spec, fmi, tmp_path)
    assert validate_fmu(str(path)) == []
    description = fmpy.read_model_description(str(path))
    assert description.fmiVersion == f"{fmi}.0"
    causality = {v.name: v.causality for v in description.modelVariables}
    assert all(causality[n] == "input" for n in mod.PLANT_STATE_NAMES)
    assert all(causality[n] == "output" for n in mod.INPUT_NAMES)
    assert all(causality[n] == "parameter" for n in mod.PARAMETERS)
    assert all(causality[f"controller.{n}"] == "local" for n in mod.CONTROLLER_STATE_NAMES)
    # No direct feedthrough: the outputs change only in doStep, and say so (an absent
    # attribute would mean a dependence on every input; FMPy reads both as an empty list).
    with zipfile.ZipFile(path) as archive:
        structure = archive.read("modelDescription.xml").decode().split("<ModelStructure>")[1]
    declared = (
        structure.split("<InitialUnknown")[0] if fmi == 3 else structure.split("</Outputs>")[0]
    )
    count = len(mod.INPUT_NAMES) * (2 if hasattr(mod, "INPUT_LOW") else 1)
    assert declared.count('dependencies=""') == count == len(description.outputs)
    h = 0.01
    times, states = _measured(spec, 1.5, h)
    table = np.array(
        [(t, *states[:, k]) for k, t in enumerate(times)],
        dtype=[("time", float)] + [(n, float) for n in mod.PLANT_STATE_NAMES],
    )
    names = [*mod.INPUT_NAMES, *(f"controller.{n}" for n in mod.CONTROLLER_STATE_NAMES)]
    limited = hasattr(mod, "INPUT_LOW")
    if limited:
        assert all(causality[f"saturated.{n}"] == "output" for n in mod.INPUT_NAMES)
        names += [f"saturated.{n}" for n in mod.INPUT_NAMES]
    result = fmpy.simulate_fmu(
        str(path),
        start_time=0.0,
        stop_time=float(times[-1]),
        output_interval=h,
        input=table,
        output=names,
        fmi_type="CoSimulation",
    )

    # At time t_{k+1} the FMU shows the input its doStep(t_k, h) computed from x(t_k);
    # at 0, the input of the initialization.
    def row(controller: object, u: np.ndarray) -> np.ndarray:
        flags = [controller.saturated.astype(float)] if limited else []  # type: ignore[attr-defined]
        return np.concatenate([u, controller.state, *flags])  # type: ignore[attr-defined]

    controller = mod.Controller(states[:, 0])
    expected = [row(controller, controller.u)]
    for k in range(len(times) - 1):
        u = controller.step(float(times[k]), states[:, k])
        expected.append(row(controller, u))
    got = np.array([[row[n] for n in names] for row in result])
    assert got.shape == (len(times), len(names))
    np.testing.assert_allclose(got, np.array(expected), rtol=1e-10, atol=1e-10)


def test_parameters_are_tunable_in_the_fmu(tmp_path: Path) -> None:
    mod = module("pvtol")
    path = _fmu("pvtol", 2, tmp_path)
    times, states = _measured("pvtol", 0.2, 0.05)
    table = np.array(
        [(t, *states[:, k]) for k, t in enumerate(times)],
        dtype=[("time", float)] + [(n, float) for n in mod.PLANT_STATE_NAMES],
    )
    result = fmpy.simulate_fmu(
        str(path),
        stop_time=float(times[-1]),
        output_interval=0.05,
        input=table,
        start_values={"g": 9.0},
        output=list(mod.INPUT_NAMES),
    )
    controller = mod.Controller(states[:, 0], params={"g": 9.0})
    np.testing.assert_allclose([result[0][n] for n in mod.INPUT_NAMES], controller.u, rtol=1e-12)


def test_a_failing_step_is_an_fmi_error_with_the_reason(tmp_path: Path) -> None:
    path = _fmu("unicycle_switch", 2, tmp_path)
    messages: list[str] = []

    def logger(*args: object) -> None:
        messages.append(repr(args))

    with pytest.raises(Exception, match="fmi2ExitInitializationMode"):
        fmpy.simulate_fmu(
            str(path),
            stop_time=1.0,
            output_interval=0.5,
            start_values={"x1": float("nan")},
            logger=logger,
        )
    assert any("a plant state or a parameter is not finite" in m for m in messages), messages


def test_the_archive_is_deterministic_and_holds_sources_and_a_binary(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from tvopt_codegen.runs.fmu import _run_compiler as run_compiler  # noqa: PLC0415

    # Two compilations (each into an empty cache of its own), the same bytes; then the
    # library comes from the cache, with no compiler run, and the archive is the same.
    monkeypatch.setenv("TVOPT_CODEGEN_CACHE", str(tmp_path / "cache-1"))
    first = build_fmu(kernels("integrator"), 3)
    monkeypatch.setenv("TVOPT_CODEGEN_CACHE", str(tmp_path / "cache-2"))
    assert build_fmu(kernels("integrator"), 3) == first
    # The library and the controller's object it was linked from.
    kept = sorted((tmp_path / "cache-2").iterdir(), key=lambda p: p.suffix)
    assert [p.suffix for p in kept] == [".o", ".so"]
    compiled: list[list[str]] = []

    def no_compiler(*args: object) -> bytes:
        raise AssertionError("compiled again")

    def counted(command: list[str]) -> None:
        compiled.append(command)
        run_compiler(command)

    with monkeypatch.context() as patch:
        patch.setattr("tvopt_codegen.runs.fmu._compile", no_compiler)
        assert build_fmu(kernels("integrator"), 3) == first
        with pytest.raises(AssertionError, match="compiled again"):
            build_fmu(kernels("integrator"), 2)  # other sources: another library
    # FMI 2's library links FMI 3's controller object: one run of the compiler, on the
    # glue alone, and the archive is the one a cold cache makes.
    with monkeypatch.context() as patch:
        patch.setattr("tvopt_codegen.runs.fmu._run_compiler", counted)
        second = build_fmu(kernels("integrator"), 2)
    assert len(compiled) == 1 and not any(c.endswith("integrator.c") for c in compiled[0])
    assert [p.suffix for p in (tmp_path / "cache-2").iterdir()].count(".o") == 1
    monkeypatch.setenv("TVOPT_CODEGEN_CACHE", str(tmp_path / "cache-3"))
    assert build_fmu(kernels("integrator"), 2) == second
    path = tmp_path / "integrator.fmu"
    path.write_bytes(first)
    with zipfile.ZipFile(path) as archive:
        names = archive.namelist()
    assert names == sorted(names)
    assert "modelDescription.xml" in names
    assert {"sources/integrator.c", "sources/integrator.h", "sources/integrator_fmi3.c"} <= set(
        names
    )
    assert any(n.startswith("binaries/") and n.endswith("integrator.so") for n in names)


@pytest.mark.parametrize("compiler", COMPILERS)
@pytest.mark.parametrize("fmi", [2, 3])
@pytest.mark.parametrize("spec", ["two_unicycles_barrier", ROBUST])
def test_the_glue_compiles_under_strict_warnings(
    spec: str, fmi: int, compiler: str, tmp_path: Path
) -> None:
    name = Path(spec).stem
    for member, text in fmu_sources(kernels(spec), fmi).items():
        (tmp_path / Path(member).name).write_text(text)
    done = subprocess.run(
        [compiler, *STRICT, "-c", str(tmp_path / f"{name}_fmi{fmi}.c")]
        + ["-I", str(tmp_path), "-I", str(fmi_headers(fmi)), "-o", str(tmp_path / "glue.o")],
        capture_output=True,
        text=True,
        check=False,
    )
    assert done.returncode == 0, done.stderr


def test_the_command_exports_and_replaces_its_own_fmu(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "out"
    out.mkdir()
    assert main(["export", "pvtol", "--fmu", "--fmi", "3", "--out", str(out)]) == 0
    assert validate_fmu(str(out / "pvtol.fmu")) == []
    assert main(["export", "pvtol", "--fmu", "--out", str(out)]) == 0  # FMI 2 replaces it
    assert fmpy.read_model_description(str(out / "pvtol.fmu")).fmiVersion == "2.0"
    assert "wrote" in capsys.readouterr().out
    assert main(["export", "pvtol", "--out", str(out)]) == EXIT_BAD_SPEC
    assert "nothing to export: give --fmu" in capsys.readouterr().err


def test_without_headers_one_line_says_what_to_install(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("TVOPT_CODEGEN_FMI_HEADERS", "/nonexistent")
    with pytest.raises(MissingExtraError, match="has no fmi2Functions.h"):
        build_fmu(kernels("integrator"), 2)
    monkeypatch.delenv("TVOPT_CODEGEN_FMI_HEADERS")
    monkeypatch.setattr("importlib.util.find_spec", lambda name: None)
    with pytest.raises(MissingExtraError, match=r"pip install 'tvopt-codegen\[fmu\]'"):
        build_fmu(kernels("integrator"), 2)
    assert shutil.which("cc") or shutil.which("gcc")


@pytest.mark.parametrize("fmi", [2, 3])
def test_reference_jets_are_fmu_inputs(fmi: int, tmp_path: Path) -> None:
    from .test_references import exact_jets

    spec = "unicycle_switch_refs"
    mod = module(spec)
    path = _fmu(spec, fmi, tmp_path)
    assert validate_fmu(str(path)) == []
    q = mod.REFERENCE_ORDER
    jet_names = [f"reference.{n}.d{j}" for n in mod.REFERENCE_NAMES for j in range(q + 1)]
    causality = {v.name: v.causality for v in fmpy.read_model_description(str(path)).modelVariables}
    assert all(causality[n] == "input" for n in jet_names)
    h = 0.05
    times, states = _measured("unicycle_switch", 1.0, h)
    rows = [(t, *states[:, k], *exact_jets(spec, float(t)).ravel()) for k, t in enumerate(times)]
    table = np.array(
        rows, dtype=[("time", float)] + [(n, float) for n in (*mod.PLANT_STATE_NAMES, *jet_names)]
    )
    result = fmpy.simulate_fmu(
        str(path), stop_time=float(times[-1]), output_interval=h, input=table,
        output=list(mod.INPUT_NAMES),
    )  # fmt: skip
    controller = mod.Controller(states[:, 0], refs=exact_jets(spec, 0.0))
    expected = [controller.u]
    for k in range(len(times) - 1):
        t = float(times[k])
        expected.append(controller.step(t, states[:, k], refs=exact_jets(spec, t)))
    got = np.array([[row[n] for n in mod.INPUT_NAMES] for row in result])
    np.testing.assert_allclose(got, np.array(expected), rtol=1e-10, atol=1e-10)


#: Steps a master may not take, and then one it may: run in a process of its own, since
#: FMPy would load this FMU's library under the same name as another test's.
_STEPS = """
import sys
from fmpy import extract, read_model_description
from fmpy.fmi2 import FMU2Slave
from fmpy.fmi3 import FMU3Slave

path, fmi = sys.argv[1], int(sys.argv[2])
description = read_model_description(path)
kind = FMU2Slave if fmi == 2 else FMU3Slave
token = description.guid if fmi == 2 else description.instantiationToken
slave = kind(guid=token, unzipDirectory=extract(path),
             modelIdentifier=description.coSimulation.modelIdentifier, instanceName="c")
slave.instantiate()
if fmi == 2:
    slave.setupExperiment(startTime=0.0)
slave.enterInitializationMode()
slave.exitInitializationMode()
refused = 0
bad = ((0.0, 0.0), (0.0, -0.01), (0.0, float("nan")), (float("nan"), 0.01), (0.0, float("inf")))
for t, h in bad:
    try:
        slave.doStep(currentCommunicationPoint=t, communicationStepSize=h)
    except Exception:
        refused += 1
slave.doStep(currentCommunicationPoint=0.0, communicationStepSize=0.01)
slave.terminate()
slave.freeInstance()
print(refused)
"""


@pytest.mark.parametrize("fmi", [2, 3])
def test_do_step_refuses_a_step_that_does_not_move_time_forward(fmi: int, tmp_path: Path) -> None:
    path = _fmu("unicycle_switch", fmi, tmp_path)
    done = subprocess.run(
        [sys.executable, "-c", _STEPS, str(path), str(fmi)],
        capture_output=True,
        text=True,
        check=False,
    )
    assert done.returncode == 0, done.stderr
    lines = done.stdout.strip().splitlines()
    assert lines[-1] == "5"  # every bad step refused, the good one taken
    # FMPy prints what the FMU logged: the master's mistake, named.
    assert sum("step size positive and finite" in line for line in lines) == 5
