"""The system C compiler, as the FMU export and the sweep's compiled loop find it."""

from __future__ import annotations

import functools
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
    """What ``cc --version`` says (part of every build's cache key).

    Asked once per compiler binary and process: a library already in the cache costs no
    process. The binary's identity (inode, size, modification time) is part of the
    memo's key, so a compiler replaced while the process runs is asked again.
    """
    try:
        status = os.stat(cc)
    except OSError:
        # Nothing to identify: ask every time, as the compiler's absence will be reported.
        return _ask(cc)
    return _version(cc, status.st_ino, status.st_size, status.st_mtime_ns)


@functools.lru_cache(maxsize=16)
def _version(cc: str, inode: int, size: int, modified: int) -> str:
    return _ask(cc)


def _ask(cc: str) -> str:
    return subprocess.run([cc, "--version"], capture_output=True, text=True, check=False).stdout
