"""Stage 6: write output files. The only module of tvopt-codegen that writes.

Every file is written atomically (a temporary file in the same folder, flushed and
then renamed over the target), so a reader or a crash sees the old file or the new
one, never half of one. A set of files is published as one transaction: all
temporaries are written first, a journal names them, and the renames run with SIGINT
and SIGTERM held back, so Ctrl-C cannot leave old and new files mixed. A process
killed outright during the renames leaves its journal; the next run into the folder
finds it (its process is gone) and completes the renames, and removes temporaries no
journal claims. Nothing a person wrote is overwritten silently: a file is
replaced only if tvopt-codegen wrote it and nobody changed it since, which is known
from the file's own stamp (generated code carries a content hash) or from the
folder's manifest ``.tvopt-manifest.json`` (SHA-256 of every file the tool wrote
there). ``force=True`` overrides both.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import re
import signal
import stat
import subprocess
import sys
import tempfile
import threading
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path
from typing import Any

import jinja2
import jinja2.bccache

from tvopt_codegen.errors import OutputError
from tvopt_codegen.stamp import is_pristine, stamped_hash, stamped_spec

#: Name of the per-folder record of what tvopt-codegen wrote.
MANIFEST = ".tvopt-manifest.json"
#: Journals of publications in progress: ``.tvopt-journal-<pid>-<random>.json``.
JOURNAL_PREFIX = ".tvopt-journal-"
_TEMP_SUFFIX = ".tvopt-tmp"
_BLOCKED = {signal.SIGINT, signal.SIGTERM}

Content = str | bytes


def _bytes(content: Content) -> bytes:
    return content.encode("utf-8") if isinstance(content, str) else content


def _digest(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


#: Largest manifest or journal read (each names a few dozen files).
_MAX_RECORD_BYTES = 4_000_000
#: Largest file recovery reads to tell whether the tool wrote it.
_MAX_OWN_FILE_BYTES = 256_000_000


def read_regular_file(path: Path, limit: int) -> bytes | None:
    """The content of ``path`` if it is a regular file of at most ``limit`` bytes.

    Anything else (missing, a folder, a symbolic link, a FIFO or device, which could
    block a read forever, or a larger file) gives ``None``; memory stays bounded by
    ``limit`` whatever the file's size.
    """
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK)
    except OSError:
        return None
    try:
        info = os.fstat(fd)
        if not stat.S_ISREG(info.st_mode) or info.st_size > limit:
            return None
        chunks, total = [], 0
        while total <= limit:
            chunk = os.read(fd, min(1 << 20, limit + 1 - total))
            if not chunk:
                break
            chunks.append(chunk)
            total += len(chunk)
        return None if total > limit else b"".join(chunks)
    except OSError:
        return None
    finally:
        os.close(fd)


def read_own_output(folder: str | Path, name: str, limit: int) -> bytes | None:
    """A file this tool wrote into ``folder`` and nobody changed since, else ``None``.

    The folder's manifest vouches for the file's SHA-256; a file it does not name,
    one edited since, or one larger than ``limit`` bytes is not read (beyond
    ``limit``).
    """
    folder = Path(folder)
    expected = _read_manifest(folder).get(name)
    if expected is None:
        return None
    data = read_regular_file(folder / name, limit)
    if data is None or _digest(data) != expected:
        return None
    return data


def _read_manifest(folder: Path) -> dict[str, str]:
    raw = read_regular_file(folder / MANIFEST, _MAX_RECORD_BYTES)
    if raw is None:
        return {}
    try:
        data = json.loads(raw.decode("utf-8"))
    except ValueError:
        return {}
    if not isinstance(data, dict):
        return {}
    return {str(k): str(v) for k, v in data.items()}


def _written_by_tool(path: Path, manifest: Mapping[str, str], current: bytes | None = None) -> bool:
    """Whether tvopt-codegen wrote ``path`` and nobody changed it since.

    The folder's manifest vouches for its SHA-256, or it is pristine generated text (its
    stamp's hash holds). ``current`` is its content when already read; otherwise the
    digest is taken in blocks (a sweep's table may be gigabytes) and the text read within
    a bound.
    """
    digest = _digest(current) if current is not None else _file_digest(path)
    if manifest.get(path.name) == digest:
        return True
    text = current if current is not None else read_regular_file(path, _MAX_OWN_FILE_BYTES)
    try:
        return text is not None and is_pristine(text.decode("utf-8"))
    except UnicodeDecodeError:
        return False


def _not_ours(path: Path) -> OutputError:
    return OutputError(
        f"{path}: was edited by hand or not written by tvopt-codegen; refusing to overwrite "
        "it (use --force to replace it)"
    )


def _may_replace(path: Path, data: bytes, manifest: Mapping[str, str], force: bool) -> bool:
    """Decide whether ``path`` may be (re)written; False when it already holds ``data``."""
    if path.is_symlink():
        raise OutputError(f"{path}: is a symbolic link; refusing to write through it")
    if not path.exists():
        return True
    if not path.is_file():
        raise OutputError(f"{path}: exists and is not a regular file")
    try:
        current = path.read_bytes()
    except OSError as exc:
        raise OutputError(f"{path}: exists and cannot be read: {exc.strerror}") from None
    if current == data:
        return False
    if force:
        return True
    with contextlib.suppress(UnicodeDecodeError):
        _refuse_another_specs_file(path, current.decode("utf-8"), data)
    if _written_by_tool(path, manifest, current):
        return True
    raise _not_ours(path)


def _refuse_another_specs_file(path: Path, current: str, data: bytes) -> None:
    """Raise when ``path`` was generated for one spec and ``data`` is another spec's file.

    Two specs whose file names meet in one folder must not replace each other's
    files, however pristine: the user would lose a controller without a word.
    """
    owner = stamped_spec(current)
    if owner is None:
        return
    try:
        incoming = stamped_spec(data.decode("utf-8"))
    except UnicodeDecodeError:
        incoming = None
    if incoming != owner:
        raise OutputError(
            f"{path}: was generated for spec '{owner}', not for "
            f"{f'spec {incoming!r}' if incoming else 'this run'}; refusing to replace "
            "another spec's file (rename a spec, choose another --out, or use --force)"
        )


def prepare_folder(out_dir: str | Path, create: bool = True) -> Path:
    """Check (and create, one level deep) an output folder; write nothing else.

    With ``create=False`` only check that it could be used: a command that may still
    fail (a simulation) checks first and creates nothing until it writes.
    """
    folder = Path(out_dir)
    if folder.is_symlink():
        raise OutputError(
            f"{folder}: output folder is a symbolic link; refusing to write through it"
        )
    if folder.exists() and not folder.is_dir():
        raise OutputError(f"{folder}: output path exists and is not a folder")
    if not folder.exists():
        parent = folder.parent
        if not parent.is_dir():
            raise OutputError(f"{folder}: output folder's parent {parent} does not exist")
        if not create:
            return folder
        try:
            folder.mkdir()
        except FileExistsError:
            # Another run created it between our check and mkdir; that is
            # fine as long as it is a real folder: each run renames whole files
            # into place, so two runs never mix their output.
            if folder.is_symlink() or not folder.is_dir():
                raise OutputError(
                    f"{folder}: output path appeared concurrently and is not a folder"
                ) from None
        except OSError as exc:
            raise OutputError(f"{folder}: cannot create output folder: {exc.strerror}") from None
    return folder


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


#: The tool's temporaries: ``.<target>.<pid>-<random>.tvopt-tmp`` (tempfile's names).
_TEMP_NAME = re.compile(r"\.(?P<target>[^/\\]+)\.(?P<pid>\d+)-[A-Za-z0-9_]+\.tvopt-tmp")


def _may_recover(folder: Path, temp: str, target: str, manifest: Mapping[str, str]) -> str:
    """Why the journal's rename ``temp -> target`` must not run ("" when it may).

    A journal is only a file in the folder: anyone able to put one there must not be
    able to move or replace a user's file through it. So only the tool's own
    temporaries (by name, regular files) are renamed, only to a plain name in the
    folder, and only over a file the tool wrote that nobody changed since.
    """
    found = _TEMP_NAME.fullmatch(temp)
    if found is None or found.group("target") != target:
        return f"{temp!r} is not a temporary of tvopt-codegen for {target!r}"
    if Path(target).name != target or target in {".", ".."}:
        return f"target {target!r} is not a plain file name in the folder"
    try:
        info = os.lstat(folder / temp)
    except FileNotFoundError:
        return ""  # renamed already (by the dead run or a concurrent one): nothing to do
    if not stat.S_ISREG(info.st_mode):
        return f"{temp!r} is not a regular file"
    path = folder / target
    if path.is_symlink() or (path.exists() and not path.is_file()):
        return f"{target!r} is not a regular file"
    if path.exists():
        current = read_regular_file(path, _MAX_OWN_FILE_BYTES)
        if current is None:
            return f"{target!r} could not be read"
        if target != MANIFEST and not _written_by_tool(path, manifest, current):
            return f"{target!r} was changed since tvopt-codegen wrote it"
    return ""


def recover(folder: Path, warn: Callable[[str], None] | None = None) -> None:
    """Finish publications of processes that died mid-way; drop orphaned temporaries.

    Parameters
    ----------
    folder : pathlib.Path
        The output folder.
    warn : callable, optional
        Told, one line each, of journal entries left alone (see :func:`_may_recover`);
        by default they are printed on stderr.
    """
    report = warn or _print_warning
    claimed: set[str] = set()
    manifest = _read_manifest(folder)
    for journal in sorted(folder.glob(f"{JOURNAL_PREFIX}*.json")):
        raw = read_regular_file(journal, _MAX_RECORD_BYTES)
        if raw is None:
            continue
        try:
            record = json.loads(raw.decode("utf-8"))
            pid = int(record["pid"])
            pairs = [(str(a), str(b)) for a, b in record["renames"]]
        except (OSError, ValueError, KeyError, TypeError):
            continue
        if _alive(pid) and pid != os.getpid():
            claimed.update(a for a, _ in pairs)
            continue  # still publishing: leave it alone
        for temp, target in pairs:
            problem = _may_recover(folder, temp, target, manifest)
            if problem:
                report(f"{folder}: left alone while finishing {journal.name}: {problem}")
                continue
            # Another run may be finishing the same journal right now.
            with contextlib.suppress(FileNotFoundError):
                os.replace(folder / temp, folder / target)
        with contextlib.suppress(FileNotFoundError):
            journal.unlink()
    for orphan in folder.glob(f".*{_TEMP_SUFFIX}"):
        if orphan.name in claimed or _TEMP_NAME.fullmatch(orphan.name) is None:
            continue
        # Temporaries are named .<target>.<pid>-<random>.tvopt-tmp: keep a live writer's.
        owner = orphan.name[: -len(_TEMP_SUFFIX)].rsplit(".", 1)[-1].split("-")[0]
        if owner.isdigit() and int(owner) != os.getpid() and _alive(int(owner)):
            continue
        if orphan.is_symlink() or not orphan.is_file():
            continue
        with contextlib.suppress(FileNotFoundError):
            orphan.unlink()


def _print_warning(message: str) -> None:
    print(f"tvopt-codegen: warning: {message}", file=sys.stderr)


@contextlib.contextmanager
def _signals_held() -> Iterator[None]:
    """Hold back SIGINT and SIGTERM (delivered right after) around the renames."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.pthread_sigmask(signal.SIG_BLOCK, _BLOCKED)
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, previous)


