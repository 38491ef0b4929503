"""Stage 4: lower a :class:`~tvopt_codegen.derivation.Derivation` to kernels.

A kernel is a named straight-line program: ordered inputs (arrays addressed by slot),
CSE'd temporaries, and named outputs of fixed shape. Kernels hold the symbolic
engine's expressions only (:mod:`tvopt_codegen.symbolic`, either engine); printing them
is the backends' job, laying out files the templates'. User names never reach kernel
code: states are ``_s0, _s1, ...``, parameters ``_p0, ...``, and so on; the names
survive only as labels for comments.

The generated controller evaluates the paper's law (``Derivation.law``, written down by
:mod:`tvopt_codegen.derivation.law`) as a chain of kernels and two numerical solves (never a
symbolic inverse, docs/architecture.md section 2)::

    jet_time(t, p, a)      -> tau                 # the jet's terms of time and parameters
                                                  # alone: once per batch of states
    jet(t, s, p, a, tau)   -> hessian, jet_rhs, R, pvec
                                                  # grad_yy f0, sum a_i grad^(i) f0 - rest,
                                                  # decoupling matrix R and p
    z = solve(hessian, jet_rhs)                   # y_imp^(k), LDL^T
                                                  # (a constant Hessian: jet returns z itself)
    decoupling(t, s, p, z, q=pvec) -> b           # b = v - p with v_i = xi_i1 or z_i
    w = solve(R, b)                               # LU with partial pivoting
    closed_loop(t, s, p, w, z) -> ds, u           # extended vector field and plant input
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Sequence
from dataclasses import dataclass

from tvopt_codegen import symbolic as sx
from tvopt_codegen.cse import Outputs, make_kernel, make_kernels, split_invariant
from tvopt_codegen.derivation import Derivation
from tvopt_codegen.derivation.calculus import equality_calculus
from tvopt_codegen.derivation.law import symbols
from tvopt_codegen.derivation.model import Model
from tvopt_codegen.lowering.kernel import Arg, Kernel, KernelSet, Output
from tvopt_codegen.lowering.plan import Plan, law_plan
from tvopt_codegen.maths.jet import Assignment, atomize, fresh_symbols
from tvopt_codegen.maths.lie import control_affine
from tvopt_codegen.maths.sparse import cholesky_program, ldl_program, lu_operations

__all__ = ["Arg", "Kernel", "KernelSet", "Output", "lower"]

_slots = symbols


#: How kernels are made: :func:`~tvopt_codegen.cse.make_kernel` (one) and
#: :func:`~tvopt_codegen.cse.make_kernels` (several over one program), sharing one
#: controller's memo of odd functions.
_Make = Callable[..., Kernel]
_MakeMany = Callable[..., list[Kernel]]


@dataclass(frozen=True)
class _Args:
    """The kernels' arguments, and the substitution of derived symbols by their slots."""

    t: Arg
    s: Arg
    p: Arg
    a: Arg
    y: Arg
    w: Arg
    z: Arg
    subs: dict[sx.Expr, sx.Expr]
    y_subs: dict[sx.Expr, sx.Expr]
    #: The reference jets (one row per reference, derivatives 0 .. q), when there are any.
    r: tuple[Arg, ...] = ()


