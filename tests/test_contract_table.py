"""The contract as data: every artifact takes its statuses and functions from one table.

A status added to :class:`tvopt_codegen.contract.Status` must appear, with its exception
and its message, in the Python module, the C header, the C module and its Python
wrapper, the FMU and the sweep's outcomes, without any other edit.
"""

from __future__ import annotations

import ctypes
import enum
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from tests.conftest import ROOT, import_file, kernels, module
from tvopt_codegen import contract, sweep
from tvopt_codegen.cli import main
from tvopt_codegen.renderer.rendering import contract_context, render
from tvopt_codegen.runs.fmu import fmu_sources

SPEC = "unicycle_switch"
CC = shutil.which("cc") or shutil.which("gcc")
#: The added status's value: one past the contract's last.
FAULT = max(contract.Status) + 1


def _wider_status() -> type[enum.IntEnum]:
    """The contract's statuses and one more, built the way :class:`Status` is."""
    meta = type(contract.Status)
    namespace = meta.__prepare__("Status", (enum.IntEnum,))
    namespace["__new__"] = contract.Status._new_member_  # type: ignore[attr-defined]
    for attribute in ("of", "label", "message"):
        namespace[attribute] = contract.Status.__dict__[attribute]
    for status in contract.Status:
        namespace[status.name] = (
            int(status),
            status.kind,
            status.exception,
            status.doc,
            status.text,
            status.explain,
        )
    namespace["TEST_FAULT"] = (
        FAULT,
        "error",
        "TestFaultError",
        "A fault that only this test adds.",
        "the test fault struck",
        "nothing is wrong",
    )
    return meta("Status", (enum.IntEnum,), namespace)


def _status_messages(source_dir: Path, name: str, tmp_path: Path) -> ctypes.CDLL:
    library = tmp_path / f"lib{name}.so"
    subprocess.run(
        [
            CC,
            "-std=c99",
            "-O0",
            "-shared",
            "-fPIC",
            "-o",
            str(library),
            str(source_dir / f"{name}.c"),
        ],
        check=True,
        capture_output=True,
    )
    lib = ctypes.CDLL(str(library))
    getattr(lib, f"{name}_status_message").restype = ctypes.c_char_p
    return lib


