"""Total time derivatives of straight-line programs (forward-mode, symbolic).

The paper needs ``grad^(j) f0`` for ``j <= k``: total derivatives along the output jet
``(y, y', ..., y^(k-1))``, the signal jets and ``t`` (ARCHITECTURE.md, section 2). Taking
them on one nested expression multiplies its size by about ten per order. Here an
expression is a straight-line program (a list of assignments ``s_i = e_i`` whose
right-hand sides use earlier symbols), and ``D`` is applied assignment by assignment:
``D s_i = sum_v (d e_i / d v) D v``, each a new assignment. Sizes then grow by a small
constant factor per order and nothing is ever expanded.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass

from tvopt_codegen import symbolic as sx

Assignment = tuple[sx.Expr, sx.Expr]


@dataclass(frozen=True)
class Program:
    """Assignments in evaluation order; each right-hand side uses only earlier symbols.

    Attributes
    ----------
    assignments : tuple of (symbol, expression)
        The straight-line program.
    """

    assignments: tuple[Assignment, ...]

    def __add__(self, other: Program) -> Program:
        return Program(self.assignments + other.assignments)

    def inline(self, expr: sx.Expr) -> sx.Expr:
        """Substitute every assignment into ``expr`` (for tests and small reports only).

        Each assignment ``expr`` reads is inlined once, in program order, and reused
        wherever it is read: substituting the assignments one by one into the whole
        expression, last first, rebuilt it once per assignment (three fifths of a team's
        ``report``).
        """
        values = dict(self.assignments)
        memo: dict[sx.Expr, sx.Expr] = {}
        for sym in self._read_by(expr):
            value = values[sym]
            memo[sym] = value.xreplace({s: memo[s] for s in value.free_symbols if s in memo})
        return expr.xreplace({s: memo[s] for s in expr.free_symbols if s in memo})

    def inlined_size(self, expr: sx.Expr) -> int:
        """The node count of ``expr`` with every assignment inlined, without building it.

        A read counts the inlined size of what it reads each time, as the inlined tree
        would: a report asks this before inlining what it would only describe if large.
        """
        values = dict(self.assignments)
        sizes: dict[sx.Expr, int] = {}

        def size(e: sx.Expr) -> int:
            if e in sizes:
                return sizes[e]
            return 1 + sum(size(a) for a in e.args)

        for sym in self._read_by(expr):
            sizes[sym] = size(values[sym])
        total = size(expr)
        release(size)
        return total

    def _read_by(self, expr: sx.Expr) -> list[sx.Expr]:
        """The assigned symbols ``expr`` reads, directly or not, in program order."""
        values = dict(self.assignments)
        needed = {s for s in expr.free_symbols if s in values}
        pending = list(needed)
        while pending:
            for s in values[pending.pop()].free_symbols:
                if s in values and s not in needed:
                    needed.add(s)
                    pending.append(s)
        return [sym for sym, _ in self.assignments if sym in needed]


def release(walk: Callable[..., object]) -> None:
    """Free a recursive nested function now, with what it holds, not at a collection.

    A nested function that calls itself holds itself in a closure cell: a reference
    cycle, which only Python's cyclic collector frees, and which keeps the walk's memo
    (often the size of the program) alive until then. Called once the walk is done, this
    empties that cell, and reference counting frees the function and its memo at once:
    the command line can then run the derivation without the collector
    (``commands.common.without_collector``), whose scans of the live expressions were a tenth of a
    large team's run.
    """
    for cell in walk.__closure__ or ():
        if cell.cell_contents is walk:
            cell.cell_contents = None


def unchanged(node: sx.Expr, args: Sequence[sx.Expr]) -> bool:
    """Whether ``args`` are ``node``'s own arguments, in order.

    A walk that rebuilds a tree leaves such a node as it is: rebuilding it would run
    the engine's constructors only to give it back. On SymPy they must be the very
    objects; SymEngine hands out a new Python object for an argument at each ``.args``,
    so there equal arguments (a comparison in C++) count.
    """
    return _same(args, node.args)


def _same(args: Sequence[sx.Expr], own: Sequence[sx.Expr]) -> bool:
    """:func:`unchanged` on arguments read once: an atom a walk gives back is the object.

    ``own`` is the node's ``.args``, read by the caller already (on SymEngine each read
    builds new Python objects).
    """
    if len(args) != len(own):
        return False
    if sx.SYMENGINE:
        # A tuple comparison asks ``a is b or a == b`` of each pair, in C.
        return tuple(args) == tuple(own)
    return all(a is b for a, b in zip(args, own, strict=True))


def fresh_symbols(prefix: str) -> Iterator[sx.Expr]:
    """Endless numbered symbols ``prefix0, prefix1, ...`` (real)."""
    index = 0
    while True:
        yield sx.symbol(f"{prefix}{index}")
        index += 1


def partial(expr: sx.Expr, var: sx.Expr) -> sx.Expr:
    """``d expr / d var`` by the sum, product, power and chain rules, as sympy's ``diff``.

    The programs' right-hand sides are single operations, where sympy's ``diff`` spends
    most of its time in the machinery of ``Derivative`` objects. The rules here build
    the same sums and products (sympy's constructors put them in the same canonical
    form); anything else is left to ``diff``. SymEngine's own ``diff`` is exact and
    fast: it is used there (:func:`_symengine_partial`).
    """
    if sx.SYMENGINE:
        return _symengine_partial(expr, var)
    if expr == var:
        return sx.Integer(1)
    if var not in expr.free_symbols:
        return sx.Integer(0)
    if expr.is_Add:
        return sx.Add(*(partial(arg, var) for arg in expr.args if var in arg.free_symbols))
    if expr.is_Mul:
        # Each term one product of all factors, as sympy's Leibniz rule for a first
        # derivative builds it (Mul._eval_derivative_n_times): a number times a sum
        # distributes only there, and the form must be the same.
        # A product of two whose factor is the variable itself differentiates to the
        # other factor: Mul(1, b) is b, the very object, so it is not built.
        args = expr.args
        one = sx.ONE
        terms = []
        for i, arg in enumerate(args):
            if var in arg.free_symbols:
                slope = partial(arg, var)
                if slope is one and len(args) == 2:
                    terms.append(args[1 - i])
                else:
                    terms.append(sx.Mul(*args[:i], slope, *args[i + 1 :]))
        return sx.Add(*terms)
    if expr.is_Pow:
        base, exponent = expr.args
        if exponent.is_Number:
            # sympy's Pow._eval_derivative with a constant exponent, term for term.
            return expr * (partial(base, var) * exponent / base)
        return sx.diff(expr, var)
    if isinstance(expr, sx.Function) and len(expr.args) == 1 and _chain_rule(type(expr)):
        return expr.fdiff(1) * partial(expr.args[0], var)
    return sx.diff(expr, var)


def _chain_rule(func: type) -> bool:
    """Whether sympy differentiates ``func`` by the plain chain rule on its ``fdiff``.

    ``Abs`` has its own rule (through the conjugate), and ``sign`` no ``fdiff`` (sympy
    gives ``2*DiracDelta``, the default ``fdiff`` an unevaluated ``Derivative``): those
    are left to ``diff``.
    """
    base = sx.Function
    return bool(
        func._eval_derivative is base._eval_derivative  # type: ignore[attr-defined]
        and func.fdiff is not base.fdiff  # type: ignore[attr-defined]
    )


def _symengine_partial(expr: sx.Expr, var: sx.Expr) -> sx.Expr:
    """``d expr / d var`` on SymEngine: its ``diff``, with the rules it lacks.

    SymEngine leaves ``Abs`` and ``sign`` underived (a ``Derivative``; they reach it
    from SymPy, which writes ``sqrt(x**2)`` of a real ``x`` as ``Abs(x)``). Where the
    expression holds one, the chain rule is applied here down to it: ``Abs(u)' =
    sign(u) u'`` as SymPy's for a real ``u``, and ``sign(u)' = 0``, its value wherever it
    is defined, where SymPy writes ``2*DiracDelta(u) u'``, which no stage can evaluate.
    """
    if not _underived(expr):
        return expr.diff(var)
    if var not in expr.free_symbols:
        return sx.ZERO
    name = sx.function_name(expr) if expr.is_Function else ""
    if name == "Abs":
        (inner,) = expr.args
        return sx.sign(inner) * _symengine_partial(inner, var)
    if name == "sign":
        return sx.ZERO
    if sx.is_piecewise(expr):
        # Only the values move (the conditions' derivative is zero where defined).
        flat = [
            item
            for value, condition in sx.piecewise_pairs(expr)
            for item in (_symengine_partial(value, var), condition)
        ]
        return sx.Piecewise(*zip(flat[::2], flat[1::2], strict=True))
    # Any other node: the chain rule through its arguments, each slope SymEngine's own
    # derivative of the node in a placeholder for that argument.
    args = expr.args
    holders = [sx.Symbol(f"_partial_arg{i}") for i in range(len(args))]
    local = expr.func(*holders)
    back = dict(zip(holders, args, strict=True))
    terms = [
        local.diff(holder).xreplace(back) * _symengine_partial(arg, var)
        for holder, arg in zip(holders, args, strict=True)
        if var in arg.free_symbols
    ]
    return sx.Add(*terms)


#: The functions SymEngine does not differentiate (see :func:`_symengine_partial`).
_UNDERIVED = frozenset({"Abs", "sign"})


def _underived(expr: sx.Expr) -> bool:
    """Whether a SymEngine ``expr`` holds ``Abs`` or ``sign``.

    A program's right-hand side is one operation on atoms: its own class tells. Only a
    nested expression is searched (``atoms``, several times the cost of ``diff`` on
    one operation).
    """
    if type(expr).__name__ in _UNDERIVED:
        return True
    if all(arg.is_Atom for arg in expr.args):
        return False
    return bool(expr.atoms(sx.Abs, sx.sign))


def _times(slope: sx.Expr, rate: sx.Expr) -> sx.Expr:
    """``slope * rate``, without building a product by 1 (``Mul(1, b)`` is ``b`` itself)."""
    if _is_one(rate):
        return slope
    if _is_one(slope):
        return rate
    return slope * rate


def _is_one(expr: sx.Expr) -> bool:
    """Whether ``expr`` is the integer 1 (SymPy's singleton; SymEngine's by value)."""
    if sx.SYMENGINE:
        return bool(expr.is_Integer and expr == sx.ONE)
    return expr is sx.ONE


def _rebuild(node: sx.Expr, args: Sequence[sx.Expr]) -> sx.Expr:
    """``node``'s kind of node over ``args`` (a SymEngine ``Piecewise`` takes pairs)."""
    if sx.SYMENGINE and sx.is_piecewise(node):
        return sx.Piecewise(*zip(args[::2], args[1::2], strict=True))
    return node.func(*args)


