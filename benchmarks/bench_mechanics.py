"""Mass-matrix plants: our C `control` against CasADi's generated C with its own numeric solve.

Planar arms of 2, 3 and 6 links (Kane's method in SymPy mechanics, ``tests/arms.py``,
through ``spec_from_sympy``), joint angles tracking sines. CasADi gets the same M, F, B,
outputs and objective and builds the same law with its own AD, but never a symbolic
inverse either: ``a = M^-1 F`` and ``W = M^-1 B`` by its ``ldl`` linear solver (an MX
``solve`` node, generated as C), ``R w = v - p`` by its ``qr``. Both C codes are compiled
with the same compiler and flags into one harness and timed in turns.

Run: ``make bench`` (a section of RESULTS.md), or alone with ``python
benchmarks/bench_mechanics.py`` (needs the ``bench`` extra: casadi).
"""

from __future__ import annotations

import math
import subprocess
import sys
import tempfile
from pathlib import Path

import casadi as ca
import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path[:0] = [str(ROOT), str(ROOT / "benchmarks")]

from casadi_peer import CFLAGS, HARNESS_RUNS, TURNS  # noqa: E402
from cold import best_wall  # noqa: E402

from tests.arms import planar_arm  # noqa: E402
from tests.casadi_oracle import casadi_mechanics_law  # noqa: E402
from tvopt_codegen.derivation import derive  # noqa: E402
from tvopt_codegen.emit import write_files  # noqa: E402
from tvopt_codegen.lowering.ir import lower  # noqa: E402
from tvopt_codegen.mechanics import spec_from_sympy  # noqa: E402
from tvopt_codegen.renderer.rendering import render  # noqa: E402
from tvopt_codegen.simulation import load_controller  # noqa: E402
from tvopt_codegen.spec import Spec, load_spec, spec_from_dict  # noqa: E402

LINKS = (2, 3, 6)


def arm_spec(links: int) -> dict[str, object]:
    """The spec of a planar arm whose joint angles track phase-shifted sines."""
    kane, q, values = planar_arm(links)
    outputs = {f"y{i + 1}": q[i] for i in range(links)}
    f0 = " + ".join(f"(y{i + 1} - 0.3*sin(t + {i}))**2" for i in range(links))
    start = {f"q{i + 1}": 0.1 * (i + 1) for i in range(links)}
    return spec_from_sympy(
        kane, outputs, f0, values, name=f"planar_arm{links}", initial_state=start
    )


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
#define REPEATS 15
static casadi_int iw[100000];
static casadi_real w[1000000];

int main(void)
{{
    double s[NS], u[NI], p[NP], acc = 0.0, tt, best_ours = 1e9, best_casadi = 1e9, t0;
    const casadi_real *arg[16];
    casadi_real *res[16];
    long i, rep, calls = {calls};
    casadi_int sz_arg, sz_res, sz_iw, sz_w;
    casadi_law_work(&sz_arg, &sz_res, &sz_iw, &sz_w);
    if (sz_iw > 100000 || sz_w > 1000000) {{ printf("work too large\n"); return 1; }}
    for (i = 0; i < NS; ++i) s[i] = {name}_default_state[i];
    for (i = 0; i < NP; ++i) p[i] = {params}[i];
    arg[0] = &tt; arg[1] = s; arg[2] = p; res[0] = u;
{turns}    printf("checksum %g\n", acc);
    return 0;
}}
"""


def bench_arm(spec: Spec, folder: Path) -> dict[str, float]:
    """Seconds per C `control` call, ours and CasADi's, and both operation counts."""
    d = derive(spec)
    links = len(d.model.x) // 2
    kernels = lower(d)
    law, peer_ops = casadi_mechanics_law(d)
    name = d.spec.name
    params = np.array([v for _, v in d.spec.parameters])
    state = np.array(d.closed_loop.initial_state)
    ours = load_controller(kernels, "python")
    reference = np.array(law(0.5, state, params)).ravel()
    assert np.allclose(ours.control(0.5, state), reference, rtol=1e-9, atol=1e-9), "laws differ"
    write_files(render(kernels, "c"), folder)
    generator = ca.CodeGenerator("casadi_law", {"with_header": True})
    generator.add(law)
    generator.generate(str(folder) + "/")
    (folder / "harness.c").write_text(
        HARNESS.format(
            name=name,
            turns=TURNS.format(name=name),
            P=name.upper(),
            np=len(params),
            calls=100_000 if links < 6 else 20_000,
            params="(const double[]){" + ", ".join(repr(float(v)) for v in params) + "}",
        )
    )
    binary = folder / "harness"
    sources = [folder / "harness.c", folder / f"{name}.c", folder / "casadi_law.c"]
    subprocess.run(["gcc", *CFLAGS, "-o", str(binary), *map(str, sources), "-lm"], check=True)
    mine = theirs = math.inf
    for _ in range(HARNESS_RUNS):
        out = subprocess.run([str(binary)], capture_output=True, text=True, check=True).stdout
        loop = [float(v) for v in out.splitlines()[0].split()[1:]]
        mine, theirs = min(mine, loop[0]), min(theirs, loop[1])
    present = {k.name for k in kernels.kernels}
    law_kernels = ("jet_time", "jet", "cholesky", "decoupling", "plant_input")
    ops = sum(kernels[k].ops for k in law_kernels if k in present) + kernels.lu_ops
    return {"ours": mine, "casadi": theirs, "ops_ours": ops, "ops_casadi": peer_ops}


