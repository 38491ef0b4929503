"""The report's building blocks, as data the templates lay out.

Paragraphs, equations (MathML and LaTeX), tables and figures.

The report prints what it shows itself, from either engine's expressions
(:mod:`tvopt_codegen.report.printing`: SymPy's LaTeX, MathML and text, in the order of
the arguments). Only a node those printers do not print is converted to SymPy
(:mod:`tvopt_codegen.symbolic.border`) and printed there, SymPy imported then, never when
the module is (``simulate`` and a report on SymEngine import no SymPy).
"""

from __future__ import annotations

import base64
import functools
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

from tvopt_codegen import symbolic as sx
from tvopt_codegen.report import printing
from tvopt_codegen.symbolic.border import sympy, to_sympy

#: Equations longer than this (LaTeX characters) are folded, shown in full on demand.
FOLD_AT = 600


#: A matrix with more entries than this, most of them zero (a team's G, R or Hessian), is
#: listed by its nonzero entries: a dense 64 x 64 array of zeros cannot be checked by eye.
SPARSE_AT = 64


#: Gradient-jet expressions above this many operations are described, not inlined.
INLINE_OPS = 400


#: Functions that are smooth (analytic) on the whole real line, by name.
ENTIRE = ("sin", "cos", "exp", "sinh", "cosh", "tanh", "atan", "asinh")


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


@functools.cache
def _printer_class() -> Any:
    """The report's MathML printer class, made on first use (it subclasses SymPy's)."""
    from sympy.printing.mathml import MathMLPresentationPrinter  # noqa: PLC0415 - the border

    class ReportMathMLPrinter(MathMLPresentationPrinter):  # type: ignore[misc]
        """Presentation MathML as a browser shows it well without a math font.

        Customizations are listed on each override; everything else is sympy's printer.
        """

        def _print_MatrixBase(self, m: Any) -> Any:
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

        def _print_Mul(self, expr: Any) -> Any:
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

    # Named as the module's attribute that hands it out, not after this function.
    ReportMathMLPrinter.__qualname__ = "ReportMathMLPrinter"
    return ReportMathMLPrinter


def __getattr__(name: str) -> Any:
    """``ReportMathMLPrinter``, SymPy's MathML printer as the report customizes it.

    Made when first asked for, so that importing this module imports no SymPy.
    """
    if name == "ReportMathMLPrinter":
        return _printer_class()
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


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


#: The report's LaTeX settings: a thin space between factors, a sum's terms and a
#: product's factors in the order of its arguments (what :mod:`printing` prints).
_LATEX = {"mul_symbol": r"\,", "order": "none"}


def shown(expr: object) -> Any:
    """``expr`` as the report shows it: an expression or matrix of the engine.

    Every formula passes here (the tests record what the report shows through it). A
    Python number becomes the engine's; anything else (a SymPy expression while
    SymEngine derives) is kept and printed by SymPy.
    """
    if isinstance(expr, sx.Basic | sx.MatrixBase):
        return expr
    if isinstance(expr, int | float):
        return sx.as_expr(expr)
    return expr


def as_sympy(expr: object) -> Any:
    """``expr`` as SymPy's: converted at the border, floats with a spec's 15 digits.

    The border keeps a double's every bit (17 digits); shown, it has the 15 digits of a
    SymPy float read from the spec (0.1, not 0.10000000000000001).
    """
    sp = sympy()
    if sx.SYMENGINE and isinstance(expr, sx.Basic | sx.MatrixBase):
        value = to_sympy(expr)
        floats = value.atoms(sp.Float)
        return value.xreplace({f: sp.Float(float(f), 15) for f in floats}) if floats else value
    return sp.sympify(expr)


def plain(expr: object) -> str:
    """``expr`` (small: a weight, a slack) as SymPy's one-line text, on either engine.

    SymPy's ``sstr(expr, order="none")``: the report's own printer, SymPy's for a node it
    does not print.
    """
    value = shown(expr)
    if _native(value):
        try:
            return printing.text(value)
        except printing.Unprintable:
            pass
    return str(sympy().sstr(as_sympy(value), order="none"))


def count_ops(expr: object) -> int:
    """SymPy's operation count of what ``expr`` shows (the inlining cap's measure)."""
    value = shown(expr)
    if _native(value):
        try:
            return printing.count_ops(value)
        except printing.Unprintable:
            pass
    return int(sympy().count_ops(as_sympy(value)))


def _native(value: object) -> bool:
    """Whether the report's own printers take ``value`` (an expression of the engine)."""
    return isinstance(value, sx.Basic | sx.MatrixBase)


