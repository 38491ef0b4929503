"""What the figures of a run, a sweep and a replay show, as data (:class:`Plot`).

Each figure is described here, where the run's results are, as the calls its panels
make: arrays, labels and styles, nothing of matplotlib. :mod:`tvopt_codegen.runs.drawing`
draws the descriptions, in this process or in a drawing process started before the
derivation (``simulate``), so that matplotlib's import does not wait for sympy's.

The planar figure follows the paper's Figs. 1-3: the moving objects, the target path
y* (dashed), each agent's path, and start points marked with stars.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING, Any, TypeAlias

import numpy as np

from tvopt_codegen import symbolic as sx
from tvopt_codegen.derivation import Derivation
from tvopt_codegen.runs.drawing import Panel, Plot

if TYPE_CHECKING:
    from tvopt_codegen.simulation import Result
    from tvopt_codegen.simulation.result import Trajectories

    #: A run as the figures of the run alone read it: certified or not yet.
    Run: TypeAlias = Result | Trajectories
    from tvopt_codegen.simulation.sampled import SampledResult
    from tvopt_codegen.sweep import SweepProgram

_COLORS = ("tab:red", "tab:purple", "tab:orange", "tab:brown", "tab:pink", "tab:olive")
_OBJECT_COLORS = ("black", "tab:blue", "tab:gray", "tab:cyan")


def _axes(stem: str, width: float, height: float) -> tuple[Plot, Panel]:
    """A one-panel figure and its panel."""
    plot = Plot(stem, (width, height))
    return plot, plot.panels[0]


def _two_panels(stem: str) -> tuple[Plot, Panel, Panel]:
    """A figure of two panels over one time axis, and its panels, top first."""
    plot = Plot(stem, (6.4, 6.0), rows=2, sharex=True)
    return plot, plot.panels[0], plot.panels[1]


def _signal_values(derivation: Derivation, result: Run, name: str) -> np.ndarray:
    d = derivation
    references = [r.name for r in d.model.references]
    if name in references and result.references is not None:
        # A reference: its true path when known, else what the controller was given.
        source = result.references
        jets = source.exact or source.jets
        row = references.index(name)
        return np.array([jets(t)[row, 0] for t in result.t])
    expr = dict((s.name, e) for s, e in d.model.signals)[name]
    values = [
        result.options.params.get(q.name, v)
        for q, v in zip(d.model.params, d.model.defaults, strict=True)
    ]
    # NumPy's module, not the name "numpy": lambdify would then run `from numpy import *`,
    # which imports f2py, numpy.testing and a dozen more (0.1 s of a small simulate).
    func = sx.lambdify([d.model.t, *d.model.params], expr, modules=[np])
    return np.broadcast_to(np.asarray(func(result.t, *values), dtype=float), result.t.shape)


def trajectory_figure(derivation: Derivation, result: Run) -> Plot:
    """The x-y picture: objects, y*, agent paths, stars at the starts."""
    d, r = derivation, result
    index = {name: i for i, name in enumerate(d.spec.outputs)}
    fig, ax = _axes(f"{d.spec.name}_paths", 6.4, 5.2)
    for j, (x_name, y_name) in enumerate(d.spec.objects):
        ox, oy = _signal_values(d, r, x_name), _signal_values(d, r, y_name)
        color = _OBJECT_COLORS[j % len(_OBJECT_COLORS)]
        ax.plot(ox, oy, color=color, lw=1.5, label=f"object {j + 1} ({x_name}, {y_name})")
        ax.plot(ox[0], oy[0], "*", color=color, ms=12)
    for j, (nx, ny) in enumerate(d.spec.agents):
        ix, iy = index[nx], index[ny]
        color = _COLORS[j % len(_COLORS)]
        ax.plot(r.outputs[ix], r.outputs[iy], color=color, lw=2, label=f"agent ({nx}, {ny})")
        ax.plot(
            r.target[ix],
            r.target[iy],
            "--",
            color="tab:green",
            lw=1.5,
            zorder=3,
            label="target y*" if j == 0 else None,
        )
        ax.plot(r.outputs[ix, 0], r.outputs[iy, 0], "*", color=color, ms=14)
    ax.set_xlabel("x")
    ax.set_ylabel("y")
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="best")
    ax.set_title(f"{d.spec.name}: paths over [0, {r.t[-1]:g}] (stars: starts)")
    return fig


def convergence_figure(derivation: Derivation, result: Result) -> Plot:
    """|y - y*| and |E| on a log scale, with the theorem's bounds."""
    r = result
    fig, ax = _axes(f"{derivation.spec.name}_convergence", 6.4, 4.0)
    norms = np.linalg.norm(r.E.reshape(len(r.t), -1), axis=1)
    floor = 1e-16
    ax.semilogy(r.t, np.maximum(r.error, floor), color="tab:red", lw=2, label="|y - y*|")
    ax.semilogy(r.t, r.bound, "--", color="tab:red", lw=1, label="bound C exp(-alpha t)")
    ax.semilogy(r.t, np.maximum(norms, floor), color="tab:blue", lw=2, label="|E|")
    ax.semilogy(
        r.t,
        r.c * norms[0] * np.exp(-r.alpha * r.t),
        "--",
        color="tab:blue",
        lw=1,
        label="c |E(0)| exp(-alpha t)",
    )
    ax.set_xlabel("t")
    ax.set_ylim(bottom=max(floor, 1e-3 * float(np.min(np.maximum(norms, floor)))))
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8)
    status = "certificate passed" if r.passed else "certificate FAILED"
    ax.set_title(f"{derivation.spec.name}: convergence (alpha = {r.alpha:.3g}; {status})")
    return fig


