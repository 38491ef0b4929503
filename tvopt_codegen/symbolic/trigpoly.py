"""Sparse polynomials with rational coefficients in symbols and sines and cosines of angles.

The exact algebra under :mod:`.trigforms`, which writes determinants and conditions as
SymPy does without SymPy. An expression in symbols and ``sin(a)``, ``cos(a)`` of a
symbol ``a`` (angle sums expanded, or each function read as an atom of its own as
SymPy's ``cancel`` reads it) is read here as a quotient of polynomials
(:func:`rational`): a monomial is ``((atom, exponent), ...)`` by atom number, a
polynomial ``{monomial: Fraction}``. On them: arithmetic (:func:`times`,
:func:`product`, :func:`add`, :func:`scaled`), the reduction by ``s^2 + c^2 = 1``
(:func:`reduced`, a normal form), the numeric and monomial content (:func:`content`),
exact division (:func:`exact_quotient`), a proof of irreducibility for one shape
(:func:`irreducible`) and the way back to an expression (:func:`poly_expr`).

Every bound here (:data:`MAX_TERMS`, the largest power and multiple of an angle) answers
None past it: the caller then lets SymPy decide.
"""

from __future__ import annotations

from collections.abc import Callable
from fractions import Fraction
from math import gcd, lcm
from typing import Any

from tvopt_codegen import symbolic as sx

#: A monomial: ``((atom, exponent), ...)`` by atom number, exponents nonzero (negative
#: only in a quotient's or a Laurent polynomial's).
Monomial = tuple[tuple[int, int], ...]
#: A polynomial: its monomials' rational coefficients, none zero.
Poly = dict[Monomial, Fraction]

#: Most terms a polynomial may reach on the way (beyond, SymPy decides).
MAX_TERMS = 400
#: Largest multiple of an angle whose sine or cosine is expanded.
_MAX_MULTIPLE = 4
#: Largest integer power multiplied out.
_MAX_POWER = 64


class Atoms:
    """The atoms of one determinant: symbols, and ``sin(a)`` and ``cos(a)`` of a symbol ``a``.

    ``kinds[i]`` is ``""`` for a symbol, ``"sin"`` or ``"cos"``; ``names[i]`` the
    symbol's or the angle's name.
    """

    def __init__(self, expand_angles: bool = True) -> None:
        #: Whether ``sin(q1 + q2)`` is expanded in ``sin(q1)``, ``cos(q1)``, ... (else it is
        #: an atom of its own, as SymPy's ``cancel`` and ``factor`` read it).
        self.expand_angles = expand_angles
        self.exprs: list[Any] = []
        self.kinds: list[str] = []
        self.names: list[str] = []
        self._index: dict[tuple[str, str], int] = {}

    def index(self, kind: str, symbol: Any) -> int:
        """The number of ``symbol`` (kind ``""``) or of its sine or cosine."""
        key = (kind, str(symbol))
        found = self._index.get(key)
        if found is None:
            found = self._index[key] = len(self.exprs)
            self.exprs.append(symbol if not kind else getattr(sx, kind)(symbol))
            self.kinds.append(kind)
            self.names.append(str(symbol))
        return found

    def variable(self, kind: str, symbol: Any) -> Poly:
        """The polynomial of one atom (``kind`` as in :meth:`index`)."""
        return {((self.index(kind, symbol), 1),): Fraction(1)}

    def partner(self, atom: int) -> int:
        """The cosine of a sine's angle, or the sine of a cosine's."""
        other = "cos" if self.kinds[atom] == "sin" else "sin"
        return self.index(other, self.exprs[atom].args[0])

    def text(self, atom: int) -> str:
        """The atom as SymPy's ``str`` writes a generator (its sort key reads it)."""
        kind, name = self.kinds[atom], self.names[atom]
        return f"{kind}({name})" if kind else name


def times(a: Monomial, b: Monomial) -> Monomial:
    """The product of two monomials (negative exponents allowed: a quotient)."""
    powers = dict(a)
    for atom, k in b:
        powers[atom] = powers.get(atom, 0) + k
    return tuple(sorted((atom, k) for atom, k in powers.items() if k))


def product(p: Poly, q: Poly) -> Poly:
    """The product of two polynomials."""
    out: Poly = {}
    for a, x in p.items():
        for b, y in q.items():
            key = times(a, b)
            out[key] = out.get(key, Fraction(0)) + x * y
    return {key: c for key, c in out.items() if c}


