"""The derivation itself: :func:`derive` runs the stages in the paper's order.

It fills the :class:`~tvopt_codegen.derivation.record.Derivation` that every later stage
reads.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

from tvopt_codegen.derivation.convexity import _constraint_convexity
from tvopt_codegen.derivation.equalities import (
    _dependent_set,
    _equality_checks,
    _lagrangian,
    _multipliers_start,
)
from tvopt_codegen.derivation.law import Law, control_law, symmetric_dense
from tvopt_codegen.derivation.linearization import (
    _closed_loop_states,
    _Decoupling,
    _decoupling,
    _error_dynamics,
    _ErrorDynamics,
    _Linearization,
    _linearize,
    _singular_start,
    _States,
    _without_extension,
)
from tvopt_codegen.derivation.meter import _Clock, _Meter
from tvopt_codegen.derivation.model import Model, build_model
from tvopt_codegen.derivation.objective import (
    _gradient_jet,
    _GradientJet,
    _Objective,
    _objective,
    objective_start,
)
from tvopt_codegen.derivation.record import (
    ClosedLoopStage,
    DecouplingStage,
    Derivation,
    ErrorDynamicsStage,
    EstimatorStage,
    JetStage,
    LinearizationStage,
    ObjectiveStage,
)
from tvopt_codegen.derivation.rejection import Rejection, initial_estimates, rejection
from tvopt_codegen.derivation.robust import robustness
from tvopt_codegen.errors import AssumptionError
from tvopt_codegen.limits import Budget
from tvopt_codegen.maths import hurwitz
from tvopt_codegen.maths.jet import (
    fresh_symbols,
)
from tvopt_codegen.spec import Spec, spec_from_dict
from tvopt_codegen.spec.estimator import estimator_gains, estimator_order
from tvopt_codegen.spec.features import refuse as refuse_pairs


def derive(
    spec: Spec | Mapping[str, Any],
    progress: Callable[[str, int, int, float], None] | None = None,
    budget: Budget | None = None,
) -> Derivation:
    """Run the paper's derivation for a spec.

    Parameters
    ----------
    spec : Spec or mapping
        A validated spec, or a mapping laid out as a spec file (see
        :func:`~tvopt_codegen.spec.spec_from_dict`).
    progress : callable, optional
        Called as ``progress(stage, expressions, nodes, seconds)`` when each step
        starts and every half second within one: the step's name, how many expressions
        the derivation has built so far, their total size in nodes (operations and
        atoms, the measure of the size budget) and the time since it began.
    budget : Budget, optional
        Time and size limits (default :class:`Budget`).

    Returns
    -------
    Derivation
        Everything the code generators and the report need.

    Raises
    ------
    AssumptionError
        When the extended plant has no vector relative degree, is not full-state
        linearizable, has a decoupling matrix singular everywhere (with a
        prolongation suggestion), when f0 is not strongly convex, or when the error
        dynamics are not Hurwitz or have the wrong order.
    SpecError
        When generated state names collide with declared names, or the initial state
        names an unknown state.
    BudgetError
        When a stage takes longer or builds larger expressions than the budget allows.
    """
    # A list of stage calls; the work is in the stage functions, the record in _record.
    if not isinstance(spec, Spec):
        spec = spec_from_dict(spec)
    meter = _Meter(spec.source, budget or Budget(), progress)
    # The budget holds inside each call too (SymPy's at the border), as the command line's
    # timer holds it.
    with meter.interrupting():
        return _derive(spec, meter)


def _derive(spec: Spec, meter: _Meter) -> Derivation:
    """:func:`derive`'s stages, in order, metered by ``meter``."""
    clock = _Clock()

    def say(stage: str) -> None:
        meter.stage = stage
        meter.report()

    # Two features that do not combine stop here, in one line naming both (docs/features.md).
    refuse_pairs(spec)
    say("model")
    model = build_model(spec)
    clock.mark("model")
    say("relative degree")
    lin = _linearize(model, meter)
    clock.mark("relative degree")
    say("error dynamics")
    dynamics = _error_dynamics(model.settings, max(lin.degrees))
    k = dynamics.k
    states = _closed_loop_states(model, lin, k)
    clock.mark("error dynamics")
    say("decoupling matrix")
    decoupling = _decoupling(lin, meter, model.mechanics)
    clock.mark("decoupling matrix")
    say("objective")
    # A leading underscore: no user name can take it (spec.py rejects those). One
    # sequence for the gradient, the Hessian and the jet: their names never collide.
    names = fresh_symbols("_g")
    # Constraints first: an infeasible or non-convex one explains itself before the
    # barrier objective's convexity check would stumble on it.
    constraint_warnings = _constraint_convexity(model, objective_start(model, states))
    objective = _objective(model, states, names, meter)
    equality_warnings = _equality_checks(model, objective_start(model, states))
    kkt = _lagrangian(model, objective, names, meter)
    states = _multipliers_start(model, states, objective)
    ext = lin.extension
    warnings = (
        objective.warnings
        + _start_warnings(model, lin, decoupling, states)
        + constraint_warnings
        + equality_warnings
        + _reference_warnings(model)
    )
    clock.mark("objective")
    say("gradient jet")
    settings = model.settings
    eso = None
    if settings.robust.eso is not None:
        eso = rejection(settings.robust.eso, lin.degrees, model.output_names)
        states = _observer_start(model, lin, states)
    jet = _gradient_jet(model, k, kkt, lin, states, names, meter)
    clock.mark("gradient jet")
    say("error bound")
    rate, rate_exact = hurwitz.certified_rate(dynamics.coefficients)
    constant = hurwitz.transient_constant(dynamics.coefficients, rate)
    unextended = _without_extension(model) if ext.counts else None
    clock.mark("error bound")
    say("law")
    law = control_law(
        hessian_entries=kkt.hessian_entries,
        grad_jet=jet.grad_jet,
        rest=jet.rest,
        R=lin.R,
        extension=ext,
        plant_inputs=model.u,
        padding=states.padding,
        states=states.symbols,
        state_names=states.names,
        multipliers=states.multipliers,
        integral=states.integral,
        eso=eso,
        outputs=tuple(model.h),
    )
    estimator = None
    if settings.estimator is not None:
        order = estimator_order(settings.estimator, jet.reference_order)
        try:
            estimator = EstimatorStage(order, estimator_gains(settings.estimator, order))
        except ValueError as exc:
            raise AssumptionError(settings.source, "references.estimator.kind", str(exc)) from None
    clock.mark("law")
    return _record(
        spec,
        model,
        _Stages(lin, dynamics, states, decoupling, objective, kkt, jet, eso, estimator),
        law,
        warnings,
        (rate, rate_exact, constant),
        unextended,
        tuple(clock.marks),
    )


