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
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass

import sympy as sp

from tvopt_codegen.derivation import Derivation
from tvopt_codegen.jet import Assignment, fresh_symbols
from tvopt_codegen.law import symbols


@dataclass(frozen=True)
class Arg:
    """One array input of a kernel.

    Attributes
    ----------
    name : str
        The argument's name in generated code (``t``, ``s``, ``p``, ...).
    symbols : tuple of sympy.Symbol
        The slot symbols, one per element, in order (empty for the scalar ``t``).
    labels : tuple of str
        The user's name for each slot (for comments).
    doc : str
        What the argument is.
    """

    name: str
    symbols: tuple[sp.Symbol, ...]
    labels: tuple[str, ...]
    doc: str


@dataclass(frozen=True)
class Output:
    """One output array of a kernel: ``shape`` and the row-major element expressions."""

    name: str
    shape: tuple[int, ...]
    exprs: tuple[sp.Expr, ...]
    doc: str


@dataclass(frozen=True)
class Kernel:
    """A named straight-line program over array inputs.

    Attributes
    ----------
    name : str
        Function name in generated code.
    doc : str
        One-line description.
    inputs : tuple of Arg
        Inputs in call order.
    body : tuple of (sympy.Symbol, sympy.Expr)
        Temporaries ``_t0, _t1, ...`` in evaluation order.
    outputs : tuple of Output
        Outputs in return order.
    ops : int
        Operation count of the body and outputs (after CSE).
    ops_before_cse : int
        Operation count of the same program before CSE.
    """

    name: str
    doc: str
    inputs: tuple[Arg, ...]
    body: tuple[Assignment, ...]
    outputs: tuple[Output, ...]
    ops: int
    ops_before_cse: int


@dataclass(frozen=True)
class KernelSet:
    """All kernels of one controller, with the derivation they came from.

    Attributes
    ----------
    derivation : Derivation
        The derived law.
    kernels : tuple of Kernel
        The kernels, see :func:`lower`.
    r_blocks : tuple of tuple of int
        The diagonal blocks of R (output indices of each, in order). The ``R`` output
        of the ``jet`` kernel holds each block's entries row by row, block after block;
        a block-diagonal R (one block per agent) is solved block by block.
    lu_ops : int
        Operations of the LU solves of those blocks (with pivoting), counted like
        kernel operations.
    """

    derivation: Derivation
    kernels: tuple[Kernel, ...]
    r_blocks: tuple[tuple[int, ...], ...] = ()
    lu_ops: int = 0

    def __getitem__(self, name: str) -> Kernel:
        for kernel in self.kernels:
            if kernel.name == name:
                return kernel
        raise KeyError(name)


_slots = symbols


def operation_count(exprs: Iterable[sp.Expr]) -> int:
    """Count the arithmetic operations and function calls that printing ``exprs`` costs.

    A sum or product of ``n`` terms is ``n - 1`` operations (a factor ``-1`` is the
    negation, or nothing in a sum, where it makes the subtraction; a factor ``b**-1`` is
    the division), every other power and every function call one, a negative or
    fractional literal one. Expressions are counted as trees, like sympy's
    ``count_ops``, but in one memoized pass: linear in the size of the DAG, where
    ``count_ops`` walks each expression anew.
    """
    memo: dict[tuple[sp.Basic, str], int] = {}

    def own(node: sp.Basic, parent: str) -> int:
        if node.is_Number:
            if parent == "mul":
                return 0
            return int(node.is_negative is True) + int(node.is_Rational and not node.is_Integer)
        if node.is_Atom:
            return 0
        if node.is_Add:
            return len(node.args) - 1
        if node.is_Mul:
            negated = parent == "add" and node.args[0].is_Number and node.args[0].is_negative
            return len(node.args) - 1 - int(bool(negated) and node.args[0] == -1)
        if node.is_Pow and node.exp == -1:
            return 0 if parent == "mul" else 1
        return 1

    def count(node: sp.Basic, parent: str = "") -> int:
        key = (node, parent)
        if key not in memo:
            kind = "mul" if node.is_Mul else "add" if node.is_Add else ""
            memo[key] = own(node, parent) + sum(count(arg, kind) for arg in node.args)
        return memo[key]

    return sum(count(sp.sympify(e)) for e in exprs)


