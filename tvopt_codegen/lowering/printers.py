"""What every backend's printer shares: sympy's canonical order, printed as it stands.

Each backend subclasses sympy's printer for its language in its own folder
(``backends/<name>/printer.py``), mixing :class:`CanonicalOrder` in.
"""

from __future__ import annotations

from typing import Any

import sympy as sp


class CanonicalOrder:
    """Canonical order of terms and factors, and one expression printed directly.

    sympy's default ("lex") order sorts the terms of every sum by monomial degrees,
    which computes each term's coefficient (with ``evalf``) and sort key: half of all
    printing time for a large controller. The canonical order is already
    deterministic (sympy sorts arguments when it builds a sum or product), so it is
    used as is, with the constant moved to the end where a reader expects it and a
    positive term first when there is one (``1 - x``, not ``-x + 1``).
    """

    _print: Any  # sympy's Printer._print, from the printer this is mixed into

    def doprint(self, expr: Any, assign_to: Any = None) -> str:
        """Print one expression.

        sympy's ``doprint`` first rebuilds the whole expression to unwrap ``re`` of
        unevaluated expressions (kernels have none) and formats the text as lines of
        code: a quarter of printing time for a large controller. One expression that
        prints as one line, with no number constant to declare, is printed directly;
        anything else goes through ``doprint`` as before.
        """
        if assign_to is None and isinstance(expr, sp.Basic):
            self._not_supported: set[Any] = set()
            self._number_symbols: set[Any] = set()
            text: str = self._print(expr)
            if "\n" not in text and not self._number_symbols and not self._not_supported:
                return text
        printed: str = super().doprint(expr, assign_to)  # type: ignore[misc]
        return printed

    def _as_ordered_terms(self, expr: sp.Expr, order: str | None = None) -> list[sp.Expr]:
        args = list(expr.args)
        terms = [a for a in args if not a.is_Number] + [a for a in args if a.is_Number]
        if negative_term(terms[0]):
            first = next((i for i, term in enumerate(terms) if not negative_term(term)), 0)
            terms.insert(0, terms.pop(first))
        return terms


def negative_term(term: sp.Expr) -> bool:
    """Whether a term prints with a leading minus sign."""
    coefficient = term.args[0] if term.is_Mul else term
    return bool(coefficient.is_Number and coefficient.is_negative)
