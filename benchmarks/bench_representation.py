"""sympy or SymEngine for the derivation's hot path: the gradient jet, measured both ways.

Run: ``make bench-representation``. Issue 33 asks whether a faster expression core
would make building the law faster than CasADi. This measures the part of the
derivation that repeats most, the total derivatives of f0's gradient program
(:func:`tvopt_codegen.maths.jet.next_derivative`: one chain rule per assignment, then the
result broken into three-address form again), with the same algorithm on both cores:

- **sympy**: the tool's own ``next_derivative``, k - 1 times;
- **SymEngine**: the same loop written on ``symengine`` expressions (its C++ ``diff``,
  ``Add``, ``Mul``), starting from the same program converted once;
- **back**: converting SymEngine's program to sympy, which the lowering and printers
  read today (the cost of changing representation at a stage border).

Each spec runs in a fresh interpreter (sympy's caches would flatter a second run); the
spec is derived first, untimed, for its gradient program. Beside them, the cold
``generate``'s own derive and lower stages (``--timings``) show how much of the
command the measured part is.

With ``--write FILE`` the table is written as Markdown with the command that made it.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "benchmarks"))

from bench_derive import generate_cold, ring_spec  # noqa: E402

#: One measurement, in a fresh interpreter: prints a JSON object.
_PROBE = r"""
import json, sys, time
import sympy as sp
import symengine as se
from tvopt_codegen.maths import jet
from tvopt_codegen.derivation import derive
from tvopt_codegen.spec import load_spec

d = derive(load_spec(sys.argv[1]))
k, ys = d.dynamics.k, list(d.model.y)
m = len(ys)
chains = [[sp.Symbol(f"_y{i}_{j}", real=True) for i in range(m)] for j in range(k)]

def rates_after(rates, j, zero):
    # y^(j) moves at y^(j+1); the last derivative's rate is 0 (rest's y^(k) = 0).
    for i in range(m):
        rates[chains[j - 1][i]] = chains[j][i] if j < k - 1 else zero
    return rates

start = time.perf_counter()
names = jet.fresh_symbols("_q")
rates = {d.model.t: sp.S.One} | dict(zip(ys, chains[0]))
program, outputs = d.objective.objective_program, tuple(d.jet.grad_jet[0])
for j in range(1, k):
    new, outputs, rates = jet.next_derivative(program, outputs, rates, names)
    program = program + new
    rates = rates_after(rates, j, sp.S.Zero)
sympy_s = time.perf_counter() - start
sympy_n = len(program.assignments)

start = time.perf_counter()
assignments = [(se.sympify(s), se.sympify(v)) for s, v in d.objective.objective_program.assignments]
outputs = [se.sympify(e) for e in d.jet.grad_jet[0]]
chains = [[se.sympify(s) for s in row] for row in chains]
convert_s = time.perf_counter() - start
count = [0]

def fresh():
    count[0] += 1
    return se.Symbol(f"_s{count[0]}")

def derivative(expr, moving):
    terms = [expr.diff(v) * moving[v] for v in sorted(expr.free_symbols & moving.keys(), key=str)]
    return se.Add(*terms) if terms else se.Integer(0)

def atomize(exprs, out, memo):
    def visit(node):
        if not node.args:
            return node
        if node in memo:
            return memo[node]
        new = node.func(*[visit(a) for a in node.args])
        sym = fresh()
        out.append((sym, new))
        memo[node] = sym
        return sym
    return [visit(e) for e in exprs]

start = time.perf_counter()
rates = {se.Symbol("t"): se.Integer(1)} | dict(zip([se.sympify(y) for y in ys], chains[0]))
for j in range(1, k):
    moving, new = dict(rates), []
    for sym, value in assignments:
        if sym in moving:
            continue
        rate = derivative(value, moving)
        if rate == 0:
            continue
        if rate.is_Symbol or rate.is_Number:
            moving[sym] = rate
            continue
        name = fresh()
        new.append((name, rate))
        moving[sym] = name
    derived = [derivative(e, moving) for e in outputs]
    pieces, memo = [], {}
    for sym, value in new:
        (root,) = atomize([value], pieces, memo)
        pieces.append((sym, root))
    outputs = atomize(derived, pieces, memo)
    assignments = assignments + pieces
    rates = rates_after(moving, j, se.Integer(0))
