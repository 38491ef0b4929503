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

from typing import Any

from tvopt_codegen.report.document import (
    FORMATS,
    HEADINGS,
    MAX_RESULT_BYTES,
    ROBUST_HEADINGS,
    read_results,
    render_report,
    report_sections,
)
from tvopt_codegen.report.entries import (
    ENTIRE,
    FOLD_AT,
    INLINE_OPS,
    SPARSE_AT,
    Entry,
    Math,
    Section,
    formula,
)

__all__ = [
    "ENTIRE",
    "Entry",
    "FOLD_AT",
    "FORMATS",
    "HEADINGS",
    "ROBUST_HEADINGS",
    "INLINE_OPS",
    "MAX_RESULT_BYTES",
    "Math",
    "ReportMathMLPrinter",
    "SPARSE_AT",
    "Section",
    "formula",
    "read_results",
    "render_report",
    "report_sections",
]


def __getattr__(name: str) -> Any:
    """``ReportMathMLPrinter``, made (and SymPy imported) when first asked for."""
    if name == "ReportMathMLPrinter":
        from tvopt_codegen.report import entries  # noqa: PLC0415 - SymPy on demand only

        return entries.ReportMathMLPrinter
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