def _arguments(d: Derivation) -> _Args:
    model, law = d.model, d.law
    m, k = len(model.u), d.dynamics.k
    s_slots, p_slots = _slots("s", len(d.closed_loop.states)), _slots("p", len(model.params))
    y_slots = _slots("y", m)
    outputs = d.spec.outputs
    subs: dict[sx.Expr, sx.Expr] = dict(zip(d.closed_loop.states, s_slots, strict=True))
    subs |= dict(zip(model.params, p_slots, strict=True))
    refs: tuple[Arg, ...] = ()
    if model.references:
        q = d.jet.reference_order
        jets = [chain[: q + 1] for chain in d.jet.reference_jet]
        r_slots = _slots("r", len(jets) * (q + 1))
        subs |= dict(zip((s for chain in jets for s in chain), r_slots, strict=True))
        labels = tuple(str(symbol) for chain in jets for symbol in chain)
        refs = (Arg("refs", r_slots, labels, "reference jets, derivatives 0 .. q of each"),)
    return _Args(
        t=Arg("t", (), (), "time"),
        s=Arg("s", s_slots, d.closed_loop.state_names, "closed-loop state"),
        p=Arg("p", p_slots, tuple(q.name for q in model.params), "parameters"),
        # The law's unknowns are slots already (law.symbols names them like _slots).
        a=Arg("a", law.a, tuple(f"a_{i}" for i in range(len(law.a))), "Hurwitz coefficients"),
        y=Arg("y", y_slots, outputs, "outputs"),
        w=Arg("w", law.w, d.linearization.extension.inputs, "inputs of the extended plant"),
        z=Arg(
            "z",
            law.z,
            tuple(f"{o}^({k})" for o in (*outputs, *(nu.name for nu in model.multipliers))),
            "y_imp^(k)" + (", then nu^(k)" if model.multipliers else ""),
        ),
        subs=subs,
        y_subs=subs | dict(zip(model.y, y_slots, strict=True)),
        r=refs,
    )


def _programs(d: Derivation, mass: _Mass | None = None) -> dict[str, list[Assignment]]:
    """The derivation's straight-line programs, by what they compute."""
    model, k = d.model, d.dynamics.k
    signals = range(len(model.signals))
    return {
        "signals": list(d.jet.signal_program.assignments)
        + [
            (d.jet.signal_jet[i][q], d.jet.signal_jet_values[i][q])
            for i in signals
            for q in range(k + 1)
        ],
        "signals0": list(d.jet.signal_program.assignments)
        + [(d.jet.signal_jet[i][0], d.jet.signal_jet_values[i][0]) for i in signals],
        "y": [
            (d.jet.y_jet[i][j], d.jet.y_jet_values[i][j])
            for i in range(len(d.jet.y_jet))
            for j in range(k)
        ],
        "jet": list(d.jet.jet_program.assignments),
        "hessian": list(d.objective.hessian_program.assignments),
        "rest": list(d.jet.rest_program.assignments),
        "mass": [] if mass is None else mass.program,
    }


@dataclass(frozen=True)
class _Mass:
    """A mass-matrix plant's run-time solve, as a program every kernel that needs it prunes.

    Attributes
    ----------
    program : list of (Symbol, Expr)
        ``M``, ``F`` and ``B`` in three-address form, one LDL^T of ``M`` and a solve per
        column of ``[F B]``, ending in the assignments of ``a = M^-1 F`` and
        ``W = M^-1 B`` to their run-time symbols.
    entries : list of Expr
        ``M``'s stored entries (its lower triangle's structural nonzeros).
    pivots : list of Expr
        The LDL^T pivots, all positive where ``M`` is positive definite.
    """

    program: list[Assignment]
    entries: list[sx.Expr]
    pivots: list[sx.Expr]


def _mass(d: Derivation) -> _Mass | None:
    """The run-time solve of a mass-matrix plant (None for ``[system.dynamics]``).

    ``M`` is factored once per evaluation, never inverted: the same square-root-free
    sparse LDL^T as the Hessian's (:func:`~tvopt_codegen.maths.sparse.ldl_program`).
    """
    mech = d.model.mechanics
    if mech is None:
        return None
    n = len(mech.coordinates)
    m = len(mech.input_matrix[0])
    pattern = [(i, j) for i in range(n) for j in range(i + 1) if mech.mass_matrix[i][j] != 0]
    columns = [list(mech.forces)] + [[mech.input_matrix[i][j] for i in range(n)] for j in range(m)]
    flat = [mech.mass_matrix[i][j] for i, j in pattern] + [e for c in columns for e in c]
    program, atoms = atomize(flat, fresh_symbols("_mass"))
    entries = list(atoms[: len(pattern)])
    rhs = [list(atoms[len(pattern) + c * n : len(pattern) + (c + 1) * n]) for c in range(m + 1)]
    solve, solutions, pivots = ldl_program(pattern, n, entries, rhs, prefix="_ldl")
    # The spec's definitions first, as written: M, F and B read them by their symbols.
    assignments = list(mech.definitions) + list(program.assignments) + solve
    for i in range(n):
        targets = [mech.accelerations[i], *mech.gains[i]]
        for c, target in enumerate(targets):
            if isinstance(target, sx.Symbol):
                assignments.append((target, solutions[c][i]))
    return _Mass(assignments, entries, pivots)


