"""The strict C profile (issue 50 item 4): every bundled example's C, in both precisions.

Each controller compiles without a warning under gcc and clang with :data:`STRICT`
(``-Werror``, ``-Wvla``), and clang's static analyser and cppcheck find nothing in it. It
allocates nothing on the heap, and gcc's call graph of it (``-fcallgraph-info``) has no
cycle (recursion) and no call through a pointer. The stack bound its header states
(``<NAME>_STACK_BOUND_BYTES``, :mod:`tvopt_codegen.backends.c.stack`) is at least what
gcc's ``-fstack-usage`` counts along every call path, on the host and on a Cortex-M4F. So are the
template paths no bundled example takes (:data:`VARIANTS`). The files are rendered once
per test run and precision (``conftest.shared``) and shared with ``test_precision`` and
``test_embedded_qemu``, and so are gcc's -O2 builds of them for the host and the Cortex-M4F
(``test_embedded_qemu`` links their objects). Every compiler and analyser run here is kept
across runs of the suite (``tests/toolcache.py``): one whose program, arguments and files
are those of an earlier run gives back that run's output and verdict. A tool that is
missing skips with the command that installs it, except in CI (``CI`` set), where
``.ci/run`` installs it and its absence is a failure.
"""

from __future__ import annotations

import functools
import os
import re
import shutil
import subprocess
import tomllib
from pathlib import Path

import pytest

from tvopt_codegen import symbolic as sx
from tvopt_codegen.backends.c import with_precision
from tvopt_codegen.backends.c.stack import FRAME_ALLOWANCE, bounds, parse
from tvopt_codegen.derivation import derive
from tvopt_codegen.lowering.ir import KernelSet, lower
from tvopt_codegen.renderer.rendering import render
from tvopt_codegen.spec import spec_from_dict

from .conftest import ROOT, SPECS, kept_folder, kernels, shared
from .embedded.harness import (
    COMMON_FLAGS,
    TARGETS,
    CallGraph,
    assemble,
    assembly_command,
    skip_reason,
)
from .toolcache import kept_run

#: Every bundled example.
BUNDLED = tuple(sorted(path.stem for path in (ROOT / "tvopt_codegen" / "examples").glob("*.toml")))

#: The template paths no bundled example takes, held to the same profile: integral action,
#: the disturbance observer, limits and a slew rate (robust_pvtol), a 3 x 3 block of R (the
#: general LU: coupled3), the extended-state observer, Levant's differentiator.
VARIANTS: dict[str, tuple[Path, dict[str, object]]] = {
    "robust_pvtol": (SPECS / "robust_pvtol.toml", {}),
    "coupled3": (SPECS / "coupled3.toml", {}),
    "drag_vehicle_eso": (
        ROOT / "tvopt_codegen" / "examples" / "drag_vehicle.toml",
        {"robust": {"eso": {"bandwidth": 20.0}}},
    ),
    "unicycle_switch_levant": (
        ROOT / "tvopt_codegen" / "examples" / "unicycle_switch_refs.toml",
        {"references": {"estimator": {"kind": "levant", "lipschitz": 10.0}}},
    ),
}


def _kernels(spec: str) -> KernelSet:
    """A bundled example's kernels, or a variant's (:data:`VARIANTS`), once per engine."""
    if spec not in VARIANTS:
        return kernels(spec)
    return _variant(spec, sx.ENGINE)


@functools.cache
def _variant(spec: str, engine: str) -> KernelSet:
    # Both precisions render the same kernels: derived once, not once per precision.
    path, changes = VARIANTS[spec]
    with path.open("rb") as stream:
        data = tomllib.load(stream)
    for section, value in changes.items():
        merged = dict(data.get(section, {}))
        merged.update(value)  # type: ignore[call-overload]
        data[section] = merged
    return lower(derive(spec_from_dict(data)))


#: The strict profile: C99, every warning the issue names, and none allowed.
STRICT = (
    "-std=c99",
    "-O2",
    "-Wall",
    "-Wextra",
    "-Wpedantic",
    "-Wshadow",
    "-Wcast-qual",
    "-Wconversion",
    "-Wundef",
    "-Wstrict-prototypes",
    "-Wdouble-promotion",
    "-Wfloat-conversion",
    "-Wvla",
    "-Werror",
)

