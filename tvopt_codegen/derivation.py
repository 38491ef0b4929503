"""Stage 3: everything the paper derives, as one :class:`Derivation`.

Both the code generators and the report read this object; nothing downstream
re-derives mathematics. The steps follow the paper: dynamic extension and vector
relative degree (Lemmas 1-2), padding chains for unequal relative degrees (Section
IV-B), the gradient jet ``grad^(j) f0`` (Lemma "Gradient Time Differentiation") and the
implicit law ``y_imp^(k)`` (equation y_kth_derivative_solution) feeding
``u = alpha + beta R^-1 [v - p]`` (Theorems for uniform and non-uniform degree).
"""

from __future__ import annotations

import functools
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import sympy as sp

from tvopt_codegen import hurwitz
from tvopt_codegen.constraints import least_violation, nonconvex
from tvopt_codegen.errors import AssumptionError, BudgetError, SpecError
from tvopt_codegen.estimator import estimator_gains
from tvopt_codegen.jet import (
    Program,
    atomize,
    fresh_symbols,
    jacobian,
    next_derivative,
    partial,
)
from tvopt_codegen.law import Law, control_law, symmetric_dense
from tvopt_codegen.lie import (
    Extension,
    RelativeDegree,
    Sampler,
    brunovsky,
    extend,
    from_entries,
    generic_rank,
    nonzero_entries,
    relative_degree,
)
from tvopt_codegen.limits import Budget
from tvopt_codegen.model import Model, build_model
from tvopt_codegen.numeric import Evaluator, Tape
from tvopt_codegen.sparse import reverse_cuthill_mckee
from tvopt_codegen.spec import Spec, spec_from_dict


def jet_symbol(name: str, order: int) -> sp.Symbol:
    """The symbol for the ``order``-th time derivative of ``name`` (y1, y1', y1'', ...).

    The primes cannot occur in user names, so jet symbols never collide with them.
    """
    if order == 0:
        return sp.Symbol(name, real=True)
    mark = "'" * order if order <= 3 else f"^({order})"
    return sp.Symbol(f"{name}{mark}", real=True)


@dataclass(frozen=True)
class Convexity:
    """Evidence for the strong convexity of f0 (paper, Assumption 1).

    Attributes
    ----------
    method : str
        ``"constant Hessian"`` (exact) or ``"sampled"``.
    m_f : float
        Smallest Hessian eigenvalue found: a lower bound estimate of the convexity
        modulus.
    points : int
        Number of sampled (y, t) points at which the Hessian was finite.
    """

    method: str
    m_f: float
    points: int


@dataclass(frozen=True)
class Derivation:
    """The complete derivation for one spec.

    Attributes
    ----------
    spec, model : Spec, Model
        The inputs of the derivation.
    extension : Extension
        The extended plant (equal to the plant when nothing is prolonged).
    relative_degree : tuple of int
        ``r_i`` per output, of the extended system.
    lie : tuple of tuple of sympy.Expr
        ``lie[i][j] = L_f^j h_i``, ``j = 0 .. r_i``.
    R, p, phi : sympy.ImmutableMatrix
        Decoupling matrix (m, m), ``p = col(L_f^{r_i} h_i)`` and coordinates ``Phi``.
    A, B : sympy.ImmutableMatrix
        Brunovsky pair of the extended system.
    k : int
        ``max r_i``: the order of the error dynamics.
    padding : tuple of tuple of str
        Names of the padding states ``xi_<output>_<j>`` per output.
    state_names : tuple of str
        Closed-loop state order: plant, extension, padding, multiplier chains.
    states : tuple of sympy.Symbol
        Symbols of ``state_names``.
    det_R : sympy.Expr or None
        ``det R`` factored, when computed symbolically (m <= 4).
    det_R_note : str
        Why ``det_R`` is None (empty when it was computed), for the summary and report.
    singular_set : tuple of str
        Conditions under which ``det R`` vanishes, in words.
    undefined_set : tuple of str
        Conditions under which R or p (and so the law) is undefined (a denominator
        or a cosine under ``tan`` vanishes, ...), in words.
    gradient : sympy.ImmutableMatrix
        ``grad_y f0`` (m, 1) over ``y``, signals, parameters and t.
    hessian_program : Program
        Assignments computing the Hessian from :attr:`jet_program` (forward mode over
        its gradient part, :func:`~tvopt_codegen.jet.jacobian`); empty when it is
        constant.
    hessian_entries : tuple of ((int, int), sympy.Expr)
        The nonzero entries ``(i, j), i >= j`` of the lower triangle of ``grad_yy f0``,
        over the programs' symbols (numbers when the Hessian is constant). The
        generated code reads the Hessian from these.
    y_jet : tuple of tuple of sympy.Symbol
        ``y_jet[i][j]`` is the symbol of ``y_i^(j)``, ``j = 0 .. k``.
    y_jet_values : tuple of tuple of sympy.Expr
        ``y_i^(j)`` for ``j < k`` as a function of the closed-loop state.
    signal_jet : tuple of tuple of sympy.Symbol
        ``signal_jet[l][q]`` is the symbol of the q-th derivative of signal l.
    signal_program : Program
        Straight-line program of the signals and their time derivatives.
    signal_jet_values : tuple of tuple of sympy.Expr
        Those derivatives over :attr:`signal_program`, ``t`` and the parameters.
    jet_program : Program
        Straight-line program of the gradient jet (see :mod:`tvopt_codegen.jet`).
    grad_jet : tuple of tuple of sympy.Expr
        ``grad^(j) f0`` for ``j = 0 .. k-1`` over the program's symbols.
    rest_program : Program
        Extra assignments used by :attr:`rest` only.
    rest : tuple of sympy.Expr
        ``grad^(k) f0`` with ``y^(k) = 0``, so ``grad^(k) f0 = Hess y^(k) + rest``.
    coefficients : tuple of float
        ``a_0 .. a_{k-1}`` of H.
    eigenvalues : tuple of complex
        Eigenvalues of the companion matrix.
    decay_rate : float
        ``alpha = -max Re(lambda)``.
    uniform : bool
        Whether all relative degrees equal k (no padding).
    convexity : Convexity
        Strong convexity evidence.
    initial_state : tuple of float
        Default initial state in :attr:`state_names` order.
    unextended : str or None
        Why the extension is needed: what the plant lacks without it (``None`` when
        nothing is prolonged).
    extension_search : tuple of str
        The prolongations the automatic search tried, in order (empty when the spec
        gave the extension).
    certified_rate : float
        The alpha of ``|expm(H t)| <= c e^{-alpha t}`` (the decay rate, or 10% less with
        repeated poles).
    certified_rate_exact : bool
        Whether ``certified_rate`` is the decay rate itself (the poles are distinct).
    warnings : tuple of str
        What the user should know but that does not stop the derivation (f0 strongly
        convex only near its minimiser, a singular default state), one line each.
    transient_constant : float
        That c, computed.
    law : Law
        The control law written down from the above (:mod:`tvopt_codegen.law`):
        everything the code generators evaluate.
    reference_jet : tuple of tuple of sympy.Symbol
        ``reference_jet[l][q]``: the q-th derivative of reference l, ``q = 0 .. k``
        (supplied by the caller, never derived).
    reference_order : int
        The highest derivative of a reference the law reads (0 without references).
    timings : tuple of (str, float)
        Seconds spent per derivation step.
    objective_program : Program
        The program of f0's own gradient and Hessian (over the outputs): the generated
        ``gradient`` and ``hessian`` functions evaluate it. With equalities the jet's
        programs are the KKT system's instead.
    objective_gradient, objective_hessian : tuple of sympy.Expr
        f0's gradient (m) and Hessian ((m, m), row-major) over that program.
    multiplier_states : tuple of tuple of str
        With equality constraints, each multiplier's chain of controller states
        ``nu_<name>_0 .. nu_<name>_<k-1>`` (the multiplier and its derivatives).
    kkt_gradient : sympy.ImmutableMatrix or None
        With equalities, the KKT map ``F = [grad f0 + J_a^T nu; a]`` over (y, nu).
    dependent_set : tuple of str
        Where the equalities' gradients are dependent (``det(J_a J_a^T) = 0``, where the
        KKT matrix is singular), in words; empty where nowhere (or without equalities).

    With equality constraints, :attr:`y_jet`, :attr:`grad_jet`, :attr:`rest`,
    :attr:`jet_program`, :attr:`hessian_program` and :attr:`hessian_entries` are those of
    the Lagrangian ``L = f0 + nu^T a`` over the outputs and then the multipliers (m + q
    entries, :attr:`n_kkt`): the law is the paper's, written for ``L``.
    """

    spec: Spec
    model: Model
    extension: Extension
    relative_degree: tuple[int, ...]
    lie: tuple[tuple[sp.Expr, ...], ...]
    R: sp.ImmutableMatrix
    p: sp.ImmutableMatrix
    phi: sp.ImmutableMatrix
    A: sp.ImmutableMatrix
    B: sp.ImmutableMatrix
    k: int
    padding: tuple[tuple[str, ...], ...]
    state_names: tuple[str, ...]
    states: tuple[sp.Symbol, ...]
    det_R: sp.Expr | None
    det_R_note: str
    singular_set: tuple[str, ...]
    undefined_set: tuple[str, ...]
    gradient: sp.ImmutableMatrix
    hessian_program: Program
    hessian_entries: tuple[tuple[tuple[int, int], sp.Expr], ...]
    y_jet: tuple[tuple[sp.Symbol, ...], ...]
    y_jet_values: tuple[tuple[sp.Expr, ...], ...]
    signal_jet: tuple[tuple[sp.Symbol, ...], ...]
    signal_program: Program
    signal_jet_values: tuple[tuple[sp.Expr, ...], ...]
    jet_program: Program
    grad_jet: tuple[tuple[sp.Expr, ...], ...]
    rest_program: Program
    rest: tuple[sp.Expr, ...]
    coefficients: tuple[float, ...]
    eigenvalues: tuple[complex, ...]
    decay_rate: float
    uniform: bool
    convexity: Convexity
    initial_state: tuple[float, ...]
    unextended: str | None
    extension_search: tuple[str, ...]
    certified_rate: float
    certified_rate_exact: bool
    warnings: tuple[str, ...]
    transient_constant: float
    law: Law
    timings: tuple[tuple[str, float], ...]
    reference_jet: tuple[tuple[sp.Symbol, ...], ...] = ()
    reference_order: int = 0
    objective_program: Program = Program(())
    objective_gradient: tuple[sp.Expr, ...] = ()
    objective_hessian: tuple[sp.Expr, ...] = ()
    multiplier_states: tuple[tuple[str, ...], ...] = ()
    kkt_gradient: sp.ImmutableMatrix | None = None
    dependent_set: tuple[str, ...] = ()

    @property
    def n_kkt(self) -> int:
        """The law's unknowns ``y^(k)`` and, with equalities, ``nu^(k)``: m + q."""
        return len(self.y_jet)

    @property
    def singular_text(self) -> str:
        """Where the law cannot be evaluated, in words ("" when nowhere is known)."""
        parts = []
        if self.singular_set:
            parts.append(f"R is singular where {'; '.join(self.singular_set)}")
        if self.undefined_set:
            parts.append(f"R or p is undefined where {'; '.join(self.undefined_set)}")
        return "; ".join(parts)

    @functools.cached_property
    def hessian(self) -> sp.ImmutableMatrix:
        """``grad_yy f0`` (m, m) as expressions, for the report and for checking.

        Differentiated symbolically from :attr:`gradient` on first use (the generated
        code never needs it: it evaluates :attr:`hessian_entries`).
        """
        return _sparse_hessian(self.gradient, self.model.y)

    @functools.cached_property
    def kkt_hessian(self) -> sp.ImmutableMatrix:
        """With equalities, the KKT matrix ``[[grad_yy L, J_a^T], [J_a, 0]]`` as expressions.

        Differentiated from :attr:`kkt_gradient` on first use, for the report.
        """
        assert self.kkt_gradient is not None
        return _sparse_hessian(self.kkt_gradient, (*self.model.y, *self.model.multipliers))