def _outputs_as_states(d: Derivation, args: _Args) -> dict[sx.Expr, sx.Expr] | None:
    """Each output's state slot -> its output slot, when every output is a distinct state.

    Then f0's gradient and Hessian at outputs are the jet program's own, its state slots
    read as the outputs' (the riders of :func:`_jet_kernels`). None otherwise: with equalities
    (the jet's gradient is the KKT map's), or an output that is a function of the state.
    """
    model = d.model
    if model.equalities:
        return None
    slots: dict[sx.Expr, sx.Expr] = {}
    for i, (y, y_slot) in enumerate(zip(model.y, args.y.symbols, strict=True)):
        value = d.jet.y_jet_values[i][0]
        slot = args.subs.get(value) if isinstance(value, sx.Symbol) else None
        if d.jet.y_jet[i][0] != y or slot is None or slot in slots:
            return None
        slots[slot] = y_slot
    return slots


@dataclass(frozen=True)
class _ObjectiveKernels:
    """f0 in three-address form (its program and result), and its kernels' specifications."""

    program: list[Assignment]
    kernels: dict[str, tuple[str, str, list[Arg], Outputs]]


def _objective_outputs(d: Derivation, args: _Args) -> _ObjectiveKernels:
    """f0, its gradient and its Hessian at outputs, as :func:`make_kernels` takes them.

    f0 in three-address form, as the gradient's program is: lowered nested, its every
    barrier argument was walked whole by each pass (canonical_odd, CSE).
    """
    m = len(d.model.u)
    on_y = [args.t, args.y, args.p, *args.r]
    f0_program, (f0,) = atomize([d.model.f0], fresh_symbols("_f0_"))
    kernels: dict[str, tuple[str, str, list[Arg], Outputs]] = {
        "objective": ("objective", "The objective f0(y, t)", on_y, [("f0", (), [f0], "f0")]),
        "gradient": (
            "gradient",
            "grad_y f0(y, t)",
            on_y,
            [("grad", (m,), list(d.objective.objective_gradient), "grad_y f0")],
        ),
        "hessian": (
            "hessian",
            "grad_yy f0(y, t)",
            on_y,
            [("hess", (m, m), d.objective.objective_hessian, "grad_yy f0")],
        ),
    }
    return _ObjectiveKernels(list(f0_program.assignments), kernels)


def _shared_outputs(
    d: Derivation, mass: _Mass | None
) -> list[tuple[str, tuple[int, ...], Sequence[sx.Expr], str]]:
    """The jet kernel's outputs besides its law: R and p, and each feature's own."""
    law, m, n = d.law, len(d.model.u), d.jet.n_kkt
    grad = d.jet.grad_jet
    # R and p share their trigonometry with the output jet: one kernel, one CSE.
    shared: list[tuple[str, tuple[int, ...], Sequence[sx.Expr], str]] = [
        ("R", (len(law.r_entries),), law.r_entries, "diagonal blocks of the decoupling matrix"),
        ("pvec", (m,), list(d.decoupling.p), "p = col(L_f^{r_i} h_i)"),
    ]
    if d.closed_loop.integral_states:
        # Integral action: the integral states' rates, grad f0, computed once with the jet.
        shared.append(
            ("grad", (n,), [grad[0][i] for i in range(n)], "grad f0: the integrals' rates")
        )
    if d.model.constraints:
        # Each inequality's margin s(t) - g_i(y, t), which the plan's check_margin reads:
        # the law sees the barrier only through 1/(s - g_i), finite past it too.
        shared.append(_margin_output(d.model))
    if mass is not None:
        # M is factored where R and p need it; the plan's check_pd reads the pivots.
        # Before the observer's f and G: the order of the plan's results (law_plan),
        # which binds them by position (lower checks it by name).
        shared += [
            ("mass", (len(mass.entries),), mass.entries, "stored entries of the mass matrix"),
            ("mass_pivot", (len(mass.pivots),), mass.pivots, "pivots of M's LDL^T"),
        ]
    if d.robustness.observer is not None:
        # The disturbance observer reads f(x) and G(x) at the state the law is evaluated
        # at: here they share the jet's trigonometry, where a kernel of their own would
        # evaluate it again at every step.
        model = d.model
        rows, cols = model.G.shape
        shared += [
            ("drift", (rows,), list(model.f), "f(x): the plant's drift (the observer's)"),
            (
                "g",
                (rows * cols,),
                [model.G[i, j] for i in range(rows) for j in range(cols)],
                "G(x), row-major (the observer's)",
            ),
        ]
    return shared