def inputs_figure(derivation: Derivation, result: Run) -> Plot:
    """Plant inputs over time."""
    fig, ax = _axes(f"{derivation.spec.name}_inputs", 6.4, 3.6)
    for i, name in enumerate(derivation.spec.inputs):
        ax.plot(result.t, result.inputs[i], lw=1.5, label=name)
    ax.set_xlabel("t")
    ax.set_ylabel("u")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    ax.set_title(f"{derivation.spec.name}: plant inputs")
    return fig


def references_figure(derivation: Derivation, result: Result) -> Plot:
    """References estimated from samples: samples, estimate, truth, and the error.

    The bottom panel shows the estimate's error per derivative order and ``|y - y*|``.
    """
    d, r = derivation, result
    source = r.references
    fig, top, bottom = _two_panels(f"{d.spec.name}_references")
    estimated = np.array([source.jets(t) for t in r.t])  # (T, n_refs, q + 1)
    truth = np.array([source.exact(t) for t in r.t]) if source.exact is not None else None
    shown = np.linspace(0, len(source.times) - 1, min(len(source.times), 400)).astype(int)
    for i, name in enumerate(ref.name for ref in d.model.references):
        color = _COLORS[i % len(_COLORS)]
        top.plot(source.times[shown], source.samples[i, shown], ".", ms=2, color=color, alpha=0.4)
        top.plot(r.t, estimated[:, i, 0], color=color, lw=1.5, label=f"{name} estimated")
        if truth is not None:
            top.plot(r.t, truth[:, i, 0], "--", color="black", lw=0.8)
    top.set_ylabel("reference")
    top.grid(alpha=0.3)
    top.legend(fontsize=7, ncol=2)
    top.set_title(
        f"{d.spec.name}: references from samples (dots; noise sd {source.noise:g}), true (dashed)"
    )
    if truth is not None:
        for order in range(estimated.shape[2]):
            gap = np.linalg.norm(estimated[:, :, order] - truth[:, :, order], axis=1)
            bottom.semilogy(r.t, np.maximum(gap, 1e-16), lw=1.2, label=f"derivative {order}")
        bottom.set_ylabel("|estimate - truth|")
        bottom.legend(fontsize=8)
    bottom.semilogy(r.t, np.maximum(r.error, 1e-16), color="black", lw=2, label="|y - y*|")
    bottom.set_xlabel("t")
    bottom.grid(alpha=0.3, which="both")
    bottom.legend(fontsize=8)
    return fig


def constraints_figure(derivation: Derivation, result: Result) -> Plot:
    """Each constraint's two sides as the boundary moves, and how far it is from failing.

    Below: the margin ``s - g`` of each inequality, and ``|a|`` of each equality under
    its bound ``c e^(-alpha t) |E(0)|``.
    """
    d, r = derivation, result
    check = r.constraints
    fig, top, bottom = _two_panels(f"{d.spec.name}_constraints")
    p = len(d.model.constraints)
    for i, constraint in enumerate((*d.model.constraints, *d.model.equalities)):
        color = _COLORS[i % len(_COLORS)]
        top.plot(r.t, check.lhs[i], color=color, lw=1.5, label=f"{constraint.name}: lhs")
        top.plot(r.t, check.rhs[i], "--", color=color, lw=1, label=f"{constraint.name}: rhs")
        if i < p:
            value, label = check.margins[i], f"s - g, {constraint.name}"
        else:
            value, label = np.abs(check.equality[i - p]), f"|a|, {constraint.name}"
        bottom.semilogy(r.t, np.maximum(value, 1e-16), color=color, lw=1.5, label=label)
    if np.any(check.slack > 0):
        bottom.semilogy(r.t, np.maximum(check.slack, 1e-16), ":", color="black", label="slack s")
    if d.model.equalities:
        envelope = r.c * float(np.linalg.norm(r.E[0])) * np.exp(-r.alpha * r.t)
        bottom.semilogy(
            r.t, envelope, ":", color="gray", label="c e^(-alpha t) |E(0)| (bound on |a|)"
        )
    top.grid(alpha=0.3)
    top.legend(fontsize=7, ncol=2)
    top.set_title(f"{d.spec.name}: constraints (dashed: the moving boundary)")
    bottom.set_xlabel("t")
    bottom.set_ylabel("margin" if not d.model.equalities else "margin, |a|")
    bottom.grid(alpha=0.3, which="both")
    bottom.legend(fontsize=7)
    return fig


