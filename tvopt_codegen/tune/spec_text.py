"""The tuned spec as text: the user's file with only the tuned values changed.

``tune`` writes its result as a new spec that a user reads beside the old one, so
everything it did not tune stays byte for byte as the user wrote it: comments, order,
layout, the other tables, the description. A small scanner finds the spans of the tuned
values (``error_dynamics.poles`` or ``coefficients``, ``robust.observer.bandwidth``,
``robust.eso.bandwidth``) wherever TOML lets them be written: under their table's
header, as dotted keys, or inside inline tables. Only those spans are replaced, and the
result is read back with ``tomllib`` and compared with the original: the changed keys
must hold exactly the requested values and every other key must be unchanged, or
nothing is returned.
"""

from __future__ import annotations

import math
import tomllib
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

from tvopt_codegen.errors import SpecError, one_line
from tvopt_codegen.spec.toml_shape import escaped, skip_string

#: Where each tuned value lives in the spec.
POLES = ("error_dynamics", "poles")
COEFFICIENTS = ("error_dynamics", "coefficients")
OBSERVER_BANDWIDTH = ("robust", "observer", "bandwidth")
ESO_BANDWIDTH = ("robust", "eso", "bandwidth")

#: A real pole, or a conjugate pair ``(re, im)`` with ``im > 0``, as the spec writes them.
PoleItem = float | tuple[float, float]

_SPACE = " \t"
_BARE_KEY = frozenset("ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789_-")
#: Marks the tables of an array of tables, whose keys no tuned value can be.
_ARRAY_TABLE = "\x00[[]]"


class _Layout(Exception):  # noqa: N818 - an internal signal, reported as a SpecError
    """The scanner met text it does not follow (the caller says which value it wanted)."""


@dataclass
class _Value:
    """A value's span in the text; an array's items too."""

    start: int
    end: int
    kind: str  # "array", "table", "string" or "scalar"
    items: list[_Value] = field(default_factory=list)


@dataclass(frozen=True)
class _Entry:
    """A key and its value: the full dotted path, the last key part's span, the value."""

    path: tuple[str, ...]
    key_start: int
    key_end: int
    value: _Value


