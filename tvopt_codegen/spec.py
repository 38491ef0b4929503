"""Stage 1: read a spec file, validate it, and parse its expressions.

The result, :class:`Spec`, holds names, numbers and sympy expressions; nothing in it
has been derived yet. Every problem is a :class:`~tvopt_codegen.errors.SpecError`
naming the file, the field and the problem.
"""

from __future__ import annotations

import hashlib
import math
import tomllib
from collections.abc import Mapping
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any

import sympy as sp

from tvopt_codegen.errors import SpecError
from tvopt_codegen.names import module_name_problem, name_problem
from tvopt_codegen.parse import ExpressionError, parse_expression

#: Largest spec file accepted, in bytes.
MAX_SPEC_BYTES = 1_000_000
#: Most integrators one input may be prolonged by.
MAX_INTEGRATORS = 8

#: Appended to a bundled example's file name where messages name the spec.
BUNDLED_SUFFIX = " (bundled example)"

#: The symbol for time in every expression.
TIME = sp.Symbol("t", real=True)


def symbol(name: str) -> sp.Symbol:
    """Return the sympy symbol that stands for a declared name (always real)."""
    return sp.Symbol(name, real=True)


@dataclass(frozen=True)
class Spec:
    """A validated spec: names, numbers and parsed expressions.

    Attributes
    ----------
    source : str
        How the spec was named (a path, or ``<name> (bundled example)``).
    sha256 : str
        SHA-256 of the spec file's bytes; stamped into every generated file.
    name, description : str
        Module name and free text.
    states, inputs, outputs : tuple of str
        Declared names, in declaration order.
    dynamics : tuple of sympy.Expr
        Right-hand side of each state equation, in state order.
    output_exprs : tuple of sympy.Expr
        Each output as an expression in the states and parameters.
    parameters : tuple of (str, float)
        Parameter names and default values.
    signals : tuple of (str, sympy.Expr)
        Time signals as explicit expressions in ``t`` and the parameters (references
        to earlier signals already substituted).
    objective : sympy.Expr
        ``f0`` in the output symbols, signal symbols, parameters and ``t``.
    extension : tuple of (str, int)
        Inputs to prolong and their number of integrators, in input order.
    poles : tuple of complex, or None
        Requested eigenvalues of the error dynamics (conjugates included).
    coefficients : tuple of float, or None
        Requested ``a_0 ... a_{k-1}`` of the companion matrix.
    t_final : float
        Simulation horizon.
    initial_state : tuple of (str, float)
        Initial values by state name, as written.
    agents : tuple of (str, str)
        Output pairs drawn as planar paths (default: consecutive output pairs).
    objects : tuple of (str, str)
        Signal pairs drawn as moving objects in the planar figure.
    extension_auto : bool
        Search the dynamic extension instead of taking ``extension``.
    extension_max_total : int or None
        Largest total number of integrators the search tries (default: the number of
        plant states).
    """

    source: str
    sha256: str
    name: str
    description: str
    states: tuple[str, ...]
    inputs: tuple[str, ...]
    dynamics: tuple[sp.Expr, ...]
    outputs: tuple[str, ...]
    output_exprs: tuple[sp.Expr, ...]
    parameters: tuple[tuple[str, float], ...]
    signals: tuple[tuple[str, sp.Expr], ...]
    objective: sp.Expr
    extension: tuple[tuple[str, int], ...]
    poles: tuple[complex, ...] | None
    coefficients: tuple[float, ...] | None
    t_final: float
    initial_state: tuple[tuple[str, float], ...]
    agents: tuple[tuple[str, str], ...] = ()
    objects: tuple[tuple[str, str], ...] = ()
    extension_auto: bool = False
    extension_max_total: int | None = None


_TOP_KEYS = {
    "name",
    "description",
    "system",
    "extension",
    "parameters",
    "signals",
    "objective",
    "error_dynamics",
    "simulation",
}