def _observer_start(model: Model, lin: _Linearization, states: _States) -> _States:
    """The closed-loop start with the observer's estimates at ``Phi(x0)``, ``d_hat = 0``.

    There the observer's error is zero: on the model the closed loop is the plain law's.
    An estimate the spec's initial state gives keeps its value.
    """
    first = states.names.index(states.eso[0][0])
    count = sum(len(chain) for chain in states.eso)
    phi = [lin.lie[i][: lin.degrees[i]] for i in range(len(lin.degrees))]
    defaults = dict(zip(model.params, model.defaults, strict=True))
    values = initial_estimates(phi, states.symbols, states.initial, defaults, model.mechanics)
    given = dict(model.settings.initial_state)
    names = states.names[first : first + count]
    values = tuple(
        float(given[name]) if name in given else value
        for name, value in zip(names, values, strict=True)
    )
    initial = (*states.initial[:first], *values, *states.initial[first + count :])
    return dataclasses.replace(states, initial=initial)


def _start_warnings(
    model: Model, lin: _Linearization, decoupling: _Decoupling, states: _States
) -> tuple[str, ...]:
    """Warnings about the start: R or p singular or undefined there."""
    defaults = dict(zip(model.params, model.defaults, strict=True))
    extension = lin.extension
    return _singular_start(
        lin.R,
        decoupling.p,
        states.symbols,
        states.initial,
        defaults,
        states.names[len(model.x) : len(model.x) + len(extension.states)],
        model.mechanics,
    )