def _jet_kernels(
    d: Derivation,
    args: _Args,
    programs: dict[str, list[Assignment]],
    kernel: _Make,
    kernels: _MakeMany,
    mass: _Mass | None,
    objective: _ObjectiveKernels,
) -> tuple[Kernel, Kernel | None, Kernel, dict[str, Kernel]]:
    """The jet (with R and p), its LDL^T solve, the optimality error E, and riders.

    The solve is left out (None) when the Hessian is constant. E reads the same gradient
    jet as the jet kernel: both are lowered together. When the outputs are states
    (:func:`_outputs_as_states`), f0's gradient and Hessian at outputs may be cut from
    the same program (:func:`.make_kernels`' riders, returned by name), where lowering
    the objective's program again for them was a sixth of a team's run.
    """
    law, m, n, k = d.law, len(d.model.u), d.jet.n_kkt, d.dynamics.k
    grad = d.jet.grad_jet
    jet_program = programs["signals"] + programs["y"] + programs["jet"] + programs["hessian"]
    jet_program += programs["rest"] + programs["mass"]
    inputs = [args.t, args.s, args.p, args.a, *args.r]
    shared = _shared_outputs(d, mass)
    what = "grad^(j) f0" if n == m else "F^(j), F = [grad f0 + J_a^T nu; a]"
    optimality_kernel = (
        "optimality",
        f"Optimality error E: row j is {what}",
        [args.t, args.s, args.p, *args.r],
        [("E", (k, n), [grad[j][i] for j in range(k) for i in range(n)], what)],
    )

    as_states = _outputs_as_states(d, args)
    riders, companions = [], []
    if as_states is not None:
        specs = objective.kernels
        riders = [(*specs[name], as_states) for name in ("gradient", "hessian")]
        # f0's kernel is lowered apart, searched when small (a union with the jet
        # cost both more operations); its size counts in whether the riders ride.
        companions = [specs["objective"]]
        jet_program = jet_program + objective.program
    ridden: dict[str, Kernel] = {}

    def with_optimality(jet_doc: str, outputs: Outputs) -> tuple[Kernel, Kernel]:
        jet, optimality, *cut = kernels(
            [("jet", jet_doc, inputs, outputs), optimality_kernel],
            jet_program,
            args.subs,
            riders=riders,
            companions=companions,
        )
        ridden.update((made.name, made) for made in cut)
        return jet, optimality

    if law.y_imp is not None:
        jet, optimality = with_optimality(
            "y_imp^(k) = Hess^-1 [sum a_i grad^(i) f0 - rest] for the constant Hessian",
            [("z", (n,), law.y_imp, args.z.doc), *shared],
        )
        return jet, None, optimality, ridden
    # The Hessian goes out as the entries of its lower triangle that the law keeps.
    pattern = law.hessian_pattern
    value = dict(d.objective.hessian_entries)
    jet, optimality = with_optimality(
        "Hessian of f0 and the right-hand side of Hess y_imp^(k) = sum a_i grad^(i) - rest",
        [
            (
                "hessian",
                (len(pattern),),
                [value.get(entry, sx.ZERO) for entry in pattern],
                "nonzero entries of the lower triangle of grad_yy f0",
            ),
            ("jet_rhs", (n,), law.jet_rhs, "sum_i a_i grad^(i) f0 - rest"),
            *shared,
        ],
    )
    h_slots, c_slots = _slots("h", len(pattern)), _slots("c", n)
    # The outputs' block is eliminated first: its pivots are positive where f0 is
    # strongly convex, the multipliers' then negative unless the constraints' gradients
    # are dependent. Their signs are flipped so that one test, every pivot positive,
    # checks both (the first m failing: not convex; a later one: dependent).
    program, solution, pivots = cholesky_program(pattern, n, h_slots, c_slots, leading=m)
    pivots = [p if b < m else -p for b, p in enumerate(pivots)]
    what = "pivots of the elimination, positive if Hess > 0"
    if n > m:
        what = "pivots of the elimination (the multipliers' negated), positive if K is a KKT matrix"
    cholesky = kernel(
        "cholesky",
        "Sparse LDL^T (square-root-free Cholesky) solve of Hess z = c (z = y_imp^(k)) "
        "and its pivots",
        [
            Arg("h", h_slots, tuple(f"H[{i}, {j}]" for i, j in pattern), "Hessian"),
            Arg("c", c_slots, tuple(f"c[{i}]" for i in range(n)), "right-hand side"),
        ],
        program,
        [
            ("z", (n,), solution, args.z.doc),
            ("pivot", (n,), pivots, what),
        ],
        {},
        search=False,  # one operation per assignment already: nothing to find
    )
    return jet, cholesky, optimality, ridden


