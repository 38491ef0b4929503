"""tvopt-codegen's controllers against CasADi building the same law, side by side in one run.

CasADi gets the same plant, outputs, signals and objective (translated from the spec's
sympy expressions to SX) and derives the law with its own AD: Lie derivatives by
``jtimes``, the gradient jet by ``jtimes`` along (t, y, y', ...), its own symbolic ``solve``.
Both C codes are compiled with the same compiler and flags into one harness.

Run: ``make bench`` (needs the ``bench`` extra: casadi, cffi). Prints a table and, with
``--write FILE``, stores it with the command, the machine and the date.
"""

from __future__ import annotations

import argparse
import math
import os
import platform
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from types import ModuleType

import casadi as ca
import numpy as np
from cffi import FFI

from tvopt_codegen.derivation import Derivation, derive
from tvopt_codegen.emit import write_files
from tvopt_codegen.lowering.ir import KernelSet, lower
from tvopt_codegen.renderer.rendering import render
from tvopt_codegen.simulation import load_controller
from tvopt_codegen.simulation.sampled import hold
from tvopt_codegen.spec import load_spec

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "benchmarks"))
from bench_mechanics import mechanics_table  # noqa: E402
from casadi_peer import CFLAGS, HARNESS_RUNS, TURNS, _to_casadi  # noqa: E402
from cold import best_wall  # noqa: E402

SPECS = ("unicycle_switch", "two_unicycles_barrier")
BATCH_C = 100_000
BATCH_PY_CASADI = 10_000


def casadi_law(d: Derivation) -> ca.Function:
    """The paper's law for ``d``'s plant and objective, derived by CasADi's own AD."""
    t, X, P, _, _, _, u = _casadi_pieces(d)
    return ca.Function("casadi_law", [t, X, P], [u])


def casadi_closed_loop(d: Derivation) -> ca.Function:
    """The closed loop ``ds/dt = f(s) + G(s) w`` under the law, all in CasADi."""
    t, X, P, f, G, w, _ = _casadi_pieces(d)
    return ca.Function("casadi_closed_loop", [t, X, P], [f + ca.mtimes(G, w)])


def _casadi_pieces(d: Derivation) -> tuple[ca.SX, ...]:
    """Time, state, parameters, the extended plant's f and G, the law's w and u."""
    assert d.dynamics.uniform, "the benchmark builds uniform-relative-degree laws only"
    model, ext = d.model, d.linearization.extension
    n, m, k = len(ext.x), len(model.y), d.dynamics.k
    t = ca.SX.sym("t")
    X = ca.SX.sym("X", n)
    P = ca.SX.sym("P", max(1, len(model.params)))
    base = [*ext.x, *model.params]
    values = [X[i] for i in range(n)] + [P[i] for i in range(len(model.params))]
    f = ca.vertcat(*[_to_casadi(e, base, values) for e in ext.f])
    G = ca.horzcat(
        *[ca.vertcat(*[_to_casadi(ext.G[i, j], base, values) for i in range(n)]) for j in range(m)]
    )
    h = [_to_casadi(e, base, values) for e in model.h]
    signal_values = [
        _to_casadi(e, [model.t, *model.params], [t, *values[n:]]) for _, e in model.signals
    ]
    Y = ca.SX.sym("Y", m, k + 1)
    f0 = _to_casadi(
        model.f0,
        [*model.y, *(s for s, _ in model.signals), *model.params, model.t],
        [*(Y[i, 0] for i in range(m)), *signal_values, *values[n:], t],
    )
    jet = [ca.gradient(f0, Y[:, 0])]
    moving = ca.vertcat(t, ca.vec(Y[:, :k]))
    rates = ca.vertcat(1, ca.vec(Y[:, 1:]))
    for _ in range(k):
        jet.append(ca.jtimes(jet[-1], moving, rates))
    rest = ca.substitute(jet[k], Y[:, k], ca.DM.zeros(m))
    hess = ca.hessian(f0, Y[:, 0])[0]
    c = sum(d.dynamics.coefficients[j] * jet[j] for j in range(k)) - rest
    lie = []
    rows, p = [], []
    for i in range(m):
        chain = [h[i]]
        for _ in range(k):
            chain.append(ca.jtimes(chain[-1], X, f))
        lie.append(chain[:k])
        rows.append(ca.mtimes(ca.jacobian(chain[k - 1], X), G))
        p.append(chain[k])
    R = ca.vertcat(*rows)
    state_jet = ca.vertcat(*[lie[i][j] for j in range(k) for i in range(m)])
    c = ca.substitute(c, ca.vec(Y[:, :k]), state_jet)
    hess = ca.substitute(hess, ca.vec(Y[:, :k]), state_jet)
    z = ca.solve(hess, c)
    w = ca.solve(R, z - ca.vertcat(*p))
    index = {s.name: i for i, s in enumerate(ext.x)}
    u = ca.vertcat(
        *[X[index[uj.name]] if uj.name in ext.states else w[j] for j, uj in enumerate(model.u)]
    )
    return t, X, P, f, G, w, u


