"""The spec reader: every section read and checked in file order.

Names come before the expressions that use them; every problem is a
:class:`~tvopt_codegen.errors.SpecError` naming the file, the field and the problem.
"""

from __future__ import annotations

import difflib
import itertools
import math
import re
from collections.abc import Iterable, Mapping
from typing import Any

import numpy as np
import sympy as sp

from tvopt_codegen.errors import SpecError, clip
from tvopt_codegen.limits import MAX_T_FINAL
from tvopt_codegen.names import module_name_problem, name_problem
from tvopt_codegen.numeric import Evaluator
from tvopt_codegen.parse import (
    NO_INDEXING,
    ExpressionError,
    Indexing,
    indexed_name,
    parse_comparison,
    parse_expression,
)
from tvopt_codegen.spec.implicit import affine_split, implicit_dynamics, mechanics_of, reserved
from tvopt_codegen.spec.types import (
    ESTIMATOR_KINDS,
    MAX_INTEGRATORS,
    TIME,
    Barrier,
    Constraint,
    Estimator,
    Limit,
    Mechanics,
    Robust,
    Spec,
    symbol,
)

#: Most values one index may take.
MAX_INDEX_COUNT = 256


#: An indexed name in a key or a list: ``base[i]``.
_INDEXED = re.compile(r"^([A-Za-z][A-Za-z0-9_]*)\[([A-Za-z][A-Za-z0-9_]*)\]$")


_TOP_KEYS = {
    "index",
    "name",
    "description",
    "system",
    "extension",
    "parameters",
    "signals",
    "references",
    "constraints",
    "objective",
    "error_dynamics",
    "robust",
    "limits",
    "simulation",
}


#: The kind of name each declaring field holds.
_ROLES = {
    "system.states": "state",
    "system.inputs": "input",
    "system.outputs": "output",
    "parameters": "parameter",
    "signals": "signal",
    "references": "reference",
}


#: What the expressions of each field may use (for a name of another kind).
_ALLOWED = (
    ("system.dynamics", "the dynamics are functions of the states, inputs and parameters"),
    ("system.outputs", "outputs are functions of the states and parameters (y = h(x))"),
    ("signals", "signals are functions of t, parameters, references and other signals"),
    ("references", "a nominal reference is a function of t and the parameters"),
    ("objective", "f0 is a function of the outputs, signals, references, parameters and t"),
    (
        "constraints",
        "constraints are functions of the outputs, signals, references, parameters and t",
    ),
    ("parameters", "parameters are constants"),
    ("simulation", "initial values are constants"),
)


#: A key or list item after expansion: the flat name, its value, the index values
#: it was expanded with, and the field to name in messages.
_Entry = tuple[str, Any, dict[str, int], str]


