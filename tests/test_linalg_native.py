"""A small determinant over a sum, written as SymPy's ``dotprodsimp`` writes it, without SymPy.

On SymEngine, :func:`linalg.det` of a 2 x 2 or 3 x 3 matrix whose expansion has a
denominator that is a sum (a mass-matrix arm's det R) builds ``cancel``'s ``P/Q`` itself
(:func:`trigforms.cancelled`) where it is sure of it, and crosses the border otherwise.
Each test holds the native path to the border's, on the same SymEngine matrix: the same
tree (so the same ``--max-size`` meter, the same ``small`` decision of
:func:`linalg.sized_det` at every size limit, and the same input to ``simplified_det``),
and the determinant's value at random points against NumPy's determinant of the
matrix's values. The border's path is the product's own with the native path switched
off (``trigforms.cancelled`` answering None).
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, Phase, given, settings
from hypothesis import strategies as st

from tvopt_codegen import symbolic as sx
from tvopt_codegen.derivation.equalities import _equality_jacobian
from tvopt_codegen.derivation.linearization import _linearize, _with_gains
from tvopt_codegen.derivation.meter import _DET_SIMPLIFY_NODES, _Meter
from tvopt_codegen.derivation.model import build_model
from tvopt_codegen.limits import Budget
from tvopt_codegen.spec import load_spec
from tvopt_codegen.symbolic import linalg, trigforms

from .conftest import ROOT, SPECS

EXAMPLES = sorted(p.stem for p in (ROOT / "tvopt_codegen" / "examples").glob("*.toml"))
TEST_SPECS = sorted(str(p) for p in SPECS.glob("*.toml"))


@contextmanager
def _border() -> Iterator[None]:
    """The product with its native ``cancel`` switched off: SymPy's ``dotprodsimp`` decides."""
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(trigforms, "cancelled", lambda written, expanded: None)
        yield


def _taken(matrix: Any) -> bool:
    """Whether :func:`linalg.det` of ``matrix`` (2 x 2 or 3 x 3) is written natively."""
    rows = matrix.tolist()
    expanded = linalg._expanded(rows) if len(rows) <= 3 else None
    if expanded is None or expanded[1] == linalg._POLYNOMIAL:
        return False
    deep = linalg._deep_expanded(linalg._written_out(rows), {})
    return trigforms.cancelled(deep, expanded[0]) is not None


def _same_value(matrix: Any, value: Any, seed: int) -> None:
    """``value`` is ``det(matrix)`` at random points (NumPy's determinant of the values)."""
    symbols = sorted(value.free_symbols | matrix.free_symbols, key=str)
    n = matrix.shape[0]
    rng = np.random.default_rng(seed)
    for point in rng.uniform(0.4, 1.3, size=(3, len(symbols))):
        at = {s: sx.Float(float(v)) for s, v in zip(symbols, point, strict=True)}
        numbers = np.array([[float(matrix[i, j].subs(at)) for j in range(n)] for i in range(n)])
        expected = np.linalg.det(numbers)
        found = float(value.subs(at))
        scale = float(np.abs(numbers).max()) ** n
        assert abs(found - expected) <= 1e-9 * max(scale, abs(expected)), (value, point)


def _agree(matrix: Any, seed: int = 0) -> bool:
    """The native path and the border give one tree and one decision; whether native ran.

    Each path's :func:`linalg.det` runs once per matrix (SymPy's ``dotprodsimp`` a
    fraction of a second): at each size limit, ``sized_det`` is given that path's
    determinant (the same function's value, kept).
    """
    taken = _taken(matrix)
    found = linalg.det(matrix)
    with _border():
        reference = linalg.det(matrix)
    assert found == reference, (matrix, found, reference)  # the tree, not only the value
    size = sx.tree_size(reference, 10_000)
    for nodes in (size - 1, size, _DET_SIMPLIFY_NODES):
        decided = []
        for value in (found, reference):
            with pytest.MonkeyPatch.context() as patch:
                patch.setattr(linalg, "det", lambda _, value=value: value)
                decided.append(linalg.sized_det(matrix, nodes))
        (native, native_small), (border, border_small) = decided
        assert native == border and native_small == border_small, (matrix, nodes)
        if native is found:  # det's own value: the decision is its size's
            assert native_small == (size <= nodes)
    _same_value(matrix, found, seed)
    return taken


