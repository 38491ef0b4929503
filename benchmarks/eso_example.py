"""The extended-state observer against the matched-input observer and integral action, by sweeps.

Run: ``make eso-example`` (writes docs/eso.md).

Three plants, each swept with its parameters off the model's by 10% (sd, normal), the
controller stepped every millisecond (both observers run in the sampled controller):

- ``drag_vehicle`` (bundled): thrust along the body axis, no sway input, linear drag;
  mass, inertia and both drags off. The sideways drag's mismatch lies outside the span of
  ``G``: the matched-input observer cannot cancel it.
- ``pvtol`` (bundled): mass and inertia off, a mismatch inside the span of ``G``.
- the two-link arm of ``tests/specs/arm2_mass.toml`` in mass-matrix form, and the same
  arm written as ``[system.dynamics]`` (``M^-1`` by hand): inertias off.

Options: ``plain``; ``integral`` (one more pole, as docs/robust.md); ``observer``
(``[robust.observer] bandwidth = 20``); ``both``; ``eso`` (``[robust.eso] bandwidth =
20``); ``eso+integral``. Scenarios: ``clean`` (exact measurements) and ``noise`` (sd 1e-3
on every measured plant state). Each sweep: ``tvopt_codegen.sweep.run_sweep`` on one
LocalCluster of 2 workers, the seed fixed.
"""

from __future__ import annotations

import argparse
import platform
import re
import sys
import time
from pathlib import Path
from typing import Any

from tvopt_codegen import sweep
from tvopt_codegen.derivation import derive
from tvopt_codegen.lowering.ir import lower
from tvopt_codegen.spec import parse_spec

sys.path.insert(0, str(Path(__file__).resolve().parent))
from robust_example import statistics  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
EXAMPLES = ROOT / "tvopt_codegen" / "examples"
SAMPLES, SEED, H, NOISE, BANDWIDTH = 200, 2026, 1e-3, 1e-3, 20.0
#: The pole integral action adds (the vehicle's and PVTOL's slowest; the arm's as its own).
INTEGRAL_POLE = {"drag_vehicle": -0.8, "pvtol": -0.8, "arm2_mass": -4.0, "arm2_dynamics": -4.0}
SPREAD = {
    "drag_vehicle": (
        ("m", "normal(1, 0.1)"),
        ("J", "normal(0.1, 0.01)"),
        ("c", "normal(0.4, 0.04)"),
        ("cr", "normal(0.1, 0.01)"),
    ),
    "pvtol": (("m", "normal(1, 0.1)"), ("J", "normal(1, 0.1)")),
    "arm2_mass": (
        ("a1", "normal(3, 0.3)"),
        ("a2", "normal(0.5, 0.05)"),
        ("a3", "normal(0.4, 0.04)"),
    ),
}
SPREAD["arm2_dynamics"] = SPREAD["arm2_mass"]
#: Per plant, groups of (scenarios, options), each scenario swept with each option.
PLAN: dict[str, tuple[tuple[tuple[str, ...], tuple[str, ...]], ...]] = {
    "drag_vehicle": (
        (
            ("clean", "noise"),
            ("plain", "integral", "observer", "both", "eso", "eso+integral", "eso@10", "eso@40"),
        ),
        # Sampled slower: the observer's discrete twin keeps its poles at exp(-omega h).
        (("clean@10", "clean@50"), ("plain", "eso")),
    ),
    "pvtol": ((("clean", "noise"), ("plain", "integral", "observer", "eso", "eso+integral")),),
    "arm2_mass": ((("clean",), ("plain", "observer", "eso")),),
    "arm2_dynamics": ((("clean",), ("plain", "observer", "eso")),),
}

_M11, _M12, _M22 = "(a1 + 2*a2*cos(q2))", "(a3 + a2*cos(q2))", "a3"
_F1 = "(a2*sin(q2)*dq2*(2*dq1 + dq2) - g1*cos(q1) - g2*cos(q1 + q2) + tau1)"
_F2 = "(-a2*sin(q2)*dq1**2 - g2*cos(q1 + q2) + tau2)"
_DET = f"({_M11}*{_M22} - {_M12}**2)"


