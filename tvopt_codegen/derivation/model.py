"""Stage 2: the control-affine plant, outputs and objective as expressions of the engine.

``x' = f(x) + G(x) u`` is recovered from the declared right-hand sides by
differentiation: ``G[:, j] = d rhs / d u_j`` and ``f = rhs(u = 0)``, after checking that
no right-hand side is more than affine in the inputs.

Every stage after this one reads the model's expressions, of the process's engine
(:mod:`tvopt_codegen.symbolic`): a spec's SymPy expressions (a :class:`Spec` built by
hand) are taken onto it here, once.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from tvopt_codegen import symbolic as sx
from tvopt_codegen.contract import PIVOT_TOLERANCE
from tvopt_codegen.errors import AssumptionError, SpecError, clip
from tvopt_codegen.maths.jet import partial
from tvopt_codegen.maths.lie import Sampler, from_entries
from tvopt_codegen.maths.numeric import Evaluator
from tvopt_codegen.spec import (
    Constraint,
    Estimator,
    Limit,
    Mechanics,
    Robust,
    Spec,
    time_symbol,
)
from tvopt_codegen.spec.constraints import barrier_objective, initial_slack, schedule
from tvopt_codegen.spec.implicit import (
    implicit_values,
    mass_matrix_at,
    problem_at_samples,
    solved_at,
)
from tvopt_codegen.symbolic.border import from_sympy


@dataclass(frozen=True)
class Settings:
    """The spec's choices for the law that the stages after :func:`build_model` read.

    Copied from the :class:`~tvopt_codegen.spec.Spec` as given: the stages read the
    model, and the spec stays the templates' and the report's.

    Attributes
    ----------
    source : str
        The spec's file name, for error messages.
    poles, coefficients : tuple or None
        ``[error_dynamics]``: the poles (complex) or the coefficients (float); one is None.
    t_final : float
        The horizon, ``[simulation] t_final``.
    initial_state : tuple of (str, float)
        ``[simulation] initial_state`` as given: closed-loop state names and values.
    extension : tuple of (str, int)
        ``[extension] integrate``: the integrators asked for each input.
    extension_auto : bool
        Whether the prolongation is searched (``[extension] auto``).
    extension_max_total : int or None
        The search's largest total of integrators (None: the number of plant states).
    allow_nonconvex : bool
        Whether a non-convex inequality or a curved equality only warns (the certificate
        then local) instead of being refused.
    robust : Robust
        ``[robust]``: integral action, the disturbance observer, the extended-state observer.
    limits : tuple of Limit
        ``[limits]``: the actuators' ranges and slew rates.
    estimator : Estimator or None
        ``[references.estimator]``: how the references' derivatives are estimated.
    """

    source: str
    poles: tuple[complex, ...] | None
    coefficients: tuple[float, ...] | None
    t_final: float
    initial_state: tuple[tuple[str, float], ...]
    extension: tuple[tuple[str, int], ...] = ()
    extension_auto: bool = False
    extension_max_total: int | None = None
    allow_nonconvex: bool = False
    robust: Robust = field(default_factory=Robust)
    limits: tuple[Limit, ...] = ()
    estimator: Estimator | None = None


@dataclass(frozen=True)
class Model:
    """The declared system in the paper's notation (equation (1)).

    Attributes
    ----------
    settings : Settings
        The spec's choices for the law (error dynamics, horizon, initial state,
        extension, ``[robust]``, ``[limits]``): what the later stages read of the spec.
    x, u, y : tuple of Symbol
        Plant states, plant inputs and output symbols, in declaration order.
    f : ImmutableMatrix
        Drift vector field, shape (n, 1).
    G : ImmutableMatrix
        Input matrix ``[g_1, ..., g_m]``, shape (n, m).
    h : ImmutableMatrix
        Output map, shape (m, 1).
    params : tuple of Symbol
        Parameters, in declaration order.
    defaults : tuple of float
        Default value of each parameter.
    signals : tuple of (Symbol, Expr)
        Each signal symbol and its expression in ``t`` and the parameters.
    f0 : Expr
        The objective in ``y``, the signal symbols, the parameters and ``t``.
    t : Symbol
        Time.
    references : tuple of Symbol
        References measured at run time: in signals and ``f0`` like signals, with their
        derivatives supplied by the caller.
    nominal : tuple of (Symbol, Expr)
        The closed form the spec gives for some references, in ``t`` and the parameters.
    objective : Expr or None
        The spec's ``f0`` when ``[constraints]`` made :attr:`f0` the barrier objective
        ``B`` (:mod:`tvopt_codegen.spec.constraints`); None otherwise.
    constraints : tuple of Constraint
        The inequalities, ``g_i(y, t) <= 0``.
    mu, slack : Expr
        The barrier's weight ``mu(t)`` and slack ``s(t)`` (0 without constraints).
    equalities : tuple of Constraint
        The equalities, ``a_j(y, t) = 0``.
    multipliers : tuple of Symbol
        Their Lagrange multipliers ``nu_<name>``, one per equality.
    mechanics : Mechanics or None
        The mass-matrix form the plant was declared in (None: ``[system.dynamics]``).

    Expressions and symbols are the engine's (:mod:`tvopt_codegen.symbolic`); the
    constraints' sides and the mechanics' too.
    """

    settings: Settings
    x: tuple[sx.Expr, ...]
    u: tuple[sx.Expr, ...]
    y: tuple[sx.Expr, ...]
    f: sx.Expr
    G: sx.Expr
    h: sx.Expr
    params: tuple[sx.Expr, ...]
    defaults: tuple[float, ...]
    signals: tuple[tuple[sx.Expr, sx.Expr], ...]
    f0: sx.Expr
    t: sx.Expr
    references: tuple[sx.Expr, ...] = ()
    nominal: tuple[tuple[sx.Expr, sx.Expr], ...] = ()
    objective: sx.Expr | None = None
    constraints: tuple[Constraint, ...] = ()
    # The engine's zero when built, not at import: the engine is chosen later.
    mu: sx.Expr = field(default_factory=lambda: sx.Integer(0))
    slack: sx.Expr = field(default_factory=lambda: sx.Integer(0))
    equalities: tuple[Constraint, ...] = ()
    multipliers: tuple[sx.Expr, ...] = ()
    mechanics: Mechanics | None = None

    @property
    def source(self) -> str:
        """The spec's file name, for error messages."""
        return self.settings.source

    @property
    def state_names(self) -> tuple[str, ...]:
        """The plant states' declared names, in order."""
        return tuple(q.name for q in self.x)

    @property
    def input_names(self) -> tuple[str, ...]:
        """The plant inputs' declared names, in order."""
        return tuple(v.name for v in self.u)

    @property
    def output_names(self) -> tuple[str, ...]:
        """The outputs' declared names, in order."""
        return tuple(v.name for v in self.y)

    @property
    def declared(self) -> frozenset[str]:
        """Every declared name: states, inputs, outputs, parameters, signals, references."""
        return frozenset(
            {
                *self.state_names,
                *self.input_names,
                *self.output_names,
                *(q.name for q in self.params),
                *(s.name for s, _ in self.signals),
                *(r.name for r in self.references),
            }
        )

    @property
    def opaque(self) -> frozenset[sx.Expr]:
        """Symbols of ``f`` and ``G`` computed at run time (``M^-1 F``, ``M^-1 B``)."""
        return self.mechanics.opaque if self.mechanics is not None else frozenset()

    def sampler(self, symbols: Sequence[sx.Expr]) -> Sampler:
        """A :class:`~tvopt_codegen.maths.lie.Sampler` over ``symbols``, parameters at defaults.

        It also knows the run-time symbols' values, solved numerically at its points.
        """
        mechanics = self.mechanics
        implicit = None
        if mechanics is not None:

            def implicit(values: Mapping[sx.Expr, object], points: int) -> Mapping[sx.Expr, object]:
                return implicit_values(mechanics, values, points)

        return Sampler(
            symbols, dict(zip(self.params, self.defaults, strict=True)), implicit=implicit
        )

    @property
    def lagrangian(self) -> sx.Expr:
        """``L = f0 + sum_j nu_j a_j``: :attr:`f0` itself without equalities."""
        return self.f0 + sx.Add(
            *(nu * c.g for nu, c in zip(self.multipliers, self.equalities, strict=True))
        )


