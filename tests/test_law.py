"""The law as data (tvopt_codegen.derivation.law) against the paper's formulas, term by term."""

from __future__ import annotations

import numpy as np
import pytest
import sympy as sp

from tvopt_codegen.derivation.law import diagonal_blocks, symmetric_dense

from .conftest import ALL_SPECS, SPECS, derivation


def test_padded_output_takes_its_first_padding_state_as_v() -> None:
    d = derivation(str(SPECS / "nonuniform.toml"))
    law = d.law
    xi = sp.Symbol("xi_y1_1", real=True)
    # Output y1 has relative degree 1 < k = 2: v_1 is the padding state, v_2 is y_imp''.
    assert law.v == (xi, law.z[1])
    # The padding chain ends in z: xi' = y_imp^(k) of that output.
    assert law.closed_loop[-1] == law.z[0]
    assert len(law.closed_loop) == len(d.closed_loop.state_names)


@pytest.mark.parametrize("spec", ALL_SPECS)
def test_closed_loop_field_is_f_plus_g_w(spec: str) -> None:
    d = derivation(spec)
    law, ext = d.law, d.linearization.extension
    w = sp.Matrix(law.w)
    dense = ext.f + ext.G * w
    n_ext = ext.G.shape[0]
    for i in range(n_ext):
        assert sp.expand(law.closed_loop[i] - dense[i]) == 0, i
    # A prolonged input is its extension state; every other plant input is w.
    for j, u in enumerate(d.model.u):
        expected = u if u.name in ext.states else law.w[j]
        assert law.plant_input[j] == expected


@pytest.mark.parametrize("spec", ALL_SPECS)
def test_jet_rhs_and_the_constant_inverse(spec: str) -> None:
    d = derivation(spec)
    # m: the outputs, and with equality constraints the multipliers after them.
    law, m, k = d.law, d.jet.n_kkt, d.dynamics.k
    # Integral action: one more coefficient, a_0 on the integral of grad f0.
    shift = 1 if d.closed_loop.integral_states else 0
    assert len(law.jet_rhs) == m and len(law.a) == k + shift
    states = dict(zip(d.closed_loop.state_names, d.closed_loop.states, strict=True))
    for i in range(m):
        expected = (
            sum((law.a[j + shift] * d.jet.grad_jet[j][i] for j in range(k)), sp.Integer(0))
            - d.jet.rest[i]
        )
        if shift:
            expected += law.a[0] * states[d.closed_loop.integral_states[i]]
        assert sp.expand(law.jet_rhs[i] - expected) == 0
    hessian = sp.Matrix(m, m, law.hessian)
    assert hessian == hessian.T
    # Every nonzero entry of the lower triangle is stored, and the diagonal always.
    for i in range(m):
        for j in range(i + 1):
            if hessian[i, j] != 0:
                assert (i, j) in law.hessian_pattern
    assert all((i, i) in law.hessian_pattern for i in range(m)) or law.constant_hessian
    if law.constant_hessian:
        assert law.y_imp is not None
        # Exact: Hess y_imp - jet_rhs is zero as an expression, not to rounding.
        residual = hessian * sp.Matrix(law.y_imp) - sp.Matrix(law.jet_rhs)
        assert all(sp.expand(e) == 0 for e in residual)
    else:
        assert law.y_imp is None


@pytest.mark.parametrize("spec", ALL_SPECS)
def test_r_blocks_hold_every_nonzero_entry_once(spec: str) -> None:
    d = derivation(spec)
    law, m = d.law, len(d.model.u)
    assert sorted(i for block in law.r_blocks for i in block) == list(range(m))
    rebuilt = sp.zeros(m, m)
    entries = iter(law.r_entries)
    for block in law.r_blocks:
        for i in block:
            for j in block:
                rebuilt[i, j] = next(entries)
    assert next(entries, None) is None
    assert rebuilt == d.linearization.R


def test_diagonal_blocks_are_connected_components() -> None:
    x = sp.Symbol("x")
    matrix = sp.Matrix(
        [
            [1, 0, 0, x, 0],
            [0, 1, 0, 0, 0],
            [0, 0, 1, 0, 2],
            [0, 0, 0, 1, 0],
            [0, 0, 3, 0, 1],
        ]
    )
    # (0, 3) through an entry above the diagonal, (2, 4) through both; 1 alone.
    assert diagonal_blocks(matrix) == ((0, 3), (1,), (2, 4))
    assert diagonal_blocks(sp.eye(3)) == ((0,), (1,), (2,))
    full = sp.Matrix(np.ones((3, 3), dtype=int))
    assert diagonal_blocks(full) == ((0, 1, 2),)


def test_symmetric_dense_mirrors_the_lower_entries_and_fills_zeros() -> None:
    a, b, c = sp.symbols("a b c", real=True)
    entries = [((0, 0), a), ((2, 0), b), ((2, 2), c), ((3, 1), sp.Integer(4))]
    dense = symmetric_dense(entries, 4)
    lower = dict(entries)
    assert dense == tuple(
        lower.get((max(i, j), min(i, j)), sp.S.Zero) for i in range(4) for j in range(4)
    )
    assert sp.Matrix(4, 4, dense).is_symmetric() and dense.count(0) == 10
