"""The objective's programs: f0's gradient and Hessian, and the gradient jet.

f0's gradient and Hessian are straight-line programs; the jet ``grad^(j) f0`` is taken along
the output jet (Lemma "Gradient Time Differentiation").
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass

import numpy as np

from tvopt_codegen import symbolic as sx
from tvopt_codegen.derivation.convexity import _check_convexity
from tvopt_codegen.derivation.linearization import _Linearization, _States
from tvopt_codegen.derivation.meter import _Meter, tree_size
from tvopt_codegen.derivation.model import Model
from tvopt_codegen.derivation.record import Convexity, _sparse_hessian, jet_symbol
from tvopt_codegen.maths.jet import (
    Program,
    atomize,
    jacobian,
    next_derivative,
    partial,
    without_atoms,
)
from tvopt_codegen.maths.lie import (
    nonzero_entries,
)


def _sparse_gradient(f0: sx.Expr, y: Sequence[sx.Expr]) -> sx.Expr:
    """Gradient of ``f0``, differentiating only where a variable occurs.

    A sum over agents is split into its terms once; each gradient entry sums the
    derivatives of the terms that contain its output: for N agents coupled to their
    neighbours this is linear in N where differentiating the whole sum is quadratic.
    """
    terms = f0.args if f0.is_Add else (f0,)
    by_output: dict[sx.Expr, list[sx.Expr]] = {yi: [] for yi in y}
    for term in terms:
        for yi in term.free_symbols & by_output.keys():
            by_output[yi].append(term)
    return sx.ImmutableMatrix([sx.Add(*(partial(term, yi) for term in by_output[yi])) for yi in y])


def _polynomial_hessian(gradient: sx.Expr, y: Sequence[sx.Expr]) -> sx.Expr | None:
    """The Hessian as expressions when the gradient is polynomial in ``y``, else ``None``.

    Quadratic objectives, the common case, have a Hessian free of ``y``: a matrix of
    numbers is inverted once at generation time, and one of parameters is checked for
    convexity exactly, at their defaults, instead of by sampling.
    """
    if not all(sx.is_polynomial(g, y) for g in gradient):
        return None
    return _sparse_hessian(gradient, y)


def _affine_split(gradient: sx.Expr, hessian: sx.Expr, y: Sequence[sx.Expr]) -> sx.Expr:
    """The gradient of a quadratic f0 written ``Hess y + b(t)``, ``b`` its value at y = 0.

    The same function, in the form whose time derivatives are cheapest: ``y^(j)`` enters
    ``grad^(j) = Hess y^(j) + b^(j)`` once, where differentiating the objective's own form
    (``S (y - o1) + (1 - S) (y - o2)``, a switch between targets) multiplies every
    ``y^(i)`` by every derivative of every weight. For the switching unicycle the
    operations that depend on the state drop from 118 to 72; the rest depend on time
    and parameters alone, which a batch of states at one time shares.
    """
    at_zero = _dropping(set(y))
    # The Hessian's nonzero entries by row: a team's is almost all zeros.
    rows: list[list[sx.Expr]] = [[] for _ in y]
    for i, j, entry in nonzero_entries(hessian):
        rows[i].append(entry * y[j])
    return sx.ImmutableMatrix([sx.Add(*rows[i]) + at_zero(gi) for i, gi in enumerate(gradient)])


def _signal_derivatives(
    expr: sx.Expr, t: sx.Expr, k: int, meter: Callable[[sx.Expr], None]
) -> list[sx.Expr] | None:
    """A signal and its first ``k`` time derivatives as expressions, unless they swell.

    Differentiated as expressions, the usual signals (polynomials, a tanh switch)
    print folded and readable: ``t/50``, not ``2*t`` times ``1/100``. A derivative
    more than four times the size of the signal is a sign of nesting, whose k-th
    derivative swells like ``size**(k+1)``: ``None`` then, and the caller takes it as
    a program.
    """
    limit = 4 * tree_size(expr, 10**6) + 50
    chain = [expr]
    for _ in range(k):
        # jet.partial builds SymPy's diff's very expression, without its Derivative
        # machinery (two milliseconds a signal and order, for every agent of a team).
        derivative = partial(chain[-1], t)
        if tree_size(derivative, limit) > limit:
            return None
        meter(derivative)
        chain.append(derivative)
    return chain


@dataclass(frozen=True)
class _Objective:
    """The gradient of f0 as a program, its Hessian, and the convexity evidence."""

    gradient: sx.Expr
    program: Program
    current: tuple[sx.Expr, ...]
    hessian_program: Program
    hessian_entries: tuple[tuple[tuple[int, int], sx.Expr], ...]
    convexity: Convexity
    warnings: tuple[str, ...]


@dataclass(frozen=True)
class _GradientJet:
    """``grad^(j) f0`` for ``j < k``, ``rest``, and the jets of y, signals and references."""

    reference_jet: tuple[tuple[sx.Expr, ...], ...]
    reference_order: int
    y_jet: tuple[tuple[sx.Expr, ...], ...]
    y_values: tuple[tuple[sx.Expr, ...], ...]
    signal_jet: tuple[tuple[sx.Expr, ...], ...]
    signal_program: Program
    signal_values: tuple[tuple[sx.Expr, ...], ...]
    program: Program
    grad_jet: tuple[tuple[sx.Expr, ...], ...]
    rest_program: Program
    rest: tuple[sx.Expr, ...]


def _programs_of(
    expr: sx.Expr, variables: Sequence[sx.Expr], names: Iterator[sx.Expr], meter: _Meter
) -> tuple[
    sx.Expr,
    Program,
    tuple[sx.Expr, ...],
    Program,
    tuple[tuple[tuple[int, int], sx.Expr], ...],
    sx.Expr | None,
]:
    """The gradient of ``expr`` in ``variables`` as a program, and its Hessian's entries.

    Returns the gradient (as expressions), its three-address program and outputs, the
    Hessian's program and nonzero lower entries ``(i, j), i >= j`` over it (numbers when
    the Hessian is constant), and the Hessian as expressions when the gradient is
    polynomial in the variables (else None).
    """
    m = len(variables)
    meter(expr)
    gradient = _sparse_gradient(expr, variables)
    meter.matrix(gradient)
    polynomial = _polynomial_hessian(gradient, variables)
    if polynomial is not None and not polynomial.free_symbols & set(variables):
        gradient = _affine_split(gradient, polynomial, variables)
        meter.matrix(gradient)
    # Three-address form: the Hessian and every total derivative below are taken
    # assignment by assignment (jet.py), never on the nested gradient.
    program, current = atomize(list(gradient), names)
    hessian_program = Program(())
    if polynomial is not None and all(entry.is_Number for entry in polynomial):
        hessian_entries = tuple(
            ((i, j), polynomial[i, j])
            for i in range(m)
            for j in range(i + 1)
            if polynomial[i, j] != 0
        )
    else:
        hessian_program, columns = jacobian(program, current, variables, names, meter)
        # Equal by Schwarz; either side may be the one that is structurally nonzero.
        lower = {(j, i): e for i in range(m) for j, e in columns[i].items() if j > i}
        lower |= {(i, j): e for i in range(m) for j, e in columns[i].items() if j <= i}
        hessian_entries = tuple(sorted(lower.items()))
    return gradient, program, tuple(current), hessian_program, hessian_entries, polynomial


def _objective(
    model: Model, states: _States, names: Iterator[sx.Expr], meter: _Meter
) -> _Objective:
    """The gradient of f0 as a program, its Hessian, and f0's convexity where it matters."""
    gradient, program, current, hessian_program, hessian_entries, polynomial = _programs_of(
        model.f0, model.y, names, meter
    )
    y0 = objective_start(model, states).tolist()
    convexity, warnings = _check_convexity(
        model,
        polynomial,
        program + hessian_program,
        current,
        hessian_entries,
        y0,
        model.settings.t_final,
        model.source,
    )
    return _Objective(
        gradient,
        program,
        tuple(current),
        hessian_program,
        hessian_entries,
        convexity,
        warnings,
    )


