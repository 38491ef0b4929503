"""Stage 3: everything the paper derives, as one :class:`Derivation`.

Both the code generators and the report read this object; nothing downstream
re-derives mathematics. The steps follow the paper: dynamic extension and vector
relative degree (Lemmas 1-2), padding chains for unequal relative degrees (Section
IV-B), the gradient jet ``grad^(j) f0`` (Lemma "Gradient Time Differentiation") and the
implicit law ``y_imp^(k)`` (equation y_kth_derivative_solution) feeding
``u = alpha + beta R^-1 [v - p]`` (Theorems for uniform and non-uniform degree).

One module per concept: :mod:`.record` (the :class:`Derivation` readers see),
:mod:`.linearization` (extension, relative degree, R and p, the closed-loop states),
:mod:`.singularity` (det R simplified, where R is singular or R and p undefined),
:mod:`.objective` (f0's programs and the gradient jet), :mod:`.convexity` (the numerical
checks of strong convexity), :mod:`.equalities` (equality constraints and the
Lagrangian), :mod:`.meter` (the budgets) and :mod:`.pipeline` (:func:`derive`, which runs
them in the paper's order).
"""

from __future__ import annotations

from tvopt_codegen.derivation.meter import tree_size
from tvopt_codegen.derivation.pipeline import derive
from tvopt_codegen.derivation.record import Convexity, Derivation, jet_symbol

__all__ = ["Convexity", "Derivation", "derive", "jet_symbol", "tree_size"]
