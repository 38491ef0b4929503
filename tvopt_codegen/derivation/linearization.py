"""Linearization: dynamic extension, relative degree, R, p and the closed-loop states.

The dynamic extension (and its search), the vector relative degree, the decoupling matrix
R and p, the Brunovsky form, the closed-loop states, and where R or p is singular or
undefined (Lemmas 1-2, Section IV-B of the paper).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from tvopt_codegen import symbolic as sx
from tvopt_codegen.derivation.meter import (
    _DET_SIMPLIFY_NODES,
    TimeLimitError,
    _Meter,
    time_limited,
    tree_size,
)
from tvopt_codegen.derivation.model import Model, Settings, start_evaluator
from tvopt_codegen.derivation.rejection import state_names
from tvopt_codegen.errors import AssumptionError, SpecError
from tvopt_codegen.maths import hurwitz
from tvopt_codegen.maths.lie import (
    Extension,
    ImplicitDerivativeError,
    RelativeDegree,
    brunovsky,
    extend,
    generic_rank,
    nonzero_entries,
    relative_degree,
)
from tvopt_codegen.spec import Mechanics
from tvopt_codegen.spec.features import refusal_line
from tvopt_codegen.spec.reader import suggestion
from tvopt_codegen.symbolic import linalg
from tvopt_codegen.symbolic.border import from_sympy, to_sympy


def _sympy() -> Any:
    """SymPy, for the border's few small expressions (det R, signs of factors)."""
    import sympy  # noqa: PLC0415 - only the decisions need it, and only when they run

    return sympy


def _circular() -> tuple[Any, ...]:
    """SymPy's classes of circular and hyperbolic functions."""
    sp = _sympy()
    return (
        sp.functions.elementary.trigonometric.TrigonometricFunction,
        sp.functions.elementary.hyperbolic.HyperbolicFunction,
    )


def _rows_text(matrix: sx.Expr) -> str:
    """A matrix's rows as text, ``[[a, b], [c, d]]``, as ``sstr`` writes a nested list."""
    return "[" + ", ".join(f"[{', '.join(map(sx.text, row))}]" for row in matrix.tolist()) + "]"


def _implicit_problem(model: Model, exc: ImplicitDerivativeError) -> str:
    """Why a mass-matrix plant cannot take the Lie derivative ``exc`` asks for."""
    output, order = exc.args
    problem = (
        f"output {model.output_names[output]!r} needs the derivative of M^-1 (its Lie "
        f"derivative of order {order} holds M^-1 F or M^-1 B"
    )
    if len(model.h) > 1:
        # Beside outputs of relative degree 2, it is what padding would need: the table's line.
        return f"{problem}): {refusal_line(('plant', 'mechanics'), ('padding', 'yes'))}"
    return (
        f"{problem}, which generated code computes at run time): [system.mechanics] supports "
        "outputs of relative degree 2 and no extension; write the plant in [system.dynamics] "
        "for more"
    )


def _linearizable(model: Model, counts: dict[str, int]) -> bool:
    """Whether the plant with these input integrators is full-state linearizable."""
    ext = extend(model.x, model.u, model.f, model.G, counts)
    sampler = model.sampler(ext.x)
    try:
        rd = relative_degree(ext.f, ext.G, model.h, ext.x, sampler, opaque=model.opaque)
    except ImplicitDerivativeError:
        return False  # it would need derivatives of M^-1 (docs/spec.md)
    if rd.R is None:
        return False
    degrees = [r for r in rd.r if r is not None]
    return sum(degrees) == len(ext.x) and generic_rank(rd.R, sampler) == len(model.u)


