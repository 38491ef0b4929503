"""The controller on a Cortex-M4F: instructions per call, memory and stack, double against single.

Every bundled example's C controller, in double and in single precision, compiled for a
Cortex-M4F (``-mcpu=cortex-m4 -mfpu=fpv4-sp-d16 -mfloat-abi=hard -O2 -ffp-contract=off``)
and run bare metal under ``qemu-system-arm -M mps2-an386 -icount shift=0``, with the
harness of ``tests/embedded`` (``bench.c``: the text there says how SysTick counts
instructions under ``-icount``). Beside them, CasADi's generated C of the same law
(``benchmarks/bench_c.py``'s ``casadi_law``; for mass-matrix plants and equalities,
``benchmarks/casadi_peers.py``'s ``casadi_peer_law``) with ``casadi_real`` double and
float. And what single precision costs in accuracy: ``loop.c``'s closed loop with the M4F's
single-precision controller against the x86-64 host's double one.

Run: ``make bench-embedded`` (needs the ARM toolchain and QEMU, ``.ci/run``'s apt-get
line, and the ``bench`` extra for CasADi). Prints the tables and, with ``--write FILE``,
stores them with the command, the tools' versions and the date.
"""

from __future__ import annotations

import argparse
import dataclasses
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))
from tests.embedded.harness import (  # noqa: E402
    COMMON_FLAGS,
    HERE,
    TARGETS,
    CallGraph,
    Loop,
    Trace,
    build_loop,
    compile_object,
    generate,
    parse,
    plant_states,
    run,
    skip_reason,
)

#: Every bundled example (``tvopt_codegen/examples``; main() checks that none is missing):
#: the Makefile's EXAMPLES first, then the others, each ``*_refs`` twin last.
EXAMPLES = (
    "integrator",
    "unicycle_switch",
    "two_unicycles_barrier",
    "pvtol",
    "flexible_joint",
    "unicycle_ring",
    "arm_on_line",
    "planar_arm3",
    "drag_vehicle",
    "two_unicycles_corridor",
    "ur5_tip",
    "integrator_refs",
    "unicycle_switch_refs",
    "two_unicycles_barrier_refs",
    "pvtol_refs",
    "unicycle_ring_refs",
)
#: Examples whose CasADi peer is ``casadi_peers.casadi_peer_law`` (mass-matrix plants:
#: ``ca.solve(M, [F B])``; an equality: the KKT law with its multiplier chains), not
#: ``bench_c.casadi_law``, which takes f and G explicitly and has no multipliers.
PEER_LAW = frozenset({"arm_on_line", "planar_arm3", "ur5_tip"})
#: `control` calls timed in one interval; the closed loop's steps (100 Hz, 1 s).
CALLS = 100
LOOP = Loop(rate=100, steps=100, substeps=4, every=10)
M4F = TARGETS["m4f"]
ICOUNT = ("-icount", "shift=0")

#: Undefined symbols that mean double arithmetic: libgcc's software double (AEABI) and
#: the double functions of <math.h>.
_DOUBLE_LIBM = frozenset(
    "sin cos tan asin acos atan atan2 sinh cosh tanh asinh acosh atanh exp log log1p expm1 "
    "sqrt pow fabs hypot cbrt floor ceil fmod".split()
)