def add(p: Poly, q: Poly, sign: int = 1) -> Poly:
    """``p + q`` (``sign`` 1) or ``p - q`` (``sign`` -1)."""
    out = dict(p)
    for key, c in q.items():
        out[key] = out.get(key, Fraction(0)) + sign * c
    return {key: c for key, c in out.items() if c}


def scaled(p: Poly, c: Fraction, monomial: Monomial = ()) -> Poly:
    """``c`` times ``p`` times ``monomial``."""
    return {times(key, monomial): c * value for key, value in p.items()}


ONE: Poly = {(): Fraction(1)}
#: A rational function: numerator and denominator (never the zero polynomial).
Rational = tuple[Poly, Poly]


def rational(node: Any, atoms: Atoms, memo: dict[Any, Rational | None]) -> Rational | None:
    """``node`` as a quotient of polynomials in its atoms, or None where it is not one."""
    if node in memo:
        return memo[node]
    out: Rational | None = None
    if node.is_Rational:
        numerator, denominator = node.as_numer_denom()
        value = Fraction(int(numerator), int(denominator))
        out = ({(): value} if value else {}, ONE)
    elif node.is_Symbol:
        out = (atoms.variable("", node), ONE)
    elif node.is_Add or node.is_Mul:
        out = ({}, ONE) if node.is_Add else (ONE, ONE)
        for arg in node.args:
            part = rational(arg, atoms, memo)
            if part is None:
                return _remember(memo, node, None)
            out = (
                _sum(out, part)
                if node.is_Add
                else (product(out[0], part[0]), product(out[1], part[1]))
            )
            if max(len(out[0]), len(out[1])) > MAX_TERMS:
                return _remember(memo, node, None)
    elif node.is_Pow and node.args[1].is_Integer:
        base = rational(node.args[0], atoms, memo)
        k = int(node.args[1])
        if base is None or (k < 0 and not base[0]) or abs(k) > _MAX_POWER:
            return _remember(memo, node, None)
        numerator, denominator = base if k >= 0 else (base[1], base[0])
        out = (ONE, ONE)
        for _ in range(abs(k)):
            out = (product(out[0], numerator), product(out[1], denominator))
            if max(len(out[0]), len(out[1])) > MAX_TERMS:
                return _remember(memo, node, None)
    elif node.is_Function and sx.function_name(node) in ("sin", "cos"):
        found = _circular(sx.function_name(node), node.args[0], atoms)
        out = None if found is None else (found, ONE)
    return _remember(memo, node, out)


def _remember(memo: dict[Any, Rational | None], node: Any, out: Rational | None) -> Rational | None:
    memo[node] = out
    return out


def _sum(p: Rational, q: Rational) -> Rational:
    if p[1] == q[1]:  # one denominator: no growth
        return add(p[0], q[0]), p[1]
    return add(product(p[0], q[1]), product(q[0], p[1])), product(p[1], q[1])


def _circular(name: str, arg: Any, atoms: Atoms) -> Poly | None:
    """``sin`` or ``cos`` of a sum of integer multiples of symbols, in their sines and cosines."""
    if not atoms.expand_angles:
        return atoms.variable(name, arg)
    return angle_sum(name, arg, atoms.variable)


def angle_sum(name: str, arg: Any, variable: Callable[[str, Any], Poly]) -> Poly | None:
    """``sin`` or ``cos`` of a sum of integer multiples of symbols, in their sines and cosines.

    ``variable(kind, symbol)`` is the polynomial of ``sin(symbol)`` or ``cos(symbol)`` in
    the caller's atoms. None where a term is not an integer multiple (at most
    ``_MAX_MULTIPLE``) of a symbol.
    """
    sine: Poly = {}
    cosine: Poly = ONE
    for term in arg.args if arg.is_Add else (arg,):
        if term.is_Symbol:
            k, symbol = 1, term
        elif (
            term.is_Mul
            and len(term.args) == 2
            and term.args[0].is_Integer
            and term.args[1].is_Symbol
        ):
            k, symbol = int(term.args[0]), term.args[1]
        else:
            return None
        if abs(k) > _MAX_MULTIPLE:
            return None
        one_sin, one_cos = variable("sin", symbol), variable("cos", symbol)
        for _ in range(abs(k)):  # the angle sum's rule, once per multiple
            sine, cosine = (
                add(product(sine, one_cos), product(cosine, one_sin), 1 if k > 0 else -1),
                add(product(cosine, one_cos), product(sine, one_sin), -1 if k > 0 else 1),
            )
    return sine if name == "sin" else cosine