def _without_extension(model: Model) -> str:
    """Describe what the plant lacks before prolongation (for the report)."""
    sampler = model.sampler(model.x)
    try:
        rd = relative_degree(model.f, model.G, model.h, model.x, sampler, opaque=model.opaque)
    except ImplicitDerivativeError as exc:
        return f"without it, {_implicit_problem(model, exc)}"
    if rd.R is None:
        missing = [str(y) for y, r in zip(model.y, rd.r, strict=True) if r is None]
        return f"without it, outputs {', '.join(missing)} have no relative degree"
    rank = generic_rank(rd.R, sampler)
    degrees = [int(r) for r in rd.r if r is not None]
    if rank < len(model.u):
        # A team's R is written out only while it is small enough to read.
        rows, cols = rd.R.shape
        shown = f"R = {_rows_text(rd.R)}" if rows <= 4 else f"R ({rows} x {cols})"
        return (
            f"without it, the decoupling matrix {shown} has generic rank {rank} < "
            f"{len(model.u)}: the inputs cannot steer every output independently"
        )
    return (
        f"without it, the relative degrees {', '.join(map(str, degrees))} sum to {sum(degrees)} "
        f"< {len(model.x)} states"
    )


def _candidates(m: int, total: int) -> list[tuple[int, ...]]:
    """Integrator counts over m inputs summing to ``total``, earlier inputs first."""
    if m == 1:
        return [(total,)]
    out = []
    for first in range(total, -1, -1):
        out += [(first, *rest) for rest in _candidates(m - 1, total - first)]
    return out


def search_extension(model: Model, max_total: int) -> tuple[dict[str, int] | None, list[str]]:
    """Find the smallest prolongation of inputs that makes the plant linearizable.

    Candidates are tried by total number of integrators (0, 1, 2, ...), and within a
    total with earlier inputs prolonged first: deterministic, and the first success is
    a smallest one.

    Parameters
    ----------
    model : Model
        The plant.
    max_total : int
        The largest total tried.

    Returns
    -------
    tuple of (dict or None, list of str)
        The integrator counts found (``None`` if none works) and every candidate tried.
    """
    from tvopt_codegen.spec import MAX_INTEGRATORS  # noqa: PLC0415 - avoids a cycle

    names = [u.name for u in model.u]
    tried: list[str] = []
    for total in range(max_total + 1):
        for counts in _candidates(len(names), total):
            if max(counts, default=0) > MAX_INTEGRATORS:
                continue
            chosen = {n: q for n, q in zip(names, counts, strict=True) if q}
            tried.append(", ".join(f"{n}: {q}" for n, q in chosen.items()) or "none")
            if _linearizable(model, chosen):
                return chosen, tried
    return None, tried


def _suggest_prolongation(model: Model, counts: dict[str, int]) -> str:
    """Find the smallest single-input prolongation that makes the plant linearizable."""
    for extra in (1, 2):
        for uj in model.u:
            trial = dict(counts)
            trial[uj.name] = trial.get(uj.name, 0) + extra
            if _linearizable(model, trial):
                table = ", ".join(f"{k} = {v}" for k, v in trial.items() if v)
                return (
                    f"; prolong input {uj.name!r} by {extra} integrator(s): "
                    f"[extension] integrate = {{ {table} }}"
                )
    return "; no prolongation of a single input by 1 or 2 integrators makes it linearizable"


#: How long det R's simplification may take before its short form stands.
_DET_SIMPLIFY_SECONDS = 5.0


def simplified_det(det: sx.Expr) -> sx.Expr:
    """A determinant in lowest terms, factored: ``factor(simplify(det))`` or as short.

    ``cancel``, then ``trigsimp`` where there are circular or hyperbolic functions: when
    that leaves a rational function (a unicycle's ``v cos^2 + v sin^2``, a quadrotor's
    thrust), its factored form is what ``simplify`` would reach, in a third of a small
    derivation's time (``simplify`` tries each of its strategies in turn, and imports
    ``sympy.physics.units`` on the way). When trigonometry remains, ``simplify`` decides:
    on random trigonometric determinants the short path's form was longer one time in
    six (benchmarks/NOTES.md). ``simplify`` has no bound of its own (487 s on a 2 x 2 R
    whose gains hold ``cos`` and ``tanh`` of sums, found by the fuzzer): past
    ``_DET_SIMPLIFY_SECONDS`` the short path's form stands. Both are det R exactly; only
    how short it prints can then depend on the machine's speed.

    A border stage: ``det`` (an expression of the engine, small: the caller bounds its
    size) is simplified in SymPy and its factored form converted back.
    """
    sp, circular = _sympy(), _circular()
    det = to_sympy(det)
    reduced = sp.cancel(det)
    if reduced.has(*circular):
        try:
            with time_limited(_DET_SIMPLIFY_SECONDS):
                reduced = sp.trigsimp(reduced)
                if reduced.has(*circular) and not _one_circular_factor(reduced):
                    return from_sympy(sp.factor(sp.simplify(det)))
        except TimeLimitError:
            pass
    return from_sympy(sp.factor(reduced))