def test_a_status_added_to_the_table_reaches_every_artifact(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    monkeypatch.setattr(contract, "Status", _wider_status())
    lowered = kernels(SPEC)

    # The Python module: a constant, an exception class, a message.
    (text,) = render(lowered, "python").values()
    assert f"STATUS_TEST_FAULT = {FAULT}" in text
    path = tmp_path / f"{SPEC}.py"
    path.write_text(text, encoding="utf-8")
    generated = import_file(path, "_tvopt_contract_table_python")
    error = generated._error(generated.STATUS_TEST_FAULT, 3)
    assert isinstance(error, generated.TestFaultError)
    assert isinstance(error, generated.ControllerError) and error.status == FAULT
    assert str(error) == "the test fault struck (column 3): nothing is wrong"

    # The C header, the C module's messages and its Python wrapper.
    c_files = render(lowered, "c")
    assert f"#define UNICYCLE_SWITCH_TEST_FAULT {FAULT}" in c_files[f"{SPEC}.h"]
    assert "case UNICYCLE_SWITCH_TEST_FAULT:" in c_files[f"{SPEC}.c"]
    wrapper = c_files[f"{SPEC}_c.py"]
    assert "class TestFaultError(ControllerError):" in wrapper
    assert "STATUS_TEST_FAULT: (TestFaultError, 'the test fault struck'" in wrapper

    # The FMU logs what the C module says of a status.
    for fmi in (2, 3):
        sources = fmu_sources(lowered, fmi)
        assert "case UNICYCLE_SWITCH_TEST_FAULT:" in sources[f"sources/{SPEC}.c"]
        assert f"return {SPEC}_status_message(status);" in sources[f"sources/{SPEC}_fmi{fmi}.c"]

    # The sweep records a sample that ends so under the status's own name.
    assert sweep.outcome_of(FAULT).label == "test_fault"
    assert sweep.outcome_of(16) is sweep.LoopOutcome.DIVERGED

    if CC is not None:
        for name, source in c_files.items():
            (tmp_path / name).write_text(source, encoding="utf-8")
        lib = _status_messages(tmp_path, SPEC, tmp_path)
        message = getattr(lib, f"{SPEC}_status_message")
        assert message(FAULT) == b"the test fault struck: nothing is wrong"


@pytest.mark.skipif(CC is None, reason="no C compiler")
@pytest.mark.parametrize("spec", [SPEC, "arm_on_line"])
def test_the_c_messages_are_the_contracts(spec: str, tmp_path: Path) -> None:
    lowered = kernels(spec)
    for name, source in render(lowered, "c").items():
        (tmp_path / name).write_text(source, encoding="utf-8")
    message = getattr(_status_messages(tmp_path, spec, tmp_path), f"{spec}_status_message")
    details = contract_context(lowered)["status_details"]
    for status in contract.statuses():
        expected = status.message(detail=details.get(status.name, ""))
        assert message(int(status)).decode() == expected
    assert message(99) == b"unknown status"


def test_every_status_has_one_exception_and_message() -> None:
    errors = [s for s in contract.statuses() if s.kind == "error"]
    assert len({s.exception for s in errors}) == len(errors)
    assert all(s.exception.endswith("Error") and s.text and s.doc for s in errors)
    assert [int(s) for s in contract.statuses()] == sorted({int(s) for s in contract.Status})
    assert contract.Status.of(6) is contract.Status.DEPENDENT_CONSTRAINTS
    with pytest.raises(ValueError, match="not a status"):
        contract.Status.of(42)
    # The sweep's own outcomes never collide with the law's.
    assert not {int(o) for o in sweep.LoopOutcome} & {int(s) for s in contract.Status}


def test_the_function_table_names_every_public_function() -> None:
    module = render(kernels(SPEC), "python")[f"{SPEC}.py"]
    header = render(kernels(SPEC), "c")[f"{SPEC}.h"]
    for function in contract.FUNCTIONS:
        assert f"\ndef {function.name}(t, " in module
        assert f"int {SPEC}_{function.name}(double t, " in header
        assert (f"int {SPEC}_{function.name}_batch(" in header) == function.batch


def test_a_sweep_records_dependent_constraints_and_finishes(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """arm_on_line with its line scaled by a parameter: at kc = 0 the constraint's gradient
    vanishes, the KKT matrix is singular, and every sample ends DEPENDENT_CONSTRAINTS."""
    pytest.importorskip("distributed")
    text = (ROOT / "tvopt_codegen" / "examples" / "arm_on_line.toml").read_text(encoding="utf-8")
    text = text.replace(
        'on_line = "cos(0.1*t)*px + sin(0.1*t)*py == 1"',
        'on_line = "kc*(cos(0.1*t)*px + sin(0.1*t)*py - 1) == 0"',
    ).replace("g0 = 9.81   # m/s^2", "g0 = 9.81   # m/s^2\nkc = 1.0")
    assert "kc*(" in text and "kc = 1.0" in text
    spec = tmp_path / "arm_kc.toml"
    spec.write_text(text, encoding="utf-8")
    out = tmp_path / "sweep"
    code = main(
        [
            "sweep",
            str(spec),
            "--samples",
            "3",
            "--param",
            "kc=0",
            "--workers",
            "1",
            "--t-final",
            "1",
            "--out",
            str(out),
        ]
    )
    assert code == 0
    summary = (out / "summary.md").read_text()
    assert "| dependent_constraints | 3 |" in summary
    import pyarrow.parquet as pq

    rows = pq.read_table(out / "summary.parquet").to_pylist()
    assert [row["status"] for row in rows] == ["dependent_constraints"] * 3


@pytest.mark.skipif(CC is None, reason="no C compiler")
def test_every_status_of_the_c_module_raises_its_exception(
    tmp_path_factory: pytest.TempPathFactory,
) -> None:
    """The C wrapper once knew four statuses: a DECREASING_TIME that reached it (one
    Controller stepped from two threads) raised KeyError: 5."""
    from tests.test_c_backend import c_module

    c = c_module(SPEC, tmp_path_factory)
    x = np.asarray(c.DEFAULT_STATE, dtype=float)[:, None]
    p = np.zeros(max(len(c.PARAMETERS), 1))
    for status in contract.statuses():
        if status.kind != "error" or status.name == "NONFINITE_INPUT":
            continue
        with pytest.raises(c.ControllerError) as raised:
            c._raise(int(status), 0, "rhs", 0.0, x, p)
        assert type(raised.value).__name__ == status.exception
        assert raised.value.status == int(status)


@pytest.mark.parametrize("backend", ["python", "c"])
def test_a_controller_stepped_back_raises_decreasing_time(
    backend: str, tmp_path_factory: pytest.TempPathFactory
) -> None:
    if backend == "c":
        if CC is None:
            pytest.skip("no C compiler")
        from tests.test_c_backend import c_module

        generated = c_module(SPEC, tmp_path_factory)
    else:
        generated = module(SPEC)
    plant = list(generated.DEFAULT_STATE[: len(generated.PLANT_STATE_NAMES)])
    controller = generated.Controller(plant, t0=1.0)
    with pytest.raises(generated.DecreasingTimeError, match="time must not decrease") as raised:
        controller.step(0.5, plant)
    assert isinstance(raised.value, ValueError) and isinstance(raised.value, ArithmeticError)
    assert raised.value.status == int(contract.Status.DECREASING_TIME)
