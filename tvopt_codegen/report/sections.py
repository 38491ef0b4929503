"""One builder per part of the derivation, in the paper's order.

Each reads the derivation and re-derives nothing.
"""

from __future__ import annotations

import importlib.util
import re
import sys
from collections.abc import Mapping, Sequence
from pathlib import Path

from tvopt_codegen import __version__
from tvopt_codegen import symbolic as sx
from tvopt_codegen.derivation import Derivation
from tvopt_codegen.lowering.ir import KernelSet
from tvopt_codegen.maths.jet import Program
from tvopt_codegen.report.entries import (
    INLINE_OPS,
    Entry,
    Math,
    Section,
    _math_entry,
    _name,
    _smoothness,
    count_ops,
    formula,
    plain,
)


def _shown(d: Derivation) -> dict[sx.Expr, sx.Expr]:
    """Display names of a mass-matrix plant's run-time symbols: ``a_i`` and ``W_i,j``.

    Their own names are reserved identifiers (``_ddq0``, ``_W0_1``) that no user name
    can take; the report shows them 1-based, as ``a = M^-1 F`` and ``W = M^-1 B``.
    """
    mech = d.model.mechanics
    if mech is None:
        return {}
    shown = {
        a: sx.symbol(f"a_{i + 1}")
        for i, a in enumerate(mech.accelerations)
        if isinstance(a, sx.Symbol)
    }
    shown |= {
        w: sx.symbol(f"W_{i + 1},{j + 1}")
        for i, row in enumerate(mech.gains)
        for j, w in enumerate(row)
        if isinstance(w, sx.Symbol)
    }
    # The definitions under the spec's names (their symbols are reserved, _let<i>).
    shown |= {
        symbol: sx.symbol(name)
        for (symbol, _), name in zip(mech.definitions, mech.definition_names, strict=True)
    }
    return shown


def _replaced(exprs: Sequence[sx.Expr], names: dict[sx.Expr, sx.Expr]) -> list[sx.Expr]:
    """``exprs`` under their display ``names``, in one substitution.

    One per expression cost a robot's report a third of a second: each passes the
    hundreds of names to the engine anew.
    """
    if not exprs:
        return []
    column = sx.matrix([[e] for e in exprs]).xreplace(names)
    return [column[i, 0] for i in range(len(exprs))]


def _mechanics(d: Derivation) -> list[Entry]:
    """The mass-matrix form: M, F, B, and how f, G, R and p are computed from them."""
    mech = d.model.mechanics
    if mech is None:
        return []
    n = len(mech.coordinates)
    coordinates = ", ".join(mech.coordinates)
    rates = ", ".join(mech.rates)
    shown = _shown(d)
    definitions: list[Entry] = []
    if mech.definitions:
        # A robot's Newton-Euler vectors: hundreds of short rows, each read once.
        definitions.append(
            Entry(
                "table",
                text=(
                    f"Definitions ({len(mech.definitions)}): named intermediate values M, F "
                    "and B use, each computed once per evaluation, in this order."
                ),
                header=("name", "definition"),
                rows=tuple(
                    (name, formula(expr))
                    for expr, name in zip(
                        _replaced([e for _, e in mech.definitions], shown),
                        mech.definition_names,
                        strict=True,
                    )
                ),
            )
        )
    return [
        Entry(
            "text",
            text=(
                f"The plant is declared in mass-matrix form, M(q) q'' = F(q, q') + B(q) u, with "
                f"coordinates q = ({coordinates}) and rates q' = ({rates}); its state is "
                f"(q, q')."
            ),
        ),
        *definitions,
        _math_entry(
            "Mass matrix (symmetric, positive definite):",
            sx.matrix(mech.mass_matrix).xreplace(shown),
            _name("M(q)", "M"),
        ),
        _math_entry(
            "Forces without the inputs:",
            sx.matrix([[f] for f in mech.forces]).xreplace(shown),
            _name("F(q, q')", "F"),
        ),
        _math_entry(
            "Input matrix:", sx.matrix(mech.input_matrix).xreplace(shown), _name("B(q)", "B")
        ),
        Entry(
            "text",
            text=(
                "M is factored at run time, never inverted: a = M^-1 F and W = M^-1 B "
                f"(shown as a_i and W_i,j below) are computed at each evaluation by one "
                f"sparse LDL^T of the {n} x {n} matrix M and a triangular solve per column of "
                "[F B], in the same kernel as R and p; the generated code reports "
                "MassMatrixNotPositiveDefiniteError where a pivot is not positive. So f = "
                "[q'; a] and G = [0; W], R = J_h W and p = (dJ_h/dt) q' + J_h a for outputs "
                "h(q); no Lie derivative differentiates a or W (relative degree 2 and no "
                "extension, docs/spec.md)."
            ),
        ),
    ]