HARNESS = r"""
#define _POSIX_C_SOURCE 199309L
#include <stdio.h>
#include <time.h>
#include "{name}.h"
#include "casadi_law.h"

static double now(void)
{{
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return ts.tv_sec + 1e-9 * ts.tv_nsec;
}}

#define NS {P}_N_STATES
#define NI {P}_N_INPUTS
#define NP {np}
#define B {batch}
/* Best of REPEATS, ours and CasADi's taking turns: a burst of load on the shared machine
 * then spoils one round of each, not the side that happened to run during it. */
#define REPEATS 15
static double S[NS * B], U[NI * B], T[B], PB[NP * B];
static casadi_int iw[1000];
static casadi_real w[200000];

int main(void)
{{
    double s[NS], u[NI], p[NP], acc = 0.0, tt, best_ours = 1e9, best_casadi = 1e9, t0;
    const casadi_real *arg[16];
    casadi_real *res[16];
    long i, rep, calls = {calls};
    for (i = 0; i < NS; ++i) s[i] = {name}_default_state[i];
    for (i = 0; i < NP; ++i) p[i] = {params}[i];
    arg[0] = &tt; arg[1] = s; arg[2] = p; res[0] = u;
{turns}    {{
        /* The stateful controller's step against a control call, taking turns likewise;
           x is the plant part of s, and time moves on by 1 us per step. */
        {name}_controller_t c;
        double best_step = 1e9, best_control = 1e9, t_step = 0.0;
        {name}_controller_init(&c, 0.0, s, NULL, p);
        for (rep = 0; rep < REPEATS; ++rep) {{
            t0 = now();
            for (i = 0; i < calls; ++i) {{
                t_step += 1e-6;
                {name}_controller_step(&c, t_step, s, u);
                acc += u[0];
            }}
            if ((now() - t0) / calls < best_step) best_step = (now() - t0) / calls;
            t0 = now();
            for (i = 0; i < calls; ++i) {{ {name}_control(1e-6 * i, s, p, u); acc += u[0]; }}
            if ((now() - t0) / calls < best_control) best_control = (now() - t0) / calls;
        }}
        printf("step %.6e %.6e\n", best_step, best_control);
    }}
    for (i = 0; i < B; ++i) {{
        long j;
        for (j = 0; j < NS; ++j) S[i * NS + j] = {name}_default_state[j] + 1e-6 * (double)(i % 97);
        for (j = 0; j < NP; ++j) PB[i * NP + j] = p[j];
        T[i] = 0.5;
    }}
    best_ours = best_casadi = 1e9;
    for (rep = 0; rep < REPEATS; ++rep) {{
        t0 = now();
        {name}_control_batch(B, 0.5, S, p, U, NULL);
        if ((now() - t0) / B < best_ours) best_ours = (now() - t0) / B;
        acc += U[0];
        arg[0] = T; arg[1] = S; arg[2] = PB; res[0] = U;
        t0 = now();
        map{batch}_casadi_law(arg, res, iw, w, 0);
        if ((now() - t0) / B < best_casadi) best_casadi = (now() - t0) / B;
        acc += U[0];
    }}
    printf("batch %.6e %.6e\n", best_ours, best_casadi);
    printf("checksum %g\n", acc);
    return 0;
}}
"""


