"""The derivation report: every derived term, for a person to check line by line.

References to the paper use its arXiv numbering: Lemmas 1-2 (static and dynamic
linearization), Theorem 3 (Hurwitz matrices), Lemma 4 (gradient time differentiation,
eq. (16)), Theorems 5-6 (uniform and non-uniform relative degree), Assumption 1
(convexity), and equations (2) R, (14) E' = H E, (15) H, (17) y_imp^(k), (18) and (20) the
laws, (19) the padding chains.

:func:`report_sections` turns a :class:`~tvopt_codegen.derivation.Derivation` (and the
kernels, and any simulation results found beside the report) into sections of
paragraphs, equations, tables, figures and preformatted text; each equation carries both
LaTeX (for the Markdown twin) and presentation MathML (for the HTML page, rendered
natively by browsers, no network). The templates in ``templates/report`` lay them out.
The report reads the derivation; it never re-derives anything.
"""

from __future__ import annotations

import base64
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import sympy as sp
from sympy.printing.mathml import MathMLPresentationPrinter

from tvopt_codegen import __version__
from tvopt_codegen.derivation import Derivation
from tvopt_codegen.emit import read_own_output
from tvopt_codegen.ir import KernelSet
from tvopt_codegen.rendering import render_template

#: Equations longer than this (LaTeX characters) are folded, shown in full on demand.
FOLD_AT = 600
#: A matrix with more entries than this, most of them zero (a team's G, R or Hessian), is
#: listed by its nonzero entries: a dense 64 x 64 array of zeros cannot be checked by eye.
SPARSE_AT = 64
#: Gradient-jet expressions above this many operations are described, not inlined.
INLINE_OPS = 400
#: Report formats and their templates.
FORMATS = {"html": "report/report.html.jinja", "md": "report/report.md.jinja"}
#: Functions that are smooth (analytic) on the whole real line.
ENTIRE = (sp.sin, sp.cos, sp.exp, sp.sinh, sp.cosh, sp.tanh, sp.atan, sp.asinh)

#: Section headings, in order (the tests check every one is present).
HEADINGS = (
    "Model",
    "Dynamic extension and padding",
    "Relative degree and linearization",
    "Objective",
    "Error dynamics",
    "Control law",
    "Generated code and provenance",
    "Simulation",
)


@dataclass(frozen=True)
class Math:
    """One displayed formula in two notations."""

    latex: str
    mathml: str

    @property
    def folded(self) -> bool:
        """Whether the formula is long enough to be shown folded."""
        return len(self.latex) > FOLD_AT


@dataclass(frozen=True)
class Entry:
    """One item of a section.

    ``kind`` is ``text`` (``text``), ``math`` (``text`` introduces ``math``), ``table``
    (``header`` and ``rows`` of strings or :class:`Math`), ``figure`` (``text`` caption,
    ``image`` PNG bytes, ``name``) or ``pre`` (``text``).
    """

    kind: str
    text: str = ""
    math: Math | None = None
    header: tuple[str, ...] = ()
    rows: tuple[tuple[str | Math, ...], ...] = ()
    image: bytes = b""
    name: str = ""

    @property
    def image_base64(self) -> str:
        """The figure as base64 text, for a data URI."""
        return base64.b64encode(self.image).decode("ascii")


@dataclass(frozen=True)
class Section:
    """A titled list of entries."""

    title: str
    entries: tuple[Entry, ...] = field(default_factory=tuple)

    @property
    def anchor(self) -> str:
        """The section's id in the HTML page."""
        return self.title.lower().replace(" ", "-")


