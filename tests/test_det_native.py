"""det R over one polynomial factor without SymPy (issue 49): SymPy's tree and text, or SymPy.

:func:`trigforms.lowest` writes a determinant that is a number times powers of symbols,
sines and cosines over one irreducible polynomial in symbols and a sine or cosine
squared (a two-link arm's ``sin(q2)/(l1 l2 m2 (m1 + m2 sin(q2)^2))``) as SymPy's
``factor(simplify(det))`` does, and refuses the rest. Each test holds what the native
path gives (on SymEngine) to what SymPy's path gives for the same determinant (the
SymPy branch of :func:`simplified_det`, run inside ``sx.using("sympy")``): the same tree
on either engine, the same text, the same singular set, and det's value at random
points; and that the native path is the one taken for arm_on_line.
"""

from __future__ import annotations

import functools
from typing import Any

import numpy as np
import pytest
import sympy as sp
from hypothesis import HealthCheck, Phase, given, settings
from hypothesis import strategies as st

from tvopt_codegen import symbolic as sx
from tvopt_codegen.derivation import derive, equalities, linearization, singularity
from tvopt_codegen.derivation.singularity import _monomial, _singular_set, simplified_det
from tvopt_codegen.spec import load_spec
from tvopt_codegen.symbolic import trigforms, trigpoly
from tvopt_codegen.symbolic.border import from_sympy, to_sympy

from .conftest import ROOT, SPECS
from .engine_cases import ARM_DET_TEXT, sympy_free_run

EXAMPLES = sorted(p.stem for p in (ROOT / "tvopt_codegen" / "examples").glob("*.toml"))
TEST_SPECS = sorted(str(p) for p in SPECS.glob("*.toml"))

a, b, m1, m2, l1, l2, x, q1, q2, theta = sp.symbols("a b m1 m2 l1 l2 x q1 q2 theta", real=True)
#: The arm's det R as the derivation hands it to simplified_det (SymPy's dotprodsimp form).
ARM_DET = (sp.sin(q1 + q2) * sp.cos(q1) - sp.cos(q1 + q2) * sp.sin(q1)) / (
    l1 * l2 * m2**2 + l1 * l2 * m1 * m2 - l1 * l2 * m2**2 * sp.cos(q2) ** 2
)


@functools.cache
def _recorded() -> dict[str, list[Any]]:
    """Every determinant each example and test spec hands to simplified_det, on SymEngine."""
    out: dict[str, list[Any]] = {}
    calls: list[Any] = []

    def spy(det: Any) -> Any:
        calls.append(det)
        return simplified_det(det)

    with pytest.MonkeyPatch.context() as patch, sx.using("symengine"):
        patch.setattr(linearization, "simplified_det", spy)
        patch.setattr(equalities, "simplified_det", spy)
        for name in (*EXAMPLES, *TEST_SPECS):
            calls.clear()
            derive(load_spec(name))
            out[name] = list(calls)
    return out


@functools.cache
def _reference(given: Any) -> tuple[Any, tuple[str, ...]]:
    """SymPy's branch on ``given`` (SymPy's): its simplified determinant and singular set.

    Once per determinant: the arm's det R is SymPy's to simplify in three tests (its own,
    the arm_on_line spec's recorded det, the process that refuses SymPy), half a second
    each; SymPy's simplify is a function of its input alone.
    """
    with sx.using("sympy"):
        reference = simplified_det(given)
        return reference, _singular_set(reference)


def _native(det: Any) -> bool:
    """Whether SymEngine's simplified_det decides ``det`` (SymEngine's) without SymPy."""
    return _monomial(det) is not None or trigforms.lowest(det) is not None


def _compare(det: Any, refused: bool = False) -> tuple[Any, tuple[str, ...]]:
    """Native (SymEngine) against SymPy's branch, for one SymEngine determinant.

    Returns SymPy's simplified tree and singular set. Where the native paths refuse
    ``det`` (``refused``, asserted), SymEngine's simplified_det runs SymPy's branch on
    ``to_sympy(det)``, the reference's own input: its result is the reference's, taken
    once (SymPy's simplify is most of this test's time), and what is compared is the
    border's crossing back and the singular set read on SymEngine.
    """
    with sx.using("symengine"):
        given = to_sympy(det)  # real symbols, as the border makes them
    reference, reference_singular = _reference(given)
    with sx.using("symengine"):
        if refused:
            assert not _native(det), det
            found = from_sympy(reference)
        else:
            found = simplified_det(det)
        singular = _singular_set(found)
        assert found == from_sympy(reference), (det, found, reference)  # SymEngine's tree
        assert sx.text(found) == sx.text(from_sympy(reference))
        assert to_sympy(found) == reference  # SymPy's tree
        assert sp.sstr(to_sympy(found)) == sp.sstr(reference)
    assert singular == reference_singular, det
    return reference, singular


