"""The dynamics of the chain, symbolically: the recursive Newton-Euler algorithm.

The bias ``C(q, q') q' + g(q)`` is one pass at zero joint acceleration, column ``j`` of
``M`` one pass at unit acceleration of joint ``j`` without velocity and gravity: algebra
on rotations and cross products, never a derivative and never an inverse. Every vector a
pass forms is named (:class:`_Lets`, the spec's ``definitions``), so that each stays a
few operations long.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import sympy as sp

from tvopt_codegen.urdf.chain import _Body


class _NameTakenError(Exception):
    """A definition's name is a joint's or link's spec name (args: the owner, the problem)."""


class _Lets:
    """Named intermediate values, the spec's ``definitions``.

    Each non-trivial expression the algorithm forms gets a name, so that every one stays
    a few operations long.
    """

    def __init__(self, owners: Mapping[str, str]) -> None:
        self.items: list[tuple[str, sp.Expr]] = []
        self.owners = dict(owners)  # casefolded name: the URDF element that made it

    def __call__(self, name: str, expr: sp.Expr) -> sp.Expr:
        expr = sp.sympify(expr)
        if expr.is_Atom or (
            expr.is_Mul and len(expr.args) == 2 and expr.args[0].is_Number and expr.args[1].is_Atom
        ):
            return expr
        owner = self.owners.get(name.casefold())
        if owner is not None:
            raise _NameTakenError(
                owner,
                f"its spec name is {name!r}, which the import also gives one of its "
                "definitions: rename it",
            )
        self.owners[name.casefold()] = "an intermediate"
        self.items.append((name, expr))
        return sp.Symbol(name, real=True)

    def vector(self, name: str, vector: Sequence[sp.Expr]) -> tuple[sp.Expr, sp.Expr, sp.Expr]:
        x, y, z = (self(f"{name}{axis}", e) for axis, e in zip("xyz", vector, strict=True))
        return (x, y, z)


def _rodrigues(axis: sp.Matrix, c: sp.Expr, s: sp.Expr) -> sp.Matrix:
    """The rotation about the unit ``axis`` by the angle whose cosine and sine are given."""
    x, y, z = axis
    cross = sp.Matrix([[0, -z, y], [z, 0, -x], [-y, x, 0]])
    outer = axis * axis.T
    return c * sp.eye(3) + s * cross + (1 - c) * outer


def _placements(
    bodies: Sequence[_Body],
    q: Sequence[sp.Expr],
    trig: Sequence[tuple[sp.Expr, sp.Expr]] | None = None,
) -> list[tuple[sp.Matrix, sp.Matrix]]:
    """Each body's frame in its parent's: the rotation ``E`` and the origin ``p``.

    ``trig`` gives each coordinate's cosine and sine (names of definitions); by default
    ``cos(q)`` and ``sin(q)`` themselves.
    """
    out = []
    for body in bodies:
        if body.kind == "revolute":
            i = body.coordinate
            c, s = trig[i] if trig is not None else (sp.cos(q[i]), sp.sin(q[i]))
            rotation = body.rotation * _rodrigues(body.axis, c, s)
            offset = body.offset
        elif body.kind == "prismatic":
            rotation = body.rotation
            offset = body.offset + body.rotation * body.axis * q[body.coordinate]
        else:
            rotation, offset = body.rotation, body.offset
        out.append((rotation, offset))
    return out


#: A vector or a matrix's rows, as the passes hold them: ``sp.Matrix`` arithmetic costs
#: more in its bookkeeping (domains, sparse dictionaries, checks for infinities) than in
#: the algebra.
_Vector = tuple[sp.Expr, sp.Expr, sp.Expr]
_Rows = tuple[_Vector, _Vector, _Vector]

_ZERO = sp.S.Zero


def _is_zero(e: sp.Expr) -> bool:
    """An exact zero: what ``sp.Matrix`` leaves out of its sparse entries."""
    return bool(e.is_Number and e == 0)


def _times(a: sp.Expr, b: sp.Expr) -> sp.Expr:
    """``a * b``, an exact zero's product known without forming it."""
    return _ZERO if _is_zero(a) or _is_zero(b) else a * b


def _plus(a: sp.Expr, b: sp.Expr) -> sp.Expr:
    """``a + b``: SymPy drops an exact zero from a sum, so the sum is the other term."""
    if _is_zero(a):
        return b
    return a if _is_zero(b) else a + b


