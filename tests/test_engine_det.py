"""det R on SymEngine without SymPy: the same records, and no SymPy for the bundled examples.

On SymEngine, det R, its factored form and its singular set are decided without SymPy
where det R is a number times powers of symbols, sines and cosines once its angles are
expanded and ``sin^2 + cos^2 = 1`` applied (:func:`singularity._monomial`), and a small
determinant with monomial denominators is not simplified through the border
(:func:`linalg.sized_det`), and one over a sum is put over one denominator as SymPy's
``dotprodsimp`` does (:func:`trigforms.cancelled`); elsewhere the border decides, as
before. Every bundled example is derived, lowered and rendered on SymEngine in a process
that cannot import SymPy; every example and test spec gives the decoupling record SymPy gives:
the singular and undefined sets' text, det R's note, and det R at random points.
The reference is SymPy's, named (``sx.using("sympy")``): whichever engine is the
process's default.
"""

from __future__ import annotations

import functools
import json
from typing import Any

import numpy as np
import pytest
import sympy as sp

from tvopt_codegen import symbolic as sx
from tvopt_codegen.derivation.singularity import (
    _monomial,
    _monomial_conditions,
    _singular_set,
    simplified_det,
)
from tvopt_codegen.renderer.rendering import render
from tvopt_codegen.symbolic import linalg
from tvopt_codegen.symbolic.border import from_sympy, to_sympy

from .conftest import SPECS, derivation, kernels
from .engine_cases import BORDER, EXAMPLES, remembered_simplify, sympy_free_run

TEST_SPECS = sorted(str(p) for p in SPECS.glob("*.toml"))


def _record(name: str) -> list[Any]:
    """``name``'s decoupling record on SymEngine, in this process: as the script's."""
    with sx.using("symengine"):
        d = derivation(name)
        render(kernels(name), "python")
        dec = d.decoupling
        return [
            list(dec.singular_set),
            list(dec.undefined_set),
            dec.det_R_note,
            None if dec.det_R is None else sx.text(dec.det_R),
        ]


@functools.cache
def _symengine_records() -> dict[str, list[Any]]:
    """Every example's and test spec's decoupling record, derived on SymEngine.

    The examples (and any in ``BORDER``) in the SymEngine process that refuses SymPy's
    import for the examples (``engine_cases.sympy_free_run``); the test specs, whose
    derivation may use SymPy, in this one (as that process did with SymPy allowed): most
    test files derive and lower them on SymEngine already (conftest's ``derivation`` and
    ``kernels``), and a second process derived them again (0.75 s).
    """
    found, _ = sympy_free_run()
    assert "records failed" not in found, found["records failed"][-3000:]
    records: dict[str, list[Any]] = dict(found["records"])
    # Through JSON, as the process's records are (a tuple would not compare as a list).
    records.update({name: json.loads(json.dumps(_record(name))) for name in TEST_SPECS})
    return records


def _values(exprs: list[Any], seed: int) -> np.ndarray:
    """SymPy expressions' values at 16 random points in [0.5, 1.5] of every symbol."""
    symbols = sorted(set().union(*(e.free_symbols for e in exprs)), key=str)
    rng = np.random.default_rng(seed)
    function = sp.lambdify(symbols, exprs, "numpy")
    rows = [function(*point) for point in rng.uniform(0.5, 1.5, size=(16, len(symbols)))]
    return np.array([np.broadcast_to(row, (len(exprs),)) for row in rows], float)


def _same_numbers(reference: Any, found: Any) -> None:
    first, second = _values([reference, found], 7).T
    assert np.all(np.isfinite(first)) and np.any(first != 0)
    np.testing.assert_allclose(second, first, rtol=1e-12, atol=1e-12 * np.abs(first).max())


