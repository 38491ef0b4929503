"""Where R or p is singular or undefined: det R in lowest terms, and where it vanishes.

What the derivation says about the places its law fails (Section IV-B of the paper):
:func:`simplified_det` (det R, and the equalities' Gram determinant, factored),
:func:`_singular_set` (where such a determinant vanishes, one condition per factor),
:func:`undefined_causes` (where R or p do not exist: denominators, ``tan``, ``log``,
roots), and :func:`_sign`, which leaves out the conditions that hold at no real point.

Its own module because it is a concept of its own, called by two stages
(:mod:`.linearization` for det R, R and p; :mod:`.equalities` for the Gram
determinant) and by ``check``'s summary: it reads expressions only, never the plant or
the spec, and it is where those stages cross the border into SymPy (factoring,
``trigsimp``, the assumptions), on small expressions, writing every condition as SymPy
does so that the generated files quote the same text on either engine.
"""

from __future__ import annotations

from collections.abc import Sequence
from fractions import Fraction
from typing import Any

from tvopt_codegen import symbolic as sx
from tvopt_codegen.derivation.meter import TimeLimitError, time_limited, tree_size
from tvopt_codegen.symbolic.border import from_sympy, sympy, to_sympy
from tvopt_codegen.symbolic.order import sympy_ordered
from tvopt_codegen.symbolic.trigforms import indefinite, lowest, sympy_text
from tvopt_codegen.symbolic.trigpoly import Poly, add, angle_sum, product, times


def _circular() -> tuple[Any, ...]:
    """SymPy's classes of circular and hyperbolic functions."""
    sp = sympy()
    return (
        sp.functions.elementary.trigonometric.TrigonometricFunction,
        sp.functions.elementary.hyperbolic.HyperbolicFunction,
    )


#: How long det R's simplification may take before its short form stands.
_DET_SIMPLIFY_SECONDS = 5.0


def simplified_det(det: sx.Expr) -> sx.Expr:
    """A determinant in lowest terms, factored: ``factor(simplify(det))`` or as short.

    ``cancel``, then ``trigsimp`` where there are circular or hyperbolic functions: when
    that leaves a rational function (a unicycle's ``v cos^2 + v sin^2``, a quadrotor's
    thrust), its factored form is what ``simplify`` would reach, in a third of a small
    derivation's time (``simplify`` tries each of its strategies in turn, and imports
    ``sympy.physics.units`` on the way). When trigonometry remains, ``simplify`` decides:
    on random trigonometric determinants the short path's form was longer one time in
    six (benchmarks/NOTES.md). ``simplify`` has no bound of its own (487 s on a 2 x 2 R
    whose gains hold ``cos`` and ``tanh`` of sums, found by the fuzzer): past
    ``_DET_SIMPLIFY_SECONDS`` the short path's form stands. Both are det R exactly; only
    how short it prints can then depend on the machine's speed.

    A border stage: ``det`` (an expression of the engine, small: the caller bounds its
    size) is simplified in SymPy and its factored form converted back. On SymEngine, a
    determinant that is a number times powers of symbols, sines and cosines is found
    without SymPy (:func:`_monomial`), as SymPy finds it, and so is one that is such a
    monomial over one irreducible polynomial in symbols and a sine or cosine squared
    (a two-link arm's: :func:`.trigforms.lowest`, which accepts only the shape whose
    SymPy form it writes).
    """
    if sx.SYMENGINE:
        found = _monomial(det)
        if found is not None:
            return _monomial_expr(*found)
        shaped = lowest(det)
        if shaped is not None:
            return shaped.expr()
    sp, circular = sympy(), _circular()
    det = to_sympy(det)
    reduced = sp.cancel(det)
    if reduced.has(*circular):
        try:
            with time_limited(_DET_SIMPLIFY_SECONDS):
                reduced = sp.trigsimp(reduced)
                if reduced.has(*circular) and not _one_circular_factor(reduced):
                    return from_sympy(sp.factor(sp.simplify(det)))
        except TimeLimitError:
            pass
    return from_sympy(sp.factor(reduced))


def _one_circular_factor(expr: sx.Expr) -> bool:
    """Whether ``expr`` is one circular or hyperbolic function of a symbol times powers.

    That is a number, powers of symbols and one ``sin(q)`` (an arm's ``l1*l2*sin(q2)``).
    No identity shortens such a product, so ``simplify`` returns it as it is (tested), and
    the short path's form is the one it would give. ``expr`` is SymPy's.
    """
    sp, circular = sympy(), _circular()
    functions = 0
    for factor in sp.Mul.make_args(expr):
        base = factor.base if factor.is_Pow and factor.exp.is_Integer else factor
        if factor.is_Number or base.is_Symbol:
            continue
        if isinstance(factor, circular) and factor.args[0].is_Symbol:
            functions += 1
            continue
        return False
    return functions == 1