def _reference_warnings(model: Model) -> tuple[str, ...]:
    """A warning for references with no nominal closed form (convexity checked at 0)."""
    unknown = [r.name for r in model.references if r not in dict(model.nominal)]
    if not unknown:
        return ()
    return (
        f"references {', '.join(unknown)} have no nominal closed form: f0's convexity "
        "was checked with them at 0 (give [references] nominal to check along it)",
    )


@dataclass(frozen=True)
class _Stages:
    """The stage records :func:`derive` gathers, handed to :func:`_record` together."""

    lin: _Linearization
    dynamics: _ErrorDynamics
    states: _States
    decoupling: _Decoupling
    objective: _Objective
    kkt: _Objective
    jet: _GradientJet
    eso: Rejection | None = None
    estimator: EstimatorStage | None = None


def _record(
    spec: Spec,
    model: Model,
    stages: _Stages,
    law: Law,
    warnings: tuple[str, ...],
    bound: tuple[float, bool, float],
    unextended: str | None,
    timings: tuple[tuple[str, float], ...],
) -> Derivation:
    """The flat :class:`Derivation` from the stage records.

    ``bound`` is the certified rate, whether it is exact, and the transient constant.
    """
    lin, dynamics, states = stages.lin, stages.dynamics, stages.states
    decoupling, objective, kkt, jet = stages.decoupling, stages.objective, stages.kkt, stages.jet
    rate, rate_exact, constant = bound
    k = dynamics.k
    ext = lin.extension
    return Derivation(
        spec=spec,
        model=model,
        linearization=LinearizationStage(
            extension=ext,
            relative_degree=lin.degrees,
            lie=lin.lie,
            R=lin.R,
            unextended=unextended,
            extension_search=lin.searched,
        ),
        decoupling=DecouplingStage(
            p=decoupling.p,
            phi=decoupling.phi,
            A=decoupling.A,
            B=decoupling.B,
            det_R=decoupling.det_R,
            det_R_note=decoupling.det_R_note,
            singular_set=decoupling.singular,
            undefined_set=decoupling.undefined,
            dependent_set=_dependent_set(model),
        ),
        closed_loop=ClosedLoopStage(
            padding=states.padding,
            state_names=states.names,
            states=states.symbols,
            initial_state=states.initial,
            multiplier_states=states.multipliers,
            integral_states=states.integral,
        ),
        dynamics=ErrorDynamicsStage(
            k=k,
            coefficients=dynamics.coefficients,
            eigenvalues=dynamics.eigenvalues,
            decay_rate=dynamics.decay_rate,
            uniform=all(r == k for r in lin.degrees),
            certified_rate=rate,
            certified_rate_exact=rate_exact,
            transient_constant=constant,
            integral_pole=dynamics.integral_pole,
            bumpless=dynamics.bumpless,
        ),
        objective=ObjectiveStage(
            gradient=objective.gradient,
            hessian_program=kkt.hessian_program,
            hessian_entries=kkt.hessian_entries,
            convexity=objective.convexity,
            objective_program=objective.program + objective.hessian_program,
            objective_gradient=objective.current,
            objective_hessian=symmetric_dense(objective.hessian_entries, len(model.y)),
            kkt_gradient=kkt.gradient if model.equalities else None,
        ),
        jet=JetStage(
            y_jet=jet.y_jet,
            y_jet_values=jet.y_values,
            signal_jet=jet.signal_jet,
            signal_program=jet.signal_program,
            signal_jet_values=jet.signal_values,
            jet_program=jet.program,
            grad_jet=jet.grad_jet,
            rest_program=jet.rest_program,
            rest=jet.rest,
            reference_jet=jet.reference_jet,
            reference_order=jet.reference_order,
        ),
        law=law,
        warnings=warnings,
        timings=timings,
        rejection=stages.eso,
        robustness=robustness(
            model,
            law,
            ext,
            states.names,
            states.integral,
            dynamics.bumpless,
            stages.eso,
        ),
        estimator=stages.estimator,
    )
