"""Rational trigonometric determinants in lowest terms without SymPy, where SymPy's form is sure.

A determinant such as a two-link arm's det R, ``sin(q2)/(l1 l2 m2 (m1 + m2 sin(q2)^2))``,
is a rational function in symbols and in the sine and cosine of angles. SymPy writes it
as ``factor(simplify(det))`` (:func:`.singularity.simplified_det`); importing SymPy for
that alone cost more than the rest of ``generate arm_on_line``. This module reads such a
determinant as a quotient of polynomials with rational coefficients in its atoms
(symbols, ``s = sin(a)`` and ``c = cos(a)`` of a symbol ``a``, angle sums expanded:
:mod:`.trigpoly`),
reduces both by ``s^2 + c^2 = 1``, cancels their monomial and numeric contents and an
exact polynomial quotient, and accepts what is left only in one shape, the one whose
SymPy form is known:

    ``k * M / (D * P)``: ``k`` a rational, ``M`` a product of powers of symbols and of
    sines and cosines (one function per angle), ``D`` a product of powers of symbols,
    ``P`` a primitive polynomial of two or more terms with integer coefficients in
    symbols and the square of the sine or cosine of at most one angle (no higher
    power), provably irreducible.

Why that shape is SymPy's: ``factor`` reads its argument as a rational function of its
generators (``sin(a)`` and ``cos(a)`` are two), so its output is the canonical factored
form of that function: the numeric content out, each irreducible factor primitive with
a positive leading coefficient in lex order of SymPy's sorted generators
(``polyutils._sort_gens``). The one choice left to ``simplify`` is how the trigonometry
is written; for ``P`` in ``sin^2`` or in ``cos^2`` it takes the form with fewer terms
(``m1 + m2 - m2 cos^2`` is ``m1 + m2 sin^2``), and where both have as many terms it keeps
whichever it was given, so that case is refused here. ``tests/test_det_native.py``
holds the result to SymPy's, tree and text, on every bundled example and test spec and
on random determinants of the shape and beside it.

Everything else (a numerator that is a sum, two polynomial factors, an angle under a sine
and a cosine in ``M``, a sine in ``D``, a function of anything but a symbol) returns
None: SymPy decides, as before.

Two more of the derivation's border crossings are answered here for such polynomials:
:func:`sympy_text`, a condition's text as SymPy's ``sstr`` writes it (where R or p is
undefined: an arm's dynamics' denominator), and :func:`indefinite`, whether a value
takes both signs (then SymPy's sound tests find no sign).
"""

from __future__ import annotations

import itertools
import re
from dataclasses import dataclass
from fractions import Fraction
from typing import Any

from tvopt_codegen import symbolic as sx
from tvopt_codegen.symbolic.trigpoly import (
    MAX_TERMS,
    ONE,
    Atoms,
    Monomial,
    Poly,
    Rational,
    add,
    content,
    exact_quotient,
    inverse,
    irreducible,
    poly_expr,
    product,
    rational,
    reduced,
    scaled,
    times,
)


@dataclass(frozen=True)
class Lowest:
    """A determinant in the accepted shape ``k * M / (D * P)`` (see the module's docstring).

    ``numerator`` and ``denominator`` are ``M`` and ``D`` as ``(atom, exponent)``;
    ``factor`` is ``P`` as written (``None`` for a monomial determinant).
    """

    atoms: Atoms
    number: Fraction
    numerator: Monomial
    denominator: Monomial
    factor: Poly | None

    def expr(self) -> sx.Expr:
        """The determinant as an expression of the engine, SymPy's ``factor`` tree."""
        out = sx.Rational(self.number.numerator, self.number.denominator)
        for atom, k in self.numerator:
            out *= self.atoms.exprs[atom] ** k
        for atom, k in self.denominator:
            out *= self.atoms.exprs[atom] ** -k
        if self.factor is not None:
            out *= poly_expr(self.factor, self.atoms) ** -1
        return out

    def conditions(self) -> list[tuple[Any, int, tuple[str, str | None]]]:
        """The numerator's atoms as :func:`.singularity._monomial_conditions` reads them."""
        return [
            (self.atoms.exprs[a], k, (self.atoms.kinds[a], self.atoms.names[a]))
            for a, k in self.numerator
        ]


