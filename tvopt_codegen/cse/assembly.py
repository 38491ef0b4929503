"""Kernels from programs: slots substituted, CSE, and the time-only part split off.

Kernels that read one program are lowered together (:func:`make_kernels`).
"""

from __future__ import annotations

import itertools
from collections.abc import Mapping, Sequence
from typing import Any

from tvopt_codegen import symbolic as sx
from tvopt_codegen.cse.coefficients import factored
from tvopt_codegen.cse.dag import Dag
from tvopt_codegen.cse.numbering import (
    SMALL_PROGRAM_OPS,
    _inline_single_use,
    _number,
    _number_dag,
    _prune,
    _reduce,
    _reduce_dag,
    numbered,
    ordered_cse,
)
from tvopt_codegen.cse.programs import inline_single_use, needed, symbols_read
from tvopt_codegen.cse.rewrite import (
    _expr,
    _rebuild,
    _replace_all,
    _same,
    _substitute,
    _unchanged,
    canonical_odd,
    operation_count,
    symbols_in,
)
from tvopt_codegen.lowering.kernel import Arg, Kernel, Output
from tvopt_codegen.maths.jet import Assignment, release

#: A kernel's outputs: (name, shape, expressions in row-major order, description).
Outputs = Sequence[tuple[str, tuple[int, ...], Sequence[sx.Expr], str]]

#: A kernel cut from another's program (:func:`make_kernels`): name, doc, inputs,
#: outputs over that program's arguments, and the renaming of those to its own inputs.
Rider = tuple[str, str, Sequence[Arg], Outputs, Mapping[sx.Expr, sx.Expr]]


def _prepare(
    assignments: Sequence[Assignment],
    exprs: Sequence[sx.Expr],
    subs: Mapping[sx.Expr, sx.Expr],
    odd: dict[sx.Expr, sx.Expr] | None,
    symbols: dict[sx.Expr, set[sx.Expr]] | None = None,
) -> tuple[list[Assignment], list[sx.Expr]]:
    """What ``exprs`` need of the program, with slots substituted and odd functions signed.

    On SymEngine the odd functions are left to :meth:`.Dag.signed_odd`, and the pruning
    to :func:`.programs.needed` on the DAG the program is read into: here it was a walk
    of every value in C++ (free symbols) for a few assignments dropped (1,024 of a ring
    of 128 agents' 38,173), which the DAG's walk drops again.
    """
    if not sx.SYMENGINE:
        # Only what the outputs need: the gradient kernel, say, reads the jet's first part.
        assignments = _prune(assignments, exprs, symbols)
    slots: dict[sx.Expr, sx.Expr] = {}
    signs: dict[sx.Expr, sx.Expr] = {} if odd is None else odd
    # Slots are symbols: substituting and signing odd functions is one pass.
    if not all(value.is_Atom for value in subs.values()):
        subs = {sym: canonical_odd(value, signs) for sym, value in subs.items()}
    if sx.SYMENGINE:
        # One walk in C++ for the whole program. The slots' values are symbols, or the
        # signals' expressions of time, seldom under a coefficient (_replace_all). Odd
        # functions are signed on the DAG the program is read into (Dag.signed_odd).
        values = _replace_all([value for _, value in assignments] + list(exprs), subs)
        n = len(assignments)
        program = [(sym, value) for (sym, _), value in zip(assignments, values[:n], strict=True)]
        return program, values[n:]
    program = [(sym, _substitute(value, subs, slots, signs)) for sym, value in assignments]
    return program, [_substitute(e, subs, slots, signs) for e in exprs]


def _package(
    name: str,
    doc: str,
    inputs: Sequence[Arg],
    outputs: Outputs,
    body: Sequence[Assignment],
    reduced: Sequence[sx.Expr],
    before: int,
    ops: int | None = None,
    reads: set[sx.Expr] | None = None,
) -> Kernel:
    """The kernel of a CSE'd program, its outputs cut to their shapes; checks its symbols.

    ``ops`` is its operation count when the caller has it (:meth:`.Dag.operations`), and
    ``reads`` the symbols it reads besides its temporaries (:func:`.programs.symbols_read`).
    """
    packed: list[Output] = []
    start = 0
    for out_name, shape, exprs, out_doc in outputs:
        packed.append(Output(out_name, shape, tuple(reduced[start : start + len(exprs)]), out_doc))
        start += len(exprs)
    allowed = {s for arg in inputs for s in arg.symbols}
    allowed.add(sx.symbol("t"))
    if reads is None:
        allowed |= {sym for sym, _ in body}
        reads = symbols_in([v for _, v in body] + list(reduced))
    stray = reads - allowed
    if stray:
        raise AssertionError(f"kernel {name}: unbound symbols {sorted(map(str, stray))}")
    return Kernel(
        name,
        doc,
        tuple(inputs),
        tuple(body),
        tuple(packed),
        operation_count([v for _, v in body] + list(reduced)) if ops is None else ops,
        before,
    )


