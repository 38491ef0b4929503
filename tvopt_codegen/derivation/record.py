"""The record of a derivation: what the code generators and the report read.

Its expressions, symbols and matrices are the process's engine's
(:mod:`tvopt_codegen.symbolic`, typed ``sx.Expr``): a reader that needs SymPy (the
report's LaTeX) converts the few it shows at the border.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from dataclasses import dataclass

from tvopt_codegen import symbolic as sx
from tvopt_codegen.derivation.law import Law
from tvopt_codegen.derivation.model import Model
from tvopt_codegen.derivation.rejection import Rejection
from tvopt_codegen.derivation.robust import Robustness
from tvopt_codegen.maths.jet import (
    Program,
)
from tvopt_codegen.maths.lie import (
    Extension,
    from_entries,
)
from tvopt_codegen.spec import Spec


def jet_symbol(name: str, order: int) -> sx.Expr:
    """The symbol for the ``order``-th time derivative of ``name`` (y1, y1', y1'', ...).

    The primes cannot occur in user names, so jet symbols never collide with them.
    """
    if order == 0:
        return sx.symbol(name)
    mark = "'" * order if order <= 3 else f"^({order})"
    return sx.symbol(f"{name}{mark}")


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

    @property
    def quadratic(self) -> bool:
        """Whether f0 is quadratic in y: its Hessian holds parameters at most."""
        return self.method == "constant Hessian"


@dataclass(frozen=True)
class LinearizationStage:
    """The extended plant and its linearization (Lemmas 1-2).

    Attributes
    ----------
    extension : Extension
        The extended plant (equal to the plant when nothing is prolonged).
    relative_degree : tuple of int
        ``r_i`` per output, of the extended system.
    lie : tuple of tuple of expression
        ``lie[i][j] = L_f^j h_i``, ``j = 0 .. r_i``.
    R : matrix
        Decoupling matrix (m, m).
    unextended : str or None
        Why the extension is needed: what the plant lacks without it (``None`` when
        nothing is prolonged).
    extension_search : tuple of str
        The prolongations the automatic search tried, in order (empty when the spec
        gave the extension).
    """

    extension: Extension
    relative_degree: tuple[int, ...]
    lie: tuple[tuple[sx.Expr, ...], ...]
    R: sx.Expr
    unextended: str | None
    extension_search: tuple[str, ...]


@dataclass(frozen=True)
class DecouplingStage:
    """``p``, the coordinates, the Brunovsky pair, and where the law is undefined.

    Attributes
    ----------
    p, phi : matrix
        ``p = col(L_f^{r_i} h_i)`` and the coordinates ``Phi``.
    A, B : matrix
        Brunovsky pair of the extended system.
    det_R : expression or None
        ``det R`` factored, when computed symbolically (m <= 4).
    det_R_note : str
        Why ``det_R`` is None (empty when it was computed), for the summary and report.
    singular_set : tuple of str
        Conditions under which ``det R`` vanishes, in words.
    undefined_set : tuple of str
        Conditions under which R or p (and so the law) is undefined (a denominator
        or a cosine under ``tan`` vanishes, ...), in words.
    dependent_set : tuple of str
        Where the equalities' gradients are dependent (``det(J_a J_a^T) = 0``, where the
        KKT matrix is singular), in words; empty where nowhere (or without equalities).
    """

    p: sx.Expr
    phi: sx.Expr
    A: sx.Expr
    B: sx.Expr
    det_R: sx.Expr | None
    det_R_note: str
    singular_set: tuple[str, ...]
    undefined_set: tuple[str, ...]
    dependent_set: tuple[str, ...] = ()

    @property
    def singular_text(self) -> str:
        """Where the law cannot be evaluated, in words ("" when nowhere is known)."""
        parts = []
        if self.singular_set:
            parts.append(f"R is singular where {'; '.join(self.singular_set)}")
        if self.undefined_set:
            parts.append(f"R or p is undefined where {'; '.join(self.undefined_set)}")
        return "; ".join(parts)


@dataclass(frozen=True)
class ClosedLoopStage:
    """The closed-loop state: plant, extension, padding and multiplier chains.

    Attributes
    ----------
    padding : tuple of tuple of str
        Names of the padding states ``xi_<output>_<j>`` per output.
    state_names : tuple of str
        Closed-loop state order: plant, extension, padding, multiplier chains.
    states : tuple of symbol
        Symbols of ``state_names``.
    initial_state : tuple of float
        Default initial state in :attr:`state_names` order.
    multiplier_states : tuple of tuple of str
        With equality constraints, each multiplier's chain of controller states
        ``nu_<name>_0 .. nu_<name>_<k-1>`` (the multiplier and its derivatives).
    integral_states : tuple of str
        With ``[robust] integral``, the integrals ``int_<output>`` of each entry of
        ``grad f0`` (with equalities, of the KKT map: ``int_nu_<name>`` for ``a_j``), last
        in the state; each is a chain of one integrator driven by that entry.
    """

    padding: tuple[tuple[str, ...], ...]
    state_names: tuple[str, ...]
    states: tuple[sx.Expr, ...]
    initial_state: tuple[float, ...]
    multiplier_states: tuple[tuple[str, ...], ...] = ()
    integral_states: tuple[str, ...] = ()


@dataclass(frozen=True)
class EstimatorStage:
    """The reference differentiator the generated controllers run (``[references.estimator]``).

    Attributes
    ----------
    order : int
        The differentiator's order: the derivatives of each reference it estimates
        (at least the law's reference order, one beyond for the linear kind).
    gains : tuple of float
        Its gains (:func:`~tvopt_codegen.spec.estimator.estimator_gains`).
    """

    order: int
    gains: tuple[float, ...]


@dataclass(frozen=True)
class ErrorDynamicsStage:
    """The error dynamics ``E' = H E`` and the theorem's constants.

    Attributes
    ----------
    k : int
        ``max r_i``: the order of the error dynamics.
    coefficients : tuple of float
        ``a_0 .. a_{k-1}`` of H; with integral action ``a_0 .. a_k`` of ``H_I``, the
        companion matrix of order k + 1 over ``col(z_I, E)``.
    integral_pole : float or None
        With integral action, the real eigenvalue of ``H_I`` closest to zero: the mode of
        ``delta = z_I - z*(E)`` (see :func:`~tvopt_codegen.maths.hurwitz.integral_split`).
    bumpless : tuple of float
        With integral action, ``b_0 .. b_{k-1}``: ``z*(E) = sum_j b_j E_j``, the integrals'
        value on which E moves as under the law without them (the controller's start,
        and what it holds while an input is clipped).
    eigenvalues : tuple of complex
        Eigenvalues of the companion matrix.
    decay_rate : float
        ``alpha = -max Re(lambda)``.
    uniform : bool
        Whether all relative degrees equal k (no padding).
    certified_rate : float
        The alpha of ``|expm(H t)| <= c e^{-alpha t}`` (the decay rate, or 10% less with
        repeated poles).
    certified_rate_exact : bool
        Whether ``certified_rate`` is the decay rate itself (the poles are distinct).
    transient_constant : float
        That c, computed.
    """

    k: int
    coefficients: tuple[float, ...]
    eigenvalues: tuple[complex, ...]
    decay_rate: float
    uniform: bool
    certified_rate: float
    certified_rate_exact: bool
    transient_constant: float
    integral_pole: float | None = None
    bumpless: tuple[float, ...] = ()


@dataclass(frozen=True)
class ObjectiveStage:
    """f0's gradient and Hessian, as expressions and programs, and its convexity.

    Attributes
    ----------
    gradient : matrix
        ``grad_y f0`` (m, 1) over ``y``, signals, parameters and t.
    hessian_program : Program
        Assignments computing the Hessian from ``jet.jet_program`` (forward mode over
        its gradient part, :func:`~tvopt_codegen.maths.jet.jacobian`); empty when it is
        constant.
    hessian_entries : tuple of ((int, int), expression)
        The nonzero entries ``(i, j), i >= j`` of the lower triangle of ``grad_yy f0``,
        over the programs' symbols (numbers when the Hessian is constant). The
        generated code reads the Hessian from these.
    convexity : Convexity
        Strong convexity evidence.
    objective_program : Program
        The program of f0's own gradient and Hessian (over the outputs): the generated
        ``gradient`` and ``hessian`` functions evaluate it. With equalities the jet's
        programs are the KKT system's instead.
    objective_gradient, objective_hessian : tuple of expression
        f0's gradient (m) and Hessian ((m, m), row-major) over that program.
    kkt_gradient : matrix or None
        With equalities, the KKT map ``F = [grad f0 + J_a^T nu; a]`` over (y, nu).
    """

    gradient: sx.Expr
    hessian_program: Program
    hessian_entries: tuple[tuple[tuple[int, int], sx.Expr], ...]
    convexity: Convexity
    objective_program: Program = Program(())
    objective_gradient: tuple[sx.Expr, ...] = ()
    objective_hessian: tuple[sx.Expr, ...] = ()
    kkt_gradient: sx.Expr | None = None


@dataclass(frozen=True)
class JetStage:
    """The output, signal and reference jets and the gradient jet ``grad^(j) f0``.

    Attributes
    ----------
    y_jet : tuple of tuple of symbol
        ``y_jet[i][j]`` is the symbol of ``y_i^(j)``, ``j = 0 .. k``.
    y_jet_values : tuple of tuple of expression
        ``y_i^(j)`` for ``j < k`` as a function of the closed-loop state.
    signal_jet : tuple of tuple of symbol
        ``signal_jet[l][q]`` is the symbol of the q-th derivative of signal l.
    signal_program : Program
        Straight-line program of the signals and their time derivatives.
    signal_jet_values : tuple of tuple of expression
        Those derivatives over :attr:`signal_program`, ``t`` and the parameters.
    jet_program : Program
        Straight-line program of the gradient jet (see :mod:`tvopt_codegen.maths.jet`).
    grad_jet : tuple of tuple of expression
        ``grad^(j) f0`` for ``j = 0 .. k-1`` over the program's symbols.
    rest_program : Program
        Extra assignments used by :attr:`rest` only.
    rest : tuple of expression
        ``grad^(k) f0`` with ``y^(k) = 0``, so ``grad^(k) f0 = Hess y^(k) + rest``.
    reference_jet : tuple of tuple of symbol
        ``reference_jet[l][q]``: the q-th derivative of reference l, ``q = 0 .. k``
        (supplied by the caller, never derived).
    reference_order : int
        The highest derivative of a reference the law reads (0 without references).
    """

    y_jet: tuple[tuple[sx.Expr, ...], ...]
    y_jet_values: tuple[tuple[sx.Expr, ...], ...]
    signal_jet: tuple[tuple[sx.Expr, ...], ...]
    signal_program: Program
    signal_jet_values: tuple[tuple[sx.Expr, ...], ...]
    jet_program: Program
    grad_jet: tuple[tuple[sx.Expr, ...], ...]
    rest_program: Program
    rest: tuple[sx.Expr, ...]
    reference_jet: tuple[tuple[sx.Expr, ...], ...] = ()
    reference_order: int = 0

    @property
    def n_kkt(self) -> int:
        """The law's unknowns ``y^(k)`` and, with equalities, ``nu^(k)``: m + q."""
        return len(self.y_jet)


@dataclass(frozen=True)
class Derivation:
    """The complete derivation for one spec, as the records of its stages.

    Attributes
    ----------
    spec, model : Spec, Model
        The inputs of the derivation.
    linearization : LinearizationStage
        The extended plant, relative degrees, Lie derivatives and R.
    decoupling : DecouplingStage
        p, Phi, the Brunovsky pair, det R and where the law is singular or undefined.
    closed_loop : ClosedLoopStage
        The closed-loop state and its default start.
    dynamics : ErrorDynamicsStage
        H's coefficients, rate and the theorem's constants.
    objective : ObjectiveStage
        f0's gradient and Hessian and their convexity evidence.
    jet : JetStage
        The jets and the gradient jet the law reads.
    law : Law
        The control law written down from the above (:mod:`tvopt_codegen.derivation.law`):
        everything the code generators evaluate.
    warnings : tuple of str
        What the user should know but that does not stop the derivation (f0 strongly
        convex only near its minimiser, a singular default state), one line each.
    timings : tuple of (str, float)
        Seconds spent per derivation step.
    rejection : Rejection or None
        The extended-state observer (``[robust.eso]``;
        :mod:`tvopt_codegen.derivation.rejection`), None without one.
    robustness : Robustness
        What the stateful controller does at a step beyond the law (limits, integral
        action's chains and bumpless start, the observers' data;
        :mod:`tvopt_codegen.derivation.robust`).
    estimator : EstimatorStage or None
        With references measured at run time and ``[references.estimator]``, the
        differentiator's order and gains; None otherwise.

    Readers name a stage's attribute by its stage (``d.closed_loop.state_names``,
    ``d.linearization.R``): the derivation forwards none of them, so each use says which
    stage it reads. With equality constraints, ``jet.y_jet``, ``jet.grad_jet``,
    ``jet.rest``, ``jet.jet_program``, ``objective.hessian_program`` and
    ``objective.hessian_entries`` are those of the Lagrangian ``L = f0 + nu^T a`` over the
    outputs and then the multipliers (m + q entries, ``jet.n_kkt``): the law is the
    paper's, written for ``L``.
    """

    spec: Spec
    model: Model
    linearization: LinearizationStage
    decoupling: DecouplingStage
    closed_loop: ClosedLoopStage
    dynamics: ErrorDynamicsStage
    objective: ObjectiveStage
    jet: JetStage
    law: Law
    warnings: tuple[str, ...]
    timings: tuple[tuple[str, float], ...]
    robustness: Robustness
    rejection: Rejection | None = None
    estimator: EstimatorStage | None = None

    @functools.cached_property
    def hessian(self) -> sx.Expr:
        """``grad_yy f0`` (m, m) as expressions, for the report and for checking.

        Differentiated symbolically from ``objective.gradient`` on first use (the
        generated code never needs it: it evaluates ``objective.hessian_entries``).
        """
        return _sparse_hessian(self.objective.gradient, self.model.y)

    @functools.cached_property
    def kkt_hessian(self) -> sx.Expr:
        """With equalities, the KKT matrix ``[[grad_yy L, J_a^T], [J_a, 0]]`` as expressions.

        Differentiated from ``objective.kkt_gradient`` on first use, for the report.
        """
        kkt_gradient = self.objective.kkt_gradient
        assert kkt_gradient is not None
        return _sparse_hessian(kkt_gradient, (*self.model.y, *self.model.multipliers))


def _sparse_hessian(gradient: sx.Expr, y: Sequence[sx.Expr]) -> sx.Expr:
    """Hessian from the gradient, differentiating each entry only by outputs it contains.

    Filled symmetrically from the upper triangle (equal by Schwarz, and then equal as
    expressions too).
    """
    m = len(y)
    entries: dict[tuple[int, int], sx.Expr] = {}
    for i, gi in enumerate(gradient):
        free = gi.free_symbols
        for j in range(i, m):
            if y[j] in free:
                value = sx.diff(gi, y[j])
                if value != 0:
                    entries[(i, j)] = entries[(j, i)] = value
    return from_entries(m, m, entries)