#: det R is simplified and factored only up to this many expression nodes.
_DET_SIMPLIFY_NODES = 400


def tree_size(expr: sp.Expr, limit: int) -> int:
    """Nodes of ``expr``'s tree, counting at most ``limit + 1`` (so the count is cheap).

    A plain stack: sympy's ``preorder_traversal`` costs a generator step per node, and
    the budget meter sizes every expression the derivation builds.
    """
    count = 0
    stack = [expr]
    while stack:
        count += 1
        if count > limit:
            break
        stack.extend(stack.pop().args)
    return count


class _Meter:
    """Checks the budget as expressions are built; knows the current stage's name."""

    def __init__(
        self,
        source: str,
        budget: Budget,
        progress: Callable[[str, int, int, float], None] | None = None,
    ) -> None:
        self.source = source
        self.budget = budget
        self.start = time.perf_counter()
        self.deadline = self.start + budget.seconds
        self.stage = "model"
        self.progress = progress
        self.expressions = 0
        self.nodes = 0
        self.last_report = self.start

    def report(self) -> None:
        """Tell the progress callback the stage, expressions and nodes so far, and time."""
        if self.progress is not None:
            now = time.perf_counter()
            self.last_report = now
            self.progress(self.stage, self.expressions, self.nodes, now - self.start)

    def check_time(self) -> None:
        """Report progress now and then; raise when the time budget is spent."""
        now = time.perf_counter()
        if now - self.last_report > 0.5:
            self.report()
        if now > self.deadline:
            raise BudgetError(
                self.source,
                self.stage,
                f"the derivation took longer than {self.budget.seconds:g} s",
            )

    def __call__(self, expr: sp.Expr) -> None:
        self.expressions += 1
        if isinstance(expr, sp.Basic) and not expr.args:
            self.nodes += 1  # an atom: most entries of a team's matrices are zeros
            return
        self.check_time()
        size = tree_size(sp.sympify(expr), self.budget.size)
        self.nodes += size
        if size > self.budget.size:
            raise BudgetError(
                self.source,
                self.stage,
                f"an expression grew past {self.budget.size} nodes (the size budget); "
                "simplify the model or objective, or raise --max-size",
            )

    def matrix(self, matrix: sp.MatrixBase) -> None:
        for entry in matrix:
            self(entry)


class _Clock:
    """Records how long each derivation step takes."""

    def __init__(self) -> None:
        self.marks: list[tuple[str, float]] = []
        self.last = time.perf_counter()

    def mark(self, stage: str) -> None:
        now = time.perf_counter()
        self.marks.append((stage, now - self.last))
        self.last = now


def _linearizable(model: Model, counts: dict[str, int]) -> bool:
    """Whether the plant with these input integrators is full-state linearizable."""
    ext = extend(model.x, model.u, model.f, model.G, counts)
    sampler = Sampler(ext.x, dict(zip(model.params, model.defaults, strict=True)))
    rd = relative_degree(ext.f, ext.G, model.h, ext.x, sampler)
    if rd.R is None:
        return False
    degrees = [r for r in rd.r if r is not None]
    return sum(degrees) == len(ext.x) and generic_rank(rd.R, sampler) == len(model.u)


