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
import sympy as sp

ROOT = Path(__file__).resolve().parent.parent
sys.path[:0] = [str(ROOT), str(ROOT / "benchmarks")]

from casadi_peer import CFLAGS, HARNESS_RUNS, _to_casadi  # noqa: E402

from tests.arms import planar_arm  # noqa: E402
from tvopt_codegen.derivation import Derivation, derive  # noqa: E402
from tvopt_codegen.emit import write_files  # noqa: E402
from tvopt_codegen.ir import lower  # noqa: E402
from tvopt_codegen.mechanics import spec_from_sympy  # noqa: E402
from tvopt_codegen.rendering import render  # noqa: E402
from tvopt_codegen.simulation import load_controller  # noqa: E402
from tvopt_codegen.spec import spec_from_dict  # noqa: E402

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


def casadi_mechanics_law(d: Derivation) -> tuple[ca.Function, int]:
    """The law for ``d``'s mass-matrix plant, built by CasADi with numeric solves of M and R.

    Returns the function and its size: the SX part's instructions (M, F, B, J, the
    curvature and y_imp'') plus the MX graph's (the two solves and the products).
    """
    model = d.model
    mech = model.mechanics
    assert mech is not None and d.k == 2
    nq, m = len(mech.coordinates), len(model.y)
    tS = ca.SX.sym("t")
    XS = ca.SX.sym("X", 2 * nq)
    PS = ca.SX.sym("P", max(1, len(model.params)))
    base = [*model.x, *model.params]
    values = [XS[i] for i in range(2 * nq)] + [PS[i] for i in range(len(model.params))]

    def cas(expr: sp.Expr) -> ca.SX:
        return _to_casadi(sp.sympify(expr), base, values)

    M = ca.vertcat(*[ca.horzcat(*[cas(e) for e in row]) for row in mech.mass_matrix])
    F = ca.vertcat(*[cas(e) for e in mech.forces])
    B = ca.vertcat(*[ca.horzcat(*[cas(e) for e in row]) for row in mech.input_matrix])
    h = ca.vertcat(*[cas(e) for e in model.h])
    q, dq = XS[:nq], XS[nq:]
    J = ca.jacobian(h, q)
    velocity = ca.jtimes(h, q, dq)
    curvature = ca.jtimes(velocity, q, dq)
    # y_imp'' from the objective's gradient jet, as benchmarks/bench_c.py builds it.
    signals = [
        _to_casadi(e, [model.t, *model.params], [tS, *values[2 * nq :]]) for _, e in model.signals
    ]
    Y = ca.SX.sym("Y", m, 3)
    f0 = _to_casadi(
        model.f0,
        [*model.y, *(s for s, _ in model.signals), *model.params, model.t],
        [*(Y[i, 0] for i in range(m)), *signals, *values[2 * nq :], tS],
    )
    jet = [ca.gradient(f0, Y[:, 0])]
    moving = ca.vertcat(tS, ca.vec(Y[:, :2]))
    rates = ca.vertcat(1, ca.vec(Y[:, 1:]))
    for _ in range(2):
        jet.append(ca.jtimes(jet[-1], moving, rates))
    rest = ca.substitute(jet[2], Y[:, 2], ca.DM.zeros(m))
    hess = ca.hessian(f0, Y[:, 0])[0]
    c = d.coefficients[0] * jet[0] + d.coefficients[1] * jet[1] - rest
    state_jet = ca.vertcat(h, velocity)
    c = ca.substitute(c, ca.vec(Y[:, :2]), state_jet)
    hess = ca.substitute(hess, ca.vec(Y[:, :2]), state_jet)
    z = ca.solve(hess, c)
    parts = ca.Function("parts", [tS, XS, PS], [M, ca.horzcat(F, B), J, curvature, z])
    t = ca.MX.sym("t")
    X = ca.MX.sym("X", 2 * nq)
    P = ca.MX.sym("P", max(1, len(model.params)))
    M_, FB, J_, curv, z_ = parts(t, X, P)
    solved = ca.solve(M_, FB, "ldl")  # M^-1 [F B], numerically: never inverted
    accel, gain = solved[:, 0], solved[:, 1:]
    R = ca.mtimes(J_, gain)
    p = curv + ca.mtimes(J_, accel)
    w = ca.solve(R, z_ - p, "qr")
    law = ca.Function("casadi_law", [t, X, P], [w])
    return law, parts.n_instructions() + law.n_instructions()


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
    for (rep = 0; rep < REPEATS; ++rep) {{
        t0 = now();
        for (i = 0; i < calls; ++i) {{ {name}_control(1e-6 * i, s, p, u); acc += u[0]; }}
        if ((now() - t0) / calls < best_ours) best_ours = (now() - t0) / calls;
        t0 = now();
        for (i = 0; i < calls; ++i) {{
            tt = 1e-6 * i;
            casadi_law(arg, res, iw, w, 0);
            acc += u[0];
        }}
        if ((now() - t0) / calls < best_casadi) best_casadi = (now() - t0) / calls;
    }}
    printf("loop %.6e %.6e\n", best_ours, best_casadi);
    printf("checksum %g\n", acc);
    return 0;
}}
"""


def bench_arm(links: int, folder: Path) -> dict[str, float]:
    """Seconds per C `control` call, ours and CasADi's, and both operation counts."""
    d = derive(spec_from_dict(arm_spec(links)))
    kernels = lower(d)
    law, peer_ops = casadi_mechanics_law(d)
    name = d.spec.name
    params = np.array([v for _, v in d.spec.parameters])
    state = np.array(d.initial_state)
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
        "Planar arms from SymPy mechanics (Kane), joint angles as outputs. Ours factors M by a",
        "generated sparse LDL^T inside the jet kernel; CasADi solves M [a W] = [F B] with its",
        "`ldl` linear solver and R w = v - p with `qr`, both in its generated C. Operations:",
        "ours, the law's kernels and R's LU; CasADi's, its SX instructions and MX nodes.",
        "",
        "| arm | ours, ns | CasADi, ns | ratio ours/peer | target | ops ours | CasADi's |",
        "|---|---|---|---|---|---|---|",
    ]
    with tempfile.TemporaryDirectory(prefix="tvopt-bench-mech-") as tmp:
        for links in LINKS:
            folder = Path(tmp) / f"arm{links}"
            folder.mkdir()
            r = bench_arm(links, folder)
            lines.append(
                f"| {links} links | {r['ours'] * 1e9:.4g} | {r['casadi'] * 1e9:.4g} | "
                f"{r['ours'] / r['casadi']:.3f} | <= 1.0 | {r['ops_ours']:.0f} | "
                f"{r['ops_casadi']:.0f} |"
            )
    lines.append("")
    return "\n".join(lines)


if __name__ == "__main__":
    print(mechanics_table())
