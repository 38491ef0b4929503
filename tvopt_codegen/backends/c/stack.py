"""A static bound on the stack the generated C uses, from the C text the generator renders.

The header states it (issue 50, item 4): for each public function, the largest sum of
frames along a call path through the file's own functions. A frame counts, each in a
slot of its own (as if the compiler shared no slot and kept nothing in registers):

- every automatic variable the function declares, at any block depth (``static`` ones
  live elsewhere), arrays at their full length, a real at the precision's size, ``int``
  and ``unsigned`` at 4 bytes, ``size_t``, ``long`` and every pointer at 8 (the largest of
  the targets: the bound must hold on each), a structure at its size with natural
  alignment;
- every parameter, at the same sizes (a target that passes them in registers may spill
  them);
- :data:`FRAME_ALLOWANCE` bytes for what the compiler adds: the return address, the
  registers the function saves (on a Cortex-M4F with its FPU, up to 9 core and 16 single
  registers), spills of unnamed temporaries and alignment.

It does not count the C library's functions (``sin``, ``sqrt``, ...), which the file
calls but does not define, nor what an interrupt pushes. The text parsed is the
generator's own output (C99, one function definition after another, no macros that
declare or call), so a small scanner suffices; it is deterministic and needs no compiler.
"""

from __future__ import annotations

import ast
import itertools
import operator
import re
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING

import jinja2

if TYPE_CHECKING:
    from tvopt_codegen.backends.c.precision import Precision

#: Bytes each frame gets beyond its variables and parameters (see the module's text).
FRAME_ALLOWANCE = 128

#: Bytes of a pointer, of ``size_t`` and ``long``: the largest of the targets (LP64).
_WIDE = 8

#: The sizes of the scalar types the templates declare, but the real (set per precision).
_SCALARS = {
    "char": 1,
    "short": 2,
    "int": 4,
    "unsigned": 4,
    "long": _WIDE,
    "size_t": _WIDE,
    "ptrdiff_t": _WIDE,
    "int8_t": 1,
    "uint8_t": 1,
    "int16_t": 2,
    "uint16_t": 2,
    "int32_t": 4,
    "uint32_t": 4,
    "int64_t": 8,
    "uint64_t": 8,
}

#: Words of a declaration that are not its type's name.
_QUALIFIERS = frozenset({"const", "volatile", "register", "restrict", "signed"})

#: A token: a name, a number, an operator (no groups: ``findall`` lists the tokens).
_TOKEN = re.compile(r"[A-Za-z_]\w*|\d[\w.]*|->|\+\+|--|<<|>>|[<>=!]=|&&|\|\||\S")
_COMMENT = re.compile(r"/\*.*?\*/|//[^\n]*", re.DOTALL)
_STRING = re.compile(r'"(?:\\.|[^"\\])*"|\'(?:\\.|[^\'\\])*\'')
_DEFINE = re.compile(r"^[ \t]*#[ \t]*define[ \t]+(\w+)[ \t]+(.+?)[ \t]*$", re.MULTILINE)
_DIRECTIVE = re.compile(r"^[ \t]*#[^\n]*$", re.MULTILINE)
_STRUCT = re.compile(r"typedef\s+struct\s*\{(.*?)\}\s*(\w+)\s*;", re.DOTALL)

_BINARY: dict[type[ast.operator], Callable[[int, int], int]] = {
    ast.Add: operator.add,
    ast.Sub: operator.sub,
    ast.Mult: operator.mul,
    ast.FloorDiv: operator.floordiv,
}


@dataclass(frozen=True)
class Function:
    """One function the file defines.

    Attributes
    ----------
    name : str
        Its C name.
    public : bool
        Whether it has external linkage (not ``static``).
    frame : int
        Its frame's bound in bytes: variables, parameters and :data:`FRAME_ALLOWANCE`.
    calls : tuple of str
        The functions of the same file it calls, each once, in order of first call.
    """

    name: str
    public: bool
    frame: int
    calls: tuple[str, ...]


def _clean(text: str) -> str:
    """``text`` without comments and with every string literal emptied."""
    text = _COMMENT.sub(" ", text)
    return _STRING.sub('""', text)


def _tokens(text: str) -> list[str]:
    return _TOKEN.findall(text)