def _per_call(func: Callable[[], object], calls: int, repeats: int = 5) -> float:
    best = math.inf
    for _ in range(repeats):
        start = time.perf_counter()
        for _ in range(calls):
            func()
        best = min(best, (time.perf_counter() - start) / calls)
    return best


def bench(name: str, folder: Path) -> dict[str, float]:
    """Every measure of one spec: ours and the peer's, in seconds (and operation counts)."""
    d = derive(load_spec(name))
    kernels: KernelSet = lower(d)
    law = casadi_law(d)
    params = np.array([v for _, v in d.spec.parameters] or [0.0])
    state = np.array(d.closed_loop.initial_state)

    # Both C codes, compiled with the same compiler and flags into one harness.
    write_files(render(kernels, "c"), folder)
    generator = ca.CodeGenerator("casadi_law", {"with_header": True})
    generator.add(law)
    generator.add(law.map(BATCH_C))
    generator.generate(str(folder) + "/")
    prefix = name.upper()
    (folder / "harness.c").write_text(
        HARNESS.format(
            name=name,
            turns=TURNS.format(name=name),
            P=prefix,
            np=len(params),
            batch=BATCH_C,
            calls=200_000,
            params="(const double[]){" + ", ".join(repr(float(v)) for v in params) + "}",
        )
    )
    binary = folder / "harness"
    subprocess.run(
        [
            "gcc",
            *CFLAGS,
            "-o",
            str(binary),
            str(folder / "harness.c"),
            str(folder / f"{name}.c"),
            str(folder / "casadi_law.c"),
            "-lm",
        ],
        check=True,
    )
    # Several processes: each gets its own stack and heap addresses (ASLR), and with them
    # its own cache and branch-predictor aliasing, which moved one side by 10% in single
    # runs. Each figure is the best over the processes.
    loop_ours = loop_casadi = batch_ours = batch_casadi = math.inf
    step_ours = step_control = math.inf
    for _ in range(HARNESS_RUNS):
        lines = dict(
            line.split(" ", 1)
            for line in subprocess.run(
                [str(binary)], capture_output=True, text=True, check=True
            ).stdout.splitlines()
        )
        loop = [float(v) for v in lines["loop"].split()]
        batch = [float(v) for v in lines["batch"].split()]
        loop_ours, loop_casadi = min(loop_ours, loop[0]), min(loop_casadi, loop[1])
        batch_ours, batch_casadi = min(batch_ours, batch[0]), min(batch_casadi, batch[1])
        step = [float(v) for v in lines["step"].split()]
        step_ours, step_control = min(step_ours, step[0]), min(step_control, step[1])

    # From Python: our compiled module, a bare cffi call of the same C, CasADi Function.
    os.environ.setdefault("TVOPT_CODEGEN_CACHE", str(folder / "cache"))
    ours = load_controller(kernels, "c")
    numpy_backend = load_controller(kernels, "python")
    library = ours._LIB._name  # noqa: SLF001 - the very library our module loaded
    ffi = FFI()
    ffi.cdef(f"int {name}_control(double, const double *, const double *, double *);")
    lib = ffi.dlopen(library)
    s_buf = ffi.new("double[]", list(state))
    p_buf = ffi.new("double[]", list(params))
    u_buf = ffi.new("double[]", len(d.spec.inputs))
    control = getattr(lib, f"{name}_control")
    u_numpy = np.empty(len(d.spec.inputs))

    def cffi_numpy() -> np.ndarray:
        s = np.asarray(state, dtype=float)
        out = np.empty_like(u_numpy)
        control(0.5, ffi.from_buffer("double[]", s), p_buf, ffi.from_buffer("double[]", out))
        return out

    reference = np.array(law(0.5, state, params)).ravel()
    assert np.allclose(ours.control(0.5, state), reference, rtol=1e-9, atol=1e-12), "laws differ"
    call_ours = _per_call(lambda: ours.control(0.5, state), 20_000)
    call_cffi = _per_call(lambda: control(0.5, s_buf, p_buf, u_buf), 50_000)
    call_cffi_numpy = _per_call(cffi_numpy, 20_000)
    call_casadi = _per_call(lambda: law(0.5, state, params), 2_000)
    # Controller.step from Python: the measured plant state at times 1 ms apart.
    plant_state = state[: len(d.spec.states)].copy()
    controller = ours.Controller(plant_state)
    clock = iter(range(1, 10**9))
    step_python = _per_call(lambda: controller.step(1e-3 * next(clock), plant_state), 20_000)

    rng = np.random.default_rng(0)
    many = state[:, None] + 0.01 * rng.standard_normal((len(state), BATCH_C))
    for i, nm in enumerate(d.closed_loop.state_names):
        if nm in d.linearization.extension.states:
            many[i] = 1.0 + 0.1 * rng.random(BATCH_C)
    batch_numpy = _per_call(lambda: numpy_backend.control(0.5, many), 1, 3) / BATCH_C
    mapped = law.map(BATCH_PY_CASADI)
    few = many[:, :BATCH_PY_CASADI]
    batch_casadi_py = _per_call(lambda: mapped(0.5, few, params), 1, 3) / BATCH_PY_CASADI

    # The law as emitted: its kernels (the Hessian's Cholesky is one) and R's block LUs.
    present = {k.name for k in kernels.kernels}
    law_kernels = ("jet_time", "jet", "cholesky", "decoupling", "closed_loop")
    ops = sum(kernels[k].ops for k in law_kernels if k in present) + kernels.lu_ops
    return {
        "loop_ours": loop_ours,
        "loop_casadi": loop_casadi,
        "step_ours": step_ours,
        "step_control": step_control,
        "batch_ours": batch_ours,
        "batch_casadi": batch_casadi,
        "call_ours": call_ours,
        "call_cffi": call_cffi,
        "call_cffi_numpy": call_cffi_numpy,
        "call_casadi": call_casadi,
        "step_python": step_python,
        "batch_numpy": batch_numpy,
        "batch_casadi_py": batch_casadi_py,
        "ops_ours": ops,
        "ops_casadi": law.n_instructions(),
    }