def _model(d: Derivation) -> Section:
    spec, model = d.spec, d.model
    shown = _shown(d)
    entries = [Entry("text", text=spec.description or "(no description)")]
    entries.append(
        Entry(
            "table",
            text="Declared names, in the order the generated code uses them.",
            header=("kind", "names"),
            rows=(
                ("states x", ", ".join(spec.states)),
                ("inputs u", ", ".join(spec.inputs)),
                ("outputs y", ", ".join(spec.outputs)),
            ),
        )
    )
    entries += _mechanics(d)
    entries.append(
        _math_entry(
            "Drift vector field (x' = f(x) + G(x) u):", model.f.xreplace(shown), _name("f(x)", "f")
        )
    )
    how = "from M, F and B" if shown else "extracted by differentiation in u"
    entries.append(
        _math_entry(f"Input matrix, {how}:", model.G.xreplace(shown), _name("G(x)", "G"))
    )
    entries.append(_math_entry("Outputs:", model.h, _name("h(x)", "h")))
    if spec.parameters:
        entries.append(
            Entry(
                "table",
                text="Parameters (defaults; overridable at run time).",
                header=("name", "default"),
                rows=tuple((n, repr(v)) for n, v in spec.parameters),
            )
        )
    if model.signals:
        entries.append(
            Entry(
                "table",
                text="Time signals, differentiated exactly as often as the law needs.",
                header=("signal", "definition", "smoothness"),
                rows=tuple((s.name, formula(e), _smoothness(e)) for s, e in model.signals),
            )
        )
    entries += _constraint_entries(d)
    entries += _reference_entries(d)
    return Section("Model", tuple(entries))


def _constraint_entries(d: Derivation) -> list[Entry]:
    """The model's inequality and equality constraints, as tables (none without)."""
    model = d.model
    entries: list[Entry] = []
    if model.constraints:
        entries.append(
            Entry(
                "table",
                text=(
                    "Constraints g_i(y, t) <= 0, kept by an interior-point homotopy: the law "
                    "tracks the minimiser of B = f0 - mu(t) sum_i log(s(t) - g_i), with the "
                    f"weight mu(t) = {plain(model.mu)} and the slack s(t) = "
                    f"{plain(model.slack)}. The objective below is B (Phi, further down, names "
                    "the linearizing coordinates)."
                ),
                header=("constraint", "as written", "g_i"),
                rows=tuple((c.name, c.text, formula(c.g)) for c in model.constraints),
            )
        )
    if model.equalities:
        chains = "; ".join(", ".join(chain) for chain in d.closed_loop.multiplier_states)
        entries.append(
            Entry(
                "table",
                text=(
                    "Equality constraints a_j(y, t) = 0, kept by the KKT system: the law is "
                    "the paper's, written for the Lagrangian L = f0 + sum_j nu_j a_j over the "
                    "outputs and the multipliers, so that E = col(F, F', ..., F^(k-1)) with "
                    "F = [grad f0 + J_a^T nu; a] obeys E' = H E. F and its Hessian, the KKT "
                    "matrix K = [[grad_yy L, J_a^T], [J_a, 0]], are shown with the objective; "
                    "K is solved at run time by LDL^T "
                    "with the outputs' block first (its pivots positive, the multipliers' "
                    "negative; a failing multiplier pivot is the status DEPENDENT_CONSTRAINTS). "
                    f"The multipliers and their derivatives are controller states: {chains}. "
                    "K is singular (the constraints' gradients dependent) "
                    + (
                        "where " + " or where ".join(d.decoupling.dependent_set)
                        if d.decoupling.dependent_set
                        else "nowhere: det(J_a J_a^T) never vanishes"
                    )
                    + "."
                ),
                header=("constraint", "as written", "a_j", "multiplier"),
                rows=tuple(
                    (c.name, c.text, formula(c.g), nu.name)
                    for c, nu in zip(model.equalities, model.multipliers, strict=True)
                ),
            )
        )
    return entries