def _minus(a: sp.Expr, b: sp.Expr) -> sp.Expr:
    if _is_zero(b):
        return a
    return -b if _is_zero(a) else a - b


def _add(u: _Vector, v: _Vector) -> _Vector:
    """``u + v`` as ``sp.Matrix`` forms it (its nonzero entries added)."""
    return (_plus(u[0], v[0]), _plus(u[1], v[1]), _plus(u[2], v[2]))


def _scale(u: _Vector, c: sp.Expr, *, left: bool) -> _Vector:
    """``c * u`` (``left``) or ``u * c``, as ``sp.Matrix`` forms it: by 0 or 1 at once."""
    if _is_zero(c):
        return (_ZERO, _ZERO, _ZERO)
    if c.is_Number and c == 1:
        return u
    x, y, z = (_ZERO if _is_zero(e) else (c * e if left else e * c) for e in u)
    return (x, y, z)


def _cross(a: _Vector, b: _Vector) -> _Vector:
    """``a.cross(b)``, by ``sp.Matrix.cross``'s operations."""
    return (
        _minus(_times(a[1], b[2]), _times(a[2], b[1])),
        _minus(_times(a[2], b[0]), _times(a[0], b[2])),
        _minus(_times(a[0], b[1]), _times(a[1], b[0])),
    )


def _dot(row: _Vector, u: _Vector) -> sp.Expr:
    """A row of a matrix product as ``sp.Matrix`` sums it.

    The products of nonzero entries, in order, in one ``Add``.
    """
    terms = [a * b for a, b in zip(row, u, strict=True) if not (_is_zero(a) or _is_zero(b))]
    return sp.Add(*terms) if terms else _ZERO


def _apply(rows: _Rows, u: _Vector) -> _Vector:
    return (_dot(rows[0], u), _dot(rows[1], u), _dot(rows[2], u))


def _rows(matrix: sp.Matrix) -> _Rows:
    return tuple(tuple(matrix[i, j] for j in range(3)) for i in range(3))  # type: ignore[return-value]


def _vector(matrix: sp.Matrix) -> _Vector:
    return (matrix[0], matrix[1], matrix[2])


def _newton_euler(
    bodies: Sequence[_Body],
    placements: Sequence[tuple[sp.Matrix, sp.Matrix]],
    dq: Sequence[sp.Expr],
    ddq: Sequence[sp.Expr],
    gravity: sp.Matrix,
    let: _Lets,
    tag: str,
) -> list[sp.Expr]:
    """The joint forces of the recursive Newton-Euler algorithm, in body frames.

    Every vector it forms is named (``let``; ``tag`` ends each name): angular velocity
    ``om``, angular and linear acceleration ``al`` and ``ac``, and the force and torque
    ``fo`` and ``to`` that each body passes to its parent.

    The vectors are tuples, each formed by the operations ``sp.Matrix`` would apply to
    its entries, in the same order (see :func:`_dot`, :func:`_add`), so that every
    expression, and the spec's text, is the one the matrices gave.
    """
    zero: _Vector = (_ZERO, _ZERO, _ZERO)
    frames = [(_rows(E), _rows(E.T), _vector(p)) for E, p in placements]
    axes = [_vector(body.axis) for body in bodies]
    omega: list[_Vector] = []
    alpha: list[_Vector] = []
    accel: list[_Vector] = []
    for number, (body, (_, back, p), axis) in enumerate(
        zip(bodies, frames, axes, strict=True), start=1
    ):
        if body.parent < 0:
            w0, a0 = zero, zero
            v0 = _scale(_vector(gravity), sp.S.NegativeOne, left=True)
        else:
            w0, a0, v0 = omega[body.parent], alpha[body.parent], accel[body.parent]
        carried = _apply(back, w0)
        linear = _apply(back, _add(_add(v0, _cross(a0, p)), _cross(w0, _cross(w0, p))))
        angular = _apply(back, a0)
        if body.kind == "revolute":
            spin = _scale(axis, dq[body.coordinate], left=False)
            w = _add(carried, spin)
            angular = _add(
                _add(angular, _scale(axis, ddq[body.coordinate], left=False)),
                _cross(carried, spin),
            )
        else:
            w = carried
            if body.kind == "prismatic":
                slide = _scale(axis, dq[body.coordinate], left=False)
                linear = _add(
                    _add(linear, _scale(_cross(carried, slide), sp.Integer(2), left=True)),
                    _scale(axis, ddq[body.coordinate], left=False),
                )
        # The velocities are those of the bias pass alone (the mass matrix's have none).
        omega.append(let.vector(f"om{number}", w) if any(e != 0 for e in w) else w)
        alpha.append(let.vector(f"al{number}{tag}", angular))
        accel.append(let.vector(f"ac{number}{tag}", linear))
    force: list[_Vector] = []
    torque: list[_Vector] = []
    for body, w, a, v in zip(bodies, omega, alpha, accel, strict=True):
        com, inertia = _vector(body.com), _rows(body.inertia)
        centre = _add(_add(v, _cross(a, com)), _cross(w, _cross(w, com)))
        f = _scale(centre, body.mass, left=True)
        force.append(f)
        torque.append(_add(_add(_apply(inertia, a), _cross(w, _apply(inertia, w))), _cross(com, f)))
    for index in reversed(range(len(bodies))):
        force[index] = let.vector(f"fo{index + 1}{tag}", force[index])
        torque[index] = let.vector(f"to{index + 1}{tag}", torque[index])
        parent = bodies[index].parent
        if parent >= 0:
            there, _, p = frames[index]
            moved = _apply(there, force[index])
            force[parent] = _add(force[parent], moved)
            torque[parent] = _add(
                _add(torque[parent], _apply(there, torque[index])), _cross(p, moved)
            )
    out: list[sp.Expr] = [sp.Integer(0)] * len(dq)
    for body, axis, f, n in zip(bodies, axes, force, torque, strict=True):
        if body.kind == "revolute":
            out[body.coordinate] = _dot(axis, n)
        elif body.kind == "prismatic":
            out[body.coordinate] = _dot(axis, f)
    return out