def lowest(det: sx.Expr) -> Lowest | None:
    """``det`` in the accepted shape, equal to it exactly, or None (SymPy decides)."""
    if _angle_sums(det, {}) is None:
        return None
    atoms = Atoms()
    found = rational(det, atoms, {})
    if found is None or not found[0] or not found[1]:
        return None
    angles = sorted({atoms.names[a] for a, kind in enumerate(atoms.kinds) if kind})
    if len(angles) > 3:
        return None
    # Each angle's square rewritten one way or the other: the numerator is a monomial in
    # at most one of them (cos^2 or 1 - sin^2); every way is tried.
    for mask in range(2 ** len(angles)):
        kinds = {a: ("cos" if mask >> i & 1 else "sin") for i, a in enumerate(angles)}
        shaped = _shaped(found, atoms, kinds)
        if shaped is not None:
            return shaped
    return None


def _angle_sums(node: Any, memo: dict[Any, bool | None]) -> bool | None:
    """Whether ``node`` holds a sine or cosine of a sum of angles; None where not plainly.

    Plainly: never under a power (a square, a denominator) nor two in one product.
    SymPy's ``simplify`` writes an arm's ``sin(q1 + q2) cos(q1) - cos(q1 + q2) sin(q1)``
    as ``sin(q2)``, and so the expansion here agrees with it, but not always its square
    (``-3 (...)^2 / (-2 - 2 l1 x)`` stays as it is: found by the tests), nor a product
    of two, which it may write with ``cos(2 q2)``.
    """
    if node in memo:
        return memo[node]
    out: bool | None = False
    if node.is_Function and sx.function_name(node) in ("sin", "cos"):
        out = not node.args[0].is_Symbol
    elif node.args:
        parts = [_angle_sums(arg, memo) for arg in node.args]
        if any(part is None for part in parts):
            out = None
        elif node.is_Pow and parts[0] and node.args[1] != 1:
            out = None
        elif node.is_Mul and sum(bool(part) for part in parts) > 1:
            out = None
        else:
            out = any(parts)
    memo[node] = out
    return out


def _shaped(found: Rational, atoms: Atoms, kinds: dict[str, str]) -> Lowest | None:
    numerator, denominator = (reduced(p, atoms, kinds) for p in found)
    if not numerator or not denominator:
        return None
    top_number, top_monomial, top = content(numerator)
    bottom_number, bottom_monomial, bottom = content(denominator)
    if len(top) > 1 and len(bottom) > 1:  # a common factor, where one divides the other
        smaller, larger = (top, bottom) if len(top) <= len(bottom) else (bottom, top)
        quotient = exact_quotient(larger, smaller)
        if quotient is None:
            return None
        number, monomial, rest = content(quotient)
        if smaller is top:
            top, bottom = ONE, rest
            bottom_number *= number
            bottom_monomial = times(bottom_monomial, monomial)
        else:
            top, bottom = rest, ONE
            top_number *= number
            top_monomial = times(top_monomial, monomial)
    if len(top) > 1:  # a polynomial factor in the numerator: its text is SymPy's to write
        return None
    ((_, top_sign),) = top.items()  # what is left of a monomial: 1 or -1
    powers = dict(top_monomial)
    for a, k in bottom_monomial:
        powers[a] = powers.get(a, 0) - k
    number = top_sign * top_number / bottom_number
    up = tuple(sorted((a, k) for a, k in powers.items() if k > 0))
    down = tuple(sorted((a, -k) for a, k in powers.items() if k < 0))
    if any(atoms.kinds[a] for a, _ in down):  # a sine or cosine below: tan, cot, csc, sec
        return None
    up_angles = [atoms.names[a] for a, _ in up if atoms.kinds[a]]
    if len(up_angles) != len(set(up_angles)):  # sin(a) cos(a): sin(2 a)/2 to SymPy
        return None
    factor: Poly | None = None
    if len(bottom) > 1:
        factor = _written(bottom, atoms)
        if factor is None:
            return None
        leading = _sign_of_leading(factor, atoms)
        if not leading:
            return None
        if leading < 0:
            factor = {m: -c for m, c in factor.items()}
            number = -number
    else:
        ((_, bottom_sign),) = bottom.items()
        number *= bottom_sign
    lowest = Lowest(atoms, number, up, down, factor)
    if not _equal(found, lowest, atoms):
        return None
    return lowest


