"""A spec mapping as TOML text: :func:`spec_toml`.

The text is written by hand (the standard library reads TOML but does not write it) and
checked by reading it back with :mod:`tomllib`: what :func:`spec_toml` returns is the
mapping it was given, or it raises one :class:`~tvopt_codegen.errors.SpecError`.
"""

from __future__ import annotations

import math
import re
import tomllib
from collections.abc import Mapping
from typing import Any

import numpy as np
import sympy as sp

from tvopt_codegen.errors import SpecError, clip, one_line

#: What errors of :func:`spec_toml` name as their source.
SOURCE_TOML = "spec_toml"

#: Deepest nesting of tables and lists :func:`spec_toml` writes (a spec nests four).
MAX_TOML_DEPTH = 32


def _toml_fail(field: str, problem: str) -> SpecError:
    return SpecError(SOURCE_TOML, one_line(field) or "(spec)", one_line(problem))


def _plain_data(value: object, field: str, depth: int) -> object:
    """``value`` as TOML's data: Python scalars, lists and string-keyed dicts.

    NumPy scalars and arrays become Python values and lists, SymPy integers and floats
    Python numbers; anything TOML cannot hold (None, NaN, a set, a SymPy expression) is
    one SpecError naming the key.
    """
    if depth > MAX_TOML_DEPTH:
        raise _toml_fail(field, f"nested deeper than {MAX_TOML_DEPTH} tables and lists")
    if value is None:
        raise _toml_fail(field, "None has no TOML spelling (leave the key out)")
    if isinstance(value, bool | np.bool_):
        return bool(value)
    if isinstance(value, str):
        try:
            value.encode("utf-8")
        except UnicodeEncodeError:
            raise _toml_fail(field, "the string holds a lone surrogate, not text") from None
        return str(value)
    if isinstance(value, int | np.integer) or (isinstance(value, sp.Integer)):
        number = int(value)
        if not -(2**63) <= number < 2**63:
            raise _toml_fail(field, f"the integer {number} is beyond TOML's 64 bits")
        return number
    if isinstance(value, float | np.floating) or isinstance(value, sp.Float):
        result = float(value)
        if not math.isfinite(result):
            raise _toml_fail(field, f"{result} is not a finite number")
        return result
    if isinstance(value, Mapping):
        out: dict[str, object] = {}
        for key, item in value.items():
            if not isinstance(key, str):
                raise _toml_fail(
                    field, f"keys are strings, got the {type(key).__name__} {clip(repr(key))}"
                )
            where = f"{field}.{key}" if field else str(key)
            out[str(_plain_data(key, where, depth + 1))] = _plain_data(item, where, depth + 1)
        return out
    if isinstance(value, np.ndarray):
        value = value.tolist()
    if isinstance(value, list | tuple):
        return [_plain_data(item, f"{field}[{i}]", depth + 1) for i, item in enumerate(value)]
    if isinstance(value, sp.Basic):
        raise _toml_fail(field, f"the sympy expression {clip(sp.sstr(value))}: give its text")
    raise _toml_fail(field, f"no TOML spelling for a {type(value).__name__}")


_ESCAPES = {
    '"': '\\"',
    "\\": "\\\\",
    "\b": "\\b",
    "\t": "\\t",
    "\n": "\\n",
    "\f": "\\f",
    "\r": "\\r",
}


def _string(text: str) -> str:
    """A TOML basic string in ASCII: quotes, backslashes and controls escaped."""
    out = []
    for ch in text:
        code = ord(ch)
        if ch in _ESCAPES:
            out.append(_ESCAPES[ch])
        elif code < 0x20 or 0x7F <= code <= 0xFFFF:
            out.append(f"\\u{code:04x}")
        elif code > 0xFFFF:
            out.append(f"\\U{code:08x}")
        else:
            out.append(ch)
    return '"' + "".join(out) + '"'


def _value(value: object) -> str:
    """One TOML value: a string, a number, a list or an inline table."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return _string(value)
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        return repr(value)
    if isinstance(value, Mapping):
        return "{ " + ", ".join(f"{_key(k)} = {_value(v)}" for k, v in value.items()) + " }"
    assert isinstance(value, list)
    return "[" + ", ".join(_value(v) for v in value) + "]"


_BARE_KEY = re.compile(r"[A-Za-z0-9_]+\Z")


def _key(key: str) -> str:
    return key if _BARE_KEY.match(key) else _string(key)


def spec_toml(spec: Mapping[str, Any]) -> str:
    """A spec mapping (as :func:`.spec_from_sympy` returns) as TOML text.

    Keys come in the mapping's order, plain values before tables, each table under its
    dotted header; a matrix is written one row per line. NumPy scalars and arrays are
    written as the Python numbers and lists they hold. The text, read back by
    :func:`tvopt_codegen.load_spec`, is the same spec (checked before returning).

    Raises
    ------
    SpecError
        When a value has no TOML spelling (None, NaN or infinity, a set, a SymPy
        expression, a lone surrogate), a key is not a string, an integer exceeds 64
        bits, or the mapping nests deeper than :data:`MAX_TOML_DEPTH`; one line naming
        the key.
    """
    if not isinstance(spec, Mapping):
        raise _toml_fail("", f"expected a mapping, got {type(spec).__name__}")
    data = _plain_data(spec, "", 0)
    assert isinstance(data, dict)
    lines: list[str] = []

    def table(path: str, body: Mapping[str, Any]) -> None:
        plain = [
            (k, v) for k, v in body.items() if not isinstance(v, Mapping) or path == "simulation"
        ]
        nested = [
            (k, v) for k, v in body.items() if isinstance(v, Mapping) and path != "simulation"
        ]
        if path:
            lines.extend(["", f"[{path}]"])
        for key, value in plain:
            one_line = f"{_key(key)} = {_value(value)}"
            if isinstance(value, list) and value and isinstance(value[0], list | str):
                if isinstance(value[0], str) and len(one_line) <= 100:
                    lines.append(one_line)
                    continue
                # A matrix one row per line, a long list one entry per line.
                rows = ",\n".join(f"    {_value(row)}" for row in value)
                lines.append(f"{_key(key)} = [\n{rows},\n]")
            else:
                lines.append(one_line)
        for key, value in nested:
            table(f"{path}.{_key(key)}" if path else _key(key), value)

    table("", data)
    text = "\n".join(lines).lstrip("\n") + "\n"
    try:
        same = tomllib.loads(text) == data
    except tomllib.TOMLDecodeError as exc:
        raise _toml_fail("", f"the TOML written does not parse ({exc})") from None
    if not same:
        raise _toml_fail("", "the TOML written does not read back as the mapping")
    return text