def write_files(
    files: Mapping[str, Content], out_dir: str | Path, force: bool = False
) -> list[Path]:
    """Write output files into ``out_dir`` as one transaction.

    All targets are checked before anything is written, so a refusal leaves the
    folder untouched; then every file is written to a temporary, and the temporaries
    are renamed over the targets together (see the module docstring).

    Parameters
    ----------
    files : mapping of str to str or bytes
        File name (relative to ``out_dir``, no folders) to content; text is UTF-8.
    out_dir : str or pathlib.Path
        The output folder; created if missing when its parent exists.
    force : bool
        Replace files that were edited by hand or not written by this tool.

    Returns
    -------
    list of pathlib.Path
        The files written (files already identical are not rewritten).

    Raises
    ------
    OutputError
        When the folder cannot be used or a file may not be replaced.
    """
    for name in files:
        if Path(name).name != name or name in {"", ".", "..", MANIFEST} or name.startswith("."):
            raise OutputError(f"{name!r}: not a plain file name")
    folder = prepare_folder(out_dir)
    try:
        recover(folder)
    except OSError as exc:
        raise OutputError(f"{folder}: cannot repair an interrupted earlier write: {exc}") from None
    manifest = _read_manifest(folder)
    pending = []
    for name, content in files.items():
        data = _bytes(content)
        if _may_replace(folder / name, data, manifest, force):
            pending.append((folder / name, data))
    if not pending:
        return []
    # Stamped files vouch for themselves; only the others need the manifest.
    unstamped = {t.name: _digest(d) for t, d in pending if not _is_stamped(d)}
    if unstamped:
        manifest.update(unstamped)
        record = json.dumps(dict(sorted(manifest.items())), indent=1) + "\n"
        pending.append((folder / MANIFEST, record.encode("utf-8")))
    temps: list[tuple[Path, Path]] = []
    try:
        for target, data in pending:
            temps.append((_write_temp(target, data), target))
        journal = folder / f"{JOURNAL_PREFIX}{os.getpid()}-{os.urandom(4).hex()}.json"
        _write_exact(
            journal,
            json.dumps(
                {"pid": os.getpid(), "renames": [[t.name, g.name] for t, g in temps]}
            ).encode(),
        )
        with _signals_held():
            for temp, target in temps:
                os.replace(temp, target)
            _sync_folder(folder)
            journal.unlink()
    except OSError as exc:
        for temp, _ in temps:
            with contextlib.suppress(FileNotFoundError):
                temp.unlink()
        raise OutputError(f"{folder}: cannot write: {exc.strerror or exc}") from None
    except BaseException:
        for temp, _ in temps:
            with contextlib.suppress(FileNotFoundError):
                temp.unlink()
        raise
    return [target for target, _ in pending if target.name != MANIFEST]


