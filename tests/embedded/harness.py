"""Build and run the closed-loop harness (``loop.c``) on ARM targets under QEMU.

One harness, five targets: the x86-64 host (the reference), arm64 and armhf Linux
(static binaries under ``qemu-aarch64`` and ``qemu-arm``), and two bare-metal images,
a Cortex-M4F on ``qemu-system-arm -M mps2-an386`` and a Cortex-M7 on ``mps2-an500``
(``startup.c``, the boards' linker scripts, semihosting output). Everything is compiled
with ``-ffp-contract=off``: no multiply-add is fused, so that double arithmetic rounds the
same on every target and only the math library can differ.

The tests (``tests/test_embedded_qemu.py``) and ``benchmarks/bench_embedded.py`` share it.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent

#: What installs every toolchain and emulator the harness uses (Debian 12).
APT_PACKAGES = (
    "gcc-arm-none-eabi",
    "libnewlib-arm-none-eabi",
    "qemu-system-arm",
    "qemu-user",
    "gcc-aarch64-linux-gnu",
    "gcc-arm-linux-gnueabihf",
    "libc6-dev-arm64-cross",
    "libc6-dev-armhf-cross",
)
INSTALL = "apt-get install --no-install-recommends " + " ".join(APT_PACKAGES)

#: Every file of the harness but the generated controller.
COMMON_FLAGS = ("-O2", "-std=c99", "-ffp-contract=off")

#: The semihosting console of the bare-metal images, on QEMU's standard output (without
#: a chardev, QEMU writes it to its standard error).
SEMIHOSTING = (
    "-chardev",
    "stdio,id=semihosting",
    "-semihosting-config",
    "enable=on,target=native,chardev=semihosting",
)


@dataclass(frozen=True)
class Target:
    """One place the harness runs.

    Attributes
    ----------
    name : str
        ``host``, ``arm64``, ``armhf``, ``m4f`` or ``m7``.
    prefix : str
        The toolchain's prefix (``""`` for the host's gcc).
    flags : tuple of str
        Code generation flags (CPU, FPU, ABI).
    link : tuple of str
        Link flags after the objects.
    runner : tuple of str
        The command that runs a binary, which is appended (empty: run it directly).
    bare : bool
        A bare-metal image (start-up file, linker script, semihosting).
    """

    name: str
    prefix: str
    flags: tuple[str, ...]
    link: tuple[str, ...]
    runner: tuple[str, ...]
    bare: bool = False

    @property
    def cc(self) -> str:
        return f"{self.prefix}gcc"

    def tool(self, name: str) -> str:
        """A binutils program of the toolchain (``objcopy``, ``nm``, ``size``)."""
        return f"{self.prefix}{name}"

    def missing(self) -> list[str]:
        """The programs of this target that are not on the PATH."""
        programs = [self.cc, self.tool("objcopy"), self.tool("nm")]
        if self.runner:
            programs.append(self.runner[0])
        return [p for p in programs if shutil.which(p) is None]


def _bare(name: str, cpu: str, fpu: str, board: str) -> Target:
    return Target(
        name=name,
        prefix="arm-none-eabi-",
        flags=(f"-mcpu={cpu}", "-mthumb", "-mfloat-abi=hard", f"-mfpu={fpu}"),
        link=(
            "-nostartfiles",
            "--specs=nosys.specs",
            f"-L{HERE}",
            f"-T{HERE / f'mps2_{board}.ld'}",
            "-Wl,--gc-sections",
            "-lm",
        ),
        runner=(
            "qemu-system-arm",
            "-M",
            f"mps2-{board}",
            "-display",
            "none",
            "-monitor",
            "none",
            "-serial",
            "none",
            *SEMIHOSTING,
            "-kernel",
        ),
        bare=True,
    )


TARGETS = {
    "host": Target("host", "", (), ("-lm",), ()),
    "arm64": Target("arm64", "aarch64-linux-gnu-", (), ("-static", "-lm"), ("qemu-aarch64",)),
    "armhf": Target("armhf", "arm-linux-gnueabihf-", (), ("-static", "-lm"), ("qemu-arm",)),
    # The M4F's FPU is single precision only: double is emulated in software (libgcc).
    "m4f": _bare("m4f", "cortex-m4", "fpv4-sp-d16", "an386"),
    # The M7 of AN500 has the double-precision FPU (FPv5, 16 double registers).
    "m7": _bare("m7", "cortex-m7", "fpv5-d16", "an500"),
}


def skip_reason(*names: str) -> str | None:
    """Why the targets ``names`` cannot run here (one line saying what to install), or None."""
    missing = sorted({p for n in names for p in TARGETS[n].missing()})
    if not missing:
        return None
    return f"no ARM toolchain or QEMU ({', '.join(missing)} missing): {INSTALL}"


def generate(spec: str, precision: str, folder: Path) -> None:
    """Write the C backend's ``<name>.c`` and ``<name>.h`` of ``spec`` in ``precision``.

    Raises
    ------
    LookupError
        When this checkout's C backend has no such precision.
    """
    from tvopt_codegen.backends import BACKENDS  # noqa: PLC0415 - sympy only when asked
    from tvopt_codegen.derivation import derive  # noqa: PLC0415
    from tvopt_codegen.lowering.ir import lower  # noqa: PLC0415
    from tvopt_codegen.renderer.rendering import render  # noqa: PLC0415
    from tvopt_codegen.spec import load_spec  # noqa: PLC0415

    backend = BACKENDS["c"]
    if precision != "double":
        try:
            from tvopt_codegen.backends.c import with_precision  # noqa: PLC0415
        except ImportError as exc:
            raise LookupError(f"the C backend has no --precision {precision}") from exc
        backend = with_precision(precision)
    files = render(lower(derive(load_spec(spec))), backend)
    folder.mkdir(parents=True, exist_ok=True)
    for name, text in files.items():
        if name.endswith((".c", ".h")) and not name.endswith(".ext.c"):
            (folder / name).write_text(text, encoding="utf-8")


def _run(command: list[str], timeout: float = 120.0, env: dict[str, str] | None = None) -> str:
    environment = {**os.environ, **env} if env else None
    done = subprocess.run(
        command, capture_output=True, text=True, timeout=timeout, check=False, env=environment
    )
    if done.returncode != 0:
        raise RuntimeError(
            f"{' '.join(command)} exited {done.returncode}:\n{done.stdout}\n{done.stderr}"
        )
    return done.stdout


def compile_object(target: Target, source: Path, out: Path, *extra: str) -> Path:
    """Compile one C file for ``target`` (the harness's flags, plus ``extra``)."""
    _run([target.cc, *COMMON_FLAGS, *target.flags, *extra, "-c", str(source), "-o", str(out)])
    return out


def assembly_command(target: Target, source: Path, out: Path, *extra: str) -> list[str]:
    """The command of :func:`compile_assembly` (for a caller that runs it its own way)."""
    return [target.cc, *COMMON_FLAGS, *target.flags, *extra, "-S", str(source), "-o", str(out)]


def compile_assembly(target: Target, source: Path, out: Path, *extra: str) -> Path:
    """Compile one C file for ``target`` to assembly, as :func:`compile_object` compiles it.

    For a build read for what the compiler reports (``-fcallgraph-info``, warnings): the
    assembler's run is skipped, and :func:`assemble` makes the very object
    :func:`compile_object` would (gcc's ``-c`` is this, then the assembler).
    """
    _run(assembly_command(target, source, out, *extra))
    return out


def assemble(target: Target, assembly: Path, out: Path) -> Path:
    """The object of ``assembly`` (:func:`compile_assembly`'s) for ``target``."""
    _run([target.cc, *target.flags, "-c", str(assembly), "-o", str(out)])
    return out


@dataclass(frozen=True)
class CallGraph:
    """gcc's ``-fcallgraph-info=su`` graph of one object file (VCG).

    Attributes
    ----------
    names : dict
        Each node's function name.
    frames : dict
        Each node's static frame in bytes: 0 for a function the file does not define
        (libm, libgcc), which has no frame in the graph.
    calls : dict
        Each node's callees.
    own : frozenset
        The nodes of the file's own functions (gcc gives each a frame, 0 bytes or more).
    """

    names: dict[str, str]
    frames: dict[str, int]
    calls: dict[str, list[str]]
    own: frozenset[str]

    @classmethod
    def read(cls, path: Path) -> CallGraph:
        """The graph gcc wrote to ``path`` (the object's ``.ci`` file)."""
        text = path.read_text(encoding="utf-8")
        names: dict[str, str] = {}
        frames: dict[str, int] = {}
        own: set[str] = set()
        for title, label in re.findall(r'node: \{ title: "([^"]+)" label: "([^"]+)"', text):
            names[title] = label.split("\\n")[0]
            size = re.search(r"(\d+) bytes", label)
            frames[title] = int(size.group(1)) if size else 0
            if size:
                own.add(title)
        calls: dict[str, list[str]] = {}
        edges = r'edge: \{ sourcename: "([^"]+)" targetname: "([^"]+)"'
        for source, target in re.findall(edges, text):
            calls.setdefault(source, []).append(target)
        return cls(names, frames, calls, frozenset(own))

    def deepest(self, node: str) -> tuple[int, list[str]]:
        """The largest sum of static frames along a call path from ``node``, and the path.

        Raises
        ------
        RuntimeError
            On recursion (a cycle in the graph), naming the cycle.
        """
        memo: dict[str, tuple[int, list[str]]] = {}

        def visit(at: str, path: tuple[str, ...]) -> tuple[int, list[str]]:
            if at in path:
                cycle = " -> ".join(self.names.get(n, n) for n in (*path, at))
                raise RuntimeError(f"recursion: {cycle}")
            if at not in memo:
                below = [visit(callee, (*path, at)) for callee in self.calls.get(at, [])]
                best = max(below, default=(0, []))
                memo[at] = (self.frames.get(at, 0) + best[0], [self.names.get(at, at), *best[1]])
            return memo[at]

        return visit(node, ())


def renamed_plant(target: Target, name: str, double: Path, out: Path) -> Path:
    """The object ``double`` (the double-precision C) with ``harness_plant`` its only entry.

    The plant runs in double whatever the controller's precision: its object is the
    double C's with ``<name>_plant`` renamed ``harness_plant`` and every other global
    symbol given a prefix, so that it links beside the controller's object.
    """
    listed = _run([target.tool("nm"), "-g", "--defined-only", "--format=posix", str(double)])
    renames = []
    for row in listed.splitlines():
        symbol = row.split()[0]
        new = "harness_plant" if symbol == f"{name}_plant" else f"harness_double_{symbol}"
        renames.append(f"{symbol} {new}")
    table = out.with_suffix(".renames")
    table.write_text("\n".join(renames) + "\n", encoding="utf-8")
    _run([target.tool("objcopy"), f"--redefine-syms={table}", str(double), str(out)])
    return out


@dataclass(frozen=True)
class Loop:
    """The closed loop's timing: RATE Hz steps, SUBSTEPS RK4 steps each, STEPS steps."""

    rate: int = 100
    steps: int = 100
    substeps: int = 4
    every: int = 10

    def defines(self) -> list[str]:
        return [
            f"-DRATE={self.rate}",
            f"-DSTEPS={self.steps}",
            f"-DSUBSTEPS={self.substeps}",
            f"-DEVERY={self.every}",
        ]


def build_loop(
    target: Target,
    name: str,
    controller: Path,
    double: Path,
    precision: str,
    folder: Path,
    loop: Loop = Loop(),  # noqa: B008 - frozen
    main: str = "loop.c",
    defines: tuple[str, ...] = (),
    controller_flags: tuple[str, ...] = (),
    objects: Mapping[str, Path] | None = None,
    support: Sequence[Path] | None = None,
) -> Path:
    """Compile and link a harness program (``loop.c`` or ``bench.c``) of ``name`` for ``target``.

    Parameters
    ----------
    controller
        The folder of the controller's generated C (in ``precision``).
    double
        The folder of the double-precision generated C (the plant).
    precision
        ``double`` or ``single``: the type the harness gives the controller.
    folder
        Where the objects and the binary go.
    loop
        The closed loop's timing.
    main
        The program's file in this folder.
    defines
        More ``-D`` options of the program.
    controller_flags
        More options of the controller's compilation (``-fstack-usage``).
    objects
        Objects already compiled for ``target`` with the harness's flags, by role:
        ``double`` (the double-precision C) and ``controller`` (the C in ``precision``);
        a role not given is compiled here.
    support
        The start-up objects (:func:`support_objects`) already compiled for ``target``;
        compiled here if not given.
    """
    folder.mkdir(parents=True, exist_ok=True)
    real = "double" if precision == "double" else "float"
    given = dict(objects or {})
    double_object = given.get("double") or compile_object(
        target, double / f"{name}.c", folder / "double.o", f"-I{double}"
    )
    if "controller" in given:
        controller_object = given["controller"]
    elif precision == "double" and not controller_flags:
        controller_object = double_object
    else:
        controller_object = compile_object(
            target,
            controller / f"{name}.c",
            folder / "controller.o",
            f"-I{controller}",
            *controller_flags,
        )
    linked = [
        controller_object,
        renamed_plant(target, name, double_object, folder / "plant.o"),
        compile_object(
            target,
            HERE / main,
            folder / "main.o",
            f"-I{controller}",
            f"-I{HERE}",
            f"-DNAME={name}",
            f"-DUNAME={name.upper()}",
            f"-DREAL={real}",
            *loop.defines(),
            *defines,
        ),
        *(support_objects(target, folder) if support is None else support),
    ]
    binary = folder / f"{name}.elf"
    _run([target.cc, *target.flags, *map(str, linked), "-o", str(binary), *target.link])
    return binary


def support_objects(target: Target, folder: Path) -> list[Path]:
    """The harness's files every program of ``target`` links, compiled into ``folder``.

    ``semihost.c`` (the output), and on bare metal ``startup.c`` (the vector table and
    reset handler): the same objects for every example, so they may be compiled once.
    """
    built = [compile_object(target, HERE / "semihost.c", folder / "semihost.o")]
    if target.bare:
        built.append(compile_object(target, HERE / "startup.c", folder / "startup.o", f"-I{HERE}"))
    return built


def run(
    target: Target,
    binary: Path,
    *qemu: str,
    timeout: float = 300.0,
    env: dict[str, str] | None = None,
) -> str:
    """Run ``binary`` on ``target`` and return its output.

    ``qemu`` adds options to a QEMU runner (``-icount shift=0``); ``env`` adds variables
    to the environment.
    """
    if not target.runner:
        return _run([str(binary)], timeout, env)
    return _run([target.runner[0], *qemu, *target.runner[1:], str(binary)], timeout, env)


@dataclass(frozen=True)
class Trace:
    """A closed loop's records: step, time, plant state and input at each."""

    steps: np.ndarray
    t: np.ndarray
    x: np.ndarray
    u: np.ndarray


def parse(text: str, n_x: int) -> Trace:
    """Read ``loop.c``'s output (every number the 16 hex digits of a double's bits).

    Raises
    ------
    RuntimeError
        When a step failed or the output stops before ``end``.
    """
    rows = []
    lines = text.splitlines()
    if not lines or lines[-1] != "end":
        raise RuntimeError(f"the loop did not finish:\n{text[-2000:]}")
    for row in lines[:-1]:
        words = row.split()
        if words[0] != "s":
            raise RuntimeError(f"the loop reported: {row}")
        bits = np.array([int(w, 16) for w in words[2:]], dtype=np.uint64)
        rows.append((int(words[1]), bits.view(np.float64)))
    values = np.array([r[1] for r in rows])
    return Trace(
        steps=np.array([r[0] for r in rows]),
        t=values[:, 0],
        x=values[:, 1 : 1 + n_x],
        u=values[:, 1 + n_x :],
    )


def plant_states(header: Path, name: str) -> int:
    """``<NAME>_N_PLANT_STATES`` of a generated header."""
    key = f"#define {name.upper()}_N_PLANT_STATES "
    for row in header.read_text(encoding="utf-8").splitlines():
        if row.startswith(key):
            return int(row.removeprefix(key))
    raise ValueError(f"{header} has no {key.strip()}")
