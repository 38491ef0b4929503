"""What SymPy folds while it builds a spec's expression, done alike on SymEngine.

SymPy evaluates as it builds: ``sqrt(8) - 2*sqrt(2)`` is 0, ``2*(x + 1)`` is
``2*x + 2``, ``atanh(1)`` is ``oo`` and ``0**(-x)`` is ``zoo**x``. SymEngine keeps such
forms, so a spec SymPy refuses (a division by zero, an undefined value) would pass on
SymEngine. :func:`_is_zero`, :func:`_distributed`, :func:`_zero_to_the` and
:func:`_at_a_pole` make the parser refuse the same specs on both engines;
:func:`_trig_of_pi_multiple` gives SymPy's own ``sin``, ``cos`` or ``tan`` of pi times a
symbol without the assumptions it would ask (most of loading a team's spec).

Its own module because it is a concern of its own: :mod:`.parse` decides what a spec
may write, this decides what each engine makes of it. It is where the two engines
differ at parse time, and where the parser crosses the border into SymPy (for one small
expression at a time).
"""

from __future__ import annotations

import cmath
from collections.abc import Callable

from tvopt_codegen import symbolic as sx

_Builder = Callable[..., sx.Expr]


def _zero_to_the(exponent: sx.Expr) -> sx.Expr:
    """``0**exponent`` as SymPy has it (``zoo**x`` for ``0**(-x)``), on SymEngine.

    SymPy asks the exponent's sign of its assumptions, which SymEngine has not: the one
    expression no sane spec holds crosses the border, so that both engines refuse it.
    """
    from tvopt_codegen.symbolic.border import from_sympy, to_sympy  # noqa: PLC0415

    zero = sx.ZERO
    return from_sympy(to_sympy(zero) ** to_sympy(exponent))


#: Where :func:`_is_zero` evaluates an expression: one value per symbol in name order,
#: irrational-looking so that no spec's own constant sits there.
_PROBE = (0.5772156649015329, 0.6180339887498949)


def _is_zero(value: sx.Expr) -> bool:
    """Whether ``value`` is zero as SymPy would have built it.

    SymPy folds while it builds (``sqrt(8)`` is ``2*sqrt(2)``, ``exp(log(2))`` is 2), so
    ``sqrt(8) - 2*sqrt(2)`` is 0 there, SymEngine keeps it: on SymEngine a value that is
    nearly zero at a fixed point is rebuilt in SymPy (the border, for that one small
    expression) and asked; anything else is not zero, as on SymPy.
    """
    if value == 0:
        return True
    if not sx.SYMENGINE:
        return False
    names = sorted(value.free_symbols, key=str)
    point = {s: sx.real(_PROBE[0] + _PROBE[1] * k) for k, s in enumerate(names)}
    try:
        number = complex((value.subs(point) if point else value).n())
    except (TypeError, ValueError, RuntimeError, ZeroDivisionError):
        return False
    if not cmath.isfinite(number) or abs(number) > 1e-9:
        return False
    from tvopt_codegen.symbolic.border import to_sympy  # noqa: PLC0415

    return bool(to_sympy(value) == 0)


def _distributed(value: sx.Expr) -> sx.Expr:
    """A number times a sum as SymPy writes it, the number multiplying each term.

    SymPy distributes ``2*(x + 1)``, ``-(x + 1)`` and ``(x + 1)/2`` when it builds them
    (its canonical form); SymEngine keeps the product. The parser does it on SymEngine
    too, so that what SymPy's form cancels (``2*(x + 1) - 2*x - 2`` is 0, and dividing
    by it is refused) cancels on both. Only a product of exactly a rational and a sum,
    as SymPy's rule.
    """
    if not sx.SYMENGINE or not value.is_Mul:
        return value
    args = value.args
    if len(args) != 2:
        return value
    number, other = (args[0], args[1]) if args[0].is_Number else (args[1], args[0])
    if not number.is_Rational or not other.is_Add:
        return value
    return sx.Add(*(number * term for term in other.args))


def _at_a_pole(name: str, args: list[sx.Expr]) -> bool:
    """Whether a function is infinite at these arguments where SymEngine does not say so.

    SymPy evaluates ``atanh(1)`` to ``oo`` and ``atan(I)`` to ``I*oo`` (refused as
    undefined); SymEngine keeps them unevaluated: asked here, on SymEngine only.
    """
    if not sx.SYMENGINE or name not in ("atanh", "atan"):
        return False
    poles = (sx.ONE, -sx.ONE) if name == "atanh" else (sx.I, -sx.I)
    return args[0] in poles


def _trig_of_pi_multiple(func: _Builder, arg: sx.Expr) -> sx.Expr | None:
    """``func(arg)`` for sin, cos or tan of pi times a non-constant factor, as sympy gives it.

    sympy's ``eval`` asks whether the factor of pi is an integer (for tan, twice) through
    the assumptions system: 14 to 30 ms for a ring's barrier ``tan(pi*g/(2*d))``, most
    of loading a team's spec. A spec's symbols are real and none of its functions is
    integer-valued, so the answer is never yes, and ``eval`` then returns the function
    unchanged after pulling out the argument's sign: done here without asking. None
    where that does not apply (sympy evaluates as usual), and always on SymEngine, which
    has no assumptions to ask.
    """
    if sx.SYMENGINE:
        return None
    # sin, cos and tan, with the sign each gives a negated argument.
    sign = {sx.sin: -1, sx.cos: 1, sx.tan: -1}.get(func)
    pi = sx.pi
    if (
        sign is None
        or not arg.is_Mul
        or pi not in arg.args
        or not arg.free_symbols
        or any(a.has(pi) for a in arg.args if a is not pi)
        or arg.has(sx.I)
        or any(s.is_integer is not None for s in arg.free_symbols)
    ):
        return None
    if arg.could_extract_minus_sign():
        return sign * func(-arg, evaluate=False)
    return func(arg, evaluate=False)