# ------------------------------------------------------------------ every spec's matrices
@functools.cache
def _matrices(name: str) -> tuple[Any, ...]:
    """``name``'s R (as ``_decoupling`` takes it) and its equalities' Gram matrix, m <= 4."""
    with sx.using("symengine"):
        spec = load_spec(name)
        model = build_model(spec)
        lin = _linearize(model, _Meter(spec.source, Budget()))
        out = [_with_gains(lin.R, model.mechanics)]
        if 0 < len(model.equalities) <= 4:
            jacobian = sx.Matrix(_equality_jacobian(model))
            out.append(jacobian * jacobian.T)
    return tuple(m for m in out if 2 <= m.shape[0] <= 4)


@pytest.mark.parametrize("name", [*EXAMPLES, *TEST_SPECS])
def test_every_specs_determinants_are_the_borders(name: str) -> None:
    """det R and the Gram determinant of each example and test spec: the border's tree,
    size decision and value, whichever path writes them."""
    with sx.using("symengine"):
        for i, matrix in enumerate(_matrices(name)):
            _agree(matrix, seed=i)


def test_the_arms_det_r_is_written_natively() -> None:
    """arm_on_line's det R is the native path's (two terms over three), SymPy's tree."""
    (matrix,) = _matrices("arm_on_line")
    with sx.using("symengine"):
        assert _taken(matrix)
        found = linalg.det(matrix)
        assert sx.tree_size(found, 1000) == 42
        numerator, denominator = found.args if found.args[0].is_Add else found.args[::-1]
        assert len(numerator.args) == 2 and denominator.args[1] == -1
        assert len(denominator.args[0].args) == 3


# ------------------------------------------------------------------ chosen matrices
def _chosen() -> list[tuple[Any, bool]]:
    """Matrices beside the arm, each with whether the native path takes it."""
    x, y, z, a, b, m1, m2, theta, J = sx.symbols(
        ["x", "y", "z", "a", "b", "m1", "m2", "theta", "J"]
    )
    q1, q2 = sx.symbols(["q1", "q2"])
    s1, c1, c2 = sx.sin(q1), sx.cos(q1), sx.cos(q2)
    d = m1 + m2 * s1**2
    return [
        # A mass-matrix arm's shape over one irreducible polynomial, a monomial beside it.
        (sx.Matrix([[x / d, y / (a * d)], [c1 / d, (x + s1) / d]]), True),
        # Everything cancels: a number (1/2) and a monomial (1/x) are left.
        (sx.Matrix([[(a + b) / (2 * (a + b + x)), -x / (2 * (a + b + x))], [1, 1]]), True),
        (sx.Matrix([[a / (x * (a + b + y)), -(b + y) / (x * (a + b + y))], [1, 1]]), True),
        # Q's leading coefficient: theta sorts after SymPy's dummies, J before them.
        (sx.Matrix([[(x + y + z) / (theta - s1), 0], [0, 1]]), True),
        (sx.Matrix([[(x + y + z) / (J - s1), 0], [0, 1]]), True),
        # Q's sign depends on the dummies' order (sin(q1) - cos(q2)): the border.
        (sx.Matrix([[(x + y + z) / (s1 - c2), 0], [0, 1]]), False),
        # Not proved irreducible: (m1 - m2 sin)(m1 + m2 sin), and (x + y)^2 + 1 multiplied
        # out where no entry has it alone.
        (sx.Matrix([[(x + y + z) / (m1**2 - m2**2 * s1**2), 0], [0, 1]]), False),
        # A sign SymEngine and SymPy might take out of an angle differently: the border.
        (sx.Matrix([[(x + y + z) / (a + sx.sin(q1 - q2)), 0], [0, 1]]), False),
        # Too few operations to be sure dotprodsimp cancels (it does not at five).
        (sx.Matrix([[a / (a + b), -1], [b / (a + b), 1]]), False),
        # A 3 x 3 over one denominator, two monomials beside it.
        (
            sx.Matrix(
                [
                    [x / d, y / d, 0],
                    [c1 / (a * d), 1, z / d],
                    [0, theta / d, (x + 1) / (b * d)],
                ]
            ),
            True,
        ),
        # tan is not read: the border.
        (sx.Matrix([[(x + y + z) / (a + sx.tan(q1)), 0], [0, 1]]), False),
        # Only numbers over the sum (3/(a (J + a x)^2) once expanded): dotprodsimp does not
        # read the expansion as a rational function and leaves it uncancelled (drawn by
        # hypothesis; the native path had written it over one denominator).
        (
            sx.Matrix(
                [
                    [m1 * c2 + 2 * c1 * theta, 1 / (J + a * x)],
                    [-3 / (a * (J + a * x)), -m2 * s1 - 3 * m2 * c2],
                ]
            ),
            False,
        ),
    ]