def base_text(example: str) -> str:
    """The spec as bundled, or the test arm, or its twin in [system.dynamics]."""
    if example == "arm2_mass":
        return (ROOT / "tests" / "specs" / "arm2_mass.toml").read_text(encoding="utf-8")
    if example == "arm2_dynamics":
        text = base_text("arm2_mass")
        mechanics = re.search(r"\[system\.mechanics\].*?(?=\n\[)", text, re.S)
        assert mechanics is not None
        dynamics = "\n".join(
            [
                "[system.dynamics]",
                'q1 = "dq1"',
                'q2 = "dq2"',
                f'dq1 = "({_M22}*{_F1} - {_M12}*{_F2})/{_DET}"',
                f'dq2 = "({_M11}*{_F2} - {_M12}*{_F1})/{_DET}"',
            ]
        )
        text = text.replace(mechanics.group(0), dynamics)
        text = text.replace('coordinates = ["q1", "q2"]', 'states = ["q1", "q2", "dq1", "dq2"]')
        return text.replace('name = "arm2"', 'name = "arm2_dynamics"')
    return (EXAMPLES / f"{example}.toml").read_text(encoding="utf-8")


def spec_text(example: str, option: str) -> str:
    """The example's spec with the option's tables appended."""
    text = base_text(example)
    if "integral" in option or option == "both":
        found = re.search(r"^poles = \[(.*)\]$", text, re.M)
        assert found is not None
        text = text.replace(found.group(0), f"poles = [{INTEGRAL_POLE[example]}, {found.group(1)}]")
    extra = []
    if option != "plain":
        extra.append("[robust]")
        if "integral" in option or option == "both":
            extra.append("integral = true")
        if option in ("observer", "both"):
            extra += ["", "[robust.observer]", f"bandwidth = {BANDWIDTH}"]
        if option.startswith("eso"):
            # eso@B: the observer at bandwidth B instead (the noise trade-off).
            bandwidth = float(option.split("@")[1]) if "@" in option else BANDWIDTH
            extra += ["", "[robust.eso]", f"bandwidth = {bandwidth}"]
    return text + "\n" + "\n".join(extra) + "\n"


def run(client: Any, example: str, option: str, scenario: str, samples: int) -> dict[str, Any]:
    """One sweep of ``samples`` closed loops; its statistics."""
    text = spec_text(example, option)
    d = derive(parse_spec(f"{example}_{option}.toml", text.encode()))
    program = sweep.sweep_program(lower(d))
    spread = tuple(
        (name, sweep.parse_distribution(dist, "--plant-param", name))
        for name, dist in SPREAD[example]
    )
    options = sweep.SweepOptions(
        samples=samples,
        seed=SEED,
        t_final=d.spec.t_final,
        plant_params=spread,
        limits=program.limits,
        noise=NOISE if scenario == "noise" else 0.0,
        # "clean@S": exact measurements, the controller stepped every S milliseconds.
        sample_time=float(scenario.split("@")[1]) / 1000 if "@" in scenario else H,
        points=201,
    )
    sweep.check_options(program, options)
    done = sweep.run_sweep(client, program, options)
    return {"example": example, "option": option, "scenario": scenario, **statistics(done)}


READING = [
    "## Reading the tables",
    "",
    "- **A mismatch outside the span of G** (the drag vehicle's sideways drag, no sway "
    "input): only the extended-state observer cancels it. The matched-input observer "
    "estimates a disturbance on the inputs and leaves the rest; integral action removes "
    "a constant offset, and this one moves with the circling target.",
    "- **A mismatch inside the span of G** (PVTOL's mass and inertia): both observers "
    "cancel it; the extended-state observer's estimate of the outputs' derivatives also "
    "takes up what the model's Phi(x) gets wrong.",
    "- **A disturbance that moves with the target** (the arm's inertial forces): the "
    "extended-state observer's estimate of the lumped term lags it by about its rate over "
    "the bandwidth, the matched-input observer estimates the input disturbance, which moves "
    "less; there the matched-input observer is the better choice. The arm in mass-matrix "
    "form and written as `[system.dynamics]` give the same statistics.",
    "- **Noise against bandwidth**: the extended-state observer differentiates the "
    "measured outputs up to their relative degree, so noise reaches its top estimates "
    "amplified by about bandwidth^r; a higher bandwidth follows a moving disturbance more "
    "closely. The `eso@10` and `eso@40` rows show the trade on the vehicle: without noise "
    "40 rad/s does best, with noise of sd 1e-3 on the measured state 10 rad/s does, and at "
    "40 rad/s the noise drives the estimates, and a loop, off (the failures column).",
    "- **Sample time**: the sampled controller runs the observer's exact discrete twin, "
    "with every pole of its error at exp(-bandwidth h) whatever h: on the vehicle at "
    "20 rad/s, stepping every 10 or 50 ms (bandwidth x h = 0.2 or 1) leaves the final "
    "error where 1 ms does (the `clean@10` and `clean@50` rows).",
    "",
]