def bundled_examples() -> dict[str, str]:
    """Return the bundled example specs: name -> first line of the description."""
    found: dict[str, str] = {}
    for entry in sorted(resources.files("tvopt_codegen.examples").iterdir(), key=lambda e: e.name):
        if entry.name.endswith(".toml"):
            data = tomllib.loads(entry.read_text(encoding="utf-8"))
            found[entry.name[: -len(".toml")]] = str(data.get("description", "")).splitlines()[0]
    return found


def read_spec_bytes(spec: str | Path) -> tuple[str, bytes]:
    """Find a spec by path or bundled-example name and return (display name, bytes).

    Parameters
    ----------
    spec : str or pathlib.Path
        A path to a TOML file, or the name of a bundled example.

    Returns
    -------
    tuple of (str, bytes)
        The name to use in messages and the raw file content.

    Raises
    ------
    SpecError
        When neither a readable file nor a bundled example of that name exists.
    """
    path = Path(spec)
    if path.suffix.lower() in {".yaml", ".yml"}:
        raise SpecError(
            str(spec),
            "(file)",
            "YAML specs are not supported (YAML 1.1 reads no as "
            "false and 1e-3 as a string); write the spec in TOML",
        )
    if path.is_file():
        size = path.stat().st_size
        if size > MAX_SPEC_BYTES:
            raise SpecError(
                str(spec), "(file)", f"file is {size} bytes; the limit is {MAX_SPEC_BYTES}"
            )
        try:
            return str(spec), path.read_bytes()
        except OSError as exc:
            raise SpecError(str(spec), "(file)", f"cannot read: {exc.strerror}") from None
    if path.exists():
        raise SpecError(str(spec), "(file)", "not a regular file")
    name = str(spec)
    examples = resources.files("tvopt_codegen.examples")
    candidate = examples / f"{name}.toml"
    if name.isidentifier() and candidate.is_file():
        return f"{name}.toml{BUNDLED_SUFFIX}", candidate.read_bytes()
    known = ", ".join(bundled_examples())
    raise SpecError(
        str(spec), "(file)", f"no such file, and no bundled example of that name ({known})"
    )


def load_spec(spec: str | Path) -> Spec:
    """Read, validate and parse a spec file.

    Parameters
    ----------
    spec : str or pathlib.Path
        A path to a TOML spec, or the name of a bundled example
        (see :func:`bundled_examples`).

    Returns
    -------
    Spec
        The validated spec.

    Raises
    ------
    SpecError
        For any problem, naming the file, the field and the problem.
    """
    source, raw = read_spec_bytes(spec)
    return parse_spec(source, raw)


def parse_spec(source: str, raw: bytes) -> Spec:
    """Validate and parse spec bytes; ``source`` names them in messages.

    Parameters
    ----------
    source : str
        Display name of the spec, used in every error message.
    raw : bytes
        The file content (UTF-8 TOML).

    Returns
    -------
    Spec
        The validated spec.
    """
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise SpecError(source, "(file)", f"not UTF-8 text (byte {exc.start})") from None
    if "\x00" in text:
        raise SpecError(source, "(file)", "binary file (contains NUL bytes)")
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise SpecError(source, "(file)", f"TOML syntax error: {exc}") from None
    return _Reader(source).read(data, hashlib.sha256(raw).hexdigest())


