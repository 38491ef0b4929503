"""How the derivation scales: ``unicycle_ring`` with N = 1 .. 32 agents, three ways.

- tvopt-codegen: spec -> derivation -> kernels -> Python and C files rendered, in process
  (the bundled ``unicycle_ring`` spec with ``[index] i = N``, nothing else changed).
- CasADi: the same plant, outputs, signals and objective written directly in SX, and its
  whole pipeline: relative degree by structural tests, Lie derivatives by ``jtimes``, the
  gradient jet by ``jtimes`` along (t, y, y'), ``solve`` for the Hessian and R, and the
  ``Function``; the operation count is its ``n_instructions``.
- naive sympy: the textbook derivation with sympy matrices (Jacobians for the Lie
  derivatives, differentiation of whole expressions for the jet, ``LUsolve``) followed by one
  ``cse`` of the law; each N runs in a child process stopped at a time budget.

Our operation count is the law as emitted: the jet (its time part too), Cholesky,
decoupling and closed-loop kernels plus the LU solves of R's diagonal blocks.

Run: ``make bench-derive`` (needs the ``bench`` extra for CasADi). Prints a table and,
with ``--write FILE``, stores it with the command, the machine and the date.
"""

from __future__ import annotations

import argparse
import math
import multiprocessing
import os
import platform
import re
import sys
import time
from importlib import resources
from pathlib import Path

import casadi as ca
import sympy as sp

from tvopt_codegen.derivation import derive
from tvopt_codegen.ir import lower
from tvopt_codegen.rendering import render
from tvopt_codegen.spec import Spec, parse_spec

SIZES = (1, 2, 4, 8, 16, 32)
LAW_KERNELS = ("jet_time", "jet", "cholesky", "decoupling", "closed_loop")
# The spec's defaults, for the peers (ours reads them from the spec).
ALPHA, D, RADIUS, SPIN = 1e-3, 40.0, 2.0, 0.1
POLES = (-1.0, -1.5)


def ring_spec(agents: int) -> Spec:
    """The bundled ``unicycle_ring`` with ``agents`` agents."""
    text = (resources.files("tvopt_codegen.examples") / "unicycle_ring.toml").read_text()
    text, count = re.subn(r"(?m)^i = \d+", f"i = {agents}", text)
    assert count == 1, "the bundled unicycle_ring spec no longer has the line 'i = N'"
    return parse_spec(f"unicycle_ring (N = {agents})", text.encode())


def ours(agents: int) -> tuple[float, int]:
    """Seconds from parsed spec to rendered Python and C, and the law's operations."""
    spec = ring_spec(agents)
    start = time.perf_counter()
    kernels = lower(derive(spec))
    render(kernels, "python")
    render(kernels, "c")
    seconds = time.perf_counter() - start
    names = {k.name for k in kernels.kernels}
    ops = sum(kernels[name].ops for name in LAW_KERNELS if name in names) + kernels.lu_ops
    return seconds, ops


def _ring_model(agents: int, lib: str) -> tuple[object, ...]:
    """Plant, outputs, signals and f0 of the ring in CasADi SX or sympy (``lib``)."""
    if lib == "casadi":
        sym = ca.SX.sym
        sin, cos, tan, pi = ca.sin, ca.cos, ca.tan, math.pi
    else:

        def sym(name: str) -> sp.Symbol:
            return sp.Symbol(name, real=True)

        sin, cos, tan, pi = sp.sin, sp.cos, sp.tan, sp.pi
    t = sym("t")
    alpha, d, radius, spin = (sym(n) for n in ("alpha", "d", "radius", "spin"))
    x, y, th, v = ([sym(f"{b}_{i}") for i in range(agents)] for b in ("x", "y", "theta", "v"))
    states = [s for i in range(agents) for s in (x[i], y[i], th[i])] + v
    f, G = [], []
    for i in range(agents):
        f += [v[i] * cos(th[i]), v[i] * sin(th[i]), 0]
        G += [[0] * (2 * agents) for _ in range(3)]
        G[3 * i + 2][2 * i + 1] = 1
    for i in range(agents):
        f.append(0)
        G.append([0] * (2 * agents))
        G[-1][2 * i] = 1
    outputs = [s for i in range(agents) for s in (x[i], y[i])]
    py = [sym(f"py_{i}") for i in range(agents)]
    px = [sym(f"px_{i}") for i in range(agents)]
    ys = [s for i in range(agents) for s in (px[i], py[i])]
    f0 = 0
    for i in range(agents):
        j = (i + 1) % agents
        ox = radius * cos(2 * pi * i / agents + spin * t) + 0.3 * t
        oy = radius * sin(2 * pi * i / agents + spin * t) + 0.2 * t
        gap = (px[i] - px[j]) ** 2 + (py[i] - py[j]) ** 2
        f0 += (px[i] - ox) ** 2 + (py[i] - oy) ** 2 + alpha * tan(gap * pi / (2 * d)) ** 2
    return t, states, f, G, outputs, ys, f0, (alpha, d, radius, spin)