class ReportMathMLPrinter(MathMLPresentationPrinter):  # type: ignore[misc]
    """Presentation MathML as a browser shows it well without a math font.

    Customizations are listed on each override; everything else is sympy's printer.
    """

    def _print_MatrixBase(self, m: sp.MatrixBase) -> Any:
        """Customizations.

        * No ``<mo>[</mo>`` fences: they stretch beside a tall matrix only with an
          OpenType MATH font, which most readers lack. The table gets the class
          ``matrix``, whose brackets the page draws in CSS at any height.
        """
        saved = self._settings["mat_delim"]
        self._settings["mat_delim"] = ""
        try:
            table = super()._print_MatrixBase(m)
        finally:
            self._settings["mat_delim"] = saved
        table.setAttribute("class", "matrix")
        return table

    def _print_Mul(self, expr: sp.Mul) -> Any:
        """Customizations.

        * The invisible times beside a multi-letter name or a function gets a thin
          space on both sides: ``wheelbase cos(phi)``, ``jx jy``, never
          ``wheelbasecos(phi)`` or ``jxjy``.
        """
        row = super()._print_Mul(expr)
        children = [c for c in row.childNodes if c.nodeType == c.ELEMENT_NODE]
        for before, node, after in zip(children, children[1:], children[2:], strict=False):
            if (
                node.tagName == "mo"
                and _text(node) == "&InvisibleTimes;"
                and (_wide(before) or _wide(after))
            ):
                node.setAttribute("lspace", "0.1667em")
                node.setAttribute("rspace", "0.1667em")
        return row


def _text(node: Any) -> str:
    return "".join(c.data for c in node.childNodes if c.nodeType == c.TEXT_NODE)


def _wide(node: Any) -> bool:
    """Whether a factor starts with a name of several letters (or is a function)."""
    while node.tagName not in ("mi", "mn", "mo") and node.firstChild is not None:
        node = node.firstChild
        if node.nodeType != node.ELEMENT_NODE:
            return False
    text = _text(node)
    return node.tagName == "mi" and len(text) > 1 and not text.startswith("&")


#: The report's LaTeX settings: a thin space between factors.
_LATEX = {"mul_symbol": r"\,"}


def _mathml(value: object) -> str:
    printer = ReportMathMLPrinter()
    return str(printer.doprint(value))


def formula(expr: object, lhs: tuple[str, str] | None = None) -> Math:
    """Both notations of ``expr``, optionally as ``lhs = expr``.

    Parameters
    ----------
    expr : sympy object
        The right-hand side.
    lhs : tuple of (str, str), optional
        The left-hand side as (LaTeX, MathML).
    """
    value = sp.sympify(expr)
    # A thin space between factors: "jx\,jy" is two names where "jx jy" reads as jxjy.
    latex = sp.latex(value, **_LATEX)
    markup = _mathml(value)
    if lhs is not None:
        latex = f"{lhs[0]} = {latex}"
        markup = f"<mrow>{lhs[1]}<mo>=</mo>{markup}</mrow>"
    return Math(latex, markup)


def _name(latex: str, text: str) -> tuple[str, str]:
    """A left-hand side: LaTeX and an MathML identifier (``text`` is plain ASCII)."""
    return latex, f"<mi>{text}</mi>"


def _math_entry(text: str, expr: object, lhs: tuple[str, str] | None = None) -> Entry:
    value = sp.sympify(expr)
    if lhs is not None and isinstance(value, sp.MatrixBase):
        size = value.rows * value.cols
        nonzero = [
            ((i, j), value[i, j])
            for i in range(value.rows)
            for j in range(value.cols)
            if value[i, j] != 0
        ]
        if size > SPARSE_AT and 2 * len(nonzero) <= size:
            zeros = size - len(nonzero)
            # Structurally symmetric (a Hessian is, entry by entry): the lower triangle says
            # it all.
            symmetric = value.rows == value.cols and all(
                value[j, i] == e for (i, j), e in nonzero if i != j
            )
            if symmetric:
                nonzero = [((i, j), e) for (i, j), e in nonzero if i >= j]
            text = (
                f"{text.rstrip(':')} ({value.rows} x {value.cols}, "
                + (
                    "symmetric; the nonzero entries of its lower triangle"
                    if symmetric
                    else "its nonzero entries"
                )
                + f", indexed from 1; the other {zeros} entries are 0):"
            )
            return Entry("math", text=text, math=_entries(nonzero, lhs))
    return Entry("math", text=text, math=formula(value, lhs))


