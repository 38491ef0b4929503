"""Stage 4: lower a :class:`~tvopt_codegen.derivation.Derivation` to kernels.

A kernel is a named straight-line program: ordered inputs (arrays addressed by slot),
CSE'd temporaries, and named outputs of fixed shape. Kernels hold sympy expressions
only; printing them is the backends' job, laying out files the templates'. User names
never reach kernel code: states are ``_s0, _s1, ...``, parameters ``_p0, ...``, and so
on; the names survive only as labels for comments.

The generated controller evaluates the paper's law (``Derivation.law``, written down by
:mod:`tvopt_codegen.law`) as a chain of kernels and two numerical solves (never a
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
from collections.abc import Sequence

import sympy as sp

from tvopt_codegen.cse import make_kernel, split_invariant
from tvopt_codegen.derivation import Derivation
from tvopt_codegen.kernel import Arg, Kernel, KernelSet, Output
from tvopt_codegen.law import symbols
from tvopt_codegen.sparse import cholesky_program, lu_operations

__all__ = ["Arg", "Kernel", "KernelSet", "Output", "lower"]

_slots = symbols


def lower(derivation: Derivation) -> KernelSet:
    """Lower a derivation to the kernels every backend prints.

    Parameters
    ----------
    derivation : Derivation
        The derived control law.

    Returns
    -------
    KernelSet
        Kernels ``jet_time`` (unless the jet has no term of time and parameters alone),
        ``jet``, ``cholesky`` (unless the Hessian is constant), ``decoupling``,
        ``closed_loop``, ``plant_input``, ``optimality``, ``objective``, ``gradient`` and
        ``hessian``.
    """
    d = derivation
    odd: dict[sp.Basic, sp.Expr] = {}
    kernel = functools.partial(make_kernel, odd=odd)
    model = d.model
    m, k = len(model.u), d.k
    n = len(d.states)
    s_slots, p_slots = _slots("s", n), _slots("p", len(model.params))
    # The law's unknowns are slots already (law.symbols names them like _slots).
    a_slots, y_slots = d.law.a, _slots("y", m)
    w_slots, z_slots = d.law.w, d.law.z
    param_names = tuple(q.name for q in model.params)
    output_names = d.spec.outputs
    arg_t = Arg("t", (), (), "time")
    arg_s = Arg("s", s_slots, d.state_names, "closed-loop state")
    arg_p = Arg("p", p_slots, param_names, "parameters")
    arg_a = Arg("a", a_slots, tuple(f"a_{i}" for i in range(k)), "Hurwitz coefficients")
    arg_y = Arg("y", y_slots, output_names, "outputs")
    arg_w = Arg("w", w_slots, d.extension.inputs, "inputs of the extended plant")
    arg_z = Arg("z", z_slots, tuple(f"{o}^({k})" for o in output_names), "y_imp^(k)")
    subs: dict[sp.Symbol, sp.Expr] = dict(zip(d.states, s_slots, strict=True))
    subs |= dict(zip(model.params, p_slots, strict=True))

    signal_block = list(d.signal_program.assignments) + [
        (d.signal_jet[li][q], d.signal_jet_values[li][q])
        for li in range(len(model.signals))
        for q in range(k + 1)
    ]
    y_block = [(d.y_jet[i][j], d.y_jet_values[i][j]) for i in range(m) for j in range(k)]
    jet_block = list(d.jet_program.assignments)
    hess_block = list(d.hessian_program.assignments)
    law = d.law
    hess_value = dict(d.hessian_entries)
    jet_program = signal_block + y_block + jet_block + hess_block
    jet_program += list(d.rest_program.assignments)
    # R and p share their trigonometry with the output jet: one kernel, one CSE.
    shared: list[tuple[str, tuple[int, ...], Sequence[sp.Expr], str]] = [
        ("R", (len(law.r_entries),), law.r_entries, "diagonal blocks of the decoupling matrix"),
        ("pvec", (m,), list(d.p), "p = col(L_f^{r_i} h_i)"),
    ]
    if law.y_imp is not None:
        jet = kernel(
            "jet",
            "y_imp^(k) = Hess^-1 [sum a_i grad^(i) f0 - rest] for the constant Hessian",
            [arg_t, arg_s, arg_p, arg_a],
            jet_program,
            [("z", (m,), law.y_imp, "y_imp^(k)"), *shared],
            subs,
        )
        cholesky = None
    else:
        # The Hessian goes out as the entries of its lower triangle that law keeps.
        hess_entries = law.hessian_pattern
        jet = kernel(
            "jet",
            "Hessian of f0 and the right-hand side of Hess y_imp^(k) = sum a_i grad^(i) - rest",
            [arg_t, arg_s, arg_p, arg_a],
            jet_program,
            [
                (
                    "hessian",
                    (len(hess_entries),),
                    [hess_value.get(entry, sp.Integer(0)) for entry in hess_entries],
                    "nonzero entries of the lower triangle of grad_yy f0",
                ),
                ("jet_rhs", (m,), law.jet_rhs, "sum_i a_i grad^(i) f0 - rest"),
                *shared,
            ],
            subs,
        )
        h_slots, c_slots = _slots("h", len(hess_entries)), _slots("c", m)
        program, solution, pivots = cholesky_program(hess_entries, m, h_slots, c_slots)
        cholesky = kernel(
            "cholesky",
            "Sparse LDL^T (square-root-free Cholesky) solve of Hess z = c (z = y_imp^(k)) "
            "and its pivots",
            [
                Arg("h", h_slots, tuple(f"H[{i}, {j}]" for i, j in hess_entries), "Hessian"),
                Arg("c", c_slots, tuple(f"c[{i}]" for i in range(m)), "right-hand side"),
            ],
            program,
            [
                ("z", (m,), solution, "y_imp^(k)"),
                ("pivot", (m,), pivots, "pivots of the elimination, positive if Hess > 0"),
            ],
            {},
            search=False,  # one operation per assignment already: nothing to find
        )

    # Everything of the jet that depends on time and parameters alone is computed once
    # per batch of states (the C backend's batch functions; a block in NumPy).
    split = split_invariant(jet, "jet_time", "The jet's terms of time and parameters alone")
    jet_time = None
    if split is not None:
        jet_time, jet = split

    q_slots = _slots("q", m)
    arg_q = Arg("q", q_slots, tuple(f"p_{o}" for o in output_names), "p of the decoupling")
    decoupling = kernel(
        "decoupling",
        "b = v - p, so that R w = b linearizes the plant",
        [arg_t, arg_s, arg_p, arg_z, arg_q],
        [],
        [("b", (m,), [law.v[i] - q_slots[i] for i in range(m)], "v - p")],
        subs,
    )
    plant_input = law.plant_input
    closed_loop = kernel(
        "closed_loop",
        "Closed-loop vector field and the plant input",
        [arg_t, arg_s, arg_p, arg_w, arg_z],
        [],
        [
            ("ds", (n,), law.closed_loop, "time derivative of the closed-loop state"),
            ("u", (m,), plant_input, "plant input"),
        ],
        subs,
    )

    plant_input_kernel = kernel(
        "plant_input",
        "The plant input alone (control needs no vector field)",
        [arg_t, arg_s, arg_p, arg_w],
        [],
        [("u", (m,), plant_input, "plant input")],
        subs,
    )

    optimality = kernel(
        "optimality",
        "Optimality error E: row j is grad^(j) f0",
        [arg_t, arg_s, arg_p],
        signal_block + y_block + jet_block,
        [("E", (k, m), [d.grad_jet[j][i] for j in range(k) for i in range(m)], "grad^(j) f0")],
        subs,
    )

    y_subs = dict(subs) | dict(zip(model.y, y_slots, strict=True))
    signal0 = list(d.signal_program.assignments) + [
        (d.signal_jet[li][0], d.signal_jet_values[li][0]) for li in range(len(model.signals))
    ]
    objective = kernel(
        "objective",
        "The objective f0(y, t)",
        [arg_t, arg_y, arg_p],
        signal0,
        [("f0", (), [model.f0], "f0")],
        y_subs,
    )
    # Both from the gradient's program (the jet's first assignments), which _kernel
    # prunes to what each needs.
    gradient = kernel(
        "gradient",
        "grad_y f0(y, t)",
        [arg_t, arg_y, arg_p],
        signal0 + jet_block,
        [("grad", (m,), list(d.grad_jet[0]), "grad_y f0")],
        y_subs,
    )
    hessian = kernel(
        "hessian",
        "grad_yy f0(y, t)",
        [arg_t, arg_y, arg_p],
        signal0 + jet_block + hess_block,
        [("hess", (m, m), law.hessian, "grad_yy f0")],
        y_subs,
    )
    return KernelSet(
        d,
        (
            *((jet_time,) if jet_time is not None else ()),
            jet,
            *((cholesky,) if cholesky is not None else ()),
            decoupling,
            closed_loop,
            plant_input_kernel,
            optimality,
            objective,
            gradient,
            hessian,
        ),
        law.r_blocks,
        sum(lu_operations(len(block)) for block in law.r_blocks),
    )