def casadi(agents: int) -> tuple[float, int]:
    """Seconds for CasADi's whole pipeline, and its ``n_instructions``."""
    start = time.perf_counter()
    t, states, f_list, G_list, h, ys, f0, params = _ring_model(agents, "casadi")
    X, Y0 = ca.vertcat(*states), ca.vertcat(*ys)
    f = ca.vertcat(*f_list)
    G = ca.SX(len(states), 2 * agents)
    for i, row in enumerate(G_list):
        for j, value in enumerate(row):
            if value:
                G[i, j] = value
    m = 2 * agents
    # Relative degree: differentiate along f until L_G L_f^(r-1) h is structurally nonzero.
    chains, rows, degrees = [], [], []
    for hi in h:
        chain = [hi]
        while True:
            gradient = ca.jacobian(chain[-1], X)
            row = ca.mtimes(gradient, G)
            chain.append(ca.mtimes(gradient, f))
            if row.nnz() and not all(ca.is_equal(row[j], 0) for j in range(m)):
                rows.append(row)
                degrees.append(len(chain) - 1)
                chains.append(chain)
                break
    k = max(degrees)
    Y1 = ca.SX.sym("Y1", m)
    Y2 = ca.SX.sym("Y2", m)
    grad = ca.gradient(f0, Y0)
    moving, rates = ca.vertcat(t, Y0), ca.vertcat(1, Y1)
    grad1 = ca.jtimes(grad, moving, rates)
    grad2 = ca.jtimes(grad1, ca.vertcat(t, Y0, Y1), ca.vertcat(1, Y1, Y2))
    rest = ca.substitute(grad2, Y2, ca.DM.zeros(m))
    a0, a1 = POLES[0] * POLES[1], -(POLES[0] + POLES[1])
    c = -a0 * grad - a1 * grad1 - rest
    hess = ca.hessian(f0, Y0)[0]
    state_jet = ca.vertcat(*(chain[0] for chain in chains), *(chain[1] for chain in chains))
    c = ca.substitute(c, ca.vertcat(Y0, Y1), state_jet)
    hess = ca.substitute(hess, ca.vertcat(Y0, Y1), state_jet)
    p = ca.vertcat(*(chain[k] for chain in chains))
    R = ca.vertcat(*rows)
    z = ca.solve(hess, c)
    w = ca.solve(R, z - p)
    u = ca.vertcat(*[s for i in range(agents) for s in (X[3 * agents + i], w[2 * i + 1])])
    law = ca.Function("law", [t, X, ca.vertcat(*params)], [u])
    seconds = time.perf_counter() - start
    assert k == 2
    return seconds, int(law.n_instructions())