class _Scanner:
    """Finds every key's value span in a TOML document that ``tomllib`` has accepted.

    It knows what it needs to stay in step: headers, dotted and quoted keys, strings of
    the four kinds, arrays over several lines with comments, inline tables. Anything
    else is :class:`_Layout`; nothing it finds is trusted without the read-back check.
    """

    def __init__(self, text: str) -> None:
        self.text = text
        self.pos = 0
        self.entries: dict[tuple[str, ...], _Entry] = {}

    def document(self) -> dict[tuple[str, ...], _Entry]:
        """Every key-value pair of the document, by its full dotted path."""
        table: tuple[str, ...] = ()
        while True:
            self.skip_blank(newlines=True)
            if self.pos >= len(self.text):
                return self.entries
            if self.text[self.pos] == "[":
                table = self.header()
            else:
                self.pair(table)
            self.end_of_line()

    def header(self) -> tuple[str, ...]:
        array = self.text.startswith("[[", self.pos)
        self.pos += 2 if array else 1
        self.skip_blank()
        keys = self.key()
        self.skip_blank()
        close = "]]" if array else "]"
        if not self.text.startswith(close, self.pos):
            raise _Layout(f"a table header without {close!r}")
        self.pos += len(close)
        path = tuple(name for name, _, _ in keys)
        return (*path, _ARRAY_TABLE) if array else path

    def pair(self, table: tuple[str, ...] | None) -> None:
        """``key = value``; recorded under ``table`` (None: inside an array, unrecorded)."""
        keys = self.key()
        self.skip_blank()
        if not self.text.startswith("=", self.pos):
            raise _Layout("a key without '='")
        self.pos += 1
        self.skip_blank()
        path = None if table is None else (*table, *(name for name, _, _ in keys))
        value = self.value(path)
        if path is not None:
            _, key_start, key_end = keys[-1]
            self.entries[path] = _Entry(path, key_start, key_end, value)

    def key(self) -> list[tuple[str, int, int]]:
        """A dotted key's parts: each name and its span (quotes included)."""
        parts = []
        while True:
            start = self.pos
            quote = self.text[start : start + 1]
            if quote in ("'", '"'):
                end = self.text.find(quote, start + 1)
                while quote == '"' and end > 0 and escaped(self.text, end):
                    end = self.text.find(quote, end + 1)
                if end < 0 or "\n" in self.text[start:end]:
                    raise _Layout("an unterminated quoted key")
                self.pos = end + 1
                raw = self.text[start : self.pos]
                # tomllib decodes the quoted key's escapes, as it did for the document.
                name = str(tomllib.loads(f"k = {raw}")["k"]) if quote == '"' else raw[1:-1]
            else:
                while self.pos < len(self.text) and self.text[self.pos] in _BARE_KEY:
                    self.pos += 1
                if self.pos == start:
                    raise _Layout("a key that is not a bare or quoted name")
                name = self.text[start : self.pos]
            parts.append((name, start, self.pos))
            self.skip_blank()
            if not self.text.startswith(".", self.pos):
                return parts
            self.pos += 1
            self.skip_blank()

    def value(self, path: tuple[str, ...] | None) -> _Value:
        start = self.pos
        ch = self.text[start : start + 1]
        if ch in ("'", '"'):
            self.pos = skip_string(self.text, start)[0]
            return _Value(start, self.pos, "string")
        if ch == "[":
            self.pos += 1
            items = []
            while True:
                self.skip_blank(newlines=True, comments=True)
                if self.text.startswith("]", self.pos):
                    break
                items.append(self.value(None))
                self.skip_blank(newlines=True, comments=True)
                if self.text.startswith(",", self.pos):
                    self.pos += 1
                elif not self.text.startswith("]", self.pos):
                    raise _Layout("an array item followed by neither ',' nor ']'")
            self.pos += 1
            return _Value(start, self.pos, "array", items)
        if ch == "{":
            self.pos += 1
            self.skip_blank()
            while not self.text.startswith("}", self.pos):
                self.pair(path)
                self.skip_blank()
                if self.text.startswith(",", self.pos):
                    self.pos += 1
                    self.skip_blank()
                elif not self.text.startswith("}", self.pos):
                    raise _Layout("an inline table's entry followed by neither ',' nor '}'")
            self.pos += 1
            return _Value(start, self.pos, "table")
        end = start
        while end < len(self.text) and self.text[end] not in ",]}#\r\n":
            end += 1
        while end > start and self.text[end - 1] in _SPACE:
            end -= 1
        if end == start:
            raise _Layout("a key without a value")
        self.pos = end
        return _Value(start, end, "scalar")

    def skip_blank(self, *, newlines: bool = False, comments: bool = False) -> None:
        """Skip spaces and tabs (and line ends; and comments: ``newlines`` implies them)."""
        text = self.text
        while self.pos < len(text):
            ch = text[self.pos]
            if ch in _SPACE or (newlines and ch in "\r\n"):
                self.pos += 1
            elif ch == "#" and (newlines or comments):
                end = text.find("\n", self.pos)
                self.pos = len(text) if end < 0 else end
            else:
                return

    def end_of_line(self) -> None:
        self.skip_blank()
        if self.text.startswith("#", self.pos):
            end = self.text.find("\n", self.pos)
            self.pos = len(self.text) if end < 0 else end
        if self.pos < len(self.text) and self.text[self.pos] not in "\r\n":
            raise _Layout("more than one key or header on a line")


def pole_items(poles: Sequence[complex]) -> list[PoleItem]:
    """The spec's spelling of ``poles``: each real pole, and each conjugate pair once.

    Parameters
    ----------
    poles : sequence of complex
        As :attr:`tvopt_codegen.spec.Spec.poles` holds them: every complex pole with its
        conjugate (exactly equal); a pair is written where its first member stands.

    Returns
    -------
    list of float or (float, float)
        A real pole as a float, a pair as ``(re, im)`` with ``im > 0``.

    Raises
    ------
    ValueError
        For no poles, a pole that is not finite, or a complex pole without its conjugate
        (a tuner's bug: the spec cannot say it).
    """
    values = [complex(p) for p in poles]
    if not values:
        raise ValueError("no poles to write")
    items: list[PoleItem] = []
    used = [False] * len(values)
    for i, pole in enumerate(values):
        if used[i]:
            continue
        used[i] = True
        if not (math.isfinite(pole.real) and math.isfinite(pole.imag)):
            raise ValueError(f"pole {pole} is not finite")
        if pole.imag == 0:
            items.append(pole.real)
            continue
        partner = next(
            (j for j in range(i + 1, len(values)) if not used[j] and values[j] == pole.conjugate()),
            None,
        )
        if partner is None:
            raise ValueError(f"pole {pole} has no conjugate among the poles")
        used[partner] = True
        items.append((pole.real, abs(pole.imag)))
    return items