def _derivative(expr: sx.Expr, rates: Mapping[sx.Expr, sx.Expr]) -> sx.Expr:
    """Chain rule: ``sum_v (d expr / d v) * rates[v]`` over the symbols that move.

    The terms are added in one sum, and a rate of 1 (time's) multiplies nothing: adding
    each term to a running total made every derivative pass through sympy's ``Add`` once
    more per term, ``0 + x`` included (a fifth of a k = 12 jet's derivation).
    On SymEngine, whose sums are in canonical order whatever the order of their
    terms, the symbols are not sorted, and ``diff`` is called directly where it
    suffices (:func:`_underived`).
    """
    if sx.SYMENGINE:
        moving = expr.free_symbols & rates.keys()
        if not _underived(expr):
            terms = [expr.diff(var) * rates[var] for var in moving]
        else:
            terms = [_symengine_partial(expr, var) * rates[var] for var in moving]
        return terms[0] if len(terms) == 1 else sx.Add(*terms)
    terms = []
    for var in sorted(expr.free_symbols & rates.keys(), key=lambda s: s.name):
        slope, rate = partial(expr, var), rates[var]
        terms.append(_times(slope, rate))
    if len(terms) == 1:
        return terms[0]
    return sx.Add(*terms)


def total_derivative(
    program: Program,
    outputs: Sequence[sx.Expr],
    rates: Mapping[sx.Expr, sx.Expr],
    names: Iterator[sx.Expr],
    check: Callable[[sx.Expr], None] | None = None,
) -> tuple[Program, tuple[sx.Expr, ...], dict[sx.Expr, sx.Expr]]:
    """Differentiate a program and its outputs along given rates of its free symbols.

    Parameters
    ----------
    program : Program
        The program defining intermediate symbols.
    outputs : sequence of expression
        Expressions over the program's symbols and free symbols.
    rates : mapping of symbol to expression
        Time derivative of each free symbol that moves (e.g. ``t -> 1``,
        ``y -> y'``). Symbols not listed are constant.
    names : iterator of symbol
        Source of fresh symbols for the new assignments.
    check : callable, optional
        Called with every new right-hand side and output (the derivation's budget meter).

    Returns
    -------
    program : Program
        The new assignments only (derivatives of the program's symbols that are not
        identically zero and not already in ``rates``); they follow ``program`` in
        evaluation order.
    outputs : tuple of expression
        The derivative of each output.
    rates : dict of symbol to expression
        ``rates`` extended with the derivative of every program symbol, so a further
        derivative of ``program + new program`` can be taken.
    """
    moving: dict[sx.Expr, sx.Expr] = dict(rates)
    new: list[Assignment] = []
    # The engine's zero: comparing with the int 0 converts it at every assignment.
    zero = sx.ZERO
    for sym, value in program.assignments:
        if sym in moving:
            continue  # differentiated by an earlier call; its rate is known
        rate = _derivative(value, moving)
        if rate == zero:
            continue
        if rate.is_Symbol or rate.is_Number:
            moving[sym] = rate
            continue
        if check is not None:
            check(rate)
        fresh = next(names)
        new.append((fresh, rate))
        moving[sym] = fresh
    derived = tuple(_derivative(sx.as_expr(e), moving) for e in outputs)
    if check is not None:
        for e in derived:
            check(e)
    return Program(tuple(new)), derived, moving