def _written(p: Poly, atoms: Atoms) -> Poly | None:
    """``P`` as SymPy's ``simplify`` writes it: in sin^2 or cos^2, the shorter; or None.

    ``p`` is primitive, without monomial content, reduced. None where ``p`` holds more
    than one angle, a power of a sine or cosine other than the square, two forms of one
    length, or where its irreducibility is not proved (:func:`.trigpoly.irreducible`).
    """
    trig = {atoms.names[a] for m in p for a, _ in m if atoms.kinds[a]}
    if len(trig) > 1:
        return None
    if not trig:
        return p if irreducible(p) else None
    if any(atoms.kinds[a] and k != 2 for m in p for a, k in m):
        # Beyond a square, simplify keeps the expansion of (1 - sin^2)^2 rather than
        # cos^4, though shorter: not a rule of fewer terms (found by the tests).
        return None
    (angle,) = trig
    # p has only one function of the angle (the other one's square was reduced away).
    forms = [reduced(p, atoms, {angle: kind}) for kind in ("sin", "cos")]
    forms.sort(key=len)
    if len(forms[0]) == len(forms[1]):
        return None
    shortest = forms[0]
    if any(abs(c) == 2 and len(m) == 1 for m, c in shortest.items() if m and atoms.kinds[m[0][0]]):
        # 2 cos^2 and -2 sin^2 are 1 + cos(2 q) and cos(2 q) - 1, which simplify may
        # write instead (it does for a + 2 cos^2, not for a - 2 cos^2: the sign SymPy's
        # factor leaves decides; found by hypothesis): SymPy's to write.
        return None
    return shortest if irreducible(shortest) else None


_GEN = re.compile(r"^(.*?)(\d*)$", re.MULTILINE)
#: SymPy's preferred generator order (``sympy.polys.polyutils._gens_order``, 1.14).
_GENS_ORDER = {
    **{letter: 301 + i for i, letter in enumerate("abcdefghijklmno")},
    **{letter: 216 + i for i, letter in enumerate("pqrstuvw")},
    "x": 124,
    "y": 125,
    "z": 126,
}


def _gen_key(text: str) -> tuple[int, str, int]:
    """SymPy's ``_sort_gens`` key of a generator written ``text``."""
    match = _GEN.match(text)
    name, index = match.groups() if match else (text, "")
    return (_GENS_ORDER.get(name, 1000), name, int(index) if index else 0)


def _sign_of_leading(p: Poly, atoms: Atoms) -> int:
    """The sign of ``p``'s leading coefficient in lex order of SymPy's sorted generators.

    0 where two generators share a key (their order would be SymPy's input's).
    """
    present = sorted({a for m in p for a, _ in m}, key=lambda a: _gen_key(atoms.text(a)))
    keys = [_gen_key(atoms.text(a)) for a in present]
    if len(set(keys)) != len(keys):
        return 0
    lead = max(p, key=lambda m: tuple(dict(m).get(a, 0) for a in present))
    return 1 if p[lead] > 0 else -1


def _equal(found: Rational, lowest: Lowest, atoms: Atoms) -> bool:
    """Whether ``lowest`` is the determinant exactly.

    That is, ``N * bottom - top * D`` is zero on the circle (its reduced form is empty).
    """
    top: Poly = {lowest.numerator: lowest.number}
    bottom: Poly = {lowest.denominator: Fraction(1)}
    if lowest.factor is not None:
        bottom = product(bottom, lowest.factor)
    kinds = {atoms.names[a]: "cos" for a, kind in enumerate(atoms.kinds) if kind}
    difference = add(product(found[0], bottom), product(top, found[1]), -1)
    return not reduced(difference, atoms, kinds)