def _one_circular_factor(expr: sx.Expr) -> bool:
    """Whether ``expr`` is one circular or hyperbolic function of a symbol times powers.

    That is a number, powers of symbols and one ``sin(q)`` (an arm's ``l1*l2*sin(q2)``).
    No identity shortens such a product, so ``simplify`` returns it as it is (tested), and
    the short path's form is the one it would give. ``expr`` is SymPy's.
    """
    sp, circular = _sympy(), _circular()
    functions = 0
    for factor in sp.Mul.make_args(expr):
        base = factor.base if factor.is_Pow and factor.exp.is_Integer else factor
        if factor.is_Number or base.is_Symbol:
            continue
        if isinstance(factor, circular) and factor.args[0].is_Symbol:
            functions += 1
            continue
        return False
    return functions == 1


def _singular_set(det: sx.Expr) -> tuple[str, ...]:
    """Describe where a determinant vanishes, one condition per factor of its numerator.

    A factor that vanishes nowhere over the reals (``vx**2 + vy**2 + 1``) is no place at
    all, and is left out: with every factor so, R is never singular. A border stage:
    ``det`` (small, simplified) is factored in SymPy, and the conditions are written as
    SymPy writes them, the same text on either engine.
    """
    sp = _sympy()
    numerator, _ = sp.fraction(sp.together(to_sympy(det)))
    if numerator.is_Number:
        return () if numerator != 0 else ("everywhere",)
    try:
        _, factors = sp.factor_list(numerator)
    except sp.PolynomialError:  # not a polynomial in its symbols: state it whole
        factors = [(numerator, 1)]
    conditions = []
    for base, _power in factors:
        if base.is_Number or _sign(base) in ("positive", "negative"):
            continue
        conditions.append(f"{sp.sstr(base)} = 0")
    return tuple(conditions)


#: Largest expression (in nodes) whose sign is asked of sympy's assumptions: the answer
#: only shortens a message, and it must stay cheap.
_SIGN_NODES = 400
#: Most symbols of a quadratic whose definiteness is decided exactly.
_QUADRATIC_SYMBOLS = 12


def _sign(expr: sx.Expr) -> str | None:
    """Whether ``expr`` is ``"positive"``, ``"nonnegative"`` or ``"negative"`` everywhere.

    None where that is not known cheaply.

    sympy's assumptions first (every spec symbol is real: a sum of squares plus a positive
    constant, an exponential, ``cosh``); then, for a quadratic polynomial with number
    coefficients, the exact test: ``z^T Q z + g^T z + c`` with ``Q`` positive definite
    has its least value ``c - g^T Q^-1 g / 4`` (``x**2 - x*y + y**2 + 1`` is positive).
    ``expr`` is SymPy's (:func:`_engine_sign` takes the engine's).
    """
    sp = _sympy()
    if tree_size(expr, _SIGN_NODES) > _SIGN_NODES:
        return None
    for candidate in (expr, -expr):
        if candidate.is_positive:
            return "positive" if candidate is expr else "negative"
    if expr.is_nonnegative:
        return "nonnegative"
    symbols = sorted(expr.free_symbols, key=lambda s: s.name)
    if not symbols or len(symbols) > _QUADRATIC_SYMBOLS:
        return None
    try:
        poly = sp.Poly(expr, *symbols)
    except sp.PolynomialError:
        return None
    if poly.total_degree() != 2 or not all(c.is_Rational for c in poly.coeffs()):
        return None
    for candidate in (poly, -poly):
        least = _least_value(candidate, symbols)
        if least is not None:
            if least > 0:
                return "positive" if candidate is poly else "negative"
            if least == 0 and candidate is poly:
                return "nonnegative"
    return None


