"""The sweep's streamed outputs: its Zarr trajectory store and its locked folder of parts.

A sweep runs for hours and writes as it goes, not one transaction at its end: the
trajectories block by block into a Zarr store (:class:`TrajectoryStore`), the finished
rows as whole Parquet parts under a folder lock (:class:`SweepFolder`), so that a sweep
killed by any signal leaves whole files that ``sweep --resume`` reads. Each part is
published with the transaction's primitives (a flushed temporary renamed into place,
the folder synced) and the folder's files are checked by its rule (nothing a user wrote
is replaced), so these classes add the sweep's layout, not a second way of writing.
"""

from __future__ import annotations

import contextlib
import os
import re
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

from tvopt_codegen.emit.transaction import (
    _TEMP_SUFFIX,
    _produce_temp,
    _sync_folder,
    check_replaceable,
    prepare_folder,
)
from tvopt_codegen.errors import OutputError


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
    kind : str
        What holds the folder (``sweep``, ``tune``), for the message to a second one.

    Raises
    ------
    OutputError
        The folder cannot be created or written, another sweep holds it, or a file the
        sweep would write belongs to the user.
    """

    LOCK = ".tvopt-sweep.lock"
    PARTS = "parts"
    _PART = re.compile(r"part-\d{8}-\d+\.parquet")

    def __init__(
        self, out_dir: str | Path, names: list[str], force: bool, kind: str = "sweep"
    ) -> None:
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
                f"{self.folder}: another {kind} is writing to this folder; wait for it, or "
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