# SymPy's ``dotprodsimp`` of a small determinant, without SymPy. SymPy writes a 2 x 2 or
# 3 x 3 determinant out, expands it and, when the expansion has a fraction and six
# operations or more, puts it over one denominator with ``cancel``, its functions read as
# independent generators (dummies): ``P/Q``, ``P`` and ``Q`` expanded polynomials with
# integer coefficients and no common factor, ``Q``'s leading coefficient positive in lex
# order of SymPy's sorted generators. That form is unique once the common factor is known
# and the leading coefficient's sign is sure; it is found here where both are: every
# denominator in the expansion is a monomial times a polynomial proved irreducible
# (:func:`.trigpoly.irreducible`; a mass-matrix arm's ``m1 + m2 - m2 cos(q2)^2``), so that the
# common factor is a monomial, a number and powers of those polynomials, each found by
# exact division.

#: Most functions in a denominator whose order among SymPy's dummies is tried.
_MAX_DUMMIES = 5
#: SymPy's ``_sort_gens`` key of its dummies (``str(Dummy())`` is ``_Dummy_<n>``).
_DUMMY_NAME = "_Dummy_"
#: ``dotprodsimp`` cancels from this many operations on (its ``count_ops_alg``).
_CANCEL_OPS = 6


def cancelled(written: sx.Expr, expanded: sx.Expr) -> sx.Expr | None:
    """SymPy's ``dotprodsimp`` of a determinant with denominators, from its expansion.

    ``written`` is the determinant written out, its functions' arguments expanded, and
    ``expanded`` the whole expanded as ``dotprodsimp`` expands it, with a denominator
    somewhere. Returns what ``dotprodsimp`` returns, ``cancel``'s ``P/Q`` as an
    expression of the engine built as SymPy's converts, or None where that is not sure:
    an atom other than a symbol or a sine or cosine of a sum of symbols with positive
    coefficients, a denominator not proved a monomial times irreducible polynomials,
    too few operations to be sure ``dotprodsimp`` cancels, or a sign that depends on the
    order of SymPy's dummies.
    """
    if not _may_hold_fractions(expanded):
        return None
    plain: dict[Any, bool] = {}
    if not (_plain_functions(written, plain) and _plain_functions(expanded, plain)):
        return None
    atoms = Atoms(expand_angles=False)
    memo: dict[Any, Rational | None] = {}
    primes = _denominator_primes((written, expanded), atoms, memo)
    if primes is None:
        return None
    terms: list[_Term] = []
    for term in expanded.args if expanded.is_Add else (expanded,):
        found = rational(term, atoms, memo)
        below = None if found is None else _factored(found[1], primes)
        if found is None or below is None:
            return None
        number, monomial, exponents = below
        terms.append((scaled(found[0], 1 / number), monomial, exponents))
    if _operations_at_least(terms) < _CANCEL_OPS:
        return None
    lowest_terms = _lowest_terms(terms, primes)
    if lowest_terms is None:
        return None
    top, bottom = lowest_terms
    sign = _leading_sign(bottom, atoms)
    if not sign:
        return None
    if sign < 0:
        top, bottom = scaled(top, Fraction(-1)), scaled(bottom, Fraction(-1))
    if len(bottom) == 1 and () in bottom:
        # Over a number SymPy's ``P/q`` distributes ``1/q`` over P's terms.
        return poly_expr(scaled(top, 1 / bottom[()]), atoms)
    return poly_expr(top, atoms) * poly_expr(bottom, atoms) ** -1


#: A term of the expansion: its numerator, and its denominator's monomial and exponents of
#: the primes (a number times a monomial times powers of irreducible polynomials, the
#: number moved above).
_Term = tuple[Poly, Monomial, tuple[int, ...]]


def _may_hold_fractions(expanded: sx.Expr) -> bool:
    """Whether ``dotprodsimp`` reads the expansion as a rational function (its ``ratfunc``).

    Its ``count_ops_alg`` says so only where a term is a bare negative power (``1/Q``) or
    a fraction with more than a number above (``x/Q``); a term such as ``3/Q`` or
    ``-1/Q`` it splits into its integer numerator and its denominator, and never looks
    at the power. An expansion of such terms and polynomials only is left as it is,
    uncancelled: ``P + 3/Q``, not ``(P Q + 3)/Q``.
    """
    for term in expanded.args if expanded.is_Add else (expanded,):
        if term.is_Pow:
            if not term.args[1].is_Number or term.args[1].is_negative:
                return True
            continue
        if not term.is_Mul:
            continue
        above = below = False
        for factor in term.args:
            if factor.is_Number:
                continue
            if factor.is_Pow and factor.args[1].is_Number and factor.args[1].is_negative:
                below = True
            else:
                above = True
        if above and below:
            return True
    return False