def build_model(spec: Spec) -> Model:
    """Build the control-affine model of a spec.

    Parameters
    ----------
    spec : Spec
        A validated spec.

    Returns
    -------
    Model
        The plant ``(f, G, h)``, objective and signals.

    Raises
    ------
    SpecError
        When a right-hand side is not affine in the inputs.
    AssumptionError
        When the numbers of inputs and outputs differ (the method needs a square plant).
    """
    spec = _on_engine(spec)
    x = tuple(sx.symbol(n) for n in spec.states)
    u = tuple(sx.symbol(n) for n in spec.inputs)
    if len(spec.inputs) != len(spec.outputs):
        raise AssumptionError(
            spec.source,
            "system.outputs",
            f"the plant has {len(spec.inputs)} inputs but {len(spec.outputs)} outputs; the "
            "method needs as many outputs as inputs",
        )
    sampler, sampled = _plant_sampler(spec, x, u)
    f_rows, G_entries = _split_affine(spec, u, sampler)
    if spec.mechanics is not None:
        _check_mass_matrix(spec, spec.mechanics, sampler, *sampled)
    f0, objective, mu, slack = _barrier_objective(spec)
    return Model(
        settings=_settings(spec),
        x=x,
        u=u,
        y=tuple(sx.symbol(n) for n in spec.outputs),
        f=sx.ImmutableMatrix(f_rows),
        G=from_entries(len(x), len(u), G_entries),
        h=sx.ImmutableMatrix(list(spec.output_exprs)),
        params=tuple(sx.symbol(n) for n, _ in spec.parameters),
        defaults=tuple(v for _, v in spec.parameters),
        signals=tuple((sx.symbol(n), e) for n, e in spec.signals),
        f0=f0,
        t=time_symbol(),
        references=tuple(sx.symbol(n) for n in spec.references),
        nominal=tuple((sx.symbol(n), e) for n, e in spec.reference_nominal),
        objective=objective,
        constraints=spec.constraints,
        mu=mu if mu is not None else sx.Integer(0),
        slack=slack if slack is not None else sx.Integer(0),
        equalities=spec.equalities,
        multipliers=tuple(sx.symbol(f"nu_{c.name}") for c in spec.equalities),
        mechanics=spec.mechanics,
    )