def _rebuild(node: sp.Basic, args: Sequence[sp.Basic]) -> sp.Basic:
    """``node.func(*args)``, without re-running a function's ``eval`` on symbolic args.

    Rebuilding ``tan(pi*g/(2*d))`` after a substitution makes sympy look for multiples
    of pi in the argument again, with assumption queries: four milliseconds a node, two
    seconds for a ring of 32 agents. Substituting symbols for symbols, or a temporary
    for its value, never gives ``eval`` anything new to simplify; numbers still
    evaluate (``sin(0)`` is 0).
    """
    if isinstance(node, sp.Function) and not all(a.is_Number for a in args):
        return node.func(*args, evaluate=False)
    return node.func(*args)


def _substitute(
    expr: sp.Basic,
    mapping: Mapping[sp.Basic, sp.Basic],
    memo: dict[sp.Basic, sp.Basic] | None = None,
) -> sp.Basic:
    """``expr.xreplace(mapping)`` with :func:`_rebuild`; ``memo`` may span many calls."""
    table: dict[sp.Basic, sp.Basic] = {} if memo is None else memo

    def visit(node: sp.Basic) -> sp.Basic:
        if node in mapping:
            return mapping[node]
        if not node.args:
            return node
        if node in table:
            return table[node]
        args = [visit(arg) for arg in node.args]
        same = all(a is b for a, b in zip(args, node.args, strict=True))
        new = node if same else _rebuild(node, args)
        table[node] = new
        return new

    return visit(sp.sympify(expr))


def _negated_atom(value: sp.Basic) -> bool:
    """Whether ``value`` is ``-x`` for a symbol or constant ``x`` (printing it costs nothing)."""
    return bool(
        value.is_Mul and len(value.args) == 2 and value.args[0] == -1 and value.args[1].is_Atom
    )


def _drop_aliases(
    assignments: Sequence[Assignment], outputs: Sequence[sp.Expr]
) -> tuple[list[Assignment], list[sp.Expr]]:
    """Substitute assignments whose value is a bare symbol or constant, or its negation."""
    alias: dict[sp.Symbol, sp.Expr] = {}
    kept: list[Assignment] = []
    for sym, raw in assignments:
        value = _substitute(raw, alias)
        if value.is_Atom or _negated_atom(value):
            alias[sym] = value
        else:
            kept.append((sym, value))
    return kept, [_substitute(e, alias) for e in outputs]


def _prune(assignments: Sequence[Assignment], outputs: Sequence[sp.Expr]) -> list[Assignment]:
    """Drop assignments that no output needs (signal orders a kernel does not use)."""
    needed: set[sp.Symbol] = set()
    for e in outputs:
        needed |= sp.sympify(e).free_symbols
    kept: list[Assignment] = []
    for sym, value in reversed(assignments):
        if sym in needed:
            kept.append((sym, value))
            needed |= sp.sympify(value).free_symbols
    return kept[::-1]


#: Programs up to this many operations get sympy's full cse; larger ones value numbering.
SMALL_PROGRAM_OPS = 1000