def _number(value: float) -> str:
    """The shortest text that reads back as exactly ``value`` (TOML takes Python's repr)."""
    return repr(float(value))


def _item_text(item: PoleItem) -> str:
    if isinstance(item, tuple):
        return f"[{_number(item[0])}, {_number(item[1])}]"
    return _number(item)


def poles_text(items: Sequence[PoleItem]) -> str:
    """``[-1.2, -3.4, [-2.0, 1.5]]``: the poles as one TOML array."""
    return "[" + ", ".join(_item_text(item) for item in items) + "]"


def _pole_edits(
    entries: dict[tuple[str, ...], _Entry], items: list[PoleItem], source: str
) -> list[tuple[int, int, str]]:
    """The replacements that make ``error_dynamics`` say ``poles = items``."""
    entry = entries.get(POLES) or entries.get(COEFFICIENTS)
    if entry is None:
        raise SpecError(
            source,
            "error_dynamics.poles",
            "cannot be rewritten in place: neither error_dynamics.poles nor "
            "error_dynamics.coefficients was found",
        )
    old = entry.value
    if entry.path == POLES and old.kind == "array" and _same_shape(old.items, items):
        # Item by item: the array's own layout (one pole a line, comments) is kept.
        edits = []
        for value, item in zip(old.items, items, strict=True):
            if isinstance(item, tuple):
                re_value, im_value = value.items
                edits.append((re_value.start, re_value.end, _number(item[0])))
                edits.append((im_value.start, im_value.end, _number(item[1])))
            else:
                edits.append((value.start, value.end, _number(item)))
        return edits
    edits = [(old.start, old.end, poles_text(items))]
    if entry.path == COEFFICIENTS:
        edits.append((entry.key_start, entry.key_end, "poles"))
    return edits


def _same_shape(values: list[_Value], items: list[PoleItem]) -> bool:
    """Whether each old item is written as the new one is (a number, or a pair of numbers)."""
    if len(values) != len(items):
        return False
    for value, item in zip(values, items, strict=True):
        if isinstance(item, tuple):
            pair = value.kind == "array" and len(value.items) == 2
            if not (pair and all(v.kind == "scalar" for v in value.items)):
                return False
        elif value.kind != "scalar":
            return False
    return True


def _bandwidth_edit(
    entries: dict[tuple[str, ...], _Entry], path: tuple[str, ...], value: float, source: str
) -> tuple[int, int, str]:
    where = ".".join(path)
    if not (math.isfinite(value) and value > 0):
        raise ValueError(f"{where} = {value!r} is not a positive bandwidth")
    entry = entries.get(path)
    if entry is None:
        raise SpecError(source, where, "cannot be rewritten in place: the spec does not set it")
    if entry.value.kind != "scalar":
        raise SpecError(source, where, "cannot be rewritten in place: it is not a number")
    return entry.value.start, entry.value.end, _number(value)


def _header_text(header: Sequence[str], newline: str) -> str:
    """Each header line as a TOML comment; control characters escaped, never a line break."""
    lines = []
    for entry in header:
        for part in entry.split("\n"):
            shown = one_line(part.removesuffix("\r"))
            lines.append(f"# {shown}".rstrip() + newline)
    return "".join(lines)


def _set(data: dict[str, Any], path: tuple[str, ...], value: object) -> None:
    for key in path[:-1]:
        data = data[key]
    data[path[-1]] = value


