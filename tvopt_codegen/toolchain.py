"""The system C compiler, as the FMU export and the sweep's compiled loop find it."""

from __future__ import annotations

import os
import shutil
import subprocess

from tvopt_codegen.errors import BuildError

#: Flags of every shared library tvopt-codegen builds itself (the generated C wrapper
#: uses the same ones, printed into it).
CFLAGS = ("-O2", "-std=c99", "-fPIC", "-shared")


def compiler() -> str:
    """``$CC``, else the first of cc, gcc and clang on the PATH.

    Raises
    ------
    BuildError
        When ``$CC`` names no program, or none of them is installed.
    """
    explicit = os.environ.get("CC")
    if explicit:
        found = shutil.which(explicit)
        if found is None:
            raise BuildError(f"the C compiler CC={explicit!r} was not found")
        return found
    for candidate in ("cc", "gcc", "clang"):
        found = shutil.which(candidate)
        if found:
            return found
    raise BuildError("no C compiler found (tried $CC, cc, gcc, clang): install gcc or clang")


def version(cc: str) -> str:
    """What ``cc --version`` says (part of every build's cache key)."""
    return subprocess.run([cc, "--version"], capture_output=True, text=True, check=False).stdout