class _Reader:
    """Validates one spec document; holds the source name for messages."""

    def __init__(self, source: str) -> None:
        self.source = source
        self.indexing = NO_INDEXING
        #: Declared name -> its kind ("state", "input", ...), for messages.
        self.roles: dict[str, str] = {}

    def read_indices(self, data: Mapping[str, Any]) -> None:
        """Read ``[index]``: each index name and how many values it takes."""
        table = self.sub(data, "index", "index")
        counts: dict[str, int] = {}
        for key, count in table.items():
            field = f"index.{key}"
            problem = name_problem(key)
            if problem:
                raise self.fail(field, problem)
            counts[key] = self.whole(count, field, 1, MAX_INDEX_COUNT, "number of values ")
        self.indexing = Indexing(counts, {}, {})

    def split(self, item: object, field: str) -> tuple[str, str | None]:
        """Split ``base[i]`` into base and index; a plain name has no index."""
        if not isinstance(item, str) or "[" not in item:
            return str(item), None
        match = _INDEXED.match(item)
        if match is None:
            raise self.fail(field, f"{item!r}: write an indexed name as base[i]")
        base, index = match.groups()
        if index not in self.indexing.counts:
            known = ", ".join(self.indexing.counts) or "none: declare them in [index]"
            raise self.fail(field, f"{item!r}: unknown index {index!r} (indices: {known})")
        return base, index

    def expand(self, items: list[tuple[str, Any, str]]) -> list[_Entry]:
        """Expand indexed names, keeping each run of items with one index together.

        ``items`` are (key, value, field for messages). ``["x[i]", "y[i]"]`` with
        ``i = 2`` becomes ``x_0, y_0, x_1, y_1``: the variables of one agent stay
        adjacent, which keeps its blocks contiguous.
        """
        out: list[_Entry] = []
        position = 0
        while position < len(items):
            key, value, where = items[position]
            base, index = self.split(key, where)
            position += 1
            if index is None:
                out.append((key, value, {}, where))
                continue
            run = [(base, value, where)]
            while position < len(items):
                next_key, next_value, next_where = items[position]
                next_base, next_index = self.split(next_key, next_where)
                if next_index != index:
                    break
                run.append((next_base, next_value, next_where))
                position += 1
            for number in range(self.indexing.counts[index]):
                for item_base, item_value, item_where in run:
                    name = indexed_name(item_base, number)
                    out.append((name, item_value, {index: number}, item_where))
        return out

    def family(self, entries: list[_Entry]) -> None:
        """Record the bases declared with an index, for ``x[k]`` in expressions."""
        families = dict(self.indexing.families)
        for name, _, bound, _ in entries:
            if bound:
                ((index, _),) = bound.items()
                base = name.rsplit("_", 1)[0]
                families[base] = self.indexing.counts[index]
        self.indexing = Indexing(self.indexing.counts, families, {})

    def bound(self, values: dict[str, int]) -> Indexing:
        indexing = self.indexing
        for index, value in values.items():
            indexing = indexing.bind(index, value)
        return indexing

    def constant(self, value: object, field: str, bound: dict[str, int]) -> float:
        """A number, or for an indexed key a constant expression such as ``2*pi*i/len(i)``."""
        if isinstance(value, str) and bound:
            try:
                expr = parse_expression(value, {}, self.bound(bound))
            except ExpressionError as exc:
                raise self.fail(field, str(exc)) from None
            # In doubles first: an exponential tower is inf at once, where sympy's
            # arbitrary-precision evalf would work on it for minutes.
            with np.errstate(all="ignore"):
                approximate = complex(Evaluator({})(expr))
            if approximate.imag != 0 or not math.isfinite(approximate.real):
                raise self.fail(field, f"{clip(value)!r} is not a finite real number")
            number = complex(expr.evalf())
            if number.imag != 0 or not math.isfinite(number.real):
                raise self.fail(field, f"{clip(value)!r} is not a finite real number")
            return number.real
        return self.number(value, field)

    def fail(self, field: str, problem: str) -> SpecError:
        return SpecError(self.source, field, problem)

    def table(
        self, data: Mapping[str, Any], field: str, allowed: set[str], required: set[str]
    ) -> None:
        """Reject unknown keys and report missing ones."""
        for key in data:
            if key not in allowed:
                hint = ", ".join(sorted(allowed))
                raise self.fail(
                    f"{field}.{key}" if field else key,
                    f"unknown key{_suggestion(key, allowed)} (expected one of: {hint})",
                )
        for key in sorted(required):
            if key not in data:
                raise self.fail(f"{field}.{key}" if field else key, "missing required key")

    def sub(self, data: Mapping[str, Any], key: str, field: str) -> dict[str, Any]:
        value = data.get(key, {})
        if not isinstance(value, dict):
            raise self.fail(field, f"expected a table, got {shown(value)}")
        return value

    def boolean(self, value: object, field: str) -> bool:
        """``value``, which must be ``true`` or ``false`` (not 1 or 0, though Python says equal)."""
        if not isinstance(value, bool):
            raise self.fail(field, f"expected true or false, got {shown(value)}")
        return value

    def whole(self, value: object, field: str, low: int, high: int, what: str = "") -> int:
        """``value``, a whole number ``low..high``; ``true`` and ``2.0`` are refused."""
        if isinstance(value, bool) or not isinstance(value, int):
            raise self.fail(field, f"expected a whole {what}{low}..{high}, got {shown(value)}")
        if not low <= value <= high:
            raise self.fail(field, f"expected a whole {what}{low}..{high}, got {clip(str(value))}")
        return value

    def number(self, value: object, field: str) -> float:
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise self.fail(field, f"expected a number, got {shown(value)}")
        result = float(value)
        if not math.isfinite(result):
            raise self.fail(field, "expected a finite number")
        return result

    def name_list(self, value: object, field: str) -> tuple[str, ...]:
        if not isinstance(value, list) or not value:
            raise self.fail(field, "expected a non-empty list of names")
        for index, item in enumerate(value):
            if not isinstance(item, str):
                raise self.fail(f"{field}[{index}]", f"expected a name, got {shown(item)}")
        entries = self.declare(
            self.expand([(item, None, f"{field}[{i}]") for i, item in enumerate(value)])
        )
        return tuple(name for name, _, _, _ in entries)

    def entries(self, table: Mapping[str, Any], field: str) -> list[_Entry]:
        """A table's items with indexed keys expanded (see :meth:`expand`)."""
        return self.expand([(key, value, f"{field}.{key}") for key, value in table.items()])

    def expression(
        self,
        text: object,
        field: str,
        names: Mapping[str, sp.Expr],
        bound: dict[str, int] | None = None,
    ) -> sp.Expr:
        if not isinstance(text, str):
            raise self.fail(field, f"expected an expression string, got {shown(text)}")
        try:
            return parse_expression(text, names, self.bound(bound or {}))
        except ExpressionError as exc:
            message = self.explain_unknown(exc, field)
            where = ", ".join(f"{k} = {v}" for k, v in (bound or {}).items())
            raise self.fail(field, f"{message} (at {where})" if where else message) from None

    def explain_unknown(self, exc: ExpressionError, field: str) -> str:
        """``exc`` as text; a declared name used where its kind may not be, said so."""
        found = re.match(r"unknown name '(\w+)'", exc.message)
        role = self.roles.get(found.group(1)) if found else None
        allowed = next((text for prefix, text in _ALLOWED if field.startswith(prefix)), None)
        if found is None or role is None or allowed is None:
            return str(exc)
        return f"column {exc.column}: {role} {found.group(1)!r} may not appear here: {allowed}"

    def read(self, data: Mapping[str, Any], sha256: str) -> Spec:
        # The spec's sections in file order, each read and checked where the next one
        # needs it (names before expressions that use them).
        self.table(data, "", _TOP_KEYS, {"name", "system", "objective", "error_dynamics"})
        name, description = self.read_title(data)

        self.read_indices(data)
        system = self.sub(data, "system", "system")
        mechanical = "mechanics" in system or "coordinates" in system
        if mechanical and ("dynamics" in system or "states" in system):
            both = "system.mechanics" if "mechanics" in system else "system.coordinates"
            raise self.fail(
                both,
                "give either states with [system.dynamics] or coordinates with "
                "[system.mechanics], not both",
            )
        self.table(
            system,
            "system",
            {"states", "inputs", "dynamics", "outputs", "coordinates", "mechanics"},
            {"inputs", "outputs"}
            | ({"coordinates", "mechanics"} if mechanical else {"states", "dynamics"}),
        )
        inputs = self.name_list(system["inputs"], "system.inputs")
        if mechanical:
            coordinates = self.name_list(system["coordinates"], "system.coordinates")
            rates = self.read_rates(system, coordinates)
            states = coordinates + rates
        else:
            states = self.name_list(system["states"], "system.states")
        outputs_table = self.sub(system, "outputs", "system.outputs")
        if not outputs_table:
            raise self.fail("system.outputs", "declare at least one output")
        output_entries = self.named_entries(outputs_table, "system.outputs")
        outputs = tuple(name for name, _, _, _ in output_entries)
        parameters_table = self.sub(data, "parameters", "parameters")
        parameter_entries = self.named_entries(parameters_table, "parameters")
        parameters = tuple(
            (name, self.constant(value, where, bound))
            for name, value, bound, where in parameter_entries
        )
        signals_table = self.sub(data, "signals", "signals")
        signal_entries = self.named_entries(signals_table, "signals")
        references_table = self.sub(data, "references", "references")
        references: tuple[str, ...] = ()
        if "references" in data:
            self.table(references_table, "references", {"names", "nominal", "estimator"}, {"names"})
            references = self.name_list(references_table["names"], "references.names")
        self.check_unique(
            states,
            inputs,
            outputs,
            tuple(name for name, _ in parameters),
            tuple(name for name, _, _, _ in signal_entries),
            references,
        )

        param_syms = {key: symbol(key) for key, _ in parameters}
        mechanics = None
        if mechanical:
            mechanics = self.read_mechanics(system, coordinates, rates, inputs, param_syms)
            dynamics = implicit_dynamics(mechanics, inputs)
        else:
            dynamics = self.read_dynamics(system, states, inputs, param_syms)
        state_names: dict[str, sp.Expr] = {n: symbol(n) for n in states} | param_syms
        output_exprs = tuple(
            self.expression(text, where, state_names, bound)
            for _, text, bound, where in output_entries
        )

        reference_syms = {name: symbol(name) for name in references}
        nominal = self.read_nominal(references_table, references, param_syms)
        estimator = self.read_estimator(references_table) if references else None
        signals = self.read_signals(signal_entries, {"t": TIME} | param_syms | reference_syms)

        objective_table = self.sub(data, "objective", "objective")
        self.table(objective_table, "objective", {"f0"}, {"f0"})
        objective_names: dict[str, sp.Expr] = (
            {"t": TIME}
            | param_syms
            | {o: symbol(o) for o in outputs}
            | {key: symbol(key) for key, _ in signals}
            | reference_syms
        )
        objective = self.expression(objective_table["f0"], "objective.f0", objective_names)

        constraints, barrier, allow_nonconvex = self.read_constraints(data, objective_names)
        equalities = tuple(c for c in constraints if c.op == "==")
        constraints = tuple(c for c in constraints if c.op != "==")
        extension, extension_auto, extension_max_total = self.read_extension(data, inputs)
        poles, coefficients = self.read_error_dynamics(data)
        robust = self.read_robust(data)
        limits = self.read_limits(data, inputs)
        t_final, initial_state = self.read_simulation(data)
        agents, objects = self.read_figure_layout(data, outputs, signals, references)
        return Spec(
            source=self.source,
            sha256=sha256,
            name=name,
            description=description,
            states=states,
            inputs=inputs,
            dynamics=tuple(dynamics),
            outputs=outputs,
            output_exprs=output_exprs,
            parameters=parameters,
            signals=tuple(signals),
            objective=objective,
            extension=extension,
            poles=poles,
            coefficients=coefficients,
            t_final=t_final,
            initial_state=initial_state,
            agents=agents,
            objects=objects,
            extension_auto=extension_auto,
            extension_max_total=extension_max_total,
            indices=tuple(self.indexing.counts.items()),
            references=references,
            reference_nominal=nominal,
            estimator=estimator,
            constraints=constraints,
            barrier=barrier,
            allow_nonconvex=allow_nonconvex,
            equalities=equalities,
            robust=robust,
            limits=limits,
            mechanics=mechanics,
        )

    def read_title(self, data: Mapping[str, Any]) -> tuple[str, str]:
        """``name`` (it names the generated module) and ``description``."""
        name = data["name"]
        if not isinstance(name, str):
            raise self.fail("name", f"expected a string, got {shown(name)}")
        problem = module_name_problem(name)
        if problem:
            raise self.fail("name", problem)
        description = data.get("description", "")
        if not isinstance(description, str):
            raise self.fail("description", f"expected a string, got {shown(description)}")
        if len(description) > 4000:
            raise self.fail("description", "longer than 4000 characters")
        control = next(
            (ch for ch in description if not ch.isprintable() and ch not in "\n\t"), None
        )
        if control is not None:
            # It reaches docstrings, comments and both reports: a terminal escape or a
            # carriage return there would rewrite what a reader sees.
            raise self.fail("description", f"holds the control character U+{ord(control):04X}")
        return name, description

    def read_dynamics(
        self,
        system: Mapping[str, Any],
        states: tuple[str, ...],
        inputs: tuple[str, ...],
        param_syms: Mapping[str, sp.Symbol],
    ) -> list[sp.Expr]:
        """``[system.dynamics]``: one right-hand side per state, in the states' order."""
        plant_names: dict[str, sp.Expr] = {n: symbol(n) for n in (*states, *inputs)}
        plant_names |= param_syms
        dynamics_table = self.sub(system, "dynamics", "system.dynamics")
        dynamics_entries = {
            name: (value, bound, where)
            for name, value, bound, where in self.entries(dynamics_table, "system.dynamics")
        }
        for key, (_, _, where) in dynamics_entries.items():
            if key not in states:
                raise self.fail(
                    where, f"{key!r} is not a declared state{_suggestion(key, set(states))}"
                )
        dynamics = []
        for state in states:
            if state not in dynamics_entries:
                raise self.fail(
                    f"system.dynamics.{state}", "missing right-hand side for this state"
                )
            text, bound, where = dynamics_entries[state]
            dynamics.append(self.expression(text, where, plant_names, bound))
        return dynamics

    def read_rates(
        self, system: Mapping[str, Any], coordinates: tuple[str, ...]
    ) -> tuple[str, ...]:
        """``system.mechanics.rates``, one per coordinate; ``d<coordinate>`` by default."""
        table = self.sub(system, "mechanics", "system.mechanics")
        if "rates" not in table:
            rates = tuple(f"d{name}" for name in coordinates)
            for name in rates:
                problem = name_problem(name)
                if problem:
                    raise self.fail("system.mechanics.rates", f"the default rate {problem}")
            return rates
        rates = self.name_list(table["rates"], "system.mechanics.rates")
        if len(rates) != len(coordinates):
            raise self.fail(
                "system.mechanics.rates",
                f"{len(rates)} rates for {len(coordinates)} coordinates (one rate each)",
            )
        return rates

    def read_mechanics(
        self,
        system: Mapping[str, Any],
        coordinates: tuple[str, ...],
        rates: tuple[str, ...],
        inputs: tuple[str, ...],
        param_syms: Mapping[str, sp.Symbol],
    ) -> Mechanics:
        """``[system.mechanics]``: ``M(q) q'' = F(q, q') + B(q) u``, shapes and names checked.

        ``M`` and ``B`` are expressions in the coordinates and parameters, ``F`` also in
        the rates. Without ``input_matrix``, ``F`` may be affine in the inputs and ``B``
        is its coefficient; symmetry and definiteness are the model's to check (they
        need evaluation).
        """
        field = "system.mechanics"
        table = self.sub(system, "mechanics", field)
        self.table(
            table,
            field,
            {"rates", "mass_matrix", "forces", "input_matrix", "definitions"},
            {"mass_matrix", "forces"},
        )
        n = len(coordinates)
        q_names: dict[str, sp.Expr] = {c: symbol(c) for c in coordinates} | dict(param_syms)
        state_names = q_names | {r: symbol(r) for r in rates}
        definitions = self.read_definitions(table, state_names, inputs)
        defined = {name: sym for name, sym, _ in definitions}
        # What each definition reads, transitively: M and B may not reach a rate through one.
        rate_symbols = {symbol(r) for r in rates}
        moving: set[sp.Symbol] = set()
        for _, sym, expr in definitions:
            if expr.free_symbols & (rate_symbols | moving):
                moving.add(sym)
        q_names = q_names | {k: v for k, v in defined.items() if v not in moving}
        state_names = state_names | defined
        with_inputs = "input_matrix" not in table
        force_names = state_names | ({u: symbol(u) for u in inputs} if with_inputs else {})
        mass = self.matrix(table["mass_matrix"], f"{field}.mass_matrix", n, n, q_names)
        forces = self.vector(table["forces"], f"{field}.forces", n, force_names)
        u = [symbol(name) for name in inputs]
        if with_inputs:
            try:
                gain, forces = affine_split(forces, u)
            except ValueError as exc:
                raise self.fail(f"{field}.forces", str(exc)) from None
        else:
            gain = self.matrix(table["input_matrix"], f"{field}.input_matrix", n, len(u), q_names)
        return mechanics_of(coordinates, rates, mass, forces, gain, definitions)

    def read_definitions(
        self,
        table: Mapping[str, Any],
        names: Mapping[str, sp.Expr],
        inputs: tuple[str, ...],
    ) -> tuple[tuple[str, sp.Symbol, sp.Expr], ...]:
        """``system.mechanics.definitions``: named intermediate values, in file order.

        Each is an expression in the coordinates, rates, parameters and the definitions
        above it, and stands for a reserved symbol (``_let<i>``): generated code computes
        it once, and nothing substitutes it into ``M``, ``F`` or ``B``.
        """
        field = "system.mechanics.definitions"
        entries = self.sub(table, "definitions", field)
        if len(entries) > 100_000:
            raise self.fail(field, "more than 100,000 definitions")
        taken = {name.casefold() for name in (*names, *inputs, *self.roles)}
        known = dict(names)
        out = []
        for index, (name, text) in enumerate(entries.items()):
            where = f"{field}.{name}"
            problem = name_problem(name)
            if problem:
                raise self.fail(where, problem)
            if name.casefold() in taken:
                raise self.fail(
                    where, "name already declared (names must be unique, ignoring case)"
                )
            expr = self.expression(text, where, known)
            sym = reserved(index)
            known[name] = sym
            taken.add(name.casefold())
            out.append((name, sym, expr))
        return tuple(out)

    def matrix(
        self, value: object, field: str, rows: int, cols: int, names: Mapping[str, sp.Expr]
    ) -> tuple[tuple[sp.Expr, ...], ...]:
        """A ``rows`` x ``cols`` list of lists of expressions (numbers or strings)."""
        if not isinstance(value, list) or len(value) != rows:
            raise self.fail(field, f"expected a list of {rows} rows")
        return tuple(
            tuple(self.vector(row, f"{field}[{i}]", cols, names)) for i, row in enumerate(value)
        )

    def vector(
        self, value: object, field: str, size: int, names: Mapping[str, sp.Expr]
    ) -> tuple[sp.Expr, ...]:
        """A list of ``size`` expressions, each a number or an expression string."""
        if not isinstance(value, list) or len(value) != size:
            raise self.fail(field, f"expected a list of {size} entries")
        entries = []
        for j, item in enumerate(value):
            where = f"{field}[{j}]"
            text = item
            if isinstance(item, int | float) and not isinstance(item, bool):
                number = self.number(item, where)
                text = str(item) if isinstance(item, int) else repr(number)
            entries.append(self.expression(text, where, names))
        return tuple(entries)

    def read_signals(self, entries: Any, names: dict[str, sp.Expr]) -> list[tuple[str, sp.Expr]]:
        """``[signals]``, in file order; ``names`` holds t, the parameters and references."""
        signals: list[tuple[str, sp.Expr]] = []
        for key, text, bound, where in entries:
            expr = self.expression(text, where, names, bound)
            signals.append((key, expr))
            # Later signals may use earlier ones; they see the explicit expression so
            # every signal is a function of t, the parameters and the references alone.
            names[key] = expr
        return signals

    def read_figure_layout(
        self,
        data: Mapping[str, Any],
        outputs: tuple[str, ...],
        signals: list[tuple[str, sp.Expr]],
        references: tuple[str, ...],
    ) -> tuple[tuple[tuple[str, str], ...], tuple[tuple[str, str], ...]]:
        """``[simulation]``'s ``agents`` and ``objects``: what the figures draw as pairs."""
        simulation = data.get("simulation", {})
        agents = self.pairs(simulation, "agents", set(outputs), "output")
        if not agents and len(outputs) % 2 == 0:
            agents = tuple((outputs[i], outputs[i + 1]) for i in range(0, len(outputs), 2))
        objects = self.pairs(
            simulation, "objects", {name for name, _ in signals} | set(references), "signal"
        )
        return agents, objects

    def read_constraints(
        self, data: Mapping[str, Any], names: Mapping[str, sp.Expr]
    ) -> tuple[tuple[Constraint, ...], Barrier | None, bool]:
        """``[constraints]``: one comparison per key, the barrier, ``allow_nonconvex``."""
        table = self.sub(data, "constraints", "constraints")
        if "constraints" not in data:
            return (), None, False
        allow = self.boolean(table.get("allow_nonconvex", False), "constraints.allow_nonconvex")
        items = {k: v for k, v in table.items() if k not in ("barrier", "allow_nonconvex")}
        if not items:
            raise self.fail("constraints", "declare at least one constraint")
        constraints = []
        for key, text, bound, where in self.entries(items, "constraints"):
            problem = name_problem(key)
            if problem:
                raise self.fail(where, problem)
            if isinstance(text, dict):
                # A table here is a misspelt [constraints.barrier] far more often than a
                # constraint written as one.
                guess = _suggestion(key, {"barrier"})
                raise self.fail(
                    where,
                    f"a table, where a constraint is a comparison string{guess}"
                    " ([constraints.barrier] is the one table [constraints] takes)",
                )
            if not isinstance(text, str):
                # A value that is no comparison, under a name like allow_nonconvex or
                # barrier, is that key misspelt.
                guess = _suggestion(key, {"allow_nonconvex", "barrier"})
                raise self.fail(where, f"expected a comparison string, got {shown(text)}{guess}")
            try:
                op, lhs, rhs = parse_comparison(text, names, self.bound(bound))
            except ExpressionError as exc:
                raise self.fail(where, self.explain_unknown(exc, where)) from None
            constraints.append(Constraint(key, op, lhs, rhs, text))
        if "barrier" in table and all(c.op == "==" for c in constraints):
            raise self.fail("constraints.barrier", "only meaningful with inequalities (<=, >=)")
        barrier_table = self.sub(table, "barrier", "constraints.barrier")
        self.table(
            barrier_table,
            "constraints.barrier",
            {"initial_weight", "final_weight", "rate", "initial_slack"},
            set(),
        )
        values: dict[str, float] = {}
        for key, default in (("initial_weight", 1.0), ("final_weight", 1e-4), ("rate", 1.0)):
            value = self.number(barrier_table.get(key, default), f"constraints.barrier.{key}")
            if not value > 0:
                raise self.fail(f"constraints.barrier.{key}", "must be positive")
            values[key] = value
        if values["final_weight"] > values["initial_weight"]:
            raise self.fail("constraints.barrier.final_weight", "must not exceed initial_weight")
        slack = barrier_table.get("initial_slack")
        if slack is not None:
            slack = self.number(slack, "constraints.barrier.initial_slack")
            if slack < 0:
                raise self.fail("constraints.barrier.initial_slack", "must not be negative")
        barrier = Barrier(values["initial_weight"], values["final_weight"], values["rate"], slack)
        return tuple(constraints), barrier, allow

    def read_nominal(
        self,
        table: Mapping[str, Any],
        references: tuple[str, ...],
        param_syms: Mapping[str, sp.Expr],
    ) -> tuple[tuple[str, sp.Expr], ...]:
        """The ``nominal`` closed forms, in t and the parameters, by reference name."""
        nominal = self.sub(table, "nominal", "references.nominal") if table else {}
        names = {"t": TIME} | dict(param_syms)
        result = []
        for key, text, bound, where in self.entries(nominal, "references.nominal"):
            if key not in references:
                raise self.fail(
                    where,
                    f"{key!r} is not a declared reference{_suggestion(key, set(references))}",
                )
            result.append((key, self.expression(text, where, names, bound)))
        order = {name: i for i, name in enumerate(references)}
        return tuple(sorted(result, key=lambda item: order[item[0]]))

    def read_estimator(self, table: Mapping[str, Any]) -> Estimator:
        """``[references.estimator]``: its kind and gain (defaults: linear, 20 rad/s)."""
        estimator = self.sub(table, "estimator", "references.estimator")
        self.table(estimator, "references.estimator", {"kind", "bandwidth", "lipschitz"}, set())
        kind = estimator.get("kind", "linear")
        if kind not in ESTIMATOR_KINDS:
            raise self.fail(
                "references.estimator.kind",
                f"expected one of {', '.join(map(repr, ESTIMATOR_KINDS))}, got {shown(kind)}",
            )
        values = {}
        for key, default in (("bandwidth", 20.0), ("lipschitz", 1.0)):
            value = self.number(estimator.get(key, default), f"references.estimator.{key}")
            if not value > 0:
                raise self.fail(f"references.estimator.{key}", "must be positive")
            values[key] = value
        if kind == "linear" and "lipschitz" in estimator:
            raise self.fail("references.estimator.lipschitz", "only meaningful for levant")
        if kind == "levant" and "bandwidth" in estimator:
            raise self.fail("references.estimator.bandwidth", "only meaningful for linear")
        return Estimator(kind, values["bandwidth"], values["lipschitz"])

    def named_entries(self, table: Mapping[str, Any], field: str) -> list[_Entry]:
        """Expanded entries of a table that declares names (outputs, parameters, ...)."""
        return self.declare(self.entries(table, field))

    def declare(self, entries: list[_Entry]) -> list[_Entry]:
        """Record indexed families and check every declared (expanded) name."""
        self.family(entries)
        for name, _, _, where in entries:
            problem = name_problem(name)
            if problem:
                raise self.fail(where, problem)
        return entries

    def check_unique(
        self,
        states: tuple[str, ...],
        inputs: tuple[str, ...],
        outputs: tuple[str, ...],
        parameters: tuple[str, ...],
        signals: tuple[str, ...],
        references: tuple[str, ...] = (),
    ) -> None:
        """Every name is declared once across all six kinds (case-insensitively)."""
        seen: dict[str, str] = {}
        groups = [
            ("system.states", states),
            ("system.inputs", inputs),
            ("system.outputs", outputs),
            ("parameters", parameters),
            ("signals", signals),
            ("references", references),
        ]
        for field, names in groups:
            for name in names:
                folded = name.casefold()
                if folded in seen:
                    raise self.fail(
                        f"{field}.{name}",
                        f"name already declared in {seen[folded]} (names must "
                        "be unique, ignoring case)",
                    )
                seen[folded] = field
                self.roles[name] = _ROLES[field]

    def read_extension(
        self, data: Mapping[str, Any], inputs: tuple[str, ...]
    ) -> tuple[tuple[tuple[str, int], ...], bool, int | None]:
        table = self.sub(data, "extension", "extension")
        self.table(table, "extension", {"integrate", "auto", "max_total"}, set())
        auto = self.boolean(table.get("auto", False), "extension.auto")
        max_total = table.get("max_total")
        if max_total is not None:
            if not auto:
                raise self.fail("extension.max_total", "only meaningful with auto = true")
            max_total = self.whole(
                max_total, "extension.max_total", 1, 3 * MAX_INTEGRATORS, "number "
            )
        if auto and "integrate" in table:
            raise self.fail("extension", "give either integrate or auto = true, not both")
        integrate = {}
        for key, count, _, field in self.entries(
            self.sub(table, "integrate", "extension.integrate"), "extension.integrate"
        ):
            integrate[key] = count
            if key not in inputs:
                raise self.fail(
                    field, f"{key!r} is not a declared input{_suggestion(key, set(inputs))}"
                )
            self.whole(count, field, 0, MAX_INTEGRATORS, "number of integrators ")
        counts = tuple((u, integrate[u]) for u in inputs if integrate.get(u, 0) > 0)
        return counts, auto, max_total

    def read_robust(self, data: Mapping[str, Any]) -> Robust:
        """``[robust]``: integral action and ``[robust.observer]``."""
        table = self.sub(data, "robust", "robust")
        self.table(table, "robust", {"integral", "observer"}, set())
        integral = self.boolean(table.get("integral", False), "robust.integral")
        bandwidth = None
        if "observer" in table:
            observer = self.sub(table, "observer", "robust.observer")
            self.table(observer, "robust.observer", {"bandwidth"}, {"bandwidth"})
            bandwidth = self.number(observer["bandwidth"], "robust.observer.bandwidth")
            if not bandwidth > 0:
                raise self.fail("robust.observer.bandwidth", "must be positive (rad/s)")
        return Robust(integral, bandwidth)

    def read_limits(self, data: Mapping[str, Any], inputs: tuple[str, ...]) -> tuple[Limit, ...]:
        """``[limits]``: each input's ``[low, high]`` (or ``L``: ``[-L, L]``), and rates."""
        table = dict(self.sub(data, "limits", "limits"))
        rates_table = self.sub(table, "rate", "limits.rate")
        table.pop("rate", None)
        ranges: dict[str, tuple[float, float]] = {}
        for name, value in table.items():
            field = f"limits.{name}"
            if name not in inputs:
                raise self.fail(
                    field,
                    f"{clip(str(name))!r} is not a plant input ({', '.join(inputs)})"
                    f"{_suggestion(str(name), set(inputs))}",
                )
            if isinstance(value, list):
                if len(value) != 2:
                    raise self.fail(field, f"expected [low, high], got {len(value)} numbers")
                low = self.number(value[0], f"{field}[0]")
                high = self.number(value[1], f"{field}[1]")
                if not low < high:
                    raise self.fail(field, f"low {low:g} must be below high {high:g}")
            else:
                high = self.number(value, field)
                if not high > 0:
                    raise self.fail(
                        field, f"a single limit L means [-L, L]: L must be positive, got {high:g}"
                    )
                low = -high
            ranges[name] = (low, high)
        rates: dict[str, float] = {}
        for name, value in rates_table.items():
            field = f"limits.rate.{name}"
            if name not in inputs:
                raise self.fail(
                    field,
                    f"{clip(str(name))!r} is not a plant input ({', '.join(inputs)})"
                    f"{_suggestion(str(name), set(inputs))}",
                )
            rate = self.number(value, field)
            if not rate > 0:
                raise self.fail(field, f"a rate limit must be positive (per second), got {rate:g}")
            rates[name] = rate
        return tuple(
            Limit(u, *ranges.get(u, (-math.inf, math.inf)), rates.get(u, math.inf))
            for u in inputs
            if u in ranges or u in rates
        )

    def read_error_dynamics(
        self, data: Mapping[str, Any]
    ) -> tuple[tuple[complex, ...] | None, tuple[float, ...] | None]:
        table = self.sub(data, "error_dynamics", "error_dynamics")
        self.table(table, "error_dynamics", {"poles", "coefficients"}, set())
        if ("poles" in table) == ("coefficients" in table):
            raise self.fail("error_dynamics", "give exactly one of 'poles' or 'coefficients'")
        if "coefficients" in table:
            values = table["coefficients"]
            if not isinstance(values, list) or not values:
                raise self.fail(
                    "error_dynamics.coefficients", "expected a non-empty list of numbers"
                )
            return None, tuple(
                self.number(v, f"error_dynamics.coefficients[{i}]") for i, v in enumerate(values)
            )
        values = table["poles"]
        if not isinstance(values, list) or not values:
            raise self.fail("error_dynamics.poles", "expected a non-empty list of poles")
        poles: list[complex] = []
        for index, value in enumerate(values):
            field = f"error_dynamics.poles[{index}]"
            if isinstance(value, list):
                if len(value) != 2:
                    raise self.fail(field, "a conjugate pair is written [re, im]")
                re, im = (self.number(v, field) for v in value)
                if im <= 0:
                    raise self.fail(field, "the imaginary part of a pair [re, im] must be positive")
                poles += [complex(re, im), complex(re, -im)]
            else:
                poles.append(complex(self.number(value, field), 0.0))
        return tuple(poles), None

    def pairs(
        self, table: Mapping[str, Any], key: str, known: set[str], kind: str
    ) -> tuple[tuple[str, str], ...]:
        """Read a list of name pairs, e.g. ``agents = [["y1", "y2"]]``."""
        value = table.get(key, [])
        field = f"simulation.{key}"
        if not isinstance(value, list):
            raise self.fail(field, "expected a list of [x, y] name pairs")
        result = []
        for index, pair in enumerate(value):
            where = f"{field}[{index}]"
            if not (isinstance(pair, list) and len(pair) == 2):
                raise self.fail(where, f"expected a pair [x, y] of names, got {shown(pair)}")
            for name in pair:
                if not isinstance(name, str):
                    raise self.fail(where, f"expected a pair [x, y] of names, got {shown(name)}")
            # ["px[i]", "py[i]"] stands for one pair per value of i.
            parts = [self.split(name, where) for name in pair]
            indices = {i for _, i in parts if i is not None}
            if len(indices) > 1:
                raise self.fail(where, "a pair may use one index only")
            values = range(self.indexing.counts[next(iter(indices))]) if indices else [None]
            for number in values:
                names = [
                    indexed_name(base, number) if i is not None and number is not None else base
                    for base, i in parts
                ]
                for name in names:
                    if name not in known:
                        raise self.fail(
                            where,
                            f"{name!r} is not a declared {kind}{_suggestion(name, known)}",
                        )
                result.append((names[0], names[1]))
        return tuple(result)

    def read_simulation(
        self, data: Mapping[str, Any]
    ) -> tuple[float, tuple[tuple[str, float], ...]]:
        table = self.sub(data, "simulation", "simulation")
        self.table(table, "simulation", {"t_final", "initial_state", "agents", "objects"}, set())
        t_final = self.number(table.get("t_final", 10.0), "simulation.t_final")
        if not 0 < t_final <= MAX_T_FINAL:
            raise self.fail("simulation.t_final", f"must be positive and at most {MAX_T_FINAL:g}")
        initial = self.sub(table, "initial_state", "simulation.initial_state")
        return t_final, tuple(
            (key, self.constant(value, where, bound))
            for key, value, bound, where in self.entries(initial, "simulation.initial_state")
        )


