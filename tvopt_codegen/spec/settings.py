"""The spec reader's settings of the law and its run.

``[error_dynamics]`` (poles or coefficients), ``[robust]``, ``[limits]`` (ranges and
rates of the inputs), ``[simulation]`` (its horizon, initial state, and the pairs
its figures draw) and ``[tune]`` (what ``tune`` searches for; nothing else reads it).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

from tvopt_codegen import symbolic as sx
from tvopt_codegen.errors import clip
from tvopt_codegen.limits import MAX_T_FINAL
from tvopt_codegen.spec.fields import _Fields, shown
from tvopt_codegen.spec.fields import suggestion as _suggestion
from tvopt_codegen.spec.parse import indexed_name
from tvopt_codegen.spec.types import Limit, Robust, TuneSettings

#: The extended-state observer's bandwidths, rad/s: its gains go up to bandwidth^(r+1).
ESO_BANDWIDTH_RANGE = (1e-6, 1e6)


class _SettingsReader(_Fields):
    """Reads ``[error_dynamics]``, ``[robust]``, ``[limits]``, ``[simulation]`` and ``[tune]``."""

    def read_robust(self, data: Mapping[str, Any]) -> Robust:
        """``[robust]``: integral action, ``[robust.observer]`` and ``[robust.eso]``."""
        table = self.sub(data, "robust", "robust")
        self.table(table, "robust", {"integral", "observer", "eso"}, set())
        integral = self.boolean(table.get("integral", False), "robust.integral")
        bandwidth = None
        if "observer" in table:
            observer = self.sub(table, "observer", "robust.observer")
            self.table(observer, "robust.observer", {"bandwidth"}, {"bandwidth"})
            bandwidth = self.number(observer["bandwidth"], "robust.observer.bandwidth")
            if not bandwidth > 0:
                raise self.fail("robust.observer.bandwidth", "must be positive (rad/s)")
        eso = None
        if "eso" in table:
            block = self.sub(table, "eso", "robust.eso")
            self.table(block, "robust.eso", {"bandwidth"}, {"bandwidth"})
            eso = self.number(block["bandwidth"], "robust.eso.bandwidth")
            if not eso > 0:
                raise self.fail("robust.eso.bandwidth", "must be positive (rad/s)")
            low, high = ESO_BANDWIDTH_RANGE
            if not low <= eso <= high:
                # Its gains are C(r + 1, j) bandwidth^j up to j = r + 1: past these bounds
                # they leave the doubles for outputs of high relative degree.
                raise self.fail(
                    "robust.eso.bandwidth",
                    f"{eso:g} rad/s is outside [{low:g}, {high:g}]: the observer's gains "
                    "are powers of it up to the relative degree + 1",
                )
        return Robust(integral, bandwidth, eso)

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

    def read_figure_layout(
        self,
        data: Mapping[str, Any],
        outputs: tuple[str, ...],
        signals: list[tuple[str, sx.Expr]],
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

    def read_tune(self, data: Mapping[str, Any], robust: Robust) -> TuneSettings | None:
        """``[tune]``: what ``tune`` searches for, its types and simple bounds checked.

        The objective's and the constraints' grammar is ``tvopt_codegen.tune``'s: here
        they are non-empty strings. None without the table.
        """
        if "tune" not in data:
            return None
        table = self.sub(data, "tune", "tune")
        self.table(
            table,
            "tune",
            {"objective", "constraints", "after", "pole_range", "min_damping", "bandwidth_range"},
            set(),
        )
        # Each key in the order the docs list them, so the first problem is the first key's.
        objective = None
        if "objective" in table:
            objective = self.requirement(table["objective"], "tune.objective")
        constraints = table.get("constraints", [])
        if not isinstance(constraints, list):
            raise self.fail(
                "tune.constraints", f"expected a list of strings, got {shown(constraints)}"
            )
        requirements = tuple(
            self.requirement(c, f"tune.constraints[{i}]") for i, c in enumerate(constraints)
        )
        after = None
        if "after" in table:
            after = self.number(table["after"], "tune.after")
            if not after >= 0:
                raise self.fail("tune.after", f"must be a time >= 0 (seconds), got {after:g}")
        pole_range = self.positive_range(table, "pole_range")
        min_damping = None
        if "min_damping" in table:
            min_damping = self.number(table["min_damping"], "tune.min_damping")
            if not 0 < min_damping <= 1:
                raise self.fail(
                    "tune.min_damping", f"a damping ratio in (0, 1] is needed, got {min_damping:g}"
                )
        bandwidth_range = self.positive_range(table, "bandwidth_range")
        if bandwidth_range is not None and robust.observer is None and robust.eso is None:
            raise self.fail(
                "tune.bandwidth_range",
                "the spec has no [robust.observer] or [robust.eso] bandwidth to tune",
            )
        return TuneSettings(
            objective, requirements, after, pole_range, min_damping, bandwidth_range
        )

    def requirement(self, value: object, field: str) -> str:
        """A requirement as written: a string with something in it."""
        if not isinstance(value, str):
            raise self.fail(field, f"expected a string, got {shown(value)}")
        if not value.strip():
            raise self.fail(field, "expected a requirement, got an empty string")
        return value

    def positive_range(self, table: Mapping[str, Any], key: str) -> tuple[float, float] | None:
        """``tune.<key> = [lo, hi]`` with ``0 < lo < hi``, or None when not given."""
        if key not in table:
            return None
        field = f"tune.{key}"
        value = table[key]
        if not isinstance(value, list) or len(value) != 2:
            raise self.fail(field, f"expected [lo, hi], got {shown(value)}")
        low = self.number(value[0], f"{field}[0]")
        high = self.number(value[1], f"{field}[1]")
        if not 0 < low < high:
            raise self.fail(field, f"expected 0 < lo < hi, got [{low:g}, {high:g}]")
        return low, high