@pytest.mark.parametrize("name", [*EXAMPLES, *TEST_SPECS])
def test_the_decoupling_record_is_sympys(name: str) -> None:
    """Singular and undefined sets' text, det R's note and det R's values, as on SymPy."""
    singular, undefined, note, det_text = _symengine_records()[name]
    with sx.using("sympy"):
        reference = derivation(name).decoupling
    assert tuple(singular) == reference.singular_set
    assert tuple(undefined) == reference.undefined_set
    assert note == reference.det_R_note
    assert (det_text is None) == (reference.det_R is None)
    det = reference.det_R
    if det_text is not None and det is not None:
        found = sp.sympify(det_text, locals={s.name: s for s in det.free_symbols})
        if found.free_symbols or det.free_symbols:
            _same_numbers(det, found)
        else:
            assert found == det


def test_the_bundled_examples_need_no_sympy() -> None:
    """The examples named free were derived with SymPy's import refused (the script's assert)."""
    records = _symengine_records()
    assert set(EXAMPLES) <= set(records)
    assert {"pvtol", "planar_arm3", "two_unicycles_corridor", "arm_on_line"} <= set(EXAMPLES) - set(
        BORDER
    )


def _monomials(count: int, seed: int) -> list[Any]:
    """Random numbers times powers of symbols and of a sine or cosine of other symbols."""
    names = ["a", "b", "Z", "l1", "l10", "l2", "q", "q2", "theta", "v"]
    symbols = [sp.Symbol(n, real=True) for n in names]
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(count):
        chosen = rng.permutation(len(symbols))[: rng.integers(1, 6)]
        term = sp.Rational(int(rng.choice([-3, -1, 1, 2, 5])), int(rng.choice([1, 1, 4])))
        for i in chosen:
            atom = symbols[i]
            kind = rng.integers(0, 3)
            if kind:
                atom = (sp.sin if kind == 1 else sp.cos)(atom)
            term *= atom ** int(rng.choice([-2, -1, 1, 1, 1, 2, 3]))
        out.append(term)
    return out


def test_a_monomials_singular_set_is_written_in_sympys_order() -> None:
    """factor_list's order: by exponent, then the Mul's (symbols, powers, cos, sin, names)."""
    for expr in _monomials(150, 11):
        with sx.using("sympy"):
            reference = _singular_set(expr)
        with sx.using("symengine"):
            converted = from_sympy(expr)
            assert _monomial(converted, expand_angles=False) is not None  # decided natively
            found = _singular_set(converted)
            short = to_sympy(simplified_det(converted))
        assert found == reference, expr
        assert short == sp.factor(expr), expr


def test_pythagoras_and_angle_sums_collapse_to_sympys_monomial() -> None:
    v, w, q1, q2, m, J = sp.symbols("v w q1 q2 m J", real=True)
    s1, c1, s12, c12 = sp.sin(q1), sp.cos(q1), sp.sin(q1 + q2), sp.cos(q1 + q2)
    cases = [
        v * s1**2 + v * c1**2,  # a unicycle
        (w * s1**2 + w * c1**2) / (J * m**2),  # a quadrotor
        (v * s1**2 + v * c1**2) * (w * sp.sin(q2) ** 2 + w * sp.cos(q2) ** 2),  # two
        -s1 * c12 + s12 * c1,  # an arm: sin(q2)
        v * s1**4 + 2 * v * s1**2 * c1**2 + v * c1**4,  # (sin^2 + cos^2)^2 = 1
        v - v * c1**2,  # v sin(q1)^2, by the other rewrite
        sp.cos(2 * q1) + 2 * s1**2,  # cos(2 q1) = 1 - 2 sin^2
        sp.sin(w / 10) ** 2 + sp.cos(w / 10) ** 2,  # a time-varying line's Gram determinant
        w * sp.sin(q1 / 10) / sp.cos(q2 + w / 3),  # SymPy writes the angle: its singular set
    ]
    for det in cases:
        with sx.using("sympy"):
            reference = simplified_det(det)
            reference_singular = _singular_set(reference)
        with sx.using("symengine"):
            converted = from_sympy(det)
            assert _monomial(converted) is not None, det
            found = to_sympy(simplified_det(converted))
            singular = _singular_set(simplified_det(converted))
        assert sp.simplify(found - reference) == 0, det
        assert singular == reference_singular, det
    with sx.using("symengine"):
        found = _monomial(from_sympy(cases[-1]), expand_angles=False)
        assert found is not None and _monomial_conditions(*found) is None


