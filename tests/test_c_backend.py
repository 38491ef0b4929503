"""The C backend: strict compilation, agreement with the Python backend, sanitizers, cache."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path
from types import ModuleType

import numpy as np
import pytest
import sympy as sp

from tvopt_codegen.derivation import derive
from tvopt_codegen.emit import write_files
from tvopt_codegen.lowering.ir import lower
from tvopt_codegen.renderer.rendering import render
from tvopt_codegen.simulation import load_controller
from tvopt_codegen.spec import load_spec

from .conftest import (
    ALL_SPECS,
    ROOT,
    SPECS,
    derivation,
    import_file,
    kernels,
    module,
    run_main,
)
from .oracle import Oracle
from .test_generated import random_states

STRICT = ["-std=c99", "-Wall", "-Wextra", "-Werror", "-pedantic"]
COMPILERS = [cc for cc in ("gcc", "clang") if shutil.which(cc)]


def _write_c(spec: str, folder: Path) -> Path:
    write_files(render(kernels(spec), "c"), folder)
    return folder / f"{derivation(spec).spec.name}.c"


_IMPORTED: dict[str, ModuleType] = {}


def c_module(spec: str, tmp_path_factory: pytest.TempPathFactory) -> ModuleType:
    if spec not in _IMPORTED:
        folder = tmp_path_factory.mktemp("cmod")
        _write_c(spec, folder)
        name = derivation(spec).spec.name
        _IMPORTED[spec] = import_file(folder / f"{name}_c.py", f"_tvopt_c_{name}")
    return _IMPORTED[spec]


#: The specs tests/test_strict_c.py does not hold to its stricter profile (it takes every
#: bundled example, robust_pvtol and coupled3).
NOT_IN_STRICT_C = tuple(s for s in ALL_SPECS if s.endswith(("nonuniform.toml", "hovercraft.toml")))


@pytest.mark.parametrize("compiler", COMPILERS)
@pytest.mark.parametrize("spec", NOT_IN_STRICT_C)
def test_compiles_cleanly_under_strict_warnings(spec: str, compiler: str, tmp_path: Path) -> None:
    source = _write_c(spec, tmp_path)
    done = subprocess.run(
        [compiler, *STRICT, "-O2", "-c", str(source), "-o", str(tmp_path / "x.o")],
        capture_output=True,
        text=True,
        check=False,
    )
    assert done.returncode == 0, done.stderr
    assert done.stderr == ""


def test_refuses_fast_math(tmp_path: Path) -> None:
    source = _write_c("integrator", tmp_path)
    done = subprocess.run(
        ["gcc", "-std=c99", "-ffast-math", "-c", str(source), "-o", str(tmp_path / "x.o")],
        capture_output=True,
        text=True,
        check=False,
    )
    assert done.returncode != 0
    assert "must not be compiled with -ffast-math" in done.stderr


def test_c_uses_only_math_and_stddef(tmp_path: Path) -> None:
    source = _write_c("two_unicycles_barrier", tmp_path)
    text = source.read_text()
    includes = sorted(line for line in text.splitlines() if line.startswith("#include"))
    assert includes == [
        '#include "two_unicycles_barrier.h"',
        "#include <math.h>",
        "#include <stddef.h>",
    ]
    assert "M_PI" not in text and "malloc(" not in text
    # No mutable state at file scope: every file-scope variable is const.
    variables = re.findall(r"^(?:static\s+)?(?:double|int|size_t)\s+\w+\s*(?:\[|=)", text, re.M)
    assert variables == []


@pytest.mark.parametrize("spec", ALL_SPECS)
def test_c_agrees_with_python(spec: str, tmp_path_factory: pytest.TempPathFactory) -> None:
    cmod, pmod = c_module(spec, tmp_path_factory), module(spec)
    states = random_states(spec, 1000, seed=11)
    for t in (0.0, 2.5, 13.0):
        for name in ("control", "rhs", "optimality_error"):
            ours, ref = getattr(cmod, name)(t, states), getattr(pmod, name)(t, states)
            np.testing.assert_allclose(ours, ref, rtol=1e-10, atol=1e-10 * np.abs(ref).max())
        y = states[: len(pmod.OUTPUT_NAMES)]
        for name in ("objective", "gradient", "hessian"):
            ours, ref = getattr(cmod, name)(t, y), getattr(pmod, name)(t, y)
            np.testing.assert_allclose(ours, ref, rtol=1e-10, atol=1e-12)
    assert cmod.STATE_NAMES == pmod.STATE_NAMES and cmod.PARAMETERS == pmod.PARAMETERS
    assert cmod.control(1.0, states[:, 0]).shape == pmod.control(1.0, states[:, 0]).shape


@pytest.mark.parametrize(
    ("state", "exception"),
    [
        ([-5.0, 4.0, 0.3, 0.0], "SingularDecouplingError"),
        ([np.nan, 4.0, 0.0, 1.0], "NonFiniteInputError"),
        ([-5.0, np.inf, 0.0, 1.0], "NonFiniteInputError"),
    ],
)
def test_same_status_at_singular_points(
    state: list[float], exception: str, tmp_path_factory: pytest.TempPathFactory
) -> None:
    cmod, pmod = c_module("unicycle_switch", tmp_path_factory), module("unicycle_switch")
    for mod in (cmod, pmod):
        with pytest.raises(getattr(mod, exception)) as info:
            mod.control(0.0, state)
        assert info.value.status == getattr(pmod, exception).status
    with pytest.raises(cmod.SingularDecouplingError, match="v = 0"):
        cmod.rhs(0.0, state if exception == "SingularDecouplingError" else [0, 0, 0, 0.0])


def test_same_status_for_a_hessian_that_is_not_positive_definite(
    tmp_path_factory: pytest.TempPathFactory,
) -> None:
    cmod, pmod = c_module("integrator", tmp_path_factory), module("integrator")
    for mod in (cmod, pmod):
        with pytest.raises(mod.HessianNotPositiveDefiniteError) as info:
            mod.control(0.0, [0.0, 0.0], {"w": -1.0})
        assert info.value.status == 3


def test_batch_reports_the_failing_column(tmp_path_factory: pytest.TempPathFactory) -> None:
    cmod = c_module("unicycle_switch", tmp_path_factory)
    states = np.array([[-5.0, -5.0, -5.0], [4.0, 4.0, 4.0], [0.0, 0.0, 0.0], [1.0, 2.0, 0.0]])
    with pytest.raises(cmod.SingularDecouplingError) as info:
        cmod.control(0.0, states)
    assert info.value.index == 2


HARNESS = """
#include "{name}.h"
#include <math.h>
#include <stdio.h>