def _double_symbols(obj: Path) -> list[str]:
    """The symbols ``obj`` calls that compute in double."""
    listed = subprocess.run(
        [M4F.tool("nm"), "-u", "--format=posix", str(obj)],
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    names = [row.split()[0] for row in listed.splitlines() if row.strip()]
    return sorted(
        n
        for n in names
        if n in _DOUBLE_LIBM
        or (n.startswith("__aeabi_") and ("d" in n.removeprefix("__aeabi_")[:3]))
    )


def _size(path: Path) -> tuple[int, int, int]:
    """``.text``, ``.data``, ``.bss`` of an object or image (Berkeley format)."""
    out = subprocess.run(
        [M4F.tool("size"), str(path)], capture_output=True, text=True, check=True
    ).stdout
    text, data, bss = (int(v) for v in out.splitlines()[1].split()[:3])
    return text, data, bss


def _records(output: str) -> dict[str, list[int]]:
    records = {}
    for row in output.splitlines():
        words = row.split()
        if words and words[0] not in ("end",):
            if words[0].startswith("fail"):
                raise RuntimeError(f"the benchmark reported: {row}")
            records[words[0]] = [int(w) for w in words[1:]]
    return records


def _per_tick(records: dict[str, list[int]]) -> float:
    """Instructions per SysTick tick, from the calibration loop (2 instructions an iteration)."""
    iterations, ticks = records["calibrate"]
    return 2 * iterations / ticks


def _deepest_stack(callgraph: Path, roots: tuple[str, ...]) -> tuple[int, list[str]]:
    """The largest sum of static frames along a call path from ``roots`` (-fcallgraph-info=su).

    Library functions (libm, libgcc) have no frame in the file's graph: they count 0
    here; the measured stack includes them.
    """
    graph = CallGraph.read(callgraph)
    return max(graph.deepest(node) for node, name in graph.names.items() if name in roots)


@dataclass
class Row:
    """One build's measures."""

    example: str
    build: str
    control: float
    step: float | None
    obj: tuple[int, int, int]
    image: tuple[int, int, int] | None
    stack: int
    static_stack: int | None
    doubles: list[str]
    per_tick: float


def _image(folder: Path, objects: list[Path], name: str) -> Path:
    """Link a bare-metal M4F image of ``objects`` with the start-up file and semihosting."""
    objects = [
        *objects,
        compile_object(M4F, HERE / "semihost.c", folder / "semihost.o"),
        compile_object(M4F, HERE / "startup.c", folder / "startup.o", f"-I{HERE}"),
    ]
    binary = folder / name
    subprocess.run(
        [M4F.cc, *M4F.flags, *map(str, objects), "-o", str(binary), *M4F.link],
        check=True,
        capture_output=True,
    )
    return binary


@dataclass(frozen=True)
class Jets:
    """The references' jets an example's calls take: the nominal closed forms' (exact).

    Attributes
    ----------
    half : list of float
        At t = 0.5 (the ``control`` calls), row after row as the C functions take them.
    start : list of float
        At t = 0 (the footprint program's init and step).
    steps : list of list of float
        At each step's time ``k / LOOP.rate`` of the closed loop.
    at : callable
        The jets at any time t (the accuracy loop's steps).
    """

    half: list[float]
    start: list[float]
    steps: list[list[float]]
    at: Callable[[float], list[float]]


def nominal_jets(example: str) -> Jets | None:
    """The jets of ``example``'s nominal references (None: it has no references)."""
    from tvopt_codegen.derivation import derive  # noqa: PLC0415 - sympy only when asked
    from tvopt_codegen.simulation.references import exact_jets  # noqa: PLC0415
    from tvopt_codegen.spec import load_spec  # noqa: PLC0415

    d = derive(load_spec(example))
    if not d.model.references:
        return None
    jets = exact_jets(d, {})

    def at(t: float) -> list[float]:
        return [float(v) for v in jets(t).ravel()]

    return Jets(
        half=at(0.5),
        start=at(0.0),
        steps=[at(k / LOOP.rate) for k in range(LOOP.steps)],
        at=at,
    )


def _literal(values: list[float]) -> str:
    """A C initializer of ``values`` (double literals that round-trip)."""
    return "{" + ", ".join(repr(v) for v in values) + "}"


def _refs_header(jets: Jets, folder: Path) -> Path:
    """Write bench.c's ``refs.h``: the jets at t = 0.5 and at every step's time."""
    width = len(jets.half)
    rows = ",\n    ".join(_literal(row) for row in jets.steps)
    (folder / "refs.h").write_text(
        "/* The references' jets (the nominal closed forms'), written by bench_embedded.py. */\n"
        f"static const REAL refs_half[{width}] = {_literal(jets.half)};\n"
        f"static const REAL refs_steps[{len(jets.steps)}][{width}] = {{\n    {rows}\n}};\n",
        encoding="utf-8",
    )
    return folder


def ours(
    example: str, precision: str, generated: Path, folder: Path, jets: Jets | None = None
) -> Row:
    """Our controller of ``example`` in ``precision`` on the M4F (``jets``: its references')."""
    c_folder = generated / example / precision
    double = generated / example / "double"
    folder.mkdir(parents=True, exist_ok=True)
    refs = ("-DREFS", f"-I{_refs_header(jets, folder)}") if jets else ()
    binary = build_loop(
        M4F,
        example,
        c_folder,
        double,
        precision,
        folder,
        LOOP,
        main="bench.c",
        defines=(f"-DCALLS={CALLS}", *refs),
        controller_flags=("-fstack-usage", "-fcallgraph-info=su"),
    )
    records = _records(run(M4F, binary, *ICOUNT))
    per_tick = _per_tick(records)
    calls, ticks = records["control"]
    steps, step_ticks = records["step"]
    controller = folder / "controller.o"
    real = "double" if precision == "double" else "float"
    footprint = _image(
        folder,
        [
            controller,
            compile_object(
                M4F,
                HERE / "footprint.c",
                folder / "footprint.o",
                f"-I{c_folder}",
                f"-I{HERE}",
                f"-DNAME={example}",
                f"-DUNAME={example.upper()}",
                f"-DREAL={real}",
                *((f"-DREFS={_literal(jets.start)}",) if jets else ()),
            ),
        ],
        "footprint.elf",
    )
    static, _ = _deepest_stack(
        folder / "controller.ci", (f"{example}_controller_step", f"{example}_control")
    )
    return Row(
        example=example,
        build=f"ours, {precision}",
        control=ticks * per_tick / calls,
        step=step_ticks * per_tick / steps,
        obj=_size(controller),
        image=_size(footprint),
        stack=records["stack"][0],
        static_stack=static,
        doubles=_double_symbols(controller),
        per_tick=per_tick,
    )


#: The accuracy loop: tests/test_embedded_qemu.py's closed loop (100 Hz, RK4 at 400 Hz,
#: 2 s from the spec's initial state), recorded every 0.1 s.
ACCURACY_LOOP = Loop(rate=100, steps=200, substeps=4, every=10)
#: The loop of the examples whose 100 Hz loop is decided by its sampling, not by the
#: precision (the barriers' sharp turns): 1 kHz, the same 2 s and records.
FAST_LOOP = Loop(rate=1000, steps=2000, substeps=4, every=100)
SAMPLING_DECIDES = ("two_unicycles_barrier", "two_unicycles_corridor", "two_unicycles_barrier_refs")
HOST = TARGETS["host"]


@dataclass(frozen=True)
class Accuracy:
    """The M4F's single-precision closed loop against the host's double one.

    Attributes
    ----------
    example : str
        The bundled example.
    rate : int
        The controller's rate (Hz).
    state, input : float
        The largest difference of the plant state and of the input at the records.
    state_scale, input_scale : float
        The largest magnitude of the double loop's plant state and input at the records.
    slow : Accuracy or None
        For an example of :data:`SAMPLING_DECIDES`, the same measure at 100 Hz.
    sampling : float or None
        For those, the largest state difference of the double loops at 100 Hz and at
        ``rate`` (the sampling's effect, beside the precision's).
    """

    example: str
    rate: int
    state: float
    input: float
    state_scale: float
    input_scale: float
    slow: Accuracy | None = None
    sampling: float | None = None


def _loop_refs(jets: Jets, loop: Loop, folder: Path) -> Path:
    """Write loop.c's ``loop_refs.h``: the jets at each step's time ``k / loop.rate``."""
    rows = [jets.at(k / loop.rate) for k in range(loop.steps + 1)]
    body = ",\n    ".join(_literal(row) for row in rows)
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "loop_refs.h").write_text(
        "/* The references' jets (the nominal closed forms'), written by bench_embedded.py. */\n"
        f"static const REAL refs_at[{len(rows)}][{len(rows[0])}] = {{\n    {body}\n}};\n",
        encoding="utf-8",
    )
    return folder