symengine_s = time.perf_counter() - start

start = time.perf_counter()
back = [(s._sympy_(), v._sympy_()) for s, v in assignments]
back_s = time.perf_counter() - start
print(json.dumps({
    "k": k, "sympy_s": sympy_s, "sympy_n": sympy_n, "symengine_s": symengine_s,
    "symengine_n": len(assignments), "convert_s": convert_s, "back_s": back_s,
}))
"""


def _spec(name: str, folder: Path) -> Path:
    """``chain12`` or ``ringN`` (the bundled ring with ``i = N``), as a file."""
    if name == "chain12":
        return ROOT / "benchmarks" / "chain12.toml"
    return ring_spec(int(name.removeprefix("ring")), folder)


def measure(names: list[str]) -> list[dict[str, float | str]]:
    """Each spec's jet on both cores (one fresh interpreter) and its cold stage times."""
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        for name in names:
            spec = _spec(name, folder)
            done = subprocess.run(
                [sys.executable, "-c", _PROBE, str(spec)],
                capture_output=True,
                text=True,
                check=True,
            )
            row: dict[str, float | str] = {"spec": name, **json.loads(done.stdout)}
            stages = generate_cold(spec, folder / f"out-{name}", timeout=900.0)
            row |= {f"cli_{k}": v for k, v in stages.items()}
            rows.append(row)
            print(
                f"{name}: sympy {row['sympy_s']:.2f} s, symengine {row['symengine_s']:.2f} s, "
                f"back {row['back_s']:.2f} s",
                file=sys.stderr,
            )
    return rows


def table(rows: list[dict[str, float | str]]) -> str:
    """The measurements as a Markdown table."""
    head = (
        "| spec | k | assignments | sympy jet s | SymEngine jet s | sympy / SymEngine "
        "| SymEngine -> sympy s | generate: derive s | generate: lower s |\n"
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|\n"
    )
    lines = [
        f"| {r['spec']} | {r['k']} | {r['sympy_n']} | {r['sympy_s']:.2f} | "
        f"{r['symengine_s']:.2f} | {float(r['sympy_s']) / float(r['symengine_s']):.1f} | "
        f"{r['back_s']:.2f} | {r['cli_derive']:.2f} | {r['cli_lower']:.2f} |"
        for r in rows
    ]
    return head + "\n".join(lines) + "\n"


def main() -> None:
    """Measure the specs given (default: chain12 and rings of 8, 32, 128); print, write."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--specs", default="chain12,ring8,ring32,ring128")
    parser.add_argument("--write", type=Path, help="write the table as Markdown here")
    args = parser.parse_args()
    try:
        import symengine  # noqa: F401, PLC0415
    except ImportError:
        sys.exit("bench_representation needs symengine: pip install -e '.[bench]'")
    rows = measure(args.specs.split(","))
    text = table(rows)
    print(text)
    if args.write:
        import symengine  # noqa: PLC0415
        import sympy  # noqa: PLC0415

        args.write.write_text(
            "# The derivation's representation: sympy or SymEngine\n\n"
            "Command: `make bench-representation  # python benchmarks/bench_representation.py "
            "--write benchmarks/REPRESENTATION.md`  \n"
            f"Machine: {platform.machine()}, {os.cpu_count()} cores, Python "
            f"{platform.python_version()}; sympy {sympy.__version__}, symengine "
            f"{symengine.__version__}  \n"
            f"Run at {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}\n\n"
            "The k - 1 total derivatives of f0's gradient program (the jet's repeated "
            "part), with the same algorithm on each core, each spec in a fresh "
            "interpreter; `SymEngine -> sympy` converts the resulting program back; the "
            "last two columns are a cold `generate`'s derive and lower stages "
            "(`--timings`), for scale.\n\n" + text
        )


if __name__ == "__main__":
    main()