def _position(
    bodies: Sequence[_Body], placements: Sequence[tuple[sp.Matrix, sp.Matrix]], link: str
) -> sp.Matrix:
    """The origin of ``link``'s frame in the base frame."""
    index = next(i for i, body in enumerate(bodies) if body.link == link)
    position = sp.zeros(3, 1)
    while index >= 0:
        E, p = placements[index]
        position = E * position + p
        index = bodies[index].parent
    return position


class _UnprintedError(Exception):
    """An expression outside what :class:`_Printer` prints as ``sp.sstr`` would."""


#: Most sort keys and float texts :class:`_Printer` keeps between calls.
_REMEMBERED = 100_000


class _Printer:
    """``sp.sstr`` for what an import prints, at a fraction of its cost.

    The import's expressions are sums of products of numbers, symbols, integer powers of
    symbols, cosines and sines, and sums; SymPy's printer spends most of its time there
    rebuilding each negative product and asking its assumptions again. This one follows
    the same rules (the order of the terms and factors, the sign taken out of a product,
    the parentheses, a float's digits by the printer's own method) without them, and
    gives up (:class:`_UnprintedError`) on anything else, which :func:`_text` then leaves to
    ``sp.sstr``: the spec text is the same to the byte.
    """

    def __init__(self) -> None:
        self.floats: dict[tuple[object, int], str] = {}
        self.keys: dict[sp.Expr, Any] = {}
        # Nested below the top: ``full_prec="auto"`` strips a float's trailing zeros there.
        self.sympy = sp.printing.str.StrPrinter()
        self.sympy._print_level = 2

    def __call__(self, expr: sp.Expr) -> str:
        if len(self.keys) + len(self.floats) > _REMEMBERED:
            # A long-lived process (a fuzzer, a test worker) imports robot after robot.
            self.keys.clear()
            self.floats.clear()
        if expr.is_Symbol:
            return str(expr.name)
        if expr.is_Add or expr.is_Mul or expr.is_Pow or expr.is_Function:
            return self.nested(expr)
        raise _UnprintedError

    def nested(self, expr: sp.Expr) -> str:
        if expr.is_Symbol:
            return str(expr.name)
        if expr.is_Mul:
            return self.product(expr)
        if expr.is_Add:
            return self.sum(expr)
        if expr.is_Float:
            key = (expr._mpf_, expr._prec)
            text = self.floats.get(key)
            if text is None:
                text = self.floats[key] = str(self.sympy._print_Float(expr))
            return text
        if expr.is_Integer:
            return str(expr.p)
        if expr.is_Pow:
            base, exp = expr.args
            if base.is_Symbol and exp.is_Integer and exp.p > 1:
                return f"{base.name}**{exp.p}"
            raise _UnprintedError
        if isinstance(expr, (sp.cos, sp.sin)) and expr.args[0].is_Symbol:
            return f"{type(expr).__name__}({expr.args[0].name})"
        raise _UnprintedError

    def key(self, expr: sp.Expr) -> Any:
        key = self.keys.get(expr)
        if key is None:
            key = self.keys[expr] = expr.sort_key()
        return key

    def terms(self, expr: sp.Expr) -> list[sp.Expr]:
        """``expr.as_ordered_terms()``, without its complex coefficients.

        SymPy sorts the terms by their monomials in the sorted generators (the factors
        other than the coefficient, each with its integer power), then by coefficient: in
        a sum whose monomials differ, as here, the monomials alone decide.
        """
        args = expr.args
        if len(args) == 2:
            # as_ordered_terms' own case: a positive number and a product of a negative
            # number and one factor, the number first.
            number, other = (args[0], args[1]) if args[0].is_Number else (args[1], args[0])
            if (
                number.is_Number
                and other.is_Mul
                and len(other.args) == 2
                and other.args[0].is_Number
                and number.is_positive
                and other.args[0].is_negative
            ):
                return [number, other]
        powers: list[dict[sp.Expr, int]] = []
        generators: set[sp.Expr] = set()
        for term in args:
            coefficient, rest = term.as_coeff_Mul()
            if not coefficient.is_Number:
                raise _UnprintedError
            power: dict[sp.Expr, int] = {}
            if rest is not sp.S.One:
                for factor in rest.args if rest.is_Mul else (rest,):
                    if (
                        factor.is_Symbol
                        or (factor.is_Add and not factor.is_number)
                        or (isinstance(factor, (sp.cos, sp.sin)) and factor.args[0].is_Symbol)
                    ):
                        base, exponent = factor, 1
                    elif factor.is_Pow and factor.args[0].is_Symbol and factor.args[1].is_Integer:
                        base, exponent = factor.args[0], int(factor.args[1].p)
                    else:
                        raise _UnprintedError
                    power[base] = exponent
                    generators.add(base)
            powers.append(power)
        order = sorted(generators, key=self.key)
        monomials = [tuple(-power.get(g, 0) for g in order) for power in powers]
        if len(set(monomials)) != len(monomials):
            raise _UnprintedError
        return [term for _, term in sorted(zip(monomials, args, strict=True), key=lambda p: p[0])]

    def sum(self, expr: sp.Expr) -> str:
        parts: list[str] = []
        for term in self.terms(expr):
            if term.is_Add:
                raise _UnprintedError
            text = self.nested(term)
            if text.startswith("-"):
                parts += ["-", text[1:]]
            else:
                parts += ["+", text]
        return ("" if parts[0] == "+" else "-") + " ".join(parts[1:])

    def product(self, expr: sp.Expr) -> str:
        args = expr.args
        if args[0] is sp.S.One or any(
            a.is_Number or (a.is_Pow and all(x.is_Integer for x in a.args)) for a in args[1:]
        ):
            raise _UnprintedError  # StrPrinter prints it as an unevaluated product
        coefficient, rest = expr.as_coeff_Mul()
        sign = ""
        factors: list[sp.Expr]
        if coefficient.is_negative:
            # _keep_coeff(-c, rest) as StrPrinter forms it, then its factors in order.
            sign = "-"
            positive = -coefficient
            if positive is sp.S.One:
                factors = list(rest.args) if rest.is_Mul else [rest]
            elif rest.is_Mul:
                factors = [positive, *rest.args]
            elif rest.is_Add or rest.is_Number:
                raise _UnprintedError
            else:
                factors = [positive, rest]
        else:
            factors = list(args)
        if len(factors) > 1:
            factors.sort(key=self.key)
        texts: list[str] = []
        for factor in factors:
            if factor.is_Rational:
                if not factor.is_Integer:
                    raise _UnprintedError
                if factor.p != 1:
                    texts.append(str(factor.p))
            elif factor.is_Add:
                texts.append(f"({self.sum(factor)})")
            elif factor.is_Pow and not (factor.exp.is_Integer and factor.exp.p > 1):
                raise _UnprintedError
            else:
                if not factor.is_commutative:
                    raise _UnprintedError
                texts.append(self.nested(factor))
        return sign + ("*".join(texts) if texts else "1")


_PRINTER = _Printer()


def _text(expr: sp.Expr) -> str:
    """An expression as spec text: ``sp.sstr``'s, by :class:`_Printer` where it can."""
    try:
        return _PRINTER(expr)
    except _UnprintedError:
        return str(sp.sstr(expr))