#: The robust controller's step: the bundled PVTOL with integral action (one more pole),
#: the observer at 20 rad/s and the thrust within [0, 1.5 x hover], against its plain step.
ROBUST_TABLES = """
[robust]
integral = true

[robust.observer]
bandwidth = 20.0

[limits]
thrust = [0.0, 14.715]
"""
#: The extended-state observer's step: the bundled PVTOL with [robust.eso] at 20 rad/s
#: (five estimates per output), against its plain step.
ESO_TABLES = """
[robust.eso]
bandwidth = 20.0
"""
#: The matched-input observer alone at 20 rad/s, for the comparison docs/robust.md makes.
OBSERVER_TABLES = """
[robust.observer]
bandwidth = 20.0
"""
ROBUST_HARNESS = r"""
#include <stdio.h>
#include <time.h>
#include "pvtol.h"
#include "robust_pvtol.h"

static double now(void)
{{
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return ts.tv_sec + 1e-9 * ts.tv_nsec;
}}

/* The measured plant states of the robust closed loop on a 10% heavier plant, every
 * millisecond over its horizon: both controllers step through the same run. */
static const double X[{points}][6] = {{ {states} }};

int main(void)
{{
    pvtol_controller_t plain;
    robust_pvtol_controller_t robust;
    double u[2], acc = 0.0, best_plain = 1e9, best_robust = 1e9, t0;
    long i, rep;
    for (rep = 0; rep < 15; ++rep) {{
        pvtol_controller_init(&plain, 0.0, X[0], NULL, NULL);
        robust_pvtol_controller_init(&robust, 0.0, X[0], NULL, NULL);
        t0 = now();
        for (i = 1; i < {points}; ++i) {{
            pvtol_controller_step(&plain, 1e-3 * (double)i, X[i], u);
            acc += u[0];
        }}
        if ((now() - t0) / ({points} - 1) < best_plain) {{
            best_plain = (now() - t0) / ({points} - 1);
        }}
        t0 = now();
        for (i = 1; i < {points}; ++i) {{
            robust_pvtol_controller_step(&robust, 1e-3 * (double)i, X[i], u);
            acc += u[0];
        }}
        if ((now() - t0) / ({points} - 1) < best_robust) {{
            best_robust = (now() - t0) / ({points} - 1);
        }}
    }}
    printf("robust %.6e %.6e\n", best_robust, best_plain);
    printf("checksum %g\n", acc);
    return 0;
}}
"""