#: cppcheck's checks (its errors are always on): nothing it reports is accepted.
CPPCHECK = (
    "--enable=warning,style,performance,portability",
    "--std=c99",
    "--error-exitcode=1",
    "--quiet",
    "--inline-suppr",
)


def generated(spec: str, precision: str) -> Path:
    """The C backend's files for ``spec`` in ``precision``, rendered once per test run."""

    def build(folder: Path) -> None:
        for name, text in render(_kernels(spec), with_precision(precision)).items():
            (folder / name).write_text(text, encoding="utf-8")

    return shared(f"c-{precision}-{Path(spec).stem}", build)


def _tool(name: str, install: str) -> str:
    """The path of ``name``; skip outside CI (saying what installs it), fail in CI."""
    found = shutil.which(name)
    if found is None:
        message = f"{name} is not installed: {install}"
        if os.environ.get("CI"):
            pytest.fail(message)
        pytest.skip(message)
    return found


def _run(
    command: list[str], folder: Path, writes: tuple[Path, ...] = ()
) -> subprocess.CompletedProcess[str]:
    """Run ``command`` in the generated ``folder`` (which it reads whole), or give back
    what it did on the same files in an earlier run (``tests/toolcache.py``)."""
    reads = sorted(p for p in folder.iterdir() if p.is_file() and not p.name.startswith("."))
    return kept_run(command, reads=reads, writes=writes, cwd=folder, cache=kept_folder())


def _clean(command: list[str], folder: Path) -> None:
    """Run ``command`` in ``folder``; it must succeed and print nothing."""
    done = _run(command, folder)
    report = (done.stdout + done.stderr).strip()
    assert done.returncode == 0 and not report, report[:3000]


#: Constructs whose clang diagnostics come from code generation, not the front end:
#: inline assembly (-Winline-asm), pragmas (a loop pragma's -Wpass-failed) and attributes
#: (``warning``/``error``: -Wattribute-warning). The controller has none of them, so
#: ``-fsyntax-only`` reports everything clang's strict build would.
BACKEND_DIAGNOSED = re.compile(r"\basm\b|__asm__|#\s*pragma|_Pragma|__attribute__")


@pytest.mark.parametrize("precision", ["double", "single"])
@pytest.mark.parametrize("example", [*BUNDLED, *VARIANTS])
def test_the_controller_compiles_warning_free_under_clang(example: str, precision: str) -> None:
    """clang's strict build; gcc's is the call-graph build of the test below.

    clang emits every warning of :data:`STRICT` in its front end: ``-fsyntax-only`` reports
    them without generating code (a fifth of the compile's time on ur5_tip; proved by
    test_clang_reports_every_strict_warning_without_generating_code), and the controller
    has none of the constructs diagnosed in code generation (:data:`BACKEND_DIAGNOSED`).
    """
    folder = generated(example, precision)
    source = _source(folder)
    code = _PROSE.sub(" ", (folder / source).read_text(encoding="utf-8"))
    headers = (p.read_text(encoding="utf-8") for p in folder.glob("*.h"))
    assert not BACKEND_DIAGNOSED.findall(code + "".join(_PROSE.sub(" ", h) for h in headers))
    clang = _tool("clang", "apt-get install clang")
    _clean([clang, *STRICT, "-fsyntax-only", source], folder)


#: One deliberate breach of each warning of :data:`STRICT`, and the flag clang names it by
#: (-Wall, -Wextra and -Wpedantic by one warning of theirs each).
BREACHES = {
    "-Wundef": "#if UNDEFINED_MACRO\n#endif\n",
    "-Wstrict-prototypes": "int proto();\n",
    "-Wzero-length-array": (
        "static int zero[0];\nint first(void);\nint first(void) { return zero[0]; }\n"
    ),
    "-Wunused-parameter": "int one(int a, int b);\nint one(int a, int b) { return a; }\n",
    "-Wunused-variable": "void idle(void);\nvoid idle(void) { int unused; }\n",
    "-Wimplicit-float-conversion": "float half(double x);\nfloat half(double x) { return x; }\n",
    "-Wfloat-conversion": "int trunc_(double x);\nint trunc_(double x) { return x; }\n",
    "-Wshorten-64-to-32": "int narrow(long x);\nint narrow(long x) { return x; }\n",
    "-Wdouble-promotion": "double twice(float x);\ndouble twice(float x) { return x * 2.0; }\n",
    "-Wcast-qual": "char *drop(const char *p);\nchar *drop(const char *p) { return (char *)p; }\n",
    "-Wvla": "int vla(int n);\nint vla(int n) { int a[n]; a[0] = 0; return a[0]; }\n",
    "-Wshadow": "int shadow(int n);\nint shadow(int n) { int m = n; { int n = m; return n; } }\n",
}