def _input_kernels(
    d: Derivation, args: _Args, kernel: _Make, mass: list[Assignment]
) -> list[Kernel]:
    """From y_imp^(k) to the plant: b = v - p, the closed-loop field, the plant input.

    With integral action the field's last entries are ``grad f0`` (the integral states'
    rates), which the jet kernel returns as ``grad``.
    """
    law, m = d.law, len(d.model.u)
    q_slots = _slots("q", m)
    arg_q = Arg("q", q_slots, tuple(f"p_{o}" for o in d.spec.outputs), "p of the decoupling")
    # An entry of p that is a number (0 for a kinematic plant) is subtracted here as that
    # number, not read from the jet's output.
    p = [d.decoupling.p[i] if d.decoupling.p[i].is_Number else q_slots[i] for i in range(m)]
    # With the extended-state observer, its estimate of the lumped disturbance too.
    lumped = law.lumped or (sx.ZERO,) * m
    what = "v - p - d_hat" if d.rejection is not None else "v - p"
    decoupling = kernel(
        "decoupling",
        f"b = {what}, so that R w = b linearizes the plant",
        [args.t, args.s, args.p, args.z, arg_q],
        [],
        [("b", (m,), [law.v[i] - p[i] - lumped[i] for i in range(m)], what)],
        args.subs,
    )
    count = len(d.closed_loop.integral_states)
    field = list(law.closed_loop)
    inputs = [args.t, args.s, args.p, args.w, args.z]
    if count:
        # The integral states' rates come from the jet kernel (its output grad).
        g_slots = _slots("e", count)
        labels = tuple(f"d{name}/dt" for name in d.closed_loop.integral_states)
        inputs.append(Arg("grad", g_slots, labels, "grad f0: the integrals' rates"))
        field[len(field) - count :] = g_slots
    closed_loop = kernel(
        "closed_loop",
        "Closed-loop vector field and the plant input",
        inputs,
        mass,
        [
            ("ds", (len(d.closed_loop.states),), field, "time derivative of the closed-loop state"),
            ("u", (m,), law.plant_input, "plant input"),
        ],
        args.subs,
    )
    plant_input = kernel(
        "plant_input",
        "The plant input alone (control needs no vector field)",
        [args.t, args.s, args.p, args.w],
        mass,
        [("u", (m,), law.plant_input, "plant input")],
        args.subs,
    )
    return [decoupling, closed_loop, plant_input]