int main(void)
{{
    double s[{P}_N_STATES], y[{P}_N_OUTPUTS];
    double out[{P}_N_STATES * {P}_K + {P}_N_OUTPUTS * {P}_N_OUTPUTS + 16];
    unsigned long seed = 12345UL;
    int i, j, counts[5] = {{0, 0, 0, 0, 0}};
    for (i = 0; i < 2000; ++i) {{
        for (j = 0; j < {P}_N_STATES; ++j) {{
            seed = seed * 6364136223846793005UL + 1442695040888963407UL;
            s[j] = {name}_default_state[j] + ((double)(seed >> 11) / 9007199254740992.0 - 0.5);
        }}
        if (i % 7 == 0) s[{P}_N_STATES - 1] = 0.0;      /* singular for prolonged speeds */
        if (i % 11 == 0) s[i % {P}_N_STATES] = NAN;      /* non-finite input */
        if (i % 13 == 0) s[0] = 1e300;                   /* overflow inside the law */
        for (j = 0; j < {P}_N_OUTPUTS; ++j) y[j] = s[j];
        counts[{name}_control(0.1 * i, s, NULL, out)]++;
        counts[{name}_rhs(0.1 * i, s, NULL, out)]++;
        counts[{name}_optimality_error(0.1 * i, s, NULL, out)]++;
        counts[{name}_hessian(0.1 * i, y, NULL, out)]++;
        {name}_rhs_batch(1, 0.1 * i, s, NULL, out, NULL);
    }}
    printf("%d %d %d %d %d\\n", counts[0], counts[1], counts[2], counts[3], counts[4]);
    return 0;
}}
"""


def run_sanitized(main_c: str, source: Path, folder: Path) -> str:
    """Build ``main_c`` with the generated C under ASan and UBSan, run it, return stdout.

    Skips when the sanitizer runtime is missing; any report fails the test.

    Unoptimised (-O0, a third of -O1's compile time on the larger controllers): every
    access and operation keeps its check, where -O1 may drop those of values it keeps in
    registers or proves dead. The warnings only optimisation brings out (-Wall's
    maybe-uninitialized) are held on every spec's C at -O2 elsewhere: test_strict_c (the
    bundled examples, coupled3, robust_pvtol) and test_compiles_cleanly_under_strict_warnings.
    """
    (folder / "main.c").write_text(main_c)
    binary = folder / "sanitized"
    build = subprocess.run(
        ["gcc", *STRICT, "-g", "-O0", "-fsanitize=address,undefined", "-fno-sanitize-recover=all"]
        + ["-o", str(binary), str(folder / "main.c"), str(source), "-lm"],
        capture_output=True,
        text=True,
        check=False,
    )
    if build.returncode != 0 and "asan" in build.stderr.lower():
        pytest.skip(f"sanitizer runtime unavailable: {build.stderr.strip()[:200]}")
    assert build.returncode == 0, build.stderr
    run = subprocess.run([str(binary)], capture_output=True, text=True, check=False, timeout=120)
    assert run.returncode == 0, (run.returncode, run.stderr)
    assert run.stderr == ""
    return run.stdout


@pytest.mark.parametrize("spec", ALL_SPECS)
def test_address_and_undefined_behaviour_sanitizers(spec: str, tmp_path: Path) -> None:
    source = _write_c(spec, tmp_path)
    name = derivation(spec).spec.name
    out = run_sanitized(HARNESS.format(name=name, P=name.upper()), source, tmp_path)
    counts = list(map(int, out.split()))
    assert sum(counts) == 8000 and counts[0] > 0 and counts[1] > 0  # OK and non-finite both seen


def _import_in_subprocess(
    folder: Path, cache: Path, extra_env: dict[str, str] | None = None
) -> subprocess.CompletedProcess[str]:
    env = dict(os.environ, TVOPT_CODEGEN_CACHE=str(cache), **(extra_env or {}))
    code = "import integrator_c as m; print(m.control(0.0, m.DEFAULT_STATE))"
    return subprocess.run(
        [sys.executable, "-c", code],
        cwd=folder,
        env=env,
        capture_output=True,
        text=True,
        check=False,
    )


def test_compiled_library_cache(tmp_path: Path) -> None:
    folder, cache = tmp_path / "gen", tmp_path / "cache"
    _write_c("integrator", folder)
    first = _import_in_subprocess(folder, cache)
    assert first.returncode == 0, first.stderr
    (library,) = cache.glob("integrator-*.so")
    stamp = library.stat().st_mtime_ns
    assert _import_in_subprocess(folder, cache).returncode == 0
    assert list(cache.glob("integrator-*.so")) == [library]  # no rebuild
    assert library.stat().st_mtime_ns == stamp
    assert _import_in_subprocess(folder, cache, {"TVOPT_CODEGEN_CFLAGS": "-O1"}).returncode == 0
    assert len(list(cache.glob("integrator-*.so"))) == 2  # changed flags: rebuilt
    source = folder / "integrator.c"
    source.write_text(source.read_text() + "\n/* edited */\n")
    assert _import_in_subprocess(folder, cache).returncode == 0
    assert len(list(cache.glob("integrator-*.so"))) == 3  # edited source: rebuilt
    assert not [p for p in cache.iterdir() if p.name.startswith(".")]  # nothing half-built


def test_kept_bytes_build_once_and_an_unusable_cache_only_costs_the_build(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """emit.caches.kept_bytes (the FMU's library): built once, then read; the key
    follows every part; a cache folder that is a file builds every time."""
    from tvopt_codegen.emit.caches import build_key, kept_bytes

    builds: list[int] = []

    def build() -> bytes:
        builds.append(1)
        return b"\x00library\xff"

    monkeypatch.setenv("TVOPT_CODEGEN_CACHE", str(tmp_path / "cache"))
    key = build_key(["a\0text"])
    assert kept_bytes(f"x-{key}", build) == kept_bytes(f"x-{key}", build) == b"\x00library\xff"
    assert len(builds) == 1
    assert [p.name for p in (tmp_path / "cache").iterdir()] == [f"x-{key}"]  # nothing partial
    assert build_key(["a\0other"]) != key and build_key(["a", "\0text"]) != key
    (tmp_path / "file").write_text("not a folder")
    monkeypatch.setenv("TVOPT_CODEGEN_CACHE", str(tmp_path / "file"))
    assert kept_bytes("y", build) == kept_bytes("y", build) == b"\x00library\xff"
    assert len(builds) == 3


def test_two_processes_importing_at_once(tmp_path: Path) -> None:
    folder, cache = tmp_path / "gen", tmp_path / "cache"
    _write_c("integrator", folder)
    env = dict(os.environ, TVOPT_CODEGEN_CACHE=str(cache))
    code = "import integrator_c as m; print(m.rhs(0.0, m.DEFAULT_STATE))"
    procs = [
        subprocess.Popen(
            [sys.executable, "-c", code],
            cwd=folder,
            env=env,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        for _ in range(2)
    ]
    outputs = [p.communicate(timeout=120) for p in procs]
    assert all(p.returncode == 0 for p in procs), outputs
    assert outputs[0][0] == outputs[1][0]
    assert len(list(cache.glob("integrator-*.so"))) == 1


def test_missing_compiler_is_a_clear_import_error(tmp_path: Path) -> None:
    folder, cache = tmp_path / "gen", tmp_path / "cache"
    _write_c("integrator", folder)
    empty = tmp_path / "bin"
    empty.mkdir()
    done = _import_in_subprocess(folder, cache, {"PATH": str(empty), "CC": ""})
    assert done.returncode != 0
    assert "ImportError: integrator: no C compiler found" in done.stderr
    assert not cache.exists() or not list(cache.iterdir())


def test_a_named_compiler_that_does_not_exist_is_not_replaced(tmp_path: Path) -> None:
    folder, cache = tmp_path / "gen", tmp_path / "cache"
    _write_c("integrator", folder)
    done = _import_in_subprocess(folder, cache, {"CC": "/nonexistent/cc"})
    assert done.returncode != 0
    assert "the C compiler CC='/nonexistent/cc' was not found" in done.stderr
    out = tmp_path / "run"
    # The command's refusal in this process: its subject is the lookup, not a process.
    env = {"CC": "/nonexistent/cc", "TVOPT_CODEGEN_CACHE": str(cache)}
    run = run_main("simulate", "integrator", "--backend", "c", "--out", str(out), env=env)
    assert run.returncode == 7, run.stderr
    assert run.stderr.count("\n") == 1 and "CC='/nonexistent/cc' was not found" in run.stderr
    assert not out.exists()


def test_compiler_error_is_reported_and_nothing_cached(tmp_path: Path) -> None:
    folder, cache = tmp_path / "gen", tmp_path / "cache"
    _write_c("integrator", folder)
    source = folder / "integrator.c"
    source.write_text(source.read_text() + "\nthis is not C;\n")
    done = _import_in_subprocess(folder, cache)
    assert done.returncode != 0
    assert "compiling" in done.stderr and "failed" in done.stderr
    assert not list(cache.glob("*.so"))


def test_example_control_loop_from_the_guide_compiles_and_runs(tmp_path: Path) -> None:
    """docs/module.md's stateful C loop, as written there, with a simulated robot around it."""
    from .conftest import ROOT

    readme = (ROOT / "docs" / "module.md").read_text()
    blocks = re.findall(r"```c\n(.*?)```", readme, re.DOTALL)
    loop = next(block for block in blocks if "controller_step" in block)
    source = _write_c("unicycle_switch", tmp_path)
    robot = textwrap.dedent("""
        #include <stdio.h>
        static double state[3] = {-5.0, 4.0, 0.0};
        static int sent = 0;
        static void read_sensors(double *x) { int i; for (i = 0; i < 3; ++i) x[i] = state[i]; }
        static void send_to_motors(const double *u) { state[2] += 1e-3 * u[1]; ++sent; }
    """)
    main_c = textwrap.dedent("""
        int main(void)
        {
            const int status = run_loop(500);
            printf("%d %d\\n", status, sent);
            return 0;
        }
    """)
    (tmp_path / "loop.c").write_text(robot + loop + main_c)
    binary = tmp_path / "loop"
    done = subprocess.run(
        ["gcc", *STRICT, "-I", str(source.parent), "-o", str(binary), str(tmp_path / "loop.c")]
        + [str(source), "-lm"],
        capture_output=True,
        text=True,
        check=False,
    )
    assert done.returncode == 0, done.stderr
    run = subprocess.run([str(binary)], capture_output=True, text=True, check=True)
    assert run.stdout.split() == ["0", "500"]


def test_barrier_at_its_pole_same_status_in_both_backends(
    tmp_path_factory: pytest.TempPathFactory,
) -> None:
    cmod, pmod = (
        c_module("two_unicycles_barrier", tmp_path_factory),
        module("two_unicycles_barrier"),
    )
    state = np.array(pmod.DEFAULT_STATE)
    state[3], state[4] = state[0] + np.sqrt(2.0), state[1]  # |pa - pb|^2 = d: tan(pi/2)
    outcomes = []
    for mod in (pmod, cmod):
        try:
            u = mod.control(0.0, state)
            assert np.all(np.isfinite(u))
            outcomes.append("finite")
        except mod.ControllerError as exc:
            outcomes.append(exc.status)
    assert outcomes[0] == outcomes[1]


def _ctypes_module(spec: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> ModuleType:
    """The same generated module imported without its CPython entry point."""
    folder = tmp_path / "ctypes"
    _write_c(spec, folder)
    name = derivation(spec).spec.name
    with monkeypatch.context() as patch:
        patch.setenv("TVOPT_CODEGEN_EXTENSION", "0")
        return import_file(folder / f"{name}_c.py", f"_tvopt_ctypes_{name}")


@pytest.mark.parametrize("spec", ["unicycle_switch", "two_unicycles_barrier", "flexible_joint"])
def test_entry_point_equals_the_ctypes_path(
    spec: str,
    tmp_path: Path,
    tmp_path_factory: pytest.TempPathFactory,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The compiled entry point and ctypes call the same C: identical to the last bit,
    for every layout of the state a user may pass."""
    fast, slow = c_module(spec, tmp_path_factory), _ctypes_module(spec, tmp_path, monkeypatch)
    assert fast._ENTRY is not None and slow._ENTRY is None  # noqa: SLF001
    states = random_states(spec, 50, seed=5)
    layouts = [
        states,  # C-contiguous (n, N)
        np.asfortranarray(states),  # columns contiguous
        states[:, ::3],  # strided columns
        np.ascontiguousarray(states.T).T,  # a transposed view
        states[:, 7],  # one state, a strided 1-D view
        list(states[:, 3]),  # a list: the general path
        states.astype(np.float32),  # another dtype: the general path
    ]
    m = len(fast.OUTPUT_NAMES)
    for layout in layouts:
        for name in ("control", "rhs", "optimality_error"):
            np.testing.assert_array_equal(
                getattr(fast, name)(1.5, layout), getattr(slow, name)(1.5, layout)
            )
        y = np.asarray(layout)[:m]
        for name in ("objective", "gradient", "hessian"):
            np.testing.assert_array_equal(getattr(fast, name)(1.5, y), getattr(slow, name)(1.5, y))
    params = {next(iter(fast.PARAMETERS)): 0.9}
    np.testing.assert_array_equal(
        fast.control(2.0, states, params), slow.control(2.0, states, params)
    )
    assert fast.control.__doc__ == slow.control.__doc__
    assert fast.control.__name__ == "control"


def test_entry_point_raises_like_the_python_backend(
    tmp_path_factory: pytest.TempPathFactory,
) -> None:
    cmod, pmod = c_module("unicycle_switch", tmp_path_factory), module("unicycle_switch")
    states = np.array([[-5.0, -5.0, -5.0], [4.0, 4.0, 4.0], [0.0, 0.0, 0.0], [1.0, 0.0, 2.0]])
    for mod in (cmod, pmod):
        with pytest.raises(mod.SingularDecouplingError, match="column 1") as info:
            mod.control(0.0, states)
        assert info.value.index == 1
        with pytest.raises(ValueError, match=r"s must have shape \(4,\) or \(4, N\), got \(3,\)"):
            mod.control(0.0, np.zeros(3))
        with pytest.raises(ValueError, match="unknown parameter"):
            mod.control(0.0, states[:, 0], {"nope": 1.0})
        with pytest.raises(TypeError, match="t must be a real number, got ndarray"):
            mod.control(np.zeros(2), states[:, 0])
        np.testing.assert_array_equal(
            mod.control(np.float32(0.5), states[:, 0]), mod.control(0.5, states[:, 0])
        )
        with pytest.raises(mod.NonFiniteInputError):
            mod.control(float("nan"), states[:, 0])


@pytest.mark.parametrize(
    ("spec", "heading"),
    [("unicycle_switch", "theta"), (str(SPECS / "hovercraft.toml"), "th")],
)
def test_lu_row_exchanges_in_both_backends(
    spec: str, heading: str, tmp_path_factory: pytest.TempPathFactory
) -> None:
    # cos(heading) leads R's first column: near +-pi/2 the unpivoted LU divides by ~0, so
    # these headings take the row exchange (the 2 x 2 unrolled solve, the 3 x 3 loop).
    cmod, pmod = c_module(spec, tmp_path_factory), module(spec)
    states = random_states(spec, 200, seed=5)
    row = pmod.STATE_NAMES.index(heading)
    states[row] = np.linspace(-np.pi, np.pi, 200)
    states[row, :4] = [np.pi / 2, -np.pi / 2, 0.0, np.pi]
    p = np.array(list(pmod.PARAMETERS.values()), dtype=float)
    u_ref, ds_ref = Oracle(derivation(spec)).law(0.7, states, p)
    for mod in (cmod, pmod):
        np.testing.assert_allclose(
            mod.control(0.7, states), u_ref, rtol=1e-10, atol=1e-10 * np.abs(u_ref).max()
        )
        np.testing.assert_allclose(
            mod.rhs(0.7, states), ds_ref, rtol=1e-10, atol=1e-10 * np.abs(ds_ref).max()
        )


def test_large_batches_through_the_entry_point(tmp_path_factory: pytest.TempPathFactory) -> None:
    # The entry point hands the C batch functions up to 64 columns at a time: results join
    # across chunks, and a failure in a later chunk names its column in the whole batch.
    cmod = c_module("unicycle_switch", tmp_path_factory)
    states = random_states("unicycle_switch", 300, seed=2)
    whole = cmod.rhs(0.5, states)
    for column in (0, 63, 64, 150, 299):
        np.testing.assert_array_equal(whole[:, column], cmod.rhs(0.5, states[:, column]))
    states[3, 150] = 0.0  # v = 0: R is singular
    with pytest.raises(cmod.SingularDecouplingError, match=r"\(column 150\)") as info:
        cmod.control(0.5, states)
    assert info.value.index == 150


def test_sparse_outputs_are_zeros_and_their_nonzero_elements(
    tmp_path: Path, tmp_path_factory: pytest.TempPathFactory
) -> None:
    """An eight-agent ring's Hessian (16 x 16, 160 zeros) is printed as zeros and its 96
    nonzero elements, in every printing; its values are sympy's (the Hessian crossed to
    SymPy at the border and lambdified there), the same in both backends, on the
    one-point and the batch path. That a sparse output's C compiles under strict
    warnings is tests/test_strict_c.py's: ur5_tip's Hessian is printed sparse and held
    there to a stricter profile under gcc and clang, in both precisions
    (test_the_strict_profile_covers_a_sparse_output)."""
    from sympy.printing.numpy import NumPyPrinter

    from tvopt_codegen.backends.c.printer import CPrinter
    from tvopt_codegen.renderer.rendering import print_kernel
    from tvopt_codegen.symbolic.border import to_sympy

    spec = tmp_path / "ring8.toml"
    text = (ROOT / "tvopt_codegen" / "examples" / "unicycle_ring.toml").read_text()
    spec.write_text(re.sub(r"(?m)^i = \d+", "i = 8", text), encoding="utf-8")
    d = derive(load_spec(spec))
    lowered = lower(d)
    (hessian,) = [k for k in lowered.kernels if k.name == "hessian"]
    printed = print_kernel(hessian, CPrinter())
    assert printed.outputs[0].sparse and len(printed.outputs[0].elements) == 96
    python = load_controller(lowered, "python")
    c = load_controller(lowered, "c")
    rng = np.random.default_rng(8)
    ys = rng.uniform(-3.0, 3.0, size=(16, 5))
    values = dict(zip(d.model.params, d.model.defaults, strict=True))
    arguments = [to_sympy(s) for s in (d.model.t, *d.model.y)]
    # SymPy's printer without its canonical term order (lambdify's own settings otherwise):
    # ordering the terms of the 256 elements was two thirds of lambdify's time, and the
    # order of a sum's terms moves its value by rounding only (far below 1e-12).
    printer = NumPyPrinter(
        {
            "fully_qualified_modules": False,
            "inline": True,
            "allow_unknown_functions": True,
            "order": "none",
        }
    )
    exact = sp.lambdify(arguments, to_sympy(d.hessian.xreplace(values)), "numpy", printer=printer)
    for column in range(5):
        expected = np.array(exact(1.5, *ys[:, column]), dtype=float)
        one = python.hessian(1.5, ys[:, column])
        np.testing.assert_allclose(one, expected, rtol=1e-12, atol=1e-12)
        np.testing.assert_array_equal(python.hessian(1.5, ys)[:, :, column], one)
        np.testing.assert_allclose(c.hessian(1.5, ys[:, column]), one, rtol=1e-13, atol=1e-13)
    assert int(np.sum(one == 0.0)) >= 160


def test_the_compiler_version_is_asked_once_per_binary(tmp_path: Path) -> None:
    """Each cached library's key holds ``cc --version``: asked once per compiler binary and
    process (a cached library then costs no process), and again when the binary changes."""
    from tvopt_codegen.toolchain import version

    log = tmp_path / "asked"
    cc = tmp_path / "cc"
    cc.write_text(f"#!/bin/sh\necho x >> {log}\necho 'cc 1.0'\n", encoding="utf-8")
    cc.chmod(0o755)
    assert version(str(cc)) == version(str(cc)) == "cc 1.0\n"
    assert log.read_text(encoding="utf-8").count("x") == 1
    cc.write_text(f"#!/bin/sh\necho x >> {log}\necho 'cc 2.0.1'\n", encoding="utf-8")
    os.utime(cc, ns=(cc.stat().st_atime_ns, cc.stat().st_mtime_ns + 1_000_000_000))
    assert version(str(cc)) == "cc 2.0.1\n"
    assert log.read_text(encoding="utf-8").count("x") == 2
