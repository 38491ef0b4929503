"""How the derivation scales: ``unicycle_ring`` with N = 1 .. 256 agents, as a user runs it.

The whole sweep runs in rounds (three by default), minutes apart, and each figure is the
median of its rounds: this shared machine has slow phases of a few minutes.

- tvopt-codegen: cold ``tvopt-codegen generate`` processes per N (an unrecorded process
  warms the file cache at the start of each round; the bundled
  ``unicycle_ring`` spec with ``[index] i = N``, nothing else changed; the NumPy module
  written to a temporary folder), timed from outside: wall seconds, the stages' shares
  from ``--timings`` (start-up is the wall time no stage accounts for: the interpreter and
  the imports of the command line), and the process's peak memory (``wait4``'s
  ``ru_maxrss``, read by a small launcher process: Linux hands a process the peak size of
  the process it was forked from, and the bench itself holds sympy and CasADi).
- CasADi: the same plant, outputs, signals and objective written directly in SX, and its
  whole pipeline: relative degree by structural tests, Lie derivatives by ``jtimes``, the
  gradient jet by ``jtimes`` along (t, y, y'), ``solve`` for the Hessian and R, and the
  ``Function``; its operation count is ``n_instructions``. Also in a cold process (a fresh
  interpreter that imports CasADi and runs the pipeline), timed from outside the same way;
  the pipeline's own seconds are timed inside that process.
  The ratio of wall times is the median of the rounds' ratios (ours against CasADi's cold
  run of the same minute).

In each round, also one cold process each of ``benchmarks/chain12.toml`` (k = 12, a
30-factor product in f0; the issue's target 5 s), ``benchmarks/planar_arm6.toml`` (a
six-link arm in mass-matrix form, target 10 s) and every bundled example (target 1.5 s).

Our operation count is the law as emitted: the jet (its time part too), Cholesky,
decoupling and closed-loop kernels plus the LU solves of R's diagonal blocks.

Run: ``make bench-derive`` (needs the ``bench`` extra for CasADi). Prints a table and,
with ``--write FILE``, stores it with the command, the machine and the date.
"""

from __future__ import annotations

import argparse
import importlib.metadata
import json
import math
import os
import platform
import re
import sys
import tempfile
import time
from importlib import resources
from pathlib import Path

import casadi as ca
import sympy as sp
from cold import cold_run

from tvopt_codegen.limits import ENGINES
from tvopt_codegen.spec import bundled_examples

SIZES = (1, 2, 4, 8, 16, 32, 64, 128, 256)
LAW_KERNELS = ("jet_time", "jet", "cholesky", "decoupling", "closed_loop")
# The spec's defaults, for the peers (ours reads them from the spec).
ALPHA, D, RADIUS, SPIN = 1e-3, 40.0, 2.0, 0.1
POLES = (-1.0, -1.5)


def _ring_model(agents: int) -> tuple[object, ...]:
    """Plant, outputs, signals and f0 of the ring in CasADi SX."""
    sym = ca.SX.sym
    sin, cos, tan, pi = ca.sin, ca.cos, ca.tan, math.pi
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
    t, states, f_list, G_list, h, ys, f0, params = _ring_model(agents)
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


#: The symbolic engine our processes derive on (``--engine``; the CLI's default if None).
ENGINE: list[str | None] = [None]


def generate_cold(spec: Path, out: Path, timeout: float) -> dict[str, float]:
    """One cold ``tvopt-codegen generate`` of ``spec``: wall, stages, memory, operations."""
    engine = [] if ENGINE[0] is None else ["--engine", ENGINE[0]]
    command = [
        sys.executable,
        "-m",
        "tvopt_codegen",
        *engine,
        "generate",
        str(spec),
        "--out",
        str(out),
        "--quiet",
        "--timings",
        "--max-seconds",
        str(timeout),
        "--max-size",
        "100000000",
    ]
    run = cold_run(command, timeout)
    wall, memory, errors = run.wall, run.peak_mb, run.stderr
    line = next(x for x in errors.splitlines() if x.startswith("timings: "))
    record: dict[str, float] = json.loads(line.removeprefix("timings: "))
    record["wall"] = wall
    record["memory"] = memory
    stages = sum(record[k] for k in ("load", "derive", "lower", "render", "write"))
    record["startup"] = wall - stages
    return record


#: Rounds of the whole sweep. Each figure is the median of its rounds, which run
#: minutes apart: this shared machine has slow phases of a few minutes (CasADi's own cold
#: N = 256 has taken from 11.8 to 17.3 s), and three runs back to back fall in one.
ROUNDS = 3