def _objective_kernels(
    d: Derivation,
    args: _Args,
    programs: dict[str, list[Assignment]],
    kernels: _MakeMany,
    objective: _ObjectiveKernels,
    ridden: dict[str, Kernel],
) -> list[Kernel]:
    """f0 and its first and second derivatives in y, at given outputs.

    Those the jet's program gave already (``ridden``, by name) are not lowered again.
    """
    # One program for the three: the signals, then the gradient's program (the jet's
    # first assignments) and f0's, which each kernel prunes to what it needs. f0's
    # kernel alone reads no assignment of the gradient's: they are not read at all.
    program = list(programs["signals0"])
    if not ridden:
        program += d.objective.objective_program.assignments
    program += objective.program
    wanted = [spec for name, spec in objective.kernels.items() if name not in ridden]
    made = iter(kernels(wanted, program, args.y_subs))
    return [ridden.get(name) or next(made) for name in objective.kernels]


def _margin_output(model: Model) -> tuple[str, tuple[int, ...], list[sx.Expr], str]:
    """The output ``margin``: each inequality's ``s(t) - g_i(y, t)``.

    The law's jet and the kernels of the public functions of B return it alike.
    """
    margins = [model.slack - sx.sympify(c.g) for c in model.constraints]
    return ("margin", (len(margins),), margins, "s(t) - g_i(y, t), each positive")


def _margin_kernels(
    d: Derivation, args: _Args, programs: dict[str, list[Assignment]], kernel: _Make
) -> list[Kernel]:
    """Each inequality's margin ``s(t) - g_i(y, t)`` at a state and at outputs.

    The public functions of a state (``optimality_error``) and of the outputs (f0, its
    gradient and Hessian) evaluate the barrier objective, which is undefined where a
    margin is not positive although its derivatives, through ``1/(s - g_i)``, are finite
    there: each checks these first, as the law checks the jet's (none without
    inequalities).
    """
    model = d.model
    if not model.constraints:
        return []
    output = [_margin_output(model)]
    return [
        kernel(
            "margin_state",
            "The inequalities' margins s(t) - g_i(y(x), t) at a closed-loop state",
            [args.t, args.s, args.p, *args.r],
            programs["signals0"] + programs["y"],
            output,
            args.subs,
        ),
        kernel(
            "margin_output",
            "The inequalities' margins s(t) - g_i(y, t) at outputs",
            [args.t, args.y, args.p, *args.r],
            programs["signals0"],
            output,
            args.y_subs,
        ),
    ]


def _plant_kernels(
    d: Derivation, args: _Args, kernel: _Make, mass: list[Assignment]
) -> list[Kernel]:
    """The plant alone: ``x' = f(x) + G(x) u`` and ``y = h(x)``, over the plant's state."""
    model = d.model
    x_slots, u_slots = _slots("x", len(model.x)), _slots("u", len(model.u))
    arg_x = Arg("x", x_slots, d.spec.states, "plant state")
    arg_u = Arg("u", u_slots, d.spec.inputs, "plant input")
    subs: dict[sx.Expr, sx.Expr] = dict(zip(model.x, x_slots, strict=True))
    subs |= dict(zip(model.u, u_slots, strict=True))
    subs |= dict(zip(model.params, args.p.symbols, strict=True))
    dx = control_affine(model.f, model.G, model.u)
    plant = kernel(
        "plant",
        "The plant alone: x' = f(x) + G(x) u",
        [args.t, arg_x, arg_u, args.p],
        mass,
        [("dx", (len(dx),), dx, "time derivative of the plant state")],
        subs,
    )
    outputs = kernel(
        "outputs",
        "The outputs y = h(x)",
        [args.t, arg_x, args.p],
        [],
        [("y", (len(model.h),), list(model.h), "outputs")],
        subs,
    )
    kernels = [plant, outputs]
    if d.rejection is not None:
        # Where the extended-state observer starts: Phi(x), its error zero on the model.
        rows = d.rejection.orders
        phi = [d.linearization.lie[i][j] for i in range(len(rows)) for j in range(rows[i])]
        names = tuple(name for chain in d.rejection.states for name in chain[:-1])
        kernels.append(
            kernel(
                "eso_start",
                "Phi(x): the extended-state observer's estimates where its error is zero",
                [args.t, args.s, args.p],
                mass,
                [("eta", (len(phi),), phi, f"Phi(x) for {', '.join(names)}")],
                args.subs,
            )
        )
    return kernels


