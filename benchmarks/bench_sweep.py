"""Sweep throughput: the compiled loop on Dask against two peers, in one run.

Run: ``make bench-sweep`` (needs the ``bench`` extra for CasADi). Every figure is
measured in this run on ``unicycle_switch`` over its 20 s horizon with RK45 rtol 1e-8,
atol 1e-10, each sample starting from its own drawn initial state:

- ``simulate``'s scipy path: :func:`tvopt_codegen.simulation.simulate` per sample (the
  NumPy controller under ``solve_ivp``, then the certificate), what a user scripting a
  loop over samples gets today;
- CasADi: the same closed loop built by CasADi's own AD (``benchmarks/bench_c.py``),
  integrated by ``integrator('cvodes')`` at the same tolerances on the same 201 output
  times, mapped over the samples with ``map(N, "thread", cores)``; it computes the
  trajectories only (no y*, no statistics), which favours it;
- ours: :func:`tvopt_codegen.sweep.run_sweep` on a ``LocalCluster`` of 1 and of 2
  workers (cluster start-up and the workers' first load of the library excluded; the
  cold command with both is timed separately).

With ``--write FILE`` the table is written as Markdown with the command that made it.
"""

from __future__ import annotations

import argparse
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import casadi as ca
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_c import casadi_closed_loop  # noqa: E402

from tvopt_codegen import simulation, sweep  # noqa: E402
from tvopt_codegen.derivation import derive  # noqa: E402
from tvopt_codegen.lowering.ir import lower  # noqa: E402
from tvopt_codegen.spec import load_spec  # noqa: E402

SPEC = "unicycle_switch"
RTOL, ATOL, POINTS = 1e-8, 1e-10, 201
SPREAD = (
    ("x1", sweep.parse_distribution("normal(-5, 0.5)", "--initial", "x1")),
    ("x2", sweep.parse_distribution("uniform(3, 5)", "--initial", "x2")),
)


def _options(samples: int, horizon: float) -> sweep.SweepOptions:
    return sweep.SweepOptions(
        samples=samples,
        seed=1,
        t_final=horizon,
        initial=SPREAD,
        rtol=RTOL,
        atol=ATOL,
        points=POINTS,
    )


def scipy_rate(program: sweep.SweepProgram, samples: int, horizon: float) -> float:
    """Samples per second of ``simulate`` (NumPy controller, solve_ivp, certificate)."""
    d = derive(load_spec(SPEC))
    controller = simulation.load_controller(lower(d), "python")
    options = _options(samples, horizon)
    started = time.perf_counter()
    for i in range(samples):
        s0 = sweep.draw(program, options, i).s0
        run = simulation.Options(
            t_final=horizon, initial_state=tuple(s0), rtol=RTOL, atol=ATOL, points=POINTS
        )
        simulation.simulate(d, controller, run)
    return samples / (time.perf_counter() - started)


def casadi_rate(program: sweep.SweepProgram, samples: int, horizon: float, threads: int) -> float:
    """Samples per second of CasADi's cvodes over the closed loop, mapped on threads."""
    d = derive(load_spec(SPEC))
    rhs = casadi_closed_loop(d)
    n, p = len(program.state_names), max(1, len(program.param_names))
    t, x, q = ca.SX.sym("t"), ca.SX.sym("x", n), ca.SX.sym("p", p)
    grid = np.linspace(0.0, horizon, POINTS)
    integrator = ca.integrator(
        "F",
        "cvodes",
        {"x": x, "p": q, "t": t, "ode": rhs(t, x, q)},
        0.0,
        grid[1:],
        {"abstol": ATOL, "reltol": RTOL},
    )
    options = _options(samples, horizon)
    starts = np.array([sweep.draw(program, options, i).s0 for i in range(samples)]).T
    params = np.tile(np.array(program.defaults)[:, None], (1, samples))
    mapped = integrator.map(samples, "thread", threads)
    best = np.inf
    for _ in range(3):
        started = time.perf_counter()
        mapped(x0=starts, p=params)
        best = min(best, time.perf_counter() - started)
    return samples / best


def our_rate(program: sweep.SweepProgram, samples: int, horizon: float, workers: int) -> float:
    """Samples per second of run_sweep on a LocalCluster of ``workers`` (best of 3)."""
    client, cluster = sweep.connect(workers, None)
    try:
        sweep.run_sweep(client, program, _options(4 * workers, horizon), chunk=1)  # warm-up
        best = np.inf
        for _ in range(3):
            run = sweep.run_sweep(client, program, _options(samples, horizon))
            best = min(best, run.seconds)
        return samples / best
    finally:
        client.close()
        cluster.close()