def _accuracy_at(
    example: str, generated: Path, folder: Path, jets: Jets | None, loop: Loop
) -> tuple[Accuracy, Trace]:
    """The measure of one loop timing, and the host's double trace."""
    double = generated / example / "double"
    refs = ("-DREFS", f"-I{_loop_refs(jets, loop, folder)}") if jets else ()
    n_x = plant_states(double / f"{example}.h", example)
    traces = {}
    for target, precision in ((HOST, "double"), (M4F, "single")):
        binary = build_loop(
            target,
            example,
            generated / example / precision,
            double,
            precision,
            folder / target.name,
            loop,
            defines=refs,
        )
        traces[target.name] = parse(run(target, binary), n_x)
    host, m4f = traces["host"], traces["m4f"]
    measure = Accuracy(
        example=example,
        rate=loop.rate,
        state=float(np.max(np.abs(m4f.x - host.x))),
        input=float(np.max(np.abs(m4f.u - host.u))),
        state_scale=float(np.max(np.abs(host.x))),
        input_scale=float(np.max(np.abs(host.u))),
    )
    return measure, host


def accuracy(example: str, generated: Path, folder: Path, jets: Jets | None) -> Accuracy:
    """``example``'s closed loop, the M4F in single against the host in double.

    ``generated`` holds the example's C in both precisions (``<example>/<precision>``).
    """
    if example not in SAMPLING_DECIDES:
        return _accuracy_at(example, generated, folder / "100", jets, ACCURACY_LOOP)[0]
    slow, slow_host = _accuracy_at(example, generated, folder / "100", jets, ACCURACY_LOOP)
    fast, fast_host = _accuracy_at(example, generated, folder / "fast", jets, FAST_LOOP)
    # Both record every 0.1 s: the same times.
    assert np.array_equal(slow_host.t, fast_host.t)
    sampling = float(np.max(np.abs(slow_host.x - fast_host.x)))
    return dataclasses.replace(fast, slow=slow, sampling=sampling)


def _g(value: float) -> str:
    """Two significant digits, as the docs write them (``2.2e-8``, ``0.53``, ``220``)."""
    if value != 0.0 and abs(value) < 1e-2:
        mantissa, exponent = f"{value:.1e}".split("e")
        return f"{mantissa.rstrip('0').rstrip('.')}e{int(exponent)}"
    return f"{float(f'{value:.2g}'):g}"