def _without_extension(model: Model) -> str:
    """Describe what the plant lacks before prolongation (for the report)."""
    sampler = Sampler(model.x, dict(zip(model.params, model.defaults, strict=True)))
    rd = relative_degree(model.f, model.G, model.h, model.x, sampler)
    if rd.R is None:
        missing = [str(y) for y, r in zip(model.y, rd.r, strict=True) if r is None]
        return f"without it, outputs {', '.join(missing)} have no relative degree"
    rank = generic_rank(rd.R, sampler)
    degrees = [int(r) for r in rd.r if r is not None]
    if rank < len(model.u):
        # A team's R is written out only while it is small enough to read.
        shown = (
            f"R = {sp.sstr(rd.R.tolist())}" if rd.R.rows <= 4 else f"R ({rd.R.rows} x {rd.R.cols})"
        )
        return (
            f"without it, the decoupling matrix {shown} has generic rank {rank} < "
            f"{len(model.u)}: the inputs cannot steer every output independently"
        )
    return (
        f"without it, the relative degrees {degrees} sum to {sum(degrees)} < {len(model.x)} states"
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


def _singular_set(det: sp.Expr) -> tuple[str, ...]:
    """Describe where a determinant vanishes, one condition per factor of its numerator."""
    numerator, _ = sp.fraction(sp.together(det))
    if numerator.is_Number:
        return () if numerator != 0 else ("everywhere",)
    try:
        _, factors = sp.factor_list(numerator)
    except sp.PolynomialError:  # not a polynomial in its symbols: state it whole
        return (f"{sp.sstr(numerator)} = 0",)
    conditions = []
    for base, _power in factors:
        if base.is_Number:
            continue
        conditions.append(f"{sp.sstr(base)} = 0")
    return tuple(conditions)


def _singular_start(
    R: sp.ImmutableMatrix,
    p: sp.ImmutableMatrix,
    states: Sequence[sp.Symbol],
    initial: Sequence[float],
    defaults: Mapping[sp.Symbol, float],
    extension_states: Sequence[str],
) -> tuple[str, ...]:
    """A warning when the spec's initial state is where the law is undefined.

    An automatic extension starts its states at 0 unless the spec gives them, and 0
    is singular for any prolonged speed: the module's DEFAULT_STATE would be unusable
    without a word.
    """
    values: dict[sp.Symbol, Any] = {q: float(v) for q, v in defaults.items()}
    values |= {sym: float(v) for sym, v in zip(states, initial, strict=True)}
    evaluate = Evaluator(values)
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


def _undefined_set(exprs: Sequence[sp.Expr], states: set[sp.Symbol]) -> tuple[str, ...]:
    """Where expressions of the states are undefined, one condition per cause.

    A denominator that vanishes, ``tan``/``sec`` where the cosine vanishes,
    ``cot``/``csc`` where the sine does, ``log`` of a non-positive and a root of a
    negative number: the places where R or p, and with them the law, do not exist
    although det R may not vanish there (a steering angle of pi/2, an Euler pitch of
    pi/2). Conditions on parameters alone are not listed.
    """
    conditions: dict[str, None] = {}
    seen: set[sp.Basic] = set()
    stack = [e for e in exprs if isinstance(e, sp.Basic)]
    while stack and len(conditions) < _MAX_UNDEFINED:
        node = stack.pop()
        if node in seen or not node.free_symbols & states:
            continue
        seen.add(node)
        condition = None
        if node.is_Pow and node.exp.is_Number and node.base.free_symbols & states:
            if node.exp.is_negative:
                condition = f"{sp.sstr(node.base)} = 0"
            elif not node.exp.is_Integer:
                condition = f"{sp.sstr(node.base)} < 0"
        elif isinstance(node, sp.tan | sp.sec):
            condition = f"cos({sp.sstr(node.args[0])}) = 0"
        elif isinstance(node, sp.cot | sp.csc):
            condition = f"sin({sp.sstr(node.args[0])}) = 0"
        elif isinstance(node, sp.log):
            condition = f"{sp.sstr(node.args[0])} <= 0"
        if condition is not None:
            conditions.setdefault(condition)
        stack.extend(reversed(node.args))
    return tuple(conditions)


def _sparse_gradient(f0: sp.Expr, y: Sequence[sp.Symbol]) -> sp.ImmutableMatrix:
    """Gradient of ``f0``, differentiating only where a variable occurs.

    A sum over agents is split into its terms once; each gradient entry sums the
    derivatives of the terms that contain its output: for N agents coupled to their
    neighbours this is linear in N where differentiating the whole sum is quadratic.
    """
    terms = sp.Add.make_args(f0)
    by_output: dict[sp.Symbol, list[sp.Expr]] = {yi: [] for yi in y}
    for term in terms:
        for yi in term.free_symbols & by_output.keys():
            by_output[yi].append(term)
    return sp.ImmutableMatrix([sp.Add(*(partial(term, yi) for term in by_output[yi])) for yi in y])


def _sparse_hessian(gradient: sp.MatrixBase, y: Sequence[sp.Symbol]) -> sp.ImmutableMatrix:
    """Hessian from the gradient, differentiating each entry only by outputs it contains.

    Filled symmetrically from the upper triangle (equal by Schwarz, and then equal as
    expressions too).
    """
    m = len(y)
    entries: dict[tuple[int, int], sp.Expr] = {}
    for i, gi in enumerate(gradient):
        free = gi.free_symbols
        for j in range(i, m):
            if y[j] in free:
                value = sp.diff(gi, y[j])
                if value != 0:
                    entries[(i, j)] = entries[(j, i)] = value
    return from_entries(m, m, entries)


def _polynomial_hessian(
    gradient: sp.MatrixBase, y: Sequence[sp.Symbol]
) -> sp.ImmutableMatrix | None:
    """The Hessian as expressions when the gradient is polynomial in ``y``, else ``None``.

    Quadratic objectives, the common case, have a Hessian free of ``y``: a matrix of
    numbers is inverted once at generation time, and one of parameters is checked for
    convexity exactly, at their defaults, instead of by sampling.
    """
    if not all(g.is_polynomial(*y) for g in gradient):
        return None
    return _sparse_hessian(gradient, y)


def _affine_split(
    gradient: sp.MatrixBase, hessian: sp.MatrixBase, y: Sequence[sp.Symbol]
) -> sp.ImmutableMatrix:
    """The gradient of a quadratic f0 written ``Hess y + b(t)``, ``b`` its value at y = 0.

    The same function, in the form whose time derivatives are cheapest: ``y^(j)`` enters
    ``grad^(j) = Hess y^(j) + b^(j)`` once, where differentiating the objective's own form
    (``S (y - o1) + (1 - S) (y - o2)``, a switch between targets) multiplies every
    ``y^(i)`` by every derivative of every weight. For the switching unicycle the
    operations that depend on the state drop from 118 to 72; the rest depend on time
    and parameters alone, which a batch of states at one time shares.
    """
    at_zero = {yi: sp.Integer(0) for yi in y}
    # The Hessian's nonzero entries by row: a team's is almost all zeros.
    rows: list[list[sp.Expr]] = [[] for _ in y]
    for i, j, entry in nonzero_entries(hessian):
        rows[i].append(entry * y[j])
    return sp.ImmutableMatrix(
        [sp.Add(*rows[i]) + gi.xreplace(at_zero) for i, gi in enumerate(gradient)]
    )


def _signal_derivatives(
    expr: sp.Expr, t: sp.Symbol, k: int, meter: Callable[[sp.Expr], None]
) -> list[sp.Expr] | None:
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
        # jet.partial builds sympy's diff's very expression, without its Derivative
        # machinery (two milliseconds a signal and order, for every agent of a team).
        derivative = partial(chain[-1], t)
        if tree_size(derivative, limit) > limit:
            return None
        meter(derivative)
        chain.append(derivative)
    return chain


#: A Hessian whose smallest eigenvalue is below this fraction of its scale (the largest
#: eigenvalue met) is degenerate: f0 is not strongly convex there.
DEGENERATE_HESSIAN = 1e-8
#: Times along the horizon at which the minimiser y*(t) is found and checked.
_PATH_POINTS = 25
#: Distances from y*(t) probed for where f0 stops being strongly convex.
_PROBE_DISTANCES = (1.0, 10.0, 100.0)
#: Up to this many outputs the fading probe steps along every axis; beyond, along this
#: many fixed directions.
_PROBE_AXES = 16
#: Memory for the Hessians of the fading probe evaluated at once.
_PROBE_BYTES = 64 * 2**20
#: Sparse Hessians whose band (in the reverse Cuthill-McKee order) is at most this wide
#: are factored as bands; wider ones by SuperLU.
_BAND_LIMIT = 32
#: Beyond this many outputs the Hessian's samples are handled as sparse matrices (a
#: team's is almost all zeros): the fading probe factors them, the convexity check takes
#: their banded eigenvalues and the search for y*(t) their banded LU (:class:`_SparseHessians`).
_SPARSE_PROBE = 64


class _ObjectiveNumbers:
    """f0, its gradient and its Hessian at many (y, t) points at once."""

    def __init__(
        self,
        model: Model,
        program: Program,
        gradient: Sequence[sp.Expr],
        entries: Sequence[tuple[tuple[int, int], sp.Expr]],
        defaults: Mapping[sp.Symbol, float],
    ) -> None:
        self.model, self.program, self.gradient = model, program, gradient
        self.entries, self.defaults = entries, defaults

    def _tape(self, outputs: Sequence[sp.Expr]) -> Tape:
        """``outputs`` compiled over (y_1 .. y_m, t): parameters at their defaults."""
        nominal = dict(self.model.nominal)
        definitions = nominal | dict(self.model.signals) | dict(self.program.assignments)
        # A reference without a nominal closed form is unknown here: taken at 0.
        constants: dict[sp.Symbol, Any] = dict(self.defaults)
        constants |= {r: 0.0 for r in self.model.references if r not in nominal}
        return Tape([*self.model.y, self.model.t], outputs, definitions, constants)

    @functools.cached_property
    def _f0(self) -> Tape:
        return self._tape([self.model.f0])

    @functools.cached_property
    def _hessian(self) -> Tape:
        return self._tape([expr for _, expr in self.entries])

    @functools.cached_property
    def _derivatives(self) -> Tape:
        return self._tape([*self.gradient, *(expr for _, expr in self.entries)])

    @staticmethod
    def _inputs(ys: np.ndarray, ts: np.ndarray) -> list[np.ndarray]:
        return [*(ys[:, i] for i in range(ys.shape[1])), ts]

    def value(self, ys: np.ndarray, ts: np.ndarray) -> np.ndarray:
        (out,) = self._f0(*self._inputs(ys, ts))
        return np.broadcast_to(np.asarray(np.real(out), dtype=float), ts.shape).copy()

    def hessian_entries(self, ys: np.ndarray, ts: np.ndarray) -> np.ndarray:
        """The Hessian's stored entries (E, P) at the points (NaN where undefined)."""
        values = np.empty((len(self.entries), len(ts)))
        for index, value in enumerate(self._hessian(*self._inputs(ys, ts))):
            values[index] = np.real(value)
        return values

    def derivatives(self, ys: np.ndarray, ts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Gradients (P, m) and Hessians (P, m, m) at the points (NaN where undefined)."""
        grads, values = self._gradients_and_entries(ys, ts)
        return grads, self._dense(values)

    def _gradients_and_entries(
        self, ys: np.ndarray, ts: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """Gradients (P, m) and the Hessian's stored entries (E, P) at the points."""
        points, m = ys.shape
        results = self._derivatives(*self._inputs(ys, ts))
        grads = np.empty((points, m))
        for i in range(m):
            grads[:, i] = np.real(results[i])
        values = np.empty((len(self.entries), points))
        for index, value in enumerate(results[m:]):
            values[index] = np.real(value)
        return grads, values

    def _dense(self, values: np.ndarray) -> np.ndarray:
        """The Hessians (P, m, m) of stored entries (E, P)."""
        m = len(self.model.y)
        matrices = np.zeros((values.shape[1], m, m))
        for ((i, j), _), value in zip(self.entries, values, strict=True):
            matrices[:, i, j] = matrices[:, j, i] = value
        return matrices

    @functools.cached_property
    def sparse(self) -> _SparseHessians | None:
        """The Hessian's pattern, for a team's outputs (beyond :data:`_SPARSE_PROBE`)."""
        m = len(self.model.y)
        return _SparseHessians([ij for ij, _ in self.entries], m) if m > _SPARSE_PROBE else None

    def extremes(self, ys: np.ndarray, ts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The Hessian's smallest and largest |eigenvalue| at each point (NaN if not finite)."""
        if self.sparse is None:
            return _smallest_eigenvalues(self.derivatives(ys, ts)[1])
        return self.sparse.extremes(self.hessian_entries(ys, ts), self._dense)

    def newton(self, ys: np.ndarray, ts: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Gradients (P, m), Newton steps H^-1 grad, and where H was finite and nonsingular.

        Non-finite gradient entries are taken as 0; where H is not usable the step is
        the solve with the identity's place taken (the caller falls back to the gradient).
        """
        if self.sparse is None:
            grads, matrices = self.derivatives(ys, ts)
            grads = np.where(np.isfinite(grads), grads, 0.0)
            usable = np.all(np.isfinite(matrices), axis=(1, 2))
            usable &= np.abs(np.linalg.det(np.where(usable[:, None, None], matrices, 1.0))) > 0
            safe = np.where(usable[:, None, None], matrices, np.eye(matrices.shape[1]))
            return grads, np.linalg.solve(safe, grads[:, :, None])[:, :, 0], usable
        grads, values = self._gradients_and_entries(ys, ts)
        grads = np.where(np.isfinite(grads), grads, 0.0)
        steps, usable = self.sparse.solve(values, grads, self._dense)
        return grads, steps, usable


def _smallest_eigenvalues(matrices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Smallest and largest |eigenvalue| of each finite matrix (NaN for the others)."""
    low = np.full(len(matrices), np.nan)
    high = np.full(len(matrices), np.nan)
    finite = np.all(np.isfinite(matrices), axis=(1, 2))
    if finite.any():
        eig = np.linalg.eigvalsh(matrices[finite])
        low[finite] = eig[:, 0]
        high[finite] = np.max(np.abs(eig), axis=1)
    return low, high


def _minimiser_path(
    numbers: _ObjectiveNumbers, y0: Sequence[float], ts: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """``y*(t)`` at every time by damped Newton (all times at once), and which converged.

    Each time starts from ``y0``; steps are Newton's where the Hessian is positive
    definite, the gradient's elsewhere, halved until f0 decreases.
    """
    points = len(ts)
    ys = np.tile(np.asarray(y0, dtype=float), (points, 1))
    converged = np.zeros(points, dtype=bool)
    with np.errstate(all="ignore"):
        # 40 steps: Newton converges in a few on a strongly convex f0; on a flat minimum
        # ((y - r)**4: linear, by 2/3 a step) they leave a Hessian ~1e-13 of its scale.
        first: np.ndarray | None = None
        for _ in range(40):
            grads, newton, usable = numbers.newton(ys, ts)
            norms = np.linalg.norm(grads, axis=1)
            if first is None:
                first = norms
            descent = usable & np.all(np.isfinite(newton), axis=1)
            descent &= np.einsum("pi,pi->p", grads, newton) > 0
            steps = np.where(descent[:, None], newton, grads)
            size = np.linalg.norm(steps, axis=1)
            converged = size <= 1e-10 * (1.0 + np.linalg.norm(ys, axis=1))
            # Located: the step vanished, or the gradient fell by eight orders.
            converged |= norms <= 1e-8 * first
            if converged.all():
                break
            value = numbers.value(ys, ts)
            scale = np.ones(points)
            accepted = converged.copy()
            for _halving in range(30):
                trial = ys - scale[:, None] * steps
                better = numbers.value(trial, ts) < value
                accepted |= better
                if accepted.all():
                    break
                scale = np.where(accepted, scale, 0.5 * scale)
            if not (accepted & ~converged).any():
                break  # no point moves any more
            ys = np.where(accepted[:, None], ys - scale[:, None] * steps, ys)
    return ys, converged


def _check_convexity(
    model: Model,
    polynomial: sp.ImmutableMatrix | None,
    program: Program,
    gradient: Sequence[sp.Expr],
    entries: Sequence[tuple[tuple[int, int], sp.Expr]],
    y0: Sequence[float],
    t_final: float,
    source: str,
) -> tuple[Convexity, tuple[str, ...]]:
    """Check the strong convexity of f0 where it matters; return the evidence and warnings.

    ``program`` computes ``gradient`` and the Hessian's lower triangle ``entries``;
    ``polynomial`` is the Hessian's symbolic form when f0 is polynomial in ``y`` (then a
    Hessian free of ``y``, t and the signals is checked exactly at the parameters'
    defaults). Otherwise the Hessian is sampled near the initial outputs and along the
    minimiser ``y*(t)`` over the horizon (found by Newton's method), where the
    theorem's bound lives: a Hessian that degenerates on ``y*`` (``(y - r)**4``) is
    refused, and one that fades away from ``y*`` (``log cosh``) gives a warning.
    """
    defaults = {q: float(v) for q, v in zip(model.params, model.defaults, strict=True)}
    m = len(model.y)
    warnings: list[str] = []
    if polynomial is not None and polynomial.free_symbols <= defaults.keys():
        fixed = Evaluator(defaults)
        matrix = np.array([[fixed(polynomial[i, j]) for j in range(m)] for i in range(m)])
        if not np.all(np.isfinite(matrix)):
            raise AssumptionError(
                source,
                "objective.f0",
                "the Hessian of f0 is not finite at the parameters' defaults (does a "
                "parameter divide by zero?)",
            )
        m_f = float(np.linalg.eigvalsh(np.real(matrix)).min())
        result = Convexity("constant Hessian", m_f, 1)
    else:
        numbers = _ObjectiveNumbers(model, program, gradient, entries, defaults)
        rng = np.random.default_rng(7)
        points = 24
        ys = np.asarray(y0) + rng.uniform(-0.1, 0.1, size=(points, m))
        ts = rng.uniform(0.0, t_final, size=points)
        low, high = numbers.extremes(ys, ts)
        path_ts = np.linspace(0.0, t_final, _PATH_POINTS)
        path, converged = _minimiser_path(numbers, y0, path_ts)
        path_low, path_high = numbers.extremes(path, path_ts)
        path_low = np.where(converged, path_low, np.nan)
        finite = np.isfinite(low).sum() + np.isfinite(path_low).sum()
        if not finite:
            raise AssumptionError(
                source,
                "objective.f0",
                f"the Hessian of f0 is not finite at any of {points} points near the initial "
                "outputs (overflow or outside its domain), so strong convexity cannot be checked",
            )
        scale = float(np.nanmax(np.concatenate([high, path_high, [0.0]])))
        m_f = float(np.nanmin(np.concatenate([low, path_low])))
        if converged.any() and np.nanmin(path_low) <= DEGENERATE_HESSIAN * scale:
            worst = int(np.nanargmin(path_low))
            where = ", ".join(
                f"{y.name} = {value:.6g}" for y, value in zip(model.y, path[worst], strict=True)
            )
            raise AssumptionError(
                source,
                "objective.f0",
                "f0 is not strongly convex at its minimiser: at t = "
                f"{path_ts[worst]:.6g}, y*(t) = ({where}), the Hessian's smallest eigenvalue "
                f"is {path_low[worst]:.3g}, below {DEGENERATE_HESSIAN:g} of its scale "
                f"{scale:.3g} (a flat minimum such as (y - r)**4: the law divides by it)",
            )
        warnings += _fading_convexity(numbers, path, path_ts, path_low, converged)
        result = Convexity("sampled near y(0) and along y*(t)", m_f, int(finite))
    if not result.m_f > 0:
        raise AssumptionError(
            source,
            "objective.f0",
            "f0 is not strongly convex in the outputs: the Hessian has eigenvalue "
            f"{result.m_f:.6g} <= 0 (the method needs grad_yy f0 positive definite)",
        )
    return result, tuple(warnings)


def _probe_directions(m: int) -> np.ndarray:
    """The directions in which :func:`_fading_convexity` steps away from ``y*``.

    Each axis both ways while there are at most :data:`_PROBE_AXES` outputs; beyond,
    :data:`_PROBE_AXES` fixed directions of +-1 entries (all ones, alternating signs, and
    seeded random signs, each with its opposite), so that every output moves by the
    probe's distance in every direction: the cost stays that of :data:`_PROBE_AXES`
    Hessians per point however many outputs there are (per axis it grew as m^4).
    """
    if m <= _PROBE_AXES:
        return np.concatenate([np.eye(m), -np.eye(m)])
    rng = np.random.default_rng(14)
    half = [np.ones(m), np.resize([1.0, -1.0], m)]
    half += [rng.choice([-1.0, 1.0], size=m) for _ in range(_PROBE_AXES // 2 - 2)]
    return np.concatenate([np.array(half), -np.array(half)])


class _SparseHessians:
    """Definiteness of one sparse symmetric pattern's matrices, by sparse factorization.

    ``A + shift I`` is positive definite exactly when its Cholesky factor exists. In
    the reverse Cuthill-McKee order a team's Hessian (a few entries per row, neighbours
    coupled) is a narrow band, whose Cholesky factorization (LAPACK's ``pbtrf``) takes
    microseconds. A pattern whose band stays wide is factored by SuperLU instead, as an
    LDL^T without pivoting in a fill-reducing symmetric order: positive definite when
    every pivot is positive (Sylvester's law of inertia). Either costs well under a
    millisecond where a dense eigenvalue decomposition costs tens.
    """

    def __init__(self, entries: Sequence[tuple[int, int]], m: int) -> None:
        lower = np.array(entries, dtype=np.int64).reshape(-1, 2)
        self.off = lower[:, 0] != lower[:, 1]
        diagonal = np.arange(m)
        self.rows = np.concatenate([lower[:, 0], lower[self.off, 1], diagonal])
        self.cols = np.concatenate([lower[:, 1], lower[self.off, 0], diagonal])
        self.m = m
        # Each entry's place in LAPACK's upper band storage of the permuted matrix:
        # ab[band + i - j, j] = A[i, j] for i <= j.
        pattern = {(i, j) for i, j in entries} | {(j, i) for i, j in entries}
        # order[k]: the output at place k of the permuted matrix; position: its inverse.
        self.order = np.array(reverse_cuthill_mckee(pattern, m), dtype=np.int64)
        position = self.position = np.empty(m, dtype=np.int64)
        position[self.order] = np.arange(m)
        first, second = position[lower[:, 0]], position[lower[:, 1]]
        low, high = np.minimum(first, second), np.maximum(first, second)
        self.band = int((high - low).max(initial=0))
        self.band_rows = self.band + low - high
        self.band_cols = high

    def _upper_band(self, values: np.ndarray) -> np.ndarray:
        """LAPACK's upper band storage of the permuted matrix of ``values`` (one point)."""
        band = np.zeros((self.band + 1, self.m))
        band[self.band_rows, self.band_cols] = values
        return band

    def extremes(
        self, values: np.ndarray, dense: Callable[[np.ndarray], np.ndarray]
    ) -> tuple[np.ndarray, np.ndarray]:
        """Smallest and largest |eigenvalue| of each point's matrix (``values`` (E, P)).

        In a narrow band, LAPACK's banded symmetric eigenvalues (``sbevd``: a reduction
        to tridiagonal form in O(m band^2)) of the permuted matrix, a similarity that
        keeps them; otherwise the dense matrices (``dense`` builds them). NaN where an
        entry is not finite.
        """
        points = values.shape[1]
        finite = np.all(np.isfinite(values), axis=0)
        if self.band > _BAND_LIMIT:
            low, high = np.full(points, np.nan), np.full(points, np.nan)
            if finite.any():
                low[finite], high[finite] = _smallest_eigenvalues(dense(values[:, finite]))
            return low, high
        from scipy.linalg import eigvals_banded  # noqa: PLC0415 - only for large teams

        low, high = np.full(points, np.nan), np.full(points, np.nan)
        for point in np.nonzero(finite)[0]:
            band = self._upper_band(values[:, point])
            eig = eigvals_banded(band, lower=False, check_finite=False)
            low[point], high[point] = eig[0], max(abs(eig[0]), abs(eig[-1]))
        return low, high

    def solve(
        self, values: np.ndarray, grads: np.ndarray, dense: Callable[[np.ndarray], np.ndarray]
    ) -> tuple[np.ndarray, np.ndarray]:
        """``H^-1 g`` at each point, and where H is finite and nonsingular (else ``g``).

        In a narrow band, LAPACK's banded LU (``gbsv``) of the permuted matrix (a
        Newton step need not be on a definite matrix); otherwise dense LU.
        """
        steps = grads.copy()
        usable = np.all(np.isfinite(values), axis=0)
        if self.band > _BAND_LIMIT:
            for point in np.nonzero(usable)[0]:
                try:
                    steps[point] = np.linalg.solve(dense(values[:, point, None])[0], grads[point])
                except np.linalg.LinAlgError:
                    usable[point] = False
            return steps, usable
        from scipy.linalg import solve_banded  # noqa: PLC0415 - only for large teams

        b = self.band
        for point in np.nonzero(usable)[0]:
            upper = self._upper_band(values[:, point])
            general = np.zeros((2 * b + 1, self.m))
            general[: b + 1] = upper
            # Below the diagonal by symmetry: A[j + d, j] = A[j, j + d].
            for d in range(1, b + 1):
                general[b + d, : self.m - d] = upper[b - d, d:]
            try:
                permuted = solve_banded((b, b), general, grads[point, self.order])
            except np.linalg.LinAlgError:
                usable[point] = False
                continue
            steps[point] = permuted[self.position]
        return steps, usable

    def positive_definite(self, values: np.ndarray, shift: float) -> bool | None:
        """Whether the matrix of ``values`` (in the entries' order) + ``shift I`` is definite.

        None when SuperLU would not keep the order symmetric (the pivots then say
        nothing of the inertia).
        """
        if self.band <= _BAND_LIMIT:
            from scipy.linalg import cholesky_banded  # noqa: PLC0415 - only for large teams

            band = self._upper_band(values)
            band[self.band] += shift
            try:
                cholesky_banded(band, lower=False, check_finite=False)
            except np.linalg.LinAlgError:
                return False
            return True
        from scipy.sparse import csc_matrix  # noqa: PLC0415 - only for large teams
        from scipy.sparse.linalg import splu  # noqa: PLC0415

        data = np.concatenate([values, values[self.off], np.full(self.m, shift)])
        matrix = csc_matrix((data, (self.rows, self.cols)), shape=(self.m, self.m))
        try:
            factor = splu(
                matrix,
                permc_spec="MMD_AT_PLUS_A",
                diag_pivot_thresh=0.0,
                options={"SymmetricMode": True},
            )
        except RuntimeError:  # an exactly zero pivot: singular, so not definite
            return False
        if not np.array_equal(factor.perm_r, factor.perm_c):
            return None
        return bool(np.all(factor.U.diagonal() > 0.0))


def _fading_sparse(
    numbers: _ObjectiveNumbers,
    points: np.ndarray,
    times: np.ndarray,
    threshold: np.ndarray,
    candidates: np.ndarray,
) -> np.ndarray:
    """Which points have a Hessian whose smallest eigenvalue lies in (-threshold, threshold).

    Sparse factorizations per candidate point: ``H - threshold I`` not definite (one
    factorization where it is, at every point where f0 is strongly convex), then
    ``H + threshold I`` definite; a dense eigenvalue decomposition where SuperLU would
    not keep a symmetric order.
    """
    m = points.shape[1]
    sparse = _SparseHessians([ij for ij, _ in numbers.entries], m)
    fading = np.zeros(len(points), dtype=bool)
    chunk = max(1, _PROBE_BYTES // (8 * max(len(numbers.entries), 1)))
    for start in range(0, len(points), chunk):
        part = slice(start, start + chunk)
        values = numbers.hessian_entries(points[part], times[part])
        for offset in np.nonzero(candidates[part])[0]:
            column, tau = values[:, offset], float(threshold[start + offset])
            if not np.all(np.isfinite(column)):
                continue
            below = sparse.positive_definite(column, -tau)
            if below:
                continue  # H - tau I > 0: strongly convex there, the common case
            above = sparse.positive_definite(column, tau)
            if above is None or below is None:
                low, _ = _smallest_eigenvalues(numbers._dense(column[:, None]))
                fading[start + offset] = bool(abs(low[0]) < tau)
            else:
                fading[start + offset] = above and not below
    return fading


def _fading_convexity(
    numbers: _ObjectiveNumbers,
    path: np.ndarray,
    ts: np.ndarray,
    path_low: np.ndarray,
    converged: np.ndarray,
) -> list[str]:
    """A warning when f0 is strongly convex near y*(t) only (its Hessian fades away)."""
    count, m = path.shape
    probes = [(d, direction) for d in _PROBE_DISTANCES for direction in _probe_directions(m)]
    # Every probe point in one array, evaluated in chunks of at most _PROBE_BYTES of
    # Hessians: the evaluator's cost is per expression, not per point.
    points = np.concatenate([path + d * direction for d, direction in probes])
    times = np.tile(ts, len(probes))
    reference = np.tile(path_low, len(probes))
    candidates = np.tile(converged, len(probes))
    # Fading, not turning negative: a barrier's periodic branches beyond its domain
    # (tan**2) are not where the outputs can go.
    if m > _SPARSE_PROBE:
        fading = _fading_sparse(numbers, points, times, 1e-6 * reference, candidates)
        if not fading.any():
            return []
        at = int(np.argmax(fading))
        low = np.full(len(points), np.nan)
        low[at] = numbers.extremes(points[None, at], times[None, at])[0][0]
    else:
        low = np.empty(len(points))
        chunk = max(count, _PROBE_BYTES // (8 * m * m))
        for start in range(0, len(points), chunk):
            part = slice(start, start + chunk)
            low[part], _ = numbers.extremes(points[part], times[part])
        fading = candidates & (np.abs(low) < 1e-6 * reference)
        if not fading.any():
            return []
    at = int(np.argmax(fading))  # the first in the order distance, direction, time
    distance, when = probes[at // count][0], ts[at % count]
    return [
        "objective.f0: f0 is strongly convex only near its minimiser: at distance "
        f"{distance:g} "
        f"from y*(t) (t = {when:.6g}) the Hessian's smallest eigenvalue is "
        f"{low[at]:.3g}, against {reference[at]:.3g} at y*; the certificate's "
        "bound holds only while the outputs stay where it is bounded below"
    ]


@dataclass(frozen=True)
class _Linearization:
    """The extended plant and its vector relative degree (Lemmas 1-2)."""

    extension: Extension
    degrees: tuple[int, ...]
    lie: tuple[tuple[sp.Expr, ...], ...]
    R: sp.ImmutableMatrix
    searched: tuple[str, ...]
    declared: frozenset[str]


@dataclass(frozen=True)
class _ErrorDynamics:
    """``H``: its order, coefficients, eigenvalues and decay rate."""

    k: int
    coefficients: tuple[float, ...]
    eigenvalues: tuple[complex, ...]
    decay_rate: float


@dataclass(frozen=True)
class _States:
    """The closed-loop state: plant, extension, padding chains; its initial value."""

    padding: tuple[tuple[str, ...], ...]
    names: tuple[str, ...]
    symbols: tuple[sp.Symbol, ...]
    initial: tuple[float, ...]
    multipliers: tuple[tuple[str, ...], ...] = ()


@dataclass(frozen=True)
class _Decoupling:
    """R, p, Phi, the Brunovsky pair, and where R is singular or R and p undefined."""

    p: sp.ImmutableMatrix
    phi: sp.ImmutableMatrix
    A: sp.ImmutableMatrix
    B: sp.ImmutableMatrix
    det_R: sp.Expr | None
    det_R_note: str
    singular: tuple[str, ...]
    undefined: tuple[str, ...]


@dataclass(frozen=True)
class _Objective:
    """The gradient of f0 as a program, its Hessian, and the convexity evidence."""

    gradient: sp.ImmutableMatrix
    program: Program
    current: tuple[sp.Expr, ...]
    hessian_program: Program
    hessian_entries: tuple[tuple[tuple[int, int], sp.Expr], ...]
    convexity: Convexity
    warnings: tuple[str, ...]


@dataclass(frozen=True)
class _GradientJet:
    """``grad^(j) f0`` for ``j < k``, ``rest``, and the jets of y, signals and references."""

    reference_jet: tuple[tuple[sp.Symbol, ...], ...]
    reference_order: int
    y_jet: tuple[tuple[sp.Symbol, ...], ...]
    y_values: tuple[tuple[sp.Expr, ...], ...]
    signal_jet: tuple[tuple[sp.Symbol, ...], ...]
    signal_program: Program
    signal_values: tuple[tuple[sp.Expr, ...], ...]
    program: Program
    grad_jet: tuple[tuple[sp.Expr, ...], ...]
    rest_program: Program
    rest: tuple[sp.Expr, ...]


def _linearize(spec: Spec, model: Model, meter: _Meter) -> _Linearization:
    """Extend the plant (as given, or by search) and find its vector relative degree."""
    source = spec.source
    counts = dict(spec.extension)
    searched: tuple[str, ...] = ()
    if spec.extension_auto:
        meter.stage = "extension search"
        meter.report()
        limit = spec.extension_max_total or len(spec.states)
        found, tried = search_extension(model, limit)
        if found is None:
            raise AssumptionError(
                source,
                "extension.auto",
                f"no prolongation of the inputs with at most {limit} integrators in all makes "
                f"the plant full-state linearizable (tried {len(tried)}: {'; '.join(tried)})",
            )
        counts = found
        searched = tuple(tried)
        meter.stage = "relative degree"
        meter.report()
    ext = extend(model.x, model.u, model.f, model.G, counts)
    declared = frozenset(
        {
            *spec.states,
            *spec.inputs,
            *spec.outputs,
            *(n for n, _ in spec.parameters),
            *(n for n, _ in spec.signals),
            *spec.references,
        }
    )
    for name in ext.states:
        if name in declared and name not in spec.inputs:
            raise SpecError(
                source,
                "extension.integrate",
                f"extension state {name!r} collides with a declared name",
            )
    defaults = dict(zip(model.params, model.defaults, strict=True))
    sampler = Sampler(ext.x, defaults)
    rd: RelativeDegree = relative_degree(ext.f, ext.G, model.h, ext.x, sampler, meter)
    m = len(model.u)
    n_ext = len(ext.x)
    for name, r in zip(spec.outputs, rd.r, strict=True):
        if r is None:
            raise AssumptionError(
                source,
                f"system.outputs.{name}",
                f"output {name!r} has no relative degree: no input reaches it within "
                f"{n_ext} derivatives",
            )
    assert rd.R is not None
    degrees = tuple(int(r) for r in rd.r if r is not None)
    named = dict(zip(spec.outputs, degrees, strict=True))
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
            f"not full-state linearizable: the relative degrees {named} sum to "
            f"{sum(degrees)}, but the extended system has {n_ext} states (internal dynamics "
            f"of dimension {n_ext - sum(degrees)})",
        )
    return _Linearization(ext, degrees, rd.lie, rd.R, searched, declared)


def _error_dynamics(spec: Spec, k: int) -> _ErrorDynamics:
    """H from the spec's poles or coefficients: of order k, and Hurwitz."""
    source = spec.source
    if spec.coefficients is not None:
        coefficients = spec.coefficients
        field, given = "error_dynamics.coefficients", len(coefficients)
    else:
        assert spec.poles is not None
        coefficients = hurwitz.coefficients_from_poles(spec.poles)
        field, given = "error_dynamics.poles", len(spec.poles)
    if given != k:
        raise AssumptionError(
            source,
            field,
            f"the error dynamics have order k = {k} (the largest relative degree), so give "
            f"{k} {'poles' if spec.poles is not None else 'coefficients'}, not {given}",
        )
    if spec.poles is not None:
        # The poles are exact as written; the companion eigenvalues would be rounded.
        eig = np.array(sorted(spec.poles, key=lambda v: (v.real, v.imag)))
        alpha = float(-max(v.real for v in spec.poles))
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
    return _ErrorDynamics(k, tuple(coefficients), tuple(complex(v) for v in eig), alpha)


def _closed_loop_states(spec: Spec, lin: _Linearization, k: int) -> _States:
    """Pad outputs of relative degree below k with integrator chains; order the state."""
    padding = tuple(
        tuple(f"xi_{name}_{j}" for j in range(1, k - r + 1))
        for name, r in zip(spec.outputs, lin.degrees, strict=True)
    )
    pad_names = [n for chain in padding for n in chain]
    for name in pad_names:
        if name in lin.declared:
            raise SpecError(
                spec.source,
                "system.outputs",
                f"padding state {name!r} collides with a declared name",
            )
    # Each equality's multiplier and its first k - 1 derivatives: the controller's own
    # integrator chain, driven by nu^(k) from the KKT system.
    multipliers = tuple(tuple(f"nu_{c.name}_{j}" for j in range(k)) for c in spec.equalities)
    for name in (
        *(n for chain in multipliers for n in chain),
        *(f"nu_{c.name}" for c in spec.equalities),
    ):
        if name in lin.declared:
            raise SpecError(
                spec.source,
                "constraints",
                f"multiplier name {name!r} collides with a declared name",
            )
    ext = lin.extension
    names = (*spec.states, *ext.states, *pad_names, *(n for chain in multipliers for n in chain))
    # With a searched extension the user cannot know its states in advance: only the
    # plant states are required then (extension states start at zero unless given).
    required = len(spec.states) + (0 if spec.extension_auto else len(ext.states))
    initial = _initial_state(spec, names, required)
    return _States(
        padding, names, tuple(sp.Symbol(n, real=True) for n in names), initial, multipliers
    )


def _decoupling(lin: _Linearization, meter: _Meter) -> _Decoupling:
    """p, Phi and the Brunovsky pair from the Lie chains; where R fails, in words."""
    R, degrees, lie = lin.R, lin.degrees, lin.lie
    m = len(degrees)
    p = sp.ImmutableMatrix([lie[i][degrees[i]] for i in range(m)])
    phi = sp.ImmutableMatrix([lie[i][j] for i in range(m) for j in range(degrees[i])])
    A, B = brunovsky(degrees)
    det_R: sp.Expr | None = None
    det_R_note = ""
    singular: tuple[str, ...] = ()
    if m > 4:
        det_R_note = f"not expanded symbolically (m = {m} > 4)"
    else:
        det = R.det(method="berkowitz")
        meter(det)
        # simplify and factor are exact but can be slow on large entries: only small ones.
        if tree_size(det, _DET_SIMPLIFY_NODES) <= _DET_SIMPLIFY_NODES:
            det_R = sp.factor(sp.simplify(det))
            # Charge simplify's time to this stage, not to the next one that checks.
            meter.check_time()
            singular = _singular_set(det_R)
        else:
            det_R_note = (
                f"not simplified symbolically (more than {_DET_SIMPLIFY_NODES} expression nodes)"
            )
    # R's nonzero entries: a team's R is m^2 entries, almost all zeros.
    entries = [e for _, _, e in nonzero_entries(R)]
    undefined = _undefined_set([*entries, *p], set(lin.extension.x))
    return _Decoupling(p, phi, A, B, det_R, det_R_note, singular, undefined)


def _programs_of(
    expr: sp.Expr, variables: Sequence[sp.Symbol], names: Iterator[sp.Symbol], meter: _Meter
) -> tuple[
    sp.ImmutableMatrix,
    Program,
    tuple[sp.Expr, ...],
    Program,
    tuple[tuple[tuple[int, int], sp.Expr], ...],
    sp.ImmutableMatrix | None,
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
    spec: Spec, model: Model, states: _States, names: Iterator[sp.Symbol], meter: _Meter
) -> _Objective:
    """The gradient of f0 as a program, its Hessian, and f0's convexity where it matters."""
    gradient, program, current, hessian_program, hessian_entries, polynomial = _programs_of(
        model.f0, model.y, names, meter
    )
    defaults = dict(zip(model.params, model.defaults, strict=True))
    values = {sym: sp.Float(v) for sym, v in zip(states.symbols, states.initial, strict=True)}
    values |= {q: sp.Float(v) for q, v in defaults.items()}
    y0 = [float(h.xreplace(values)) for h in model.h]
    convexity, warnings = _check_convexity(
        model,
        polynomial,
        program + hessian_program,
        current,
        hessian_entries,
        y0,
        spec.t_final,
        spec.source,
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
    names: Iterator[sp.Symbol],
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
    rates: dict[sp.Symbol, sp.Expr] = {model.t: sp.Integer(1)} | reference_rates
    for chain in (*y_jet, *signal_jet):
        for j in range(k):
            rates[chain[j]] = chain[j + 1]
    program = objective.program
    current: Sequence[sp.Expr] = objective.current
    grad_jet = [tuple(current)]
    rest_program = Program(())
    rest: tuple[sp.Expr, ...] = ()
    for order in range(1, k + 1):
        new, current, rates = next_derivative(program, current, rates, names, meter)
        if order < k:
            program = program + new
            grad_jet.append(tuple(current))
        else:
            # grad^(k) is affine in y^(k) with slope Hess: dropping y^(k) leaves the rest.
            drop = {chain[k]: sp.Integer(0) for chain in y_jet}
            rest_program = Program(tuple((s, e.xreplace(drop)) for s, e in new.assignments))
            rest = tuple(e.xreplace(drop) for e in current)
    signal_program = Program(())
    signal_chains: list[tuple[sp.Expr, ...]] = []
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
            signal_rates: dict[sp.Symbol, sp.Expr] = {model.t: sp.Integer(1)} | reference_rates
            for _ in range(k):
                new, chain, signal_rates = next_derivative(part, chain, signal_rates, names, meter)
                part = part + new
                derivatives.append(chain[0])
            signal_program = signal_program + part
        signal_chains.append(tuple(derivatives))
    state_of = dict(zip(states.names, states.symbols, strict=True))
    degrees = lin.degrees
    y_values = tuple(
        tuple(
            lin.lie[i][j] if j < degrees[i] else state_of[states.padding[i][j - degrees[i]]]
            for j in range(k)
        )
        for i in range(len(model.y))
    ) + tuple(tuple(state_of[name] for name in chain) for chain in states.multipliers)
    # The highest derivative of a reference that the law or the optimality error reads.
    used: set[sp.Basic] = set()
    for part in (program, rest_program, signal_program):
        for _, value in part.assignments:
            used |= value.free_symbols
    for exprs in (*grad_jet, rest, *signal_chains):
        for value in exprs:
            used |= sp.sympify(value).free_symbols
    order = max(
        (j for chain in reference_jet for j, symbol in enumerate(chain) if symbol in used),
        default=0,
    )
    return _GradientJet(
        reference_jet,
        order,
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


def objective_start(model: Model, states: _States) -> np.ndarray:
    """The outputs at the initial state, parameters at their defaults."""
    values = {sym: sp.Float(v) for sym, v in zip(states.symbols, states.initial, strict=True)}
    values |= {q: sp.Float(v) for q, v in zip(model.params, model.defaults, strict=True)}
    return np.array([float(h.xreplace(values)) for h in model.h])


def _constraint_convexity(spec: Spec, model: Model, y0: np.ndarray) -> tuple[str, ...]:
    """Refuse a constraint that is not convex in the outputs, unless the spec allows it.

    Each ``g_i``'s Hessian in ``y`` is sampled around the initial outputs over the
    horizon (signals and nominal references at their values there; references without
    one at 0).
    """
    if not model.constraints:
        return ()
    rng = np.random.default_rng(18)
    points = 64
    ys = y0[None, :] + rng.uniform(-2.0, 2.0, size=(points, len(y0)))
    evaluate = _evaluator_at(model, ys, rng.uniform(0.0, spec.t_final, size=points))
    _feasible_at_the_end(spec, model, y0)
    found = nonconvex(model.constraints, model.y, evaluate, points)
    if not found:
        return ()
    names = ", ".join(f"{name} (Hessian eigenvalue {value:.3g})" for name, value in found)
    if not spec.allow_nonconvex:
        raise AssumptionError(
            spec.source,
            f"constraints.{found[0][0]}",
            f"not convex in the outputs: {names}; the barrier method needs convex "
            "inequalities (set allow_nonconvex = true to accept a local certificate)",
        )
    return (f"constraints not convex in the outputs: {names}; the certificate is local only",)


def _evaluator_at(model: Model, ys: np.ndarray, ts: np.ndarray) -> Evaluator:
    """Numbers for expressions in the outputs and t at points (one row of ``ys`` each).

    Parameters at their defaults, signals and nominal references defined (references
    without one at 0).
    """
    values: dict[sp.Symbol, Any] = {y: ys[:, i] for i, y in enumerate(model.y)}
    values[model.t] = ts
    values |= {q: float(v) for q, v in zip(model.params, model.defaults, strict=True)}
    nominal = dict(model.nominal)
    values |= {r: 0.0 for r in model.references if r not in nominal}
    evaluate = Evaluator(values)
    for symbol, expr in nominal.items():
        evaluate.define(symbol, expr)
    for symbol, expr in model.signals:
        evaluate.define(symbol, expr)
    return evaluate


def _equality_jacobian(model: Model) -> list[list[sp.Expr]]:
    """``J_a``: the equalities' derivatives in the outputs, (q, m)."""
    return [[sp.diff(c.g, y) for y in model.y] for c in model.equalities]


def _equality_checks(spec: Spec, model: Model, y0: np.ndarray) -> tuple[str, ...]:
    """Refuse equalities the KKT law cannot keep: too many, dependent, or not affine.

    Equalities not affine in the outputs make the feasible set non-convex: refused
    unless ``allow_nonconvex``, and then a warning says the certificate is local only.
    Dependence is decided on ``J_a`` at the initial outputs over the horizon (at every
    output when ``J_a`` is constant).
    """
    if not model.equalities:
        return ()
    q, m = len(model.equalities), len(model.y)
    names = ", ".join(c.name for c in model.equalities)
    if q > m:
        raise AssumptionError(
            spec.source,
            "constraints",
            f"{q} equality constraints ({names}) on {m} outputs: at most {m} can be independent",
        )
    warnings: tuple[str, ...] = ()
    curved = [
        c.name
        for c in model.equalities
        if any(sp.diff(c.g, yi, yj) != 0 for yi in model.y for yj in model.y)
    ]
    if curved:
        if not spec.allow_nonconvex:
            raise AssumptionError(
                spec.source,
                f"constraints.{curved[0]}",
                f"not affine in the outputs: {', '.join(curved)}; the feasible set of a "
                "curved equality is not convex (set allow_nonconvex = true to accept a "
                "local certificate)",
            )
        warnings = (
            f"equality constraints not affine in the outputs: {', '.join(curved)}; "
            "the certificate is local only",
        )
    jacobian_a = _equality_jacobian(model)
    points = 5
    ts = np.linspace(0.0, spec.t_final, points)
    evaluate = _evaluator_at(model, np.repeat(y0[None, :], points, axis=0), ts)
    matrices = np.zeros((points, q, m))
    for i, row in enumerate(jacobian_a):
        for j, entry in enumerate(row):
            if entry != 0:
                matrices[:, i, j] = np.broadcast_to(np.real(evaluate(entry)), (points,))
    constant = all(sp.sympify(e).is_Number for row in jacobian_a for e in row)
    for index in range(points):
        singular = np.linalg.svd(matrices[index], compute_uv=False)
        if not singular[-1] > 1e-9 * max(1.0, float(singular[0])):
            where = "everywhere" if constant else f"at the initial outputs and t = {ts[index]:g}"
            raise AssumptionError(
                spec.source,
                "constraints",
                f"the equality constraints {names} are dependent: their gradients in the "
                f"outputs have rank {int(np.sum(singular > 1e-9 * singular[0]))} < {q} "
                f"{where} (drop or combine the redundant ones)",
            )
    return warnings


def _dependent_set(model: Model) -> tuple[str, ...]:
    """Where the equalities' gradients are dependent (K singular), in words.

    ``det(J_a J_a^T) = 0``, factored, for up to four equalities of small expressions; a
    note saying it was not computed otherwise.
    """
    q = len(model.equalities)
    if not q:
        return ()
    if q > 4:
        return (f"not computed symbolically (q = {q} > 4)",)
    jacobian_a = sp.Matrix(_equality_jacobian(model))
    gram = jacobian_a * jacobian_a.T
    det = gram.det(method="berkowitz")
    if tree_size(det, _DET_SIMPLIFY_NODES) > _DET_SIMPLIFY_NODES:
        return (f"not simplified symbolically (more than {_DET_SIMPLIFY_NODES} expression nodes)",)
    return _singular_set(sp.factor(sp.simplify(det)))


def _lagrangian(
    model: Model, objective: _Objective, names: Iterator[sp.Symbol], meter: _Meter
) -> _Objective:
    """With equalities, the KKT map ``F = grad L`` over (y, nu) and its Hessian ``K``.

    ``L = f0 + nu^T a``: its gradient is ``[grad f0 + J_a^T nu; a]`` and its Hessian the
    KKT matrix ``[[grad_yy L, J_a^T], [J_a, 0]]``, so the paper's law written for
    ``L`` over (y, nu) is the KKT law (docs/constraints.md). Without equalities, the
    objective itself.
    """
    if not model.equalities:
        return objective
    variables = (*model.y, *model.multipliers)
    gradient, program, current, hessian_program, entries, _ = _programs_of(
        model.lagrangian, variables, names, meter
    )
    # The (nu, nu) block is structurally zero; its diagonal is stored all the same, as
    # the elimination fills it (the Schur complement -J Hess^-1 J^T).
    m = len(variables)
    value = dict(entries)
    entries = tuple(
        sorted(value.items() | {((i, i), sp.Integer(0)) for i in range(m) if (i, i) not in value})
    )
    return _Objective(
        gradient,
        program,
        current,
        hessian_program,
        entries,
        objective.convexity,
        objective.warnings,
    )


def _multipliers_start(spec: Spec, model: Model, states: _States, objective: _Objective) -> _States:
    """The multiplier chains' initial values: nu(0) by least squares, its derivatives 0.

    ``nu(0)`` minimises ``|grad f0 + J_a^T nu|`` at the initial outputs and t = 0, so the
    KKT map starts as small as the plant's state allows; any start is admissible (the
    theorem holds for every ``E_F(0)``). Values given in ``[simulation]`` are kept.
    """
    if not model.equalities:
        return states
    y0 = objective_start(model, states)
    evaluate = _evaluator_at(model, y0[None, :], np.zeros(1))
    m, q = len(model.y), len(model.equalities)
    g = np.array(
        [float(np.real(np.broadcast_to(evaluate(e), (1,))[0])) for e in objective.gradient]
    )
    jacobian_a = np.array(
        [
            [float(np.real(np.broadcast_to(evaluate(e), (1,))[0])) for e in row]
            for row in _equality_jacobian(model)
        ]
    ).reshape(q, m)
    nu0 = np.linalg.lstsq(jacobian_a.T, -g, rcond=None)[0]
    given = dict(spec.initial_state)
    initial = list(states.initial)
    for chain, value in zip(states.multipliers, nu0, strict=True):
        if chain[0] not in given:
            initial[states.names.index(chain[0])] = float(value)
    return _States(states.padding, states.names, states.symbols, tuple(initial), states.multipliers)


def _feasible_at_the_end(spec: Spec, model: Model, y0: np.ndarray) -> None:
    """Refuse constraints that no output satisfies at the end of the horizon."""
    worst = least_violation(model, spec.t_final, y0)
    if worst > 1e-7:
        raise AssumptionError(
            spec.source,
            "constraints",
            f"infeasible at the horizon's end t = {spec.t_final:g}: every output violates a "
            f"constraint (the least violation found is {worst:.3g})",
        )


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
    # Longer than most functions here on purpose: a list of stage calls, then the keyword
    # list of the flat Derivation record; the work is in the stage functions above.
    if not isinstance(spec, Spec):
        spec = spec_from_dict(spec)
    meter = _Meter(spec.source, budget or Budget(), progress)
    clock = _Clock()

    def say(stage: str) -> None:
        meter.stage = stage
        meter.report()

    say("model")
    model = build_model(spec)
    clock.mark("model")
    say("relative degree")
    lin = _linearize(spec, model, meter)
    clock.mark("relative degree")
    say("error dynamics")
    dynamics = _error_dynamics(spec, max(lin.degrees))
    k = dynamics.k
    states = _closed_loop_states(spec, lin, k)
    clock.mark("error dynamics")
    say("decoupling matrix")
    decoupling = _decoupling(lin, meter)
    clock.mark("decoupling matrix")
    say("objective")
    # A leading underscore: no user name can take it (spec.py rejects those). One
    # sequence for the gradient, the Hessian and the jet: their names never collide.
    names = fresh_symbols("_g")
    # Constraints first: an infeasible or non-convex one explains itself before the
    # barrier objective's convexity check would stumble on it.
    constraint_warnings = _constraint_convexity(spec, model, objective_start(model, states))
    objective = _objective(spec, model, states, names, meter)
    equality_warnings = _equality_checks(spec, model, objective_start(model, states))
    kkt = _lagrangian(model, objective, names, meter)
    states = _multipliers_start(spec, model, states, objective)
    defaults = dict(zip(model.params, model.defaults, strict=True))
    ext = lin.extension
    warnings = objective.warnings + _singular_start(
        lin.R,
        decoupling.p,
        states.symbols,
        states.initial,
        defaults,
        states.names[len(spec.states) : len(spec.states) + len(ext.states)],
    )
    warnings += constraint_warnings + equality_warnings
    unknown = [r.name for r in model.references if r not in dict(model.nominal)]
    if unknown:
        warnings += (
            f"references {', '.join(unknown)} have no nominal closed form: f0's convexity "
            "was checked with them at 0 (give [references] nominal to check along it)",
        )
    clock.mark("objective")
    say("gradient jet")
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
    )
    if spec.estimator is not None:
        try:
            estimator_gains(spec.estimator, jet.reference_order)
        except ValueError as exc:
            raise AssumptionError(spec.source, "references.estimator.kind", str(exc)) from None
    clock.mark("law")
    return Derivation(
        spec=spec,
        model=model,
        extension=ext,
        relative_degree=lin.degrees,
        lie=lin.lie,
        R=lin.R,
        p=decoupling.p,
        phi=decoupling.phi,
        A=decoupling.A,
        B=decoupling.B,
        k=k,
        padding=states.padding,
        state_names=states.names,
        states=states.symbols,
        det_R=decoupling.det_R,
        det_R_note=decoupling.det_R_note,
        singular_set=decoupling.singular,
        undefined_set=decoupling.undefined,
        gradient=objective.gradient,
        hessian_program=kkt.hessian_program,
        hessian_entries=kkt.hessian_entries,
        objective_program=objective.program + objective.hessian_program,
        objective_gradient=objective.current,
        objective_hessian=symmetric_dense(objective.hessian_entries, len(model.y)),
        multiplier_states=states.multipliers,
        kkt_gradient=kkt.gradient if model.equalities else None,
        dependent_set=_dependent_set(model),
        y_jet=jet.y_jet,
        y_jet_values=jet.y_values,
        signal_jet=jet.signal_jet,
        signal_program=jet.signal_program,
        signal_jet_values=jet.signal_values,
        jet_program=jet.program,
        grad_jet=jet.grad_jet,
        rest_program=jet.rest_program,
        rest=jet.rest,
        coefficients=dynamics.coefficients,
        eigenvalues=dynamics.eigenvalues,
        decay_rate=dynamics.decay_rate,
        uniform=all(r == k for r in lin.degrees),
        convexity=objective.convexity,
        initial_state=states.initial,
        unextended=unextended,
        extension_search=lin.searched,
        certified_rate=rate,
        certified_rate_exact=rate_exact,
        warnings=warnings,
        transient_constant=constant,
        law=law,
        timings=tuple(clock.marks),
        reference_jet=jet.reference_jet,
        reference_order=jet.reference_order,
    )


def _initial_state(spec: Spec, state_names: Sequence[str], required: int) -> tuple[float, ...]:
    """Order the spec's initial state; plant and extension states must all be given."""
    given = dict(spec.initial_state)
    for key in given:
        if key not in state_names:
            raise SpecError(
                spec.source,
                f"simulation.initial_state.{key}",
                f"not a state of the closed loop (states: {', '.join(state_names)})",
            )
    if given:
        for name in state_names[:required]:
            if name not in given:
                raise SpecError(
                    spec.source,
                    f"simulation.initial_state.{name}",
                    "missing (every plant and extension state needs a value)",
                )
    return tuple(float(given.get(name, 0.0)) for name in state_names)