def _on_engine(spec: Spec) -> Spec:
    """``spec`` with its expressions of the process's engine: the spec's own, if they are.

    The reader parses into the engine; a :class:`Spec` built by hand may hold SymPy's
    expressions all the same. Those are converted here, once, sharing one memo, so that
    a subexpression common to the plant and the objective converts once
    (:func:`from_sympy` passes the engine's own through, at the price of a type check).
    On SymPy the spec is the model's as it is.
    """
    if not sx.SYMENGINE:
        return spec
    memo: dict[Any, Any] = {}

    def engine(expr: Any) -> Any:
        return from_sympy(expr, memo)

    def rows(matrix: Sequence[Sequence[Any]]) -> tuple[tuple[Any, ...], ...]:
        return tuple(tuple(engine(e) for e in row) for row in matrix)

    def constraints(given: Sequence[Constraint]) -> tuple[Constraint, ...]:
        return tuple(dataclasses.replace(c, lhs=engine(c.lhs), rhs=engine(c.rhs)) for c in given)

    mechanics = spec.mechanics
    if mechanics is not None:
        mechanics = dataclasses.replace(
            mechanics,
            mass_matrix=rows(mechanics.mass_matrix),
            forces=tuple(engine(e) for e in mechanics.forces),
            input_matrix=rows(mechanics.input_matrix),
            accelerations=tuple(engine(e) for e in mechanics.accelerations),
            gains=rows(mechanics.gains),
            definitions=tuple((engine(s), engine(e)) for s, e in mechanics.definitions),
        )
    return dataclasses.replace(
        spec,
        dynamics=tuple(engine(e) for e in spec.dynamics),
        output_exprs=tuple(engine(e) for e in spec.output_exprs),
        signals=tuple((n, engine(e)) for n, e in spec.signals),
        objective=engine(spec.objective),
        reference_nominal=tuple((n, engine(e)) for n, e in spec.reference_nominal),
        constraints=constraints(spec.constraints),
        equalities=constraints(spec.equalities),
        mechanics=mechanics,
    )


def _settings(spec: Spec) -> Settings:
    """The spec's choices for the law, as the later stages read them."""
    return Settings(
        source=spec.source,
        poles=spec.poles,
        coefficients=spec.coefficients,
        t_final=spec.t_final,
        initial_state=spec.initial_state,
        extension=spec.extension,
        extension_auto=spec.extension_auto,
        extension_max_total=spec.extension_max_total,
        allow_nonconvex=spec.allow_nonconvex,
        robust=spec.robust,
        limits=spec.limits,
        estimator=spec.estimator,
    )


