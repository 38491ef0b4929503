"""Lie derivatives, dynamic extension, vector relative degree and the Brunovsky pair
(lie.py), on hand-derived systems."""

from __future__ import annotations

import sympy as sp

from tvopt_codegen import symbolic as sx
from tvopt_codegen.maths.lie import Sampler, brunovsky, extend, generic_rank, relative_degree
from tvopt_codegen.symbolic.border import to_sympy

from .conftest import derivation


def _symbols() -> tuple[sx.Expr, ...]:
    """x1, x2, theta, v, omega on the engine in use (built per test, never at import)."""
    return tuple(sx.symbols(["x1", "x2", "theta", "v", "omega"]))


def _unicycle() -> tuple[sx.Expr, sx.Expr, sx.Expr]:
    x1, x2, theta, _, _ = _symbols()
    f = sx.Matrix([0, 0, 0])
    G = sx.Matrix([[sx.cos(theta), 0], [sx.sin(theta), 0], [0, 1]])
    h = sx.Matrix([x1, x2])
    return f, G, h


def _is_zero_matrix(matrix: sx.Expr) -> bool:
    """Whether every entry of ``matrix`` expands to zero (no simplification needed)."""
    return all(sx.expand(entry) == 0 for entry in matrix)


def test_raw_unicycle_has_a_singular_decoupling_matrix() -> None:
    """y = (x1, x2): both outputs have relative degree 1, and R = [[cos, 0], [sin, 0]]."""
    x1, x2, theta, _, _ = _symbols()
    f, G, h = _unicycle()
    sampler = Sampler((x1, x2, theta), {})
    rd = relative_degree(f, G, h, (x1, x2, theta), sampler)
    assert rd.r == (1, 1)
    assert rd.R is not None
    assert _is_zero_matrix(rd.R - sx.Matrix([[sx.cos(theta), 0], [sx.sin(theta), 0]]))
    assert generic_rank(rd.R, sampler) == 1


def test_prolonged_unicycle_is_full_state_linearizable() -> None:
    """One integrator on v: states (x1, x2, theta, v), relative degrees (2, 2), det R = v."""
    x1, x2, theta, v, omega = _symbols()
    f, G, h = _unicycle()
    ext = extend((x1, x2, theta), (v, omega), f, G, {"v": 1})
    assert ext.states == ("v",) and ext.inputs == ("v_d1", "omega")
    assert ext.f == sx.Matrix([v * sx.cos(theta), v * sx.sin(theta), 0, 0])
    assert ext.G == sx.Matrix([[0, 0], [0, 0], [0, 1], [1, 0]])
    sampler = Sampler(ext.x, {})
    rd = relative_degree(ext.f, ext.G, h, ext.x, sampler)
    assert rd.r == (2, 2)
    assert rd.R is not None
    expected = sx.Matrix([[sx.cos(theta), -v * sx.sin(theta)], [sx.sin(theta), v * sx.cos(theta)]])
    assert _is_zero_matrix(rd.R - expected)
    # v cos^2 + v sin^2: only SymPy's simplify (the border) reduces it to v.
    assert sp.simplify(to_sympy(rd.R.det())) == to_sympy(v)
    # L_f h and L_f^2 h: the chains Phi is read from, and p = 0 (no drift beyond v).
    assert rd.lie[0][:3] == (x1, v * sx.cos(theta), 0)
    assert rd.lie[1][:3] == (x2, v * sx.sin(theta), 0)


def test_two_integrators_make_an_input_chain() -> None:
    x1, x2, theta, v, omega = _symbols()
    f, G, _ = _unicycle()
    ext = extend((x1, x2, theta), (v, omega), f, G, {"v": 2})
    assert ext.states == ("v", "v_d1") and ext.inputs == ("v_d2", "omega")
    v_d1 = sx.symbol("v_d1")
    assert list(ext.f)[3:] == [v_d1, 0]
    assert ext.G[4, 0] == 1 and ext.G[3, 0] == 0


def test_brunovsky_pair_of_non_uniform_degrees() -> None:
    A, B = brunovsky((1, 3))
    assert A == sx.Matrix([[0, 0, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1], [0, 0, 0, 0]])
    assert B == sx.Matrix([[1, 0], [0, 0], [0, 0], [0, 1]])


def test_derivation_reads_r_p_and_phi_from_the_lie_chains() -> None:
    x1, x2, theta, v, _ = _symbols()
    d = derivation("unicycle_switch")
    assert d.linearization.relative_degree == (2, 2)
    assert d.closed_loop.state_names == ("x1", "x2", "theta", "v")
    assert d.decoupling.det_R == v
    assert d.decoupling.singular_set == ("v = 0",)
    assert d.decoupling.p == sx.Matrix([0, 0])
    assert list(d.decoupling.phi) == [x1, v * sx.cos(theta), x2, v * sx.sin(theta)]
    assert d.decoupling.A == sx.Matrix([[0, 1, 0, 0], [0, 0, 0, 0], [0, 0, 0, 1], [0, 0, 0, 0]])
    assert d.decoupling.B == sx.Matrix([[0, 0], [1, 0], [0, 0], [0, 1]])
    assert d.dynamics.uniform and d.dynamics.k == 2 and d.closed_loop.padding == ((), ())


