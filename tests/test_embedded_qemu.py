"""The controller on ARM, under QEMU (issue 50 item 2).

Five bundled examples (PVTOL and the two arms, one in mass-matrix form, among them) run
the same closed loop (``tests/embedded/loop.c``: the controller stepped at 100 Hz, the
plant integrated in double by RK4 at 400 Hz, 2 s) on the x86-64 host, on arm64 and
armhf Linux (``qemu-aarch64``, ``qemu-arm``) and on two bare-metal boards: a Cortex-M7
in double (``qemu-system-arm -M mps2-an500``) and a Cortex-M4F in single precision
(``mps2-an386``). Every number the loop prints is a double's bits.

- Linux double equals the host bit for bit. Everything is compiled with
  ``-ffp-contract=off``, so the only difference left is glibc's libm, which is the same
  source on every architecture but built per FPU: on an x86-64 CPU with FMA, glibc picks
  its FMA-compiled ``sin``/``cos`` (arm64's libm fuses as well, and matches them), and
  armhf's VFPv3 has no fused multiply-add, so armhf matches the host with those variants
  turned off (``GLIBC_TUNABLES=glibc.cpu.hwcaps=-FMA,-AVX2``). Measured: without the
  tunable, armhf differs from the host in the last bits on planar_arm3 and flexible_joint.
- Bare metal's math library is newlib's: the M7's double loop differs from the host's
  by at most the bound per example below (measured, with a margin of about 10), and
  never less than a few ulps of the quantity's size (:data:`ULPS`).
- The M4F's single-precision controller against the same double plant tracks the host's
  double loop within the tolerance per example below (measured, margin about 10).
"""

from __future__ import annotations

import os
import platform
import shutil
from pathlib import Path

import numpy as np
import pytest

from tests.conftest import shared, skip_summary
from tests.embedded import harness
from tests.embedded.harness import (
    TARGETS,
    Loop,
    Trace,
    build_loop,
    parse,
    plant_states,
    run,
    skip_reason,
)
from tests.test_strict_c import generated, host_object, m4f_object

#: Each QEMU test compiles and runs closed loops (1-3 s; the module's total is ~25 s on
#: one core): slow, by hand, until tests/durations.json records them.
slow = pytest.mark.slow

#: 2 s of closed loop at 100 Hz, the plant's RK4 at 400 Hz.
LOOP = Loop(rate=100, steps=200, substeps=4, every=10)

#: glibc on x86-64 without its FMA-compiled math functions: the libm armhf's rounds as.
NO_FMA = {"GLIBC_TUNABLES": "glibc.cpu.hwcaps=-FMA,-AVX2"}

#: The Cortex-M7's double loop (newlib's libm) against the host's: the largest
#: difference of the plant state and of the input over the records, bounded at about 10
#: times what was measured (2026-12-05, QEMU 7.2, arm-none-eabi-gcc 12.2, newlib 4.3, the
#: C of the SymEngine engine): pvtol 0 and 1.8e-16, planar_arm3 1.6e-15 and 6.8e-14,
#: arm_on_line 1.1e-16 and 3.6e-15, unicycle_switch 2.2e-16 and 0, flexible_joint
#: 1.4e-17 and 1.1e-16 (on SymPy's C: pvtol 0 and 3.5e-18, planar_arm3 2.4e-15 and
#: 3.6e-14, arm_on_line 6.9e-17 and 5.3e-15, unicycle_switch 0 and 1.3e-16,
#: flexible_joint 1.4e-17 and 2.2e-16). At most a few ulps either way (see ULPS).
BARE_DOUBLE = {
    "pvtol": (1e-16, 2e-15),
    "planar_arm3": (3e-14, 4e-13),
    "arm_on_line": (1e-15, 6e-14),
    "unicycle_switch": (2e-15, 2e-15),
    "flexible_joint": (2e-16, 3e-15),
}