def _singular_set(det: sx.Expr) -> tuple[str, ...]:
    """Describe where a determinant vanishes, one condition per factor of its numerator.

    A factor that vanishes nowhere over the reals (``vx**2 + vy**2 + 1``) is no place at
    all, and is left out: with every factor so, R is never singular. A border stage:
    ``det`` (small, simplified) is factored in SymPy, and the conditions are written as
    SymPy writes them, the same text on either engine (on SymEngine, where the
    numerator is a monomial, without SymPy: :func:`_numerator`, :func:`_monomial_conditions`).
    """
    if sx.SYMENGINE:
        found = _monomial(_numerator(det), expand_angles=False)
        native = None if found is None else _monomial_conditions(*found)
        if native is not None:
            return native
    sp = sympy()
    numerator, _ = sp.fraction(sp.together(to_sympy(det)))
    if numerator.is_Number:
        return () if numerator != 0 else ("everywhere",)
    try:
        _, factors = sp.factor_list(numerator)
    except sp.PolynomialError:  # not a polynomial in its symbols: state it whole
        factors = [(numerator, 1)]
    conditions = []
    for base, _power in factors:
        if base.is_Number or _sign(base) in ("positive", "negative"):
            continue
        conditions.append(f"{sp.sstr(base)} = 0")
    return tuple(conditions)


def _numerator(det: sx.Expr) -> sx.Expr:
    """``det``'s numerator as SymPy's ``fraction(together(det))`` has it, where that is plain.

    Where ``det`` is a product of factors and powers of polynomials (no fraction inside a
    power's base), ``together`` leaves it as it is and the numerator is the product of
    the factors that are not a negative power (``sin(q2)`` of an arm's
    ``sin(q2)/(l1 l2 m2 (m1 + m2 sin(q2)^2))``), when none of those is a sum; elsewhere
    ``det`` itself, which :func:`_monomial` reads as before.
    """
    factors = det.args if det.is_Mul else (det,)
    numerator = sx.ONE
    for factor in factors:
        if factor.is_Pow and factor.args[1].is_Integer and factor.args[1].is_negative:
            if not _polynomial(factor.args[0]):
                return det
        elif factor.is_Add or (factor.is_Pow and factor.args[0].is_Add):
            return det  # a sum above: factor_list's, not rewritten by sin^2 + cos^2 = 1
        else:
            numerator *= factor
    return numerator


def _polynomial(expr: sx.Expr) -> bool:
    """Whether ``expr`` has no negative or fractional power anywhere (``together`` keeps it)."""
    stack = [expr]
    while stack:
        node = stack.pop()
        if node.is_Pow and not (node.args[1].is_Integer and not node.args[1].is_negative):
            return False
        stack.extend(node.args)
    return True


#: Largest expression (in nodes) whose sign is asked of sympy's assumptions: the answer
#: only shortens a message, and it must stay cheap.
_SIGN_NODES = 400
#: Most symbols of a quadratic whose definiteness is decided exactly.
_QUADRATIC_SYMBOLS = 12


def _sign(expr: sx.Expr) -> str | None:
    """Whether ``expr`` is ``"positive"``, ``"nonnegative"`` or ``"negative"`` everywhere.

    None where that is not known cheaply.

    sympy's assumptions first (every spec symbol is real: a sum of squares plus a positive
    constant, an exponential, ``cosh``); then, for a quadratic polynomial with number
    coefficients, the exact test: ``z^T Q z + g^T z + c`` with ``Q`` positive definite
    has its least value ``c - g^T Q^-1 g / 4`` (``x**2 - x*y + y**2 + 1`` is positive).
    ``expr`` is SymPy's (:func:`_engine_sign` takes the engine's).
    """
    sp = sympy()
    if tree_size(expr, _SIGN_NODES) > _SIGN_NODES:
        return None
    for candidate in (expr, -expr):
        if candidate.is_positive:
            return "positive" if candidate is expr else "negative"
    if expr.is_nonnegative:
        return "nonnegative"
    symbols = sorted(expr.free_symbols, key=lambda s: s.name)
    if not symbols or len(symbols) > _QUADRATIC_SYMBOLS:
        return None
    try:
        poly = sp.Poly(expr, *symbols)
    except sp.PolynomialError:
        return None
    if poly.total_degree() != 2 or not all(c.is_Rational for c in poly.coeffs()):
        return None
    for candidate in (poly, -poly):
        least = _least_value(candidate, symbols)
        if least is not None:
            if least > 0:
                return "positive" if candidate is poly else "negative"
            if least == 0 and candidate is poly:
                return "nonnegative"
    return None