def ordered_cse(
    assignments: Sequence[Assignment], outputs: Sequence[sp.Expr], search: bool = True
) -> tuple[tuple[Assignment, ...], tuple[sp.Expr, ...]]:
    """CSE a straight-line program and its outputs, keeping evaluation order valid.

    One ``sympy.cse`` pass sees every right-hand side and output. A common
    subexpression found in an assignment only uses symbols defined before it, so each
    extracted temporary is emitted just before its first use. Temporaries are then
    renamed ``_t0, _t1, ...`` in emission order, which makes the text deterministic.

    Parameters
    ----------
    assignments : sequence of (sympy.Symbol, sympy.Expr)
        The program; right-hand sides use only earlier symbols and the inputs.
    outputs : sequence of sympy.Expr
        Output expressions over the program and the inputs.
    search : bool
        Allow sympy's ``cse`` (on programs up to :data:`SMALL_PROGRAM_OPS`), which also
        finds common parts of sums and products. A program built one operation per
        assignment (the Cholesky solve) has none to find: value numbering suffices.

    Returns
    -------
    body : tuple of (sympy.Symbol, sympy.Expr)
        The temporaries in evaluation order.
    outputs : tuple of sympy.Expr
        The reduced outputs.
    """
    kept, outs = _drop_aliases(_prune(assignments, outputs), outputs)
    exprs = [value for _, value in kept] + outs
    names = sp.numbered_symbols("_cse", real=True)
    if search and operation_count(exprs) <= SMALL_PROGRAM_OPS:
        # sympy's cse also finds common parts of sums and products (a*b in a*b*c and
        # a*b*d): worth its superlinear time on the programs of a few agents only.
        replacements, reduced = sp.cse(exprs, symbols=names, order="canonical")
    else:
        replacements, reduced = _value_numbering(exprs, names)
    defined = dict(replacements)
    order: list[Assignment] = []
    emitted: set[sp.Symbol] = set()

    def need(expr: sp.Expr) -> None:
        for sym in sorted(expr.free_symbols & defined.keys() - emitted, key=_cse_index):
            need(defined[sym])
            if sym not in emitted:
                emitted.add(sym)
                order.append((sym, defined[sym]))

    for (sym, _), value in zip(kept, reduced[: len(kept)], strict=True):
        need(value)
        order.append((sym, value))
    for value in reduced[len(kept) :]:
        need(value)
    # CSE can leave an assignment that is just a temporary (the program computed a
    # value CSE found elsewhere first): substitute those too.
    order, outs = _drop_aliases(order, list(reduced[len(kept) :]))
    # Merging equal values can leave a temporary with one use, and inlining can make
    # two values equal: alternate to a fixed point (two or three rounds in practice).
    while True:
        size = len(order)
        order, outs = _merge_equal(order, outs)
        order, outs = _inline_single_use(order, outs)
        if len(order) == size:
            break
    renames: dict[sp.Symbol, sp.Expr] = {}
    body: list[Assignment] = []
    for index, (sym, value) in enumerate(order):
        new = sp.Symbol(f"_t{index}", real=True)
        body.append((new, _substitute(value, renames)))
        renames[sym] = new
    return tuple(body), tuple(_substitute(e, renames) for e in outs)


def _value_numbering(
    exprs: Sequence[sp.Expr], names: Iterable[sp.Symbol]
) -> tuple[list[Assignment], list[sp.Expr]]:
    """Common subexpression elimination by value numbering, linear in the DAG size.

    Every compound subexpression that occurs more than once becomes a temporary. This
    is the tree pass of ``sympy.cse`` without its search for common subsets of sums
    and products, which is quadratic in their number of terms and took minutes on a
    ring of three agents (issue 7). The jet arrives in three-address form, where
    such subsets are already separate assignments, so little is lost.
    """
    names = iter(names)
    seen: set[sp.Basic] = set()
    repeated: set[sp.Basic] = set()

    def worth(node: sp.Basic) -> bool:
        # A negated symbol or number is not worth a temporary: printing it is free.
        return not (node.is_Atom or _negated_atom(node))

    def find(node: sp.Basic) -> None:
        stack = [node]
        while stack:
            current = stack.pop()
            if not worth(current):
                continue
            if current in seen:
                repeated.add(current)
                continue
            seen.add(current)
            stack.extend(current.args)

    for expr in exprs:
        find(expr)
    replacements: list[Assignment] = []
    built: dict[sp.Basic, sp.Expr] = {}

    def build(node: sp.Basic) -> sp.Expr:
        if node.is_Atom:
            return node
        if node in built:
            return built[node]
        args = [build(arg) for arg in node.args]
        same = all(a is b for a, b in zip(args, node.args, strict=True))
        new = node if same else _rebuild(node, args)
        if node in repeated:
            sym = next(names)
            replacements.append((sym, new))
            new = sym
        built[node] = new
        return new

    reduced = [build(sp.sympify(e)) for e in exprs]
    return replacements, reduced