def _g(value: float) -> str:
    return f"{value:.3g}"


def document(rows: list[dict[str, Any]], seconds: float, command: str) -> str:
    """docs/eso.md."""
    out = [
        "# The extended-state observer, judged by sweeps",
        "",
        f"Command: `{command}`.",
        f"Machine: {platform.machine()}, Python {platform.python_version()}; "
        f"{seconds:.0f} s in all; seed {SEED}; {rows[0]['runs']} samples per sweep.",
        "",
        "Every sweep steps the controller every millisecond (both observers run in the "
        "sampled controller), unless a scenario says otherwise: `clean@S` is the "
        "controller stepped every S ms. `clean`: exact measurements; `noise`: Gaussian "
        "noise of sd "
        f"{NOISE:g} on every measured plant state. `observer` is `[robust.observer] "
        f"bandwidth = {BANDWIDTH:g}` (a matched input disturbance), `eso` is `[robust.eso] "
        f"bandwidth = {BANDWIDTH:g}` (the lumped disturbance at each output's top "
        "derivative), `eso@B` the same at bandwidth B, `integral` adds `[robust] integral = "
        "true` and one pole. Final error: "
        "`|y - y*|` at the end of the horizon; failures: runs whose law became undefined or "
        "that diverged, with the Clopper-Pearson 95% upper bound on the failure probability.",
        "",
    ]
    titles = {
        "drag_vehicle": "drag_vehicle (mass, inertia, both drags: normal, 10% sd)",
        "pvtol": "pvtol (`m`, `J`: normal, 10% sd)",
        "arm2_mass": "two-link arm in mass-matrix form (`a1`, `a2`, `a3`: normal, 10% sd)",
        "arm2_dynamics": "the same arm written as `[system.dynamics]`",
    }
    for example in PLAN:
        mine = [row for row in rows if row["example"] == example]
        out += [
            f"## {titles[example]}",
            "",
            "| scenario | option | median | p95 | worst | p95 of plain's | failures "
            "| 95% upper bound |",
            "|---|---|---:|---:|---:|---:|---:|---:|",
        ]
        for row in mine:
            plain = next(
                r for r in mine if r["option"] == "plain" and r["scenario"] == row["scenario"]
            )
            ratio = row["p95"] / plain["p95"]
            out.append(
                f"| {row['scenario']} | {row['option']} | {_g(row['median'])} | "
                f"{_g(row['p95'])} | {_g(row['worst'])} | {100 * ratio:.3g}% | "
                f"{row['failures']}/{row['runs']} | {100 * row['upper']:.2g}% |"
            )
        out.append("")
    out += READING
    return "\n".join(out)


def main() -> int:
    """Run the sweeps; print the document, or write it with ``--write``."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--write", type=Path, help="write the document here")
    parser.add_argument("--samples", type=int, default=SAMPLES)
    args = parser.parse_args()
    start = time.perf_counter()
    client, cluster = sweep.connect(2, None)
    rows = []
    try:
        for example, groups in PLAN.items():
            for scenarios, options in groups:
                for scenario in scenarios:
                    for option in options:
                        row = run(client, example, option, scenario, args.samples)
                        print(
                            f"{example} {scenario} {option}: p95 {row['p95']:.3g}, "
                            f"failures {row['failures']}/{row['runs']}",
                            file=sys.stderr,
                            flush=True,
                        )
                        rows.append(row)
    finally:
        client.close()
        if cluster is not None:
            cluster.close()
    command = "make eso-example (python benchmarks/eso_example.py --write docs/eso.md)"
    text = document(rows, time.perf_counter() - start, command)
    if args.write:
        args.write.write_text(text + "\n", encoding="utf-8")
    else:
        print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
