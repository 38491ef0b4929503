"""Tracking from sampled references against the noise on the samples.

For each bundled references twin that ``make reference-noise`` lists, the nominal
references are sampled at 1 kHz over the horizon, Gaussian noise of three levels is
added, the spec's differentiator estimates the jets online, and the closed loop runs
(``simulate --reference-file``). The table gives the final ``|y - y*|`` relative to the
initial one, ``sup |d|`` of ``E' = H E + d``, and the input-to-state check.

A second table gives the default estimator's accuracy per derivative on clean samples.

Run: ``make reference-noise`` (writes docs/references-noise.md).
"""

from __future__ import annotations

import argparse
import platform
import sys
import time
from pathlib import Path

import numpy as np

from tvopt_codegen import derive, load_spec, lower
from tvopt_codegen.simulation import load_controller, resolve_options, simulate
from tvopt_codegen.simulation.references import exact_jets, sampled_source

SPECS = ("unicycle_switch_refs", "pvtol_refs")
NOISE = (0.0, 1e-3, 1e-2)
RATE = 1000.0


def rows() -> list[tuple[str, str, float, float, float, float, bool]]:
    """(spec, estimator, noise, final/initial, sup |d|, ISS ratio, passed) per run."""
    out = []
    for name in SPECS:
        d = derive(load_spec(name))
        module = load_controller(lower(d), "python")
        options = resolve_options(d)
        jets = exact_jets(d, {})
        times = np.arange(0.0, options.t_final + 0.5 / RATE, 1.0 / RATE)
        values = np.array([jets(t)[:, 0] for t in times]).T
        assert d.spec.estimator is not None
        for noise in NOISE:
            source = sampled_source(d, module, {}, times, values, noise, seed=1)
            result = simulate(d, module, options, references=source)
            ratio = float(result.error[-1] / result.error[0])
            out.append(
                (
                    name,
                    d.spec.estimator.kind,
                    noise,
                    ratio,
                    result.disturbance,
                    result.iss_ratio,
                    result.passed,
                )
            )
    return out


#: The specs whose differentiator is the default (linear, 20 rad/s), for the accuracy
#: table: every bundled references twin that uses it, and a figure-eight with a wall.
ACCURACY_SPECS = (
    "integrator_refs",
    "unicycle_switch_refs",
    "two_unicycles_barrier_refs",
    "unicycle_ring_refs",
    str(Path(__file__).resolve().parent.parent / "tests" / "specs" / "figure8_wall.toml"),
)


def accuracy() -> list[tuple[str, int, list[float], float]]:
    """Per spec: the law's order q, each derivative's relative error, final/initial.

    The estimator alone runs over clean samples at :data:`RATE`; a derivative's error is
    the largest over the second half of the horizon (after the start's transient) over
    the reference's own largest value of that derivative there. Then the closed loop.
    """
    out = []
    for name in ACCURACY_SPECS:
        d = derive(load_spec(name))
        module = load_controller(lower(d), "python")
        jets = exact_jets(d, {})
        times = np.arange(0.0, d.spec.t_final + 0.5 / RATE, 1.0 / RATE)
        truth = np.array([jets(t) for t in times])  # (T, references, q + 1)
        values = truth[:, :, 0].T
        estimator = module.ReferenceEstimator(values[:, 0], 0.0)
        estimates = [estimator.jets(0.0)]
        for index in range(1, len(times)):
            estimates.append(estimator.update(float(times[index]), values[:, index]))
        late = times >= times[-1] / 2
        error = np.abs(np.array(estimates) - truth)[late]
        scale = np.maximum(np.abs(truth[late]).max(axis=(0, 1)), 1e-300)
        relative = (error.max(axis=(0, 1)) / scale).tolist()
        source = sampled_source(d, module, {}, times, values)
        result = simulate(d, module, resolve_options(d), references=source)
        short = Path(name).stem
        out.append(
            (short, d.jet.reference_order, relative, float(result.error[-1] / result.error[0]))
        )
    return out


def accuracy_table(results: list[tuple[str, int, list[float], float]]) -> str:
    """The Markdown table of :func:`accuracy`."""
    width = max(q for _, q, _, _ in results) + 1
    lines = [
        "| spec | q | "
        + " | ".join(f"derivative {j}" for j in range(width))
        + " | final / initial `|y - y*|` |",
        "|---|---|" + "---|" * width + "---|",
    ]
    for name, q, relative, ratio in results:
        cells = [f"{value:.1e}" for value in relative] + ["-"] * (width - len(relative))
        lines.append(f"| {name} | {q} | " + " | ".join(cells) + f" | {ratio:.2e} |")
    return "\n".join(lines)


def table(results: list[tuple[str, str, float, float, float, float, bool]]) -> str:
    """The Markdown table of :func:`rows`."""
    lines = [
        "| spec | estimator | noise sd | final / initial `|y - y*|` | sup `|d|` | "
        "`|E|` / ISS bound (max) | certificate |",
        "|---|---|---|---|---|---|---|",
    ]
    for name, kind, noise, ratio, sup_d, iss, passed in results:
        lines.append(
            f"| {name} | {kind} | {noise:g} | {ratio:.3e} | {sup_d:.3g} | {iss:.3g} | "
            f"{'passed' if passed else 'FAILED'} |"
        )
    return "\n".join(lines)


def main() -> int:
    """Print the table; with --write, store it with the command and the machine."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--write", type=Path, help="also store the table in this Markdown file")
    args = parser.parse_args()
    started = time.perf_counter()
    text = table(rows())
    accurate = accuracy_table(accuracy())
    print(text)
    print()
    print(accurate)
    if args.write:
        header = (
            "# Tracking from sampled references, against noise\n\n"
            "Command: `make reference-noise` (`python benchmarks/reference_noise.py --write "
            "docs/references-noise.md`).\n"
            f"Machine: {platform.machine()}, Python {sys.version.split()[0]}; samples at "
            f"{RATE:g} Hz of the nominal references, Gaussian noise seeded; "
            f"{time.perf_counter() - started:.0f} s in all.\n\n"
            "The bound: `|E(t)| <= c e^(-alpha t) |E(0)| + int_0^t c e^(-alpha (t - s)) "
            "|d(s)| ds`, checked at every output time (ratio at most 1).\n\n"
        )
        accuracy_text = (
            "\n\n## The default estimator's accuracy, per derivative\n\n"
            "The linear differentiator (20 rad/s) estimates one derivative beyond the law's "
            "highest, q, and joins consecutive samples by a straight line (first-order hold). "
            "Clean samples at 1 kHz; each derivative's largest error over the second half of "
            "the horizon, relative to the reference's largest value of that derivative there; "
            "then the closed loop's final over initial `|y - y*|`.\n\n"
        )
        args.write.write_text(header + text + accuracy_text + accurate + "\n", encoding="utf-8")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
