"""The mass-matrix form ``M(q) q'' = F(q, q') + B(q) u`` as a control-affine plant.

The plant's state is ``(q, q')``; its vector field is ``f = [q'; a]``, ``G = [0; W]``
with ``a = M^-1 F`` and ``W = M^-1 B``. Those are never formed symbolically (for a
two-link arm SymPy's ``M.inv()`` takes seconds and pages, for three links minutes):
they are run-time symbols (:attr:`Mechanics.accelerations`, :attr:`Mechanics.gains`)
that generated code computes by factoring ``M`` numerically at each evaluation. Where
``M`` couples no coordinates (a team of robots), ``a_i`` and ``W_ij`` are zero unless
``F`` or ``B`` reaches ``i``'s block of ``M``: the symbols keep that sparsity.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import cast

import numpy as np

from tvopt_codegen import symbolic as sx
from tvopt_codegen.maths.jet import partial
from tvopt_codegen.maths.lie import Sampler, connected_groups
from tvopt_codegen.maths.numeric import Evaluator
from tvopt_codegen.spec.types import Mechanics


def affine_split(
    exprs: Sequence[sx.Expr], inputs: Sequence[sx.Expr]
) -> tuple[tuple[tuple[sx.Expr, ...], ...], tuple[sx.Expr, ...]]:
    """Split expressions affine in ``inputs`` into their coefficients and the rest.

    Returns
    -------
    coefficients : tuple of tuple of Expr
        ``d expr_i / d u_j``, row by row.
    rest : tuple of Expr
        Each expression at ``u = 0``.

    Raises
    ------
    ValueError
        When a coefficient depends on an input (one line, naming both).
    """
    present = set(inputs)
    # Zero of the inputs' own engine: the mechanics door splits SymPy's expressions
    # whatever the process's engine is, and must get SymPy's zero back.
    zero = {u: u * 0 for u in inputs}
    rows = []
    for i, expr in enumerate(exprs):
        row = []
        for u in inputs:
            coefficient = partial(expr, u) if u in expr.free_symbols else zero[u]
            if coefficient.free_symbols & present:
                raise ValueError(
                    f"entry {i} is not affine in the inputs: the coefficient of {u.name!r} "
                    f"depends on {sorted(s.name for s in coefficient.free_symbols & present)}"
                )
            row.append(coefficient)
        rows.append(tuple(row))
    return tuple(rows), tuple(expr.xreplace(zero) for expr in exprs)


def mechanics_of(
    coordinates: tuple[str, ...],
    rates: tuple[str, ...],
    mass: tuple[tuple[sx.Expr, ...], ...],
    forces: tuple[sx.Expr, ...],
    gain: tuple[tuple[sx.Expr, ...], ...],
    definitions: tuple[tuple[str, sx.Expr, sx.Expr], ...] = (),
) -> Mechanics:
    """The :class:`Mechanics` record with its run-time symbols (zero where structurally zero).

    ``(M^-1 v)_i`` can be nonzero only if ``v`` is nonzero somewhere in the block of
    ``M`` (connected component of its pattern) that holds ``i``.
    """
    n = len(coordinates)
    links = [(i, j) for i in range(n) for j in range(i) if mass[i][j] != 0 or mass[j][i] != 0]
    block_of = {}
    for number, group in enumerate(connected_groups(range(n), links)):
        for i in group:
            block_of[i] = number

    def reaches(column: Sequence[sx.Expr]) -> set[int]:
        return {block_of[i] for i, entry in enumerate(column) if entry != 0}

    force_blocks = reaches(forces)
    m = len(gain[0]) if gain else 0
    gain_blocks = [reaches([gain[i][j] for i in range(n)]) for j in range(m)]
    accelerations = tuple(
        sx.symbol(f"_ddq{i}") if block_of[i] in force_blocks else sx.ZERO for i in range(n)
    )
    gains = tuple(
        tuple(
            sx.symbol(f"_W{i}_{j}") if block_of[i] in gain_blocks[j] else sx.ZERO for j in range(m)
        )
        for i in range(n)
    )
    return Mechanics(
        coordinates=coordinates,
        rates=rates,
        mass_matrix=mass,
        forces=forces,
        input_matrix=gain,
        accelerations=accelerations,
        gains=gains,
        definitions=tuple((symbol, expr) for _, symbol, expr in definitions),
        definition_names=tuple(name for name, _, _ in definitions),
    )


def implicit_dynamics(mechanics: Mechanics, inputs: Sequence[str]) -> list[sx.Expr]:
    """The right-hand sides of ``(q, q')``: ``q_i' = rate_i``, ``rate_i' = a_i + W_i u``."""
    u = sx.symbols(inputs)
    rows: list[sx.Expr] = sx.symbols(mechanics.rates)
    for a, gains in zip(mechanics.accelerations, mechanics.gains, strict=True):
        rows.append(a + sx.Add(*(w * uj for w, uj in zip(gains, u, strict=True))))
    return rows


def evaluator(mechanics: Mechanics, values: Mapping[sx.Expr | str, object]) -> Evaluator:
    """An evaluator of ``values`` that also knows the mechanics' definitions.

    ``values`` may be keyed by the engine's symbols, by names, or by the other engine's
    symbols (see :func:`engine_keyed`).
    """
    evaluate = Evaluator(engine_keyed(values))
    for symbol, expr in mechanics.definitions:
        evaluate.define(symbol, expr)
    return evaluate


def engine_keyed(values: Mapping[sx.Expr | str, object]) -> Mapping[sx.Expr, object]:
    """``values`` keyed by the process engine's symbols.

    A caller's values for a spec's symbols are its own: a name (a spec's parameters are
    name-value pairs), or a symbol of either engine (a SymPy user's ``Symbol("m",
    real=True)`` while the spec's expressions are SymEngine's). Keyed by another engine's
    symbol they would match nothing, and the evaluator would name a symbol the caller
    did give a value ("no value for the symbol m"). Names and the other engine's symbols
    become the engine's real symbol of that name; the engine's own keys stay as they are.

    Raises
    ------
    TypeError
        For a key that is neither a name nor an expression of the engine nor another
        engine's symbol.
    """
    if all(isinstance(key, sx.Basic) for key in values):
        return cast("Mapping[sx.Expr, object]", values)
    keyed: dict[sx.Expr, object] = {}
    for key, value in values.items():
        if isinstance(key, str):
            keyed[sx.symbol(key)] = value
        elif isinstance(key, sx.Basic):
            keyed[key] = value
        elif getattr(key, "is_Symbol", False) is True and isinstance(
            getattr(key, "name", None), str
        ):
            keyed[sx.symbol(key.name)] = value
        else:
            raise TypeError(
                f"a value's key must be a name or a symbol, not {key!r} ({type(key).__name__})"
            )
    return keyed


def reserved(index: int) -> sx.Expr:
    """The reserved symbol of the ``index``-th definition (no spec name starts with ``_``)."""
    return sx.symbol(f"_let{index}")


def _at(evaluate: Evaluator, expr: sx.Expr, points: int) -> np.ndarray:
    value = np.asarray(evaluate(expr))
    if np.iscomplexobj(value):
        value = np.where(np.abs(value.imag) > 1e-12, np.nan, value.real)
    return np.broadcast_to(np.asarray(value, dtype=float), (points,))


def mass_matrix_at(
    mechanics: Mechanics, values: Mapping[sx.Expr | str, object], points: int = 1
) -> np.ndarray:
    """``M`` at ``points`` points (values: arrays of that length or floats), shape (P, n, n).

    ``values`` is keyed as :func:`evaluator` takes it: names or either engine's symbols.
    """
    evaluate = evaluator(mechanics, values)
    n = len(mechanics.coordinates)
    return np.stack(
        [
            np.stack([_at(evaluate, mechanics.mass_matrix[i][j], points) for j in range(n)], -1)
            for i in range(n)
        ],
        -2,
    )


def implicit_values(
    mechanics: Mechanics, values: Mapping[sx.Expr | str, object], points: int = 1
) -> dict[sx.Expr, np.ndarray]:
    """The run-time symbols' values at points: ``a = M^-1 F``, ``W = M^-1 B`` solved numerically.

    Parameters
    ----------
    mechanics : Mechanics
        The mass-matrix form.
    values : mapping of Symbol or str to array or float
        The states and parameters (arrays of length ``points``, or floats), keyed by
        name or by either engine's symbols (:func:`engine_keyed`).
    points : int
        How many points.

    Returns
    -------
    dict of Symbol to numpy.ndarray
        One array of length ``points`` per run-time symbol; NaN where ``M`` is singular
        or an entry is undefined (the callers' samplers skip such points).
    """
    return solved_at(mechanics, values, points)[0]


def solved_at(
    mechanics: Mechanics, values: Mapping[sx.Expr | str, object], points: int = 1
) -> tuple[dict[sx.Expr, np.ndarray], np.ndarray, np.ndarray]:
    """:func:`implicit_values`, with ``M`` (shape (P, n, n)) and ``[F | B]`` (P, n, m + 1).

    The matrices it solved with, for checks that need them at the same points
    (:func:`problem_at_samples`) without evaluating them again.
    """
    values = engine_keyed(values)
    evaluate = evaluator(mechanics, values)
    n = len(mechanics.coordinates)
    mass = mass_matrix_at(mechanics, values, points)
    m = len(mechanics.input_matrix[0]) if mechanics.input_matrix else 0
    rhs = np.stack(
        [
            np.stack(
                [_at(evaluate, mechanics.forces[i], points)]
                + [_at(evaluate, mechanics.input_matrix[i][j], points) for j in range(m)],
                -1,
            )
            for i in range(n)
        ],
        -2,
    ).reshape(points, n, m + 1)
    solution = np.full((points, n, m + 1), np.nan)
    for k in range(points):
        if np.all(np.isfinite(mass[k])) and np.all(np.isfinite(rhs[k])):
            try:
                solution[k] = np.linalg.solve(mass[k], rhs[k])
            except np.linalg.LinAlgError:
                pass  # singular here: NaN
    # The definitions too: M, F and B read them, and a sampler evaluating those needs them.
    out: dict[sx.Expr, np.ndarray] = {
        symbol: _at(evaluate, symbol, points) for symbol, _ in mechanics.definitions
    }
    for i in range(n):
        if mechanics.accelerations[i].is_Symbol:
            out[mechanics.accelerations[i]] = solution[:, i, 0]
        for j in range(m):
            if mechanics.gains[i][j].is_Symbol:
                out[mechanics.gains[i][j]] = solution[:, i, j + 1]
    return out, mass, rhs


def problem_at_samples(
    mechanics: Mechanics,
    mass: np.ndarray,
    rhs: np.ndarray,
    sampler: Sampler,
    tolerance: float,
) -> tuple[str, str] | None:
    """What a physics engine would refuse in ``M``, ``F``, ``B`` at the sampler's points.

    The points are those the symmetry check samples (random states and inputs, the
    parameters at their defaults), where :func:`solved_at` already evaluated ``M``,
    ``F`` and ``B``: the check costs one batched eigenvalue computation. An entry that
    is infinite at a point is refused; one that is undefined there (NaN: a square root
    or a logarithm outside its domain) is not, as the point may lie outside the
    robot's workspace. Where every entry of ``M`` is finite, ``M`` must be positive
    definite: its smallest eigenvalue above ``tolerance`` times its largest entry, as
    the generated code's LDL^T pivots must be.

    Parameters
    ----------
    mechanics : Mechanics
        The mass-matrix form, ``M`` already found symmetric.
    mass, rhs : numpy.ndarray
        ``M`` and ``[F | B]`` at the sampler's points, as :func:`solved_at` returns them.
    sampler : Sampler
        The points (its symbols and values), to name the failing one.
    tolerance : float
        The relative pivot tolerance of the generated code.

    Returns
    -------
    tuple of (str, str) or None
        The field (``system.mechanics.mass_matrix[i][j]`` where one entry is to blame)
        and a one-line problem naming the point; None when every point passes.
    """
    n = len(mechanics.coordinates)
    index = {s.name: k for k, s in enumerate(sampler.symbols)}

    def point(k: int, names: Sequence[str]) -> str:
        return ", ".join(f"{n} = {sampler.values[k, index[n]]:.4g}" for n in names if n in index)

    coordinates = mechanics.coordinates
    for k, i, j in zip(*np.nonzero(np.isinf(mass)), strict=True):
        return (
            f"system.mechanics.mass_matrix[{i}][{j}]",
            f"M[{i}][{j}] is infinite at the sample point {point(int(k), coordinates)}",
        )
    for k, i, j in zip(*np.nonzero(np.isinf(rhs)), strict=True):
        field, what, names = (
            (f"forces[{i}]", f"F[{i}]", (*coordinates, *mechanics.rates))
            if j == 0
            else (f"input_matrix[{i}][{j - 1}]", f"B[{i}][{j - 1}]", coordinates)
        )
        return (
            f"system.mechanics.{field}",
            f"{what} is infinite at the sample point {point(int(k), names)}",
        )
    defined = np.flatnonzero(np.all(np.isfinite(mass), axis=(1, 2)))
    if not defined.size:
        return None
    smallest = np.linalg.eigvalsh(mass[defined])[:, 0]
    scale = np.max(np.abs(mass[defined]), axis=(1, 2))
    failing = np.flatnonzero(~(smallest > tolerance * scale))
    if not failing.size:
        return None
    k = int(defined[failing[0]])
    where = point(k, coordinates)
    diagonal = [i for i in range(n) if not mass[k, i, i] > 0]
    if diagonal:
        i = diagonal[0]
        return (
            f"system.mechanics.mass_matrix[{i}][{i}]",
            f"M is not positive definite at the sample point {where}: M[{i}][{i}] = "
            f"{mass[k, i, i]:.6g} (a mass or an inertia must be positive)",
        )
    return (
        "system.mechanics.mass_matrix",
        f"M is not positive definite at the sample point {where}: its smallest eigenvalue "
        f"is {smallest[failing[0]]:.6g}",
    )
