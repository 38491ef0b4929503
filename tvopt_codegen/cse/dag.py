"""The CSE on SymEngine over a hash-consed DAG of integer node ids (issue 49).

On SymEngine every ``.args`` builds new Python objects, and a dictionary hit between
two distinct but equal expressions compares their trees in C++: the Python walks of
:mod:`tvopt_codegen.cse.numbering` cost microseconds a node. Here a program is read
once into a :class:`Dag`, where a node is an integer and equal subtrees share one id
(keyed on the node's class and its children's ids, cheap tuples of ints). Pruning,
alias dropping, value numbering, merging (negations looked up on ids), single-use
counting and operation counts then work on ints.

Where a substitution changes a node's children, the node is made on ids when its
constructor would only rename, splice nested sums or products, fold numbers or
collect like terms with rational coefficients (:meth:`Dag._plain`); its expression
is built when asked for, by the constructor, from its children's. Anything else
(distributing a number over a sum, factors of one base meeting, a sum cancelling
whole, a function's arguments becoming equal, float coefficients) is left to the
engine's constructor (:func:`~tvopt_codegen.cse.rewrite._rebuild_symengine`) and the
result read back into the table. The passes are those of
:mod:`~tvopt_codegen.cse.numbering`, step for step: kernels of the same size, in less
time.

Three passes are SymEngine's own, for its forms where SymPy's differ: a rational times
a sum is distributed when the program is read (:meth:`Dag.distribute`; SymPy's ``Mul``
does it, SymEngine keeps ``-(a + b)``), a kernel's sums whose terms share one
coefficient are written ``c*(...)`` last (:func:`~.coefficients.factored`), and merging reads
``(1/2)*_t`` of ``_t = 2*x`` as ``x`` (:meth:`Dag.merge_equal`). Odd functions are
signed (:meth:`Dag.signed_odd`) on the table, not by SymEngine's walks of the
expressions. The passes over a program on ids are :mod:`~tvopt_codegen.cse.programs`'.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from typing import Any

from tvopt_codegen import symbolic as sx
from tvopt_codegen.cse.rewrite import _NEGATED_TERMS, _odd, _rebuild_symengine, _signed_nested
from tvopt_codegen.maths.jet import release

#: A program on ids: (symbol's id, value's id) in evaluation order.
Program = list[tuple[int, int]]

# A node's kind, for the passes' tests (is it a sum, a product, a number?).
_SYMBOL, _NUMBER, _ADD, _MUL, _POW, _OTHER = range(6)
_COMPOUND = (_ADD, _MUL)


class Dag:
    """Expressions of one engine as integer ids, equal subtrees one id.

    ``expr[i]`` is an expression of node ``i`` (None until asked for, for a node made
    by a rename: :meth:`expression`), ``args[i]`` its children's ids (empty for a
    leaf), ``kind[i]`` one of the kinds above. For numbers, ``cost[i]`` is what the
    number costs alone (a negative or a fraction: one operation).
    """

    def __init__(self) -> None:
        self.expr: list[sx.Expr | None] = []
        self.args: list[tuple[int, ...]] = []
        self.kind: list[int] = []
        self.cost: dict[int, int] = {}
        # An expression object -> its id: SymEngine's == compares pointers first, so a
        # hit on an object of the table's own nodes (a rebuilt node's children) is cheap.
        self._ids: dict[sx.Expr, int] = {}
        # A compound node's (class, name, children) -> its id; sums' and products'
        # children sorted, as SymEngine may order equal ones' terms apart.
        self._keys: dict[tuple[Any, ...], int] = {}
        # A compound node's key's head (its class, and a function's name; a leaf's is
        # empty), and the node whose constructor builds it (itself, unless made by a
        # rename: :meth:`rebuild`).
        self._head: list[tuple[Any, ...]] = []
        self._template: list[int] = []
        self._types: dict[Any, tuple[int, bool]] = {}
        self._leaf_cost = 0
        self._negated: dict[int, int] = {}  # a number -> its negation
        self._counts: dict[int, dict[int, int]] = {}  # a node -> its symbols' uses
        self._add = type(sx.symbol("_dag") + sx.symbol("_dag_"))
        self._symbol = type(sx.symbol("_dag"))
        self.minus_one = self.intern(sx.Integer(-1))
        self.one = self.intern(sx.Integer(1))
        self.zero = self.intern(sx.Integer(0))
        self._numbers: dict[tuple[int, int, bool], int] = {}  # (a, b, sum?) -> a + b or a*b
        self._rational: dict[int, bool] = {}  # a number -> whether it is rational
        # A product, whose constructor builds the products made on ids (_product).
        self._mul = self.intern(sx.Integer(2) * sx.symbol("_dag"))
        self._below: dict[int, int] = {}
        self._splits: dict[int, tuple[tuple[int, ...], int]] = {}  # a term -> _split's
        self.factorings: dict[int, int] = {}  # a sum or product -> factored's rewrite
        self.magnitudes: dict[int, int] = {}  # a number -> its absolute value

    def intern(self, expr: sx.Expr) -> int:
        """The id of ``expr``, its new nodes added.

        A sum is not looked up by its expression: SymEngine's hash of ``a + b`` combines
        its terms' so that sums of neighbouring symbols collide (683 sums of one hash on
        a ring of 128 agents), and every colliding entry is compared in C++. Its terms'
        ids, looked up, key it instead.

        Reading a program is a call of this per value and per new child: the children's
        look-up and the new node's lists are written out here, where the calls of
        helpers for them were a third of its time.
        """
        cls = type(expr)
        add = self._add
        ids = self._ids
        if cls is not add:
            found = ids.get(expr)
            if found is not None:
                return found
        args = expr.args
        if not args:
            # A leaf equal to one in the table was found above: this one is new.
            i = self._new(expr, (), self._leaf_kind(expr), (), len(self.expr))
            ids[expr] = i
            return i
        info = self._types.get(cls)
        if info is None:
            info = self._types[cls] = self._describe(expr)
        kind, commutative = info
        # Most children of a three-address program's values are symbols and numbers met
        # before: looked up in place, a call of intern only for the others.
        get, intern = ids.get, self.intern
        children = tuple(
            [
                intern(arg) if type(arg) is add or (known := get(arg)) is None else known
                for arg in args
            ]
        )
        if commutative:
            head: tuple[Any, ...] = (cls,)
            key: tuple[Any, ...] = (cls, *sorted(children))
        else:
            # An undefined function's class is not its name.
            head = (cls, sx.function_name(expr)) if expr.is_Function else (cls,)
            key = (*head, *children)
        keys = self._keys
        i = keys.get(key, -1)
        if i < 0:
            i = keys[key] = len(self.expr)
            self.expr.append(expr)
            self.args.append(children)
            self.kind.append(kind)
            self._template.append(i)
            self._head.append(head)
        if cls is not add:
            ids[expr] = i
        return i

    def read(self, program: Iterable[tuple[sx.Expr, sx.Expr]]) -> Program:
        """The ids of a program's (symbol, value) pairs, in order.

        Its symbols are most of the leaves it adds, each new: added as symbols without
        asking the engine what they are (each ``.args`` and ``is_...`` makes new Python
        objects), which was a tenth of reading a ring's jet.
        """
        intern, ids, new = self.intern, self._ids, self._new
        symbol = self._symbol
        read: Program = []
        append = read.append
        for sym, value in program:
            if type(sym) is symbol:
                i = ids.get(sym)
                if i is None:
                    i = ids[sym] = new(sym, (), _SYMBOL, (), len(self.expr))
            else:
                i = intern(sym)
            append((i, intern(value)))
        return read

    @staticmethod
    def _describe(expr: sx.Expr) -> tuple[int, bool]:
        """A compound node's kind, and whether its children's order is immaterial."""
        if expr.is_Add:
            return _ADD, True
        if expr.is_Mul:
            return _MUL, True
        return (_POW if expr.is_Pow else _OTHER), False

    def _leaf_kind(self, expr: sx.Expr) -> int:
        """A leaf's kind; a number's cost alone is kept (:meth:`operations`)."""
        if expr.is_Number:
            negative = expr.is_negative is True
            self._leaf_cost = int(negative) + int(bool(expr.is_Rational and not expr.is_Integer))
            return _NUMBER
        return _SYMBOL if expr.is_Symbol else _OTHER

    def _new(
        self,
        expr: sx.Expr | None,
        children: tuple[int, ...],
        kind: int,
        head: tuple[Any, ...],
        template: int,
    ) -> int:
        """A new node; ``template`` is the node whose constructor builds it."""
        i = len(self.expr)
        self.expr.append(expr)
        self.args.append(children)
        self.kind.append(kind)
        if kind == _NUMBER:
            self.cost[i] = self._leaf_cost
        self._template.append(template)
        self._head.append(head)
        return i

    def rebuild(self, i: int, children: tuple[int, ...]) -> int:
        """Node ``i`` with ``children``, by its engine's constructor (terms collect).

        Where the constructor would find nothing to do but splice (:meth:`_plain`) the
        node is made on ids alone, its expression built when asked for (:meth:`expression`).
        """
        plain = self._plain(i, children)
        if plain is None and self.kind[i] == _MUL:
            distributed = self._distributed(children)
            if distributed is not None:
                return distributed
        if plain is not None:
            kind = self.kind[i]
            if len(plain) == 1 and kind in (_ADD, _MUL):
                return plain[0]  # a sum of one term, a product of one factor: that one
            children = plain
            if kind in (_ADD, _MUL):
                key: tuple[Any, ...] = (self._head[i][0], *sorted(children))
            else:
                key = (*self._head[i], *children)
            found = self._keys.get(key)
            if found is not None:
                return found
            j = self._keys[key] = self._new(None, children, kind, self._head[i], self._template[i])
            return j
        expression = self.expression
        built = _rebuild_symengine(expression(i), [expression(c) for c in children])
        return self.intern(built)

    def expression(self, i: int) -> sx.Expr:
        """The expression of node ``i``, built from its children's if it has none yet."""
        built = self.expr[i]
        if built is None:
            expression = self.expression
            template = self.expr[self._template[i]]
            built = _rebuild_symengine(template, [expression(c) for c in self.args[i]])
            self.expr[i] = built
            if type(built) is not self._add:
                self._ids[built] = i
        return built

    def _plain(self, i: int, children: tuple[int, ...]) -> tuple[int, ...] | None:
        """Node ``i``'s children as its constructor would keep them, None if it would do more.

        A sum's or product's one child alone is what its constructor returns (``-1*-s``
        is ``s``).

        A sum splices the sums among its terms and adds up its numbers, then keeps its
        terms when no two share their factors (``2*s + s``, ``s - s`` collect). A
        product splices the products among its factors and multiplies its numbers,
        then keeps its factors when no two share a base (``s*s**2``), none is a power
        of a number (``2*2**s``), and no rational coefficient is left with one sum
        (which :func:`~.rewrite._distributed` distributes). Another node keeps symbols
        for symbols, all distinct (``atan2(s, s)`` evaluates).
        """
        kind = self.kind
        k = kind[i]
        if k == _ADD:
            return self._plain_sum(children)
        if k == _MUL:
            return self._plain_product(children)
        old = self.args[i]
        changed = [c for c, o in zip(children, old, strict=True) if c != o]
        if any(kind[c] != _SYMBOL for c in changed) or len(set(children)) < len(children):
            return None
        if k == _POW or self.expression(self._template[i]).is_Function:
            return children
        return None

    def _plain_sum(self, children: tuple[int, ...]) -> tuple[int, ...] | None:
        """:meth:`_plain` for a sum, like terms collected as SymEngine's ``Add`` does.

        Only rational coefficients are added up here: a float's sum is the engine's.
        """
        kind, args = self.kind, self.args
        splits = self._splits
        number = self.zero
        terms: dict[tuple[int, ...], int] = {}  # a term's factors -> the term
        coefficients: dict[tuple[int, ...], int] = {}  # ... -> its coefficient, collected
        for c in children:
            for term in args[c] if kind[c] == _ADD else (c,):
                if kind[term] == _NUMBER:
                    number = self._arithmetic(number, term, True)
                    continue
                split = splits.get(term)
                key, coefficient = self._split(term) if split is None else split
                if key not in terms:
                    terms[key] = term
                    coefficients[key] = coefficient
                    continue
                known = coefficients[key]
                if not (self.is_rational(known) and self.is_rational(coefficient)):
                    return None
                coefficients[key] = self._arithmetic(known, coefficient, True)
                terms[key] = -1  # rebuilt below
        kept: list[int] = []
        for key, term in terms.items():
            coefficient = coefficients[key]
            if term >= 0:
                kept.append(term)
            elif coefficient == self.zero:
                continue
            elif coefficient == self.one and len(key) == 1:
                if kind[key[0]] == _ADD:
                    return None  # a sum as a term: the engine splices it
                kept.append(key[0])
            else:
                made = self._product(key if coefficient == self.one else (coefficient, *key))
                if made is None:
                    return None
                kept.append(made)
        if not kept:
            return None
        return tuple(kept) if number == self.zero else (number, *kept)

    def _split(self, term: int) -> tuple[tuple[int, ...], int]:
        """A sum's term as :meth:`_plain_sum` collects it: its factors, its coefficient.

        Kept per node: inlining rebuilds a sum each time a term of it changes, and
        its other terms are split again each time (a k = 12 chain's sums, a dozen
        times over).
        """
        key = self._term(term)
        first = self.args[term][0] if key != (term,) else -1
        coefficient = first if first >= 0 and self.kind[first] == _NUMBER else self.one
        split = self._splits[term] = (key, coefficient)
        return split

    def is_rational(self, number: int) -> bool:
        """Whether the number node ``number`` is exact (kept per node)."""
        found = self._rational.get(number)
        if found is None:
            found = self._rational[number] = bool(self.expression(number).is_Rational)
        return found

    def _product(self, children: tuple[int, ...]) -> int | None:
        """The product of ``children`` (a coefficient first, then factors), made on ids.

        None where the engine would do more (:meth:`_plain_product`).
        """
        plain = self._plain_product(children)
        if plain != children:
            return None
        head = self._head[self._mul]
        key = (head[0], *sorted(children))
        found = self._keys.get(key)
        if found is None:
            found = self._keys[key] = self._new(None, children, _MUL, head, self._mul)
        return found

    def _number_and_factors(self, children: tuple[int, ...]) -> tuple[int, list[int]]:
        """The product of ``children``'s numbers, and its other factors (products flattened)."""
        kind, args = self.kind, self.args
        number = self.one
        factors: list[int] = []
        for c in children:
            for factor in args[c] if kind[c] == _MUL else (c,):
                if kind[factor] == _NUMBER:
                    number = self._arithmetic(number, factor, False)
                else:
                    factors.append(factor)
        return number, factors

    def _plain_product(self, children: tuple[int, ...]) -> tuple[int, ...] | None:
        """:meth:`_plain` for a product."""
        kind, args = self.kind, self.args
        number, factors = self._number_and_factors(children)
        bases = []
        for c in factors:
            if kind[c] == _POW:
                base = args[c][0]
                if kind[base] == _NUMBER:
                    return None
                bases.append(base)
            else:
                bases.append(c)
        if len(set(bases)) < len(bases) or number == self.zero or not factors:
            return None
        if number == self.one:
            return tuple(factors)
        if len(factors) == 1 and kind[factors[0]] == _ADD:
            return None  # a number times a sum: distributed
        return (number, *factors)

    def _distributed(self, children: tuple[int, ...]) -> int | None:
        """The product of ``children`` when it is a rational times one sum, distributed.

        As :func:`~.rewrite._distributed` distributes it: ``c*(a + b)`` is ``c*a + c*b``,
        each term's coefficient multiplied, a term that is itself a number times a sum
        distributed in turn, the terms then collected (:meth:`_plain_sum`). Made on ids: a
        k = 12 chain's inlining distributes thousands of such products, and the engine
        built each one's whole tree first. None where the engine would do more, or where
        the product is not a rational times one sum.
        """
        kind, args = self.kind, self.args
        number, factors = self._number_and_factors(children)
        if (
            len(factors) != 1
            or kind[factors[0]] != _ADD
            or number in (self.one, self.zero)
            or not self.is_rational(number)
        ):
            return None
        total = factors[0]
        terms: list[int] = []
        for term in args[total]:
            if kind[term] == _NUMBER:
                terms.append(self._arithmetic(number, term, False))
                continue
            scaled = (number, *(args[term] if kind[term] == _MUL else (term,)))
            plain = self._plain_product(scaled)
            if plain is None:
                made = self._distributed(scaled)
                if made is None:
                    return None
            elif len(plain) == 1:
                made = plain[0]
            else:
                made = self._node(plain, _MUL, self._mul)
            terms.append(made)
        kept = self._plain_sum(tuple(terms))
        if kept is None:
            return None
        return kept[0] if len(kept) == 1 else self._node(kept, _ADD, total)

    def _node(self, children: tuple[int, ...], kind: int, like: int) -> int:
        """The sum or product of ``children`` (kept as they are), of node ``like``'s class."""
        cls = self._head[like][0]
        key = (cls, *sorted(children))
        found = self._keys.get(key)
        if found is None:
            found = self._keys[key] = self._new(
                None, children, kind, self._head[like], self._template[like]
            )
        return found

    def _arithmetic(self, a: int, b: int, add: bool) -> int:
        """The number ``a + b`` (or ``a*b``), as the engine computes it."""
        key = (a, b, add)
        found = self._numbers.get(key)
        if found is None:
            x, y = self.expression(a), self.expression(b)
            found = self._numbers[key] = self.intern(x + y if add else x * y)
        return found

    def _term(self, i: int) -> tuple[int, ...]:
        """A sum's term ``i`` as the constructor collects it: without its coefficient."""
        args = self.args[i]
        if self.kind[i] == _MUL:
            return tuple(sorted(c for c in args if self.kind[c] != _NUMBER))
        return (i,)

    def negated_atom(self, i: int) -> bool:
        """Whether node ``i`` is ``-x`` for a leaf ``x`` (printing it costs nothing)."""
        args = self.args[i]
        return (
            self.kind[i] == _MUL
            and len(args) == 2
            and args[0] == self.minus_one
            and not self.args[args[1]]
        )

    def _negated_number(self, i: int) -> int:
        negated = self._negated.get(i)
        if negated is None:
            negated = self._negated[i] = self.intern(-self.expression(i))
        return negated

    def _find(self, key: tuple[Any, ...]) -> int | None:
        """The sum or product ``key`` (its class, its children's ids), if it is a node."""
        kind, *children = key
        return self._keys.get((kind, *sorted(children)))

    def negation(self, i: int) -> int | None:
        """The node ``-i`` as :func:`~.rewrite._negate` writes it, None if there is none.

        Read off the table, without building: SymEngine's ``-`` of a product negates its
        coefficient, and :func:`~.rewrite._negate` of a sum negates its terms. A sum
        whose negated terms are not all nodes already cannot be one itself: a value
        that no earlier node equals cannot equal an earlier value (:meth:`merge_equal`).
        """
        if self.kind[i] == _ADD:
            terms = []
            for term in self.args[i]:
                negated = self._negated_term(term)
                if negated is None:
                    return None
                terms.append(negated)
            return self._find((sx.Add, *terms))
        return self._negated_term(i)

    def _negated_term(self, i: int) -> int | None:
        """``-i`` for a node that is not a sum (SymEngine keeps ``-(a + b)`` a product)."""
        kind, args = self.kind[i], self.args[i]
        if kind == _NUMBER:
            return self._negated_number(i)
        if kind == _MUL and self.kind[args[0]] == _NUMBER:
            coefficient = self._negated_number(args[0])
            if coefficient == self.one:
                rest = args[1:]
                return rest[0] if len(rest) == 1 else self._find((sx.Mul, *rest))
            return self._find((sx.Mul, coefficient, *args[1:]))
        if kind == _MUL:
            return self._find((sx.Mul, self.minus_one, *args))
        return self._find((sx.Mul, self.minus_one, i))

    def trivial(self, i: int) -> bool:
        """A leaf or a negated one: not worth a temporary.

        :meth:`negated_atom` written out: every pass asks this of every value.
        """
        args = self.args
        own = args[i]
        return not own or (
            self.kind[i] == _MUL and len(own) == 2 and own[0] == self.minus_one and not args[own[1]]
        )

    def substitute(self, i: int, mapping: dict[int, int], memo: dict[int, int]) -> int:
        """Node ``i`` with ``mapping`` applied, as :func:`~.rewrite._substitute` does.

        ``mapping``'s keys are leaves (the program's symbols): a compound node is
        looked up in ``memo`` only, and a leaf child is mapped where it is met, without
        a call of its own (most of a three-address program's children are leaves).
        """
        if not self.args[i]:
            return mapping.get(i, i)
        done = memo.get(i)
        if done is not None:
            return done
        # A method, not a nested function: the passes call this once per value of a
        # program (150 thousand times on a ring of 128 agents), most of them a node of
        # leaves, and making and releasing a closure for each cost more than the walk.
        return self._substituted(i, mapping.get, memo)

    def _substituted(self, node: int, get: Callable[..., int], memo: dict[int, int]) -> int:
        """:meth:`substitute`'s walk of a compound ``node`` not in ``memo``; ``get`` the mapping's.

        A child in ``memo`` already (a shared one) is looked up in place, not called.
        """
        args = self.args
        own = args[node]
        visit = self._substituted
        recall = memo.get
        new = tuple(
            [
                (
                    get(c, c)
                    if not args[c]
                    else (done if (done := recall(c)) is not None else visit(c, get, memo))
                )
                for c in own
            ]
        )
        made = node if new == own else self.rebuild(node, new)
        memo[node] = made
        return made

    def signed_odd(
        self, program: Program, outputs: Sequence[int], memo: dict[sx.Expr, sx.Expr]
    ) -> tuple[Program, list[int]]:
        """``program`` and ``outputs`` with their odd functions signed (:func:`.canonical_odd`).

        Found among the table's nodes (a scan of their classes), where SymEngine's
        ``atoms`` walked the whole program in C++ (a tenth of a second on a ring of
        128 agents); seldom does one change sign, and only then is the program walked.
        ``memo`` is :func:`.canonical_odd`'s, shared by a controller's kernels.
        """
        odd = set(_odd())
        mapping: dict[int, int] = {}
        for i, head in enumerate(self._head):
            if head and head[0] in odd:
                expr = self.expression(i)
                signed = _signed_nested(expr, memo)
                if signed != expr:
                    mapping[i] = self.intern(signed)
        if not mapping:
            return program, list(outputs)
        args = self.args
        done: dict[int, int] = {}

        def visit(node: int) -> int:
            target = mapping.get(node)
            if target is not None:
                return target
            found = done.get(node)
            if found is None:
                own = args[node]
                new = tuple([visit(c) for c in own])
                found = done[node] = node if new == own else self.rebuild(node, new)
            return found

        return walked(program, outputs, visit)

    def distribute(self, program: Program, outputs: Sequence[int]) -> tuple[Program, list[int]]:
        """Every rational times a sum in ``program`` and ``outputs`` distributed, as SymPy's.

        SymEngine keeps ``c*(a + b)`` (and ``-(a + b)``) as a product where SymPy's
        ``Mul`` distributes it: a negated sum then costs a negation of its own, outside
        a sum, and like terms across the two stay apart (:meth:`_distributed`).
        """
        args, kind = self.args, self.kind
        memo: dict[int, int] = {}

        def visit(node: int) -> int:
            own = args[node]
            if not own:
                return node
            done = memo.get(node)
            if done is not None:
                return done
            new = tuple([visit(c) if args[c] else c for c in own])
            done = node if new == own else self.rebuild(node, new)
            pair = args[done]
            # A product of two is a rational times a sum only with a sum (or a product
            # holding one) among them: most are a number times a symbol, asked for nothing.
            if (
                kind[done] == _MUL
                and len(pair) == 2
                and (kind[pair[0]] in _COMPOUND or kind[pair[1]] in _COMPOUND)
            ):
                distributed = self._distributed(pair)
                if distributed is not None:
                    done = distributed
            memo[node] = done
            return done

        return walked(program, outputs, visit)

    def _unscaled(self, product: int, values: dict[int, int]) -> int:
        """``c*_t*...`` as ``x*...`` where ``_t = k*x``, ``c*k = 1``, ``x`` a leaf.

        A temporary ``_t = 2*x`` that has several uses, one of them ``(1/2)*_t``: that
        one is ``x`` itself (``values``: the temporaries' values so far).
        """
        kind, args = self.kind, self.args
        factors = args[product]
        coefficient = factors[0]
        if kind[coefficient] != _NUMBER or not self.is_rational(coefficient):
            return product
        for factor in factors[1:]:
            value = values.get(factor)
            # Only for x a leaf: (1/2)*_t is one operation, x*... may be more.
            if (
                value is None
                or kind[value] != _MUL
                or len(args[value]) != 2
                or args[args[value][1]]
            ):
                continue
            scale = args[value][0]
            if kind[scale] == _NUMBER and self._arithmetic(coefficient, scale, False) == self.one:
                rest = [self.expression(f) for f in factors[1:] if f != factor]
                return self.intern(sx.Mul(*rest, self.expression(args[value][1])))
        return product

    def operations(self, roots: Iterable[int]) -> int:
        """:func:`~.rewrite.operation_count` of the nodes ``roots`` (memoised per DAG)."""
        args, kind, cost = self.args, self.kind, self.cost
        below = self._below
        minus_one = self.minus_one

        def own(node: int, parent: int) -> int:
            k = kind[node]
            if k == _NUMBER:
                return 0 if parent == _MUL else cost[node]
            a = args[node]
            if not a:
                return 0
            if k == _ADD:
                return len(a) - 1
            if k == _MUL:
                first = a[0]
                negated = parent == _ADD and first == minus_one
                return len(a) - 1 - int(negated)
            if k == _POW and a[1] == minus_one:
                return 0 if parent == _MUL else 1
            return 1

        def count(node: int) -> int:
            total = below.get(node)
            if total is None:
                k = kind[node]
                parent = k if k in (_ADD, _MUL) else _OTHER
                total = 0
                for arg in args[node]:
                    a = args[arg]
                    if a:
                        # own(arg, parent) written out for a compound child: a call
                        # per edge was a third of the count.
                        k = kind[arg]
                        if k == _ADD:
                            total += len(a) - 1
                        elif k == _MUL:
                            total += len(a) - 1 - (parent == _ADD and a[0] == minus_one)
                        elif k == _POW and a[1] == minus_one:
                            total += parent != _MUL
                        else:
                            total += 1
                        # A shared child is counted already: looked up, not called.
                        sub = below.get(arg)
                        total += count(arg) if sub is None else sub
                    elif kind[arg] == _NUMBER and parent != _MUL:
                        total += cost[arg]
                below[node] = total
            return total

        total = sum(own(r, _OTHER) + count(r) for r in roots)
        release(count)
        return total

    def merge_equal(self, order: Program, outputs: list[int]) -> tuple[Program, list[int]]:
        """:func:`~.numbering._merge_equal` on ids."""
        first: dict[int, int] = {}
        rename: dict[int, int] = {}
        memo: dict[int, int] = {}
        kept: Program = []
        values: dict[int, int] = {}
        for sym, raw in order:
            value = self.substitute(raw, rename, memo)
            if self.kind[value] == _MUL:
                value = self._unscaled(value, values)
            if self.trivial(value):
                rename[sym] = value
                continue
            same = first.get(value)
            if same is not None:
                rename[sym] = same
                continue
            if not (self.kind[value] == _ADD and len(self.args[value]) > _NEGATED_TERMS):
                opposite = self.negation(value)
                negated = None if opposite is None else first.get(opposite)
                if negated is not None:
                    rename[sym] = self._node((self.minus_one, negated), _MUL, self._mul)
                    continue
            first[value] = sym
            values[sym] = value
            kept.append((sym, value))
        return kept, [self.substitute(e, rename, memo) for e in outputs]

    def symbol_counts(self, root: int) -> dict[int, int]:
        """How often each symbol occurs in ``root``'s tree (kept per root)."""
        counts = self._counts.get(root)
        if counts is None:
            args, kind = self.args, self.kind
            counts = {}
            stack = [root]
            while stack:
                node = stack.pop()
                own = args[node]
                if own:
                    stack.extend(own)
                elif kind[node] == _SYMBOL:
                    counts[node] = counts.get(node, 0) + 1
            self._counts[root] = counts
        return counts


def walked(
    program: Program, outputs: Sequence[int], visit: Callable[[int], int]
) -> tuple[Program, list[int]]:
    """``program``'s values and ``outputs`` through the recursive walk ``visit``, then freed."""
    walked = [(sym, visit(value)) for sym, value in program]
    walked_outputs = [visit(e) for e in outputs]
    release(visit)
    return walked, walked_outputs