def accuracy_table(measures: list[Accuracy]) -> str:
    """The Markdown table of the accuracy loop, one row an example."""
    lines = [
        "| example | state | input | state scale | input scale |",
        "|---|---|---|---|---|",
    ]
    for a in measures:
        name = (
            a.example if a.rate == ACCURACY_LOOP.rate else f"{a.example}, at {a.rate // 1000} kHz"
        )
        lines.append(
            f"| {name} | {_g(a.state)} | {_g(a.input)} | {_g(a.state_scale)} | "
            f"{_g(a.input_scale)} |"
        )
    return "\n".join(lines)


def casadi_refs_law(d: Any) -> Any:
    """``bench_c.casadi_law`` of a spec with references measured at run time.

    The same construction (CasADi's own AD: Lie derivatives by ``jtimes``, the gradient's
    jet by ``jtimes`` along (t, y, y', ..., r, r', ...), its symbolic ``solve``), with each
    reference a symbol whose time derivative is the next entry of its jet. The jets are a
    fourth argument laid out as our C functions take them: reference after reference, its
    derivatives 0 .. REFERENCE_ORDER.
    """
    import casadi as ca  # noqa: PLC0415 - the bench extra
    from casadi_peer import _to_casadi  # noqa: PLC0415

    assert d.dynamics.uniform, "the benchmark builds uniform-relative-degree laws only"
    model, ext = d.model, d.linearization.extension
    n, m, k = len(ext.x), len(model.y), d.dynamics.k
    refs, q = list(model.references), d.jet.reference_order
    assert q >= k - 1, "the gradient's jet reads a reference derivative beyond the jets"
    t = ca.SX.sym("t")
    X = ca.SX.sym("X", n)
    P = ca.SX.sym("P", max(1, len(model.params)))
    jets = ca.SX.sym("J", len(refs) * (q + 1))
    # R[i, j]: reference i's j-th derivative; those beyond q the law never reads (zero).
    R = ca.vertcat(
        *[
            ca.horzcat(*[jets[i * (q + 1) + j] if j <= q else ca.SX(0) for j in range(k + 1)])
            for i in range(len(refs))
        ]
    )
    base = [*ext.x, *model.params]
    values = [X[i] for i in range(n)] + [P[i] for i in range(len(model.params))]
    f = ca.vertcat(*[_to_casadi(e, base, values) for e in ext.f])
    G = ca.horzcat(
        *[ca.vertcat(*[_to_casadi(ext.G[i, j], base, values) for i in range(n)]) for j in range(m)]
    )
    h = [_to_casadi(e, base, values) for e in model.h]
    now = [t, *(R[i, 0] for i in range(len(refs))), *values[n:]]
    signal_values = [_to_casadi(e, [model.t, *refs, *model.params], now) for _, e in model.signals]
    Y = ca.SX.sym("Y", m, k + 1)
    f0 = _to_casadi(
        model.f0,
        [*model.y, *(s for s, _ in model.signals), *refs, *model.params, model.t],
        [*(Y[i, 0] for i in range(m)), *signal_values, *now[1:], t],
    )
    jet = [ca.gradient(f0, Y[:, 0])]
    moving = ca.vertcat(t, ca.vec(Y[:, :k]), ca.vec(R[:, :k]))
    rates = ca.vertcat(1, ca.vec(Y[:, 1:]), ca.vec(R[:, 1:]))
    for _ in range(k):
        jet.append(ca.jtimes(jet[-1], moving, rates))
    rest = ca.substitute(jet[k], Y[:, k], ca.DM.zeros(m))
    hess = ca.hessian(f0, Y[:, 0])[0]
    c = sum(d.dynamics.coefficients[j] * jet[j] for j in range(k)) - rest
    lie, rows, p = [], [], []
    for i in range(m):
        chain = [h[i]]
        for _ in range(k):
            chain.append(ca.jtimes(chain[-1], X, f))
        lie.append(chain[:k])
        rows.append(ca.mtimes(ca.jacobian(chain[k - 1], X), G))
        p.append(chain[k])
    state_jet = ca.vertcat(*[lie[i][j] for j in range(k) for i in range(m)])
    c = ca.substitute(c, ca.vec(Y[:, :k]), state_jet)
    hess = ca.substitute(hess, ca.vec(Y[:, :k]), state_jet)
    w = ca.solve(ca.vertcat(*rows), ca.solve(hess, c) - ca.vertcat(*p))
    index = {s.name: i for i, s in enumerate(ext.x)}
    u = ca.vertcat(
        *[X[index[uj.name]] if uj.name in ext.states else w[j] for j, uj in enumerate(model.u)]
    )
    return ca.Function("casadi_law", [t, X, P, jets], [u])