def _engine_sign(expr: sx.Expr, memo: dict[Any, Any]) -> str | None:
    """:func:`_sign` of an expression of the engine (``memo``: the border's, shared).

    On SymEngine, a value seen to take both signs (:func:`.trigforms.indefinite`: an
    arm's dynamics' denominator, whose parameters may be of any sign) has none, as
    SymPy's sound tests would find, without SymPy.
    """
    if tree_size(expr, _SIGN_NODES) > _SIGN_NODES:
        return None
    if sx.SYMENGINE and indefinite(expr):
        return None
    return _sign(to_sympy(expr, memo))


def _least_value(poly: Any, symbols: Sequence[Any]) -> Any:
    """The least value of a quadratic polynomial with a positive definite Hessian, or None.

    SymPy's ``Poly`` and ``Rational``.
    """
    sp = sympy()
    n = len(symbols)
    quadratic = sp.zeros(n, n)
    linear = sp.zeros(n, 1)
    constant = sp.Integer(0)
    for monomial, coefficient in poly.terms():
        powers = [(i, k) for i, k in enumerate(monomial) if k]
        if not powers:
            constant = coefficient
        elif len(powers) == 1 and powers[0][1] == 1:
            linear[powers[0][0]] = coefficient
        elif len(powers) == 1:
            quadratic[powers[0][0], powers[0][0]] = coefficient
        else:
            (i, _), (j, _) = powers
            quadratic[i, j] = quadratic[j, i] = coefficient / 2
    if not quadratic.is_positive_definite:
        return None
    return constant - (linear.T * quadratic.inv() * linear)[0, 0] / 4


#: At most this many conditions are listed where R or p is undefined.
_MAX_UNDEFINED = 6


def _undefined_set(exprs: Sequence[sx.Expr], states: set[sx.Expr]) -> tuple[str, ...]:
    """Where expressions of the states are undefined, one condition per cause.

    The conditions of :func:`undefined_causes`, without their causes.
    """
    return tuple(condition for condition, _ in undefined_causes(exprs, states))


def undefined_causes(exprs: Sequence[sx.Expr], states: set[sx.Expr]) -> tuple[tuple[str, str], ...]:
    """Where expressions of the states are undefined: each condition and its cause.

    A denominator that vanishes, ``tan``/``sec`` where the cosine vanishes,
    ``cot``/``csc`` where the sine does, ``log`` of a non-positive and a root of a
    negative number: the places where R or p, and with them the law, do not exist
    although det R may not vanish there (a steering angle of pi/2, an Euler pitch of
    pi/2). Conditions on parameters alone are not listed, nor any that holds at no real
    point (``sqrt(vx**2 + vy**2 + 1)`` is defined everywhere): see :func:`_sign`.
    ``x**(-1/2)`` has two, ``x = 0`` (a denominator) and ``x < 0`` (a root).

    The walk is the engine's; only the values whose sign is asked (small ones) and
    those a condition writes cross the border, each shared subexpression once.
    """
    conditions: dict[str, str] = {}
    seen: set[Any] = set()
    memo: dict[Any, Any] = {}
    keys: dict[Any, tuple[Any, ...]] = {}
    stack = [e for e in exprs if isinstance(e, sx.Basic)]
    while stack and len(conditions) < _MAX_UNDEFINED:
        node = stack.pop()
        if node in seen or not node.free_symbols & states:
            continue
        seen.add(node)
        found: list[tuple[str, str, sx.Expr, tuple[str, ...]]] = []
        name = sx.function_name(node) if node.is_Function else ""
        if node.is_Pow and node.exp.is_Number and node.base.free_symbols & states:
            # Written only for a condition: a square's base needs no text (nor SymPy).
            if node.exp.is_negative or not node.exp.is_Integer:
                base = _condition_text(node.base, memo)
            if node.exp.is_negative:
                found.append((f"{base} = 0", "a denominator vanishes", node.base, _NONZERO))
            if not node.exp.is_Integer:
                root = "a square root" if getattr(node.exp, "q", 0) == 2 else "a fractional power"
                found.append((f"{base} < 0", f"{root} of a negative", node.base, _NONNEGATIVE))
        elif name in ("tan", "sec"):
            arg = node.args[0]
            cause = f"the cosine under {name} vanishes"
            found.append((f"cos({_condition_text(arg, memo)}) = 0", cause, sx.cos(arg), _NONZERO))
        elif name in ("cot", "csc"):
            arg = node.args[0]
            cause = f"the sine under {name} vanishes"
            found.append((f"sin({_condition_text(arg, memo)}) = 0", cause, sx.sin(arg), _NONZERO))
        elif name == "log":
            arg = node.args[0]
            text = _condition_text(arg, memo)
            found.append((f"{text} <= 0", "a log of a non-positive", arg, _POSITIVE))
        for condition, cause, value, never in found:
            if _engine_sign(value, memo) not in never:
                conditions.setdefault(condition, cause)
        # In SymPy's order of arguments on both engines: which conditions are found
        # first, and kept within _MAX_UNDEFINED, reaches the generated files.
        stack.extend(reversed(sympy_ordered(node.args, keys)))
    return tuple(conditions.items())