def _engine_sign(expr: sx.Expr, memo: dict[Any, Any]) -> str | None:
    """:func:`_sign` of an expression of the engine (``memo``: the border's, shared)."""
    if tree_size(expr, _SIGN_NODES) > _SIGN_NODES:
        return None
    return _sign(to_sympy(expr, memo))


def _least_value(poly: Any, symbols: Sequence[Any]) -> Any:
    """The least value of a quadratic polynomial with a positive definite Hessian, or None.

    SymPy's ``Poly`` and ``Rational``.
    """
    sp = _sympy()
    n = len(symbols)
    quadratic = sp.zeros(n, n)
    linear = sp.zeros(n, 1)
    constant = sp.Integer(0)
    for monomial, coefficient in poly.terms():
        powers = [(i, k) for i, k in enumerate(monomial) if k]
        if not powers:
            constant = coefficient
        elif len(powers) == 1 and powers[0][1] == 1:
            linear[powers[0][0]] = coefficient
        elif len(powers) == 1:
            quadratic[powers[0][0], powers[0][0]] = coefficient
        else:
            (i, _), (j, _) = powers
            quadratic[i, j] = quadratic[j, i] = coefficient / 2
    if not quadratic.is_positive_definite:
        return None
    return constant - (linear.T * quadratic.inv() * linear)[0, 0] / 4


def _singular_start(
    R: sx.Expr,
    p: sx.Expr,
    states: Sequence[sx.Expr],
    initial: Sequence[float],
    defaults: Mapping[sx.Expr, float],
    extension_states: Sequence[str],
    mechanics: Mechanics | None = None,
) -> tuple[str, ...]:
    """A warning when the spec's initial state is where the law is undefined.

    A mass-matrix plant's run-time symbols (``M^-1 F``, ``M^-1 B``) are solved for
    numerically there.

    An automatic extension starts its states at 0 unless the spec gives them, and 0
    is singular for any prolonged speed: the module's DEFAULT_STATE would be unusable
    without a word.
    """
    evaluate = start_evaluator(states, initial, defaults, mechanics)
    with np.errstate(all="ignore"):
        # R's nonzero entries only: a team's R is block diagonal.
        matrix = np.zeros(R.shape, dtype=complex)
        for i, j, entry in nonzero_entries(R):
            matrix[i, j] = complex(evaluate(entry))
        rest = np.array([complex(evaluate(e)) for e in p])
    finite = bool(np.all(np.isfinite(matrix)) and np.all(np.isfinite(rest)))
    if finite and np.all(matrix.imag == 0) and np.linalg.cond(matrix.real) < 1e12:
        return ()
    where = ", ".join(f"{sym.name} = {v:.6g}" for sym, v in zip(states, initial, strict=True))
    if len(where) > 120:
        where = where[:117] + "..."
    zeros = [
        name
        for name, v in zip((s.name for s in states), initial, strict=True)
        if name in extension_states and v == 0
    ]
    hint = (
        f"; the extension states {', '.join(zeros)} start at 0 unless "
        "simulation.initial_state gives them (by name)"
        if zeros
        else ""
    )
    what = "R is singular there" if finite else "R or p is not finite there"
    return (
        f"simulation.initial_state: the law is undefined at the initial state ({where}): "
        f"{what}{hint}; DEFAULT_STATE cannot be simulated as it is",
    )


#: At most this many conditions are listed where R or p is undefined.
_MAX_UNDEFINED = 6


def _undefined_set(exprs: Sequence[sx.Expr], states: set[sx.Expr]) -> tuple[str, ...]:
    """Where expressions of the states are undefined, one condition per cause.

    The conditions of :func:`undefined_causes`, without their causes.
    """
    return tuple(condition for condition, _ in undefined_causes(exprs, states))