def _plain_functions(node: Any, memo: dict[Any, bool]) -> bool:
    """Whether every function is a sine or cosine of a polynomial with positive coefficients.

    Such an argument is written alike by both engines (neither takes a sign out of it),
    so that the functions are the same generators to both; and it holds no fraction,
    which ``dotprodsimp`` would not look into.
    """
    if node in memo:
        return memo[node]
    if node.is_Function:
        out = sx.function_name(node) in ("sin", "cos") and _positive_polynomial(node.args[0])
    else:
        out = all(_plain_functions(arg, memo) for arg in node.args)
    memo[node] = out
    return out


def _positive_polynomial(arg: Any) -> bool:
    """Whether ``arg`` is a sum of positive multiples of products of powers of symbols."""
    if not arg.free_symbols:
        return False
    for term in arg.args if arg.is_Add else (arg,):
        for factor in term.args if term.is_Mul else (term,):
            if factor.is_Number:
                if not (factor.is_Rational and factor > 0):
                    return False
            elif factor.is_Pow:
                base, k = factor.args
                if not (base.is_Symbol and k.is_Integer and k > 0):
                    return False
            elif not factor.is_Symbol:
                return False
    return True


def _denominator_primes(
    trees: tuple[sx.Expr, ...], atoms: Atoms, memo: dict[Any, Rational | None]
) -> list[Poly] | None:
    """The denominators' polynomial factors proved irreducible, once each up to sign.

    Each denominator (a negative power's base, in the determinant as written and as
    expanded) is a number times a monomial times a primitive polynomial; where that
    polynomial has two terms or more and is proved irreducible (:func:`.trigpoly.irreducible`),
    it is one of the primes (an expansion's ``(m1 + m2 - m2 cos^2)^2``, multiplied
    out, is not proved, but the entry's own denominator is). None where a denominator
    is not a polynomial.
    """
    primes: list[Poly] = []
    seen: set[Any] = set()
    stack = list(trees)
    while stack:
        node = stack.pop()
        if node in seen:
            continue
        seen.add(node)
        if node.is_Pow and node.args[1].is_negative:
            base = rational(node.args[0], atoms, memo)
            if base is None or base[1] != ONE:
                return None
            _, _, rest = content(base[0])
            negated = scaled(rest, Fraction(-1))
            if len(rest) > 1 and irreducible(rest) and rest not in primes:
                if negated not in primes:
                    primes.append(rest)
        stack.extend(node.args)
    return primes


def _factored(p: Poly, primes: list[Poly]) -> tuple[Fraction, Monomial, tuple[int, ...]] | None:
    """``p`` as a signed number, a monomial and the primes' exponents, or None if it is not."""
    number, monomial, rest = content(p)
    exponents = []
    for prime in primes:
        k = 0
        while len(rest) > 1:
            quotient = exact_quotient(rest, prime)
            if quotient is None:
                break
            rest, k = quotient, k + 1
        exponents.append(k)
    if len(rest) != 1 or () not in rest:  # a factor that is none of the primes
        return None
    return number * rest[()], monomial, tuple(exponents)


def _operations_at_least(terms: list[_Term]) -> int:
    """A lower bound on ``count_ops_alg`` of SymPy's expansion of the determinant.

    SymPy's expansion is a sum of terms, each a number times a monomial over a
    denominator: its terms over one denominator (up to a number) sum to one polynomial,
    so they are at least as many as that polynomial's terms. A sum of ``n`` terms counts
    ``n - 1`` operations at least, a term over a monomial at least one (the division),
    and a term over a sum at least two (the division and the sum below).
    """
    groups: dict[tuple[Monomial, tuple[int, ...]], Poly] = {}
    for numerator, monomial, exponents in terms:
        key = (monomial, exponents)
        groups[key] = add(groups.get(key, {}), numerator)
    count = sum(len(numerator) for numerator in groups.values())
    divisions = sum(
        len(numerator) * (2 if any(exponents) else 1 if monomial else 0)
        for (monomial, exponents), numerator in groups.items()
    )
    return count - 1 + divisions