def _reference_entries(d: Derivation) -> list[Entry]:
    """The references measured at run time and their estimator, as a table (none without)."""
    spec, model = d.spec, d.model
    entries: list[Entry] = []
    if model.references:
        estimator = spec.estimator
        assert estimator is not None
        gain = (
            f"every pole at -{estimator.bandwidth:g} rad/s"
            if estimator.kind == "linear"
            else f"L = {estimator.lipschitz:g} bounds derivative {d.jet.reference_order + 1}"
        )
        nominal = dict(model.nominal)
        entries.append(
            Entry(
                "table",
                text=(
                    f"References measured at run time: every call takes their jets up to "
                    f"derivative q = {d.jet.reference_order}, the highest the law reads "
                    f"(REFERENCE_ORDER). From samples, the {estimator.kind} differentiator "
                    f"estimates them ({gain}); between samples a jet follows its Taylor "
                    "polynomial."
                ),
                header=("reference", "jet the law reads", "nominal closed form"),
                rows=tuple(
                    (
                        r.name,
                        ", ".join(str(s) for s in chain[: d.jet.reference_order + 1]),
                        formula(nominal[r]) if r in nominal else "(none: samples only)",
                    )
                    for r, chain in zip(model.references, d.jet.reference_jet, strict=True)
                ),
            )
        )
    return entries


def _extension(d: Derivation) -> Section:
    ext = d.linearization.extension
    entries: list[Entry] = []
    if ext.counts:
        added = "; ".join(f"input {u} integrated {q} time(s)" for u, q in ext.counts)
        entries.append(
            Entry(
                "text",
                text=(
                    f"Dynamic extension (paper, Lemma 2, eqs. (3)-(5)): {added}. "
                    f"New states {', '.join(ext.states)}; the extended plant's inputs are "
                    f"{', '.join(ext.inputs)}. Why: {d.linearization.unextended}."
                ),
            )
        )
        if d.linearization.extension_search:
            entries.append(
                Entry(
                    "text",
                    text=(
                        "Found by the automatic search (smallest total number of integrators "
                        "first, earlier inputs first); tried: "
                        f"{'; '.join(d.linearization.extension_search)}."
                    ),
                )
            )
        entries.append(
            _math_entry("Drift of the extended plant:", ext.f, _name(r"\tilde f", "f&#771;"))
        )
        entries.append(
            _math_entry("Input matrix of the extended plant:", ext.G, _name(r"\tilde G", "G&#771;"))
        )
    else:
        entries.append(
            Entry(
                "text",
                text=(
                    "No dynamic extension: the plant as declared has a vector relative degree "
                    "with a generically nonsingular decoupling matrix (static feedback "
                    "linearization)."
                ),
            )
        )
    pads = [
        (o, ", ".join(chain))
        for o, chain in zip(d.spec.outputs, d.closed_loop.padding, strict=True)
        if chain
    ]
    if pads:
        entries.append(
            Entry(
                "table",
                text=(
                    "Padding chains (paper, Sec. IV-B, eq. (19)): channel i gets "
                    f"k - r_i = {d.dynamics.k} - r_i integrators xi; "
                    "xi_<output>_1 is that channel's "
                    "Brunovsky input, the last one is driven by y_imp^(k)."
                ),
                header=("output", "padding states"),
                rows=tuple(pads),
            )
        )
    else:
        entries.append(
            Entry("text", text=f"No padding: every relative degree equals k = {d.dynamics.k}.")
        )
    return Section("Dynamic extension and padding", tuple(entries))