def _flat(outputs: Outputs) -> list[sx.Expr]:
    return [e for _, _, exprs, _ in outputs for e in exprs]


def _symbolic(outputs: Outputs) -> tuple[list[sx.Expr], list[int]]:
    """A kernel's output expressions that are not numbers, and their places in ``_flat``.

    Numbers need no substitution, CSE or inlining, but each pass did its per-expression
    work on every one: a team's Hessian is almost all zeros (259 thousand of its 262
    thousand entries at 256 agents), and lowering it took longer than the objective's
    and gradient's kernels together.
    """
    flat = _flat(outputs)
    where = [i for i, e in enumerate(flat) if not isinstance(e, sx.Number)]
    return [flat[i] for i in where], where


def _constant_ops(outputs: Outputs) -> int:
    """What a kernel's outputs that are numbers cost (a fraction or a negative: one).

    Counted once per distinct number: a team's Hessian is 65 thousand entries at 128
    agents, almost all zero, and counting each as an expression took a second.
    """
    # Keyed with the class too: a float and a rational may compare equal, not cost so.
    costs: dict[tuple[type, sx.Expr], int] = {}
    total = 0
    for e in _flat(outputs):
        if isinstance(e, sx.Number):
            key = (type(e), e)
            cost = costs.get(key)
            if cost is None:
                cost = costs[key] = operation_count([e])
            total += cost
    return total


def _scatter(outputs: Outputs, where: Sequence[int], reduced: Sequence[sx.Expr]) -> list[sx.Expr]:
    """The outputs, flat, with the reduced expressions put back at ``where``."""
    flat = _flat(outputs)
    for i, expr in zip(where, reduced, strict=True):
        flat[i] = expr
    return flat


def make_kernel(
    name: str,
    doc: str,
    inputs: Sequence[Arg],
    assignments: Sequence[Assignment],
    outputs: Outputs,
    subs: Mapping[sx.Expr, sx.Expr],
    odd: dict[sx.Expr, sx.Expr] | None = None,
    search: bool = True,
    symbols: dict[sx.Expr, set[sx.Expr]] | None = None,
) -> Kernel:
    """Substitute slot symbols, CSE, and package a kernel.

    ``odd`` is the :func:`canonical_odd` memo shared by one controller's kernels, and
    ``symbols`` the memo of free symbols (:func:`_prune`): the kernels read the same
    programs. ``search=False`` skips the engine's search for common sub-sums
    (:func:`ordered_cse`).
    """
    exprs, where = _symbolic(outputs)
    program, flat = _prepare(assignments, exprs, subs, odd, symbols)
    if sx.SYMENGINE:
        dag = Dag()
        ids = dag.read(program)
        outs = [dag.intern(_expr(e)) for e in flat]
        ids, outs = dag.signed_odd(ids, outs, {} if odd is None else odd)
        ids = needed(dag, ids, outs)
        before = dag.operations([v for _, v in ids] + outs)
        order, outs = factored(dag, *_reduce_dag(dag, ids, outs, search, pruned=True))
        body, reduced = _number_dag(dag, order, outs)
        ops = dag.operations([v for _, v in order] + outs) + _constant_ops(outputs)
        reads = symbols_read(dag, order, outs)
        flat = _scatter(outputs, where, reduced)
        return _package(name, doc, inputs, outputs, body, flat, before, ops, reads)
    before = operation_count([v for _, v in program] + flat)
    body, reduced = ordered_cse(program, flat, search)
    return _package(name, doc, inputs, outputs, body, _scatter(outputs, where, reduced), before)