def _lowest_terms(terms: list[_Term], primes: list[Poly]) -> Rational | None:
    """The sum of the terms as ``P/Q`` in lowest terms over the integers, or None.

    Over the least common denominator (a monomial times powers of the primes), the
    common factor of numerator and denominator is their numbers' and monomials' common
    part times each prime to the least of its multiplicities, each counted by exact
    division: the primes are irreducible and pairwise not associate.
    """
    most = [max(exponents[i] for _, _, exponents in terms) for i in range(len(primes))]
    below: dict[int, int] = {}
    for _, monomial, _ in terms:
        for atom, k in monomial:
            below[atom] = max(below.get(atom, 0), k)
    lcd_monomial = tuple(sorted(below.items()))
    total: Poly = {}
    for numerator, monomial, exponents in terms:
        part = scaled(numerator, Fraction(1), times(lcd_monomial, inverse(monomial)))
        for prime, k, top_k in zip(primes, exponents, most, strict=True):
            for _ in range(top_k - k):
                part = product(part, prime)
                if len(part) > MAX_TERMS:
                    return None
        total = add(total, part)
    if not total:
        return None
    top_number, top_monomial, top = content(total)
    bottom: Poly = ONE
    for prime, k in zip(primes, most, strict=True):
        for _ in range(k):
            quotient = exact_quotient(top, prime) if len(top) > 1 else None
            if quotient is None:
                bottom = product(bottom, prime)
            else:
                top = quotient
    common = tuple((a, min(k, below[a])) for a, k in top_monomial if a in below)
    ratio = top_number  # over a denominator of number 1
    numerator = scaled(top, Fraction(ratio.numerator), times(top_monomial, inverse(common)))
    denominator = scaled(bottom, Fraction(ratio.denominator), times(lcd_monomial, inverse(common)))
    lcd: Poly = {lcd_monomial: Fraction(1)}
    for prime, k in zip(primes, most, strict=True):
        for _ in range(k):
            lcd = product(lcd, prime)
    if add(product(numerator, lcd), product(denominator, total), -1):
        return None  # not the sum: a guard, never expected
    return numerator, denominator


def _leading_sign(p: Poly, atoms: Atoms) -> int:
    """The sign of ``p``'s leading coefficient in lex order of SymPy's sorted generators.

    ``cancel``'s generators are the symbols and a dummy per function, sorted by
    ``_sort_gens``; the dummies' order among themselves is that in which ``dotprodsimp``
    met the functions, so every order of them is tried: 0 where the sign depends on it.
    """
    present = sorted({a for m in p for a, _ in m})
    functions = [a for a in present if atoms.kinds[a]]
    symbols = [a for a in present if not atoms.kinds[a]]
    keys = {a: _gen_key(atoms.names[a]) for a in symbols}
    if len(set(keys.values())) < len(keys) or len(functions) > _MAX_DUMMIES:
        return 0  # two symbols of one key (x1, x01): SymPy's order is its input's
    if any(key[1] == _DUMMY_NAME for key in keys.values()):
        return 0
    dummy = (1000, _DUMMY_NAME, 0)
    before = sorted((a for a in symbols if keys[a] < dummy), key=keys.__getitem__)
    after = sorted((a for a in symbols if keys[a] > dummy), key=keys.__getitem__)
    signs = set()
    for order in itertools.permutations(functions):
        gens = [*before, *order, *after]
        lead = max(p, key=lambda m: tuple(dict(m).get(a, 0) for a in gens))
        signs.add(1 if p[lead] > 0 else -1)
    return signs.pop() if len(signs) == 1 else 0


# SymPy's text of a condition, without SymPy. A condition where R or p is undefined quotes
# an expression (a dynamics' denominator) as SymPy's default ``sstr`` writes it: a sum's
# terms in SymPy's ``as_ordered_terms`` order (descending lex in its generators, sorted by
# ``sort_key``), a product's factors by ``sort_key``. Written here for integers, symbols,
# sines and cosines of symbols, sums, products and positive integer powers (an arm's
# ``l2**2*m2*(l1**2*(m1 + m2) + ...) - (l1*l2*m2*cos(q2) + l2**2*m2)**2``): None
# elsewhere, and where SymPy's constructors would rebuild the tree otherwise (a number
# times one sum, which SymPy distributes; a power of a sum with a negative term).