def _values(expr: Any, symbols: list[Any], points: np.ndarray) -> np.ndarray:
    return np.array([float(expr.subs(dict(zip(symbols, p, strict=True)))) for p in points])


def _same_value(det: Any, found: Any, seed: int = 5) -> None:
    """``found`` and ``det`` (SymPy's) agree at random points: exactness, independently."""
    symbols = sorted(det.free_symbols | found.free_symbols, key=str)
    points = np.random.default_rng(seed).uniform(0.3, 1.4, size=(6, len(symbols)))
    left = sp.lambdify(symbols, det, "math")
    right = sp.lambdify(symbols, found, "math")
    first = np.array([left(*p) for p in points])
    second = np.array([right(*p) for p in points])
    np.testing.assert_allclose(second, first, rtol=1e-11)


def test_arm_on_line_det_is_native_and_sympys() -> None:
    """The arm's det R: the native path, SymPy's tree, its text and its singular set."""
    with sx.using("symengine"):
        det = from_sympy(ARM_DET)
        assert _monomial(det) is None  # not the monomial path: a sum below
        assert trigforms.lowest(det) is not None
    reference, singular = _compare(det)
    assert sp.sstr(reference) == "sin(q2)/(l1*l2*m2*(m1 + m2*sin(q2)**2))"
    assert singular == ("sin(q2) = 0",)
    _same_value(ARM_DET, reference)


def test_arm_on_line_derivation_takes_the_native_path() -> None:
    """The determinant arm_on_line's derivation really hands over is the native path's."""
    dets = _recorded()["arm_on_line"]
    with sx.using("symengine"):
        assert any(trigforms.lowest(d) is not None and _monomial(d) is None for d in dets)
        assert all(_native(d) for d in dets)  # det R and the equality's Gram determinant


@pytest.mark.parametrize("name", [*EXAMPLES, *TEST_SPECS])
def test_every_recorded_det_is_sympys(name: str) -> None:
    """Each spec's det R and Gram determinant decided natively is what SymPy gives.

    (One that is not goes through SymPy's branch on both engines alike.)
    """
    for det in _recorded()[name]:
        with sx.using("symengine"):
            native = _native(det)
        if native:
            _compare(det)


def test_bundled_examples_need_sympy_for_no_det() -> None:
    """Every bundled example's determinants are decided natively on SymEngine."""
    recorded = _recorded()
    with sx.using("symengine"):
        assert all(_native(d) for name in EXAMPLES for d in recorded[name])
    assert recorded["arm_on_line"] and recorded["pvtol"]


# ------------------------------------------------------------------ random determinants
_SYMBOLS = [a, b, m1, m2, l1, l2, x]
_ANGLES = [q1, q2, theta]