def _difference(old: object, new: object, path: str = "") -> str | None:
    """The dotted path of the first value that differs (types too), or None."""
    if isinstance(old, dict) or isinstance(new, dict):
        if not (isinstance(old, dict) and isinstance(new, dict)):
            return path or "(file)"
        if old.keys() != new.keys():
            key = next(iter(old.keys() ^ new.keys()))
            return f"{path}.{key}" if path else key
        for key in old:
            found = _difference(old[key], new[key], f"{path}.{key}" if path else key)
            if found is not None:
                return found
        return None
    if isinstance(old, list) or isinstance(new, list):
        if not (isinstance(old, list) and isinstance(new, list)) or len(old) != len(new):
            return path
        for index, (a, b) in enumerate(zip(old, new, strict=True)):
            found = _difference(a, b, f"{path}[{index}]")
            if found is not None:
                return found
        return None
    if type(old) is not type(new):
        return path
    if isinstance(old, float) and isinstance(new, float) and math.isnan(old) and math.isnan(new):
        return None
    return None if old == new else path


def tuned_text(
    text: str,
    source: str,
    *,
    poles: Sequence[complex] | None,
    bandwidth: float | None = None,
    eso_bandwidth: float | None = None,
    header: Sequence[str] = (),
) -> str:
    """The spec ``text`` with the tuned values in place and nothing else changed.

    Parameters
    ----------
    text : str
        The user's spec, as read from its file.
    source : str
        How errors name the spec (its path).
    poles : sequence of complex or None
        The error dynamics' poles, conjugates included (see :func:`pole_items`); written as
        ``poles = [...]`` in place of the spec's ``poles`` or ``coefficients``. None: left
        as the spec has them.
    bandwidth : float or None
        ``robust.observer.bandwidth``, rad/s (None: unchanged).
    eso_bandwidth : float or None
        ``robust.eso.bandwidth``, rad/s (None: unchanged).
    header : sequence of str
        Lines put at the very top as TOML comments (``tuned by tvopt-codegen tune ...``).

    Returns
    -------
    str
        The new spec: outside the replaced values and the header, byte for byte ``text``.
        A ``poles`` array keeps its layout (lines, comments) when it has as many items,
        of the same kinds, as the new one; otherwise it becomes one line.

    Raises
    ------
    SpecError
        When ``text`` is not TOML, a value to change is not in the spec or is laid out
        where the scanner does not follow it (``cannot be rewritten in place: ...``), or
        the result would not read back as the original with exactly these changes.
    ValueError
        For values no spec can hold: no poles, a pole or bandwidth that is not finite, a
        complex pole without its conjugate, a bandwidth that is not positive.
    """
    try:
        original = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise SpecError(source, "(file)", f"TOML syntax error: {exc}") from None
    items = None if poles is None else pole_items(poles)
    bandwidths = [
        (path, float(value))
        for path, value in ((OBSERVER_BANDWIDTH, bandwidth), (ESO_BANDWIDTH, eso_bandwidth))
        if value is not None
    ]
    # The field an unreadable layout is reported under: the first value asked for.
    first = ".".join(POLES if items is not None or not bandwidths else bandwidths[0][0])
    try:
        entries = _Scanner(text).document()
    except _Layout as exc:
        raise SpecError(source, first, f"cannot be rewritten in place: {exc}") from None

    edits = [] if items is None else _pole_edits(entries, items, source)
    edits += [_bandwidth_edit(entries, path, value, source) for path, value in bandwidths]
    result = text
    for start, end, replacement in sorted(edits, reverse=True):
        result = result[:start] + replacement + result[end:]
    result = _header_text(header, "\r\n" if "\r\n" in text else "\n") + result

    # Read back: exactly the requested changes, and nothing else.
    expected = original
    for path, value in bandwidths:
        _set(expected, path, value)
    if items is not None:
        _set(expected, POLES, [list(i) if isinstance(i, tuple) else i for i in items])
    if items is not None and POLES not in entries:
        del expected["error_dynamics"]["coefficients"]
    try:
        written = tomllib.loads(result)
    except tomllib.TOMLDecodeError as exc:
        raise SpecError(
            source, first, f"cannot be rewritten in place: the result is not TOML ({exc})"
        ) from None
    wrong = _difference(expected, written)
    if wrong is not None:
        raise SpecError(
            source,
            wrong,
            "cannot be rewritten in place: the rewritten spec would say something else here",
        )
    return result
