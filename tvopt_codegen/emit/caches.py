"""The writer's caches: compiled libraries and jinja's compiled templates.

Both live in one cache folder (``$TVOPT_CODEGEN_CACHE`` or ``~/.cache/tvopt-codegen``)
and outlast a command: :func:`cached_library` compiles C sources once per content and
compiler (the sweep's loop on every worker of a machine), :func:`kept_bytes` keeps what
another build makes under its :func:`build_key` (an FMU's library), :func:`template_cache` keeps
jinja's compiled templates (a tenth of a small command).

This is the only module of :mod:`tvopt_codegen.emit` that imports jinja2 or runs the
C compiler (through :mod:`tvopt_codegen.toolchain`), so that the transaction, which
every command that writes a file loads, needs neither; ``tests/test_architecture.py``
keeps it so. The renderer imports this module alone.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import subprocess
import tempfile
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path

import jinja2
import jinja2.bccache


def cache_folder() -> Path:
    """Where compiled libraries are kept: ``$TVOPT_CODEGEN_CACHE`` or ~/.cache/tvopt-codegen."""
    explicit = os.environ.get("TVOPT_CODEGEN_CACHE")
    return Path(explicit) if explicit else Path.home() / ".cache" / "tvopt-codegen"


class _TemplateCache(jinja2.FileSystemBytecodeCache):
    """jinja's compiled templates, kept across commands (a tenth of a small command).

    jinja names an entry by the template's file and checks the source's checksum and
    the interpreter's bytecode version on load, so an edited template, a user's own
    template folder or a new Python compiles afresh; entries are published by rename.
    """

    def dump_bytecode(self, bucket: jinja2.bccache.Bucket) -> None:
        # A cache that cannot be written (full disk, read-only home) only costs speed.
        with contextlib.suppress(OSError):
            super().dump_bytecode(bucket)


def template_cache() -> jinja2.BytecodeCache | None:
    """The bytecode cache of the templates, in :func:`cache_folder`; None if unusable."""
    folder = cache_folder() / "templates"
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError:
        return None
    return _TemplateCache(str(folder))


def build_key(parts: Iterable[str]) -> str:
    """The cache key of a build: the compiler, its version and flags, then ``parts``.

    A hex digest over each part's own digest, so that no two splits of one text collide.
    """
    from tvopt_codegen.toolchain import CFLAGS, compiler, version  # noqa: PLC0415

    cc = compiler()
    key = hashlib.sha256()
    for part in (cc, version(cc), "\0".join(CFLAGS), *parts):
        key.update(hashlib.sha256(part.encode("utf-8")).digest())
    return key.hexdigest()


def kept_bytes(name: str, build: Callable[[], bytes]) -> bytes:
    """The bytes ``build`` makes, kept in :func:`cache_folder` under ``name`` (its key).

    Read when kept; otherwise built and published by rename, so that a concurrent reader
    (another worker) sees the whole file or none. A cache that cannot be read or written
    only costs the build.
    """
    try:
        kept = cache_folder() / name
        if kept.is_file():
            return kept.read_bytes()
    except OSError:
        return build()
    data = build()
    with contextlib.suppress(OSError):
        kept.parent.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=kept.parent, prefix=".", delete=False) as handle:
            partial = Path(handle.name)
            handle.write(data)
        try:
            os.replace(partial, kept)
        finally:
            partial.unlink(missing_ok=True)
    return data


def cached_library(sources: Mapping[str, str], main: str) -> Path:
    """Compile ``main`` (with the other sources beside it) once per content and compiler.

    The library is cached under a hash of the sources, the compiler, its version and
    the flags; a concurrent build of the same key (two workers of one machine) publishes
    by rename, so a reader sees a whole library or none.

    Parameters
    ----------
    sources : mapping of str to str
        File name to text; ``main`` is the one compiled, the others are its includes.
    main : str
        The translation unit.

    Returns
    -------
    pathlib.Path
        The shared library.

    Raises
    ------
    BuildError
        Without a C compiler, when the cache folder is unusable, or when compiling fails.
    """
    from tvopt_codegen.errors import BuildError  # noqa: PLC0415
    from tvopt_codegen.toolchain import CFLAGS, compiler  # noqa: PLC0415

    cc = compiler()
    key = build_key(f"{n}\0{t}" for n, t in sorted(sources.items()))
    cache = cache_folder()
    stem = Path(main).stem
    library = cache / f"{stem}-{key[:24]}.so"
    if library.is_file():
        return library
    try:
        cache.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryDirectory(prefix=f".{stem}-", dir=cache) as folder:
            for name, text in sources.items():
                (Path(folder) / name).write_text(text, encoding="utf-8")
            partial = Path(folder) / "library.so"
            command = [
                cc,
                *CFLAGS,
                "-I",
                folder,
                "-o",
                str(partial),
                str(Path(folder) / main),
                "-lm",
            ]
            done = subprocess.run(command, capture_output=True, text=True, check=False)
            if done.returncode != 0:
                detail = " ".join(done.stderr.strip().splitlines()[:3]) or "(no message)"
                raise BuildError(f"compiling {main} with {cc} failed: {detail}")
            os.replace(partial, library)
    except OSError as exc:
        raise BuildError(
            f"the cache folder {cache} cannot be used ({exc.strerror or exc}); set "
            "TVOPT_CODEGEN_CACHE to a writable folder"
        ) from None
    return library