def _median(runs: list[dict[str, float]]) -> dict[str, float]:
    """The run of median wall time (its stages and memory with it); ``runs`` is odd."""
    return sorted(runs, key=lambda r: r["wall"])[len(runs) // 2]


def _spread(runs: list[dict[str, float]]) -> str:
    walls = [r["wall"] for r in runs]
    return f"{min(walls):.2f}-{max(walls):.2f}"


def ring_spec(agents: int, folder: Path) -> Path:
    """The bundled ``unicycle_ring`` with ``i = agents``, written into ``folder``."""
    text = (resources.files("tvopt_codegen.examples") / "unicycle_ring.toml").read_text()
    text, found = re.subn(r"(?m)^i = \d+", f"i = {agents}", text)
    assert found == 1, "the bundled unicycle_ring spec no longer has the line 'i = N'"
    spec = folder / f"ring{agents}.toml"
    spec.write_text(text, encoding="utf-8")
    return spec


def ours_cold(agents: int, folder: Path, timeout: float) -> dict[str, float]:
    """One cold ``tvopt-codegen generate`` of the ring of ``agents``."""
    return generate_cold(ring_spec(agents, folder), folder / f"out{agents}", timeout)


def singles() -> list[tuple[Path, float]]:
    """Specs timed beside the ring, with the issue's target for each (cold CLI seconds)."""
    examples = resources.files("tvopt_codegen.examples")
    return [
        (Path(__file__).resolve().parent / "chain12.toml", 5.0),
        # A six-link arm in mass-matrix form (issue 32's target: 10 s).
        (Path(__file__).resolve().parent / "planar_arm6.toml", 10.0),
        # ur5_tip, a six-joint URDF arm: issue 32's target for it is 10 s.
        *(
            (Path(str(examples / f"{name}.toml")), 10.0 if name == "ur5_tip" else 1.5)
            for name in bundled_examples()
        ),
    ]


def singles_table(runs: dict[Path, list[dict[str, float]]]) -> str:
    """The k = 12 chain and every bundled example: the median of the rounds."""
    lines = [
        "| spec | CLI wall s | range s | target s | start-up | load | derive | lower | render "
        "| ops |",
        "|" + "---|" * 10,
    ]
    for spec, target in singles():
        r = _median(runs[spec])
        shares = " | ".join(f"{r[k]:.2f}" for k in ("startup", "load", "derive", "lower", "render"))
        lines.append(
            f"| {spec.stem} | {r['wall']:.2f} | {_spread(runs[spec])} | {target:.1f} | {shares} "
            f"| {int(r['ops'])} |"
        )
    return "\n".join(lines)


def casadi_cold(agents: int, timeout: float) -> tuple[float, float, int, float]:
    """CasADi in a fresh interpreter: wall, the pipeline's seconds, ``n_instructions``, MB.

    The peak memory is the interpreter's own maximum resident set, as ours is.

    The wall time includes the imports, as ours does; the pipeline is timed inside.
    """
    here = Path(__file__).resolve()
    code = (
        f"import sys; sys.path.insert(0, {str(here.parent)!r}); "
        f"from bench_derive import casadi; print(*casadi({agents}))"
    )
    run = cold_run([sys.executable, "-c", code], timeout)
    seconds, instructions = run.stdout.split()
    return run.wall, float(seconds), int(instructions), run.peak_mb


def ring_table(
    ours: dict[int, list[dict[str, float]]],
    cold: dict[int, list[float]],
    inside: dict[int, list[tuple[float, int, float]]],
) -> str:
    """Per N: our median run, CasADi's medians, and the median of the rounds' ratios.

    A round's ratio sets our run beside CasADi's cold run of the same minute, so the
    machine's phase cancels in it.
    """
    lines = [
        "| N | CLI wall s | range s | s per agent | start-up | load | derive | lower | render "
        "| write | peak MB | ours ops | CasADi s (cold) | CasADi s (pipeline) | CasADi peak MB "
        "| CasADi instr. | wall ours/CasADi cold | ops ours/CasADi |",
        "|" + "---|" * 18,
    ]
    for agents, runs in ours.items():
        r = _median(runs)
        shares = " | ".join(
            f"{100 * r[k] / r['wall']:.0f}%"
            for k in ("startup", "load", "derive", "lower", "render", "write")
        )
        ca_cold = sorted(cold[agents])[len(runs) // 2]
        ca_s = sorted(s for s, _, _ in inside[agents])[len(runs) // 2]
        ca_mb = sorted(mb for _, _, mb in inside[agents])[len(runs) // 2]
        ca_ops = inside[agents][0][1]
        ratio = sorted(o["wall"] / c for o, c in zip(runs, cold[agents], strict=True))
        lines.append(
            f"| {agents} | {r['wall']:.2f} | {_spread(runs)} | {r['wall'] / agents:.3f} "
            f"| {shares} | {r['memory']:.0f} | {int(r['ops'])} | {ca_cold:.2f} | {ca_s:.3f} "
            f"| {ca_mb:.0f} | {ca_ops} | {ratio[len(ratio) // 2]:.1f} | {r['ops'] / ca_ops:.2f} |"
        )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    """Measure every size, print the table and optionally store it."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", default=",".join(map(str, SIZES)))
    parser.add_argument("--timeout", type=float, default=900.0, help="s per cold process")
    parser.add_argument("--rounds", type=int, default=ROUNDS, help="sweeps (odd)")
    parser.add_argument("--write", type=Path, help="also store the table in this file")
    parser.add_argument(
        "--engine", choices=("sympy", "symengine"), help="our symbolic engine (default: the CLI's)"
    )
    args = parser.parse_args(argv)
    ENGINE[0] = args.engine
    sizes = [int(s) for s in args.sizes.split(",")]
    if args.rounds < 1 or args.rounds % 2 == 0:
        parser.error("--rounds must be odd (each figure is a median)")
    ours: dict[int, list[dict[str, float]]] = {n: [] for n in sizes}
    cold: dict[int, list[float]] = {n: [] for n in sizes}
    inside: dict[int, list[tuple[float, int, float]]] = {n: [] for n in sizes}
    single: dict[Path, list[dict[str, float]]] = {spec: [] for spec, _ in singles()}
    with tempfile.TemporaryDirectory(prefix="bench-derive-") as tmp:
        folder = Path(tmp)
        for round_ in range(1, args.rounds + 1):
            # Not recorded: a process that finds the file cache cold (sympy's thousand
            # modules read from disk: seen at 2 s of iowait for a bare import, after
            # other work evicted them) and, once per installation, compiles the templates.
            ours_cold(1, folder, args.timeout)
            for agents in sizes:
                r = ours_cold(agents, folder, args.timeout)
                ours[agents].append(r)
                wall, seconds, instructions, peak = casadi_cold(agents, args.timeout)
                cold[agents].append(wall)
                inside[agents].append((seconds, instructions, peak))
                print(
                    f"round {round_}: N = {agents}: {r['wall']:.2f} s, CasADi cold "
                    f"{cold[agents][-1]:.2f} s",
                    flush=True,
                )
            for spec, runs in single.items():
                r = generate_cold(spec, folder / f"s-{spec.stem}", args.timeout)
                runs.append(r)
                print(f"round {round_}: {spec.stem}: {r['wall']:.2f} s", flush=True)
    table = ring_table(ours, cold, inside)
    chain_and_examples = singles_table(single)
    print(table + "\n\n" + chain_and_examples)
    if args.write:
        command = "make bench-derive  # python benchmarks/bench_derive.py " + " ".join(
            argv if argv is not None else sys.argv[1:]
        )
        machine = (
            f"{platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}"
        )
        engine = args.engine or f"{ENGINES[0]}, the command line's default"
        versions = (
            f"ours on {engine} (sympy {sp.__version__}, symengine "
            f"{importlib.metadata.version('symengine')}), casadi {ca.__version__}"
        )
        args.write.write_text(
            "# Derivation scaling: unicycle_ring, N agents, cold processes\n\n"
            f"Command: `{command}`  \nMachine: {machine}; {versions}  \n"
            f"Date: {time.strftime('%Y-%m-%d')}\n\n"
            "Cold `tvopt-codegen generate ringN.toml --out DIR` processes per N (the "
            "bundled `unicycle_ring` with `i = N`, the NumPy module written), timed from "
            f"outside: the median of {args.rounds} rounds of the whole sweep, which run "
            "minutes apart (this machine has slow phases of a few minutes), each after an "
            "unrecorded run that warms the file cache; the range is the rounds' fastest "
            "and slowest. The stages' shares of its wall time "
            "come from `--timings` (start-up: the interpreter and the command line's "
            "imports; load: the spec, with the engine's "
            "import; derive; lower: kernels and CSE; render; write). Peak memory is the "
            "process's maximum resident set. CasADi: the same law built directly in SX "
            "(relative degree, Lie derivatives, gradient jet, solves, Function), in a cold "
            "interpreter (imports included), and its pipeline alone as timed inside that "
            "process. Peak memory is each process's own: they are started from a small "
            "launcher, as Linux hands a process the peak size of its parent. Operations: our "
            "emitted law (jet, Cholesky, decoupling and closed-loop kernels, LU of R's "
            "blocks) against CasADi's n_instructions. The ratio of wall times is the median "
            "of the rounds' ratios: each sets our run beside CasADi's cold run of the same "
            "minute, so the machine's phase cancels in it.\n\n" + table + "\n\n"
            "## The k = 12 chain and the bundled examples\n\n"
            "Cold `tvopt-codegen generate` runs, in seconds, in the same rounds: the median "
            "(its "
            "stages, start-up to render as above, absolute). `chain12` is "
            "`benchmarks/chain12.toml`: a chain of 12 integrators whose f0 tracks a "
            "30-factor product, the issue's high-order case; `planar_arm6` is "
            "`benchmarks/planar_arm6.toml`: a six-link arm in mass-matrix form from SymPy "
            "mechanics (M factored at run time).\n\n" + chain_and_examples + "\n",
            encoding="utf-8",
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