def test_clang_reports_every_strict_warning_without_generating_code(tmp_path: Path) -> None:
    """``-fsyntax-only`` reports each warning of the strict profile as the full build does:
    the same diagnostics, naming every breach of :data:`BREACHES`, and fails alike."""
    clang = _tool("clang", "apt-get install clang")
    (tmp_path / "breaches.c").write_text("".join(BREACHES.values()), encoding="utf-8")
    reports = []
    for mode in (["-fsyntax-only"], ["-c", "-o", "breaches.o"]):
        done = subprocess.run(
            [clang, *STRICT, *mode, "breaches.c"],
            cwd=tmp_path,
            capture_output=True,
            text=True,
            check=False,
        )
        assert done.returncode != 0
        reports.append(done.stderr)
    assert reports[0] == reports[1]
    named = set(re.findall(r"\[-Werror,(-W[\w-]+)\]", reports[0]))
    assert named == set(BREACHES), named ^ set(BREACHES)
    # Each breach is its own line of the file's functions: one diagnostic each.
    assert len(re.findall(r"error: ", reports[0])) == len(BREACHES), reports[0]


@pytest.mark.parametrize("precision", ["double", "single"])
@pytest.mark.parametrize("example", [*BUNDLED, *VARIANTS])
def test_the_static_analysers_find_nothing(example: str, precision: str) -> None:
    folder = generated(example, precision)
    (source,) = (p.name for p in folder.glob("*.c") if not p.name.endswith(".ext.c"))
    clang = _tool("clang", "apt-get install clang")
    _clean([clang, "--analyze", "-std=c99", source, "-o", "/dev/null"], folder)
    cppcheck = _tool("cppcheck", "apt-get install cppcheck")
    _clean([cppcheck, *CPPCHECK, source], folder)


#: A call of the C library's allocators (the controller must make none), and the comments
#: and strings that may say "free" without calling it.
HEAP = re.compile(r"\b(malloc|calloc|realloc|free|alloca|__builtin_alloca)\s*\(")
_PROSE = re.compile(r'/\*.*?\*/|//[^\n]*|"(?:\\.|[^"\\])*"', re.DOTALL)


def _source(folder: Path) -> str:
    """The controller's ``.c`` in ``folder`` (not the CPython entry point's)."""
    (source,) = (p.name for p in folder.glob("*.c") if not p.name.endswith(".ext.c"))
    return source


def stated_bounds(header: str) -> dict[str, int]:
    """The bound the header states for each public function (its table of bounds)."""
    table = header.split(" * Stack: ", 1)[1].split(" */", 1)[0]
    return {name: int(n) for name, n in re.findall(r"^ \*   (\w+) +(\d+)$", table, re.MULTILINE)}


def _frames(ci: Path) -> dict[str, int]:
    """gcc's deepest static stack per function of the file, from its ``.ci`` call graph."""
    graph = CallGraph.read(ci)
    return {graph.names[node]: graph.deepest(node)[0] for node in graph.own}


def m4f_build(example: str, precision: str) -> Path:
    """The controller compiled for the Cortex-M4F at -O2 (the harness's flags), once per run.

    The folder holds its assembly (``controller.s``) and gcc's call graph beside it
    (``controller.ci``, ``-fcallgraph-info=su``, which changes no byte of the code): the
    stack check below reads the graph; :func:`m4f_object` assembles the object that
    test_embedded_qemu links into its M4F loop, for the examples it runs alone.
    """

    def build(out: Path) -> None:
        folder = generated(example, precision)
        assembly = out / "controller.s"
        command = assembly_command(
            TARGETS["m4f"], folder / _source(folder), assembly, "-fcallgraph-info=su"
        )
        done = _run(command, folder, (assembly, out / "controller.ci"))
        assert done.returncode == 0, done.stderr[:3000]

    return shared(f"m4f-{precision}-{example}", build)