def _draw(pick: Any) -> Any:
    """A random determinant of the accepted shape, written one of several longer ways.

    ``pick(n)`` draws an integer in ``[0, n)``: the same builder serves numpy's generator
    and hypothesis' ``data.draw``.
    """
    number = sp.Rational([-3, -1, 1, 2, 5][pick(5)], [1, 1, 2, 3][pick(4)])
    monomial = sp.Integer(1)
    for symbol in _SYMBOLS:
        if pick(4) == 0:
            monomial *= symbol ** [-2, -1, 1, 2][pick(4)]
    angle_functions = {}
    for angle in _ANGLES:
        if pick(3) == 0:
            function = [sp.sin, sp.cos][pick(2)]
            angle_functions[angle] = function
            monomial *= function(angle) ** [1, 1, 2, 3][pick(4)]
    angle = _ANGLES[pick(3)]
    square = [sp.sin, sp.cos][pick(2)](angle) ** 2
    terms = []
    for _ in range(2 + pick(2)):
        term = sp.Integer([-2, -1, 1, 1, 3][pick(5)])
        for symbol in _SYMBOLS:
            if pick(5) == 0:
                term *= symbol ** (1 + pick(2))
        if pick(2):
            term *= square ** (1 + pick(4) // 3)  # now and then beyond the shape
        terms.append(term)
    factor = sp.Add(*terms)
    if pick(3) == 0:  # written in the other function: sin^2 = 1 - cos^2 (or back)
        other = (sp.cos if square.base.func == sp.sin else sp.sin)(angle) ** 2
        factor = factor.subs(square, 1 - other)
    numerator, denominator = number * monomial, factor
    if pick(3) == 0:  # a common factor over and under
        common = [a + b, m1 + m2 * sp.sin(q1) ** 2, l1 * x + 1][pick(3)]
        numerator, denominator = numerator * common, denominator * common
    if pick(4) == 0 and q2 in monomial.free_symbols and angle_functions.get(q2) == sp.sin:
        # an arm's angle sum: sin(q2) = sin(q1 + q2) cos(q1) - cos(q1 + q2) sin(q1)
        arm = sp.sin(q1 + q2) * sp.cos(q1) - sp.cos(q1 + q2) * sp.sin(q1)
        numerator = numerator.subs(sp.sin(q2), arm)
    if pick(2):
        return sp.expand(numerator) / sp.expand(denominator)
    return numerator / denominator


def _check_random(det: Any) -> bool:
    """Compare native and SymPy for one drawn determinant; whether native took it."""
    with sx.using("symengine"):
        converted = from_sympy(det)
        taken = _native(converted)
    if taken:
        reference, _ = _compare(converted)
        _same_value(det, reference)
    return taken


def test_random_determinants_of_the_shape_are_sympys() -> None:
    """Sixteen drawn determinants: most are taken natively, and each taken is SymPy's.

    (Each taken costs SymPy's simplify, half a second; the hypothesis test below draws
    more of the same family.)
    """
    rng = np.random.default_rng(49)
    taken = sum(_check_random(_draw(lambda n: int(rng.integers(n)))) for _ in range(16))
    assert taken >= 8, taken  # the path is exercised, not only refused


# No shrinking: each example costs SymPy's simplify (half a second), and a shrink of a
# failure took five minutes; the failing draw is printed whole instead.
@settings(
    max_examples=10,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow],
    phases=(Phase.explicit, Phase.reuse, Phase.generate),
)
@given(st.data())
def test_drawn_determinants_are_sympys_when_taken(data: st.DataObject) -> None:
    """Hypothesis' draws of the same family: whatever the native path takes is SymPy's."""
    _check_random(_draw(lambda n: data.draw(st.integers(0, n - 1))))


def test_beside_the_shape_sympy_decides() -> None:
    """Two forms of one length, a factor above, sin cos of one angle, a sine below, a
    reducible or unproved factor, two factors: refused, and SymPy's result stands."""
    s, c = sp.sin(q1), sp.cos(q1)
    arm = sp.sin(q1 + q2) * sp.cos(q1) - sp.cos(q1 + q2) * sp.sin(q1)
    for det in (
        s / (2 - c**2),  # 1 + sin^2 is as long: SymPy keeps what it is given
        s / (a * s**2 + b * c**2),
        (m1 + m2 * s**2) / l1,  # a polynomial above: its text is SymPy's to write
        s * c / (m1 + m2 * s**2),  # sin(2 q1)/2
        a / (c * (m1 + m2 * s**2)),  # tan
        a / (m1**2 - m2**2 * s**2),  # (m1 - m2 sin)(m1 + m2 sin)
        s / (1 + s**2),  # irreducible, but not by the rule
        s / (1 + 2 * a * b**2 * sp.expand((1 - s**2) ** 2)),  # SymPy keeps it, not c^4 (drawn)
        -3 * arm**2 / (b**2 * m1**2 * (-2 - 2 * x * l1)),  # SymPy keeps the square (drawn)
        arm * sp.cos(q1 + q2) / (1 + x),  # two angle sums in a product
        a / ((m1 + m2 * s**2) * (a + b)),  # two factors
        a / (m1 + m2 * sp.sin(q2) ** 2 + b * s**2),  # two angles
        a / (m1 + m2 * sp.sin(x / 10) ** 2),  # an angle that is not a symbol
        # 2 cos^2 below: SymPy writes cos(2 q2) + 1 (drawn; and -2 sin^2 as cos(2 q2) - 1)
        2 * b**2 * l1 * sp.cos(theta) / (-l2 * m2**2 * m1 - 2 * sp.cos(q2) ** 2),
        a / (m1 - 2 * sp.sin(q2) ** 2),
    ):
        with sx.using("symengine"):
            converted = from_sympy(det)
            assert trigforms.lowest(converted) is None, det
        _compare(converted, refused=True)


