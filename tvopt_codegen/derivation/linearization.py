"""Linearization: dynamic extension, relative degree, R, p and the closed-loop states.

The dynamic extension (and its search), the vector relative degree, the decoupling matrix
R and p, the Brunovsky form and the closed-loop states (Lemmas 1-2, Section IV-B of the
paper). Where R or p is singular or undefined is :mod:`.singularity`'s to say.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from tvopt_codegen import symbolic as sx
from tvopt_codegen.derivation.meter import _DET_SIMPLIFY_NODES, _Meter
from tvopt_codegen.derivation.model import Model, Settings, start_evaluator
from tvopt_codegen.derivation.rejection import state_names
from tvopt_codegen.derivation.singularity import _singular_set, _undefined_set, simplified_det
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
        # Simplifying is exact but can be slow on large entries: only small ones.
        det, small = linalg.sized_det(R, _DET_SIMPLIFY_NODES)
        meter(det)
        if small:
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