def _naive_sympy(agents: int, queue: multiprocessing.Queue[tuple[float, int]]) -> None:
    start = time.perf_counter()
    t, states, f_list, G_list, h, ys, f0, _ = _ring_model(agents, "sympy")
    X, f, G = sp.Matrix(states), sp.Matrix(f_list), sp.Matrix(G_list)
    m = 2 * agents
    H = sp.Matrix(h)
    lf = H.jacobian(X) * f
    R = lf.jacobian(X) * G
    p = lf.jacobian(X) * f
    Y0 = sp.Matrix(ys)
    Y1 = sp.Matrix([sp.Symbol(f"{s}_1", real=True) for s in ys])
    Y2 = sp.Matrix([sp.Symbol(f"{s}_2", real=True) for s in ys])
    grad = sp.Matrix([f0]).jacobian(Y0).T
    hess = grad.jacobian(Y0)
    grad1 = grad.diff(t) + hess * Y1
    grad2 = grad1.diff(t) + grad1.jacobian(Y0) * Y1 + grad1.jacobian(Y1) * Y2
    rest = grad2.subs(dict.fromkeys(Y2, 0))
    a0, a1 = POLES[0] * POLES[1], -(POLES[0] + POLES[1])
    c = -a0 * grad - a1 * grad1 - rest
    jet = dict(zip(Y0, H, strict=True)) | dict(zip(Y1, lf, strict=True))
    z = hess.subs(jet).LUsolve(c.subs(jet))
    w = R.LUsolve(z - p)
    replacements, reduced = sp.cse(list(w))
    ops = int(sum(sp.count_ops(e) for e in [*(e for _, e in replacements), *reduced]))
    assert len(reduced) == m
    queue.put((time.perf_counter() - start, ops))


def naive_sympy(agents: int, budget: float) -> tuple[float, int] | None:
    """The naive derivation in a child process; ``None`` when it exceeds ``budget`` s."""
    context = multiprocessing.get_context("fork")
    queue: multiprocessing.Queue[tuple[float, int]] = context.Queue()
    child = context.Process(target=_naive_sympy, args=(agents, queue))
    child.start()
    child.join(budget)
    if child.is_alive():
        child.kill()
        child.join()
        return None
    return queue.get() if not queue.empty() else None


def main(argv: list[str] | None = None) -> int:
    """Measure every size, print the table and optionally store it."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", default=",".join(map(str, SIZES)))
    parser.add_argument("--budget", type=float, default=60.0, help="naive sympy, s per N")
    parser.add_argument("--write", type=Path, help="also store the table in this file")
    args = parser.parse_args(argv)
    sizes = [int(s) for s in args.sizes.split(",")]
    header = (
        "| N | ours s | CasADi s | naive sympy s | ours ops | CasADi instr. | naive ops "
        "| ops ours/CasADi |"
    )
    lines = [header, "|" + "---|" * 8]
    naive_alive = True
    for agents in sizes:
        ours_s, ours_ops = ours(agents)
        ca_s, ca_ops = casadi(agents)
        naive = naive_sympy(agents, args.budget) if naive_alive else None
        if naive is None:
            naive_alive = False
        naive_s = f"{naive[0]:.2f}" if naive else f"> {args.budget:.0f}"
        naive_ops = str(naive[1]) if naive else "-"
        lines.append(
            f"| {agents} | {ours_s:.2f} | {ca_s:.2f} | {naive_s} | {ours_ops} | {ca_ops} "
            f"| {naive_ops} | {ours_ops / ca_ops:.2f} |"
        )
        print(lines[-1], flush=True)
    table = "\n".join(lines)
    print(table)
    if args.write:
        command = "make bench-derive  # python benchmarks/bench_derive.py " + " ".join(
            argv if argv is not None else sys.argv[1:]
        )
        machine = (
            f"{platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}"
        )
        versions = f"sympy {sp.__version__}, casadi {ca.__version__}"
        args.write.write_text(
            "# Derivation scaling: unicycle_ring, N agents\n\n"
            f"Command: `{command}`  \nMachine: {machine}; {versions}  \n"
            f"Date: {time.strftime('%Y-%m-%d')}\n\n"
            "Seconds from a parsed spec to the generated files (ours: derivation, kernels, "
            "Python and C rendered; CasADi: relative degree, Lie derivatives, gradient jet, "
            "solves, Function; naive sympy: matrices, LUsolve and one cse, in a child "
            f"process stopped after {args.budget:.0f} s). Operations: our emitted law "
            "(jet, Cholesky, decoupling and closed-loop kernels, LU of R's blocks) against "
            "CasADi's n_instructions and sympy's count_ops after cse.\n\n" + table + "\n",
            encoding="utf-8",
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