def reduced(p: Poly, atoms: Atoms, kinds: dict[str, str]) -> Poly:
    """``p`` modulo ``sin^2 + cos^2 = 1``: each angle's ``kinds[angle]`` squared rewritten.

    With ``kinds[a] == "cos"`` every ``cos(a)^2`` becomes ``1 - sin(a)^2``, so ``cos(a)``
    is left to the power 0 or 1 (and the other way round): a normal form, so that a
    polynomial is zero on the circle exactly when its reduced form is empty.
    """
    out: Poly = {}
    work = list(p.items())
    while work:
        monomial, c = work.pop()
        atom = next(
            (
                a
                for a, k in monomial
                if atoms.kinds[a] and k >= 2 and kinds.get(atoms.names[a]) == atoms.kinds[a]
            ),
            None,
        )
        if atom is None:
            out[monomial] = out.get(monomial, Fraction(0)) + c
            continue
        powers = dict(monomial)
        powers[atom] -= 2
        lower = tuple(sorted((a, k) for a, k in powers.items() if k))
        work.append((lower, c))
        work.append((times(lower, ((atoms.partner(atom), 2),)), -c))
    return {key: c for key, c in out.items() if c}


def content(p: Poly) -> tuple[Fraction, Monomial, Poly]:
    """``p`` as a positive rational times a monomial times a primitive integer polynomial."""
    common: dict[int, int] | None = None
    for monomial in p:
        powers = dict(monomial)
        common = (
            powers if common is None else {a: min(k, powers.get(a, 0)) for a, k in common.items()}
        )
    content = tuple(sorted((a, k) for a, k in (common or {}).items() if k))
    numerators = gcd(*(c.numerator for c in p.values()))
    denominators = lcm(*(c.denominator for c in p.values()))
    number = Fraction(numerators, denominators)
    inverse = tuple((a, -k) for a, k in content)
    return number, content, {times(key, inverse): c / number for key, c in p.items()}


def _dense(monomial: Monomial, n: int) -> tuple[int, ...]:
    powers = dict(monomial)
    return tuple(powers.get(a, 0) for a in range(n))


def exact_quotient(p: Poly, q: Poly) -> Poly | None:
    """``p / q`` where ``q`` divides ``p`` in the polynomial ring, else None.

    Division by the lex-leading term: exact division always succeeds so, and a leading
    term that does not divide (or a remainder) proves ``q`` does not divide ``p``.
    """
    n = 1 + max((a for m in (*p, *q) for a, _ in m), default=0)

    def lead(r: Poly) -> Monomial:
        return max(r, key=lambda m: _dense(m, n))

    top = lead(q)
    quotient: Poly = {}
    rest = dict(p)
    for _ in range(4 * MAX_TERMS):
        if not rest:
            return quotient
        head = lead(rest)
        powers = dict(head)
        for a, k in top:
            powers[a] = powers.get(a, 0) - k
        if any(k < 0 for k in powers.values()):
            return None
        step = tuple(sorted((a, k) for a, k in powers.items() if k))
        c = rest[head] / q[top]
        quotient[step] = c
        rest = add(rest, scaled(q, c, step), -1)
    return None


def poly_expr(p: Poly, atoms: Atoms) -> sx.Expr:
    """A polynomial as an expression of the engine."""
    out = sx.Integer(0)
    for monomial, c in p.items():
        term = sx.Rational(c.numerator, c.denominator)
        for atom, k in monomial:
            term *= atoms.exprs[atom] ** k
        out += term
    return out


def irreducible(p: Poly) -> bool:
    """Whether ``p`` (primitive, no monomial content) is provably irreducible.

    When ``p = A x + B`` for an atom ``x`` of degree 1, with ``A`` one term and no atom of
    ``A`` dividing every term of ``B``: a factor free of ``x`` would divide ``A`` (so be
    a monomial) and ``B`` (so hold no atom of ``A``), so be a number, and ``p`` is
    primitive.
    """
    atoms = {a for m in p for a, _ in m}
    for x in sorted(atoms):
        degrees = [dict(m).get(x, 0) for m in p]
        if max(degrees) != 1:
            continue
        with_x = [m for m, d in zip(p, degrees, strict=True) if d == 1]
        without = [m for m, d in zip(p, degrees, strict=True) if d == 0]
        if len(with_x) != 1 or not without:
            continue
        coefficient_atoms = {a for a, _ in with_x[0] if a != x}
        if all(any(a not in dict(m) for m in without) for a in coefficient_atoms):
            return True
    return False


def inverse(monomial: Monomial) -> Monomial:
    """``1 / monomial``: its exponents negated."""
    return tuple((atom, -k) for atom, k in monomial)