def _robust_run(module: ModuleType, horizon: float = 12.0, h: float = 1e-3) -> np.ndarray:
    """The robust PVTOL's plant states, every ``h``, on a plant 10% heavier (RK4)."""
    x = np.array(module.DEFAULT_STATE[:6])
    controller = module.Controller(x)
    states = [x]

    def plant(t: float, s: np.ndarray, u: np.ndarray) -> np.ndarray:
        return np.asarray(module.plant(t, s, u, {"m": 1.1}))

    for k in range(1, int(round(horizon / h)) + 1):
        x = hold(plant, (k - 1) * h, k * h, x, controller.u)
        controller.step(k * h, x)
        states.append(x)
    return np.array(states)


def robust_step(folder: Path, tables: str = ROBUST_TABLES) -> tuple[float, float]:
    """Seconds per C controller step: the robust PVTOL's and the plain PVTOL's."""
    text = (ROOT / "tvopt_codegen" / "examples" / "pvtol.toml").read_text(encoding="utf-8")
    if "integral" in tables:
        text = text.replace("poles = [", "poles = [-0.8, ")
    text = text.replace('name = "pvtol"', 'name = "robust_pvtol"')
    write_files(render(lower(derive(load_spec("pvtol"))), "c"), folder)
    robust = folder / "robust_pvtol.toml"
    robust.write_text(text + tables, encoding="utf-8")
    kernels = lower(derive(load_spec(str(robust))))
    write_files(render(kernels, "c"), folder)
    states = _robust_run(load_controller(kernels, "python"))
    (folder / "robust.c").write_text(
        ROBUST_HARNESS.format(
            points=len(states),
            states=", ".join("{" + ", ".join(repr(float(v)) for v in row) + "}" for row in states),
        )
    )
    binary = folder / "robust"
    subprocess.run(
        ["gcc", *CFLAGS, "-o", str(binary)]
        + [str(folder / f) for f in ("robust.c", "pvtol.c", "robust_pvtol.c")]
        + ["-lm"],
        check=True,
    )
    ours = plain = math.inf
    for _ in range(HARNESS_RUNS):
        out = subprocess.run([str(binary)], capture_output=True, text=True, check=True).stdout
        values = [float(v) for v in out.splitlines()[0].split()[1:]]
        ours, plain = min(ours, values[0]), min(plain, values[1])
    return ours, plain


#: Every bundled example: the NumPy module's single-state call against CasADi's.
EXAMPLES = (
    "integrator",
    "unicycle_switch",
    "two_unicycles_barrier",
    "pvtol",
    "flexible_joint",
    "unicycle_ring",
)


def single_state() -> list[tuple[str, float, float]]:
    """Per example, the single-state call of the NumPy module and of CasADi.

    The NumPy module's ``control`` for one state, and a CasADi Function call on the
    same state, in seconds: the best of 150 rounds of 200 calls, the two taking turns
    round by round so that a busy spell of a shared machine slows both alike.
    """
    rows = []
    for name in EXAMPLES:
        d = derive(load_spec(name))
        module = load_controller(lower(d), "python")
        law = casadi_law(d)
        state = np.array(d.closed_loop.initial_state)
        params = np.array([v for _, v in d.spec.parameters] or [0.0])
        ours = peer = math.inf
        for _ in range(150):
            ours = min(ours, _per_call(lambda m=module, s=state: m.control(0.5, s), 200, 1))
            peer = min(peer, _per_call(lambda f=law, s=state, p=params: f(0.5, s, p), 200, 1))
        rows.append((name, ours, peer))
    return rows