def _condition_text(expr: sx.Expr, memo: dict[Any, Any]) -> str:
    """``expr`` as SymPy writes it, on either engine: the generated code quotes it.

    SymEngine orders a sum's terms its own way; the condition's text, in the generated
    module's and the C file's messages, is the same as on SymPy (golden files).
    """
    if not sx.SYMENGINE:
        return sx.text(expr)
    native = sympy_text(expr)  # a polynomial in symbols, sines and cosines: no SymPy
    return native if native is not None else str(sympy().sstr(to_sympy(expr, memo)))


#: The signs of a value under which each kind of condition holds nowhere.
_NONZERO = ("positive", "negative")
_NONNEGATIVE = ("positive", "nonnegative")
_POSITIVE = ("positive",)


# det R without SymPy (SymEngine): a determinant is a Laurent polynomial in its atoms
# (symbols, and the sine and cosine of each angle a sum of angles expands to), reduced
# by sin^2 + cos^2 = 1; when that leaves one term, the term is det R in lowest terms and
# its atoms in the numerator are the singular set. Monomials and polynomials, and their
# arithmetic, are :mod:`.trigpoly`'s (its own atoms differ: a function of any angle here).
#: An atom's kind: ``("", name)``, ``("sin", name)``, or ``("cos", None)`` past a symbol.
_Kind = tuple[str, str | None]
#: An atom, its exponent and its kind.
_Power = tuple[Any, int, _Kind]


class _Atoms:
    """The atoms of one determinant: symbols, and ``sin(u)`` and ``cos(u)`` of an angle ``u``.

    ``kinds[i]`` is ``("", name)`` for a symbol, ``("sin", name)`` or ``("cos", name)``
    for a function of a symbol, and ``("sin", None)`` for one of any other angle (a
    time-varying line's ``t/10``), which can be simplified but not written as SymPy does.
    """

    def __init__(self) -> None:
        self.exprs: list[Any] = []
        self.kinds: list[_Kind] = []
        self._index: dict[tuple[str, Any], int] = {}

    def index(self, kind: str, arg: Any) -> int:
        key = (kind, arg)
        found = self._index.get(key)
        if found is None:
            found = self._index[key] = len(self.exprs)
            self.exprs.append(arg if not kind else getattr(sx, kind)(arg))
            self.kinds.append((kind, str(arg) if arg.is_Symbol else None))
        return found

    def variable(self, kind: str, arg: Any) -> Poly:
        return {((self.index(kind, arg), 1),): Fraction(1)}


#: Most terms a polynomial may reach on the way (beyond, SymPy decides).
_MONOMIAL_TERMS = 400


def _laurent(node: Any, atoms: _Atoms, angles: bool, memo: dict[Any, Poly | None]) -> Poly | None:
    """``node`` as a Laurent polynomial in its atoms, or None where it is not one."""
    if node in memo:
        return memo[node]
    out: Poly | None = None
    if node.is_Rational:
        numerator, denominator = node.as_numer_denom()
        value = Fraction(int(numerator), int(denominator))
        out = {(): value} if value else {}
    elif node.is_Symbol:
        out = atoms.variable("", node)
    elif node.is_Add or node.is_Mul:
        out = {} if node.is_Add else {(): Fraction(1)}
        for arg in node.args:
            part = _laurent(arg, atoms, angles, memo)
            if part is None or len(out) > _MONOMIAL_TERMS:
                out = None
                break
            out = add(out, part) if node.is_Add else product(out, part)
    elif node.is_Pow and node.args[1].is_Integer:
        base = _laurent(node.args[0], atoms, angles, memo)
        k = int(node.args[1])
        if base is not None and len(base) == 1:  # a term's power: its exponents times k
            ((monomial, c),) = base.items()
            out = {tuple((a, e * k) for a, e in monomial if k): c**k}
        elif base is not None and k >= 0:
            out = {(): Fraction(1)}
            for _ in range(k):
                out = product(out, base)
                if len(out) > _MONOMIAL_TERMS:
                    out = None
                    break
    elif node.is_Function and sx.function_name(node) in ("sin", "cos"):
        out = _circular_of(sx.function_name(node), node.args[0], atoms, angles)
    memo[node] = out
    return out