def _gradient_jet(
    model: Model,
    k: int,
    objective: _Objective,
    lin: _Linearization,
    states: _States,
    names: Iterator[sx.Expr],
    meter: _Meter,
) -> _GradientJet:
    """Total time derivatives of the gradient up to order k (the paper's lemma).

    With equalities the gradient is the KKT map's, over the outputs and the multipliers,
    whose jets are the controller's multiplier chains.
    """
    variables = (*model.y, *model.multipliers)
    y_jet = tuple(tuple(jet_symbol(y.name, j) for j in range(k + 1)) for y in variables)
    signal_jet = tuple(tuple(jet_symbol(s.name, q) for q in range(k + 1)) for s, _ in model.signals)
    reference_jet = tuple(
        tuple(jet_symbol(r.name, q) for q in range(k + 1)) for r in model.references
    )
    reference_rates = {chain[j]: chain[j + 1] for chain in reference_jet for j in range(k)}
    rates: dict[sx.Expr, sx.Expr] = {model.t: sx.Integer(1)} | reference_rates
    for chain in (*y_jet, *signal_jet):
        for j in range(k):
            rates[chain[j]] = chain[j + 1]
    program = objective.program
    current: Sequence[sx.Expr] = objective.current
    grad_jet = [tuple(current)]
    rest_program = Program(())
    rest: tuple[sx.Expr, ...] = ()
    for order in range(1, k + 1):
        new, current, rates = next_derivative(program, current, rates, names, meter)
        if order < k:
            program = program + new
            grad_jet.append(tuple(current))
        else:
            # grad^(k) is affine in y^(k) with slope Hess: dropping y^(k) leaves the rest.
            drop = _dropping({chain[k] for chain in y_jet})
            rest_program, rest = without_atoms(
                [(s, drop(e)) for s, e in new.assignments], [drop(e) for e in current]
            )
    signal_program = Program(())
    signal_chains: list[tuple[sx.Expr, ...]] = []
    measured = set(model.references)
    for _, expr in model.signals:
        # A signal of references moves with their jets: differentiated as a program.
        derivatives = (
            None if expr.free_symbols & measured else _signal_derivatives(expr, model.t, k, meter)
        )
        if derivatives is None:
            # Its derivatives swell (a nested signal): differentiate it as a program,
            # linear in its size per order, like the gradient.
            part, chain = atomize([expr], names)
            derivatives = [chain[0]]
            signal_rates: dict[sx.Expr, sx.Expr] = {model.t: sx.Integer(1)} | reference_rates
            for _ in range(k):
                new, chain, signal_rates = next_derivative(part, chain, signal_rates, names, meter)
                part = part + new
                derivatives.append(chain[0])
            signal_program = signal_program + part
        signal_chains.append(tuple(derivatives))
    state_of = dict(zip(states.names, states.symbols, strict=True))
    degrees = lin.degrees
    # With the extended-state observer the law reads its estimates of y^(j), 1 <= j < r_i,
    # where it read Phi(x): under mismatch L_f^j h is not y^(j). y itself is measured,
    # h(x): the objective, its barriers and the optimality error's first row read the
    # plant's own outputs, as without the observer.
    below = (
        [
            [lin.lie[i][0], *(state_of[name] for name in chain[1:-1])]
            for i, chain in enumerate(states.eso)
        ]
        if states.eso
        else [lin.lie[i][: degrees[i]] for i in range(len(model.y))]
    )
    y_values = tuple(
        tuple(
            below[i][j] if j < degrees[i] else state_of[states.padding[i][j - degrees[i]]]
            for j in range(k)
        )
        for i in range(len(model.y))
    ) + tuple(tuple(state_of[name] for name in chain) for chain in states.multipliers)
    return _GradientJet(
        reference_jet,
        _reference_order(
            reference_jet,
            (program, rest_program, signal_program),
            (*grad_jet, rest, *signal_chains),
        ),
        y_jet,
        y_values,
        signal_jet,
        signal_program,
        tuple(signal_chains),
        program,
        tuple(grad_jet),
        rest_program,
        rest,
    )