def peer_law(example: str, d: Any) -> Any:
    """CasADi's law of ``example`` (without references): ``casadi_law``, or ``PEER_LAW``'s."""
    if example in PEER_LAW:
        from casadi_peers import casadi_peer_law  # noqa: PLC0415 - imports casadi

        return casadi_peer_law(d)
    from bench_c import casadi_law  # noqa: PLC0415 - imports casadi and cffi

    return casadi_law(d)


def check_peer(example: str, jets: Jets | None) -> None:
    """Check that CasADi's law of ``example`` is ours where the benchmark calls it.

    Raises
    ------
    RuntimeError
        When the two inputs differ by more than 1e-9 at t = 0.5, the default state.
    """
    import numpy as np  # noqa: PLC0415

    from tvopt_codegen.derivation import derive  # noqa: PLC0415
    from tvopt_codegen.lowering.ir import lower  # noqa: PLC0415
    from tvopt_codegen.simulation import load_controller  # noqa: PLC0415
    from tvopt_codegen.spec import load_spec  # noqa: PLC0415

    d = derive(load_spec(example))
    state = np.array(d.closed_loop.initial_state, dtype=float)
    params = [float(v) for _, v in d.spec.parameters] or [0.0]
    module = load_controller(lower(d), "python")
    if jets:
        peer = casadi_refs_law(d)(0.5, state, params, jets.half)
        width = len(jets.half) // len(d.model.references)
        ours_u = module.control(0.5, state, refs=np.reshape(jets.half, (-1, width)))
    else:
        peer = peer_law(example, d)(0.5, state, params)
        ours_u = module.control(0.5, state)
    gap = float(np.max(np.abs(np.ravel(np.array(peer)) - np.ravel(ours_u))))
    if not gap <= 1e-9:
        raise RuntimeError(f"{example}: CasADi's law differs from ours by {gap:.3g}")


def casadi_row(example: str, real: str, folder: Path, jets: Jets | None = None) -> Row:
    """CasADi's generated C of ``example``'s law with ``casadi_real`` = ``real`` on the M4F."""
    import casadi as ca  # noqa: PLC0415 - the bench extra

    from tvopt_codegen.derivation import derive  # noqa: PLC0415
    from tvopt_codegen.spec import load_spec  # noqa: PLC0415

    folder.mkdir(parents=True, exist_ok=True)
    d = derive(load_spec(example))
    generator = ca.CodeGenerator("casadi_law", {"with_header": True, "casadi_real": real})
    generator.add(casadi_refs_law(d) if jets else peer_law(example, d))
    generator.generate(str(folder) + "/")
    state = [float(v) for v in d.closed_loop.initial_state]
    params = [float(v) for _, v in d.spec.parameters] or [0.0]
    law = compile_object(M4F, folder / "casadi_law.c", folder / "casadi_law.o", f"-I{folder}")
    main = compile_object(
        M4F,
        HERE / "casadi_bench.c",
        folder / "casadi_bench.o",
        f"-I{folder}",
        f"-I{HERE}",
        "-DSTATE={" + ", ".join(repr(v) for v in state) + "}",
        "-DPARAMS={" + ", ".join(repr(v) for v in params) + "}",
        f"-DCALLS={CALLS}",
        *((f"-DREFS={_literal(jets.half)}",) if jets else ()),
    )
    records = _records(run(M4F, _image(folder, [law, main], "casadi.elf"), *ICOUNT))
    calls, ticks = records["control"]
    per_tick = _per_tick(records)
    return Row(
        example=example,
        build=f"CasADi, casadi_real {real}",
        control=ticks * per_tick / calls,
        step=None,
        obj=_size(law),
        image=None,
        stack=records["stack"][0],
        static_stack=None,
        doubles=_double_symbols(law),
        per_tick=per_tick,
    )


def _version(command: list[str]) -> str:
    out = subprocess.run(command, capture_output=True, text=True, check=False).stdout
    return out.splitlines()[0] if out else "?"


