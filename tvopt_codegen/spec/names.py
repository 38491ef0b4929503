"""Rules for the names users give to states, inputs, outputs, parameters and signals.

User names never become identifiers in generated code (values are addressed by array
slot), but they appear in comments, docstrings, string literals and the report, and
they name the generated module. These rules keep all of that unambiguous.
"""

from __future__ import annotations

import importlib.machinery
import keyword
import os
import re
import sys

from tvopt_codegen.backends import BACKENDS
from tvopt_codegen.spec.parse import CONSTANTS, FUNCTIONS

_IDENTIFIER = re.compile(r"[A-Za-z][A-Za-z0-9_]*\Z")

#: Names the spec language reserves: ``t`` is time in every expression. (Generated code
#: addresses user values by slot, so no other name needs reserving for it.)
TOOL_NAMES = frozenset({"t"})


def name_problem(name: object) -> str | None:
    """Say why ``name`` cannot name a state, input, output, parameter or signal.

    Parameters
    ----------
    name : object
        The candidate name as read from the spec.

    Returns
    -------
    str or None
        A one-line reason, or ``None`` when the name is acceptable.
    """
    if not isinstance(name, str):
        return f"names must be strings, got {type(name).__name__}"
    if not name.isascii():
        return f"name {name!r} is not ASCII"
    if name.startswith("_"):
        return f"name {name!r} starts with an underscore (reserved for generated code)"
    if not _IDENTIFIER.match(name):
        return f"name {name!r} is not an identifier (letters, digits, '_'; starts with a letter)"
    if len(name) > 64:
        return f"name {name!r} is longer than 64 characters"
    if keyword.iskeyword(name) or keyword.issoftkeyword(name) or name in {"True", "False", "None"}:
        return f"name {name!r} is a Python keyword"
    if name in FUNCTIONS or name in CONSTANTS:
        return f"name {name!r} is a built-in function or constant of spec expressions"
    if name in TOOL_NAMES:
        return f"name {name!r} is reserved (t is time)"
    # Every registered backend's words, asked of the registry: the spec reader imports no
    # backend by name, and a backend another package registers is heard too.
    for backend in BACKENDS.values():
        for what, words in backend.reserved_as:
            if name in words:
                return f"name {name!r} is {what}"
        if name in backend.reserved:
            return f"name {name!r} is a reserved word of the {backend.name} backend"
    return None


def module_name_problem(name: object) -> str | None:
    """Say why ``name`` cannot name the generated module, or return ``None``.

    Parameters
    ----------
    name : object
        The spec's ``name`` field.

    Returns
    -------
    str or None
        A one-line reason, or ``None`` when the name is acceptable.
    """
    problem = name_problem(name)
    if problem is not None:
        return problem
    assert isinstance(name, str)
    if name != name.lower():
        return f"module name {name!r} must be lower case (it names files on every platform)"
    if name in _WINDOWS_DEVICES:
        return f"module name {name!r} is a reserved device name on Windows"
    if name in sys.stdlib_module_names or name in sys.builtin_module_names:
        return f"module name {name!r} shadows the Python standard module of that name"
    if name in _C_HEADERS:
        return (
            f"module name {name!r} would write {name}.h, which shadows the C header of that "
            "name that the generated C includes, or a header of the C standard library"
        )
    if _installed(name):
        return f"module name {name!r} shadows the installed package of that name"
    return None


#: The C standard library's headers and those the generated C and the FMU include, lower
#: case (a case-insensitive file system would take fmi2functions.h for fmi2Functions.h):
#: ``<name>.h`` beside the generated C would be found before them.
_C_HEADERS = frozenset(
    {
        "assert", "complex", "ctype", "errno", "fenv", "float", "inttypes", "iso646",
        "limits", "locale", "math", "setjmp", "signal", "stdalign", "stdarg", "stdatomic",
        "stdbool", "stddef", "stdint", "stdio", "stdlib", "stdnoreturn", "string", "tgmath",
        "threads", "time", "uchar", "wchar", "wctype", "python", "arrayobject",
        "fmi2functions", "fmi2functiontypes", "fmi2typesplatform", "fmi3functions",
        "fmi3functiontypes", "fmi3platformtypes",
    }
)  # fmt: skip


_WINDOWS_DEVICES = frozenset(
    {
        "con",
        "prn",
        "aux",
        "nul",
        *(f"com{i}" for i in range(1, 10)),
        *(f"lpt{i}" for i in range(1, 10)),
    }
)


#: The tool's own imports, installed or not (an editable install is found by its finder).
_OWN_IMPORTS = frozenset({"numpy", "scipy", "sympy", "jinja2", "tvopt_codegen"})

#: The interpreter's own finders: PathFinder is asked directly, without the working folder.
_STANDARD_FINDERS = (
    importlib.machinery.BuiltinImporter,
    importlib.machinery.FrozenImporter,
    importlib.machinery.PathFinder,
)


def _installed(name: str) -> bool:
    """Whether ``name`` imports from an installed location (not the working folder).

    Asked of the import system for this one name: the module path without the working
    folder (where a module generated earlier may sit), then any finder an installer
    added (an editable install's). Listing every installed distribution's top-level
    names instead (``importlib.metadata.packages_distributions``) reads each one's file
    list, 0.4 s of every command in an environment with the optional integrations.
    """
    if name in _OWN_IMPORTS:
        return True
    here = os.path.abspath(os.getcwd())
    paths = [p for p in sys.path if p and os.path.abspath(p) != here]
    if importlib.machinery.PathFinder.find_spec(name, paths) is not None:
        return True
    for finder in sys.meta_path:
        if finder in _STANDARD_FINDERS or not hasattr(finder, "find_spec"):
            continue
        try:
            if finder.find_spec(name, None) is not None:
                return True
        except Exception:  # noqa: BLE001 - a third-party finder's failure is not ours
            continue
    return False
