"""The execution plan: the order of kernel calls, solves and checks, as data.

Every backend evaluates the law the same way; the plan says how, once, and the
templates loop over it. One evaluation of the law at a state is

- the common :attr:`Plan.steps`: the jet, the solve for ``y_imp^(k)``, ``b = v - p``,
  the solve ``R w = b``, each result checked for finiteness;
- then :attr:`Plan.control` (the plant input alone, what ``control`` needs) or
  :attr:`Plan.rhs` (the closed-loop vector field and the plant input).

A step's ``op`` is one of

``call``
    Evaluate the kernel ``kernel`` on the values ``args`` (in the kernel's input
    order) into the values ``results`` (in its output order).
``solve_ldl``
    ``results[0] = Hess^-1 args[1]`` with the generated LDL^T kernel ``kernel`` on the
    Hessian's stored entries ``args[0]``; fails with :attr:`Status.HESSIAN_NOT_PD` when a
    pivot is not above :data:`PIVOT_TOLERANCE` times the largest entry. With equality
    constraints the matrix is the KKT matrix and the kernel's last pivots are the
    multipliers' (negated): one of those failing is
    :attr:`Status.DEPENDENT_CONSTRAINTS`. Which pivot means which status is the step's
    ``pivots``, printed by every backend.
``solve_lu``
    ``results[0] = R^-1 args[1]`` by LU with partial pivoting over R's diagonal blocks
    ``args[0]``; fails with :attr:`Status.SINGULAR_DECOUPLING` likewise.
``check``
    Every entry of ``args`` is finite, or the law fails with
    :attr:`Status.NONFINITE_OUTPUT`, naming ``what``.
``check_pd``
    A mass-matrix plant's ``M``, factored inside the jet kernel: every pivot
    ``args[1]`` of its LDL^T exceeds :data:`PIVOT_TOLERANCE` times the largest entry of
    ``args[0]``, or the law fails with :attr:`Status.MASS_MATRIX_NOT_PD`. An ``M`` with a
    non-finite entry passes here and fails the finiteness check that follows.
``check_margin``
    With inequality constraints, every margin ``s(t) - g_i(y, t)`` in ``args[0]`` is
    positive, or the law fails with :attr:`Status.OUTSIDE_BARRIER`. The law reads the
    barrier only through ``1/(s - g_i)`` and its powers, finite on both sides of it:
    without this check a state past the barrier gets a finite law with status OK. A
    non-finite margin passes here and fails the finiteness check that follows.

The statuses and the tolerance are the contract's (:mod:`tvopt_codegen.contract`);
the plan says which step fails with which.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from tvopt_codegen.contract import PIVOT_TOLERANCE, Status

__all__ = ["PIVOT_TOLERANCE", "Plan", "Status", "Step", "Value", "law_plan"]


@dataclass(frozen=True)
class Value:
    """An array the plan computes or reads.

    Attributes
    ----------
    name : str
        Its name in every backend's law.
    size : int
        Number of entries.
    role : str
        ``input`` (an argument of the law: ``t``, ``s``, ``p``, ``a``), ``batch`` (the
        same for every state of a batch: ``tau``), ``output`` (a result of the law:
        ``u``, ``ds``) or ``local``.
    storage : str
        The name of the buffer that holds it, for backends that solve in place: its own
        name, or that of the value that later overwrites it (``R w = b`` is solved in
        ``w``'s buffer, which holds ``b`` until then).
    doc : str
        What it is.
    """

    name: str
    size: int
    role: str
    storage: str
    doc: str


@dataclass(frozen=True)
class Step:
    """One step of the plan (see the module docstring for the operations).

    Attributes
    ----------
    op : str
        ``call``, ``solve_ldl``, ``solve_lu``, ``check``, ``check_pd`` or
        ``check_margin``.
    kernel : str
        The kernel a ``call`` or ``solve_ldl`` evaluates ("" otherwise).
    args, results : tuple of str
        Value names read and written.
    status : Status
        What the law returns when the step fails (``OK`` for a call, which cannot).
    what : str
        For a check: what is not finite, in the error message.
    alone : tuple of str
        For a check: the values among ``args`` whose non-finite entries no later check
        would see. A backend that only needs to know *whether* the law failed (the
        Python backend's one-point path, which then answers through the array path)
        checks these alone.
    note : str
        A comment for the generated code ("" for none); for a check, why ``alone`` holds
        what it holds (printed where only ``alone`` is checked).
    pivots : tuple of (int, Status)
        For a solve: the status of a failing pivot, by range: pivot ``i`` fails with the
        status of the first entry whose bound exceeds ``i`` (empty: ``status`` for all).
    """

    op: str
    kernel: str = ""
    args: tuple[str, ...] = ()
    results: tuple[str, ...] = ()
    status: Status = Status.OK
    what: str = ""
    alone: tuple[str, ...] = ()
    note: str = ""
    pivots: tuple[tuple[int, Status], ...] = ()


@dataclass(frozen=True)
class Plan:
    """How a backend evaluates the law at one state.

    Attributes
    ----------
    values : tuple of Value
        Every value the steps read or write.
    per_batch : tuple of Step
        Calls whose arguments are the same for every state of a batch (the jet's terms
        of time and parameters): made once per call of ``control`` or ``rhs``.
    steps : tuple of Step
        The steps every evaluation makes, in order.
    control, rhs : tuple of Step
        The steps that end an evaluation for the plant input alone, and for the
        closed-loop vector field and the plant input.
    runtime : tuple of str
        The run-time pieces the steps use, for backends to emit only those:
        ``definite`` (the check of a mass matrix's pivots), ``ldl`` (the check around
        the LDL^T kernel), ``lu_1``, ``lu_2`` and ``lu`` (solves of 1 x 1, unrolled
        2 x 2 and larger blocks of R).
    """

    values: tuple[Value, ...]
    per_batch: tuple[Step, ...]
    steps: tuple[Step, ...]
    control: tuple[Step, ...]
    rhs: tuple[Step, ...]
    runtime: tuple[str, ...]

    def value(self, name: str) -> Value:
        """The value called ``name``."""
        for value in self.values:
            if value.name == name:
                return value
        raise KeyError(name)

    @property
    def locals(self) -> tuple[Value, ...]:
        """The values a backend's law holds in buffers of its own, one per storage."""
        return tuple(v for v in self.values if v.role == "local" and v.storage == v.name)


#: From y_imp^(k) to the extended plant's input: b = v - p, checked, then R w = b.
_DECOUPLE = (
    Step("call", "decoupling", ("t", "s", "p", "z", "pvec"), ("b",)),
    Step("check", args=("b",), status=Status.NONFINITE_OUTPUT, what="v - p", alone=("b",)),
    Step(
        "solve_lu",
        args=("r", "b"),
        results=("w",),
        status=Status.SINGULAR_DECOUPLING,
        note="w = R^-1 (v - p) by LU with partial pivoting (a symbolic solve loses digits).",
    ),
)
#: The end of an evaluation for the plant input alone (``control``).
_CONTROL = (
    Step("call", "plant_input", ("t", "s", "p", "w"), ("u",)),
    Step(
        "check", args=("u",), status=Status.NONFINITE_OUTPUT, what="the plant input", alone=("u",)
    ),
)
#: The end of an evaluation for the closed-loop vector field and the plant input (``rhs``).
_RHS = (
    Step("call", "closed_loop", ("t", "s", "p", "w", "z"), ("ds", "u")),
    Step(
        "check",
        args=("ds", "u"),
        status=Status.NONFINITE_OUTPUT,
        what="the closed-loop vector field",
        alone=("ds", "u"),
    ),
)


def _pivots(m: int, n: int) -> tuple[tuple[int, Status], ...]:
    """What a failing pivot of the Hessian's LDL^T means (``Step.pivots``).

    With equality constraints the matrix is the KKT matrix: the outputs' pivots first,
    then the multipliers'.
    """
    if n > m:
        return ((m, Status.HESSIAN_NOT_PD), (n, Status.DEPENDENT_CONSTRAINTS))
    return ((m, Status.HESSIAN_NOT_PD),)


def _runtime(
    hessian: int, r_blocks: tuple[tuple[int, ...], ...], mass: int = 0, margins: int = 0
) -> tuple[str, ...]:
    """The run-time pieces (``Plan.runtime``) a law with these solves and checks uses."""
    sizes = {len(block) for block in r_blocks}
    return (
        *(("definite",) if mass else ()),
        *(("margin",) if margins else ()),
        *(("ldl",) if hessian else ()),
        *(("lu_1",) if 1 in sizes else ()),
        *(("lu_2",) if 2 in sizes else ()),
        *(("lu",) if any(size > 2 for size in sizes) else ()),
    )


_CHECK_PD = Step(
    "check_pd",
    args=("mass", "mass_pivot"),
    status=Status.MASS_MATRIX_NOT_PD,
    what="the mass matrix",
    note="M(q) was factored (LDL^T) in the jet: never inverted, checked here.",
)

_CHECK_MARGIN = Step(
    "check_margin",
    args=("margin",),
    status=Status.OUTSIDE_BARRIER,
    what="the inequality constraints' margins",
    note="Past a barrier 1/(s - g_i) is finite: the margins themselves say where y is.",
)

_SOLVE_HESSIAN = Step(
    "solve_ldl",
    "cholesky",
    ("hess", "jet_rhs"),
    ("z",),
    Status.HESSIAN_NOT_PD,
    note="y_imp^(k) = Hess^-1 [sum a_i grad^(i) f0 - rest]: solved, never inverted.",
)


def _jet_outputs(
    *,
    hessian: int,
    n: int,
    n_inputs: int,
    integral: bool,
    margins: int,
    mass: tuple[int, int],
    observer: int,
) -> tuple[list[Value], tuple[str, ...], Step, str]:
    """What the jet kernel returns, in its output order (lower checks the binding).

    Returns
    -------
    values : list of Value
        The values only the jet writes (``z``, ``r`` and ``pvec`` are declared by the
        caller, which every plan has).
    results : tuple of str
        The jet call's results.
    check : Step
        The finiteness check of the results a later step does not check itself.
    call_note : str
        The jet call's comment.
    """
    values: list[Value] = []
    if hessian:
        values += [
            Value("hess", hessian, "local", "hess", "stored entries of the Hessian of f0"),
            Value("jet_rhs", n, "local", "jet_rhs", "sum a_i grad^(i) f0 - rest"),
        ]
        results: tuple[str, ...] = ("hess", "jet_rhs", "r", "pvec")
        alone: tuple[str, ...] = ("hess", "r")
        what = "the Hessian, the gradient jet, the decoupling matrix or p"
        note = (
            "The right-hand side and p reach b, which is checked below; an infinite Hessian "
            "entry can leave z finite, and an entry of R no plant input depends on could hide."
        )
        call_note = ""
    else:
        results = ("z", "r", "pvec")
        alone = ("r",)
        what = "the gradient jet, the decoupling matrix or p"
        note = (
            "z and p reach b, which is checked below; R is checked here, since an entry of R "
            "that no plant input depends on could hide in w."
        )
        call_note = "y_imp^(k): the constant Hessian of f0 was inverted exactly at generation time."
    if integral:
        values.append(Value("grad", n, "local", "grad", "grad f0: the integral states' rates"))
        results += ("grad",)
    if margins:
        values.append(Value("margin", margins, "local", "margin", "s(t) - g_i(y, t)"))
        results += ("margin",)
    # M's entries and pivots are checked by check_pd, the observer's f and G by no one.
    check = Step(
        "check", args=results, status=Status.NONFINITE_OUTPUT, what=what, alone=alone, note=note
    )
    if mass[0]:
        values += [
            Value("mass", mass[0], "local", "mass", "stored entries of the mass matrix M(q)"),
            Value("mass_pivot", mass[1], "local", "mass_pivot", "pivots of M's LDL^T"),
        ]
        results += ("mass", "mass_pivot")
    if observer:
        values += [
            Value("drift", observer, "output", "drift", "f(x), the plant's drift"),
            Value("g", observer * n_inputs, "output", "g", "G(x), row-major"),
        ]
        results += ("drift", "g")
    return values, results, check, call_note


def law_plan(
    *,
    n_states: int,
    n_inputs: int,
    n_outputs: int,
    n_params: int,
    n_kkt: int | None = None,
    k: int,
    tau: int,
    hessian: int,
    r_blocks: tuple[tuple[int, ...], ...],
    references: int = 0,
    integral: bool = False,
    observer: int = 0,
    mass: tuple[int, int] = (0, 0),
    margins: int = 0,
) -> Plan:
    """The plan of the law for a controller's sizes.

    Parameters
    ----------
    n_states, n_inputs, n_outputs, n_params, k : int
        Sizes of the closed-loop state, the plant input, the outputs, the parameters,
        and the number of Hurwitz coefficients (the order of the error dynamics, one more
        with integral action).
    tau : int
        Number of the jet's terms of time and parameters alone (0: the jet has none, and
        there is no ``jet_time`` kernel).
    hessian : int
        Number of the Hessian's stored entries (0: the Hessian is constant, inverted at
        generation time, and the ``jet`` kernel returns ``z`` itself).
    r_blocks : tuple of tuple of int
        R's diagonal blocks.
    references : int, optional
        Number of entries of the reference jets (0: the spec has no references).
    n_kkt : int, optional
        The law's unknowns: the outputs' and, with equality constraints, the
        multipliers' k-th derivatives (default: the outputs alone).
    integral : bool, optional
        Integral action: the jet kernel also returns ``grad f0`` (the integral states'
        rates), which the closed-loop kernel reads.
    observer : int, optional
        With a disturbance observer, the number of plant states: the jet kernel also
        returns ``drift`` (``f(x)``) and ``g`` (``G(x)``, row-major), outputs of the law
        that the stateful controller reads and no check looks at (0: no observer).
    mass : (int, int), optional
        For a plant in mass-matrix form, the numbers of stored entries of ``M`` and of
        coordinates: the jet kernel factors ``M`` and also returns those entries
        (``mass``) and the pivots (``mass_pivot``), which ``check_pd`` checks first.
    margins : int, optional
        The number of inequality constraints: the jet kernel also returns their margins
        ``s(t) - g_i(y, t)`` (``margin``), which ``check_margin`` checks before the
        finiteness check (0: none).

    Returns
    -------
    Plan
        The plan.
    """
    m = n_outputs
    n = m if n_kkt is None else n_kkt
    r_entries = sum(len(block) ** 2 for block in r_blocks)
    values = [
        Value("t", 1, "input", "t", "time"),
        Value("s", n_states, "input", "s", "closed-loop state"),
        Value("p", max(n_params, 1), "input", "p", "parameters"),
        Value("a", k, "input", "a", "Hurwitz coefficients"),
    ]
    per_batch: list[Step] = []
    jet_args: tuple[str, ...] = ("t", "s", "p", "a")
    if references:
        values.append(Value("refs", references, "input", "refs", "reference jets"))
        jet_args += ("refs",)
    if tau:
        values.append(Value("tau", tau, "batch", "tau", "the jet's terms of time and parameters"))
        per_batch.append(Step("call", "jet_time", ("t", "p", "a"), ("tau",)))
        jet_args += ("tau",)
    jet_values, jet_results, check, call_note = _jet_outputs(
        hessian=hessian,
        n=n,
        n_inputs=n_inputs,
        integral=integral,
        margins=margins,
        mass=mass,
        observer=observer,
    )
    values += jet_values
    values += [
        Value("z", n, "local", "z", "y_imp^(k)" + (", then nu^(k)" if n > m else "")),
        Value("r", r_entries, "local", "r", "diagonal blocks of R, each row-major"),
        Value("pvec", m, "local", "pvec", "p = col(L_f^{r_i} h_i)"),
        Value("b", m, "local", "w", "v - p"),
        Value("w", m, "local", "w", "input of the extended plant, R^-1 (v - p)"),
        Value("u", n_inputs, "output", "u", "plant input"),
        Value("ds", n_states, "output", "ds", "time derivative of the closed-loop state"),
    ]
    steps = [Step("call", "jet", jet_args, jet_results, note=call_note)]
    # M's definiteness and the barriers' margins first: a failure of either also makes
    # results non-finite, and the finiteness check would name the wrong cause.
    steps += [_CHECK_PD] if mass[0] else []
    steps += [_CHECK_MARGIN] if margins else []
    steps.append(check)
    if hessian:
        steps.append(dataclasses.replace(_SOLVE_HESSIAN, pivots=_pivots(m, n)))
    steps += _DECOUPLE
    runtime = _runtime(hessian, r_blocks, mass[0], margins)
    rhs = _RHS
    if integral:
        call = _RHS[0]
        rhs = (dataclasses.replace(call, args=(*call.args, "grad")), *_RHS[1:])
    return Plan(tuple(values), tuple(per_batch), tuple(steps), _CONTROL, rhs, runtime)