def _merge_equal(
    order: list[Assignment], outputs: list[sp.Expr]
) -> tuple[list[Assignment], list[sp.Expr]]:
    """Merge temporaries that compute the same value as an earlier one, or its negation.

    CSE compares expressions, not values, before its own replacements: two products
    that only become equal once their factors are named stay apart (``a**2 + 1`` twice
    after ``a = tan(...)`` was extracted). And a pairwise term such as a barrier between
    agents a and b differentiates into ``xa - xb`` for one and ``xb - xa`` for the other.
    One pass in evaluation order catches both, each match turning the next ones up.
    """
    first: dict[sp.Basic, sp.Symbol] = {}
    rename: dict[sp.Symbol, sp.Expr] = {}
    # A node is rewritten once: a renamed symbol is only used after its assignment,
    # so no node seen before a rename can contain it.
    memo: dict[sp.Basic, sp.Basic] = {}
    kept: list[Assignment] = []
    for sym, raw in order:
        value = _substitute(raw, rename, memo)
        if value in first:
            rename[sym] = first[value]
            continue
        # Negating a long sum builds a new one term by term; exact opposites are short
        # differences (xa - xb) and products, so longer sums are not tried.
        if not (value.is_Add and len(value.args) > _NEGATED_TERMS):
            negated = -value
            if negated in first:
                rename[sym] = -first[negated]
                continue
        first[value] = sym
        kept.append((sym, value))
    return kept, [_substitute(e, rename, memo) for e in outputs]


#: Sums up to this many terms are looked up negated too (:func:`_merge_equal`).
_NEGATED_TERMS = 4


def _inline_single_use(
    order: list[Assignment], outputs: list[sp.Expr]
) -> tuple[list[Assignment], list[sp.Expr]]:
    """Substitute temporaries used exactly once back into their one user.

    The jet is derived in three-address form (one operation per assignment), which
    makes differentiation linear; printed that way, every operation would become a
    named array in NumPy. Shared work stays in temporaries; the rest reads as the
    expression it is.
    """
    uses: dict[sp.Symbol, int] = {}
    for expr in [value for _, value in order] + outputs:
        # Occurrences, not containing expressions: x*x uses x twice (inlining it would
        # compute it twice).
        for node in sp.preorder_traversal(expr):
            if node.is_Symbol:
                uses[node] = uses.get(node, 0) + 1
    inline: dict[sp.Symbol, sp.Expr] = {}
    kept: list[Assignment] = []
    for sym, raw in order:
        value = _substitute(raw, inline)
        if uses.get(sym, 0) == 1:
            inline[sym] = value
        else:
            kept.append((sym, value))
    return kept, [_substitute(e, inline) for e in outputs]


def _cse_index(sym: sp.Symbol) -> int:
    return int(sym.name[len("_cse") :])


#: Odd functions: f(-x) = -f(x).
_ODD = (sp.sin, sp.tan, sp.sinh, sp.tanh, sp.asin, sp.atan, sp.asinh, sp.atanh)