_SortKey = tuple[Any, ...]
_NUMBER_CLASS = (1, 0, "Number")
_ONE_KEY: _SortKey = (_NUMBER_CLASS, (0, ()), (), Fraction(1))
_FUNCTION_CLASS = {"sin": (4, 20, "sin"), "cos": (4, 21, "cos")}
#: SymPy's printing precedences (``sympy.printing.precedence.PRECEDENCE``).
_ADD, _MUL, _POW = 40, 50, 60


def _plain(node: Any, memo: dict[Any, bool]) -> bool:
    """Whether ``node`` is in the class printed here, as SymPy would hold it."""
    if node in memo:
        return memo[node]
    if node.is_Integer or node.is_Symbol:
        out = True
    elif node.is_Function:
        out = sx.function_name(node) in _FUNCTION_CLASS and node.args[0].is_Symbol
    elif node.is_Pow:
        base, k = node.args
        out = bool(k.is_Integer and int(k) >= 2 and _plain(base, memo) and not base.is_Integer)
        if out and base.is_Add:  # SymPy keeps the sign of a sum's power as given: be sure
            out = all(_coefficient(term) > 0 for term in base.args)
    elif node.is_Mul:
        numbers = [arg for arg in node.args if arg.is_Number]
        out = len(numbers) <= 1 and all(n.is_Integer for n in numbers)
        out = out and all(_plain(arg, memo) for arg in node.args)
        if out and len(node.args) == 2 and numbers and any(arg.is_Add for arg in node.args):
            out = False  # SymPy distributes a number over a sum
    elif node.is_Add:
        out = all(_plain(arg, memo) for arg in node.args)
    else:
        out = False
    memo[node] = out
    return out


def _coefficient(term: Any) -> Fraction:
    """A term's number (1 where it has none)."""
    if term.is_Number:
        return Fraction(int(term))
    if term.is_Mul:
        for arg in term.args:
            if arg.is_Number:
                return Fraction(int(arg))
    return Fraction(1)


def _split(term: Any) -> tuple[Fraction, list[Any]]:
    """``as_coeff_Mul`` and ``Mul.make_args`` of the rest: the number and the factors."""
    if term.is_Number:
        return Fraction(int(term)), []
    factors = list(term.args) if term.is_Mul else [term]
    number = Fraction(1)
    rest = []
    for factor in factors:
        if factor.is_Number:
            number *= int(factor)
        else:
            rest.append(factor)
    return number, rest


def _sort_key(node: Any, memo: dict[Any, _SortKey]) -> _SortKey:
    """SymPy's ``Expr.sort_key`` (default order) of a node of the class."""
    if node in memo:
        return memo[node]
    if node.is_Integer:
        out: _SortKey = (_NUMBER_CLASS, (0, ()), (), Fraction(int(node)))
    elif node.is_Symbol:
        out = ((2, 0, "Symbol"), (1, (str(node),)), _ONE_KEY, Fraction(1))
    else:
        number, factors = _split(node) if node.is_Mul else (Fraction(1), [node])
        rest = factors[0] if len(factors) == 1 else None
        exponent = _ONE_KEY
        if rest is not None and rest.is_Pow:
            rest, k = rest.args
            exponent = _sort_key(k, memo)
        if rest is not None and rest.is_Symbol:
            args: tuple[Any, ...] = (str(rest),)
            kind = (2, 0, "Symbol")
        elif rest is None:  # a product of several factors
            args = tuple(sorted(_sort_key(f, memo) for f in factors))
            kind = (3, 0, "Mul")
        elif rest.is_Add:
            args = tuple(_sort_key(t, memo) for t in _ordered_terms(rest, memo))
            kind = (3, 1, "Add")
        else:  # sin or cos of a symbol
            args = tuple(_sort_key(a, memo) for a in rest.args)
            kind = _FUNCTION_CLASS[sx.function_name(rest)]
        out = (kind, (len(args), args), exponent, number)
    memo[node] = out
    return out