def next_derivative(
    program: Program,
    outputs: Sequence[sx.Expr],
    rates: Mapping[sx.Expr, sx.Expr],
    names: Iterator[sx.Expr],
    check: Callable[[sx.Expr], None] | None = None,
) -> tuple[Program, tuple[sx.Expr, ...], dict[sx.Expr, sx.Expr]]:
    """One more total derivative (:func:`total_derivative`), back in three-address form.

    Each new assignment is broken into single operations again, in order (a later
    assignment may use an earlier one's symbol), so that the derivative after this one
    differentiates small expressions only: the k-th derivative grows linearly in k.
    """
    new, current, moving = total_derivative(program, outputs, rates, names, check)
    # One walker for every assignment, its pieces written just before it: a walk per
    # assignment (a closure, a program and their release each) was a fifth of this.
    walker = _Atomizer(names, {})
    alias = walker.alias
    for sym, value in new.assignments:
        root = walker.visit(sx.as_expr(value))
        if root.is_Atom:
            # A rate that is a subtree assigned already (or a number): its symbol stands
            # for it wherever it is read, where an assignment of one symbol to another
            # was a third of a team's jet, walked by every pass of lowering after.
            alias[sym] = root
        else:
            walker.out.append((sym, root))
    current = tuple(walker.visit(sx.as_expr(e)) for e in current)
    if alias:
        moving = {sym: alias.get(rate, rate) for sym, rate in moving.items()}
    return Program(tuple(walker.out)), current, moving