def m4f_object(example: str, precision: str) -> Path:
    """The object of :func:`m4f_build`, once per run: the bytes ``-c`` would have made."""

    def build(out: Path) -> None:
        assemble(
            TARGETS["m4f"], m4f_build(example, precision) / "controller.s", out / "controller.o"
        )

    return shared(f"m4f-object-{precision}-{example}", build) / "controller.o"


#: The harness's code generation flags (tests/embedded/harness.py) that :data:`STRICT` does
#: not give: gcc's strict build is then the harness's host build as well (contraction
#: needs a fused multiply-add, which x86-64's baseline does not have: no byte changes).
HARNESS_ONLY = tuple(flag for flag in COMMON_FLAGS if flag not in STRICT)


def host_build(example: str, precision: str) -> Path:
    """gcc's strict -O2 build of the controller for the host, once per run.

    The folder holds what gcc printed (``printed``: nothing, or the reason the build
    failed), and when it compiled, the assembly (``controller.s``) and gcc's call graph
    (``controller.ci``). Read by the strict test below, and assembled by
    :func:`host_object` for test_embedded_qemu's host loop.
    """
    gcc = _tool("gcc", "apt-get install gcc")

    def build(out: Path) -> None:
        folder = generated(example, precision)
        assembly = out / "controller.s"
        command = [gcc, *STRICT, *HARNESS_ONLY, "-fcallgraph-info=su", "-S", _source(folder)]
        done = _run([*command, "-o", str(assembly)], folder, (assembly, out / "controller.ci"))
        printed = (done.stdout + done.stderr).strip()
        if done.returncode != 0:
            printed = printed or f"gcc exited {done.returncode}"
            assembly.unlink(missing_ok=True)
        (out / "printed").write_text(printed, encoding="utf-8")

    return shared(f"host-{precision}-{example}", build)


def host_object(example: str, precision: str) -> Path | None:
    """The object of :func:`host_build` (the bytes ``-c`` would have made), or None when
    gcc's strict build failed (the strict test reports why)."""
    built = host_build(example, precision)
    if not (built / "controller.s").is_file():
        return None

    def build(out: Path) -> None:
        assemble(TARGETS["host"], built / "controller.s", out / "controller.o")

    return shared(f"host-object-{precision}-{example}", build) / "controller.o"


def _measured(target: str, folder: Path, out: Path, *flags: str) -> dict[str, int]:
    """gcc's deepest static stack per function of the controller compiled for ``target``
    (to assembly: the graph is gcc's, and no object is needed)."""
    assembly = out / "controller.s"
    command = assembly_command(
        TARGETS[target], folder / _source(folder), assembly, *flags, "-fcallgraph-info=su"
    )
    done = _run(command, folder, (assembly, out / "controller.ci"))
    assert done.returncode == 0, done.stderr[:3000]
    return _frames(out / "controller.ci")