def _linearization(d: Derivation) -> Section:
    entries: list[Entry] = [
        Entry(
            "table",
            text="Vector relative degree of the extended plant (paper, Definition 1).",
            header=("output", "relative degree r_i", "Lie derivatives L_f^j h_i, j < r_i"),
            rows=tuple(
                (o, str(r), formula(sx.matrix([list(d.linearization.lie[i][:r])])))
                for i, (o, r) in enumerate(
                    zip(d.spec.outputs, d.linearization.relative_degree, strict=True)
                )
            ),
        )
    ]
    entries.append(
        _math_entry(
            "Decoupling matrix, rows L_G L_f^(r_i - 1) h_i (paper, eq. (2)):",
            d.linearization.R.xreplace(_shown(d)),
            _name("R(x)", "R"),
        )
    )
    if d.decoupling.det_R is not None and d.decoupling.det_R_note:
        # A mass-matrix plant: det R det M, which vanishes where R is singular.
        entries.append(
            _math_entry(
                "det R det M = det(J_h B), factored (M is positive definite, so R is singular "
                "exactly where this vanishes):",
                d.decoupling.det_R,
                _name(r"\det(J_h B)", "det(J_h B)"),
            )
        )
    elif d.decoupling.det_R is not None:
        entries.append(
            _math_entry("Its determinant, factored:", d.decoupling.det_R, _name(r"\det R", "det R"))
        )
        where = (
            "R is singular when " + " or when ".join(d.decoupling.singular_set) + "."
            if d.decoupling.singular_set
            else "R is never singular."
        )
        entries.append(
            Entry(
                "text",
                text=where + " The generated code checks every pivot at "
                "run time and reports SingularDecouplingError there.",
            )
        )
    else:
        entries.append(
            Entry(
                "text",
                text=(
                    f"det R is {d.decoupling.det_R_note}; "
                    "the generated code checks every pivot at run time."
                ),
            )
        )
    if d.decoupling.undefined_set:
        entries.append(
            Entry(
                "text",
                text="R or p, and with them the law, is undefined where "
                + " or where ".join(d.decoupling.undefined_set)
                + " (a vanishing denominator, or a cosine under tan); det R says nothing "
                "there.",
            )
        )
    entries.append(
        _math_entry(
            "p = col(L_f^(r_i) h_i):", d.decoupling.p.xreplace(_shown(d)), _name("p(x)", "p")
        )
    )
    entries.append(
        _math_entry(
            "Coordinates Phi (paper, Lemmas 1-2):", d.decoupling.phi, _name(r"\Phi(x)", "&#934;")
        )
    )
    entries.append(_math_entry("Brunovsky pair, A:", d.decoupling.A, _name("A", "A")))
    entries.append(_math_entry("Brunovsky pair, B:", d.decoupling.B, _name("B", "B")))
    return Section("Relative degree and linearization", tuple(entries))


def _objective(d: Derivation) -> Section:
    model = d.model
    entries = [
        _math_entry("The objective (signals by name):", model.f0, _name("f_0(y, t)", "f0")),
        _math_entry(
            "Its gradient, written Hess y + b with b its value at y = 0 (f0 is quadratic in "
            "y: in this form y enters each time derivative once, grad^(j) = Hess y^(j) + "
            "b^(j)):"
            if not d.hessian.free_symbols & set(model.y)
            else "Its gradient:",
            d.objective.gradient,
            _name(r"\nabla_y f_0", "&#8711;f0"),
        ),
        _math_entry("Its Hessian:", d.hessian, _name(r"\nabla_{yy} f_0", "&#8711;&#178;f0")),
    ]
    conv = d.objective.convexity
    how = (
        "the Hessian is constant, so its smallest eigenvalue is exact"
        if conv.quadratic
        else f"sampled at {conv.points} points (y within 0.1 of the initial outputs, t over the "
        "horizon, parameters at their defaults): an estimate, not a proof"
    )
    entries.append(
        Entry(
            "text",
            text=(
                f"Strong convexity (paper, Assumption 1): m_f = {conv.m_f:.6g} > 0; {how}. The "
                "generated code checks positive definiteness at run time (the pivots of an "
                "LDL^T factorization)."
            ),
        )
    )
    if model.equalities:
        assert d.objective.kkt_gradient is not None
        entries += [
            _math_entry(
                "With equality constraints the law is written for L = f0 + nu^T a over (y, nu): "
                "its gradient, the KKT map F = [grad f0 + J_a^T nu; a], is what E holds:",
                d.objective.kkt_gradient,
                _name("F", "F"),
            ),
            _math_entry(
                "Its Hessian, the KKT matrix K = [[grad_yy L, J_a^T], [J_a, 0]], which the "
                "generated code factors (the outputs' block first):",
                d.kkt_hessian,
                _name("K", "K"),
            ),
        ]
    return Section("Objective", tuple(entries))


