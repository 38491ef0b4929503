"""The fixed run-time Python of a generated controller, as real modules.

Every module here holds Python that a generated file carries unchanged: the input
checks, the solves, the stateful controller's numerics. Each is linted and type-checked
like the rest of the package, and the templates copy its text (``{{ "arguments" |
verbatim("convert") }}``) instead of carrying a copy of their own, so that a generated
file stays one self-contained module that imports nothing from tvopt-codegen (users run
it without the tool installed).

A module's copied text is everything below its :data:`MARKER` line, cut into named
pieces by :data:`SECTION` lines where the pieces land in different places of the
generated file. Above the marker a module imports what it needs to be checked on its own:
what the generated file defines around the copied text comes from
:mod:`~tvopt_codegen.backends.python.runtime.provided`, typed placeholders that are
never copied.
"""

from __future__ import annotations

import functools
from pathlib import Path

#: The line above which a module is not copied (its imports and placeholders).
MARKER = "# --- copied verbatim into the generated controller below this line ---"
#: A line that starts a named piece of the copied text: ``# --- section: <name> ---``.
SECTION = "# --- section: "

#: Every module with copied text (``provided`` has none: it stands in for the rest of
#: the generated file).
MODULES = (
    "errors",
    "statuses",
    "arguments",
    "domain",
    "linalg",
    "blocks",
    "chains",
    "limits",
    "controller",
    "estimator",
    "differentiator_linear",
    "differentiator_levant",
    "eso",
    "evaluators",
)


class RuntimeSourceError(LookupError):
    """A template asked for a module or section that does not exist (a bug here)."""


@functools.cache
def sections(module: str) -> dict[str | None, str]:
    """The copied pieces of ``module``: by section name, or under None when it has none.

    Each piece loses its leading and trailing blank lines and its final newline: the
    template places it on a line of its own and spaces it from its neighbours.
    """
    if module not in MODULES:
        raise RuntimeSourceError(f"no run-time module {module!r}; known: {', '.join(MODULES)}")
    text = Path(__file__).with_name(f"{module}.py").read_text(encoding="utf-8")
    head, found, body = text.partition(MARKER + "\n")
    if not found:
        raise RuntimeSourceError(f"run-time module {module!r} has no marker line {MARKER!r}")
    pieces: dict[str | None, list[str]] = {None: []}
    current: str | None = None
    for line in body.splitlines():
        if line.startswith(SECTION) and line.endswith(" ---"):
            current = line.removeprefix(SECTION).removesuffix(" ---")
            if current in pieces:
                raise RuntimeSourceError(f"section {current!r} twice in {module!r}")
            pieces[current] = []
        else:
            pieces[current].append(line)
    out = {name: "\n".join(lines).strip("\n") for name, lines in pieces.items()}
    if len(out) > 1:
        if out.pop(None):
            raise RuntimeSourceError(f"text before the first section of {module!r}")
    return out


def verbatim(module: str, section: str | None = None) -> str:
    """The copied text of ``module`` (of its ``section``, if it has sections).

    The templates' filter: ``{{ "linalg" | verbatim("batch") }}``.
    """
    pieces = sections(module)
    if section not in pieces:
        raise RuntimeSourceError(
            f"run-time module {module!r} has no section {section!r}; "
            f"it has: {', '.join(str(name) for name in pieces)}"
        )
    return pieces[section]