def _entries(nonzero: Sequence[tuple[tuple[int, int], sp.Expr]], lhs: tuple[str, str]) -> Math:
    """``[M]_ij = value`` for each listed entry, one per line, in both notations."""
    latex = (
        r"\begin{aligned}"
        + r" \\ ".join(
            rf"\left[{lhs[0]}\right]_{{{i + 1}, {j + 1}}} &= {sp.latex(e, **_LATEX)}"
            for (i, j), e in nonzero
        )
        + r"\end{aligned}"
    )
    rows = "".join(
        f"<mtr><mtd><msub><mrow><mo>[</mo>{lhs[1]}<mo>]</mo></mrow>"
        f"<mrow><mn>{i + 1}</mn><mo>,</mo><mn>{j + 1}</mn></mrow></msub></mtd>"
        f"<mtd><mo>=</mo></mtd><mtd>{_mathml(e)}</mtd></mtr>"
        for (i, j), e in nonzero
    )
    return Math(latex, f"<mtable>{rows}</mtable>")


def _smoothness(expr: sp.Expr) -> str:
    used = sorted({type(f).__name__ for f in expr.atoms(sp.Function)})
    restricted = [f for f in used if not any(f == g.__name__ for g in ENTIRE)]
    if not used:
        return "polynomial in t: C-infinity"
    if not restricted:
        return f"built from {', '.join(used)}: C-infinity for all t"
    return f"C-infinity where {', '.join(restricted)} are defined and smooth"