def _pole(value: complex) -> str:
    if value.imag == 0:
        return f"{value.real:.6g}"
    return f"{value.real:.6g} {'+' if value.imag > 0 else '-'} {abs(value.imag):.6g}i"


def _error_dynamics(d: Derivation) -> Section:
    k, m = d.dynamics.k, d.jet.n_kkt
    order = len(d.dynamics.coefficients)
    # With equalities E holds the KKT map F and its derivatives instead of grad f0's.
    first, last = ("F", f"F^({k - 1})") if d.model.equalities else ("grad f0", f"grad^({k - 1}) f0")
    # Shown only: ones above the diagonal, the coefficients (floats) in the last row.
    companion = sx.matrix(
        [
            [
                sx.real(d.dynamics.coefficients[j])
                if i == order - 1
                else (sx.ONE if j == i + 1 else sx.ZERO)
                for j in range(order)
            ]
            for i in range(order)
        ]
    )
    if d.closed_loop.integral_states:
        law = (
            f"With integral action z_I = int {first} dt (states "
            f"{', '.join(d.closed_loop.integral_states)}), "
            f"col(z_I, E) with E = col({first}, ..., {last}) "
            f"obeys col(z_I, E)' = H_I col(z_I, E) with H_I = companion(a) kron I_{m}: one "
            "more pole per output (see Robustness)."
        )
    else:
        law = (
            f"E = col({first}, ..., {last}) obeys E' = H E with H = companion(a) "
            f"kron I_{m} (paper, eqs. (14)-(15))."
        )
    entries = [
        Entry("text", text=law),
        _math_entry(
            "Companion matrix, last row a_0 .. a_k:"
            if d.closed_loop.integral_states
            else "Companion matrix, last row a_0 .. a_{k-1}:",
            companion,
            _name(r"\mathrm{companion}(a)", "companion(a)"),
        ),
        Entry(
            "table",
            text="Spectrum and the constants of |expm(H t)| <= c exp(-alpha t) (paper, Theorem 3).",
            header=("quantity", "value"),
            rows=(
                ("poles", ", ".join(_pole(p) for p in d.dynamics.eigenvalues)),
                ("coefficients a", ", ".join(f"{a:.10g}" for a in d.dynamics.coefficients)),
                ("decay rate -max Re(lambda)", f"{d.dynamics.decay_rate:.6g}"),
                (
                    "alpha used in the bound",
                    f"{d.dynamics.certified_rate:.6g}"
                    + ("" if d.dynamics.certified_rate_exact else " (repeated poles: 10% epsilon)"),
                ),
                (
                    "c = sup_t |expm(H t)| e^(alpha t), computed",
                    f"{d.dynamics.transient_constant:.6g}",
                ),
            ),
        ),
        Entry(
            "text",
            text=(
                "Hence |y(t) - y*(t)| <= C exp(-alpha t) with C = c |E(0)| / m_f (paper, "
                "Theorems 5 and 6); `tvopt-codegen simulate` checks this along a run."
            ),
        ),
    ]
    return Section("Error dynamics", tuple(entries))


#: An inlined jet of more nodes than this many times INLINE_OPS is described without
#: being built. A tree has about two nodes per operation (its leaves), and sympy's
#: evaluation as it is built grows it by at most one product per term (a number
#: distributed over a sum); only a cancellation it could not foresee would have shrunk
#: such a tree under INLINE_OPS.
_NODES_PER_OP = 3