# One test per file for what gcc's builds show, each build serving every check it can
# (a build of every example in both precisions is a few tenths of a second): gcc's strict
# -O2 build is warning-free and its call graph has no call through a pointer and no cycle;
# the stated stack bound holds above gcc's frames at -O0 (nothing inlined: the bound's
# scanner found exactly gcc's functions), -O2 and on the Cortex-M4F. The builds stop at
# assembly: gcc's diagnostics and call graph are its compiler's, not the assembler's (the
# controller has no inline assembly: BACKEND_DIAGNOSED).
@pytest.mark.parametrize("precision", ["double", "single"])
@pytest.mark.parametrize("example", [*BUNDLED, *VARIANTS])
def test_gcc_no_heap_no_recursion_no_pointer_calls_and_the_stack_bound(
    example: str, precision: str, tmp_path: Path
) -> None:
    folder = generated(example, precision)
    source = _source(folder)
    code = _PROSE.sub(" ", (folder / source).read_text(encoding="utf-8"))
    assert not HEAP.findall(code), HEAP.findall(code)
    built = host_build(example, precision)
    printed = (built / "printed").read_text(encoding="utf-8")
    assert (built / "controller.s").is_file() and not printed, printed[:3000]
    ci = built / "controller.ci"
    graph = CallGraph.read(ci)
    assert not [t for t in graph.names if "__indirect_call" in t], "a call through a pointer"
    for node in graph.names:
        graph.deepest(node)  # raises on recursion, naming the cycle

    (header,) = folder.glob("*.h")
    bounds = stated_bounds(header.read_text(encoding="utf-8"))
    prefix = header.stem
    assert bounds[f"{prefix}_controller_step"] > 0
    builds: dict[str, dict[str, int]] = {"host -O2 (strict)": _frames(ci)}
    out = tmp_path / "O0"
    out.mkdir()
    builds["host -O0"] = _measured("host", folder, out, "-O0")
    text = (folder / source).read_text(encoding="utf-8")
    found = parse(text, header.read_text(encoding="utf-8"), 8)
    assert set(builds["host -O0"]) == set(found), set(builds["host -O0"]) ^ set(found)
    if skip_reason("m4f") is None:
        builds["m4f -O2"] = _frames(m4f_build(example, precision) / "controller.ci")
    elif os.environ.get("CI"):
        pytest.fail(f"{skip_reason('m4f')}")
    for build, measured in builds.items():
        for name, bound in bounds.items():
            # A function inlined everywhere has no frame of its own: nothing to compare.
            if name in measured:
                assert measured[name] <= bound, (build, name, measured[name], bound)


def test_the_strict_profile_covers_a_sparse_output() -> None:
    """A sparse output (its zeros, then its nonzero elements) is among the C held to the
    profile: ur5_tip's Hessian. test_c_backend's eight-agent ring checks the sparse
    printing's values and leaves its strict compilation to this file."""
    from tvopt_codegen.backends.c.printer import CPrinter  # noqa: PLC0415
    from tvopt_codegen.renderer.rendering import print_kernel  # noqa: PLC0415

    assert "ur5_tip" in BUNDLED
    (hessian,) = [k for k in _kernels("ur5_tip").kernels if k.name == "hessian"]
    (output,) = print_kernel(hessian, CPrinter()).outputs
    assert output.sparse and 0 < len(output.elements) < output.size
    for precision in ("double", "single"):
        folder = generated("ur5_tip", precision)
        code = (folder / _source(folder)).read_text(encoding="utf-8")
        # The sparse form's zeroing loop, as the C template prints it.
        assert f"for (zero = 0; zero < {output.size}; ++zero)" in code, precision
        assert "/* the nonzero elements below */" in code, precision


def test_the_stack_bound_counts_every_variable_and_refuses_recursion() -> None:
    header = "#define N 3\ntypedef struct {\n    double t;\n    unsigned char s[N];\n} c_t;\n"
    source = """
/* free(x) in a comment calls nothing */
static double leaf(const double *x, size_t n)
{
    double sum = 0.0, term[N * 2];
    size_t i;
    for (i = 0; i < n; ++i) {
        const double v = x[i];
        sum += v + term[i];
    }
    return sum;
}

int entry(c_t *c, double t)
{
    c_t next;
    int status = 0;
    next.t = t + leaf(&c->t, 1) + leaf(&t, 1);
    *c = next;
    return status;
}
"""
    functions = parse(source, header, 8)
    # leaf: x, n; sum, term[6], i, v. entry: c, t; next (16: 8 + 3, aligned to 8), status.
    assert functions["leaf"].frame == FRAME_ALLOWANCE + 8 + 8 + 8 + 48 + 8 + 8
    assert functions["entry"].frame == FRAME_ALLOWANCE + 8 + 8 + 16 + 4
    assert functions["entry"].calls == ("leaf",)
    assert bounds(functions) == {"entry": functions["entry"].frame + functions["leaf"].frame}
    recursive = (
        "static int f(int n)\n{\n    return n ? f(n - 1) : 0;\n}\nint g(void) { return f(3); }\n"
    )
    with pytest.raises(ValueError, match="recursion: g -> f -> f"):
        bounds(parse(recursive, "", 8))
    with pytest.raises(ValueError, match="unknown type: widget_t"):
        parse("int g(void)\n{\n    widget_t w;\n    return 0;\n}\n", "", 8)