#: No M7 bound is below this many units in the last place of the quantity's largest
#: magnitude over the records (the states' 0.5-5, the inputs' 1.5-30). Ten times a
#: measured 0, or a thousandth of an ulp, would demand bit equality, which newlib's libm
#: does not promise: a last-bit difference at one record is what a change of the
#: generated C's rounding order gives (the engine's CSE form changed it: pvtol's input
#: 1.8e-16 at a scale of 10.4, unicycle_switch's state 2.2e-16, one ulp of 1.27).
ULPS = 4


def _m7_bound(table: float, host: np.ndarray) -> float:
    """``table``, or :data:`ULPS` ulps of the largest magnitude in ``host`` if more."""
    return max(table, ULPS * float(np.spacing(np.max(np.abs(host)))))


#: The Cortex-M4F's single-precision loop against the host's double one: the largest
#: difference of the plant state and of the input, at about 10 times what was measured:
#: pvtol 1.6e-6 and 2.5e-6, planar_arm3 9.3e-7 and 1.9e-5, arm_on_line 1.2e-7 and
#: 4.7e-6, unicycle_switch 1.6e-7 and 5.5e-7, flexible_joint 2.2e-8 and 2.5e-7 (state
#: scales 0.5-5, inputs 1.5-30).
SINGLE = {
    "pvtol": (2e-5, 3e-5),
    "planar_arm3": (1e-5, 2e-4),
    "arm_on_line": (2e-6, 5e-5),
    "unicycle_switch": (2e-6, 6e-6),
    "flexible_joint": (3e-7, 3e-6),
}
EXAMPLES = tuple(BARE_DOUBLE)


def _need(*targets: str) -> None:
    reason = skip_reason(*targets)
    if reason:
        pytest.skip(reason)


def _c(example: str, precision: str) -> Path:
    """The example's generated C in ``precision``, made once per run.

    The folder ``test_strict_c`` and ``test_precision`` check and load (rendered from the
    run's cached kernels): the harness compiles exactly the C those tests hold to the
    strict profile, and no example is derived again for it.
    """
    return generated(example, precision)


def _trace(example: str, target: str, precision: str, fma: bool = True) -> Trace:
    """The closed loop of ``example`` on ``target``, built and run once per run.

    ``fma=False`` is the host's run with glibc's FMA variants off (:data:`NO_FMA`).
    """

    def build(folder: Path) -> None:
        # The M4F's objects and the host's are test_strict_c's (the same C, flags and
        # compiler, built once per run for its stack and strict checks); every target's
        # start-up objects are built once.
        objects: dict[str, Path] = {}
        if target == "m4f":
            objects = {"double": m4f_object(example, "double")}
            objects["controller"] = m4f_object(example, precision)
        elif target == "host" and precision == "double":
            strict = host_object(example, "double")
            if strict is not None:  # else compiled here, the strict test saying why not there
                objects = {"double": strict}
        binary = build_loop(
            TARGETS[target],
            example,
            _c(example, precision),
            _c(example, "double"),
            precision,
            folder,
            LOOP,
            objects=objects,
            support=_support(target),
        )
        (folder / "out").write_text(run(TARGETS[target], binary), encoding="utf-8")
        if target == "host":
            (folder / "out-no-fma").write_text(
                run(TARGETS[target], binary, env=NO_FMA), encoding="utf-8"
            )

    folder = shared(f"embedded-run-{example}-{target}-{precision}", build)
    n_x = plant_states(_c(example, "double") / f"{example}.h", example)
    return parse((folder / ("out" if fma else "out-no-fma")).read_text(encoding="utf-8"), n_x)


def _support(target: str) -> list[Path]:
    """The start-up objects of ``target`` (:func:`harness.support_objects`), once per run."""

    def build(folder: Path) -> None:
        harness.support_objects(TARGETS[target], folder)

    folder = shared(f"embedded-support-{target}", build)
    return sorted(folder.glob("*.o"))


def _bits(trace: Trace) -> np.ndarray:
    return np.concatenate([trace.t, trace.x.ravel(), trace.u.ravel()]).view(np.uint64)