def _circular_of(name: str, arg: Any, atoms: _Atoms, angles: bool) -> Poly | None:
    """``sin`` or ``cos`` of an angle; (``angles``) of a sum of multiples of symbols, expanded."""
    if arg.is_Symbol or not angles:
        return atoms.variable(name, arg)
    expanded = angle_sum(name, arg, atoms.variable)
    return atoms.variable(name, arg) if expanded is None else expanded


def _pythagoras(p: Poly, atoms: _Atoms, kind: str) -> Poly:
    """``p`` with every ``kind``'s square (``sin`` or ``cos``) written as 1 minus the other's."""
    other = "cos" if kind == "sin" else "sin"
    out: Poly = {}
    work = list(p.items())
    while work:
        monomial, c = work.pop()
        powers = dict(monomial)
        atom = next((a for a, k in monomial if atoms.kinds[a][0] == kind and k >= 2), None)
        if atom is None:
            out[monomial] = out.get(monomial, Fraction(0)) + c
            continue
        powers[atom] -= 2
        lower = tuple(sorted((a, k) for a, k in powers.items() if k))
        work.append((lower, c))
        work.append((times(lower, ((atoms.index(other, atoms.exprs[atom].args[0]), 2),)), -c))
    return {key: c for key, c in out.items() if c}


def _monomial(det: sx.Expr, expand_angles: bool = True) -> tuple[Fraction, list[_Power]] | None:
    """A determinant as a number times powers of atoms, each angle under one sine or cosine.

    Tries det as it is, then with every ``sin^2`` written ``1 - cos^2``, then every
    ``cos^2`` written ``1 - sin^2`` (a unicycle's ``v sin^2 + v cos^2`` is ``v``; an
    arm's ``sin(q1 + q2) cos(q1) - sin(q1) cos(q1 + q2)``, its angles expanded, is
    ``sin(q2)``). One angle under both a sine and a cosine is left to SymPy, which might
    write ``sin(q) cos(q)`` as ``sin(2 q)/2`` or ``sin/cos`` as ``tan``.
    """
    atoms = _Atoms()
    poly = _laurent(det, atoms, expand_angles, {})
    if poly is None:
        return None
    for candidate in (poly, _pythagoras(poly, atoms, "sin"), _pythagoras(poly, atoms, "cos")):
        if len(candidate) > 1:
            continue
        if not candidate:
            return Fraction(0), []
        ((monomial, c),) = candidate.items()
        angles = [atoms.exprs[a].args[0] for a, _ in monomial if atoms.kinds[a][0]]
        if len(angles) != len(set(angles)):
            continue
        return c, [(atoms.exprs[a], k, atoms.kinds[a]) for a, k in monomial]
    return None


def _monomial_expr(c: Fraction, powers: list[_Power]) -> sx.Expr:
    """``c`` times the powers, an expression of the engine."""
    out = sx.Rational(c.numerator, c.denominator)
    for atom, k, _ in powers:
        out *= atom**k
    return out


def _monomial_conditions(c: Fraction, powers: list[_Power]) -> tuple[str, ...] | None:
    """The singular set of ``c`` times the powers, as :func:`_singular_set` writes it.

    SymPy's ``factor_list`` gives a monomial's atoms in the order of its ``Mul``, stably
    sorted by exponent: there a symbol comes before a power, a power before a function
    (``cos`` before ``sin``), and like with like by name (a power by its base). None
    where the numerator holds a function of an angle other than a symbol (SymPy writes
    that angle).
    """
    if not c:
        return ("everywhere",)
    numerator = [item for item in powers if item[1] > 0]
    if any(kind[1] is None for _, _, kind in numerator):
        return None

    def atom_key(kind: _Kind) -> tuple[int, str, str]:
        return (2, kind[0], str(kind[1])) if kind[0] else (0, "", str(kind[1]))

    def key(item: _Power) -> tuple[int, tuple[Any, ...]]:
        _, k, kind = item
        return (k, atom_key(kind) if k == 1 else (1, atom_key(kind), k))

    numerator.sort(key=key)
    return tuple(
        f"{kind[0]}({kind[1]}) = 0" if kind[0] else f"{kind[1]} = 0" for _, _, kind in numerator
    )