def startup() -> list[tuple[str, float, str]]:
    """Cold ``tvopt-codegen`` processes as a user starts them, and the peer.

    The peer is a Python process importing sympy, numpy and scipy (what every command
    used to load).
    """
    cli = [sys.executable, "-m", "tvopt_codegen"]
    peer = best_wall([sys.executable, "-c", "import sympy, numpy, scipy"], 5)
    return [
        ("`tvopt-codegen --version`", best_wall([*cli, "--version"], 5), "<= 0.25 s"),
        ("`tvopt-codegen --help`", best_wall([*cli, "--help"], 5), "<= 0.25 s"),
        (
            "`tvopt-codegen check unicycle_switch`",
            best_wall([*cli, "check", "unicycle_switch"], 5),
            "<= 1.5 s",
        ),
        ("(peer) `python -c 'import sympy, numpy, scipy'`", peer, ""),
    ]


def eso_rows(eso: tuple[float, float], observer: tuple[float, float] | None = None) -> list[str]:
    """The observers' steps against the plain one, as table rows."""
    rows = [
        f"| pvtol with [robust.eso] step vs the plain pvtol step, ns | {eso[0] * 1e9:.4g} | "
        f"{eso[1] * 1e9:.4g} | {eso[0] / eso[1]:.3f} | <= 1.5 |",
    ]
    if observer is not None:
        rows.append(
            f"| pvtol with [robust.observer] step vs the plain pvtol step, ns | "
            f"{observer[0] * 1e9:.4g} | {observer[1] * 1e9:.4g} | "
            f"{observer[0] / observer[1]:.3f} | |"
        )
    return rows


def extra_tables(
    single: list[tuple[str, float, float]],
    start: list[tuple[str, float, str]],
    robust: tuple[float, float],
    eso: tuple[float, float],
    observer: tuple[float, float],
) -> str:
    """The robust controller's step, the single-state call and start-up sections."""
    peer = start[-1][1]
    lines = [
        "### The robust controller's C step (limits, integral action, observer)",
        "",
        "| measure | ours | peer | ratio ours/peer | target |",
        "|---|---|---|---|---|",
        f"| robust_pvtol step vs the plain pvtol step, ns | {robust[0] * 1e9:.4g} | "
        f"{robust[1] * 1e9:.4g} | {robust[0] / robust[1]:.3f} | <= 1.5 |",
        *eso_rows(eso, observer),
        "",
        "### NumPy backend, one state per call (`control(t, s)` with a 1-D float array)",
        "",
        "| example | ours, us | CasADi Function, us | ratio ours/peer | target |",
        "|---|---|---|---|---|",
    ]
    for name, ours, casadi in single:
        lines.append(
            f"| {name} | {ours * 1e6:.3g} | {casadi * 1e6:.3g} | {ours / casadi:.3f} | <= 20 us |"
        )
    lines += [
        "",
        "### Start-up: cold processes (best of 5)",
        "",
        "| command | wall, s | ratio to the peer | target |",
        "|---|---|---|---|",
    ]
    for label, seconds, target in start:
        lines.append(f"| {label} | {seconds:.3f} | {seconds / peer:.2f} | {target} |")
    lines.append("")
    return "\n".join(lines)