def make_kernels(
    kernels: Sequence[tuple[str, str, Sequence[Arg], Outputs]],
    assignments: Sequence[Assignment],
    subs: Mapping[sx.Expr, sx.Expr],
    odd: dict[sx.Expr, sx.Expr] | None = None,
    symbols: dict[sx.Expr, set[sx.Expr]] | None = None,
    riders: Sequence[Rider] = (),
    companions: Sequence[tuple[str, str, Sequence[Arg], Outputs]] = (),
) -> list[Kernel]:
    """Kernels (name, doc, inputs, outputs) over one program, lowered together when large.

    ``odd`` and ``symbols`` are memos one controller's kernels share (:func:`make_kernel`).

    ``riders`` are kernels cut from the same program whose outputs the program's
    arguments compute under other names (:data:`Rider`: f0's gradient and Hessian at
    outputs that are states, from the jet's program of the state): they ride the
    kernels' union, their inputs renamed last, and follow them in the result, when
    both the kernels and the riders with their ``companions`` (the kernels lowered
    apart with them, here f0's: counted, never made) would be lowered as a union
    (:func:`_lowered_together`). Otherwise they are left out of the result, to be
    lowered apart with their companions, and change nothing.

    The jet kernel and the optimality error read the same gradient jet; lowered apart,
    each substitutes, numbers and inlines it anew (a third of lowering's time on a ring
    of 64 agents, half of it for a k = 12 chain). When every kernel is large enough
    for value numbering alone (:data:`SMALL_PROGRAM_OPS`), the program and all outputs
    are reduced once, and each kernel keeps what its outputs need, inlining what is
    then used once. Smaller kernels are made one by one, as :func:`make_kernel` would:
    the engine's fuller search suits them, and a union could pass its size limit.
    """
    primary = (len(kernels), len(riders))
    kernels = [*kernels, *(rider[:4] for rider in riders), *companions]
    renames: list[Mapping[sx.Expr, sx.Expr] | None] = [None] * len(kernels)
    renames[primary[0] : sum(primary)] = [rider[4] for rider in riders]
    symbolic = [_symbolic(outputs) for *_, outputs in kernels]
    sizes = [len(exprs) for exprs, _ in symbolic]
    # The kernels cut from one program share its nodes: each is walked once.
    symbols = {} if symbols is None else symbols
    program, flat = _prepare(
        assignments, [e for exprs, _ in symbolic for e in exprs], subs, odd, symbols
    )
    ends = list(itertools.accumulate(sizes))
    wheres = [where for _, where in symbolic]
    if sx.SYMENGINE:
        return _make_kernels_dag(kernels, program, flat, sizes, ends, wheres, odd, renames, primary)
    parts = [flat[end - size : end] for size, end in zip(sizes, ends, strict=True)]
    counts: dict[sx.Expr, int] = {}
    programs = [_prune(program, part, symbols) for part in parts]
    befores = [
        operation_count([v for _, v in mine] + part, counts)
        for mine, part in zip(programs, parts, strict=True)
    ]
    union, count = _lowered_together(befores, primary)
    kernels, befores = kernels[:count], befores[:count]
    made = []
    if not union:
        for (name, doc, inputs, outputs), mine, part, where, before in zip(
            kernels, programs[:count], parts[:count], wheres[:count], befores, strict=True
        ):
            body, reduced = ordered_cse(mine, part)
            made.append(
                _package(
                    name, doc, inputs, outputs, body, _scatter(outputs, where, reduced), before
                )
            )
        return made
    order, outs = _reduce(program, flat[: ends[count - 1]], search=False, symbols=symbols)
    for (name, doc, inputs, outputs), size, end, where, before, rename in zip(
        kernels, sizes[:count], ends[:count], wheres[:count], befores, renames[:count], strict=True
    ):
        mine = outs[end - size : end]
        body, reduced = _number(*_inline_single_use(_prune(order, mine, symbols), mine), rename)
        made.append(
            _package(name, doc, inputs, outputs, body, _scatter(outputs, where, reduced), before)
        )
    return made


def _lowered_together(befores: Sequence[int], primary: tuple[int, int]) -> tuple[bool, int]:
    """Whether :func:`make_kernels`' kernels are lowered as one union, and how many are made.

    ``befores`` are the operation counts before CSE of the kernels, then of the riders
    and their companions; ``primary`` the numbers of kernels and riders. The riders
    ride a union only, and only when lowered apart with their companions they would be
    a union too: a kernel small enough for the engine's search gets it as it would
    apart (f0's gradient at 24 agents: 608 operations so, 921 cut from the jet's union).
    """
    kernels, riders = primary
    union = kernels >= 2 and min(befores[:kernels]) > SMALL_PROGRAM_OPS
    group = befores[kernels:]
    ride = union and riders > 0 and len(group) >= 2 and min(group) > SMALL_PROGRAM_OPS
    return union, kernels + riders if ride else kernels


