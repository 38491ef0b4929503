"""The spec reader: every section read and checked in file order.

Names come before the expressions that use them; every problem is a
:class:`~tvopt_codegen.errors.SpecError` naming the file, the field and the problem.
:class:`_Reader` reads the title and the parameters and puts the spec together; each
family of sections is read by a module of its own: ``fields`` (tables, numbers, names,
indices, expressions), ``plant`` (``[system]``, ``[extension]``), ``objective``
(``[references]``, ``[signals]``, ``[objective]``, ``[constraints]``) and ``settings``
(``[error_dynamics]``, ``[robust]``, ``[limits]``, ``[simulation]``, ``[tune]``).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from tvopt_codegen.spec.fields import MAX_INDEX_COUNT, shown, suggestion
from tvopt_codegen.spec.names import module_name_problem
from tvopt_codegen.spec.objective import _ObjectiveReader
from tvopt_codegen.spec.plant import _PlantReader
from tvopt_codegen.spec.settings import _SettingsReader
from tvopt_codegen.spec.types import Spec, symbol, time_symbol

# Imported from here before the reader was split into modules.
__all__ = ["MAX_INDEX_COUNT", "shown", "suggestion"]

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
    "tune",
}


class _Reader(_PlantReader, _ObjectiveReader, _SettingsReader):
    """Validates one spec document; holds the source name for messages."""

    def read(self, data: Mapping[str, Any], sha256: str) -> Spec:
        """Read and check a whole spec document, section by section.

        Parameters
        ----------
        data : Mapping
            The document, as TOML reads it (or a caller's dict of the same shape).
        sha256 : str
            The hex digest of the document, recorded in the spec.

        Returns
        -------
        Spec
            Its names, numbers and parsed expressions.

        Raises
        ------
        SpecError
            At the first problem, in file order.
        """
        # The spec's sections in file order, each read and checked where the next one
        # needs it (names before expressions that use them).
        self.table(data, "", _TOP_KEYS, {"name", "system", "objective", "error_dynamics"})
        name, description = self.read_title(data)

        self.read_indices(data)
        system = self.read_system_names(data)
        parameters = self.read_parameters(data)
        signal_entries = self.named_entries(self.sub(data, "signals", "signals"), "signals")
        references_table, references = self.read_reference_names(data)
        self.check_unique(
            system.states,
            system.inputs,
            system.outputs,
            tuple(name for name, _ in parameters),
            tuple(name for name, _, _, _ in signal_entries),
            references,
        )

        param_syms = {key: symbol(key) for key, _ in parameters}
        dynamics, mechanics, output_exprs = self.read_plant(system, param_syms)

        reference_syms = {name: symbol(name) for name in references}
        nominal = self.read_nominal(references_table, references, param_syms)
        estimator = self.read_estimator(references_table) if references else None
        signals = self.read_signals(
            signal_entries, {"t": time_symbol()} | param_syms | reference_syms
        )
        objective, objective_names = self.read_objective(
            data, system.outputs, signals, reference_syms, param_syms
        )

        constraints, barrier, allow_nonconvex = self.read_constraints(data, objective_names)
        equalities = tuple(c for c in constraints if c.op == "==")
        constraints = tuple(c for c in constraints if c.op != "==")
        extension, extension_auto, extension_max_total = self.read_extension(data, system.inputs)
        poles, coefficients = self.read_error_dynamics(data)
        robust = self.read_robust(data)
        limits = self.read_limits(data, system.inputs)
        t_final, initial_state = self.read_simulation(data)
        agents, objects = self.read_figure_layout(data, system.outputs, signals, references)
        tune = self.read_tune(data, robust)
        return Spec(
            source=self.source,
            sha256=sha256,
            name=name,
            description=description,
            states=system.states,
            inputs=system.inputs,
            dynamics=tuple(dynamics),
            outputs=system.outputs,
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
            tune=tune,
        )

    def read_parameters(self, data: Mapping[str, Any]) -> tuple[tuple[str, float], ...]:
        """``[parameters]``: each name and its value, in declaration order.

        Parameters
        ----------
        data : Mapping
            The whole spec document.

        Returns
        -------
        tuple of (str, float)
            Each parameter and its value (for an indexed key, its constant expression
            evaluated at each value of the index).

        Raises
        ------
        SpecError
            When a name is not one or a value is not a finite real number.
        """
        parameters_table = self.sub(data, "parameters", "parameters")
        parameter_entries = self.named_entries(parameters_table, "parameters")
        return tuple(
            (name, self.constant(value, where, bound))
            for name, value, bound, where in parameter_entries
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