def canonical_odd(expr: sp.Expr, memo: dict[sp.Basic, sp.Expr] | None = None) -> sp.Expr:
    """Write every odd function with the sign of its argument pulled out.

    sympy keeps ``tanh((a - t)/b)`` and ``tanh((t - a)/b)`` apart (neither argument
    "extracts" a minus sign, so neither is rewritten), and CSE then evaluates both. Of
    such a pair the argument with the smaller canonical sort key is kept; sympy leaves
    it alone on re-evaluation because it does not extract a sign either.

    ``memo`` (node -> rewritten node) may be shared between calls: the kernels of one
    controller repeat the same trigonometry, and each node is then decided once.
    """

    def negate(arg: sp.Expr) -> sp.Expr:
        # Distribute the sign into a sum factor: -(a - t)/b becomes (t - a)/b.
        if arg.is_Mul:
            for i, factor in enumerate(arg.args):
                if factor.is_Add:
                    return sp.Mul(*arg.args[:i], -factor, *arg.args[i + 1 :])
        return -arg

    def flips(e: sp.Expr) -> bool:
        arg = e.args[0]
        other = negate(arg)
        if other.could_extract_minus_sign():
            return False
        return bool(sp.default_sort_key(sp.expand(other)) < sp.default_sort_key(sp.expand(arg)))

    table: dict[sp.Basic, sp.Expr] = {} if memo is None else memo

    def rewrite(node: sp.Basic) -> sp.Expr:
        if node.is_Atom:
            return node
        if node in table:
            return table[node]
        args = [rewrite(arg) for arg in node.args]
        new = (
            node
            if all(a is b for a, b in zip(args, node.args, strict=True))
            else _rebuild(node, args)
        )
        if isinstance(new, _ODD) and flips(new):
            # Not re-evaluated: eval would find nothing the original's did not.
            new = -new.func(negate(new.args[0]), evaluate=False)
        table[node] = new
        return new

    expr = sp.sympify(expr)
    if not expr.atoms(*_ODD):
        return expr
    return rewrite(expr)


def _kernel(
    name: str,
    doc: str,
    inputs: Sequence[Arg],
    assignments: Sequence[Assignment],
    outputs: Sequence[tuple[str, tuple[int, ...], Sequence[sp.Expr], str]],
    subs: Mapping[sp.Symbol, sp.Expr],
    odd: dict[sp.Basic, sp.Expr] | None = None,
    search: bool = True,
) -> Kernel:
    """Substitute slot symbols, CSE, and package a kernel.

    ``odd`` is the :func:`canonical_odd` memo shared by one controller's kernels;
    ``search=False`` skips sympy's search for common sub-sums (:func:`ordered_cse`).
    """
    # Only what the outputs need: the gradient kernel, say, reads the jet's first part.
    assignments = _prune(assignments, [e for _, _, exprs, _ in outputs for e in exprs])
    slots: dict[sp.Basic, sp.Basic] = {}
    program = [
        (sym, canonical_odd(_substitute(value, subs, slots), odd)) for sym, value in assignments
    ]
    flat = [
        canonical_odd(_substitute(e, subs, slots), odd) for _, _, exprs, _ in outputs for e in exprs
    ]
    before = operation_count([v for _, v in program] + flat)
    body, reduced = ordered_cse(program, flat, search)
    packed: list[Output] = []
    start = 0
    for out_name, shape, exprs, out_doc in outputs:
        packed.append(Output(out_name, shape, reduced[start : start + len(exprs)], out_doc))
        start += len(exprs)
    allowed = {s for arg in inputs for s in arg.symbols} | {sym for sym, _ in body}
    allowed.add(sp.Symbol("t", real=True))
    for expr in [v for _, v in body] + list(reduced):
        stray = expr.free_symbols - allowed
        if stray:
            raise AssertionError(f"kernel {name}: unbound symbols {sorted(map(str, stray))}")
    return Kernel(
        name,
        doc,
        tuple(inputs),
        body,
        tuple(packed),
        operation_count([v for _, v in body] + list(reduced)),
        before,
    )


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
    given: set[sp.Basic] = {sym for arg in invariant_args for sym in arg.symbols}
    given.add(sp.Symbol("t", real=True))
    invariant = set(given)
    time_body: list[Assignment] = []
    for sym, value in kernel.body:
        if value.free_symbols <= invariant:
            invariant.add(sym)
            time_body.append((sym, value))
    if not time_body:
        return None
    names = fresh_symbols("_h")
    shared: dict[sp.Expr, sp.Symbol] = {}  # invariant value -> the state part's name for it
    memo: dict[sp.Basic, sp.Expr] = {}

    def fixed(node: sp.Basic) -> bool:
        return bool(node.free_symbols <= invariant)

    def share(node: sp.Expr) -> sp.Expr:
        # Numbers and the inputs themselves are at hand in the state part already.
        if node.is_Number or node in given:
            return node
        if node not in shared:
            shared[node] = node if node in invariant else next(names)
        return shared[node]

    def hoist(node: sp.Basic) -> sp.Expr:
        if node.is_Atom:
            return share(node) if node.is_Symbol and node in invariant else node
        if node in memo:
            return memo[node]
        if fixed(node):
            new = share(node)
        elif node.is_Add or node.is_Mul:
            # (x + t + 1) -> x + _h0: the invariant terms or factors become one.
            part = [a for a in node.args if fixed(a)]
            rest = [hoist(a) for a in node.args if not fixed(a)]
            new = node.func(*rest, *([share(node.func(*part))] if part else []))
        else:
            new = _rebuild(node, [hoist(a) for a in node.args])
        memo[node] = new
        return new

    state_body = tuple((sym, hoist(value)) for sym, value in kernel.body if sym not in invariant)
    state_outputs = tuple(
        Output(out.name, out.shape, tuple(hoist(sp.sympify(e)) for e in out.exprs), out.doc)
        for out in kernel.outputs
    )
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