def test_exact_quotient_and_irreducibility_rule() -> None:
    """The two proofs the shape rests on, on polynomials with known answers."""
    atoms = trigpoly.Atoms()
    memo: dict[Any, Any] = {}
    with sx.using("symengine"):

        def poly(expr: Any) -> trigpoly.Poly:
            found = trigpoly.rational(from_sympy(expr), atoms, memo)
            assert found is not None and found[1] == trigpoly.ONE
            return found[0]

        product = poly(sp.expand((a + b) * (m1 + m2 * a**2)))
        assert trigpoly.exact_quotient(product, poly(a + b)) == poly(m1 + m2 * a**2)
        assert trigpoly.exact_quotient(product, poly(a - b)) is None
        assert trigpoly.exact_quotient(poly(a**2 + b), poly(a + b)) is None
        assert trigpoly.irreducible(poly(m1 + m2 * a**2))
        assert trigpoly.irreducible(poly(a * m1 + b))
        assert not trigpoly.irreducible(poly(a * m1 + a * b))  # a divides it: not proved
        assert not trigpoly.irreducible(poly(m1**2 - m2**2))  # (m1 - m2)(m1 + m2)


# ------------------------------------------------------------------ processes
# One SymEngine process that cannot import SymPy for both tests below, and for
# test_engine_det's and test_report_printing's checks (engine_cases.sympy_free_run): the
# arm's det R decided, then ``generate arm_on_line`` on both backends. Each part reports
# its own failure, so that each test sees only its own.


def test_the_arms_det_is_decided_in_a_process_that_refuses_sympy() -> None:
    """simplified_det and the singular set of the arm's det R import no SymPy."""
    assert str(ARM_DET) == ARM_DET_TEXT  # the process decides this very determinant
    found, _ = sympy_free_run()
    assert "det failed" not in found, found["det failed"][-2000:]
    text, singular = found["det"]
    reference, _ = _reference(ARM_DET)
    with sx.using("symengine"):
        assert text == sx.text(from_sympy(reference))
    assert singular == ["sin(q2) = 0"]


def test_generate_arm_on_line_imports_no_sympy() -> None:
    """``generate arm_on_line`` on both backends, in a SymEngine process that cannot import
    SymPy, writes generated/arm_on_line.py and generated/c/arm_on_line* byte for byte:
    det R (symbolic/linalg), its simplified form and singular set, and the undefined set
    (a denominator's text and sign) are all decided natively."""
    found, folder = sympy_free_run()
    assert "generate failed" not in found, found["generate failed"][-2000:]
    assert found["sympy modules"] == [], found
    written = (folder / "arm_on_line.py").read_text()
    assert written == (ROOT / "generated" / "arm_on_line.py").read_text()
    assert "R or p is undefined where l2**2*m2*(l1**2*(m1 + m2)" in written
    golden = sorted((ROOT / "generated" / "c").glob("arm_on_line*"))
    assert len(golden) == 4
    for path in golden:
        assert (folder / path.name).read_bytes() == path.read_bytes(), path.name


def test_the_singular_set_reads_a_plain_numerator_natively() -> None:
    """Over a polynomial, a numerator of atoms is read without SymPy; a sum above is SymPy's."""
    s, c = sp.sin(q1), sp.cos(q1)
    for det, native in (
        (s / (a + b), True),
        (a * b**2 * s**2 / (x * (m1 + m2 * s**2)), True),
        (1 / (a + b), True),
        (3 * a / (1 + x) ** 2, True),
        ((a * s**2 + a * c**2) / (a + b), False),  # factor_list keeps sin^2 + cos^2
        ((a + b) * s / (1 + x), False),
        (s / (1 + 1 / x), False),  # together moves x above
    ):
        with sx.using("sympy"):
            reference = _singular_set(det)
        with sx.using("symengine"):
            converted = from_sympy(det)
            numerator = singularity._numerator(converted)
            assert (numerator != converted or not converted.is_Mul) == native, det
            assert _singular_set(converted) == reference, det