def _model(d: Derivation) -> Section:
    spec, model = d.spec, d.model
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
    entries.append(
        _math_entry("Drift vector field (x' = f(x) + G(x) u):", model.f, _name("f(x)", "f"))
    )
    entries.append(
        _math_entry("Input matrix, extracted by differentiation in u:", model.G, _name("G(x)", "G"))
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
    if model.constraints:
        entries.append(
            Entry(
                "table",
                text=(
                    "Constraints g_i(y, t) <= 0, kept by an interior-point homotopy: the law "
                    "tracks the minimiser of Phi = f0 - mu(t) sum_i log(s(t) - g_i), with the "
                    f"weight mu(t) = {sp.sstr(model.mu)} and the slack s(t) = "
                    f"{sp.sstr(model.slack)}. The objective below is Phi."
                ),
                header=("constraint", "as written", "g_i"),
                rows=tuple((c.name, c.text, formula(c.g)) for c in model.constraints),
            )
        )
    if model.equalities:
        chains = "; ".join(", ".join(chain) for chain in d.multiplier_states)
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
                        "where " + " or where ".join(d.dependent_set)
                        if d.dependent_set
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
    if model.references:
        estimator = spec.estimator
        assert estimator is not None
        gain = (
            f"every pole at -{estimator.bandwidth:g} rad/s"
            if estimator.kind == "linear"
            else f"L = {estimator.lipschitz:g} bounds derivative {d.reference_order + 1}"
        )
        nominal = dict(model.nominal)
        entries.append(
            Entry(
                "table",
                text=(
                    f"References measured at run time: every call takes their jets up to "
                    f"derivative q = {d.reference_order}, the highest the law reads "
                    f"(REFERENCE_ORDER). From samples, the {estimator.kind} differentiator "
                    f"estimates them ({gain}); between samples a jet follows its Taylor "
                    "polynomial."
                ),
                header=("reference", "jet the law reads", "nominal closed form"),
                rows=tuple(
                    (
                        r.name,
                        ", ".join(str(s) for s in chain[: d.reference_order + 1]),
                        formula(nominal[r]) if r in nominal else "(none: samples only)",
                    )
                    for r, chain in zip(model.references, d.reference_jet, strict=True)
                ),
            )
        )
    return Section("Model", tuple(entries))


def _extension(d: Derivation) -> Section:
    ext = d.extension
    entries: list[Entry] = []
    if ext.counts:
        added = "; ".join(f"input {u} integrated {q} time(s)" for u, q in ext.counts)
        entries.append(
            Entry(
                "text",
                text=(
                    f"Dynamic extension (paper, Lemma 2, eqs. (3)-(5)): {added}. "
                    f"New states {', '.join(ext.states)}; the extended plant's inputs are "
                    f"{', '.join(ext.inputs)}. Why: {d.unextended}."
                ),
            )
        )
        if d.extension_search:
            entries.append(
                Entry(
                    "text",
                    text=(
                        "Found by the automatic search (smallest total number of integrators "
                        f"first, earlier inputs first); tried: {'; '.join(d.extension_search)}."
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
        (o, ", ".join(chain)) for o, chain in zip(d.spec.outputs, d.padding, strict=True) if chain
    ]
    if pads:
        entries.append(
            Entry(
                "table",
                text=(
                    "Padding chains (paper, Sec. IV-B, eq. (19)): channel i gets "
                    f"k - r_i = {d.k} - r_i integrators xi; xi_<output>_1 is that channel's "
                    "Brunovsky input, the last one is driven by y_imp^(k)."
                ),
                header=("output", "padding states"),
                rows=tuple(pads),
            )
        )
    else:
        entries.append(Entry("text", text=f"No padding: every relative degree equals k = {d.k}."))
    return Section("Dynamic extension and padding", tuple(entries))


def _linearization(d: Derivation) -> Section:
    entries: list[Entry] = [
        Entry(
            "table",
            text="Vector relative degree of the extended plant (paper, Definition 1).",
            header=("output", "relative degree r_i", "Lie derivatives L_f^j h_i, j < r_i"),
            rows=tuple(
                (o, str(r), formula(sp.Matrix([list(d.lie[i][:r])])))
                for i, (o, r) in enumerate(zip(d.spec.outputs, d.relative_degree, strict=True))
            ),
        )
    ]
    entries.append(
        _math_entry(
            "Decoupling matrix, rows L_G L_f^(r_i - 1) h_i (paper, eq. (2)):",
            d.R,
            _name("R(x)", "R"),
        )
    )
    if d.det_R is not None:
        entries.append(
            _math_entry("Its determinant, factored:", d.det_R, _name(r"\det R", "det R"))
        )
        where = (
            "R is singular when " + " or when ".join(d.singular_set) + "."
            if d.singular_set
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
                text=f"det R is {d.det_R_note}; the generated code checks every pivot at run time.",
            )
        )
    if d.undefined_set:
        entries.append(
            Entry(
                "text",
                text="R or p, and with them the law, is undefined where "
                + " or where ".join(d.undefined_set)
                + " (a vanishing denominator, or a cosine under tan); det R says nothing "
                "there.",
            )
        )
    entries.append(_math_entry("p = col(L_f^(r_i) h_i):", d.p, _name("p(x)", "p")))
    entries.append(
        _math_entry("Coordinates Phi (paper, Lemmas 1-2):", d.phi, _name(r"\Phi(x)", "&#934;"))
    )
    entries.append(_math_entry("Brunovsky pair, A:", d.A, _name("A", "A")))
    entries.append(_math_entry("Brunovsky pair, B:", d.B, _name("B", "B")))
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
            d.gradient,
            _name(r"\nabla_y f_0", "&#8711;f0"),
        ),
        _math_entry("Its Hessian:", d.hessian, _name(r"\nabla_{yy} f_0", "&#8711;&#178;f0")),
    ]
    conv = d.convexity
    how = (
        "the Hessian is constant, so its smallest eigenvalue is exact"
        if conv.method == "constant Hessian"
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
        assert d.kkt_gradient is not None
        entries += [
            _math_entry(
                "With equality constraints the law is written for L = f0 + nu^T a over (y, nu): "
                "its gradient, the KKT map F = [grad f0 + J_a^T nu; a], is what E holds:",
                d.kkt_gradient,
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
    k, m = d.k, d.n_kkt
    # With equalities E holds the KKT map F and its derivatives instead of grad f0's.
    first, last = ("F", f"F^({k - 1})") if d.model.equalities else ("grad f0", f"grad^({k - 1}) f0")
    companion = sp.zeros(k, k)
    for i in range(k - 1):
        companion[i, i + 1] = 1
    for j, a in enumerate(d.coefficients):
        companion[k - 1, j] = sp.Float(a, 15)
    entries = [
        Entry(
            "text",
            text=(
                f"E = col({first}, ..., {last}) obeys E' = H E with H = companion(a) "
                f"kron I_{m} (paper, eqs. (14)-(15))."
            ),
        ),
        _math_entry(
            "Companion matrix, last row a_0 .. a_{k-1}:",
            companion,
            _name(r"\mathrm{companion}(a)", "companion(a)"),
        ),
        Entry(
            "table",
            text="Spectrum and the constants of |expm(H t)| <= c exp(-alpha t) (paper, Theorem 3).",
            header=("quantity", "value"),
            rows=(
                ("poles", ", ".join(_pole(p) for p in d.eigenvalues)),
                ("coefficients a", ", ".join(f"{a:.10g}" for a in d.coefficients)),
                ("decay rate -max Re(lambda)", f"{d.decay_rate:.6g}"),
                (
                    "alpha used in the bound",
                    f"{d.certified_rate:.6g}"
                    + ("" if d.certified_rate_exact else " (repeated poles: 10% epsilon)"),
                ),
                ("c = sup_t |expm(H t)| e^(alpha t), computed", f"{d.transient_constant:.6g}"),
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


def _control_law(d: Derivation) -> Section:
    k = d.k
    theorem = (
        "Theorem 5, Control Law for Uniform Vector Relative Degree Systems: u = alpha + "
        "beta R^-1 [y_imp^(k) - p] (eq. (18))"
        if d.uniform
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
                f"y^(k) = 0. Program size: {len(d.jet_program.assignments)} assignments for "
                f"grad^(j), j < k, and {len(d.rest_program.assignments)} more for rest. The "
                "generated code solves Hess z = sum a_i grad^(i) f0 - rest (LDL^T, a "
                "square-root-free Cholesky, or the exact constant inverse when the Hessian is "
                "constant) and R w = v - p (LU with partial pivoting); no symbolic inverse is "
                "formed."
            ),
        ),
    ]
    program = d.jet_program + d.rest_program
    for j in range(1, k):
        exprs = [program.inline(e) for e in d.grad_jet[j]]
        if sum(sp.count_ops(e) for e in exprs) <= INLINE_OPS:
            entries.append(
                _math_entry(
                    f"grad^({j}) f0, inlined for checking:",
                    sp.Matrix(exprs),
                    _name(rf"\nabla_y^{{({j})}} f_0", f"&#8711;({j})f0"),
                )
            )
    rest = [program.inline(e) for e in d.rest]
    if sum(sp.count_ops(e) for e in rest) <= INLINE_OPS:
        entries.append(
            _math_entry(
                f"rest = grad^({k}) f0 at y^({k}) = 0, inlined:",
                sp.Matrix(rest),
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
                    ("sympy", sp.__version__),
                ),
            ),
        ),
    )


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


#: Largest simulation output the report reads: a certificate is a few KB, a figure
#: a few hundred.
MAX_RESULT_BYTES = {"certificate.txt": 1_000_000, "png": 20_000_000}


def read_results(folder: str | Path, name: str) -> dict[str, bytes]:
    """The simulation outputs of ``name`` in ``folder`` the report shows (may be empty).

    Only files ``simulate`` wrote there and nobody changed since are read, each within
    a size bound, so a stray or huge file of that name costs neither memory nor trust.
    """
    found = {}
    for stem in ("certificate.txt", "paths.png", "convergence.png", "inputs.png"):
        file_name = f"{name}_{stem}"
        limit = MAX_RESULT_BYTES.get(stem, MAX_RESULT_BYTES["png"])
        data = read_own_output(folder, file_name, limit)
        if data is not None:
            found[file_name] = data
    return found


def report_sections(
    derivation: Derivation, kernels: KernelSet, results: Mapping[str, bytes] | None = None
) -> tuple[Section, ...]:
    """All sections of the report, in :data:`HEADINGS` order."""
    d = derivation
    return (
        _model(d),
        _extension(d),
        _linearization(d),
        _objective(d),
        _error_dynamics(d),
        _control_law(d),
        _provenance(d, kernels),
        _simulation(d, results or {}),
    )


def render_report(
    derivation: Derivation,
    kernels: KernelSet,
    results: Mapping[str, bytes] | None = None,
    formats: Sequence[str] = ("html", "md"),
) -> dict[str, str]:
    """The report files, ``<name>_report.html`` and/or ``<name>_report.md``, as text.

    Parameters
    ----------
    derivation : Derivation
        What to report.
    kernels : KernelSet
        The lowered kernels (for operation counts).
    results : mapping of str to bytes, optional
        Simulation outputs found beside the report (certificate and PNG figures).
    formats : sequence of str
        ``"html"``, ``"md"`` or both.
    """
    sections = report_sections(derivation, kernels, results)
    context = {
        "d": derivation,
        "spec": derivation.spec,
        "sections": sections,
        "tool_version": __version__,
        "sympy_version": sp.__version__,
    }
    return {
        f"{derivation.spec.name}_report.{fmt}": render_template(FORMATS[fmt], context)
        for fmt in formats
    }