def _make_kernels_dag(
    kernels: Sequence[tuple[str, str, Sequence[Arg], Outputs]],
    program: Sequence[Assignment],
    flat: Sequence[sx.Expr],
    sizes: Sequence[int],
    ends: Sequence[int],
    wheres: Sequence[Sequence[int]],
    odd: dict[sx.Expr, sx.Expr] | None,
    renames: Sequence[Mapping[sx.Expr, sx.Expr] | None],
    primary: tuple[int, int],
) -> list[Kernel]:
    """:func:`make_kernels` on SymEngine, its program read once into a :class:`.Dag`.

    The same steps, on the DAG's integer ids; expressions are built for what the
    kernels hold, and where inlining collects terms. ``odd`` is :func:`make_kernel`'s;
    ``primary`` the numbers of kernels and riders (their inputs renamed by
    ``renames``), companions after them.
    """
    dag = Dag()
    ids = dag.read(program)
    outs = [dag.intern(_expr(e)) for e in flat]
    ids, outs = dag.signed_odd(ids, outs, {} if odd is None else odd)
    parts = [outs[end - size : end] for size, end in zip(sizes, ends, strict=True)]
    programs = [needed(dag, ids, part) for part in parts]
    befores = [
        dag.operations([v for _, v in mine] + part)
        for mine, part in zip(programs, parts, strict=True)
    ]
    union, count = _lowered_together(befores, primary)
    kernels, programs, befores = kernels[:count], programs[:count], befores[:count]
    made = []
    if not union:
        for kernel, mine, part, where, before in zip(
            kernels, programs, parts[:count], wheres[:count], befores, strict=True
        ):
            order, reduced_ids = _reduce_dag(dag, mine, part, True, pruned=True)
            made.append(_dag_kernel(dag, order, reduced_ids, kernel, where, before))
        return made
    # What all outputs need is what one of the kernels needs: the program filtered,
    # where a walk of its DAG again was the largest of the walks.
    wanted = {sym for mine in programs for sym, _ in mine}
    union_program = [(sym, value) for sym, value in ids if sym in wanted]
    whole, whole_outs = _reduce_dag(dag, union_program, outs[: ends[count - 1]], False, pruned=True)
    for kernel, size, end, where, before, rename in zip(
        kernels, sizes[:count], ends[:count], wheres[:count], befores, renames[:count], strict=True
    ):
        mine_outs = whole_outs[end - size : end]
        order, reduced_ids = inline_single_use(dag, needed(dag, whole, mine_outs), mine_outs)
        made.append(_dag_kernel(dag, order, reduced_ids, kernel, where, before, rename))
    return made


def _dag_kernel(
    dag: Dag,
    order: Any,
    reduced_ids: list[int],
    kernel: tuple[str, str, Any, Any],
    where: Sequence[int],
    before: int,
    rename: Mapping[sx.Expr, sx.Expr] | None = None,
) -> Kernel:
    """A kernel from its program on the DAG: numbered, counted and packaged.

    ``rename`` renames its inputs (a rider's: :func:`make_kernels`).
    """
    name, doc, inputs, outputs = kernel
    order, reduced_ids = factored(dag, order, reduced_ids)
    body, reduced = _number_dag(dag, order, reduced_ids, rename)
    ops = dag.operations([v for _, v in order] + reduced_ids) + _constant_ops(outputs)
    reads = symbols_read(dag, order, reduced_ids)
    if rename:
        reads = {rename.get(sym, sym) for sym in reads}
    flat = _scatter(outputs, where, reduced)
    return _package(name, doc, inputs, outputs, body, flat, before, ops, reads)


def _kept(node: sx.Expr, args: Sequence[sx.Expr]) -> sx.Expr:
    """:func:`~.rewrite._rebuild`, a number times a sum kept whole on SymEngine.

    The kernel's last pass wrote sums of terms with one coefficient as ``c*(...)``
    (:func:`~.coefficients.factored`); hoisting a sum's invariant terms must not distribute the
    ``c`` again. SymPy's constructor distributes it itself.
    """
    if sx.SYMENGINE and node.is_Mul:
        return sx.Mul(*args)
    return _rebuild(node, args)


#: Inputs that are the same for every state of a batch (one time, one parameter vector).
_INVARIANT_INPUTS = ("t", "p", "a")