def without_atoms(
    assignments: Sequence[Assignment], outputs: Sequence[sx.Expr]
) -> tuple[Program, tuple[sx.Expr, ...]]:
    """``assignments`` without those whose value is an atom, that atom put where they are read.

    Setting a program's highest derivatives to zero (the jet's rest) leaves assignments
    of zero and of one symbol to another; every pass of lowering would walk them.
    """
    alias: dict[sx.Expr, sx.Expr] = {}
    kept: list[Assignment] = []

    def replaced(expr: sx.Expr) -> sx.Expr:
        if not alias:
            return expr
        if expr.is_Atom:
            return alias.get(expr, expr)
        held = {s: alias[s] for s in expr.free_symbols if s in alias}
        return expr.xreplace(held) if held else expr

    for sym, raw in assignments:
        value = replaced(sx.as_expr(raw))
        if value.is_Atom:
            alias[sym] = value
        else:
            kept.append((sym, value))
    return Program(tuple(kept)), tuple(replaced(sx.as_expr(e)) for e in outputs)


def atomize(
    exprs: Sequence[sx.Expr], names: Iterator[sx.Expr], memo: dict[sx.Expr, sx.Expr] | None = None
) -> tuple[Program, tuple[sx.Expr, ...]]:
    """Break expressions into one operation per assignment (three-address form).

    Equal subtrees share one assignment (``memo``). Differentiating such a program
    costs one small derivative per operation, so the k-th total derivative grows
    linearly in the size of f0's gradient instead of re-walking nested subtrees.

    Parameters
    ----------
    exprs : sequence of expression
        Expressions to break up.
    names : iterator of symbol
        Source of names for the assignments.
    memo : dict, optional
        Subtree -> symbol, shared between calls that should share assignments.

    Returns
    -------
    tuple of (Program, tuple of expression)
        The assignments and the outputs (each a symbol or an atom).
    """
    walker = _Atomizer(names, {} if memo is None else memo)
    outputs = tuple(walker.visit(sx.as_expr(e)) for e in exprs)
    return Program(tuple(walker.out)), outputs


