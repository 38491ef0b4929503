"""Stage 6: write output files. The only module of tvopt-codegen that writes.

Every file is written atomically (a temporary file in the same folder, flushed and
then renamed over the target), so a reader or a crash sees the old file or the new
one, never half of one. Nothing a person wrote is overwritten silently: a file is
replaced only if tvopt-codegen wrote it and nobody changed it since, which is known
from the file's own stamp (generated code carries a content hash) or from the
folder's manifest ``.tvopt-manifest.json`` (SHA-256 of every file the tool wrote
there). ``force=True`` overrides both.
"""

from __future__ import annotations

import hashlib
import json
import os
import tempfile
from collections.abc import Mapping
from pathlib import Path

from tvopt_codegen.errors import OutputError
from tvopt_codegen.render import is_pristine, stamped_hash

#: Name of the per-folder record of what tvopt-codegen wrote.
MANIFEST = ".tvopt-manifest.json"

Content = str | bytes


def _bytes(content: Content) -> bytes:
    return content.encode("utf-8") if isinstance(content, str) else content


def _digest(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def _read_manifest(folder: Path) -> dict[str, str]:
    path = folder / MANIFEST
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return {}
    if not isinstance(data, dict):
        return {}
    return {str(k): str(v) for k, v in data.items()}


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
    if force or manifest.get(path.name) == _digest(current):
        return True
    try:
        if is_pristine(current.decode("utf-8")):
            return True
    except UnicodeDecodeError:
        pass
    raise OutputError(
        f"{path}: was edited by hand or not written by tvopt-codegen; refusing to overwrite "
        "it (use --force to replace it)"
    )


def prepare_folder(out_dir: str | Path) -> Path:
    """Check (and create, one level deep) an output folder; write nothing else."""
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
        try:
            folder.mkdir()
        except OSError as exc:
            raise OutputError(f"{folder}: cannot create output folder: {exc.strerror}") from None
    return folder


def write_files(
    files: Mapping[str, Content], out_dir: str | Path, force: bool = False
) -> list[Path]:
    """Write output files into ``out_dir`` atomically.

    All targets are checked before anything is written, so a refusal leaves the
    folder untouched.

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
        if Path(name).name != name or name in {"", ".", "..", MANIFEST}:
            raise OutputError(f"{name!r}: not a plain file name")
    folder = prepare_folder(out_dir)
    manifest = _read_manifest(folder)
    pending = []
    for name, content in files.items():
        data = _bytes(content)
        if _may_replace(folder / name, data, manifest, force):
            pending.append((folder / name, data))
    written: list[Path] = []
    for target, data in pending:
        _atomic_write(target, data)
        written.append(target)
    # Stamped files vouch for themselves; only the others need the manifest.
    unstamped = {t.name: _digest(d) for t, d in pending if not _is_stamped(d)}
    if unstamped:
        manifest.update(unstamped)
        record = json.dumps(dict(sorted(manifest.items())), indent=1) + "\n"
        _atomic_write(folder / MANIFEST, record.encode("utf-8"))
    return written


def _is_stamped(data: bytes) -> bool:
    try:
        return stamped_hash(data.decode("utf-8")) is not None
    except UnicodeDecodeError:
        return False


def _atomic_write(target: Path, data: bytes) -> None:
    """Write ``data`` to ``target`` through a temporary file in the same folder."""
    fd, tmp_name = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent)
    try:
        with os.fdopen(fd, "wb") as handle:
            handle.write(data)
            handle.flush()
            os.fsync(handle.fileno())
        os.chmod(tmp_name, 0o644)
        os.replace(tmp_name, target)
    except BaseException as exc:
        try:
            os.unlink(tmp_name)
        except FileNotFoundError:
            pass
        if isinstance(exc, OSError):
            raise OutputError(f"{target}: cannot write: {exc.strerror or exc}") from None
        raise