def _reference_order(
    reference_jet: Sequence[Sequence[sx.Expr]],
    programs: Sequence[Program],
    outputs: Sequence[Sequence[sx.Expr]],
) -> int:
    """The highest derivative of a reference that the law or the optimality error reads.

    0 without references, the programs unread: on SymEngine each expression's symbols
    are a new Python set, a tenth of a long jet's time.
    """
    if not reference_jet:
        return 0
    used: set[sx.Expr] = set()
    for part in programs:
        for _, value in part.assignments:
            used |= value.free_symbols
    for exprs in outputs:
        for value in exprs:
            used |= sx.sympify(value).free_symbols
    return max(
        (j for chain in reference_jet for j, symbol in enumerate(chain) if symbol in used),
        default=0,
    )


def _dropping(symbols: set[sx.Expr]) -> Callable[[sx.Expr], sx.Expr]:
    """A function setting ``symbols`` to 0 in an expression, the expression itself if none occur.

    Each expression is rebuilt over the symbols it holds only: SymEngine's ``xreplace``
    copies its whole mapping first, one per output of a team, into every one of the
    jet's thousands of small assignments (half a second for 32 agents).
    """

    def drop(expr: sx.Expr) -> sx.Expr:
        held = symbols & expr.free_symbols
        return expr.xreplace(dict.fromkeys(held, sx.Integer(0))) if held else expr

    return drop


def objective_start(model: Model, states: _States) -> np.ndarray:
    """The outputs at the initial state, parameters at their defaults."""
    values = {sym: sx.real(v) for sym, v in zip(states.symbols, states.initial, strict=True)}
    values |= {q: sx.real(v) for q, v in zip(model.params, model.defaults, strict=True)}
    # Each output gets only the values of its own symbols: SymEngine converts the whole
    # mapping on every xreplace, and a team's (every state of every agent) made this
    # quadratic in the agents (0.3 s a call at 128).
    return np.array(
        [float(h.xreplace({s: values[s] for s in h.free_symbols if s in values})) for h in model.h]
    )