# ------------------------------------------------------------------ a condition's text
def _random_tree(rng: Any, depth: int) -> Any:
    """A random SymEngine tree of sums, products, powers, numbers, symbols, sin and cos."""
    symbols = sx.symbols(["a", "b", "x", "y", "l1", "l2", "m1", "m10", "m2", "q2", "theta", "Z"])
    if depth == 0 or rng.random() < 0.1:
        r = rng.random()
        if r < 0.15:
            number = rng.choice([-3, -2, -1, 1, 2, 5])
            return rng.choice([sx.Integer(number), sx.Rational(1, 2)])
        if r < 0.35:
            return rng.choice([sx.sin, sx.cos])(rng.choice(symbols))
        return rng.choice(symbols)
    r = rng.random()
    if r < 0.45:
        return sum((_random_tree(rng, depth - 1) for _ in range(rng.randint(2, 4))), sx.ZERO)
    if r < 0.85:
        out = sx.ONE
        for _ in range(rng.randint(2, 3)):
            out *= _random_tree(rng, depth - 1)
        return out
    return _random_tree(rng, depth - 1) ** rng.randint(2, 3)


def test_a_conditions_text_is_sympys() -> None:
    """sympy_text writes 600 random trees as SymPy's sstr does, or declines (rationals)."""
    import random  # noqa: PLC0415

    rng = random.Random(7)
    written = 0
    with sx.using("symengine"):
        for _ in range(600):
            tree = _random_tree(rng, rng.randint(1, 3))
            text = trigforms.sympy_text(tree)
            if text is not None:
                written += 1
                assert text == sp.sstr(to_sympy(tree)), tree
        arm = sx.sympify(
            "l2**2*m2*(l1**2*(m1 + m2) + 2*l1*l2*m2*cos(q2) + l2**2*m2)"
            " - (l1*l2*m2*cos(q2) + l2**2*m2)**2"
        )
        assert trigforms.sympy_text(arm) == sp.sstr(to_sympy(arm))
        assert trigforms.sympy_text(2 * (arm.args[0] + 1)) is None  # SymPy distributes 2
    assert written > 300


def test_a_value_of_both_signs_has_none() -> None:
    """indefinite finds both signs only where there are: SymPy's sign is then None."""
    with sx.using("symengine"):
        x, y, q = sx.symbols(["x", "y", "q"])
        assert trigforms.indefinite(x * y) and trigforms.indefinite(x - sx.cos(q))
        for never in (x**2 + 1, sx.sin(q) ** 2 + sx.cos(q) ** 2, (x - y) ** 2, 2 + sx.cos(q)):
            assert not trigforms.indefinite(never), never
        import random  # noqa: PLC0415

        rng = random.Random(3)
        both = 0
        for _ in range(60):
            tree = _random_tree(rng, 2)
            if trigforms.indefinite(tree):
                both += 1
                assert singularity._sign(to_sympy(tree)) is None, tree
    assert both > 20


def test_cancels_view_keeps_angle_sums_as_atoms() -> None:
    """Atoms(expand_angles=False) reads functions as SymPy's cancel does: the arm's det R is
    two terms in four atoms over its monomial content times a polynomial of three terms."""
    with sx.using("symengine"):
        atoms = trigpoly.Atoms(expand_angles=False)
        found = trigpoly.rational(from_sympy(ARM_DET), atoms, {})
        assert found is not None
        numerator, denominator = found
        assert len(numerator) == 2 and len(atoms.exprs) >= 4
        number, monomial, rest = trigpoly.content(denominator)
        assert number == 1 and len(monomial) == 3 and len(rest) == 3  # l1 l2 m2 (...)
        assert any(not e.is_Symbol and not e.args[0].is_Symbol for e in atoms.exprs)
        plain = trigpoly.Atoms()
        assert trigpoly.rational(from_sympy(ARM_DET), plain, {}) is not None
        assert all(e.is_Symbol or e.args[0].is_Symbol for e in plain.exprs)  # expanded