def table(rows: list[Row]) -> str:
    """The Markdown tables: per example, each build's measures, and single against double."""
    lines = [
        "| example | build | instructions / `control` | instructions / `Controller` step "
        "| object .text / .data / .bss (bytes) | image .text / .data / .bss | stack, measured "
        "| stack, -fstack-usage path | double routines called |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        step = f"{r.step:,.0f}" if r.step is not None else "(no stateful step)"
        image = " / ".join(f"{v:,}" for v in r.image) if r.image else ""
        static = f"{r.static_stack:,}" if r.static_stack is not None else ""
        more = ", ..." if len(r.doubles) > 4 else ""
        listed = "`, `".join(r.doubles[:4])
        doubles = f"{len(r.doubles)} (`{listed}`{more})" if r.doubles else "none"
        lines.append(
            f"| {r.example} | {r.build} | {r.control:,.0f} | {step} | "
            f"{' / '.join(f'{v:,}' for v in r.obj)} | {image} | {r.stack:,} | {static} | "
            f"{doubles} |"
        )
    lines += [
        "",
        "Single against double, and ours against CasADi's float-typedef C "
        "(instructions per `control` call; ratio below 1: fewer):",
        "",
        "| example | single / double (ours) | single / double, `Controller` step | "
        "ours single / CasADi float | ours double / CasADi double |",
        "|---|---|---|---|---|",
    ]
    by = {(r.example, r.build): r for r in rows}
    for example in dict.fromkeys(r.example for r in rows):
        single, double = by[(example, "ours, single")], by[(example, "ours, double")]
        cf = by.get((example, "CasADi, casadi_real float"))
        cd = by.get((example, "CasADi, casadi_real double"))
        assert single.step is not None and double.step is not None
        lines.append(
            f"| {example} | {single.control / double.control:.3f} | "
            f"{single.step / double.step:.3f} | "
            f"{f'{single.control / cf.control:.3f}' if cf else '(no peer)'} | "
            f"{f'{double.control / cd.control:.3f}' if cd else '(no peer)'} |"
        )
    return "\n".join(lines)


def main() -> int:
    """Measure every example, print the tables and optionally store them."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--write", type=Path, help="also store the tables in this Markdown file")
    parser.add_argument("--examples", nargs="*", default=list(EXAMPLES))
    args = parser.parse_args()
    from tvopt_codegen.spec.files import bundled_examples  # noqa: PLC0415

    missing = sorted(set(bundled_examples()) - set(EXAMPLES))
    if missing:
        print(f"bench_embedded.EXAMPLES lacks {', '.join(missing)}", file=sys.stderr)
        return 1
    reason = skip_reason("m4f", "host")
    if reason:
        print(reason, file=sys.stderr)
        return 1
    rows: list[Row] = []
    measures: list[Accuracy] = []
    with tempfile.TemporaryDirectory(prefix="tvopt-embedded-") as tmp:
        base = Path(tmp)
        for example in args.examples:
            for precision in ("double", "single"):
                generate(example, precision, base / "c" / example / precision)
            jets = nominal_jets(example)
            for precision in ("double", "single"):
                rows.append(ours(example, precision, base / "c", base / example / precision, jets))
            check_peer(example, jets)
            for real in ("double", "float"):
                rows.append(casadi_row(example, real, base / example / f"casadi-{real}", jets))
            measures.append(accuracy(example, base / "c", base / example / "accuracy", jets))
            print(f"{example}: done", file=sys.stderr)
    text = table(rows)
    print(text)
    print(accuracy_table(measures))
    if args.write:
        args.write.write_text(
            _document(text, rows) + "\n" + _accuracy_section(measures), encoding="utf-8"
        )
    return 0


def _document(text: str, rows: list[Row]) -> str:
    import casadi as ca  # noqa: PLC0415

    single = [r for r in rows if r.build == "ours, single"]
    double = {r.example: r for r in rows if r.build == "ours, double"}
    by = {(r.example, r.build): r for r in rows}
    worst = max(single, key=lambda r: r.control / double[r.example].control)
    peers = [
        (r.example, r.control / by[(r.example, "CasADi, casadi_real float")].control)
        for r in single
        if (r.example, "CasADi, casadi_real float") in by
    ]
    low, high = min(peers, key=lambda p: p[1]), max(peers, key=lambda p: p[1])
    worst_step = max(single, key=lambda r: (r.step or 0.0) / (double[r.example].step or 1.0))
    promoting = [r.example for r in single if r.doubles]
    no_double = (
        "calls no double routine"
        if not promoting
        else f"calls double routines in {', '.join(promoting)}"
    )
    flash = {id(r): r.image[0] + r.image[1] for r in rows if r.image}
    largest = max((r for r in rows if r.image), key=lambda r: flash[id(r)])
    deepest = max(rows, key=lambda r: r.stack)
    refs = [e for e in EXAMPLES if e.endswith("_refs")]
    rates = sorted({round(r.per_tick, 3) for r in rows})
    ticks = " or ".join(f"{v:g}" for v in rates)
    header = [
        "# The controller on a Cortex-M4F: instructions, memory, stack",
        "",
        "Command: `make bench-embedded` (`python benchmarks/bench_embedded.py --write "
        "benchmarks/EMBEDDED.md`).",
        f"Tools: {_version([M4F.cc, '--version'])}; "
        f"{_version(['qemu-system-arm', '--version'])}; casadi {ca.__version__}; "
        f"{time.strftime('%Y-%m-%d')}.",
        f"Flags: `{' '.join((*COMMON_FLAGS, *M4F.flags))}`; newlib's libm, libgcc's software "
        "double.",
        "",
        "**These are instructions, not cycles.** Each image runs under "
        "`qemu-system-arm -M mps2-an386 -icount shift=0`: QEMU advances its virtual clock "
        "by exactly 1 ns per executed instruction, and SysTick, clocked from the core clock, "
        f"ticks every {ticks} of them (measured in each image on a loop of a known "
        "instruction count: "
        "`tests/embedded/bench.c`). The counts repeat exactly from run to run; they are not "
        "cycles: QEMU models no pipeline, flash wait states or caches, nor the longer "
        "latencies of the FPU's divide and square root. A count includes the "
        "call, its arguments and the loop around it (a handful of instructions).",
        "",
        f"- `control`: {CALLS} calls at t = 0.5 s and the example's default closed-loop "
        "state (parameters NULL: the defaults); the count per call.",
        f"- `Controller` step: a closed loop of {LOOP.steps} steps at {LOOP.rate} Hz (the "
        "plant integrated in double by RK4 between them) records what each step is given; "
        "the controller is initialised again and the same steps are counted together; the "
        "mean. A step advances the controller's states and evaluates the law.",
        "- object: `arm-none-eabi-size` of the generated `<name>.c` alone (`.text` includes "
        "the constants). image: a program that runs `controller_init` and one "
        "`controller_step` and nothing else (`tests/embedded/footprint.c`), linked with "
        "the start-up file, `--gc-sections`, newlib's libm and libgcc: what the controller "
        "costs in flash with the library routines it pulls in.",
        "- stack, measured: the free stack painted, then `control`, `controller_init` and "
        "10 steps run, and the deepest word written found (libm and libgcc included). "
        "-fstack-usage path: the largest sum of the static frames `-fstack-usage "
        "-fcallgraph-info=su` reports along a call path from `controller_step` or "
        "`control` within the generated file (library routines count 0 there).",
        "- double routines called: the undefined symbols of the object that compute in "
        "double (libgcc's `__aeabi_d*` and `<math.h>`'s double functions). On the M4F each "
        "is software emulation.",
        f"- references ({', '.join(refs)}: `[references]`, measured at run time): "
        "`control`, `controller_init` and `controller_step` take the references' jets "
        "(docs/references.md). They are given the exact jets of the spec's nominal closed "
        "forms (`[references.nominal]`): at t = 0.5 for `control`, at each step's time "
        "for the closed loop's steps (`refs.h`, written per example), at t = 0 in the "
        "footprint program. With exact jets each is the law of its closed-form twin "
        "(`tests/test_references.py`); the jets replace the twin's closed forms of t, so "
        "the call does not evaluate them.",
        "- drag_vehicle: the bundled spec has no `[robust.eso]` table (its description "
        "names the observer as the remedy for a mismatched plant, docs/robust.md), so its "
        "C is the plain law with its integrator chain, like the others.",
        f"- memory: the largest image ({largest.example}, {largest.build}: "
        f"{flash[id(largest)]:,} bytes of flash; ur5_tip's generated C is "
        "the largest source) and the deepest stack "
        f"({deepest.example}, {deepest.build}: {deepest.stack:,} bytes) fit the board's "
        "4 MB of code memory and 4 MB of RAM (`tests/embedded/mps2_an386.ld`) many times "
        "over.",
        "- CasADi: `benchmarks/bench_c.py`'s `casadi_law` (the same plant, outputs and "
        "objective, derived by CasADi's AD), generated by `casadi.CodeGenerator` with "
        "`casadi_real` set to `double` or `float`, compiled with the same flags; its call "
        "is `casadi_law(arg, res, iw, w, 0)` at the same state (and for the `*_refs` "
        "examples the same jets: `casadi_refs_law` here builds the law the same way with "
        "each reference a symbol whose time derivative is the next entry of its jet, the "
        "jets a fourth argument). Before it is timed, each CasADi law is evaluated at that "
        "point and checked against our controller's `control` there (1e-9). CasADi has no "
        "stateful controller: no step column.",
        "- CasADi, mass-matrix plants (planar_arm3, ur5_tip) and the equality (arm_on_line): "
        "`benchmarks/casadi_peers.py`'s `casadi_peer_law`, casadi_law's construction with "
        "two additions. For `M(q) q'' = F + B u`, `M`, `F`, `B` (after the spec's "
        "definitions, ur5_tip's Newton-Euler vectors) are CasADi expressions and "
        "`[M^-1 F, M^-1 B] = ca.solve(M, [F B])`, one solve of every right-hand side: what "
        "a CasADi user writes for forward dynamics, and what casadi_law uses for the "
        "Hessian and R. On SX CasADi expands it: up to 3 x 3 into the adjugate over the "
        "determinant (planar_arm3's `M`), above into a QR factorization whose C calls "
        "`sqrt` (ur5_tip's 6 x 6 `M`); a hand-written LDL^T would be our factorization "
        "translated, not CasADi's. For the equality, the law is the paper's law for "
        "`L = f0 + nu a` over `(y, nu)` as our derivation defines it (docs/constraints.md): "
        "`L`'s gradient (the KKT map) differentiated along t, the outputs' jets and the "
        "multiplier's chain, whose states `nu_on_line_0`, `nu_on_line_1` follow the "
        "plant's in the CasADi law's state argument as in our `control`'s, and "
        "`(y'', nu'') = K^-1 [...]` by `ca.solve` of the 3 x 3 KKT matrix `K`; the law "
        "returns the inputs, not `nu''`, as `control` does.",
        "",
        f"Single precision costs at most {worst.control / double[worst.example].control:.3f} "
        f"of double's instructions per `control` call on every one of the {len(single)} "
        f"examples (the largest ratio: {worst.example}; the issue's target is 1/10), at "
        f"most {(worst_step.step or 0.0) / (double[worst_step.example].step or 1.0):.3f} "
        f"per `Controller` step ({worst_step.example}), and {no_double}. CasADi's C with "
        "`casadi_real` float still calls double ones where it has a literal or a function "
        "of <math.h> (the last column): our single-precision call takes "
        f"{low[1]:.3f} ({low[0]}) to {high[1]:.3f} ({high[0]}) of its instructions.",
        "",
    ]
    return "\n".join(header) + "\n" + text + "\n"


def _accuracy_section(measures: list[Accuracy]) -> str:
    """EMBEDDED.md's section on what single precision costs in accuracy."""
    plain = [a for a in measures if a.slow is None]
    lines = [
        "## What single precision costs in accuracy",
        "",
        "The closed loop of `tests/embedded/loop.c` (`tests/test_embedded_qemu.py`'s: the "
        f"controller at {ACCURACY_LOOP.rate} Hz, the plant in double by RK4 at "
        f"{ACCURACY_LOOP.rate * ACCURACY_LOOP.substeps} Hz, "
        f"{ACCURACY_LOOP.steps // ACCURACY_LOOP.rate} s from the spec's initial state), the "
        "Cortex-M4F's single-precision controller (the same double plant, on the M4F) against "
        "the x86-64 host's double loop: the largest difference of the plant state and of the "
        f"input at the loop's records (every {ACCURACY_LOOP.every / ACCURACY_LOOP.rate:g} s, "
        f"{ACCURACY_LOOP.steps // ACCURACY_LOOP.every + 1} of them), and the scales, the "
        "largest magnitude of the double loop's state and input there. The `*_refs` "
        "examples' steps take the exact jets of their nominal closed forms at each step's "
        "time (`loop_refs.h`, written per example), so each loop is, up "
        "to rounding, its closed-form twin's.",
        "",
    ]
    if plain:
        worst = max(plain, key=lambda a: max(a.state / a.state_scale, a.input / a.input_scale))
        relative = max(worst.state / worst.state_scale, worst.input / worst.input_scale)
        lines += [
            f"Single precision stays within {_g(relative)} times the scale on every example "
            f"but the barrier loops below (the largest: {worst.example}).",
            "",
        ]
    fast = [a for a in measures if a.slow is not None and a.sampling is not None]
    if fast:
        lines += [
            f"{', '.join(a.example for a in fast)} are measured at {FAST_LOOP.rate // 1000} "
            f"kHz (RK4 at {FAST_LOOP.rate * FAST_LOOP.substeps // 1000} kHz, records at the "
            f"same times) because at {ACCURACY_LOOP.rate} Hz their sampled loops, not the "
            "precision, decide: the barrier's sharp turns are sampled too coarsely, so that "
            "single precision's small differences grow across a turn, and the double "
            f"loop at {ACCURACY_LOOP.rate} Hz is itself far from the one at "
            f"{FAST_LOOP.rate // 1000} kHz. At {ACCURACY_LOOP.rate} Hz:",
            "",
            "| example | single against double: state | input | double at "
            f"{ACCURACY_LOOP.rate} Hz against {FAST_LOOP.rate // 1000} kHz: state | state "
            "scale | input scale |",
            "|---|---|---|---|---|---|",
        ]
        for a in fast:
            assert a.slow is not None and a.sampling is not None
            lines.append(
                f"| {a.example} | {_g(a.slow.state)} | {_g(a.slow.input)} | "
                f"{_g(a.sampling)} | {_g(a.slow.state_scale)} | {_g(a.slow.input_scale)} |"
            )
        lines += ["", "Every example, measured:"]
    lines += ["", accuracy_table(measures), ""]
    return "\n".join(lines)


if __name__ == "__main__":
    sys.exit(main())