def undefined_causes(exprs: Sequence[sx.Expr], states: set[sx.Expr]) -> tuple[tuple[str, str], ...]:
    """Where expressions of the states are undefined: each condition and its cause.

    A denominator that vanishes, ``tan``/``sec`` where the cosine vanishes,
    ``cot``/``csc`` where the sine does, ``log`` of a non-positive and a root of a
    negative number: the places where R or p, and with them the law, do not exist
    although det R may not vanish there (a steering angle of pi/2, an Euler pitch of
    pi/2). Conditions on parameters alone are not listed, nor any that holds at no real
    point (``sqrt(vx**2 + vy**2 + 1)`` is defined everywhere): see :func:`_sign`.
    ``x**(-1/2)`` has two, ``x = 0`` (a denominator) and ``x < 0`` (a root).

    The walk is the engine's; only the values whose sign is asked (small ones) and
    those a condition writes cross the border, each shared subexpression once.
    """
    conditions: dict[str, str] = {}
    seen: set[Any] = set()
    memo: dict[Any, Any] = {}
    stack = [e for e in exprs if isinstance(e, sx.Basic)]
    while stack and len(conditions) < _MAX_UNDEFINED:
        node = stack.pop()
        if node in seen or not node.free_symbols & states:
            continue
        seen.add(node)
        found: list[tuple[str, str, sx.Expr, tuple[str, ...]]] = []
        name = sx.function_name(node) if node.is_Function else ""
        if node.is_Pow and node.exp.is_Number and node.base.free_symbols & states:
            base = _condition_text(node.base, memo)
            if node.exp.is_negative:
                found.append((f"{base} = 0", "a denominator vanishes", node.base, _NONZERO))
            if not node.exp.is_Integer:
                root = "a square root" if getattr(node.exp, "q", 0) == 2 else "a fractional power"
                found.append((f"{base} < 0", f"{root} of a negative", node.base, _NONNEGATIVE))
        elif name in ("tan", "sec"):
            arg = node.args[0]
            cause = f"the cosine under {name} vanishes"
            found.append((f"cos({_condition_text(arg, memo)}) = 0", cause, sx.cos(arg), _NONZERO))
        elif name in ("cot", "csc"):
            arg = node.args[0]
            cause = f"the sine under {name} vanishes"
            found.append((f"sin({_condition_text(arg, memo)}) = 0", cause, sx.sin(arg), _NONZERO))
        elif name == "log":
            arg = node.args[0]
            text = _condition_text(arg, memo)
            found.append((f"{text} <= 0", "a log of a non-positive", arg, _POSITIVE))
        for condition, cause, value, never in found:
            if _engine_sign(value, memo) not in never:
                conditions.setdefault(condition, cause)
        stack.extend(reversed(node.args))
    return tuple(conditions.items())


def _condition_text(expr: sx.Expr, memo: dict[Any, Any]) -> str:
    """``expr`` as SymPy writes it, on either engine: the generated code quotes it.

    SymEngine orders a sum's terms its own way; the condition's text, in the generated
    module's and the C file's messages, is the same as on SymPy (golden files).
    """
    if not sx.SYMENGINE:
        return sx.text(expr)
    return str(_sympy().sstr(to_sympy(expr, memo)))


#: The signs of a value under which each kind of condition holds nowhere.
_NONZERO = ("positive", "negative")
_NONNEGATIVE = ("positive", "nonnegative")
_POSITIVE = ("positive",)


@dataclass(frozen=True)
class _Linearization:
    """The extended plant and its vector relative degree (Lemmas 1-2)."""

    extension: Extension
    degrees: tuple[int, ...]
    lie: tuple[tuple[sx.Expr, ...], ...]
    R: sx.Expr
    searched: tuple[str, ...]
    declared: frozenset[str]


@dataclass(frozen=True)
class _ErrorDynamics:
    """``H``: its order, coefficients, eigenvalues and decay rate."""

    k: int
    coefficients: tuple[float, ...]
    eigenvalues: tuple[complex, ...]
    decay_rate: float
    integral_pole: float | None = None
    bumpless: tuple[float, ...] = ()