def _host_has_fma() -> bool:
    try:
        text = Path("/proc/cpuinfo").read_text(encoding="utf-8")
    except OSError:
        return False
    return any(line.startswith("flags") and " fma" in line for line in text.splitlines())


def _x86_64_host() -> None:
    if platform.machine() != "x86_64" or os.name != "posix":
        pytest.skip("the reference loop is an x86-64 Linux build (by design)")


def test_a_missing_toolchain_skips_with_the_line_that_installs_it(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setattr(shutil, "which", lambda p: None if "qemu" in p else "/usr/bin/x")
    reason = skip_reason("host", "m4f")
    assert reason is not None and "qemu-system-arm missing" in reason
    assert "gcc" not in reason.split("(")[1].split(")")[0]
    assert skip_summary([reason]).endswith("(as root, `.ci/run` does it)`")
    assert all(package in skip_summary([reason]) for package in harness.APT_PACKAGES)


def test_the_loop_output_is_read_to_the_bit_and_a_failed_step_is_an_error() -> None:
    values = [0.1, -0.0, 1e-300, 2.5, float.fromhex("0x1.fffffffffffffp-1")]
    text = "s 7" + "".join(f" {np.float64(v).view(np.uint64):016x}" for v in values) + "\nend\n"
    trace = parse(text, 2)
    assert trace.steps.tolist() == [7] and trace.t.tolist() == [0.1]
    assert trace.x.tolist() == [[-0.0, 1e-300]] and trace.u.tolist() == [values[3:]]
    assert str(trace.x[0, 0]) == "-0.0"
    with pytest.raises(RuntimeError, match="fail 3 2"):
        parse("fail 3 2\nend\n", 2)
    with pytest.raises(RuntimeError, match="did not finish"):
        parse(text.replace("end\n", ""), 2)


@slow
@pytest.mark.parametrize("example", EXAMPLES)
def test_arm64_linux_double_equals_host(example: str) -> None:
    _x86_64_host()
    _need("host", "arm64")
    if not _host_has_fma():
        pytest.skip("this x86-64 CPU has no FMA: its libm rounds as armhf's (by design)")
    host, arm64 = _trace(example, "host", "double"), _trace(example, "arm64", "double")
    assert len(host.steps) == LOOP.steps // LOOP.every + 1
    np.testing.assert_array_equal(_bits(arm64), _bits(host))


@slow
@pytest.mark.parametrize("example", EXAMPLES)
def test_armhf_linux_double_equals_host(example: str) -> None:
    _x86_64_host()
    _need("host", "armhf")
    host = _trace(example, "host", "double", fma=False)
    np.testing.assert_array_equal(_bits(_trace(example, "armhf", "double")), _bits(host))


@slow
@pytest.mark.parametrize("example", EXAMPLES)
def test_cortex_m7_double_within_bound(example: str) -> None:
    _x86_64_host()
    _need("host", "m7")
    host, m7 = _trace(example, "host", "double"), _trace(example, "m7", "double")
    x_bound, u_bound = BARE_DOUBLE[example]
    np.testing.assert_array_equal(m7.t, host.t)
    assert np.max(np.abs(m7.x - host.x)) <= _m7_bound(x_bound, host.x)
    assert np.max(np.abs(m7.u - host.u)) <= _m7_bound(u_bound, host.u)


@slow
@pytest.mark.parametrize("example", EXAMPLES)
def test_cortex_m4f_single_tracks_double(example: str) -> None:
    _x86_64_host()
    _need("host", "m4f")
    host, m4f = _trace(example, "host", "double"), _trace(example, "m4f", "single")
    x_tol, u_tol = SINGLE[example]
    assert np.max(np.abs(m4f.x - host.x)) <= x_tol
    assert np.max(np.abs(m4f.u - host.u)) <= u_tol
    # Not vacuous: single precision does differ from double.
    assert np.max(np.abs(m4f.u - host.u)) > 0.0
