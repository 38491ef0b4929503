"""What a read spec is: :class:`Spec` and its parts (constraints, barrier, estimator).

Names, numbers and expressions of the process's engine; nothing in it has been derived
yet.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from tvopt_codegen import symbolic as sx

#: Most integrators one input may be prolonged by.
MAX_INTEGRATORS = 8

#: The name of time in every expression.
TIME_NAME = "t"


def symbol(name: str) -> sx.Expr:
    """Return the symbol that stands for a declared name (always real), of the engine."""
    return sx.symbol(name)


def time_symbol() -> sx.Expr:
    """The symbol for time in every expression, of the engine in use now."""
    return sx.symbol(TIME_NAME)


def __getattr__(name: str) -> sx.Expr:
    # ``TIME`` is built when asked, of the engine in use then: a symbol built at import
    # would fix the engine (and import it) before anyone chose one.
    if name == "TIME":
        return time_symbol()
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


@dataclass(frozen=True)
class Robust:
    """What the law does about a plant that is not its model (``[robust]``).

    Attributes
    ----------
    integral : bool
        Keep ``z_I = int grad f0 dt`` as controller states: the error dynamics take one
        more pole per output, and a constant matched disturbance leaves ``grad f0 -> 0``.
    observer : float or None
        The bandwidth (rad/s) of the disturbance observer that estimates a matched input
        disturbance ``d`` in ``x' = f + G (u + d)`` from the measured plant state and the
        applied input; None: no observer.
    eso : float or None
        The bandwidth (rad/s) of the extended-state observer: per output, the output's
        derivatives below its relative degree and the lumped disturbance at the top one,
        estimated from the measured outputs; the law reads the estimates and cancels the
        disturbance through ``v`` (see :mod:`tvopt_codegen.derivation.rejection`); None:
        none.
    """

    integral: bool = False
    observer: float | None = None
    eso: float | None = None

    @property
    def any(self) -> bool:
        """Whether any option is on."""
        return self.integral or self.observer is not None or self.eso is not None


@dataclass(frozen=True)
class TuneSettings:
    """What ``tune`` searches for and within what (``[tune]``); no other command reads it.

    The strings are kept as written: their grammar is ``tvopt_codegen.tune.requirements``'s.
    A None or empty value leaves the choice to ``tune`` (its default or its command line).

    Attributes
    ----------
    objective : str or None
        ``tune.objective``: what the search minimises, e.g. ``"max |e| after 2"``.
    constraints : tuple of str
        ``tune.constraints``: requirements every accepted candidate meets.
    after : float or None
        ``tune.after``: seconds; the requirements judge the run from this time on.
    pole_range : (float, float) or None
        ``tune.pole_range``: ``(lo, hi)``, ``0 < lo < hi``, rad/s: the poles' magnitudes
        the search may choose.
    min_damping : float or None
        ``tune.min_damping``: in ``(0, 1]``, the least damping ratio of a conjugate pair
        (1: real poles only).
    bandwidth_range : (float, float) or None
        ``tune.bandwidth_range``: ``(lo, hi)``, ``0 < lo < hi``, rad/s: the observer's
        (``robust.observer`` or ``robust.eso``) bandwidths the search may choose.
    """

    objective: str | None = None
    constraints: tuple[str, ...] = ()
    after: float | None = None
    pole_range: tuple[float, float] | None = None
    min_damping: float | None = None
    bandwidth_range: tuple[float, float] | None = None


@dataclass(frozen=True)
class Limit:
    """One actuator's limits (``[limits]`` and ``[limits.rate]``).

    Attributes
    ----------
    input : str
        The plant input's name.
    low, high : float
        Its range (``-inf`` or ``inf`` when only a rate is given).
    rate : float
        The largest ``|du/dt|`` of the applied input, per second (``inf``: none).
    """

    input: str
    low: float
    high: float
    rate: float = float("inf")


@dataclass(frozen=True)
class Mechanics:
    """A plant in mass-matrix form, ``M(q) q'' = F(q, q') + B(q) u`` (``[system.mechanics]``).

    The spec's states are the coordinates, then the rates; the rates' right-hand sides
    are ``a_i + sum_j W_ij u_j`` in the run-time symbols :attr:`accelerations` (``a =
    M^-1 F``) and :attr:`gains` (``W = M^-1 B``), which generated code computes by
    factoring ``M`` at each evaluation: ``M`` is never inverted symbolically.

    Attributes
    ----------
    coordinates, rates : tuple of str
        ``q`` and ``q'``, in order.
    mass_matrix : tuple of tuple of Expr
        ``M(q)``, symmetric, row by row.
    forces : tuple of Expr
        ``F(q, q')``, without the inputs.
    input_matrix : tuple of tuple of Expr
        ``B(q)``, one row per coordinate, one column per input.
    accelerations : tuple of Expr
        ``a = M^-1 F``, one per coordinate: a run-time symbol, or 0 where no force
        reaches the coordinate's block of ``M``.
    gains : tuple of tuple of Expr
        ``W = M^-1 B``, row by row, likewise.
    definitions : tuple of (Symbol, Expr)
        Named intermediate values ``M``, ``F`` and ``B`` may use, in order, each in the
        coordinates, rates, parameters and earlier ones (a robot's link velocities, say):
        reserved symbols ``_let<i>``, evaluated once per evaluation, never substituted.
    definition_names : tuple of str
        The spec's name of each definition (for the report).
    """

    coordinates: tuple[str, ...]
    rates: tuple[str, ...]
    mass_matrix: tuple[tuple[sx.Expr, ...], ...]
    forces: tuple[sx.Expr, ...]
    input_matrix: tuple[tuple[sx.Expr, ...], ...]
    accelerations: tuple[sx.Expr, ...]
    gains: tuple[tuple[sx.Expr, ...], ...]
    definitions: tuple[tuple[sx.Expr, sx.Expr], ...] = ()
    definition_names: tuple[str, ...] = ()

    @property
    def opaque(self) -> frozenset[sx.Expr]:
        """The run-time symbols: no derivation step may differentiate them."""
        entries = (*self.accelerations, *(w for row in self.gains for w in row))
        return frozenset(e for e in entries if e.is_Symbol)


@dataclass(frozen=True)
class Spec:
    """A validated spec: names, numbers and parsed expressions.

    Attributes
    ----------
    source : str
        How the spec was named (a path, or ``<name> (bundled example)``).
    sha256 : str
        SHA-256 of the spec file's bytes; stamped into every generated file.
    name, description : str
        Module name and free text.
    states, inputs, outputs : tuple of str
        Declared names, in declaration order.
    dynamics : tuple of Expr
        Right-hand side of each state equation, in state order.
    output_exprs : tuple of Expr
        Each output as an expression in the states and parameters.
    parameters : tuple of (str, float)
        Parameter names and default values.
    signals : tuple of (str, Expr)
        Time signals as explicit expressions in ``t`` and the parameters (references
        to earlier signals already substituted).
    objective : Expr
        ``f0`` in the output symbols, signal symbols, parameters and ``t``.
    extension : tuple of (str, int)
        Inputs to prolong and their number of integrators, in input order.
    poles : tuple of complex, or None
        Requested eigenvalues of the error dynamics (conjugates included).
    coefficients : tuple of float, or None
        Requested ``a_0 ... a_{k-1}`` of the companion matrix.
    t_final : float
        Simulation horizon.
    initial_state : tuple of (str, float)
        Initial values by state name, as written.
    agents : tuple of (str, str)
        Output pairs drawn as planar paths (default: consecutive output pairs).
    objects : tuple of (str, str)
        Signal pairs drawn as moving objects in the planar figure.
    extension_auto : bool
        Search the dynamic extension instead of taking ``extension``.
    extension_max_total : int or None
        Largest total number of integrators the search tries (default: the number of
        plant states).
    indices : tuple of (str, int)
        The ``[index]`` table: each index and its count. Indexed names are already
        expanded everywhere else (``x[i]`` with ``i = 3`` is ``x_0, x_1, x_2``).
    references : tuple of str
        Targets measured at run time (``[references] names``): used in signals and the
        objective like signals, their derivative jets supplied with every call.
    reference_nominal : tuple of (str, Expr)
        A closed form in ``t`` and the parameters for some references (``nominal``): the
        convexity check, ``simulate`` without samples and the report use it.
    estimator : Estimator or None
        The differentiator that turns reference samples into jets (None without
        references).
    constraints : tuple of Constraint
        ``[constraints]``: inequalities on the outputs, kept by an interior-point
        homotopy (see :mod:`tvopt_codegen.spec.constraints`).
    barrier : Barrier
        The homotopy's weight and slack schedule.
    allow_nonconvex : bool
        Accept inequalities that are not convex in the outputs, or equalities that are
        not affine in them (the certificate is then local only).
    equalities : tuple of Constraint
        ``[constraints]`` written with ``==``: ``a_j(y, t) = 0``, kept by the KKT system
        with a multiplier chain per equality (see :mod:`tvopt_codegen.spec.constraints`).
    robust : Robust
        ``[robust]``: integral action and the disturbance observer (both off by default).
    limits : tuple of Limit
        ``[limits]``: the actuators' ranges and slew rates, in input order (inputs without
        a limit are left out).
    mechanics : Mechanics or None
        ``[system.mechanics]``: the plant in mass-matrix form (None: ``[system.dynamics]``).
    tune : TuneSettings or None
        ``[tune]``: what ``tune`` searches for (None: no such table); nothing else reads it.
    """

    source: str
    sha256: str
    name: str
    description: str
    states: tuple[str, ...]
    inputs: tuple[str, ...]
    dynamics: tuple[sx.Expr, ...]
    outputs: tuple[str, ...]
    output_exprs: tuple[sx.Expr, ...]
    parameters: tuple[tuple[str, float], ...]
    signals: tuple[tuple[str, sx.Expr], ...]
    objective: sx.Expr
    extension: tuple[tuple[str, int], ...]
    poles: tuple[complex, ...] | None
    coefficients: tuple[float, ...] | None
    t_final: float
    initial_state: tuple[tuple[str, float], ...]
    agents: tuple[tuple[str, str], ...] = ()
    objects: tuple[tuple[str, str], ...] = ()
    extension_auto: bool = False
    extension_max_total: int | None = None
    indices: tuple[tuple[str, int], ...] = ()
    references: tuple[str, ...] = ()
    reference_nominal: tuple[tuple[str, sx.Expr], ...] = ()
    estimator: Estimator | None = None
    constraints: tuple[Constraint, ...] = ()
    barrier: Barrier | None = None
    allow_nonconvex: bool = False
    equalities: tuple[Constraint, ...] = ()
    robust: Robust = field(default_factory=Robust)
    limits: tuple[Limit, ...] = ()
    mechanics: Mechanics | None = None
    tune: TuneSettings | None = None


@dataclass(frozen=True)
class Constraint:
    """One constraint of ``[constraints]``: ``lhs op rhs``.

    Attributes
    ----------
    name : str
        Its key in the spec.
    op : str
        ``"<="``, ``">="`` or ``"=="``.
    lhs, rhs : Expr
        The two sides, in outputs, signals, references, parameters and ``t``.
    text : str
        As written.
    """

    name: str
    op: str
    lhs: sx.Expr
    rhs: sx.Expr
    text: str

    @property
    def g(self) -> sx.Expr:
        """``g(y, t) <= 0`` (``a(y, t) = 0`` for an equality): ``lhs - rhs`` or its negative."""
        return self.rhs - self.lhs if self.op == ">=" else self.lhs - self.rhs


@dataclass(frozen=True)
class Barrier:
    """The interior-point homotopy's schedule (``[constraints.barrier]``).

    Attributes
    ----------
    initial_weight, final_weight, rate : float
        ``mu(t) = mu_inf + (mu_0 - mu_inf) exp(-rate t)``; the slack decays at the same rate.
    initial_slack : float or None
        ``s(0)``; None: from the initial outputs (twice the largest violation plus 0.1,
        or 0 when the start is strictly feasible).
    """

    initial_weight: float = 1.0
    final_weight: float = 1e-4
    rate: float = 1.0
    initial_slack: float | None = None


#: The differentiators a spec may choose for its references.
ESTIMATOR_KINDS = ("linear", "levant")


@dataclass(frozen=True)
class Estimator:
    """How reference samples become derivative jets (``[references.estimator]``).

    Attributes
    ----------
    kind : str
        ``"linear"``: a high-gain linear differentiator, every pole at ``-bandwidth``;
        ``"levant"``: Levant's robust exact differentiator for signals whose next
        derivative is bounded by ``lipschitz``.
    bandwidth : float
        rad/s, for ``linear``.
    lipschitz : float
        The bound ``L`` on ``|r^(q+1)|``, for ``levant``.
    """

    kind: str = "linear"
    bandwidth: float = 20.0
    lipschitz: float = 1.0