def _is_stamped(data: bytes) -> bool:
    try:
        return stamped_hash(data.decode("utf-8")) is not None
    except UnicodeDecodeError:
        return False


def _write_temp(target: Path, data: bytes) -> Path:
    """Write ``data`` to a new temporary file beside ``target`` (flushed to disk)."""
    return _produce_temp(target, lambda handle: handle.write(data))


def _produce_temp(target: Path, produce: Callable[[Any], object]) -> Path:
    """A new temporary beside ``target`` that ``produce`` writes into (flushed to disk).

    Named ``.<target>.<pid>-<random>.tvopt-tmp``, so that :func:`recover` knows it; it is
    removed if ``produce`` or the disk fails.
    """
    fd, name = tempfile.mkstemp(
        prefix=f".{target.name}.{os.getpid()}-", suffix=_TEMP_SUFFIX, dir=target.parent
    )
    try:
        with os.fdopen(fd, "wb") as handle:
            produce(handle)
            handle.flush()
            os.fsync(handle.fileno())
        os.chmod(name, 0o644)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(name)
        raise
    return Path(name)


def _write_exact(path: Path, data: bytes) -> None:
    """Write a small file in full, atomically (the journal)."""
    os.replace(_write_temp(path, data), path)


def _sync_folder(folder: Path) -> None:
    """Flush the folder's entries so the renames survive a power cut."""
    with contextlib.suppress(OSError):
        fd = os.open(folder, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


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
    from tvopt_codegen.toolchain import CFLAGS, compiler, version  # noqa: PLC0415

    cc = compiler()
    key = hashlib.sha256()
    for part in (
        cc,
        version(cc),
        "\0".join(CFLAGS),
        *(f"{n}\0{t}" for n, t in sorted(sources.items())),
    ):
        key.update(hashlib.sha256(part.encode("utf-8")).digest())
    cache = cache_folder()
    stem = Path(main).stem
    library = cache / f"{stem}-{key.hexdigest()[:24]}.so"
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


class TrajectoryStore:
    """A Zarr store written block by block as a sweep's samples finish.

    A crash keeps every block written before it. The store is created whole (every
    array at full size, filled with NaN) so that xarray reads it at any moment.

    Parameters
    ----------
    path : str or pathlib.Path
        The store's folder; it must not exist.
    variables : mapping of str to (tuple of str, tuple of int, tuple of int)
        Each array's dimension names, shape and chunks.
    coords : mapping of str to numpy.ndarray
        Coordinate arrays (one dimension each, named like it).
    attrs : mapping
        The store's attributes (JSON-ready).
    resume : bool
        Open the store an interrupted sweep created (the same arrays) to fill the rest.

    Raises
    ------
    MissingExtraError
        Without zarr.
    OutputError
        When ``path`` exists (or, to resume, does not hold these arrays) or cannot be
        created.
    """

    def __init__(
        self,
        path: str | Path,
        variables: Mapping[str, tuple[tuple[str, ...], tuple[int, ...], tuple[int, ...]]],
        coords: Mapping[str, Any],
        attrs: Mapping[str, Any],
        resume: bool = False,
    ) -> None:
        try:
            import zarr  # noqa: PLC0415
        except ImportError:
            from tvopt_codegen.errors import MissingExtraError  # noqa: PLC0415

            raise MissingExtraError(
                "--trajectories needs zarr: pip install 'tvopt-codegen[sweep]'"
            ) from None
        target = Path(path)
        if resume:
            self._arrays = self._reopen(zarr, target, variables)
            return
        if target.exists() or target.is_symlink():
            raise OutputError(f"{target}: already exists; refusing to replace a trajectory store")
        try:
            group = zarr.open_group(str(target), mode="w-")
            for name, values in coords.items():
                # Text as zarr's variable-length strings (fixed-width UTF-32 has no v3 spec).
                kind = str if values.dtype.kind == "U" else values.dtype
                array = group.create_array(
                    name, shape=values.shape, dtype=kind, dimension_names=(name,)
                )
                array[:] = values
            self._arrays = {
                name: group.create_array(
                    name,
                    shape=shape,
                    chunks=chunks,
                    dtype="f8",
                    fill_value=float("nan"),
                    dimension_names=dims,
                )
                for name, (dims, shape, chunks) in variables.items()
            }
            group.attrs.update(dict(attrs))
        except OSError as exc:
            raise OutputError(f"{target}: cannot create the trajectory store: {exc}") from None

    @staticmethod
    def _reopen(
        zarr: Any,
        target: Path,
        variables: Mapping[str, tuple[tuple[str, ...], tuple[int, ...], tuple[int, ...]]],
    ) -> dict[str, Any]:
        if target.is_symlink() or not target.is_dir():
            raise OutputError(f"{target}: the interrupted sweep's trajectory store is missing")
        try:
            group = zarr.open_group(str(target), mode="r+")
            arrays = {name: group[name] for name in variables}
        except (OSError, KeyError, ValueError) as exc:
            raise OutputError(f"{target}: cannot reopen the trajectory store: {exc}") from None
        for name, (_dims, shape, _chunks) in variables.items():
            if tuple(arrays[name].shape) != tuple(shape):
                raise OutputError(f"{target}: {name} is not this sweep's array (its shape)")
        return arrays

    def write(self, start: int, values: Mapping[str, Any]) -> None:
        """Store a block of samples beginning at sample ``start`` (first axis).

        Raises
        ------
        OutputError
            The disk refused the write (full): the blocks written before stay.
        """
        try:
            for name, block in values.items():
                self._arrays[name][start : start + len(block)] = block
        except OSError as exc:
            raise OutputError(
                f"cannot write the trajectories: {exc.strerror or exc}; the finished samples "
                "are kept: make room, then `tvopt-codegen sweep --resume` on the folder"
            ) from None


def _file_digest(path: Path) -> str | None:
    """SHA-256 of a regular file, read in blocks (a sweep's table may be gigabytes)."""
    digest = hashlib.sha256()
    try:
        with open(path, "rb") as handle:
            while block := handle.read(1 << 20):
                digest.update(block)
    except OSError:
        return None
    return digest.hexdigest()


def check_replaceable(out_dir: str | Path, names: Iterator[str] | list[str], force: bool) -> None:
    """Raise unless every file ``names`` in ``out_dir`` may be (re)written by this tool.

    The rule of :func:`write_files`, asked before the content exists: a command that
    runs for hours (a sweep) refuses a user's file at its start, not at its end. A file
    may be replaced when it is absent, when the manifest vouches for it, or when it is
    pristine generated text; ``force`` allows any regular file.
    """
    folder = Path(out_dir)
    if not folder.is_dir():
        return
    manifest = _read_manifest(folder)
    for name in names:
        path = folder / name
        if path.is_symlink():
            raise OutputError(f"{path}: is a symbolic link; refusing to write through it")
        if not path.exists():
            continue
        if not path.is_file():
            raise OutputError(f"{path}: exists and is not a regular file")
        if not force and not _written_by_tool(path, manifest):
            raise _not_ours(path)


def write_stream(
    out_dir: str | Path, name: str, produce: Callable[[Any], object], force: bool = False
) -> Path:
    """Write one file that is too large to hold in memory, atomically.

    ``produce`` writes the content to the binary file handle it is given (a temporary
    beside the target); the temporary is flushed and renamed over ``name`` only when
    ``produce`` returns, and the manifest records the file's SHA-256.

    Raises
    ------
    OutputError
        When the target may not be replaced (see :func:`check_replaceable`) or the disk
        refuses the write (full, read-only).
    """
    folder = prepare_folder(out_dir)
    check_replaceable(folder, [name], force)
    target = folder / name
    temp: Path | None = None
    try:
        temp = _produce_temp(target, produce)
        digest = _file_digest(temp)
        manifest = _read_manifest(folder)
        manifest[name] = str(digest)
        record = json.dumps(dict(sorted(manifest.items())), indent=1) + "\n"
        with _signals_held():
            os.replace(temp, target)
            _write_exact(folder / MANIFEST, record.encode("utf-8"))
            _sync_folder(folder)
    except OSError as exc:
        if temp is not None:
            with contextlib.suppress(FileNotFoundError):
                temp.unlink()
        raise OutputError(f"{target}: cannot write: {exc.strerror or exc}") from None
    except BaseException:
        if temp is not None:
            with contextlib.suppress(FileNotFoundError):
                temp.unlink()
        raise
    return target


class SweepFolder:
    """A sweep's output folder while the sweep runs: locked, its rows kept as they finish.

    Finished samples go to ``parts/`` (each part a whole file, published by rename), so
    that a sweep killed by any signal leaves whole files that ``sweep --resume`` reads.
    A lock (``flock`` on ``.tvopt-sweep.lock``, released by the kernel when the process
    dies, even by SIGKILL) keeps a second sweep out of the folder while one runs.

    Parameters
    ----------
    out_dir : str or pathlib.Path
        The folder; created (one level deep) when missing.
    names : list of str
        The files the sweep will write there: each must be replaceable
        (:func:`check_replaceable`) before the first sample runs.
    force : bool
        Replace files not written by this tool.

    Raises
    ------
    OutputError
        The folder cannot be created or written, another sweep holds it, or a file the
        sweep would write belongs to the user.
    """

    LOCK = ".tvopt-sweep.lock"
    PARTS = "parts"
    _PART = re.compile(r"part-\d{8}-\d+\.parquet")

    def __init__(self, out_dir: str | Path, names: list[str], force: bool) -> None:
        folder = Path(out_dir)
        self.created = not folder.exists() and not folder.is_symlink()
        self.folder = prepare_folder(folder)
        self._lock: int | None = None
        try:
            self._lock = os.open(
                self.folder / self.LOCK, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW, 0o644
            )
        except OSError as exc:
            self._abandon()
            raise OutputError(
                f"{self.folder}: cannot write in the output folder: {exc.strerror or exc}"
            ) from None
        import fcntl  # noqa: PLC0415 - POSIX only, like the signals the sweep keeps

        try:
            fcntl.flock(self._lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(self._lock)
            self._lock = None
            raise OutputError(
                f"{self.folder}: another sweep is writing to this folder; wait for it, or "
                "choose another --out"
            ) from None
        try:
            check_replaceable(self.folder, names, force)
            parts = self.folder / self.PARTS
            if parts.is_symlink() or (parts.exists() and not parts.is_dir()):
                raise OutputError(f"{parts}: exists and is not the sweep's folder of parts")
        except BaseException:
            self.close(failed=True)
            raise
        self._sequence = len(self.parts())

    def parts(self) -> list[Path]:
        """The parts written so far (by this run or an interrupted one), by name."""
        where = self.folder / self.PARTS
        if not where.is_dir():
            return []
        return sorted(p for p in where.iterdir() if self._PART.fullmatch(p.name) and p.is_file())

    def write_part(self, produce: Callable[[Any], object]) -> Path:
        """Publish one part: ``produce`` writes it to a temporary, renamed when whole.

        Raises
        ------
        OutputError
            The disk refused the write (full, read-only); the parts already written stay.
        """
        where = self.folder / self.PARTS
        try:
            where.mkdir(exist_ok=True)
            self._sequence += 1
            target = where / f"part-{self._sequence:08d}-{os.getpid()}.parquet"
            temp = _produce_temp(target, produce)
            try:
                os.replace(temp, target)
                _sync_folder(where)
            except BaseException:
                with contextlib.suppress(FileNotFoundError):
                    temp.unlink()
                raise
        except OSError as exc:
            raise OutputError(
                f"{where}: cannot write the finished samples: {exc.strerror or exc}; those "
                f"written so far are kept: make room, then `tvopt-codegen sweep --resume "
                f"{self.folder}`"
            ) from None
        return target

    def clear_parts(self) -> None:
        """Remove the parts (the table holds them all now) and their folder if empty."""
        where = self.folder / self.PARTS
        for part in self.parts():
            with contextlib.suppress(FileNotFoundError):
                part.unlink()
        if where.is_dir():
            for orphan in where.glob(f".part-*{_TEMP_SUFFIX}"):
                with contextlib.suppress(FileNotFoundError):
                    orphan.unlink()
            with contextlib.suppress(OSError):
                where.rmdir()

    def _abandon(self) -> None:
        """Remove the folder if this run created it and nothing is in it."""
        if self.created:
            with contextlib.suppress(OSError):
                self.folder.rmdir()

    def close(self, failed: bool = False) -> None:
        """Release the lock; after a failure, leave no empty folder behind."""
        if self._lock is not None:
            with contextlib.suppress(FileNotFoundError):
                (self.folder / self.LOCK).unlink()
            os.close(self._lock)
            self._lock = None
        if failed:
            self._abandon()