def _plant_sampler(
    spec: Spec, x: tuple[sx.Expr, ...], u: tuple[sx.Expr, ...]
) -> tuple[Sampler, list[np.ndarray]]:
    """The sampler that decides affinity, and where it leaves ``M`` and ``[F | B]``.

    Parameters
    ----------
    spec : Spec
        A validated spec.
    x, u : tuple of Symbol
        The plant's states and inputs, the sampler's free symbols.

    Returns
    -------
    sampler : Sampler
        Over ``(*x, *u)`` with the parameters at their defaults; for a mechanical plant
        it also solves the run-time symbols at its points.
    sampled : list of numpy.ndarray
        Empty until the sampler first evaluates a mechanical plant, then ``M`` and
        ``[F | B]`` at its points (filled in place).
    """
    # Affinity is decided by evaluation at random points first: a nonzero value proves
    # non-affinity at once, and simplify (slow on hostile input) is never reached then.
    mechanics = spec.mechanics
    # M, F and B at the sampler's points, kept for the checks a physics engine makes.
    sampled: list[np.ndarray] = []

    def implicit(values: Mapping[sx.Expr, object], points: int) -> Mapping[sx.Expr, object]:
        assert mechanics is not None
        solved, mass, rhs = solved_at(mechanics, values, points)
        sampled[:] = [mass, rhs]
        return solved

    sampler = Sampler(
        (*x, *u),
        dict(
            zip(
                (sx.symbol(n) for n, _ in spec.parameters),
                (v for _, v in spec.parameters),
                strict=True,
            )
        ),
        implicit=None if mechanics is None else implicit,
    )
    return sampler, sampled


def _split_affine(
    spec: Spec, u: tuple[sx.Expr, ...], sampler: Sampler
) -> tuple[list[sx.Expr], dict[tuple[int, int], sx.Expr]]:
    """``f`` and ``G`` of the declared right-hand sides, after checking their affinity.

    Parameters
    ----------
    spec : Spec
        A validated spec.
    u : tuple of Symbol
        The plant inputs.
    sampler : Sampler
        Decides whether a coefficient's derivative in an input is zero.

    Returns
    -------
    f_rows : list of Expr
        Each right-hand side with the inputs at 0, in the states' order.
    G_entries : dict of (int, int) to Expr
        The nonzero entries of ``G``, by (state, input) position.

    Raises
    ------
    SpecError
        When a right-hand side is not affine in the inputs.
    """
    G_entries: dict[tuple[int, int], sx.Expr] = {}
    f_rows = []
    inputs = set(u)
    for i, (state, rhs) in enumerate(zip(spec.states, spec.dynamics, strict=True)):
        # Only the inputs that occur are differentiated: a plant of N agents has N times
        # the inputs, each in a few equations, and a dense sweep would be quadratic.
        present = rhs.free_symbols
        row = {j: partial(rhs, uj) for j, uj in enumerate(u) if uj in present}
        for j, gij in row.items():
            if gij != 0:
                G_entries[i, j] = gij
            # Only the inputs that occur in the coefficient, in declaration order: a
            # team's G is almost all zeros, and looping over every input for every
            # entry was cubic (9 s for 128 agents).
            occurring = gij.free_symbols & inputs
            if not occurring:
                continue
            for uk in u:
                if uk in occurring and not sampler.is_zero(partial(gij, uk)):
                    raise SpecError(
                        spec.source,
                        f"system.dynamics.{state}",
                        f"not affine in the inputs: the coefficient of {spec.inputs[j]!r} "
                        f"depends on input {str(uk)!r}",
                    )
        # Only the inputs it holds: SymEngine copies the whole mapping into each call.
        f_rows.append(rhs.xreplace(dict.fromkeys(inputs & present, sx.Integer(0))))
    return f_rows, G_entries