class _Reader:
    """Validates one spec document; holds the source name for messages."""

    def __init__(self, source: str) -> None:
        self.source = source

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
                    f"{field}.{key}" if field else key, f"unknown key (expected one of: {hint})"
                )
        for key in sorted(required):
            if key not in data:
                raise self.fail(f"{field}.{key}" if field else key, "missing required key")

    def sub(self, data: Mapping[str, Any], key: str, field: str) -> dict[str, Any]:
        value = data.get(key, {})
        if not isinstance(value, dict):
            raise self.fail(field, f"expected a table, got {type(value).__name__}")
        return value

    def number(self, value: object, field: str) -> float:
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise self.fail(field, f"expected a number, got {type(value).__name__} {value!r}")
        result = float(value)
        if not math.isfinite(result):
            raise self.fail(field, "expected a finite number")
        return result

    def name_list(self, value: object, field: str) -> tuple[str, ...]:
        if not isinstance(value, list) or not value:
            raise self.fail(field, "expected a non-empty list of names")
        for index, item in enumerate(value):
            problem = name_problem(item)
            if problem:
                raise self.fail(f"{field}[{index}]", problem)
        return tuple(value)

    def expression(self, text: object, field: str, names: Mapping[str, sp.Expr]) -> sp.Expr:
        if not isinstance(text, str):
            raise self.fail(field, f"expected an expression string, got {type(text).__name__}")
        try:
            return parse_expression(text, names)
        except ExpressionError as exc:
            raise self.fail(field, str(exc)) from None

    def read(self, data: Mapping[str, Any], sha256: str) -> Spec:
        self.table(data, "", _TOP_KEYS, {"name", "system", "objective", "error_dynamics"})
        name = data["name"]
        problem = module_name_problem(name)
        if problem:
            raise self.fail("name", problem)
        description = data.get("description", "")
        if not isinstance(description, str):
            raise self.fail("description", "expected a string")
        if len(description) > 4000:
            raise self.fail("description", "longer than 4000 characters")

        system = self.sub(data, "system", "system")
        self.table(
            system,
            "system",
            {"states", "inputs", "dynamics", "outputs"},
            {"states", "inputs", "dynamics", "outputs"},
        )
        states = self.name_list(system["states"], "system.states")
        inputs = self.name_list(system["inputs"], "system.inputs")
        outputs_table = self.sub(system, "outputs", "system.outputs")
        if not outputs_table:
            raise self.fail("system.outputs", "declare at least one output")
        outputs = tuple(outputs_table)
        for out in outputs:
            problem = name_problem(out)
            if problem:
                raise self.fail(f"system.outputs.{out}", problem)
        parameters_table = self.sub(data, "parameters", "parameters")
        parameters = tuple(
            (key, self.number(value, f"parameters.{key}"))
            for key, value in parameters_table.items()
        )
        for key, _ in parameters:
            problem = name_problem(key)
            if problem:
                raise self.fail(f"parameters.{key}", problem)
        signals_table = self.sub(data, "signals", "signals")
        for key in signals_table:
            problem = name_problem(key)
            if problem:
                raise self.fail(f"signals.{key}", problem)
        self.check_unique(states, inputs, outputs, parameters_table, signals_table)

        param_syms = {key: symbol(key) for key, _ in parameters}
        plant_names: dict[str, sp.Expr] = {n: symbol(n) for n in (*states, *inputs)} | param_syms
        dynamics_table = self.sub(system, "dynamics", "system.dynamics")
        for key in dynamics_table:
            if key not in states:
                raise self.fail(f"system.dynamics.{key}", "not a declared state")
        dynamics = []
        for state in states:
            if state not in dynamics_table:
                raise self.fail(
                    f"system.dynamics.{state}", "missing right-hand side for this state"
                )
            dynamics.append(
                self.expression(dynamics_table[state], f"system.dynamics.{state}", plant_names)
            )
        state_names: dict[str, sp.Expr] = {n: symbol(n) for n in states} | param_syms
        output_exprs = tuple(
            self.expression(outputs_table[o], f"system.outputs.{o}", state_names) for o in outputs
        )

        signal_names: dict[str, sp.Expr] = {"t": TIME} | param_syms
        signals: list[tuple[str, sp.Expr]] = []
        for key, text in signals_table.items():
            expr = self.expression(text, f"signals.{key}", signal_names)
            signals.append((key, expr))
            # Later signals may use earlier ones; they see the explicit expression so
            # every signal is a function of t and the parameters alone.
            signal_names[key] = expr

        objective_table = self.sub(data, "objective", "objective")
        self.table(objective_table, "objective", {"f0"}, {"f0"})
        objective_names: dict[str, sp.Expr] = (
            {"t": TIME}
            | param_syms
            | {o: symbol(o) for o in outputs}
            | {key: symbol(key) for key, _ in signals}
        )
        objective = self.expression(objective_table["f0"], "objective.f0", objective_names)

        extension, extension_auto, extension_max_total = self.read_extension(data, inputs)
        poles, coefficients = self.read_error_dynamics(data)
        t_final, initial_state = self.read_simulation(data)
        simulation = data.get("simulation", {})
        agents = self.pairs(simulation, "agents", set(outputs), "output")
        if not agents and len(outputs) % 2 == 0:
            agents = tuple((outputs[i], outputs[i + 1]) for i in range(0, len(outputs), 2))
        objects = self.pairs(simulation, "objects", set(signals_table), "signal")
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
        )

    def check_unique(
        self,
        states: tuple[str, ...],
        inputs: tuple[str, ...],
        outputs: tuple[str, ...],
        parameters: Mapping[str, Any],
        signals: Mapping[str, Any],
    ) -> None:
        """Every name is declared once across all five kinds (case-insensitively)."""
        seen: dict[str, str] = {}
        groups = [
            ("system.states", states),
            ("system.inputs", inputs),
            ("system.outputs", outputs),
            ("parameters", tuple(parameters)),
            ("signals", tuple(signals)),
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

    def read_extension(
        self, data: Mapping[str, Any], inputs: tuple[str, ...]
    ) -> tuple[tuple[tuple[str, int], ...], bool, int | None]:
        table = self.sub(data, "extension", "extension")
        self.table(table, "extension", {"integrate", "auto", "max_total"}, set())
        auto = table.get("auto", False)
        if not isinstance(auto, bool):
            raise self.fail("extension.auto", f"expected true or false, got {auto!r}")
        max_total = table.get("max_total")
        if max_total is not None:
            if not auto:
                raise self.fail("extension.max_total", "only meaningful with auto = true")
            if (
                isinstance(max_total, bool)
                or not isinstance(max_total, int)
                or not (1 <= max_total <= 3 * MAX_INTEGRATORS)
            ):
                raise self.fail(
                    "extension.max_total", f"expected a whole number 1..{3 * MAX_INTEGRATORS}"
                )
        if auto and "integrate" in table:
            raise self.fail("extension", "give either integrate or auto = true, not both")
        integrate = self.sub(table, "integrate", "extension.integrate")
        for key, count in integrate.items():
            field = f"extension.integrate.{key}"
            if key not in inputs:
                raise self.fail(field, "not a declared input")
            if isinstance(count, bool) or not isinstance(count, int):
                raise self.fail(field, f"expected a whole number of integrators, got {count!r}")
            if not 0 <= count <= MAX_INTEGRATORS:
                raise self.fail(field, f"number of integrators must be 0..{MAX_INTEGRATORS}")
        counts = tuple((u, integrate[u]) for u in inputs if integrate.get(u, 0) > 0)
        return counts, auto, max_total

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
            if not (isinstance(pair, list) and len(pair) == 2):
                raise self.fail(f"{field}[{index}]", "expected a pair [x, y] of names")
            for name in pair:
                if name not in known:
                    raise self.fail(f"{field}[{index}]", f"{name!r} is not a declared {kind}")
            result.append((pair[0], pair[1]))
        return tuple(result)

    def read_simulation(
        self, data: Mapping[str, Any]
    ) -> tuple[float, tuple[tuple[str, float], ...]]:
        table = self.sub(data, "simulation", "simulation")
        self.table(table, "simulation", {"t_final", "initial_state", "agents", "objects"}, set())
        t_final = self.number(table.get("t_final", 10.0), "simulation.t_final")
        if t_final <= 0:
            raise self.fail("simulation.t_final", "must be positive")
        initial = self.sub(table, "initial_state", "simulation.initial_state")
        return t_final, tuple(
            (key, self.number(value, f"simulation.initial_state.{key}"))
            for key, value in initial.items()
        )