def _inlined(program: Program, exprs: Sequence[sx.Expr]) -> list[sx.Expr] | None:
    """``exprs`` with the program inlined, or None where that is sure to be too long.

    A team's gradient jet inlines to expressions of millions of nodes, which took most
    of its report to build only to be described instead.
    """
    nodes = sum(program.inlined_size(e) for e in exprs)
    if nodes > _NODES_PER_OP * INLINE_OPS:
        return None
    return [program.inline(e) for e in exprs]


def _control_law(d: Derivation) -> Section:
    k = d.dynamics.k
    theorem = (
        "Theorem 5, Control Law for Uniform Vector Relative Degree Systems: u = alpha + "
        "beta R^-1 [y_imp^(k) - p] (eq. (18))"
        if d.dynamics.uniform
        else "Theorem 6, Control Law for General Vector Relative Degree System: u = alpha + "
        "beta R^-1 [alpha~(xi) + beta~(xi) y_imp^(k) - p] (eq. (20)), with the padding "
        "chains of eq. (19)"
    )
    law = (
        r"y_{\mathrm{imp}}^{(k)} = \nabla_{yy}^{-1} f_0 \Big[\sum_{i=0}^{k-1} a_i "
        r"\nabla_y^{(i)} f_0 - \sum_{m=1}^{k-1} \binom{k-1}{m} \nabla_{yy}^{(m)} f_0\, "
        r"y^{(k-m)} - \nabla_{yt}^{(k-1)} f_0\Big]"
    )
    law_mathml = (
        "<mrow><msubsup><mi>y</mi><mi>imp</mi><mrow><mo>(</mo><mi>k</mi><mo>)</mo>"
        "</mrow></msubsup><mo>=</mo><msubsup><mo>&#8711;</mo><mi>yy</mi><mrow><mo>-</mo>"
        "<mn>1</mn></mrow></msubsup><msub><mi>f</mi><mn>0</mn></msub><mo>[</mo>"
        "<munderover><mo>&#8721;</mo><mrow><mi>i</mi><mo>=</mo><mn>0</mn></mrow><mrow>"
        "<mi>k</mi><mo>-</mo><mn>1</mn></mrow></munderover><msub><mi>a</mi><mi>i</mi>"
        "</msub><msubsup><mo>&#8711;</mo><mi>y</mi><mrow><mo>(</mo><mi>i</mi><mo>)</mo>"
        "</mrow></msubsup><msub><mi>f</mi><mn>0</mn></msub><mo>-</mo><mi>rest</mi>"
        "<mo>]</mo></mrow>"
    )
    entries = [
        Entry("text", text=f"Theorem used: {theorem} (k = {k})."),
        Entry(
            "math",
            text="The implicit law (paper, eq. (17)):",
            math=Math(law, law_mathml),
        ),
        Entry(
            "text",
            text=(
                "The gradient jet grad^(j) f0 (paper, Lemma 4, eq. (16)) is the total time "
                "derivative along t, the output "
                "jet y, y', ... and the signal jets, taken on a straight-line program (never "
                "expanded); grad^(k) f0 = Hess y^(k) + rest, and rest is grad^(k) f0 with "
                f"y^(k) = 0. Program size: {len(d.jet.jet_program.assignments)} assignments for "
                f"grad^(j), j < k, and {len(d.jet.rest_program.assignments)} more for rest. The "
                "generated code solves Hess z = sum a_i grad^(i) f0 - rest (LDL^T, a "
                "square-root-free Cholesky, or the exact constant inverse when the Hessian is "
                "constant) and R w = v - p (LU with partial pivoting); no symbolic inverse is "
                "formed."
            ),
        ),
    ]
    program = d.jet.jet_program + d.jet.rest_program
    for j in range(1, k):
        exprs = _inlined(program, d.jet.grad_jet[j])
        if exprs is not None and sum(count_ops(e) for e in exprs) <= INLINE_OPS:
            entries.append(
                _math_entry(
                    f"grad^({j}) f0, inlined for checking:",
                    sx.matrix([[e] for e in exprs]),
                    _name(rf"\nabla_y^{{({j})}} f_0", f"&#8711;({j})f0"),
                )
            )
    rest = _inlined(program, d.jet.rest)
    if rest is not None and sum(count_ops(e) for e in rest) <= INLINE_OPS:
        entries.append(
            _math_entry(
                f"rest = grad^({k}) f0 at y^({k}) = 0, inlined:",
                sx.matrix([[e] for e in rest]),
                _name(r"\mathrm{rest}", "rest"),
            )
        )
    return Section("Control law", tuple(entries))