def lu_operations(size: int) -> int:
    """Operations of the generated LU solve with partial pivoting of one block."""
    factor = sum(1 + 2 * (size - j) + 2 for j in range(size) for _ in range(j + 1, size))
    return factor + sum(2 * (size - j - 1) + 1 for j in range(size))


def _fill(pattern: set[tuple[int, int]], order: Sequence[int]) -> list[list[int]]:
    """Column patterns of the Cholesky factor of a symmetric pattern in a given order.

    ``pattern`` holds the structurally nonzero ``(i, j)`` of the matrix; the result
    lists, for each column ``b`` of the permuted factor, the rows ``a > b`` that are
    nonzero in L (the matrix's own entries plus fill from elimination).
    """
    position = {index: a for a, index in enumerate(order)}
    below: list[set[int]] = [set() for _ in order]
    for i, j in pattern:
        a, b = position[i], position[j]
        if a > b:
            below[b].add(a)
    columns: list[list[int]] = []
    for b in range(len(order)):
        rows = sorted(below[b])
        columns.append(rows)
        # Eliminating b connects all its later neighbours: that is the fill.
        for x, first in enumerate(rows):
            for second in rows[x + 1 :]:
                below[first].add(second)
    return columns


def elimination_order(pattern: set[tuple[int, int]], m: int) -> tuple[int, ...]:
    """Order the Cholesky elimination: natural, or reverse Cuthill-McKee if it fills less."""
    from scipy.sparse import csr_matrix  # noqa: PLC0415 - only needed here
    from scipy.sparse.csgraph import reverse_cuthill_mckee  # noqa: PLC0415

    natural = tuple(range(m))
    if not pattern:
        return natural
    rows, cols = zip(*sorted(pattern), strict=True)
    graph = csr_matrix(([1] * len(rows), (rows, cols)), shape=(m, m))
    rcm = tuple(int(i) for i in reverse_cuthill_mckee(graph, symmetric_mode=True))

    def size(order: Sequence[int]) -> int:
        return sum(len(c) for c in _fill(pattern, order))

    return rcm if size(rcm) < size(natural) else natural


