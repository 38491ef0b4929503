"""The spec reader's plant: ``[system]`` and ``[extension]``.

States with ``[system.dynamics]``, or coordinates with ``[system.mechanics]`` (its
rates, definitions, ``M``, ``F`` and ``B``); inputs, outputs and their expressions; and
the integrators ``[extension]`` prolongs inputs by.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, NamedTuple

from tvopt_codegen import symbolic as sx
from tvopt_codegen.spec.fields import _Entry, _Fields
from tvopt_codegen.spec.fields import suggestion as _suggestion
from tvopt_codegen.spec.implicit import affine_split, implicit_dynamics, mechanics_of, reserved
from tvopt_codegen.spec.names import name_problem
from tvopt_codegen.spec.types import MAX_INTEGRATORS, Mechanics, symbol


class _System(NamedTuple):
    """The names ``[system]`` declares, before any expression of it is read.

    Attributes
    ----------
    table : dict
        The ``[system]`` table itself.
    mechanical : bool
        Whether the plant is given by ``[system.mechanics]`` (else ``[system.dynamics]``).
    inputs, states : tuple of str
        Inputs and states (for a mechanical plant, the coordinates then the rates).
    coordinates, rates : tuple of str
        A mechanical plant's coordinates and their rates (empty otherwise).
    output_entries : list of (str, object, dict, str)
        ``[system.outputs]``, expanded: each output's name, text, index values and field.
    """

    table: dict[str, Any]
    mechanical: bool
    inputs: tuple[str, ...]
    states: tuple[str, ...]
    coordinates: tuple[str, ...]
    rates: tuple[str, ...]
    output_entries: list[_Entry]

    @property
    def outputs(self) -> tuple[str, ...]:
        """The outputs' names, in declaration order."""
        return tuple(name for name, _, _, _ in self.output_entries)


class _PlantReader(_Fields):
    """Reads ``[system]`` and ``[extension]``."""

    def read_system_names(self, data: Mapping[str, Any]) -> _System:
        """``[system]``'s keys and the names it declares: inputs, states, outputs.

        Parameters
        ----------
        data : Mapping
            The whole spec document.

        Returns
        -------
        _System
            The table and its names; expressions are read later, by :meth:`read_plant`.

        Raises
        ------
        SpecError
            When the table mixes the two forms of a plant, misses or misspells a key,
            declares no output, or a name is not one.
        """
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
        coordinates: tuple[str, ...] = ()
        rates: tuple[str, ...] = ()
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
        return _System(
            system,
            mechanical,
            inputs,
            states,
            coordinates,
            rates,
            output_entries,
        )

    def read_plant(
        self, system: _System, param_syms: dict[str, sx.Expr]
    ) -> tuple[list[sx.Expr], Mechanics | None, tuple[sx.Expr, ...]]:
        """The plant's expressions: right-hand sides (or mechanics) and outputs.

        Parameters
        ----------
        system : _System
            What :meth:`read_system_names` read.
        param_syms : dict of str to Symbol
            The parameters' symbols, by name.

        Returns
        -------
        dynamics : list of Expr
            One right-hand side per state, in the states' order.
        mechanics : Mechanics or None
            The mass-matrix form, for a plant given by ``[system.mechanics]``.
        output_exprs : tuple of Expr
            Each output's expression in the states and parameters.

        Raises
        ------
        SpecError
            When an expression does not parse or uses a name its field may not.
        """
        mechanics = None
        if system.mechanical:
            mechanics = self.read_mechanics(
                system.table, system.coordinates, system.rates, system.inputs, param_syms
            )
            dynamics = implicit_dynamics(mechanics, system.inputs)
        else:
            dynamics = self.read_dynamics(system.table, system.states, system.inputs, param_syms)
        state_names: dict[str, sx.Expr] = {n: symbol(n) for n in system.states} | param_syms
        output_exprs = tuple(
            self.expression(text, where, state_names, bound)
            for _, text, bound, where in system.output_entries
        )
        return dynamics, mechanics, output_exprs

    def read_dynamics(
        self,
        system: Mapping[str, Any],
        states: tuple[str, ...],
        inputs: tuple[str, ...],
        param_syms: Mapping[str, sx.Expr],
    ) -> list[sx.Expr]:
        """``[system.dynamics]``: one right-hand side per state, in the states' order."""
        plant_names: dict[str, sx.Expr] = {n: symbol(n) for n in (*states, *inputs)}
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
        param_syms: Mapping[str, sx.Expr],
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
        q_names: dict[str, sx.Expr] = {c: symbol(c) for c in coordinates} | dict(param_syms)
        state_names = q_names | {r: symbol(r) for r in rates}
        definitions = self.read_definitions(table, state_names, inputs)
        defined = {name: sym for name, sym, _ in definitions}
        # What each definition reads, transitively: M and B may not reach a rate through one.
        rate_symbols = {symbol(r) for r in rates}
        moving: set[sx.Expr] = set()
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
        names: Mapping[str, sx.Expr],
        inputs: tuple[str, ...],
    ) -> tuple[tuple[str, sx.Expr, sx.Expr], ...]:
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
        self, value: object, field: str, rows: int, cols: int, names: Mapping[str, sx.Expr]
    ) -> tuple[tuple[sx.Expr, ...], ...]:
        """A ``rows`` x ``cols`` list of lists of expressions (numbers or strings)."""
        if not isinstance(value, list) or len(value) != rows:
            raise self.fail(field, f"expected a list of {rows} rows")
        return tuple(
            tuple(self.vector(row, f"{field}[{i}]", cols, names)) for i, row in enumerate(value)
        )

    def vector(
        self, value: object, field: str, size: int, names: Mapping[str, sx.Expr]
    ) -> tuple[sx.Expr, ...]:
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