class _Sizes:
    """The size of a type or a declarator, given the file's macros and structures."""

    def __init__(self, real: int, defines: Mapping[str, str], real_names: frozenset[str]):
        self.scalars = {**_SCALARS, "double": 8, "float": 4, **dict.fromkeys(real_names, real)}
        self.defines = defines
        self.structs: dict[str, tuple[int, int]] = {}

    def constant(self, tokens: list[str]) -> int:
        """The value of an integer constant expression (an array's length)."""
        expression = " ".join(self._expand(tokens, depth=0)).replace("/", "//")
        return self._evaluate(ast.parse(expression, mode="eval").body)

    def _expand(self, tokens: list[str], depth: int) -> list[str]:
        if depth > 20:
            raise ValueError("macros nest too deep")
        out: list[str] = []
        for token in tokens:
            if token in self.defines:
                out += ["(", *self._expand(_tokens(self.defines[token]), depth + 1), ")"]
            else:
                out.append(token.rstrip("uUlL") if token[0].isdigit() else token)
        return out

    def _evaluate(self, node: ast.expr) -> int:
        if isinstance(node, ast.Constant) and isinstance(node.value, int):
            return node.value
        if isinstance(node, ast.BinOp) and type(node.op) in _BINARY:
            return _BINARY[type(node.op)](self._evaluate(node.left), self._evaluate(node.right))
        if isinstance(node, ast.UnaryOp) and isinstance(node.op, ast.USub):
            return -self._evaluate(node.operand)
        raise ValueError(f"not an integer constant: {ast.unparse(node)}")

    def type_size(self, words: list[str]) -> tuple[int, int]:
        """Size and alignment of the type named by ``words`` (qualifiers dropped)."""
        names = [w for w in words if w not in _QUALIFIERS]
        if names and names[-1] == "char" and len(names) <= 2:
            return 1, 1
        if names and names[-1] in self.structs:
            return self.structs[names[-1]]
        size = max((self.scalars[w] for w in names if w in self.scalars), default=0)
        if not size:
            raise ValueError(f"unknown type: {' '.join(words)}")
        return size, size

    def declarators(self, base: tuple[int, int], tokens: list[str]) -> list[tuple[int, int]]:
        """Size and alignment of each declarator of a declaration (after its type)."""
        sizes = []
        for part in _split(tokens, ","):
            head = part
            if "=" in part:
                # An initializer: the head ends at the first "=" unless a bracket
                # precedes it (where the general split finds the one outside).
                end = part.index("=")
                head = part[:end] if _BRACKETS.isdisjoint(part[:end]) else _split(part, "=")[0]
            size, align = (_WIDE, _WIDE) if "*" in head else base
            count = 1
            i = 0
            while i < len(head):
                if head[i] == "[":
                    end = _closing(head, i)
                    count *= self.constant(head[i + 1 : end])
                    i = end
                i += 1
            sizes.append((size * count, align))
        return sizes

    def add_struct(self, name: str, body: str) -> None:
        """Record ``typedef struct { body } name;`` at its size with natural alignment."""
        offset, widest = 0, 1
        for statement in _split(_tokens(body), ";"):
            if not statement:
                continue
            words, rest = _type_words(statement, self)
            for size, align in self.declarators(self.type_size(words), rest):
                offset = -(-offset // align) * align + size
                widest = max(widest, align)
        self.structs[name] = (-(-offset // widest) * widest, widest)


#: The tokens that open or close a bracket.
_BRACKETS = frozenset("()[]{}")


def _split(tokens: list[str], separator: str) -> list[list[str]]:
    """``tokens`` split at ``separator`` outside parentheses, brackets and braces."""
    if separator not in tokens:
        return [list(tokens)]
    # Only brackets and separators move the split: the loop visits those alone (a
    # kernel's declaration is a long expression).
    parts: list[list[str]] = []
    depth = 0
    start = 0
    for i in [i for i, t in enumerate(tokens) if t in _BRACKETS or t == separator]:
        token = tokens[i]
        if token in "([{":
            depth += 1
        elif token in ")]}":
            depth -= 1
        elif depth == 0:
            parts.append(tokens[start:i])
            start = i + 1
    parts.append(tokens[start:])
    return parts


def _closing(tokens: list[str], start: int) -> int:
    """The index of the bracket that closes the one at ``start``."""
    pairs = {"(": ")", "[": "]", "{": "}"}
    opening, closing = tokens[start], pairs[tokens[start]]
    depth = 0
    for i, token in enumerate(itertools.islice(tokens, start, None), start):
        if token == opening:
            depth += 1
        elif token == closing:
            depth -= 1
            if depth == 0:
                return i
    raise ValueError(f"unbalanced {opening}")


def _closings(tokens: list[str]) -> dict[int, int]:
    """The index of the bracket closing each one that opens, as :func:`_closing` finds it.

    One pass over the brackets alone, a stack per kind (each kind is counted apart), for
    the scan of a whole file: :func:`_closing` from each function's brace would walk its
    body token by token.
    """
    pairs = {")": "(", "]": "[", "}": "{"}
    open_at: dict[str, list[int]] = {"(": [], "[": [], "{": []}
    closings: dict[int, int] = {}
    for i in [i for i, t in enumerate(tokens) if t in _BRACKETS]:
        token = tokens[i]
        if token in open_at:
            open_at[token].append(i)
        elif open_at[pairs[token]]:
            closings[open_at[pairs[token]].pop()] = i
    return closings


def _type_words(statement: list[str], sizes: _Sizes) -> tuple[list[str], list[str]]:
    """The words naming a declaration's type, and the declarators after them."""
    i = 0
    while i < len(statement) and (
        statement[i] in _QUALIFIERS
        or statement[i] in sizes.scalars
        or statement[i] in sizes.structs
        or statement[i] in {"char", "static", "struct"}
    ):
        i += 1
    return statement[:i], statement[i:]


#: The keywords a statement that declares nothing may start with.
_STATEMENTS = frozenset(
    "return if else for while do switch case default goto break continue sizeof".split()
)


def _is_declaration(statement: list[str], sizes: _Sizes) -> bool:
    """Whether ``statement`` declares variables; an unknown type is an error, not a miss."""
    words, rest = _type_words(statement, sizes)
    names = [w for w in words if w not in _QUALIFIERS and w != "static"]
    if not names:
        # Two names in a row start only a declaration: of a type the sizes do not know.
        if (
            len(statement) > 1
            and statement[0] not in _STATEMENTS
            and statement[0].isidentifier()
            and statement[1].isidentifier()
        ):
            raise ValueError(f"unknown type: {statement[0]}")
        return False
    return bool(rest) and (rest[0] == "*" or rest[0].isidentifier())


def parse(source: str, header: str, real_size: int) -> dict[str, Function]:
    """The functions ``source`` defines, with their frames' bounds and calls.

    Parameters
    ----------
    source, header : str
        The rendered ``<name>.c`` and ``<name>.h`` (the header's macros and structures
        size the source's arrays and variables).
    real_size : int
        Bytes of the precision's real: 8 (double) or 4 (single).

    Returns
    -------
    dict of str to Function
        By name, in the order of their definitions.

    Raises
    ------
    ValueError
        For a declaration whose type or array length it cannot size.
    """
    header, source = _clean(header), _clean(source)
    defines = dict(_DEFINE.findall(header))
    defines.update(_DEFINE.findall(source))
    reals = frozenset(re.findall(r"typedef\s+(?:double|float)\s+(\w+)\s*;", header + source))
    sizes = _Sizes(real_size, defines, reals)
    for body, name in _STRUCT.findall(header + "\n" + source):
        sizes.add_struct(name, body)
    tokens = _tokens(_DIRECTIVE.sub(" ", source))
    functions: dict[str, tuple[bool, int, list[str]]] = {}
    closings = _closings(tokens)

    def closing(i: int) -> int:
        if i not in closings:
            raise ValueError(f"unbalanced {tokens[i]}")
        return closings[i]

    start = 0
    i = 0
    while i < len(tokens):
        token = tokens[i]
        if token == ";":
            start = i + 1
        elif token in "([":
            i = closing(i)
        elif token == "{":
            end = closing(i)
            signature = tokens[start:i]
            if signature and signature[-1] == ")" and "=" not in signature:
                opening = len(signature) - 1
                depth = 0
                while True:
                    depth += (signature[opening] == ")") - (signature[opening] == "(")
                    if depth == 0:
                        break
                    opening -= 1
                name = signature[opening - 1]
                frame = _frame(signature[opening + 1 : -1], tokens[i + 1 : end], sizes)
                functions[name] = ("static" not in signature[:opening], frame, tokens[i + 1 : end])
            i = end
            start = i + 1
        i += 1
    return {
        name: Function(
            name=name,
            public=public,
            frame=frame,
            calls=tuple(
                dict.fromkeys(
                    t
                    for j, t in enumerate(body[:-1])
                    if t in functions and body[j + 1] == "(" and (j == 0 or body[j - 1] != ".")
                )
            ),
        )
        for name, (public, frame, body) in functions.items()
    }


def _frame(parameters: list[str], body: list[str], sizes: _Sizes) -> int:
    """The bound of one frame: parameters, automatic variables and the allowance."""
    total = FRAME_ALLOWANCE
    if parameters != ["void"]:
        for parameter in _split(parameters, ","):
            words, rest = _type_words(parameter, sizes)
            total += sum(size for size, _ in sizes.declarators(sizes.type_size(words), rest))
    depth = 0
    start = 0
    # Only these tokens end a statement or move the depth: the loop visits those alone.
    for i in [i for i, t in enumerate(body) if t in _STATEMENT_MARKS]:
        token = body[i]
        # A statement starts after ; { or } outside parentheses (a for's header holds ;).
        if depth == 0 and token in ";{}":
            statement = body[start:i]
            scalar = _scalar_declaration(statement, sizes)
            if scalar is not None:
                total += -(-scalar // 4) * 4
            elif statement and statement[0] != "static" and _is_declaration(statement, sizes):
                words, rest = _type_words(statement, sizes)
                total += sum(
                    -(-size // 4) * 4 for size, _ in sizes.declarators(sizes.type_size(words), rest)
                )
            start = i + 1
            continue
        depth += (token == "(") - (token == ")")
    return total


#: The tokens :func:`_frame` reads: the ends of statements and parentheses.
_STATEMENT_MARKS = frozenset(";{}()")


def _scalar_declaration(statement: list[str], sizes: _Sizes) -> int | None:
    """The size of ``const <scalar type> <name> = <expression>``, one declarator; else None.

    A kernel's body is thousands of these (one per temporary): sized here from their
    first four tokens, as :func:`_is_declaration` and :meth:`_Sizes.declarators` size
    them, without reading the expression but for a comma (a second declarator).
    """
    if len(statement) < 5 or statement[0] != "const" or statement[3] != "=":
        return None
    kind, name = statement[1], statement[2]
    if (
        kind not in sizes.scalars
        or kind == "char"
        or kind in sizes.structs
        or not name.isidentifier()
        or name in _QUALIFIERS
        or name in sizes.scalars
        or name in sizes.structs
        or name in {"char", "static", "struct"}
        or "," in statement
    ):
        return None
    return sizes.scalars[kind]


def bounds(functions: Mapping[str, Function]) -> dict[str, int]:
    """Each public function's bound: its frame plus the deepest of its callees', in bytes.

    Raises
    ------
    ValueError
        When the call graph has a cycle (recursion has no static bound).
    """
    memo: dict[str, int] = {}

    def deepest(name: str, path: tuple[str, ...]) -> int:
        if name in path:
            raise ValueError(f"recursion: {' -> '.join((*path, name))}")
        if name not in memo:
            below = (deepest(callee, (*path, name)) for callee in functions[name].calls)
            memo[name] = functions[name].frame + max(below, default=0)
        return memo[name]

    return {name: deepest(name, ()) for name, f in functions.items() if f.public}


def stack_bounds(source: str, header: str, real_size: int) -> dict[str, int]:
    """The bound of every public function of a rendered C pair (:func:`parse`, :func:`bounds`)."""
    return bounds(parse(source, header, real_size))


#: The templates of the pair the header's bound is computed from.
_PAIR = ("c/controller.h.jinja", "c/controller.c.jinja")


@jinja2.pass_context
def header_bounds(context: jinja2.runtime.Context, precision: Precision) -> dict[str, int]:
    """The ``c_stack_bounds`` filter: the bounds of the pair the header being rendered heads.

    It renders the pair once more with the header's variables (``stack_pass`` set, so
    that the header's own call returns ``{}`` and does not recurse) and parses it: the
    bound is a function of the generated text alone, the same on every machine.
    """
    if context.get("stack_pass"):
        return {}
    variables = {**context.parent, "stack_pass": True}
    header, source = (
        context.environment.get_template(name).render({**variables, "template_name": name})
        for name in _PAIR
    )
    # The source reads no stack bound: this text is the file's, before its hash. The
    # renderer takes it from here instead of rendering it again (the header's is not).
    from tvopt_codegen.renderer.rendering import RENDERED  # noqa: PLC0415 - rendering now

    rendered = context.get(RENDERED)
    if isinstance(rendered, dict):
        rendered[_PAIR[1]] = source
    return stack_bounds(source, header, 4 if precision.single else 8)