def lower(derivation: Derivation) -> KernelSet:
    """Lower a derivation to the kernels every backend prints, and the plan that runs them.

    Parameters
    ----------
    derivation : Derivation
        The derived control law.

    Returns
    -------
    KernelSet
        Kernels ``jet_time`` (unless the jet has no term of time and parameters alone),
        ``jet``, ``cholesky`` (unless the Hessian is constant), ``decoupling``,
        ``closed_loop``, ``plant_input``, ``optimality``, ``objective``, ``gradient``,
        ``hessian``, and the plant alone: ``plant`` and ``outputs``; the execution plan
        (:mod:`tvopt_codegen.lowering.plan`).
    """
    d = derivation
    # One memo of odd functions for all kernels: a node's sign is decided once (by the
    # node alone, so the kernels' order does not matter).
    odd: dict[sx.Expr, sx.Expr] = {}
    # And one memo of free symbols: the kernels prune the same programs.
    symbols: dict[sx.Expr, set[sx.Expr]] = {}
    kernel = functools.partial(make_kernel, odd=odd, symbols=symbols)
    kernels = functools.partial(make_kernels, odd=odd, symbols=symbols)
    args = _arguments(d)
    mass = _mass(d)
    programs = _programs(d, mass)
    objective = _objective_outputs(d, args)
    jet, cholesky, optimality, ridden = _jet_kernels(
        d, args, programs, kernel, kernels, mass, objective
    )
    # Everything of the jet that depends on time and parameters alone is computed once
    # per batch of states (the C backend's batch functions; a block in NumPy).
    split = split_invariant(jet, "jet_time", "The jet's terms of time and parameters alone")
    jet_time = None
    if split is not None:
        jet_time, jet = split
    rest = _input_kernels(d, args, kernel, programs["mass"]) + [optimality]
    rest += _objective_kernels(d, args, programs, kernels, objective, ridden)
    rest += _margin_kernels(d, args, programs, kernel)
    rest += _plant_kernels(d, args, kernel, programs["mass"])
    law = d.law
    plan = law_plan(
        n_states=len(d.closed_loop.states),
        n_inputs=len(d.model.u),
        n_outputs=len(d.spec.outputs),
        n_kkt=d.jet.n_kkt,
        n_params=len(d.model.params),
        k=len(d.dynamics.coefficients),
        integral=bool(d.closed_loop.integral_states),
        observer=len(d.spec.states) if d.robustness.observer is not None else 0,
        tau=0 if jet_time is None else jet_time.outputs[0].shape[0],
        hessian=0 if cholesky is None else jet.outputs[0].shape[0],
        r_blocks=law.r_blocks,
        references=len(args.r[0].symbols) if args.r else 0,
        mass=(0, 0) if mass is None else (len(mass.entries), len(mass.pivots)),
        margins=len(d.model.constraints),
    )
    lowered = (
        *((jet_time,) if jet_time is not None else ()),
        jet,
        *((cholesky,) if cholesky is not None else ()),
        *rest,
    )
    check_binding(lowered, plan)
    return KernelSet(
        d,
        lowered,
        plan,
        law.r_blocks,
        sum(lu_operations(len(block)) for block in law.r_blocks),
    )


#: A kernel output's name where the plan's value has another.
_PLAN_NAMES = {"R": "r", "hessian": "hess"}


