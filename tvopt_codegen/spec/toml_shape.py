"""Bounds on the shape of a TOML document, checked before ``tomllib`` reads it.

``tomllib`` recurses once per nested array or inline table (a 5000-deep array exhausts
the stack) and its cost grows with the square of a dotted key's length (a 60 KB key
``a.a.a...`` takes gigabytes). No spec needs more than a few levels, so one linear
pass over the text refuses deeper documents at once, with the line they are on.
"""

from __future__ import annotations

#: Most arrays and inline tables open inside one another.
MAX_NESTING = 32
#: Most parts of one key (``a.b.c`` has three) or table header.
MAX_KEY_PARTS = 32


class ShapeError(ValueError):
    """The document nests deeper than the limits; ``line`` is 1-based."""

    def __init__(self, line: int, problem: str) -> None:
        super().__init__(f"line {line}: {problem}")
        self.line = line
        self.problem = problem


def check_shape(text: str) -> None:
    """Raise :class:`ShapeError` when ``text`` nests deeper than the limits.

    The scan knows just enough TOML to tell keys from values: strings (basic,
    literal and their multi-line forms, with escapes), comments, table headers, the
    keys at the start of a line and inside inline tables, arrays and inline tables.
    It never rejects a document ``tomllib`` would accept within the limits; whatever
    is malformed is left for ``tomllib`` to report.

    Parameters
    ----------
    text : str
        The document.

    Raises
    ------
    ShapeError
        On the first array or inline table deeper than :data:`MAX_NESTING`, or the
        first key or header with more than :data:`MAX_KEY_PARTS` parts.
    """
    stack: list[str] = []  # open '[' (array) and '{' (inline table)
    line = 1
    i, n = 0, len(text)
    in_key = True  # at the start of a line: a key, a header or a comment follows
    parts = 1
    while i < n:
        ch = text[i]
        if ch == "\n":
            line += 1
            if not stack:
                in_key, parts = True, 1
            i += 1
        elif ch == "#":
            end = text.find("\n", i)
            i = n if end < 0 else end
        elif ch in "\"'":
            i, line = skip_string(text, i, line)
        elif in_key and ch == ".":
            parts += 1
            if parts > MAX_KEY_PARTS:
                raise ShapeError(line, f"a key has more than {MAX_KEY_PARTS} dotted parts")
            i += 1
        elif in_key and ch == "=":
            in_key = False
            i += 1
        elif ch == "[" and in_key and not stack:
            # A table header: its key continues to the closing bracket(s).
            end = i + 2 if text.startswith("[[", i) else i + 1
            i = end
        elif ch == "]" and in_key and not stack:
            in_key = False
            i += 2 if text.startswith("]]", i) else 1
        elif ch in "[{":
            stack.append(ch)
            if len(stack) > MAX_NESTING:
                raise ShapeError(
                    line, f"arrays and inline tables nest deeper than {MAX_NESTING} levels"
                )
            if ch == "{":
                in_key, parts = True, 1
            i += 1
        elif ch in "]}":
            if stack:
                stack.pop()
            in_key = False
            i += 1
        elif ch == "," and stack and stack[-1] == "{":
            in_key, parts = True, 1
            i += 1
        else:
            i += 1


def skip_string(text: str, i: int, line: int = 0) -> tuple[int, int]:
    """Index after the string starting at ``i``, and the line it ends on.

    Basic, literal or either multi-line; an unterminated one ends at the end of its line
    (or of the text) and is tomllib's to report. ``tune``'s spec writer finds strings so.
    """
    quote = text[i]
    if text.startswith(quote * 3, i):
        end = i + 3
        while True:
            found = text.find(quote * 3, end)
            if found < 0:
                return len(text), line + text.count("\n", i)
            if quote == '"' and escaped(text, found):
                end = found + 1
                continue
            # Up to two more quotes may belong to the string ("""a""""" ends after 5).
            stop = found + 3
            while stop < len(text) and text[stop] == quote and stop - found < 5:
                stop += 1
            return stop, line + text.count("\n", i, stop)
    end = i + 1
    while end < len(text):
        ch = text[end]
        if ch == "\n":
            return end, line  # unterminated: tomllib reports it
        if ch == "\\" and quote == '"':
            end += 2
            continue
        if ch == quote:
            return end + 1, line
        end += 1
    return end, line


def escaped(text: str, index: int) -> bool:
    """Whether the character at ``index`` follows an odd run of backslashes."""
    count = 0
    while index - count - 1 >= 0 and text[index - count - 1] == "\\":
        count += 1
    return count % 2 == 1