@dataclass(frozen=True)
class _States:
    """The closed-loop state: plant, extension, padding chains; its initial value."""

    padding: tuple[tuple[str, ...], ...]
    names: tuple[str, ...]
    symbols: tuple[sx.Expr, ...]
    initial: tuple[float, ...]
    multipliers: tuple[tuple[str, ...], ...] = ()
    integral: tuple[str, ...] = ()
    #: With ``[robust.eso]``, each output's observer states (estimates, then d_hat).
    eso: tuple[tuple[str, ...], ...] = ()


@dataclass(frozen=True)
class _Decoupling:
    """R, p, Phi, the Brunovsky pair, and where R is singular or R and p undefined."""

    p: sx.Expr
    phi: sx.Expr
    A: sx.Expr
    B: sx.Expr
    det_R: sx.Expr | None
    det_R_note: str
    singular: tuple[str, ...]
    undefined: tuple[str, ...]


def _linearize(model: Model, meter: _Meter) -> _Linearization:
    """Extend the plant (as given, or by search) and find its vector relative degree."""
    settings = model.settings
    source = settings.source
    outputs = model.output_names
    counts = dict(settings.extension)
    searched: tuple[str, ...] = ()
    if settings.extension_auto:
        meter.stage = "extension search"
        meter.report()
        limit = settings.extension_max_total or len(model.x)
        if model.mechanics is not None:
            # A mass-matrix plant takes no prolongation (docs/features.md): "none" is the one
            # candidate, and when it fails the relative degree below says why in one line.
            limit = 0
        found, tried = search_extension(model, limit)
        if found is None and model.mechanics is None:
            raise AssumptionError(
                source,
                "extension.auto",
                f"no prolongation of the inputs with at most {limit} integrators in all makes "
                f"the plant full-state linearizable (tried {len(tried)}: {'; '.join(tried)})",
            )
        counts = found or {}
        searched = tuple(tried)
        meter.stage = "relative degree"
        meter.report()
    ext = extend(model.x, model.u, model.f, model.G, counts)
    declared = model.declared
    inputs = model.input_names
    for name in ext.states:
        if name in declared and name not in inputs:
            raise SpecError(
                source,
                "extension.integrate",
                f"extension state {name!r} collides with a declared name",
            )
    sampler = model.sampler(ext.x)
    try:
        rd: RelativeDegree = relative_degree(
            ext.f, ext.G, model.h, ext.x, sampler, meter, opaque=model.opaque
        )
    except ImplicitDerivativeError as exc:
        where = "extension" if any(counts.values()) else f"system.outputs.{outputs[exc.args[0]]}"
        raise AssumptionError(source, where, _implicit_problem(model, exc)) from None
    m = len(model.u)
    n_ext = len(ext.x)
    for name, r in zip(outputs, rd.r, strict=True):
        if r is None:
            raise AssumptionError(
                source,
                f"system.outputs.{name}",
                f"output {name!r} has no relative degree: no input reaches it within "
                f"{n_ext} derivatives",
            )
    assert rd.R is not None
    degrees = tuple(int(r) for r in rd.r if r is not None)
    named = ", ".join(f"{o} = {r}" for o, r in zip(outputs, degrees, strict=True))
    rank = generic_rank(rd.R, sampler)
    if rank < m:
        suggestion = _suggest_prolongation(model, counts)
        raise AssumptionError(
            source,
            "extension",
            f"the decoupling matrix R is singular everywhere (generic rank {rank} < {m}; "
            f"relative degrees {named}){suggestion}",
        )
    if sum(degrees) != n_ext:
        raise AssumptionError(
            source,
            "system.outputs",
            f"not full-state linearizable: the relative degrees ({named}) sum to "
            f"{sum(degrees)}, but the extended system has {n_ext} states (internal dynamics "
            f"of dimension {n_ext - sum(degrees)})",
        )
    return _Linearization(ext, degrees, rd.lie, rd.R, searched, declared)