def early_figures(derivation: Derivation, run: Run) -> list[Plot]:
    """The figures of :func:`figures` that show the run alone, not its certificate.

    ``<name>_paths`` (with agents) and ``<name>_inputs``: drawn while the run is
    certified, from the arrays its :class:`Result` then holds.
    """
    plots = [trajectory_figure(derivation, run)] if derivation.spec.agents else []
    return [*plots, inputs_figure(derivation, run)]


def figures(derivation: Derivation, result: Result) -> list[Plot]:
    """All figures of a run: ``<name>_{paths,convergence,inputs}``.

    And ``<name>_constraints`` for a spec with constraints, ``<name>_references`` when
    the references were estimated from samples.
    """
    plots = []
    if derivation.spec.agents:
        plots.append(trajectory_figure(derivation, result))
    plots.append(convergence_figure(derivation, result))
    plots.append(inputs_figure(derivation, result))
    if result.constraints is not None:
        plots.append(constraints_figure(derivation, result))
    if result.references is not None and result.references.estimated:
        plots.append(references_figure(derivation, result))
    return plots


def sampled_figure(derivation: Derivation, result: SampledResult) -> Plot:
    """``<name>_sampled``: the sampled outputs over the continuous ones, their distance."""
    d, r = derivation, result
    fig, top, bottom = _two_panels(f"{d.spec.name}_sampled")
    continuous = r.continuous
    for i, name in enumerate(d.spec.outputs):
        color = _COLORS[i % len(_COLORS)]
        top.plot(continuous.t, continuous.outputs[i], color=color, lw=2, label=f"{name}")
        run = r.runs[0]
        top.step(run.t, run.outputs[i], where="post", color="black", lw=0.8, ls="--")
    top.plot([], [], color="black", lw=0.8, ls="--", label=f"sampled, H = {r.runs[0].h:g}")
    top.set_ylabel("y")
    top.grid(alpha=0.3)
    top.legend(fontsize=8, ncol=2)
    top.set_title(f"{d.spec.name}: continuous (solid) and sampled (dashed) outputs")
    for index, run in enumerate(r.runs):
        bottom.semilogy(
            run.t,
            np.maximum(run.distance, 1e-16),
            lw=1.2,
            color=("tab:red", "tab:blue")[index % 2],
            label=f"|y - y_continuous|, H = {run.h:g} (max {run.deviation:.2e})",
        )
    bottom.set_xlabel("t")
    bottom.grid(alpha=0.3, which="both")
    bottom.legend(fontsize=8)
    return fig


def _trajectory_error(program: SweepProgram, trajectory: np.ndarray) -> tuple[Any, Any]:
    """Times and ``|y - y*|`` of one sweep trajectory (rows: t, s, y, y*, ...)."""
    n, m = len(program.state_names), len(program.output_names)
    y = trajectory[:, 1 + n : 1 + n + m]
    target = trajectory[:, 1 + n + m : 1 + n + 2 * m]
    return trajectory[:, 0], np.linalg.norm(y - target, axis=1)


