r"""The report's LaTeX, MathML and text, printed from either engine's expressions without SymPy.

Converting what the report shows to SymPy and printing it there took most of a report's
time (``ur5_tip``: 341 definitions and six matrices, 3.6 s, SymPy's import alone 0.5-1.3
s). These printers walk the expressions through the :mod:`~tvopt_codegen.symbolic` API
for the nodes a derivation holds (sums, products, powers, symbols, numbers, the
elementary functions, ``Piecewise`` and relations) and raise :class:`Unprintable` on any
other, which :mod:`~tvopt_codegen.report.entries` then hands to SymPy's printers.

The LaTeX (:mod:`.latex`) is SymPy's ``latex(expr, order="none", mul_symbol=r"\,")`` and
the text (:mod:`.text`) SymPy's ``sstr(expr, order="none")`` character for character (the
tests hold it on real derivations): a sum's terms and a product's factors in SymPy's order
of its arguments (:mod:`.nodes`, the same from either engine) rather than SymPy's default
printing order, whose sorting was a third of its printing time. The MathML
(:mod:`.mathml`) is SymPy's presentation markup for the same nodes, in the same order,
with the report's two changes (matrices as ``mtable`` of class ``matrix`` without fences;
a thin space around an invisible times beside a name of several letters or a function).
:func:`count_ops` is SymPy's operation count, the report's cap on an inlined jet.
"""

from __future__ import annotations

from tvopt_codegen.report.latex import latex
from tvopt_codegen.report.mathml import mathml
from tvopt_codegen.report.nodes import Unprintable
from tvopt_codegen.report.text import count_ops, text

__all__ = ["Unprintable", "count_ops", "latex", "mathml", "text"]