def check_binding(kernels: Sequence[Kernel], plan: Plan) -> None:
    """Check that every call of the plan binds each kernel output to the value it is.

    The backends bind a call's ``results`` to the kernel's outputs by position. The jet
    kernel's outputs depend on the features a spec combines (integral action, a mass
    matrix, an observer), and each feature appends its own: two lists kept in the same
    order by hand once put the observer's ``f(x)`` in the mass matrix's place, and the
    law failed at every state. Checked here by name and size, such a slip is an
    internal error at generation time, not a controller that is wrong.

    Raises
    ------
    RuntimeError
        Naming the kernel, the position and the two names.
    """
    by_name = {kernel.name: kernel for kernel in kernels}
    for step in (*plan.per_batch, *plan.steps, *plan.control, *plan.rhs):
        if step.op != "call":
            continue
        kernel = by_name[step.kernel]
        names = tuple(_PLAN_NAMES.get(out.name, out.name) for out in kernel.outputs)
        if names != step.results:
            raise RuntimeError(
                f"the plan binds kernel {step.kernel}'s outputs {names} as {step.results}"
            )
        for out in kernel.outputs:
            value = plan.value(_PLAN_NAMES.get(out.name, out.name))
            if value.size != len(out.exprs):
                raise RuntimeError(
                    f"kernel {step.kernel}'s output {out.name} has {len(out.exprs)} entries, "
                    f"the plan's value {value.name} {value.size}"
                )


@dataclass(frozen=True)
class CheckKernels:
    """Kernels that check a run rather than control it (the sweep's compiled loop).

    Attributes
    ----------
    decoupling : Kernel
        The whole decoupling matrix R(s), row-major (for det R).
    constraints : Kernel or None
        The barrier's slack s(t), then each constraint g_i(y, t).
    equalities : Kernel or None
        ``a(y, t)``, ``J_a`` and ``sum_j nu_j grad_yy a_j`` (the multipliers' curvature).
    """

    decoupling: Kernel
    constraints: Kernel | None
    equalities: Kernel | None


def check_kernels(derivation: Derivation) -> CheckKernels:
    """Lower the check kernels of a derivation (on demand: only a sweep needs them).

    Their derivatives come from :mod:`tvopt_codegen.derivation.calculus`; lowering, as
    for the law's kernels, only substitutes slots and applies CSE.
    """
    d = derivation
    model = d.model
    args = _arguments(d)
    m = d.linearization.R.rows
    # R = J_h M^-1 B of a mass-matrix plant reads the run-time solve.
    mass = _mass(d)
    decoupling = make_kernel(
        "sweep_decoupling",
        "The decoupling matrix R(s), row-major",
        [args.t, args.s, args.p],
        [] if mass is None else mass.program,
        [
            (
                "r",
                (m * m,),
                [d.linearization.R[i, j] for i in range(m) for j in range(m)],
                "decoupling matrix R",
            )
        ],
        args.subs,
        odd={},
    )
    constraints = None
    if model.constraints:
        values = [model.slack, *(sx.sympify(c.g) for c in model.constraints)]
        constraints = make_kernel(
            "sweep_constraints",
            "The barrier's slack s(t), then each constraint g_i(y, t) (<= 0 when kept)",
            [args.t, args.y, args.p],
            list(model.signals),
            [("g", (len(values),), values, "slack and constraint values")],
            args.y_subs,
            odd={},
        )
    equalities = None
    if model.equalities:
        slots = symbols("nu", len(model.multipliers))
        arg_nu = Arg("nu", slots, tuple(nu.name for nu in model.multipliers), "multipliers")
        calculus = equality_calculus(model)
        n, q = len(model.y), len(model.equalities)
        equalities = make_kernel(
            "sweep_equalities",
            "The equalities a_j(y, t), their Jacobian in y and sum_j nu_j grad_yy a_j",
            [args.t, args.y, args.p, arg_nu],
            list(model.signals),
            [
                ("a", (q,), calculus.values, "equality values (0 when kept)"),
                ("jac", (q, n), calculus.jacobian, "J_a"),
                (
                    "curv",
                    (n, n),
                    calculus.curvature(model.multipliers),
                    "the multipliers' curvature",
                ),
            ],
            args.y_subs | dict(zip(model.multipliers, slots, strict=True)),
            odd={},
        )
    return CheckKernels(decoupling, constraints, equalities)
