"""The spec reader's objective: ``[references]``, ``[signals]``, ``[objective]``.

And ``[constraints]``, which are written in the same names as ``f0``: the outputs,
signals, references, parameters and ``t``.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from tvopt_codegen import symbolic as sx
from tvopt_codegen.spec.fields import _Fields, shown
from tvopt_codegen.spec.fields import suggestion as _suggestion
from tvopt_codegen.spec.names import name_problem
from tvopt_codegen.spec.parse import ExpressionError, parse_comparison
from tvopt_codegen.spec.types import (
    ESTIMATOR_KINDS,
    Barrier,
    Constraint,
    Estimator,
    symbol,
    time_symbol,
)


class _ObjectiveReader(_Fields):
    """Reads ``[references]``, ``[signals]``, ``[objective]`` and ``[constraints]``."""

    def read_reference_names(
        self, data: Mapping[str, Any]
    ) -> tuple[dict[str, Any], tuple[str, ...]]:
        """``[references]``'s keys and the names it declares.

        Parameters
        ----------
        data : Mapping
            The whole spec document.

        Returns
        -------
        table : dict
            The ``[references]`` table (empty when the spec has none).
        references : tuple of str
            The references' names, in declaration order.

        Raises
        ------
        SpecError
            When the table misses or misspells a key, or a name is not one.
        """
        references_table = self.sub(data, "references", "references")
        references: tuple[str, ...] = ()
        if "references" in data:
            self.table(references_table, "references", {"names", "nominal", "estimator"}, {"names"})
            references = self.name_list(references_table["names"], "references.names")
        return references_table, references

    def read_objective(
        self,
        data: Mapping[str, Any],
        outputs: tuple[str, ...],
        signals: list[tuple[str, sx.Expr]],
        reference_syms: dict[str, sx.Expr],
        param_syms: dict[str, sx.Expr],
    ) -> tuple[sx.Expr, dict[str, sx.Expr]]:
        """``[objective]``: ``f0``, and the names it (and every constraint) may use.

        Parameters
        ----------
        data : Mapping
            The whole spec document.
        outputs : tuple of str
            The outputs' names.
        signals : list of (str, Expr)
            The signals, as :meth:`read_signals` read them.
        reference_syms, param_syms : dict of str to Symbol
            The references' and parameters' symbols, by name.

        Returns
        -------
        objective : Expr
            ``f0``.
        names : dict of str to Expr
            ``t``, the parameters, outputs, signals and references, by name.

        Raises
        ------
        SpecError
            When ``f0`` is missing, does not parse or uses a name it may not.
        """
        objective_table = self.sub(data, "objective", "objective")
        self.table(objective_table, "objective", {"f0"}, {"f0"})
        objective_names: dict[str, sx.Expr] = (
            {"t": time_symbol()}
            | param_syms
            | {o: symbol(o) for o in outputs}
            | {key: symbol(key) for key, _ in signals}
            | reference_syms
        )
        objective = self.expression(objective_table["f0"], "objective.f0", objective_names)
        return objective, objective_names

    def read_signals(self, entries: Any, names: dict[str, sx.Expr]) -> list[tuple[str, sx.Expr]]:
        """``[signals]``, in file order; ``names`` holds t, the parameters and references."""
        signals: list[tuple[str, sx.Expr]] = []
        for key, text, bound, where in entries:
            expr = self.expression(text, where, names, bound)
            signals.append((key, expr))
            # Later signals may use earlier ones; they see the explicit expression so
            # every signal is a function of t, the parameters and the references alone.
            names[key] = expr
        return signals

    def read_constraints(
        self, data: Mapping[str, Any], names: Mapping[str, sx.Expr]
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
        param_syms: Mapping[str, sx.Expr],
    ) -> tuple[tuple[str, sx.Expr], ...]:
        """The ``nominal`` closed forms, in t and the parameters, by reference name."""
        nominal = self.sub(table, "nominal", "references.nominal") if table else {}
        names = {"t": time_symbol()} | dict(param_syms)
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