def test_chosen_determinants_are_the_borders() -> None:
    """Cancelled to a number or a monomial, either sign of Q, and the refusals."""
    with sx.using("symengine"):
        for i, (matrix, native) in enumerate(_chosen()):
            assert _agree(matrix, seed=i) == native, matrix


def test_an_infinite_entry_is_left_to_the_border() -> None:
    """An entry that is SymEngine's complex infinity (1/0 drawn at random) is no crash."""
    with sx.using("symengine"):
        x, y = sx.symbols(["x", "y"])
        matrix = sx.Matrix([[x * (sx.ONE / sx.ZERO) + 1 / (x + y), 1], [1, x]])
        found = linalg.det(matrix)
        with _border():
            assert found == linalg.det(matrix)


# ------------------------------------------------------------------ random matrices
def _draw(pick: Callable[[int], int]) -> Any:
    """A random 2 x 2 or 3 x 3 rational trigonometric matrix with sums below.

    ``pick(n)`` draws an integer in ``[0, n)`` (numpy's generator or hypothesis' draw).
    Entries are small polynomials in symbols and sines and cosines (of angle sums too),
    over one or two of a few denominators, now and then with a number or a monomial
    beside the sum and now and then squared; some denominators are not irreducible or
    not provably so, where the border must decide.
    """
    x, a, m1, m2, theta, J = sx.symbols(["x", "a", "m1", "m2", "theta", "J"])
    q1, q2 = sx.symbols(["q1", "q2"])
    atoms = [x, a, m1, m2, theta, J, sx.sin(q1), sx.cos(q1), sx.cos(q2), sx.sin(q1 + q2)]
    below = [
        m1 + m2 * sx.sin(q2) ** 2,
        m1 + m2 - m2 * sx.cos(q2) ** 2,
        a * x + J,
        2 * theta - 3 * sx.cos(q1),
        x**2 - a**2,  # (x - a)(x + a): not proved, the border
        1 + theta**2 + m1 * x,
    ]

    def polynomial(terms: int) -> Any:
        out = sx.ZERO
        for _ in range(terms):
            term = sx.Integer([-3, -1, 1, 1, 2][pick(5)])
            for _ in range(pick(3)):
                term *= atoms[pick(len(atoms))]
            out += term
        return out

    n = 2 + (pick(3) == 0)  # a 3 x 3 one time in three: SymPy takes 0.2-1.4 s on one
    first, second = below[pick(len(below))], below[pick(len(below))]
    rows = []
    for _ in range(n):
        row = []
        for _ in range(n):
            choice = pick(6)
            entry = polynomial(1 + pick(2) * (n == 2))
            if choice < 3:
                entry /= first
            elif choice == 3 and n == 2:
                entry /= second ** (1 + pick(2))
            elif choice == 4:
                entry /= sx.Rational([1, 2, 3][pick(3)], 1) * atoms[pick(6)] * first
            row.append(entry)
        rows.append(row)
    return sx.Matrix(rows)


def test_random_determinants_are_the_borders() -> None:
    """Twelve drawn matrices: most written natively, each the border's tree."""
    rng = np.random.default_rng(49)
    with sx.using("symengine"):
        taken = [_agree(_draw(lambda n: int(rng.integers(n))), seed=k) for k in range(12)]
    assert sum(taken) >= 6, taken  # the native path is exercised, not only refused


# No shrinking: a failing draw is printed whole (the matrix in the assertion).
@settings(
    max_examples=12,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow],
    phases=(Phase.explicit, Phase.reuse, Phase.generate),
)
@given(st.data())
def test_drawn_determinants_are_the_borders(data: st.DataObject) -> None:
    """Hypothesis' draws of the same family: whatever the native path writes is SymPy's."""
    with sx.using("symengine"):
        _agree(_draw(lambda n: data.draw(st.integers(0, n - 1))))