def sweep_figures(
    program: SweepProgram,
    runs: int,
    finals: np.ndarray,
    settle: np.ndarray,
    worst: Mapping[int, np.ndarray],
) -> list[Plot]:
    """``sweep_histograms``: final error and settling time; ``sweep_worst``: the worst runs.

    ``finals`` and ``settle`` are the ok samples' final errors and settling times (NaN:
    never settled) of the ``runs`` samples.
    """
    histograms = Plot("sweep_histograms", (9.0, 3.6), cols=2)
    left, right = histograms.panels
    ok = finals
    if len(finals):
        positive = np.maximum(finals, 1e-16)
        low, high = np.log10(positive.min()), np.log10(positive.max())
        bins = np.logspace(low - 0.1, high + 0.1, 30) if high > low else 10
        left.hist(positive, bins=bins, color="tab:blue", edgecolor="white")
        left.set_xscale("log")
    left.set_xlabel("final |y - y*|")
    left.set_ylabel("samples")
    left.set_title(f"{program.name}: {len(ok)} of {runs} runs ok", fontsize=10)
    settle = settle[np.isfinite(settle)]
    if len(settle):
        right.hist(settle, bins=30, color="tab:orange", edgecolor="white")
    right.set_xlabel("settling time to 1% of |y - y*|(0) (s)")
    right.set_title(f"{len(ok) - len(settle)} never settled", fontsize=10)
    for axes in (left, right):
        axes.grid(alpha=0.3)
    fig, axes = _axes("sweep_worst", 6.4, 4.0)
    for rank, (index, trajectory) in enumerate(worst.items()):
        t, error = _trajectory_error(program, trajectory)
        axes.semilogy(
            t,
            np.maximum(error, 1e-16),
            color=_COLORS[rank % len(_COLORS)],
            lw=1.2,
            label=f"sample {index}",
        )
    axes.set_xlabel("t")
    axes.set_ylabel("|y - y*|")
    axes.set_title(f"{program.name}: the {len(worst)} worst runs by final error", fontsize=10)
    axes.grid(alpha=0.3, which="both")
    if worst:
        axes.legend(fontsize=8)
    return [histograms, fig]


def replay_figure(program: SweepProgram, row: Mapping[str, Any], trajectory: np.ndarray) -> Plot:
    """``sample_<id>``: one replayed run's outputs over their targets, and its error."""
    n, m = len(program.state_names), len(program.output_names)
    fig, top, bottom = _two_panels(f"sample_{row['sample']}")
    t = trajectory[:, 0]
    for i, name in enumerate(program.output_names):
        color = _COLORS[i % len(_COLORS)]
        top.plot(t, trajectory[:, 1 + n + i], color=color, lw=1.5, label=name)
        top.plot(t, trajectory[:, 1 + n + m + i], color=color, lw=1.0, ls="--")
    top.plot([], [], color="black", lw=1.0, ls="--", label="y* (dashed)")
    top.legend(fontsize=8, ncol=2)
    top.grid(alpha=0.3)
    top.set_title(f"{program.name}, sample {row['sample']}: {row['status']}", fontsize=10)
    _, error = _trajectory_error(program, trajectory)
    bottom.semilogy(t, np.maximum(error, 1e-16), color="tab:red", lw=1.2)
    bottom.set_xlabel("t")
    bottom.set_ylabel("|y - y*|")
    bottom.grid(alpha=0.3, which="both")
    return fig


def tune_figure(
    name: str,
    objective: str,
    points: Sequence[tuple[float, float, float, bool]],
    original: tuple[float, float, float],
    chosen: tuple[float, float, float],
) -> Plot:
    """``tune_tradeoff``: each candidate's objective against saturation and input effort.

    ``points`` are ``(objective, mean fraction of time saturated, p95 peak |u|,
    feasible)`` per candidate; ``original`` and ``chosen`` the spec's gains' and the
    tuned gains' first three.
    """
    plot = Plot("tune_tradeoff", (10.0, 4.0), cols=2)
    left, right = plot.panels
    data = np.array([p[:3] for p in points], dtype=float).reshape(-1, 3)
    feasible = np.array([p[3] for p in points], dtype=bool)
    shown = np.isfinite(data[:, 0])
    for axes, column, label in (
        (left, 1, "mean fraction of time an input is clipped"),
        (right, 2, "p95 of the peak |u|"),
    ):
        for keep, style, legend in (
            (feasible & shown, {"color": "tab:blue", "marker": "o"}, "feasible"),
            (~feasible & shown, {"color": "tab:gray", "marker": "x"}, "infeasible"),
        ):
            if keep.any():
                axes.semilogy(
                    data[keep, column],
                    data[keep, 0],
                    ls="none",
                    ms=4,
                    alpha=0.6,
                    label=legend,
                    **style,
                )
        axes.semilogy(
            [original[column]],
            [original[0]],
            ls="none",
            marker="s",
            ms=9,
            color="black",
            label="the spec's gains",
        )
        axes.semilogy(
            [chosen[column]],
            [chosen[0]],
            ls="none",
            marker="*",
            ms=14,
            color="tab:red",
            label="tuned",
        )
        axes.set_xlabel(label)
        axes.grid(alpha=0.3, which="both")
    left.set_ylabel(objective)
    left.set_title(f"{name}: the spec's gains and {len(points) - 1} candidates", fontsize=10)
    right.legend(fontsize=8)
    return plot
