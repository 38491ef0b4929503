"""Tuning against sweeps: CMA-ES against TPE and random search of the same budget, one run.

Run: ``make tune-example`` (``python benchmarks/bench_tune.py --write benchmarks/TUNE.md
--doc docs/tune.md``). Every row is one cold ``tvopt-codegen tune`` process on a local
cluster of 2 workers, timed from outside; the figures are read back from the folder it
wrote (``tune.json``). The cases are the issue's:

- **PVTOL** with 10% mass and inertia mismatch, measurement noise 1e-3, 100 Hz sampling
  and saturated inputs (thrust within [0, 20], torque within +-5): 200 candidates of 200
  samples each, the best and the bundled poles checked on 1,000 fresh samples (another
  seed). The same command is run a second time (its tuned spec must be byte-identical),
  and a third time killed by SIGTERM halfway and resumed (it must end where the
  uninterrupted run did).
- **planar_arm3** (mass-matrix form) with its three masses 10% off, the same noise and
  sampling, torques within about 1.5 times their nominal peaks: 100 candidates of 100
  samples each, 1,000 fresh samples.

optuna's TPE (``--method tpe``) and random search (``--method random``) run the same
budget in the same batches, from the same seed.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
START, END = "<!-- tune-example: benchmarks/bench_tune.py -->", "<!-- /tune-example -->"
SEED = 2026

PVTOL = (
    "pvtol",
    "--plant-param", "m=normal(1, 0.1)",
    "--plant-param", "J=normal(1, 0.1)",
    "--measurement-noise", "0.001",
    "--sample-time", "0.01",
    "--saturation", "thrust=0:20",
    "--saturation", "torque=5",
    "--evaluations", "200",
    "--samples", "200",
)  # fmt: skip
ARM = (
    "planar_arm3",
    "--plant-param", "m1=normal(2, 0.2)",
    "--plant-param", "m2=normal(1.75, 0.175)",
    "--plant-param", "m3=normal(1.5, 0.15)",
    "--measurement-noise", "0.001",
    "--sample-time", "0.01",
    "--saturation", "tau1=45",
    "--saturation", "tau2=18",
    "--saturation", "tau3=6",
    "--evaluations", "100",
    "--samples", "100",
)  # fmt: skip
COMMON = ("--seed", str(SEED), "--check-samples", "1000", "--workers", "2", "--progress", "never")


def command(case: tuple[str, ...], out: Path, *extra: str) -> list[str]:
    """The ``tvopt-codegen tune`` command line of a case."""
    tune = [sys.executable, "-m", "tvopt_codegen", "tune"]
    return [*tune, *case, *COMMON, *extra, "--out", str(out)]


def run(case: tuple[str, ...], out: Path, *extra: str) -> tuple[float, dict[str, Any]]:
    """One cold process: its wall time and its record."""
    started = time.perf_counter()
    done = subprocess.run(command(case, out, *extra), capture_output=True, text=True, check=False)
    wall = time.perf_counter() - started
    if done.returncode:
        raise SystemExit(f"{case[0]}: exit {done.returncode}: {done.stderr.strip()}")
    return wall, json.loads((out / "tune.json").read_text())


def killed_and_resumed(case: tuple[str, ...], out: Path, after: float) -> tuple[int, int]:
    """Kill a tune by SIGTERM ``after`` seconds in, resume it; evaluations kept, exit code."""
    process = subprocess.Popen(
        command(case, out), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True
    )
    time.sleep(after)
    process.send_signal(signal.SIGTERM)
    process.communicate(timeout=600)
    kept = len(json.loads((out / "tune.json").read_text())["evaluations"])
    resumed = subprocess.run(
        [sys.executable, "-m", "tvopt_codegen", "tune", "--resume", str(out), "--workers", "2",
         "--progress", "never"],
        capture_output=True, text=True, check=False,
    )  # fmt: skip
    if resumed.returncode:
        raise SystemExit(f"resume: exit {resumed.returncode}: {resumed.stderr.strip()}")
    return kept, process.returncode


def poles(evaluation: dict[str, Any]) -> str:
    """The chosen poles (a pair once) and bandwidth, as the tables print them."""
    parts = []
    for re, im in evaluation["poles"]:
        if im < 0:
            continue
        parts.append(f"{re:g}" if im == 0 else f"{re:g} ± {im:g}j")
    text = ", ".join(parts)
    return text + (f"; bandwidth {evaluation['bandwidth']:g}" if evaluation["bandwidth"] else "")


def row(name: str, method: str, wall: float, record: dict[str, Any]) -> str:
    """A table row: the fresh check of the spec's gains and the tuned ones."""
    fresh = record["fresh"]
    before, after = fresh["original"], fresh["tuned"]
    chosen = record["evaluations"][record["best"]]

    def number(value: float) -> str:
        return f"{value:.4g}"

    ratio = after["p95_final_error"] / before["p95_final_error"]
    return (
        f"| {name} | {method} | {wall:.0f} s | {poles(chosen)} | "
        f"{number(before['p95_final_error'])} | {number(after['p95_final_error'])} | "
        f"{ratio:.3f} | {before['failures']} / {100 * before['failure_bound']:.2f}% | "
        f"{after['failures']} / {100 * after['failure_bound']:.2f}% | "
        f"{100 * after['saturation']:.1f}% |"
    )