def _error_dynamics(settings: Settings, k: int) -> _ErrorDynamics:
    """H from the spec's poles or coefficients (``settings``): of order k, and Hurwitz."""
    source = settings.source
    poles = settings.poles
    if settings.coefficients is not None:
        coefficients = settings.coefficients
        field, given = "error_dynamics.coefficients", len(coefficients)
    else:
        assert poles is not None
        coefficients = hurwitz.coefficients_from_poles(poles)
        field, given = "error_dynamics.poles", len(poles)
    kind = "poles" if poles is not None else "coefficients"
    # A count that does not match is the spec's mistake (exit 2), not the method's.
    if settings.robust.integral and given != k + 1:
        raise SpecError(
            source,
            field,
            f"the error dynamics have order k = {k} (the largest relative degree) and "
            f"[robust] integral adds one per output, so give {k + 1} {kind}, not {given}",
        )
    if not settings.robust.integral and given != k:
        raise SpecError(
            source,
            field,
            f"the error dynamics have order k = {k} (the largest relative degree), so give "
            f"{k} {kind}, not {given}",
        )
    if poles is not None:
        # The poles are exact as written; the companion eigenvalues would be rounded.
        eig = np.array(sorted(poles, key=lambda v: (v.real, v.imag)))
        alpha = float(-max(v.real for v in poles))
    else:
        eig = hurwitz.eigenvalues(coefficients)
        alpha = hurwitz.decay_rate(coefficients)
    if not alpha > 0:
        raise AssumptionError(
            source,
            field,
            f"H is not Hurwitz: eigenvalue {complex(eig[-1]):.6g} has real part >= 0 "
            "(coefficients a_i are the last row of the companion matrix; for poles -1, -2 "
            "they are a_0 = -2, a_1 = -3)",
        )
    pole: float | None = None
    bumpless: tuple[float, ...] = ()
    if settings.robust.integral:
        split = hurwitz.integral_split(coefficients, poles)
        if split is None:
            raise SpecError(
                source,
                field,
                "integral action takes a real pole (its own) among the k + 1: every one given "
                "is complex",
            )
        pole, _, bumpless = split
    return _ErrorDynamics(
        k, tuple(coefficients), tuple(complex(v) for v in eig), alpha, pole, bumpless
    )


def _closed_loop_states(model: Model, lin: _Linearization, k: int) -> _States:
    """Pad outputs of relative degree below k with integrator chains; order the state."""
    settings, outputs = model.settings, model.output_names
    padding = tuple(
        tuple(f"xi_{name}_{j}" for j in range(1, k - r + 1))
        for name, r in zip(outputs, lin.degrees, strict=True)
    )
    pad_names = [n for chain in padding for n in chain]
    # Each equality's multiplier and its first k - 1 derivatives: the controller's own
    # integrator chain, driven by nu^(k) from the KKT system.
    multipliers = tuple(tuple(f"nu_{c.name}_{j}" for j in range(k)) for c in model.equalities)
    # With integral action, the integral of each entry of grad f0 (or of the KKT map):
    # a chain of one integrator per entry, last in the state.
    integral: tuple[str, ...] = ()
    if settings.robust.integral:
        integral = (
            *(f"int_{name}" for name in outputs),
            *(f"int_nu_{c.name}" for c in model.equalities),
        )
    # The extended-state observer's estimates sit before the integrals, which stay last.
    eso = state_names(outputs, lin.degrees) if settings.robust.eso is not None else ()
    generated = (
        ("system.outputs", "padding state", pad_names),
        ("robust.eso", "observer state", tuple(n for chain in eso for n in chain)),
        (
            "constraints",
            "multiplier name",
            (
                *(n for chain in multipliers for n in chain),
                *(f"nu_{c.name}" for c in model.equalities),
            ),
        ),
        ("robust.integral", "integral state", integral),
    )
    for field, kind, names_of in generated:
        for name in names_of:
            if name in lin.declared:
                raise SpecError(
                    settings.source, field, f"{kind} {name!r} collides with a declared name"
                )
    ext = lin.extension
    names = (
        *model.state_names,
        *ext.states,
        *pad_names,
        *(n for chain in multipliers for n in chain),
        *(n for chain in eso for n in chain),
        *integral,
    )
    # With a searched extension the user cannot know its states in advance: only the
    # plant states are required then (extension states start at zero unless given).
    required = len(model.x) + (0 if settings.extension_auto else len(ext.states))
    initial = _initial_state(settings, names, required)
    return _States(
        padding,
        names,
        tuple(sx.symbol(n) for n in names),
        initial,
        multipliers,
        integral,
        eso,
    )