def cholesky_program(
    entries: Sequence[tuple[int, int]], m: int, h: Sequence[sp.Symbol], c: Sequence[sp.Symbol]
) -> tuple[list[Assignment], list[sp.Expr], list[sp.Expr]]:
    """A straight-line sparse, square-root-free Cholesky (LDL^T) solve of ``Hess z = c``.

    Parameters
    ----------
    entries : sequence of (int, int)
        The structurally nonzero ``(i, j)``, ``i >= j``, of the symmetric matrix, in the
        order of its input symbols ``h``.
    m : int
        The matrix size.
    h, c : sequence of sympy.Symbol
        Symbols of the entries and of the right-hand side.

    Returns
    -------
    assignments : list of (sympy.Symbol, sympy.Expr)
        The factorization and both triangular solves, one small expression each.
    z : list of sympy.Expr
        The solution, in the matrix's own order.
    pivots : list of sympy.Expr
        ``D_b = A_bb - sum_k L_bk^2 D_k`` of each elimination step, the squares of the
        pivots of the classical Cholesky factor: the matrix is positive definite (to the
        tolerance) when every one is positive, checked by the caller before the result
        is used.

    Notes
    -----
    ``Hess = L D L^T`` with unit lower-triangular ``L``: one reciprocal per pivot and no
    square root, where the classical factor needs ``1/sqrt`` per pivot (a ``pow`` call
    in C, several times the cost of a division). Only the entries of L that the pattern
    and its fill make nonzero are formed, in an elimination order chosen to fill little
    (:func:`elimination_order`): for a ring of agents that is linear in their number
    where a dense factorization is cubic.
    """
    pattern = {(i, j) for i, j in entries} | {(j, i) for i, j in entries}
    order = elimination_order(pattern, m)
    position = {index: a for a, index in enumerate(order)}
    value: dict[tuple[int, int], sp.Expr] = {}
    for symbol, (i, j) in zip(h, entries, strict=True):
        a, b = sorted((position[i], position[j]), reverse=True)
        value[(a, b)] = symbol
    columns = _fill(pattern, order)
    names = fresh_symbols("_chol")
    program: list[Assignment] = []

    def assign(expr: sp.Expr) -> sp.Expr:
        if expr.is_Atom:
            return expr
        symbol = next(names)
        program.append((symbol, expr))
        return symbol

    # scaled[(a, k)] = L[a, k] * D[k]: formed once, it turns every later dot product
    # into plain multiply-adds.
    unit: dict[tuple[int, int], sp.Expr] = {}
    scaled: dict[tuple[int, int], sp.Expr] = {}
    row_entries: list[list[int]] = [[] for _ in range(m)]  # columns k < a with L[a, k] != 0
    inverse: list[sp.Expr] = []
    pivots: list[sp.Expr] = []
    for b in range(m):
        pivot = assign(
            value.get((b, b), sp.Integer(0))
            - sp.Add(*(unit[(b, k)] * scaled[(b, k)] for k in row_entries[b]))
        )
        pivots.append(pivot)
        inverse.append(assign(1 / pivot))
        for a in columns[b]:
            shared = set(row_entries[a]) & set(row_entries[b])
            dot = sp.Add(*(unit[(a, k)] * scaled[(b, k)] for k in sorted(shared)))
            scaled[(a, b)] = assign(value.get((a, b), sp.Integer(0)) - dot)
            unit[(a, b)] = assign(scaled[(a, b)] * inverse[b])
            row_entries[a].append(b)
    forward: list[sp.Expr] = []
    for a in range(m):
        dot = sp.Add(*(unit[(a, k)] * forward[k] for k in row_entries[a]))
        forward.append(assign(c[order[a]] - dot))
    backward: dict[int, sp.Expr] = {}
    for a in reversed(range(m)):
        dot = sp.Add(*(unit[(k, a)] * backward[k] for k in columns[a]))
        backward[a] = assign(forward[a] * inverse[a] - dot)
    z = [backward[position[i]] for i in range(m)]
    return program, z, pivots


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
    kernel = functools.partial(_kernel, odd=odd)
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