def _provenance(d: Derivation, kernels: KernelSet) -> Section:
    rows = tuple((k.name, k.doc, str(k.ops_before_cse), str(k.ops)) for k in kernels.kernels)
    times = tuple((stage, f"{seconds * 1e3:.1f}") for stage, seconds in d.timings)
    return Section(
        "Generated code and provenance",
        (
            Entry(
                "table",
                text=(
                    "Kernels of the generated code (operations: a sum or product of n "
                    "terms counts n - 1, every power, division, negation and function "
                    "call one)."
                ),
                header=("kernel", "what", "ops before CSE", "ops after CSE"),
                rows=rows,
            ),
            Entry(
                "table", text="Time spent per derivation step.", header=("step", "ms"), rows=times
            ),
            Entry(
                "table",
                text="Provenance.",
                header=("item", "value"),
                rows=(
                    ("spec", d.spec.source),
                    ("spec sha256", d.spec.sha256),
                    ("tvopt-codegen", __version__),
                    ("sympy", _sympy_version()),
                    *_engine_rows(),
                ),
            ),
        ),
    )


def _sympy_version() -> str:
    """SymPy's version, without importing SymPy: a report on SymEngine imports none.

    SymPy's own ``__version__`` where it is loaded; else read from its ``release.py``,
    where ``sympy.__version__`` comes from, found but not imported. Its metadata says the
    same, but ``importlib.metadata`` took a tenth of a cold ``report``'s CPU to load
    (email, csv, zipfile and a scan of every distribution on the path); it is the
    fallback where the file does not say.
    """
    loaded = sys.modules.get("sympy")
    if loaded is not None:
        return str(loaded.__version__)
    found = importlib.util.find_spec("sympy")
    if found is not None and found.origin is not None:
        try:
            text = (Path(found.origin).parent / "release.py").read_text(encoding="utf-8")
        except OSError:
            text = ""
        match = re.search(r"""^__version__ = ["']([^"'\n]+)["']$""", text, re.M)
        if match is not None:
            return match.group(1)
    from importlib import metadata  # noqa: PLC0415 - the fallback, dear to load

    return metadata.version("sympy")


def _engine_rows() -> tuple[tuple[str, str], ...]:
    """The engine that derived, when it is not SymPy."""
    if not sx.SYMENGINE:
        return ()
    import symengine  # noqa: PLC0415 - loaded with the engine already

    return (("symengine (derivation)", str(symengine.__version__)),)


def _simulation(d: Derivation, results: Mapping[str, bytes]) -> Section:
    name = d.spec.name
    certificate = results.get(f"{name}_certificate.txt")
    if certificate is None:
        return Section(
            "Simulation",
            (
                Entry(
                    "text",
                    text=(
                        f"No simulation results beside this report. Run `tvopt-codegen simulate "
                        f"{name} --out DIR` and then `tvopt-codegen report {name} --out DIR`."
                    ),
                ),
            ),
        )
    entries = [Entry("pre", text=certificate.decode("utf-8", "replace"))]
    captions = {
        "paths": "Paths: objects, the target y* (dashed) and the agents (stars: starts).",
        "convergence": "|y - y*| and |E| with the theorem's bounds.",
        "inputs": "Plant inputs.",
    }
    for stem, caption in captions.items():
        image = results.get(f"{name}_{stem}.png")
        if image is not None:
            entries.append(Entry("figure", text=caption, image=image, name=f"{name}_{stem}.png"))
    return Section("Simulation", tuple(entries))
