"""The one-screen derivation summary printed by ``tvopt-codegen check``."""

from __future__ import annotations

from collections.abc import Sequence

from tvopt_codegen import symbolic as sx
from tvopt_codegen.derivation import Derivation
from tvopt_codegen.derivation.linearization import law_expressions
from tvopt_codegen.derivation.singularity import undefined_causes
from tvopt_codegen.lowering.ir import KernelSet

#: The most items a list of the summary shows whole; a longer one (a ring of 128 agents
#: has 384 states) shows its first :data:`HEAD` and last :data:`TAIL` and its length, so
#: that each line stays a line (the report lists every item).
LISTED = 24
HEAD, TAIL = 9, 3


def _listed(items: Sequence[str], separator: str = ", ") -> str:
    """``items`` joined, or their first and last few and how many there are."""
    if len(items) <= LISTED:
        return separator.join(items)
    shown = [*items[:HEAD], "...", *items[-TAIL:]]
    return f"{separator.join(shown)} ({len(items)} in all)"


def _number(value: float) -> str:
    return f"{value:.6g}"


def _pole(value: complex) -> str:
    if value.imag == 0:
        return _number(value.real)
    sign = "+" if value.imag > 0 else "-"
    return f"{_number(value.real)}{sign}{_number(abs(value.imag))}i"


def _ordinal(n: int) -> str:
    """``1st``, ``2nd``, ``3rd``, ``4th``, ..., ``11th``, ``21st``."""
    suffix = "th" if 10 <= n % 100 <= 20 else {1: "st", 2: "nd", 3: "rd"}.get(n % 10, "th")
    return f"{n}{suffix}"


def _law_line(d: Derivation) -> str:
    """The control law, every letter on it defined on the same line.

    The paper writes ``u = alpha + beta R^-1 [...]``, where alpha and beta are the
    dynamic extension's maps; beside the decay rate alpha of the error dynamics that
    read as one letter with two meanings, so the line names the extended plant's input
    instead.
    """
    trajectory = (
        f"y_imp^({d.dynamics.k}), the implicit trajectory's {_ordinal(d.dynamics.k)} derivative"
    )
    if d.dynamics.uniform:
        v, law = trajectory, "uniform relative degree theorem"
    else:
        v = f"the padding chains' output, driven by {trajectory}"
        law = "non-uniform theorem"
    if d.linearization.extension.counts:
        lhs = "w"
        ext = (
            f"; w = ({_listed(d.linearization.extension.inputs)}), "
            "the extended plant's inputs (an "
            "integrated input's last derivative, or the input itself)"
        )
    else:
        lhs, ext = "u", ""
    return (
        f"  law: {lhs} = R^-1 (v - p): R the decoupling matrix, p the drift of the outputs' "
        f"highest derivatives (their value at zero input), v = {v}{ext} ({law})"
    )