class _Atomizer:
    """The walk of :func:`atomize`: its memo of subtrees, the names, the assignments so far.

    A method, not a nested function: nothing to release after the walk (no cycle).
    """

    def __init__(self, names: Iterator[sx.Expr], table: dict[sx.Expr, sx.Expr]) -> None:
        self.names, self.table = names, table
        #: Symbols that stand for an atom (:func:`next_derivative`), replaced where met.
        self.alias: dict[sx.Expr, sx.Expr] = {}
        self.out: list[Assignment] = []

    def visit(self, node: sx.Expr) -> sx.Expr:
        """``node`` as an atom or the symbol of its assignment, its pieces assigned first."""
        alias = self.alias
        if node.is_Atom:
            return alias.get(node, node) if alias else node
        table = self.table
        # One lookup (a SymEngine node hashes and compares in a microsecond).
        known = table.get(node)
        if known is not None:
            return known
        own = node.args
        visit = self.visit
        # An atom is its own result: asked here, not in a call per atom.
        if alias:
            get = alias.get
            args = [get(arg, arg) if arg.is_Atom else visit(arg) for arg in own]
        else:
            args = [arg if arg.is_Atom else visit(arg) for arg in own]
        if node.is_Mul:
            # Products become chains of two factors: the derivative of an n-factor
            # product is n terms of n - 1 factors, quadratic; of a chain, linear.
            numbers = [a for a in args if a.is_Number]
            factors = [a for a in args if not a.is_Number]
            while len(factors) > 2:
                pair = sx.Mul(factors[0], factors[1])
                known = table.get(pair)
                if known is not None:
                    factors = [known, *factors[2:]]
                    continue
                symbol = next(self.names)
                self.out.append((symbol, pair))
                table[pair] = symbol
                factors = [symbol, *factors[2:]]
            args = [*numbers, *factors]
        # Arguments that came back as they were (atoms, in the same order) leave the
        # node as it is: rebuilding it (sympy's flatten) would only give it back.
        rebuilt = node if _same(args, own) else _rebuild(node, args)
        if rebuilt.is_Atom:
            table[node] = rebuilt
            return rebuilt
        symbol = next(self.names)
        self.out.append((symbol, rebuilt))
        table[node] = symbol
        return symbol


def jacobian(
    program: Program,
    outputs: Sequence[sx.Expr],
    variables: Sequence[sx.Expr],
    names: Iterator[sx.Expr],
    check: Callable[[sx.Expr], None] | None = None,
) -> tuple[Program, tuple[dict[int, sx.Expr], ...]]:
    """Forward-mode Jacobian of a program's outputs, with sparse tangents.

    Every symbol carries the nonzero entries of its gradient with respect to
    ``variables`` (index -> expression): a variable its own unit vector, an assignment
    ``s = e(v, ...)`` the sum ``sum_v (d e / d v) * tangent(v)``, entry by entry. Entries
    that are not a symbol or a number become new assignments. The cost is the number of
    nonzero tangent entries, about the program's size times the number of variables
    each assignment depends on: for the gradient of an objective coupling each agent
    to its neighbours, its Hessian in time linear in the number of agents.

    Parameters
    ----------
    program : Program
        The program (in three-address form, see :func:`atomize`, for small entries).
    outputs : sequence of expression
        Expressions over the program's symbols and free symbols.
    variables : sequence of symbol
        The independent variables (free symbols of the program).
    names : iterator of symbol
        Source of fresh symbols for the new assignments.
    check : callable, optional
        Called with every new right-hand side (the derivation's budget meter).

    Returns
    -------
    program : Program
        The new assignments only; they follow ``program`` in evaluation order.
    jacobian : tuple of dict of int to expression
        For each output, its nonzero partial derivatives by variable index.
    """
    tangent: dict[sx.Expr, dict[int, sx.Expr]] = {
        v: {j: sx.Integer(1)} for j, v in enumerate(variables)
    }

    zero = sx.ZERO  # the engine's: comparing with the int 0 converts it each time

    def propagate(expr: sx.Expr) -> dict[int, sx.Expr]:
        terms: dict[int, list[sx.Expr]] = {}
        # On SymEngine, whether its own diff suffices is asked once per expression, not
        # once per variable (partial asks it at each call).
        plain = sx.SYMENGINE and not _underived(expr)
        for var in sorted(expr.free_symbols & tangent.keys(), key=lambda s: s.name):
            slope = expr.diff(var) if plain else partial(expr, var)
            if slope == zero:
                continue
            for j, rate in tangent[var].items():
                terms.setdefault(j, []).append(_times(slope, rate))
        result = {j: sx.Add(*terms[j]) for j in sorted(terms)}
        return {j: value for j, value in result.items() if value != zero}

    new: list[Assignment] = []
    for sym, value in program.assignments:
        entries: dict[int, sx.Expr] = {}
        for j, rate in propagate(value).items():
            if rate.is_Symbol or rate.is_Number:
                entries[j] = rate
                continue
            if check is not None:
                check(rate)
            fresh = next(names)
            new.append((fresh, rate))
            entries[j] = fresh
        if entries:
            tangent[sym] = entries
    derived = tuple(propagate(sx.as_expr(e)) for e in outputs)
    return Program(tuple(new)), derived