def shown(value: object) -> str:
    """A value as an error quotes it: its TOML type and its text, clipped.

    Every type check names both, since ``1`` where ``true`` belongs reads the same in a
    message that gives the value alone; and a value may be of any type, so nothing here
    assumes a string.
    """
    kinds: tuple[tuple[type, str], ...] = (
        (bool, "boolean"),
        (int, "integer"),
        (float, "float"),
        (str, "string"),
        (list, "array"),
        (tuple, "array"),
        (dict, "table"),
    )
    kind = next((name for cls, name in kinds if isinstance(value, cls)), None)
    if kind is None:
        # tomllib's dates and times, or anything a Python caller put in the dict.
        name = type(value).__name__
        kind = {"datetime": "date-time", "date": "date", "time": "time"}.get(name, name)
    return f"{kind} {clip(_toml_text(value, 3))}"


def _toml_text(value: object, depth: int) -> str:
    """``value`` written as TOML would (``true``, ``"a"``, ``[1, 2]``), nested ``depth`` deep."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return repr(clip(value))
    if isinstance(value, list | tuple | dict):
        if depth == 0:
            return "[...]" if not isinstance(value, dict) else "{...}"
        if isinstance(value, dict):
            pairs = itertools.islice(value.items(), 8)
            return (
                "{ "
                + ", ".join(f"{clip(str(k))} = {_toml_text(v, depth - 1)}" for k, v in pairs)
                + " }"
            )
        return "[" + ", ".join(_toml_text(v, depth - 1) for v in itertools.islice(value, 8)) + "]"
    text = repr(value) if isinstance(value, float) else str(value)
    return clip(text)


def suggestion(key: str, allowed: Iterable[str]) -> str:
    """``: did you mean 'x'?`` for the allowed key closest to a misspelt one, or nothing.

    Every place that refuses a key or a name it does not know asks this, at any depth:
    ``constraints.barier``, ``robust.observer.bandwith``, an initial value of ``thetaa``.
    """
    close = difflib.get_close_matches(key, sorted(allowed), n=1, cutoff=0.7)
    return f": did you mean '{close[0]}'?" if close else ""


_suggestion = suggestion