def cold_command(samples: int, workers: int) -> float:
    """Wall seconds of a fresh ``tvopt-codegen sweep`` process, derivation to last file."""
    with tempfile.TemporaryDirectory() as folder:
        command = [
            sys.executable,
            "-m",
            "tvopt_codegen",
            "sweep",
            SPEC,
            "--samples",
            str(samples),
            "--seed",
            "1",
            "--initial",
            "x1=normal(-5, 0.5)",
            "--initial",
            "x2=uniform(3, 5)",
            "--workers",
            str(workers),
            "--out",
            str(Path(folder) / "out"),
        ]
        started = time.perf_counter()
        subprocess.run(command, check=True, capture_output=True)
        return time.perf_counter() - started


def main() -> None:
    """Measure every engine and print (or write) the table."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--samples", type=int, default=4000, help="samples per timed sweep")
    parser.add_argument("--scipy-samples", type=int, default=5, help="samples through simulate")
    parser.add_argument("--casadi-samples", type=int, default=1000, help="samples through CasADi")
    parser.add_argument("--write", help="write the Markdown table here")
    args = parser.parse_args()
    horizon = 20.0
    cores = os.cpu_count() or 1
    program = sweep.sweep_program(lower(derive(load_spec(SPEC))))
    scipy = scipy_rate(program, args.scipy_samples, horizon)
    casadi = casadi_rate(program, args.casadi_samples, horizon, cores)
    one = our_rate(program, args.samples, horizon, 1)
    two = our_rate(program, args.samples, horizon, 2)
    cold = cold_command(1000, 2)
    efficiency = two / (2 * one)
    rows = [
        ("simulate per sample (scipy RK45 + NumPy controller + certificate)", scipy, "1"),
        (f"CasADi integrator cvodes, map(N, 'thread', {cores})", casadi, f"{casadi / scipy:.0f}"),
        ("sweep, 1 worker", one, f"{one / scipy:.0f}"),
        ("sweep, 2 workers", two, f"{two / scipy:.0f}"),
    ]
    lines = [
        "# Sweep throughput",
        "",
        f"`unicycle_switch`, 20 s horizon, RK45 rtol {RTOL:g}, atol {ATOL:g}, {POINTS} output "
        f"times, initial x1 ~ normal(-5, 0.5), x2 ~ uniform(3, 5). Machine: {platform.machine()}, "
        f"{cores} cores, Python {platform.python_version()}. Produced by `make bench-sweep` "
        f"(`python benchmarks/bench_sweep.py --write benchmarks/SWEEP.md`).",
        "",
        "| engine | samples/s | vs simulate |",
        "|---|---:|---:|",
        *[f"| {name} | {rate:.1f} | {ratio}x |" for name, rate, ratio in rows],
        "",
        f"- Ours against CasADi's cvodes map: **{two / casadi:.1f}x** with 2 workers "
        f"({one / casadi:.1f}x with one), target >= 2x. CasADi integrates only; each of our "
        "samples also follows y* by Newton at every output time and measures the run.",
        f"- Ours against `simulate` per sample: **{two / scipy:.0f}x** with 2 workers "
        "(target >= 100x).",
        f"- Parallel efficiency from 1 to 2 workers: **{100 * efficiency:.0f}%** (target >= 80%).",
        f"- A cold `tvopt-codegen sweep unicycle_switch --samples 1000 --workers 2` process "
        f"(derivation, C build from the cache, cluster start, sweep, files): {cold:.1f} s.",
        "",
        "Sweep rates time `run_sweep` from the first task sent to the last result, on a "
        "running cluster whose workers have loaded the compiled loop once; best of three.",
        "",
    ]
    text = "\n".join(lines)
    print(text)
    if args.write:
        # The scale section (benchmarks/sweep_scale.py) is another run's: kept as it is.
        path = Path(args.write)
        kept = path.read_text(encoding="utf-8") if path.exists() else ""
        marker = "<!-- scale: benchmarks/sweep_scale.py -->"
        if marker in kept:
            text = text.rstrip("\n") + "\n\n" + marker + kept.split(marker, 1)[1]
        path.write_text(text, encoding="utf-8")


if __name__ == "__main__":
    main()