def test_what_sympy_might_write_otherwise_is_left_to_it() -> None:
    """One angle under a sine and a cosine (sin(2 q)/2, tan), a sum that stays: the border."""
    q, r, c = sp.symbols("q r c", real=True)
    for det in (
        sp.sin(q) * sp.cos(q),
        sp.sin(q) / sp.cos(q),
        sp.sin(q + r),
        2 * c + sp.sin(q),
        sp.tan(q) * c,
        sp.exp(q),
        c**2 - 1,
        1 / (c + 1),
    ):
        # Both engines' simplified_det ask SymPy's branch for simplify of one input:
        # worked out once (a function of its input alone), each engine's result compared.
        with remembered_simplify():
            with sx.using("sympy"):
                reference = simplified_det(det)
                reference_singular = _singular_set(reference)
            with sx.using("symengine"):
                converted = from_sympy(det)
                assert _monomial(converted) is None, det
                found = to_sympy(simplified_det(converted))
                singular = _singular_set(simplified_det(converted))
        assert sp.simplify(found - reference) == 0
        assert singular == reference_singular, det


def test_a_small_determinant_is_sympys_and_sized_alike() -> None:
    """Written out and expanded without SymPy where it has no denominators: SymPy's own.

    With monomial denominators, ``sized_det`` keeps the expansion (equal in value) and
    its size bound decides as SymPy's ``cancel`` form's size does.
    """
    x, y, z = sp.symbols("x y z", real=True)
    pool = [0, 0, 1, -1, x, x * sp.sin(y), z**2 + 1, x * y - 3, sp.Rational(1, 3), 1 / x]
    pool += [sp.cos(x * (y + 1)), y / (x * z), sp.sin(x) ** 2, 1 / (x + y), x**-2 * y]
    rng = np.random.default_rng(23)
    native = 0
    for _ in range(150):
        n = int(rng.integers(2, 4))
        matrix = sp.ImmutableMatrix(n, n, [pool[k] for k in rng.integers(0, len(pool), n * n)])
        reference = matrix.det(method="berkowitz")
        small = sx.tree_size(reference, 400) <= 400
        with sx.using("symengine"):
            converted = from_sympy(matrix)
            expanded = linalg._expanded(converted.tolist())
            found = to_sympy(linalg.det(converted))
            sized, decided = linalg.sized_det(converted, 400)
            sized = to_sympy(sized)
        plain = expanded is not None and expanded[1] == linalg._POLYNOMIAL
        native += plain
        if expanded is not None:  # SymPy's size exactly, or a bound of its cancel form's
            size = sx.tree_size(reference, 10_000)
            own = sx.tree_size(expanded[0], 10_000)  # on SymEngine
            if plain:
                assert own == size
            elif expanded[1] == linalg._MONOMIALS:
                assert linalg._cancelled_bound(expanded[0]) >= size
        assert found == reference
        assert decided == small
        assert sp.expand(sp.cancel(sized - reference)) == 0
    assert native > 20  # the path without SymPy was taken


def test_a_4x4_det_is_simplified_or_not_alike_on_both_engines() -> None:
    """Near the size limit, SymPy's own 4 x 4 det decides (SymEngine's terms differ)."""
    import random

    from tvopt_codegen.symbolic import linalg

    rng = random.Random(11)  # its first 30 draws hold four matrices that once split
    syms = sp.symbols("a b c d e f", real=True)

    def entry() -> Any:
        a, b = rng.choice(syms), rng.choice(syms)
        return rng.choice([0, a, a * b, sp.sin(a), 1 + a, a - b, a**2 + b, 2 * a * sp.cos(b)])

    for _ in range(30):
        matrix = sp.ImmutableMatrix(4, 4, [entry() for _ in range(16)])
        small = sx.tree_size(matrix.det(method="berkowitz"), 400) <= 400
        with sx.using("symengine"):
            assert linalg.sized_det(from_sympy(matrix), 400)[1] == small