def _barrier_objective(
    spec: Spec,
) -> tuple[sx.Expr, sx.Expr | None, sx.Expr | None, sx.Expr | None]:
    """The objective the method tracks: ``f0``, or with ``[constraints]`` the barrier's.

    Parameters
    ----------
    spec : Spec
        A validated spec.

    Returns
    -------
    f0 : Expr
        The spec's objective, or the barrier objective ``B`` when it has inequalities.
    objective : Expr or None
        The spec's objective when ``f0`` is ``B``; None otherwise.
    mu, slack : Expr or None
        The barrier's weight ``mu(t)`` and slack ``s(t)``; None without inequalities.
    """
    f0: sx.Expr = spec.objective
    objective = mu = slack = None
    if spec.constraints:
        assert spec.barrier is not None
        time = time_symbol()
        # The start: outputs of the initial plant state; signals, references (nominal,
        # else 0) and t at 0; parameters at their defaults.
        given = dict(spec.initial_state)
        defaults = {sx.symbol(n): sx.real(v) for n, v in spec.parameters}
        start: dict[sx.Expr, sx.Expr] = {time: sx.Integer(0)}
        start |= {sx.symbol(n): sx.real(given.get(n, 0.0)) for n in spec.states}
        nominal = dict(spec.reference_nominal)
        for name in spec.references:
            start[sx.symbol(name)] = nominal.get(name, sx.Integer(0))
        start |= {sx.symbol(n): e for n, e in spec.signals}
        values = {
            sx.symbol(o): e.xreplace(start).xreplace(defaults)
            for o, e in zip(spec.outputs, spec.output_exprs, strict=True)
        }
        for key, value in start.items():
            values.setdefault(key, value.xreplace(start).xreplace(defaults).xreplace(start))
        values |= defaults
        s0 = initial_slack(spec.constraints, spec.barrier, values)
        mu, slack = schedule(spec.barrier, s0, time)
        objective = f0
        f0 = barrier_objective(f0, spec.constraints, mu, slack)
    return f0, objective, mu, slack


def _check_mass_matrix(
    spec: Spec, mechanics: Mechanics, sampler: Sampler, at_mass: np.ndarray, at_rhs: np.ndarray
) -> None:
    """``M`` is symmetric (at random points), positive definite at the initial state and there.

    ``at_mass`` and ``at_rhs`` are ``M`` and ``[F | B]`` at the sampler's points.

    Raises
    ------
    SpecError
        When ``M[i][j]`` and ``M[j][i]`` differ.
    AssumptionError
        When ``M`` is not positive definite (or not finite) at the initial state with
        the parameters at their defaults, or at one of the random points; or an entry of
        ``M``, ``F`` or ``B`` is infinite at one of them.
    """
    field = "system.mechanics.mass_matrix"
    mass = mechanics.mass_matrix
    n = len(mass)
    for i in range(n):
        for j in range(i):
            if mass[i][j] != mass[j][i] and not sampler.is_zero(mass[i][j] - mass[j][i]):
                raise SpecError(
                    spec.source,
                    f"{field}[{i}][{j}]",
                    f"M is not symmetric: M[{i}][{j}] = {clip(sx.text(mass[i][j]))} but "
                    f"M[{j}][{i}] = {clip(sx.text(mass[j][i]))}",
                )
    given = dict(spec.initial_state)
    values: dict[sx.Expr, object] = {sx.symbol(n): v for n, v in spec.parameters}
    values |= {sx.symbol(name): float(given.get(name, 0.0)) for name in spec.states}
    with np.errstate(all="ignore"):
        start = mass_matrix_at(mechanics, values)[0]
    where = "at the initial state" + ("" if given else " (every state 0)")
    if not np.all(np.isfinite(start)):
        raise AssumptionError(spec.source, field, f"M is not finite {where}")
    smallest = float(np.linalg.eigvalsh(start)[0])
    scale = float(np.max(np.abs(start))) if start.size else 0.0
    if not smallest > PIVOT_TOLERANCE * scale:
        raise AssumptionError(
            spec.source,
            field,
            f"M is not positive definite {where}: its smallest eigenvalue is {smallest:.6g}",
        )
    # Where the symmetry check sampled M: finite, and positive definite where defined.
    problem = problem_at_samples(mechanics, at_mass, at_rhs, sampler, PIVOT_TOLERANCE)
    if problem is not None:
        raise AssumptionError(spec.source, *problem)


def start_evaluator(
    states: Sequence[sx.Expr],
    initial: Sequence[float],
    defaults: Mapping[sx.Expr, float],
    mechanics: Mechanics | None,
) -> Evaluator:
    """An evaluator of expressions at the initial state with the default parameters.

    A mass-matrix plant's run-time symbols (``M^-1 F``, ``M^-1 B``) are solved for
    numerically there. The start's warnings and the extended-state observer's start
    evaluate the law's pieces with it.
    """
    values: dict[sx.Expr, Any] = {q: float(v) for q, v in defaults.items()}
    values |= {sym: float(v) for sym, v in zip(states, initial, strict=True)}
    if mechanics is not None:
        with np.errstate(all="ignore"):
            solved = implicit_values(mechanics, values)
        values |= {sym: float(v[0]) for sym, v in solved.items()}
    return Evaluator(values)
