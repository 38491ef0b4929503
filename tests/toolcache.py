"""Compiler and analyser runs the suite keeps across its runs (a small ccache of its own).

The strict C profile compiles and analyses every bundled example's controller in both
precisions (gcc to assembly with its call graph, for the host and the Cortex-M4F; clang's
static analyser; cppcheck): about a minute of the two cores' time in every run, spent on
sources that did not change since the last one. :func:`kept_run` runs such a command once
per *everything it reads*, as ccache does, and keeps what it printed, its exit code and the
files it wrote:

- the program: its resolved path, size and modification time (an upgraded compiler is a
  new key), and every argument, with the paths it reads and writes replaced by their
  role, so that a new run's temporary folders do not make a new key;
- the bytes of every file it reads (the caller names them: the controller's source and
  header).

A changed source, header, flag or tool runs the command again, so a cached verdict is
the verdict the tool would give now. The suite's cache folder is
:func:`tests.conftest.kept_folder` (``.test-cache/`` in the checkout, ``TVOPT_TEST_CACHE``
to move it, ``TVOPT_TEST_CACHE=off`` to keep nothing past a run); CI starts from a clean
clone, so every run there is a cold one. The benchmark harness (``benchmarks/``) never
uses this: it times the tools.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import shutil
import subprocess
import tempfile
from collections.abc import Sequence
from pathlib import Path

#: Bump when what an entry holds changes: old entries are then never read.
FORMAT = "1"


def _program(name: str) -> str:
    """The identity of program ``name``: its path and the size and time of its file."""
    found = shutil.which(name)
    if found is None:
        raise FileNotFoundError(f"{name} is not on the PATH")
    real = os.path.realpath(found)
    stat = os.stat(real)
    return f"{real}\0{stat.st_size}\0{stat.st_mtime_ns}"


def _placeholders(reads: Sequence[Path], writes: Sequence[Path]) -> list[tuple[str, str]]:
    """(path text, its role) for every read and written file, the longest paths first."""
    pairs = [(str(p), f"<read {i}>") for i, p in enumerate(reads)]
    pairs += [(str(p), f"<write {i}>") for i, p in enumerate(writes)]
    # Folders too: a tool names a file beside its output by the output's folder.
    pairs += [(str(p.parent), f"<folder of write {i}>") for i, p in enumerate(writes)]
    pairs += [(str(p.parent), f"<folder of read {i}>") for i, p in enumerate(reads)]
    return sorted(pairs, key=lambda pair: -len(pair[0]))


def _generic(text: str, pairs: list[tuple[str, str]]) -> str:
    for path, role in pairs:
        text = text.replace(path, role)
    return text


def _specific(text: str, pairs: list[tuple[str, str]]) -> str:
    for path, role in reversed(pairs):
        text = text.replace(role, path)
    return text


def _kept(path: Path, pairs: list[tuple[str, str]]) -> bytes:
    """A written file's bytes, its text's paths by their roles (assembly names its source)."""
    data = path.read_bytes()
    try:
        return b"T" + _generic(data.decode("utf-8"), pairs).encode("utf-8")
    except UnicodeDecodeError:
        return b"B" + data


def _restored(kept: Path, pairs: list[tuple[str, str]]) -> bytes:
    data = kept.read_bytes()
    if data[:1] == b"T":
        return _specific(data[1:].decode("utf-8"), pairs).encode("utf-8")
    return data[1:]


def kept_run(
    command: Sequence[str],
    *,
    reads: Sequence[Path],
    writes: Sequence[Path] = (),
    cwd: Path | None = None,
    cache: Path | None,
    timeout: float = 300.0,
) -> subprocess.CompletedProcess[str]:
    """Run ``command``, or give back what it did the last time it read the same.

    Parameters
    ----------
    command
        The program (a name on the PATH, or a path) and its arguments.
    reads
        Every file the command reads besides the tool's own (system headers, the tool's
        configuration: those change with the tool's package, whose program is keyed).
    writes
        The files the command writes that the caller reads afterwards; a missing one
        after a successful run is an error. Written again on a hit.
    cwd
        The working folder (the command's relative paths are relative to it); it is
        keyed as a role too.
    cache
        The folder entries are kept in; None runs the command every time.
    timeout
        Seconds before the command is killed (not kept).

    Returns
    -------
    subprocess.CompletedProcess
        Its exit code, standard output and error (text), as the tool printed them in
        this run's folders.
    """
    if cache is None:
        return subprocess.run(
            list(command), cwd=cwd, capture_output=True, text=True, timeout=timeout, check=False
        )
    pairs = _placeholders(reads, writes)
    if cwd is not None:
        pairs = sorted([*pairs, (str(cwd), "<cwd>")], key=lambda pair: -len(pair[0]))
    key = hashlib.sha256()
    for part in (FORMAT, _program(command[0]), *(_generic(a, pairs) for a in command[1:])):
        key.update(hashlib.sha256(part.encode("utf-8")).digest())
    for path in reads:
        key.update(hashlib.sha256(path.read_bytes()).digest())
    entry = cache / "tools" / key.hexdigest()
    kept = _read(entry, writes, pairs)
    if kept is not None:
        return subprocess.CompletedProcess(list(command), *kept)
    done = subprocess.run(
        list(command), cwd=cwd, capture_output=True, text=True, timeout=timeout, check=False
    )
    missing = [path for path in writes if not path.is_file()]
    if done.returncode == 0 and missing:
        raise FileNotFoundError(f"{command[0]} succeeded without writing {missing[0]}")
    # A cache that cannot be written (a read-only checkout, a full disk) only costs the
    # next run its tool's time, as the product's library cache does.
    with contextlib.suppress(OSError):
        _publish(entry, done, writes, pairs)
    return done


def _read(
    entry: Path, writes: Sequence[Path], pairs: list[tuple[str, str]]
) -> tuple[int, str, str] | None:
    """A kept run's exit code and printed text, its files written again; None if not kept
    (or unreadable: then the tool runs)."""
    try:
        kept = json.loads((entry / "record.json").read_text(encoding="utf-8"))
        for index, path in enumerate(writes):
            if (entry / str(index)).is_file():
                path.write_bytes(_restored(entry / str(index), pairs))
    except (OSError, ValueError):
        return None
    return kept["returncode"], _specific(kept["stdout"], pairs), _specific(kept["stderr"], pairs)


def _publish(
    entry: Path,
    done: subprocess.CompletedProcess[str],
    writes: Sequence[Path],
    pairs: list[tuple[str, str]],
) -> None:
    """Keep ``done`` and the files it wrote as ``entry``, published by rename: a worker
    reading at the same time sees a whole entry or none."""
    entry.parent.mkdir(parents=True, exist_ok=True)
    partial = Path(tempfile.mkdtemp(prefix=".", dir=entry.parent))
    try:
        for index, path in enumerate(writes):
            if path.is_file():
                (partial / str(index)).write_bytes(_kept(path, pairs))
        text = {
            "returncode": done.returncode,
            "stdout": _generic(done.stdout, pairs),
            "stderr": _generic(done.stderr, pairs),
        }
        (partial / "record.json").write_text(json.dumps(text), encoding="utf-8")
        try:
            partial.rename(entry)
        except OSError:
            pass  # another worker published the same entry first: theirs is as good
    finally:
        shutil.rmtree(partial, ignore_errors=True)