def format_summary(derivation: Derivation, kernels: KernelSet | None = None) -> str:
    """Describe a derivation in a few lines a control engineer can check at a glance.

    Parameters
    ----------
    derivation : Derivation
        The derivation to describe.
    kernels : KernelSet, optional
        When given, operation counts of the generated kernels are included.

    Returns
    -------
    str
        The summary, lines joined by newlines, no trailing newline.
    """
    d = derivation
    spec = d.spec
    lines = [f"{spec.name}  ({spec.source})"]
    lines.append(
        f"  plant: {len(spec.states)} states ({_listed(spec.states)}), "
        f"{len(spec.inputs)} inputs ({_listed(spec.inputs)}), "
        f"{len(spec.outputs)} outputs ({_listed(spec.outputs)})"
    )
    if spec.mechanics is not None:
        size = len(spec.mechanics.coordinates)
        lines.append(
            f"  mass-matrix form: M ({size} x {size}) factored at run time (LDL^T), never inverted"
        )
    if d.linearization.extension.counts:
        added = _listed(
            [f"{name} integrated {count}x" for name, count in d.linearization.extension.counts],
            "; ",
        )
        lines.append(
            f"  extension: {added}; new states {_listed(d.linearization.extension.states)}; "
            f"inputs of the extended plant {_listed(d.linearization.extension.inputs)}"
        )
        if d.linearization.extension_search:
            lines.append(
                "  extension found by the automatic search after trying: "
                + "; ".join(d.linearization.extension_search)
            )
    else:
        lines.append("  extension: none (static feedback linearization)")
    degrees = _listed(
        [f"{o}: {r}" for o, r in zip(spec.outputs, d.linearization.relative_degree, strict=True)]
    )
    kind = "uniform" if d.dynamics.uniform else "non-uniform, padded"
    lines.append(
        f"  relative degree: {degrees}  "
        f"(sum {sum(d.linearization.relative_degree)} = n; {kind}; k = {d.dynamics.k})"
    )
    pads = [name for chain in d.closed_loop.padding for name in chain]
    lines.append(f"  padding states: {_listed(pads) if pads else 'none'}")
    lines.append(f"  closed-loop state: {_listed(d.closed_loop.state_names)}")
    if d.decoupling.det_R is not None:
        where = (
            f"singular where {'; '.join(d.decoupling.singular_set)}"
            if d.decoupling.singular_set
            else "never singular"
        )
        what = (
            d.decoupling.det_R_note or "det R"
        )  # det(J_h B) = det R det M for a mass-matrix plant
        lines.append(f"  {what.split(' = ')[0]} = {sx.text(d.decoupling.det_R)}; {where}")
    else:
        lines.append(
            f"  det R: {d.decoupling.det_R_note}; singularity is checked at run time by pivoting"
        )
    causes = undefined_causes(
        law_expressions(d.linearization.R, d.decoupling.p, d.model.mechanics),
        set(d.linearization.extension.x),
    )
    if causes:
        where = "; ".join(f"{condition} ({cause})" for condition, cause in causes)
        lines.append(f"  R or p undefined where {where}")
    lines.append(
        f"  f0: strongly convex ({d.objective.convexity.method}, m_f ~ "
        f"{_number(d.objective.convexity.m_f)} over {d.objective.convexity.points} point(s))"
    )
    lines.append(
        "  error dynamics: poles "
        + ", ".join(_pole(p) for p in d.dynamics.eigenvalues)
        + "; a = ("
        + ", ".join(_number(a) for a in d.dynamics.coefficients)
        + ")"
        + f"; decay rate alpha = {_number(d.dynamics.decay_rate)}"
    )
    lines.append(_law_line(d))
    if d.model.constraints:
        listed = "; ".join(f"{c.name}: {c.text}" for c in d.model.constraints)
        lines.append(
            f"  constraints: {listed}; kept by the barrier objective B = f0 - mu(t) sum "
            f"log(s(t) - g_i) with mu(t) = {sx.text(d.model.mu)}, s(t) = {sx.text(d.model.slack)}"
        )
    if d.model.equalities:
        listed = "; ".join(f"{c.name}: {c.text}" for c in d.model.equalities)
        chains = ", ".join(chain[0] for chain in d.closed_loop.multiplier_states)
        lines.append(
            f"  equality constraints: {listed}; kept by the KKT system of L = f0 + nu^T a over "
            f"(y, nu): the multipliers and their first {d.dynamics.k - 1} derivative(s) "
            "are controller "
            f"states ({chains}, ...), E = col(F, ..., F^({d.dynamics.k - 1})) with "
            "F = [grad f0 + J_a^T nu; a]"
        )
        where = "; ".join(d.decoupling.dependent_set) if d.decoupling.dependent_set else "nowhere"
        lines.append(f"  KKT matrix singular (the equalities' gradients dependent) where: {where}")
    if d.model.references and spec.estimator is not None:
        lines.append(
            f"  references: {', '.join(spec.references)}; every call takes their jets to "
            f"derivative q = {d.jet.reference_order} (refs, shape ({len(spec.references)}, "
            f"{d.jet.reference_order + 1})); from samples: the {spec.estimator.kind} differentiator"
        )
    if kernels is not None:
        ops = ", ".join(f"{k.name} {k.ops}" for k in kernels.kernels)
        lines.append(f"  operations after CSE: {ops}")
    total = sum(seconds for _, seconds in d.timings)
    lines.append(f"  derivation time: {total:.2f} s")
    return "\n".join(lines)