def table(results: dict[str, dict[str, float]]) -> str:
    """The Markdown table of :func:`bench`'s results, one section per spec."""
    us = 1e6
    rows = [
        ("C loop, ns per `control`", "loop_ours", "loop_casadi", 1e9, "<= 1.0"),
        ("C batch of 100k, ns per state", "batch_ours", "batch_casadi", 1e9, "<= 1.0"),
        (
            "C controller step vs our `control` call, ns",
            "step_ours",
            "step_control",
            1e9,
            "<= 1.3",
        ),
        ("Python call, us (ours vs bare cffi)", "call_ours", "call_cffi", us, "<= 2.0"),
        ("Python call, us (ours vs CasADi Function)", "call_ours", "call_casadi", us, "<= 0.05"),
        (
            "Python `Controller.step`, us (vs our `control` call; target: step <= 2 us)",
            "step_python",
            "call_ours",
            us,
            "<= 5.0",
        ),
        (
            "Python batch, us per state (NumPy vs CasADi map)",
            "batch_numpy",
            "batch_casadi_py",
            us,
            "<= 0.1",
        ),
        (
            "operations (ours incl. solves vs CasADi instructions)",
            "ops_ours",
            "ops_casadi",
            1,
            "<= 1.5",
        ),
    ]
    lines = []
    for name, res in results.items():
        lines += [
            f"### {name}",
            "",
            "| measure | ours | peer | ratio ours/peer | target |",
            "|---|---|---|---|---|",
        ]
        for label, a, b, scale, target in rows:
            ratio = res[a] / res[b]
            lines.append(
                f"| {label} | {res[a] * scale:.4g} | {res[b] * scale:.4g} | "
                f"{ratio:.3f} | {target} |"
            )
        lines.append(
            f"| (reference) cffi call with numpy in and out, us | "
            f"{res['call_cffi_numpy'] * us:.4g} | | | |"
        )
        lines.append("")
    return "\n".join(lines)


def main() -> int:
    """Run the benchmark, print the table and optionally store it."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--write", type=Path, help="also store the table in this Markdown file")
    parser.add_argument(
        "--eso-only",
        action="store_true",
        help="time only the two observers' C steps against the plain one",
    )
    args = parser.parse_args()
    if args.eso_only:
        with tempfile.TemporaryDirectory(prefix="tvopt-bench-") as tmp:
            (Path(tmp) / "eso").mkdir()
            (Path(tmp) / "observer").mkdir()
            eso = robust_step(Path(tmp) / "eso", ESO_TABLES)
            observer = robust_step(Path(tmp) / "observer", OBSERVER_TABLES)
        rows = [
            "| measure | ours | peer | ratio ours/peer | target |",
            "|---|---|---|---|---|",
            *eso_rows(eso, observer),
        ]
        print("\n".join(rows))
        if args.write:
            header = [
                "# The observers' C step against the plain one",
                "",
                "Produced by `python benchmarks/bench_c.py --eso-only --write "
                "benchmarks/OBSERVERS.md` (the same rows are in `make bench`'s RESULTS.md). "
                f"Machine: {platform.machine()}, gcc {' '.join(CFLAGS)}; the best of "
                f"{HARNESS_RUNS} runs of each harness, both controllers stepping through the "
                "same measured states of PVTOL on a 10% heavier plant at 1 kHz, taking turns.",
                "",
            ]
            args.write.write_text("\n".join(header + rows) + "\n", encoding="utf-8")
        return 0
    results = {}
    with tempfile.TemporaryDirectory(prefix="tvopt-bench-") as tmp:
        for name in SPECS:
            folder = Path(tmp) / name
            folder.mkdir()
            results[name] = bench(name, folder)
        robust_folder = Path(tmp) / "robust"
        robust_folder.mkdir()
        robust = robust_step(robust_folder)
        eso_folder = Path(tmp) / "eso"
        eso_folder.mkdir()
        eso = robust_step(eso_folder, ESO_TABLES)
        observer_folder = Path(tmp) / "observer"
        observer_folder.mkdir()
        observer = robust_step(observer_folder, OBSERVER_TABLES)
    text = table(results) + "\n" + extra_tables(single_state(), startup(), robust, eso, observer)
    text += "\n" + mechanics_table()
    print(text)
    if args.write:
        cpu = next(
            (
                line.split(":", 1)[1].strip()
                for line in Path("/proc/cpuinfo").read_text().splitlines()
                if line.startswith("model name")
            ),
            platform.processor(),
        )
        header = [
            "# C and NumPy backends against CasADi",
            "",
            "Command: `make bench` (`python benchmarks/bench_c.py --write benchmarks/RESULTS.md`).",
            f"Machine: {os.cpu_count()} cores, {cpu}; Python {platform.python_version()}, "
            f"casadi {ca.__version__}, gcc `{CFLAGS}`; {time.strftime('%Y-%m-%d')}.",
            "Ratios come from one run; absolute times are noisy on a shared machine.",
            "",
        ]
        args.write.write_text("\n".join(header) + "\n" + text + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
