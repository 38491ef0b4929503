"""The writer's transaction: the only way tvopt-codegen puts a file in a folder.

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

This module needs the standard library, the stamp and the error types only: no
template engine and no compiler, which live in :mod:`~tvopt_codegen.emit.caches`, so
that writing a file loads neither. It prints nothing; what recovery left alone is
returned and told to the caller's ``warn``.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import re
import signal
import stat
import tempfile
import threading
import warnings
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path
from typing import Any

from tvopt_codegen.emit.stamp import is_pristine, stamped_hash, stamped_spec
from tvopt_codegen.errors import OutputError, raise_pending_signal

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


def recover(folder: Path, warn: Callable[[str], None] | None = None) -> tuple[str, ...]:
    """Finish publications of processes that died mid-way; drop orphaned temporaries.

    Parameters
    ----------
    folder : pathlib.Path
        The output folder.
    warn : callable, optional
        Told, one line each and as they are found, of journal entries left alone (see
        :func:`_may_recover`).

    Returns
    -------
    tuple of str
        The same lines: the journal entries left alone, in the order found.
    """
    left: list[str] = []
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
                left.append(f"{folder}: left alone while finishing {journal.name}: {problem}")
                if warn is not None:
                    warn(left[-1])
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
    return tuple(left)


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


def _runtime_warning(text: str) -> None:
    """A library caller's way of hearing what a command would print as a warning."""
    warnings.warn(text, RuntimeWarning, stacklevel=4)


def write_files(
    files: Mapping[str, Content],
    out_dir: str | Path,
    force: bool = False,
    warn: Callable[[str], None] | None = None,
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
    warn : callable
        Told, one line each, of an interrupted earlier write's journal entries that
        recovery left alone (:func:`recover`). The commands pass their warning line;
        without one, each is a :class:`RuntimeWarning` (the library's callers filter or
        record them as they do any warning).

    Returns
    -------
    list of pathlib.Path
        The files written (files already identical are not rewritten).

    Raises
    ------
    OutputError
        When the folder cannot be used or a file may not be replaced.
    """
    raise_pending_signal()  # a Ctrl-C that compiled code swallowed still writes nothing
    for name in files:
        if Path(name).name != name or name in {"", ".", "..", MANIFEST} or name.startswith("."):
            raise OutputError(f"{name!r}: not a plain file name")
    folder = prepare_folder(out_dir)
    try:
        recover(folder, warn or _runtime_warning)
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
    raise_pending_signal()
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