def main() -> None:
    """Measure, print the section, put it in ``--write`` and ``--doc``."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--write", help="the benchmark's page (benchmarks/TUNE.md)")
    parser.add_argument("--doc", help="the page whose worked example this fills (docs/tune.md)")
    args = parser.parse_args()
    work = Path(tempfile.mkdtemp(prefix="bench-tune-"))
    results: dict[tuple[str, str], tuple[float, dict[str, Any]]] = {}
    for name, case in (("pvtol", PVTOL), ("planar_arm3", ARM)):
        for method in ("cma", "tpe", "random"):
            print(f"{name}, {method} ...", file=sys.stderr, flush=True)
            results[name, method] = run(case, work / f"{name}-{method}", "--method", method)
    print("pvtol, cma again ...", file=sys.stderr, flush=True)
    run(PVTOL, work / "pvtol-again")
    same = (work / "pvtol-again" / "pvtol_tuned.toml").read_bytes() == (
        work / "pvtol-cma" / "pvtol_tuned.toml"
    ).read_bytes()
    print("pvtol, killed and resumed ...", file=sys.stderr, flush=True)
    half = results["pvtol", "cma"][0] / 2
    kept, code = killed_and_resumed(PVTOL, work / "pvtol-resumed", half)
    resumed_same = (work / "pvtol-resumed" / "pvtol_tuned.toml").read_bytes() == (
        work / "pvtol-cma" / "pvtol_tuned.toml"
    ).read_bytes()
    figure = work / "pvtol-cma" / "tune_tradeoff.png"
    cores = os.cpu_count() or 1
    lines = [
        START,
        "",
        f"Machine: {platform.machine()}, {cores} cores, Python {platform.python_version()}; "
        "each row one cold `tvopt-codegen tune` process on a local cluster of 2 workers "
        f"(`--workers 2 --seed {SEED} --check-samples 1000`). Produced by `make tune-example` "
        "(`python benchmarks/bench_tune.py --write benchmarks/TUNE.md --doc docs/tune.md`).",
        "",
        "- PVTOL: `tvopt-codegen tune pvtol --plant-param m='normal(1, 0.1)' --plant-param "
        "J='normal(1, 0.1)' --measurement-noise 0.001 --sample-time 0.01 --saturation "
        "thrust=0:20 --saturation torque=5 --evaluations 200 --samples 200`; the bundled "
        "poles are -1, -1.5, -2, -2.5.",
        "- planar_arm3 (mass-matrix form): `--plant-param m1='normal(2, 0.2)' "
        "--plant-param m2='normal(1.75, 0.175)' --plant-param m3='normal(1.5, 0.15)' "
        "--measurement-noise 0.001 --sample-time 0.01 --saturation tau1=45 --saturation "
        "tau2=18 --saturation tau3=6 --evaluations 100 --samples 100` (the torques within "
        "about 1.5 times their nominal peaks); the bundled poles are -2, -3.",
        "",
        "The objective is the default, the p95 of the final |y - y*| (a failed sample "
        "counts as infinite), under the default constraint: the failure probability's "
        "Clopper-Pearson bound no worse than the bundled poles' on the tuning samples. The "
        "columns after the poles are measured on 1,000 fresh samples (seed "
        f"{SEED + 1}), which the search never saw.",
        "",
        "| example | search | wall | tuned poles | p95 final error, bundled | p95, tuned | "
        "tuned / bundled | failures / bound, bundled | failures / bound, tuned | "
        "time saturated, tuned |",
        "|---|---|---:|---|---:|---:|---:|---:|---:|---:|",
    ]
    for (name, method), (wall, record) in results.items():
        lines.append(row(name, method, wall, record))

    def fresh(name: str, method: str) -> float:
        return float(results[name, method][1]["fresh"]["tuned"]["p95_final_error"])

    lines += [
        "",
        "- On the fresh samples, against the same budget in the same batches: "
        + "; ".join(
            f"{name}: CMA-ES {fresh(name, 'cma'):.4g}, TPE {fresh(name, 'tpe'):.4g}, random "
            f"{fresh(name, 'random'):.4g}"
            for name in ("pvtol", "planar_arm3")
        )
        + ".",
        f"- The same PVTOL command run twice: tuned specs byte-identical: "
        f"**{'yes' if same else 'no'}**.",
        f"- Killed by SIGTERM after {half:.0f} s (exit {code}, {kept - 1} of 200 candidates "
        f"recorded), then `tune --resume`: the tuned spec byte-identical to the "
        f"uninterrupted run's: **{'yes' if resumed_same else 'no'}**.",
        "",
        END,
    ]
    section = "\n".join(lines) + "\n"
    print(section)
    for target in (args.write, args.doc):
        if target:
            path = Path(target)
            text = path.read_text() if path.exists() else ""
            if START in text and END in text:
                head, rest = text.split(START, 1)
                text = head + section.rstrip("\n") + rest.split(END, 1)[1]
            else:
                text = text + ("\n" if text else "") + section
            path.write_text(text)
    if args.doc:
        target = ROOT / "docs" / "figures" / "tune_pvtol_tradeoff.png"
        shutil.copyfile(figure, target)
        shutil.copyfile(work / "pvtol-cma" / "tune.md", ROOT / "docs" / "tune-pvtol.md")
    shutil.rmtree(work)


if __name__ == "__main__":
    main()
