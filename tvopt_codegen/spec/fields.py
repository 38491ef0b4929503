"""The ground every section of the spec reader stands on.

:class:`_Fields` holds the source name and the ``[index]`` table, and reads what every
section is made of: tables (unknown keys refused with the nearest known one), booleans,
whole and real numbers, lists of names, indexed names (``base[i]``, expanded), and
expressions, whose messages say which kinds of name a field may use. Every problem is a
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

from tvopt_codegen import symbolic as sx
from tvopt_codegen.errors import SpecError, clip
from tvopt_codegen.maths.numeric import Evaluator
from tvopt_codegen.spec.names import name_problem
from tvopt_codegen.spec.parse import (
    NO_INDEXING,
    ExpressionError,
    Indexing,
    indexed_name,
    parse_expression,
)

#: Most values one index may take.
#: The derivation's budgets (--max-seconds, --max-size), not this bound, limit how large a
#: team can be: on SymEngine a ring of 1,024 agents derives in seconds.
MAX_INDEX_COUNT = 4096


#: An indexed name in a key or a list: ``base[i]``.
_INDEXED = re.compile(r"^([A-Za-z][A-Za-z0-9_]*)\[([A-Za-z][A-Za-z0-9_]*)\]$")


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


class _Fields:
    """Reads the parts every section is made of; holds the source name for messages."""

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
        names: Mapping[str, sx.Expr],
        bound: dict[str, int] | None = None,
    ) -> sx.Expr:
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