def split_invariant(kernel: Kernel, name: str, doc: str) -> tuple[Kernel, Kernel] | None:
    """Split off the part of ``kernel`` that depends on time and parameters alone.

    A batch of states at one time shares everything that does not involve the state:
    the signals and their derivatives, a switch such as ``tanh((t - a)/b)``, sums of
    such terms inside a state-dependent expression. Those become a kernel of
    :data:`_INVARIANT_INPUTS` that returns them as one array ``tau``; the remaining
    kernel reads ``tau`` as an input. Temporaries keep their names; a hoisted sub-sum or
    sub-product of a larger expression gets a name ``_h0, _h1, ...``.

    Returns
    -------
    (Kernel, Kernel) or None
        The invariant kernel ``name`` and the rest (``kernel``'s name, inputs plus
        ``tau``), or None when nothing would be shared.
    """
    invariant_args = [arg for arg in kernel.inputs if arg.name in _INVARIANT_INPUTS]
    given: set[sx.Expr] = {sym for arg in invariant_args for sym in arg.symbols}
    given.add(sx.symbol("t"))
    invariant = set(given)
    time_body: list[Assignment] = []
    for sym, value in kernel.body:
        if value.free_symbols <= invariant:
            invariant.add(sym)
            time_body.append((sym, value))
    if not time_body:
        return None
    names = numbered("_h")
    shared: dict[sx.Expr, sx.Expr] = {}  # invariant value -> the state part's name for it
    memo: dict[sx.Expr, sx.Expr] = {}

    known: dict[sx.Expr, bool] = {}

    def fixed(node: sx.Expr) -> bool:
        # Bottom-up and memoized: sympy's free_symbols walks the whole subtree on every
        # call, which made hoisting quadratic in an expression's depth. Leaves too: a
        # look-up costs less than SymEngine's .args, made anew at each call.
        found = known.get(node)
        if found is None:
            args = node.args
            if args:
                found = all(fixed(arg) for arg in args)
            else:
                found = not node.is_Symbol or node in invariant
            known[node] = found
        return found

    def share(node: sx.Expr) -> sx.Expr:
        # Numbers and the inputs themselves are at hand in the state part already.
        if node.is_Number or node in given:
            return node
        if node not in shared:
            shared[node] = node if node in invariant else next(names)
        return shared[node]

    same = _same()

    def hoist(node: sx.Expr) -> sx.Expr:
        if node.is_Atom:
            return share(node) if node.is_Symbol and node in invariant else node
        done = memo.get(node)
        if done is not None:
            return done
        own = node.args
        flags = [fixed(a) for a in own]
        if all(flags):
            new = share(node)
        elif (node.is_Add or node.is_Mul) and any(
            f and not a.is_Number for a, f in zip(own, flags, strict=True)
        ):
            # (x + t + 1) -> x + _h0: the invariant terms or factors become one.
            part = [a for a, f in zip(own, flags, strict=True) if f]
            rest = [hoist(a) for a, f in zip(own, flags, strict=True) if not f]
            new = _kept(node, [*rest, share(_rebuild(node, part))])
        else:
            args = [hoist(a) for a in own]
            # Nothing hoisted below: the node as it is (rebuilding would give it back).
            new = node if _unchanged(same, own, args) else _kept(node, args)
        memo[node] = new
        return new

    state_body = tuple((sym, hoist(value)) for sym, value in kernel.body if sym not in invariant)
    state_outputs = tuple(
        Output(out.name, out.shape, tuple(hoist(_expr(e)) for e in out.exprs), out.doc)
        for out in kernel.outputs
    )
    release(hoist)
    release(fixed)
    tau_values = list(shared)
    time_program = _prune(time_body, tau_values)
    tau = Output("tau", (len(tau_values),), tuple(tau_values), "terms of time and parameters")
    time_ops = operation_count([v for _, v in time_program] + tau_values)
    time_kernel = Kernel(
        name, doc, tuple(invariant_args), tuple(time_program), (tau,), time_ops, time_ops
    )
    arg_tau = Arg(
        "tau",
        tuple(shared.values()),
        tuple(f"{name} tau[{i}]" for i in range(len(shared))),
        f"terms of time and parameters alone ({name})",
    )
    state_ops = operation_count(
        [v for _, v in state_body] + [e for o in state_outputs for e in o.exprs]
    )
    state_kernel = Kernel(
        kernel.name,
        kernel.doc,
        (*kernel.inputs, arg_tau),
        state_body,
        state_outputs,
        state_ops,
        kernel.ops_before_cse - time_ops,
    )
    return time_kernel, state_kernel