def mechanics_table() -> str:
    """The Markdown section: per arm, ns per C `control` call and the ratio."""
    lines = [
        "### Mass-matrix plants: C `control` against CasADi with its own numeric solve",
        "",
        "Planar arms from SymPy mechanics (Kane), joint angles as outputs, and the bundled",
        "URDF arm `ur5_tip` (tip position and wrist joints as outputs). Ours factors M by a",
        "generated sparse LDL^T inside the jet kernel; CasADi solves M [a W] = [F B] with its",
        "`ldl` linear solver and R w = v - p with `qr`, both in its generated C. Operations:",
        "ours, the law's kernels and R's LU; CasADi's, its SX instructions and MX nodes.",
        "",
        "| arm | ours, ns | CasADi, ns | ratio ours/peer | target | ops ours | CasADi's |",
        "|---|---|---|---|---|---|---|",
    ]
    arms = [(f"planar, {links} links", spec_from_dict(arm_spec(links))) for links in LINKS]
    arms.append(("ur5_tip (URDF, 6 joints, tip position)", load_spec("ur5_tip")))
    with tempfile.TemporaryDirectory(prefix="tvopt-bench-mech-") as tmp:
        for index, (label, spec) in enumerate(arms):
            folder = Path(tmp) / f"arm{index}"
            folder.mkdir()
            r = bench_arm(spec, folder)
            lines.append(
                f"| {label} | {r['ours'] * 1e9:.4g} | {r['casadi'] * 1e9:.4g} | "
                f"{r['ours'] / r['casadi']:.3f} | <= 1.0 | {r['ops_ours']:.0f} | "
                f"{r['ops_casadi']:.0f} |"
            )
    lines += [
        "",
        "Cold processes (best of 3) of what a robotics user runs first:",
        "",
        "| command | wall, s | target |",
        "|---|---|---|",
    ]
    with tempfile.TemporaryDirectory(prefix="tvopt-bench-cold-") as tmp:
        cli = [sys.executable, "-m", "tvopt_codegen"]
        urdf = str(ROOT / "tests" / "robots" / "ur5_like.urdf")
        commands = [
            ("`import-urdf tests/robots/ur5_like.urdf --tip tool0`", [
                *cli, "import-urdf", urdf, "--tip", "tool0", "--out", f"{tmp}/ur5.toml",
                "--force"], "<= 5 s"),
            ("`generate ur5_tip`", [*cli, "generate", "ur5_tip", "--out", tmp, "--quiet"],
             "<= 10 s"),
            ("`generate benchmarks/planar_arm6.toml`", [
                *cli, "generate", str(ROOT / "benchmarks" / "planar_arm6.toml"), "--out", tmp,
                "--quiet"], "<= 10 s"),
        ]  # fmt: skip
        for label, command, target in commands:
            lines.append(f"| {label} | {best_wall(command, 3):.2f} | {target} |")
    lines.append("")
    return "\n".join(lines)


if __name__ == "__main__":
    print(mechanics_table())