def _decoupling(
    lin: _Linearization, meter: _Meter, mechanics: Mechanics | None = None
) -> _Decoupling:
    """p, Phi and the Brunovsky pair from the Lie chains; where R fails, in words.

    For a mass-matrix plant R is ``J_h M^-1 B`` in the run-time symbols ``W = M^-1 B``:
    the determinant taken is that of ``J_h B`` (R with ``W`` replaced by ``B``), which
    is ``det R det M`` and vanishes where R is singular (``M`` is positive definite);
    ``det_R_note`` says so.
    """
    degrees, lie = lin.degrees, lin.lie
    R = _with_gains(lin.R, mechanics)
    note_for_det = "" if mechanics is None else "det(J_h B) = det R det M"
    m = len(degrees)
    p = sx.matrix([[lie[i][degrees[i]]] for i in range(m)])
    phi = sx.matrix([[lie[i][j]] for i in range(m) for j in range(degrees[i])])
    A, B = brunovsky(degrees)
    det_R: sx.Expr | None = None
    det_R_note = ""
    singular: tuple[str, ...] = ()
    if m > 4:
        det_R_note = f"not expanded symbolically (m = {m} > 4)"
    else:
        det = linalg.det(R)
        meter(det)
        # Simplifying is exact but can be slow on large entries: only small ones.
        if tree_size(det, _DET_SIMPLIFY_NODES) <= _DET_SIMPLIFY_NODES:
            det_R = simplified_det(det)
            # Charge the simplification's time to this stage, not to the next one.
            meter.check_time()
            singular = _singular_set(det_R)
        else:
            det_R_note = (
                f"not simplified symbolically (more than {_DET_SIMPLIFY_NODES} expression nodes)"
            )
    if note_for_det and det_R is not None:
        det_R_note = note_for_det
    undefined = _undefined_set(law_expressions(lin.R, p, mechanics), set(lin.extension.x))
    return _Decoupling(p, phi, A, B, det_R, det_R_note, singular, undefined)


def _with_gains(R: sx.Expr, mechanics: Mechanics | None) -> sx.Expr:
    """R, with a mass-matrix plant's run-time symbols ``W = M^-1 B`` replaced by ``B``."""
    if mechanics is None:
        return R
    gains = {
        w: mechanics.input_matrix[i][j]
        for i, row in enumerate(mechanics.gains)
        for j, w in enumerate(row)
        if isinstance(w, sx.Symbol)
    }
    return R.xreplace(gains)


def law_expressions(R: sx.Expr, p: sx.Expr, mechanics: Mechanics | None = None) -> list[sx.Expr]:
    """R's nonzero entries and p: where any is undefined, so is the law.

    What :func:`undefined_causes` is asked about, by the derivation and by ``check``
    alike (a team's R is m^2 entries, almost all zeros).
    """
    return [e for _, _, e in nonzero_entries(_with_gains(R, mechanics))] + list(p)


def _initial_state(
    settings: Settings, state_names: Sequence[str], required: int
) -> tuple[float, ...]:
    """Order the spec's initial state; plant and extension states must all be given."""
    given = dict(settings.initial_state)
    for key in given:
        if key not in state_names:
            raise SpecError(
                settings.source,
                f"simulation.initial_state.{key}",
                f"not a state of the closed loop (states: {', '.join(state_names)})"
                f"{suggestion(key, state_names)}",
            )
    if given:
        for name in state_names[:required]:
            if name not in given:
                raise SpecError(
                    settings.source,
                    f"simulation.initial_state.{name}",
                    "missing (every plant and extension state needs a value)",
                )
    return tuple(float(given.get(name, 0.0)) for name in state_names)
