"""The border with SymPy: conversions both ways, for the few expressions that cross it.

SymPy is the reference engine and the only one that simplifies, factors, solves and
prints LaTeX and MathML. What needs it (det R's factored form and singular set, the
convexity checks, the report, SymPy mechanics and URDF import) converts the small
expressions it needs with :func:`to_sympy` and the results back with
:func:`from_sympy`; converting a whole law costs several times deriving it on
SymEngine, so nothing converts a whole law. On the SymPy engine both are the identity.

Symbols cross as real symbols of the same name (SymEngine has no assumptions; the
derivation's symbols are all real), numbers exactly (a SymEngine double becomes the
SymPy float of the same value), and the walk is memoised over the expression's DAG, so
shared subexpressions convert once.
"""

from __future__ import annotations

from typing import Any

from tvopt_codegen import symbolic as sx


def sympy() -> Any:
    """SymPy, imported when the border is first crossed (its import is 0.5-1.3 s)."""
    import sympy as module  # noqa: PLC0415 - the border is the only place that needs it

    return module


def to_sympy(expr: Any, memo: dict[Any, Any] | None = None) -> Any:
    """``expr`` (an expression or a matrix) as a SymPy expression, real symbols kept real."""
    if not sx.SYMENGINE:
        return expr
    sp = sympy()
    if isinstance(expr, sx.MatrixBase):
        rows, cols = expr.shape
        return sp.ImmutableMatrix(
            rows, cols, [to_sympy(expr[i, j], memo) for i in range(rows) for j in range(cols)]
        )
    known: dict[Any, Any] = {} if memo is None else memo
    return _to_sympy(expr, known, sp)


def _to_sympy(node: Any, memo: dict[Any, Any], sp: Any) -> Any:
    done = memo.get(node)
    if done is not None:
        return done
    if node.is_Symbol:
        out = sp.Symbol(str(node), real=True)
    elif node.is_Integer:
        out = sp.Integer(int(node))
    elif node.is_Rational:
        numerator, denominator = node.as_numer_denom()
        out = sp.Rational(int(numerator), int(denominator))
    elif node.is_Float:
        out = sp.Float(float(node), 17)
    elif node.is_Atom:
        # pi, E, I, oo, zoo, nan and SymEngine's booleans: SymPy's own conversion.
        out = sp.sympify(node)
    else:
        args = [_to_sympy(arg, memo, sp) for arg in node.args]
        if sx.is_piecewise(node):
            out = sp.Piecewise(*[(args[i], args[i + 1]) for i in range(0, len(args), 2)])
        elif node.is_Add:
            out = sp.Add(*args)
        elif node.is_Mul:
            out = sp.Mul(*args)
        elif node.is_Pow:
            out = sp.Pow(*args)
        elif node.is_Function:
            name = sx.function_name(node)
            func = getattr(sp, name, None)
            out = func(*args) if func is not None else sp.Function(name, real=True)(*args)
        else:
            # Relations and logic: SymPy's class of the same name (StrictLessThan, And, ...).
            out = getattr(sp, type(node).__name__)(*args)
    memo[node] = out
    return out


def from_sympy(expr: Any, memo: dict[Any, Any] | None = None) -> Any:
    """A SymPy expression (or matrix) as one of the process's engine.

    An expression already of the engine is returned as it is, so that a stage can take
    either while the stages before it move onto the API.
    """
    if not sx.SYMENGINE:
        return expr
    import symengine  # noqa: PLC0415 - loaded with the engine already

    if isinstance(expr, symengine.Basic | symengine.MatrixBase):
        return expr
    sp = sympy()
    if isinstance(expr, sp.MatrixBase):
        rows, cols = expr.shape
        return symengine.ImmutableMatrix(
            [[from_sympy(expr[i, j], memo) for j in range(cols)] for i in range(rows)]
        )
    known: dict[Any, Any] = {} if memo is None else memo
    return _from_sympy(sp.sympify(expr), known, sp, symengine)


def _from_sympy(node: Any, memo: dict[Any, Any], sp: Any, se: Any) -> Any:
    done = memo.get(node)
    if done is not None:
        return done
    if node.is_Symbol:
        out = se.Symbol(node.name)
    elif node.is_Integer:
        out = se.Integer(int(node))
    elif node.is_Rational:
        out = se.Rational(int(node.p), int(node.q))
    elif node.is_Float:
        out = se.RealDouble(float(node))
    elif isinstance(node, sp.Piecewise):
        pairs = [
            (_from_sympy(pair.expr, memo, sp, se), _from_sympy(pair.cond, memo, sp, se))
            for pair in node.args
        ]
        out = se.Piecewise(*pairs)
    elif node.is_Atom or not node.args:
        out = se.sympify(node)
    else:
        args = [_from_sympy(arg, memo, sp, se) for arg in node.args]
        if node.is_Add:
            out = se.Add(*args)
        elif node.is_Mul:
            out = se.Mul(*args)
        elif node.is_Pow:
            out = se.Pow(*args)
        elif isinstance(node.func, sp.core.function.UndefinedFunction):
            # First: a user's function named gamma or beta is not SymEngine's.
            out = se.Function(node.func.__name__)(*args)
        elif isinstance(node, sp.Function) and hasattr(se, node.func.__name__):
            out = getattr(se, node.func.__name__)(*args)
        else:
            out = se.sympify(node.func(*[sp.sympify(a) for a in node.args]))
    memo[node] = out
    return out


__all__ = ["from_sympy", "sympy", "to_sympy"]