def _ordered_terms(node: Any, memo: dict[Any, _SortKey]) -> list[Any]:
    """SymPy's ``Add.as_ordered_terms()`` of a sum of the class."""
    terms = list(node.args)
    numbers = [t for t in terms if t.is_Number]
    others = [t for t in terms if not t.is_Number]
    if len(terms) == 2 and numbers and others[0].is_Mul:
        number, factors = _split(others[0])
        if len(others[0].args) == 2 and number < 0 < int(numbers[0]):
            return [numbers[0], others[0]]  # ``1 - x``: the number first
    powers: list[dict[Any, int]] = []
    for term in terms:
        _, factors = _split(term)
        powers.append(
            {(f.args[0] if f.is_Pow else f): (int(f.args[1]) if f.is_Pow else 1) for f in factors}
        )
    gens = sorted({g for p in powers for g in p}, key=lambda g: _sort_key(g, memo))
    order = sorted(
        range(len(terms)),
        key=lambda i: (tuple(-powers[i].get(g, 0) for g in gens), _split(terms[i])[0]),
    )
    return [terms[i] for i in order]


def _precedence(node: Any) -> int:
    if node.is_Add:
        return _ADD
    if node.is_Mul:
        return _ADD if _split(node)[0] < 0 else _MUL
    if node.is_Integer:
        return _ADD if int(node) < 0 else 1000
    if node.is_Pow:
        return _POW
    return 1000 if node.is_Symbol else 70


def _text(node: Any, memo: dict[Any, _SortKey]) -> str:
    """SymPy's ``sstr`` of a node of the class."""
    if node.is_Integer or node.is_Symbol:
        return str(int(node)) if node.is_Integer else str(node)
    if node.is_Function:
        return f"{sx.function_name(node)}({_text(node.args[0], memo)})"
    if node.is_Pow:
        base, k = node.args
        inner = _text(base, memo)
        return f"({inner})**{int(k)}" if _precedence(base) <= _POW else f"{inner}**{int(k)}"
    if node.is_Mul:
        number, factors = _split(node)
        sign = "-" if number < 0 else ""
        items = ([sx.Integer(abs(int(number)))] if abs(number) != 1 else []) + sorted(
            factors, key=lambda f: _sort_key(f, memo)
        )
        level = _precedence(node)
        parts = [
            f"({_text(f, memo)})" if _precedence(f) <= level else _text(f, memo) for f in items
        ]
        return sign + "*".join(parts)
    out = []
    for term in _ordered_terms(node, memo):
        text = _text(term, memo)
        sign = "+"
        if text.startswith("-"):
            sign, text = "-", text[1:]
        out.extend([sign, text])
    first = out.pop(0)
    return ("" if first == "+" else first) + " ".join(out)


def sympy_text(expr: sx.Expr) -> str | None:
    """``expr`` as SymPy's ``sstr`` writes it, or None outside the class written here."""
    if not _plain(expr, {}):
        return None
    return _text(expr, {})


def indefinite(expr: sx.Expr, points: int = 64) -> bool:
    """Whether ``expr`` is seen to take both signs at real points (then no sign is known).

    A rational function in symbols and sines and cosines of symbols, evaluated at fixed
    pseudo-random points; a value counts only well away from its rounding error. Where
    ``expr`` is positive at one real point and negative at another, no sound test calls
    it positive, negative or non-negative: SymPy's assumptions would answer None.
    """
    import math  # noqa: PLC0415 - only here
    import random  # noqa: PLC0415 - only here

    atoms = Atoms()
    found = rational(expr, atoms, {})
    if found is None:
        return False
    draw = random.Random(49)
    signs: set[int] = set()
    for _ in range(points):
        values: dict[str, float] = {}
        for name in atoms.names:
            values.setdefault(name, draw.uniform(-2.0, 2.0))
        atom_values = [
            values[name] if not kind else getattr(math, kind)(values[name])
            for kind, name in zip(atoms.kinds, atoms.names, strict=True)
        ]
        parts = []
        for poly in found:
            total = scale = 0.0
            for monomial, c in poly.items():
                term = float(c)
                for atom, k in monomial:
                    term *= atom_values[atom] ** k
                total += term
                scale += abs(term)
            parts.append((total, scale))
        (top, top_scale), (bottom, bottom_scale) = parts
        if abs(top) <= 1e-9 * top_scale or abs(bottom) <= 1e-9 * bottom_scale:
            continue
        signs.add(1 if (top > 0) == (bottom > 0) else -1)
        if len(signs) == 2:
            return True
    return False