def _latex(value: object) -> str:
    """``value``'s LaTeX: the report's printer, SymPy's for what it does not print."""
    if _native(value):
        try:
            return printing.latex(value)
        except printing.Unprintable:
            pass
    return str(sympy().latex(as_sympy(value), **_LATEX))


def _mathml(value: object) -> str:
    """``value``'s presentation MathML: the report's printer, else SymPy's as customized."""
    if _native(value):
        try:
            return printing.mathml(value)
        except printing.Unprintable:
            pass
    printer = _printer_class()({"order": "none"})
    return str(printer.doprint(as_sympy(value)))


def formula(expr: object, lhs: tuple[str, str] | None = None) -> Math:
    """Both notations of ``expr``, optionally as ``lhs = expr``.

    Parameters
    ----------
    expr : expression, matrix or number
        The right-hand side, of either engine.
    lhs : tuple of (str, str), optional
        The left-hand side as (LaTeX, MathML).
    """
    value = shown(expr)
    latex, markup = _latex(value), _mathml(value)
    if lhs is not None:
        latex = f"{lhs[0]} = {latex}"
        markup = f"<mrow>{lhs[1]}<mo>=</mo>{markup}</mrow>"
    return Math(latex, markup)


def _name(latex: str, text: str) -> tuple[str, str]:
    """A left-hand side: LaTeX and an MathML identifier (``text`` is plain ASCII)."""
    return latex, f"<mi>{text}</mi>"


def _math_entry(text: str, expr: object, lhs: tuple[str, str] | None = None) -> Entry:
    value = shown(expr)
    if lhs is not None and isinstance(value, sx.MatrixBase):
        rows, cols = value.shape
        size = rows * cols
        nonzero = [((i, j), value[i, j]) for i in range(rows) for j in range(cols)]
        nonzero = [(at, e) for at, e in nonzero if e != 0]
        if size > SPARSE_AT and 2 * len(nonzero) <= size:
            zeros = size - len(nonzero)
            # Structurally symmetric (a Hessian is, entry by entry): the lower triangle says
            # it all.
            symmetric = rows == cols and all(value[j, i] == e for (i, j), e in nonzero if i != j)
            if symmetric:
                nonzero = [((i, j), e) for (i, j), e in nonzero if i >= j]
            text = (
                f"{text.rstrip(':')} ({rows} x {cols}, "
                + (
                    "symmetric; the nonzero entries of its lower triangle"
                    if symmetric
                    else "its nonzero entries"
                )
                + f", indexed from 1; the other {zeros} entries are 0):"
            )
            return Entry("math", text=text, math=_entries(nonzero, lhs))
    return Entry("math", text=text, math=formula(value, lhs))


def _entries(nonzero: Sequence[tuple[tuple[int, int], Any]], lhs: tuple[str, str]) -> Math:
    """``[M]_ij = value`` for each listed entry, one per line, in both notations."""
    text = (
        r"\begin{aligned}"
        + r" \\ ".join(
            rf"\left[{lhs[0]}\right]_{{{i + 1}, {j + 1}}} &= {_latex(e)}" for (i, j), e in nonzero
        )
        + r"\end{aligned}"
    )
    rows = "".join(
        f"<mtr><mtd><msub><mrow><mo>[</mo>{lhs[1]}<mo>]</mo></mrow>"
        f"<mrow><mn>{i + 1}</mn><mo>,</mo><mn>{j + 1}</mn></mrow></msub></mtd>"
        f"<mtd><mo>=</mo></mtd><mtd>{_mathml(e)}</mtd></mtr>"
        for (i, j), e in nonzero
    )
    return Math(text, f"<mtable>{rows}</mtable>")


def _functions(expr: sx.Expr) -> set[str]:
    """The names of the functions applied in ``expr`` (``exp`` for a power of e)."""
    found: set[str] = set()
    seen: set[Any] = set()
    stack = [expr]
    while stack:
        node = stack.pop()
        if node in seen:
            continue
        seen.add(node)
        if node.is_Pow and type(node.args[0]).__name__ == "Exp1":
            found.add("exp")
        elif node.is_Function:
            found.add("Piecewise" if sx.is_piecewise(node) else sx.function_name(node))
        stack.extend(node.args)
    return found


def _smoothness(expr: sx.Expr) -> str:
    used = sorted(_functions(expr))
    restricted = [f for f in used if f not in ENTIRE]
    if not used:
        return "polynomial in t: C-infinity"
    if not restricted:
        return f"built from {', '.join(used)}: C-infinity for all t"
    return f"C-infinity where {', '.join(restricted)} are defined and smooth"
