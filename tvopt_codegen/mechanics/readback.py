"""The last check of :func:`~tvopt_codegen.mechanics.spec_from_sympy`: the spec reads back.

The spec mapping is read by the project's own reader (and written as TOML and read
again), and every expression it reads (of the process's engine, brought to SymPy at the
border) is compared with the one that was written: equal as trees, else equal at random
points. A difference is one
:class:`~tvopt_codegen.errors.SpecError` naming the field, and no spec is returned.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import sympy as sp

from tvopt_codegen.errors import clip
from tvopt_codegen.maths.numeric import Evaluator
from tvopt_codegen.mechanics.language import SOURCE_SYMPY, _fail
from tvopt_codegen.mechanics.toml_text import spec_toml
from tvopt_codegen.symbolic.border import from_sympy, to_sympy


def _rational(expr: sp.Expr) -> sp.Expr:
    """``expr`` with each float as the exact decimal the reader makes of it."""
    floats = expr.atoms(sp.Float)
    if not floats:
        return expr
    return expr.xreplace({f: sp.Rational(repr(float(f))) for f in floats})


def _same(ours: sp.Expr, read: sp.Expr) -> bool:
    """Whether the reader's expression is ours: structurally, else at random points.

    Evaluated, not simplified: a nonzero difference at a random point is a proof, and
    simplify on a robot's forcing takes minutes.
    """
    ours = _rational(ours)
    if ours == read:
        return True
    symbols = sorted(ours.free_symbols | read.free_symbols, key=str)
    rng = np.random.default_rng(20191127)
    points = 6
    values = {
        s: rng.uniform(0.3, 1.7, points) * np.where(rng.uniform(size=points) < 0.5, -1, 1)
        for s in symbols
    }
    # The evaluator reads the engine's expressions: SymPy's, or ours brought over.
    memo: dict[Any, Any] = {}
    evaluate = Evaluator({from_sympy(s, memo): v for s, v in values.items()})
    a = np.broadcast_to(np.asarray(evaluate(from_sympy(ours, memo)), dtype=complex), (points,))
    b = np.broadcast_to(np.asarray(evaluate(from_sympy(read, memo)), dtype=complex), (points,))
    defined = np.isfinite(a) & np.isfinite(b)
    if not np.array_equal(np.isfinite(a), np.isfinite(b)):
        return False
    if not defined.any():
        return True  # undefined at every point, both: no simplify (minutes on a robot)
    scale = max(1.0, float(np.max(np.abs(a[defined]))))
    return bool(np.all(np.abs(a[defined] - b[defined]) <= 1e-9 * scale))


def _reads_back(
    spec: dict[str, Any],
    mass: list[list[sp.Expr]],
    forces: Sequence[sp.Expr],
    gain: Sequence[Sequence[sp.Expr]],
    outputs: Mapping[str, sp.Expr | str],
) -> None:
    """The spec, read by the project's own reader (and through TOML), is what we built."""
    from tvopt_codegen.spec import spec_from_dict  # noqa: PLC0415 - the reader imports much

    read = spec_from_dict(spec, source=SOURCE_SYMPY)
    spec_toml(spec)  # raises if the TOML would not read back as this mapping
    mech = read.mechanics
    assert mech is not None
    # The reader builds the engine's expressions; ours are SymPy's (identity on SymPy).
    memo: dict[Any, Any] = {}

    def sympy_of(expr: Any) -> sp.Expr:
        return to_sympy(expr, memo)

    pairs: list[tuple[str, sp.Expr, sp.Expr]] = []
    for i, row in enumerate(mass):
        for j, entry in enumerate(row):
            pairs.append((f"mass_matrix[{i}][{j}]", entry, sympy_of(mech.mass_matrix[i][j])))
    for i, entry in enumerate(forces):
        pairs.append((f"forces[{i}]", entry, sympy_of(mech.forces[i])))
    for i, gains in enumerate(gain):
        for j, entry in enumerate(gains):
            pairs.append((f"input_matrix[{i}][{j}]", entry, sympy_of(mech.input_matrix[i][j])))
    for where, ours, theirs in pairs:
        if not _same(ours, theirs):
            raise _fail(
                f"system.mechanics.{where}",
                f"{clip(sp.sstr(ours))} would read back as {clip(sp.sstr(theirs))}",
            )
    for (key, value), read_output in zip(outputs.items(), read.output_exprs, strict=True):
        read_expr = sympy_of(read_output)
        if not isinstance(value, str) and not _same(value, read_expr):
            raise _fail(
                f"system.outputs.{key}",
                f"{clip(sp.sstr(value))} would read back as {clip(sp.sstr(read_expr))}",
            )