def test_generic_rank_by_blocks_is_the_rank_of_the_whole_matrix() -> None:
    """Rank block by block (a team's R) against numpy's rank of the whole matrix at each
    sample: shuffled block patterns, blocks that lose rank everywhere or at some points
    only, a scale that sets the tolerance, entries undefined at some samples."""
    import random

    import numpy as np

    a, b, c = sx.symbols(["a", "b", "c"])
    sampler = Sampler((a, b, c), {})
    pieces = [a, sx.cos(b), a * b - 1, sx.sqrt(c), sx.log(a), 3 * a, sx.real(1e12) * b, c**2, b]
    rng = random.Random(3)

    def reference(matrix: sx.Expr) -> int:
        rows, cols = matrix.shape
        values = np.zeros((len(sampler.values), rows, cols))
        for i in range(rows):
            for j in range(cols):
                if matrix[i, j] != 0:
                    values[:, i, j] = sampler.evaluate(matrix[i, j])
        ranks = [
            int(np.linalg.matrix_rank(point, tol=1e-9 * max(1.0, np.abs(point).max())))
            for point in values
            if np.all(np.isfinite(point))
        ]
        return max(ranks, default=0)

    seen = set()
    for _ in range(60):
        size = rng.randint(1, 8)
        matrix = sx.zeros(size, size)
        for _ in range(rng.randint(0, 3 * size)):
            matrix[rng.randrange(size), rng.randrange(size)] = rng.choice(pieces)
        if size > 1 and rng.random() < 0.5:  # a row that is a multiple of another
            matrix[1, :] = 2 * matrix[0, :]
        rows, cols = list(range(size)), list(range(size))
        rng.shuffle(rows)
        rng.shuffle(cols)
        shuffled = sx.Matrix([[matrix[i, j] for j in cols] for i in rows])
        want = reference(shuffled)
        seen.add(want)
        assert generic_rank(shuffled, sampler) == want, shuffled
    assert len(seen) >= 6
    # Undefined everywhere in one block: no sample counts, whatever the other blocks.
    undefined = sx.Matrix([[a, 0, 0], [0, b, 1], [0, sx.log(-(a**2) - 1), 2]])
    assert reference(undefined) == 0
    assert generic_rank(undefined, sampler) == 0


def test_a_teams_decoupling_matrix_is_the_dense_formulas() -> None:
    """Three prolonged unicycles with coupled drift and non-uniform degrees: R and the
    Lie chains read from sparse rows equal the textbook dense formula
    R[i] = d(L_f^(r_i - 1) h_i)/dx G, and R's zeros are exact zeros."""
    xs = sx.symbols([f"{name}{i}" for name in ("a", "b", "th", "v") for i in range(3)])
    a, b, th, vv = xs[0:3], xs[3:6], xs[6:9], xs[9:12]
    w = sx.symbols([f"w{i}" for i in range(3)])
    x = (*a, *b, *th)
    # Each agent drifts towards the next one: f couples the team.
    f = sx.Matrix(
        [0.1 * (a[(i + 1) % 3] - a[i]) for i in range(3)]
        + [0.1 * (b[(i + 1) % 3] - b[i]) for i in range(3)]
        + [0, 0, 0]
    )
    G = sx.zeros(9, 6)
    for i in range(3):
        G[i, i] = sx.cos(th[i])
        G[3 + i, i] = sx.sin(th[i])
        G[6 + i, 3 + i] = 1
    ext = extend(x, (*vv, *w), f, G, {f"v{i}": 1 for i in range(3)})
    # Outputs of two relative degrees: positions (2) and one heading (1).
    h = sx.Matrix([a[0], b[0], a[1], b[1], a[2], th[2]])
    sampler = Sampler(ext.x, {})
    rd = relative_degree(ext.f, ext.G, h, ext.x, sampler)
    assert rd.r == (2, 2, 2, 2, 2, 1)
    assert rd.R is not None and rd.R.shape == (6, 6)
    state = sx.Matrix(ext.x)
    for i, r in enumerate(rd.r):
        lie = h[i]
        for _ in range(r - 1):
            lie = (sx.Matrix([lie]).jacobian(state) * ext.f)[0]
        row = sx.Matrix([lie]).jacobian(state) * ext.G
        assert sx.expand(rd.lie[i][r - 1] - lie) == 0
        for j in range(6):
            assert sx.expand(rd.R[i, j] - row[j]) == 0, (i, j)
            # Exact zeros: R holds none where the dense formula is not identically zero.
            assert (rd.R[i, j] == 0) == (sp.simplify(to_sympy(row[j])) == 0)
    assert generic_rank(rd.R, sampler) == 6
