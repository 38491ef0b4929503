"""Tracking from sampled references against the noise on the samples.

For each bundled references twin that ``make reference-noise`` lists, the nominal
references are sampled at 1 kHz over the horizon, Gaussian noise of three levels is
added, the spec's differentiator estimates the jets online, and the closed loop runs
(``simulate --reference-file``). The table gives the final ``|y - y*|`` relative to the
initial one, ``sup |d|`` of ``E' = H E + d``, and the input-to-state check.

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
    print(text)
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
        args.write.write_text(header + text + "\n", encoding="utf-8")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
