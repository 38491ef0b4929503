"""The sweep's table: one schema, rows kept in parts as they finish, merged in order.

A sweep's rows reach the client in the order their chunks finish. They are kept in
*parts* (Parquet files, one row group per chunk, written by :mod:`~tvopt_codegen.emit`
as whole files), so that a sweep stopped by any signal loses at most the chunks not yet
flushed, and ``--resume`` runs only the samples no part holds. The final
``summary.parquet`` is built from the parts in sample order, in row groups of
:data:`TABLE_ROW_GROUP` rows whatever the chunks were: the same rows give the same
bytes, however many times the sweep was stopped and resumed. Nothing here holds more
than a row group of rows at once, and :func:`~.results.tally_table` reads only the columns
the statistics need.

Every column's type is fixed by the program and the options (:func:`row_schema`), not
inferred from the rows: a part whose samples all failed has the same schema as one
whose samples all succeeded.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from tvopt_codegen.errors import MissingExtraError, OutputError, clip
from tvopt_codegen.sweep.options import SweepOptions
from tvopt_codegen.sweep.program import SweepProgram

#: Rows of one row group of ``summary.parquet``.
TABLE_ROW_GROUP = 65_536
#: A part is written once this many rows wait in the client, or ``--checkpoint-seconds``
#: after the last part, whichever comes first.
PART_ROWS = 50_000
#: The status of a sample whose run raised (the message is its ``error`` column).
ERROR_STATUS = "error"


def pyarrow() -> tuple[Any, Any]:
    """``pyarrow`` and ``pyarrow.parquet``, or the one-line message saying what to install."""
    try:
        import pyarrow as pa  # noqa: PLC0415
        import pyarrow.parquet as pq  # noqa: PLC0415
    except ImportError:
        raise MissingExtraError(
            "sweep reads and writes Parquet with pyarrow: pip install 'tvopt-codegen[sweep]'"
        ) from None
    return pa, pq


def row_columns(program: SweepProgram, options: SweepOptions) -> list[tuple[str, str]]:
    """Every column of a sample's row, in order, with its kind: int, float, str or bool."""
    columns = [
        ("sample", "int"),
        ("seed", "int"),
        ("status", "str"),
        ("t_end", "float"),
        ("final_error", "float"),
        ("max_error", "float"),
        ("settling_1pct", "float"),
        ("settling_01pct", "float"),
        ("integrated_error", "float"),
        ("max_error_after", "float"),
    ]
    columns += [(f"max_abs_{name}", "float") for name in program.input_names]
    columns += [("time_saturated", "float"), ("min_det_ratio", "float")]
    if program.constraints:
        columns += [
            ("min_margin", "float"),
            ("violations", "int"),
            ("time_outside", "float"),
            ("final_constraint", "float"),
        ]
    if program.equalities:
        columns += [("max_equality", "float"), ("final_equality", "float")]
    columns += [
        ("steps", "int"),
        ("rejected_steps", "int"),
        ("nominal", "bool"),
        ("certificate_holds", "bool"),
    ]
    columns += [(f"initial.{name}", "float") for name, _ in options.initial]
    columns += [(f"param.{name}", "float") for name, _ in options.params]
    columns += [(f"plant.{name}", "float") for name, _ in options.plant_params]
    columns.append(("error", "str"))
    return columns


def failed_row(
    program: SweepProgram, options: SweepOptions, index: int, seed: int, error: BaseException
) -> dict[str, Any]:
    """The row of a sample whose run raised: its status is :data:`ERROR_STATUS`."""
    empty: dict[str, Any] = {"int": 0, "float": math.nan, "str": None, "bool": False}
    row = {name: empty[kind] for name, kind in row_columns(program, options)}
    message = " ".join(str(error).split()) or "no message"
    row |= {
        "sample": index,
        "seed": seed,
        "status": ERROR_STATUS,
        "certificate_holds": None,
        "error": f"{type(error).__name__}: {message}"[:500],
    }
    return row


def row_schema(program: SweepProgram, options: SweepOptions) -> Any:
    """The table's ``pyarrow.Schema``."""
    pa, _ = pyarrow()
    kinds = {"int": pa.int64(), "float": pa.float64(), "str": pa.string(), "bool": pa.bool_()}
    return pa.schema([(name, kinds[kind]) for name, kind in row_columns(program, options)])


def record_batch(rows: Sequence[Mapping[str, Any]], schema: Any) -> Any:
    """One chunk's rows as a ``pyarrow.RecordBatch`` of the table's schema.

    Built from NumPy buffers, as ``RecordBatch.from_pylist`` builds it (a ``None`` or a
    missing key is a null): pyarrow's conversions from Python and to NumPy import pandas
    at their first call, to test for its types (a quarter of a second of a sweep
    command's CPU, for a library the command never uses).
    """
    pa, _ = pyarrow()
    columns = [_column(pa, f.type, [row.get(f.name) for row in rows]) for f in schema]
    return pa.RecordBatch.from_arrays(columns, schema=schema)


def _column(pa: Any, kind: Any, values: list[Any]) -> Any:
    """One column of :func:`record_batch`: an int64, float64, string or bool array."""
    count = len(values)
    missing = np.fromiter((v is None for v in values), bool, count)
    nulls = int(missing.sum())
    valid = pa.py_buffer(np.packbits(~missing, bitorder="little")) if nulls else None
    if kind == pa.string():
        encoded = [b"" if v is None else v.encode() for v in values]
        offsets = np.zeros(count + 1, np.int32)
        np.cumsum([len(e) for e in encoded], out=offsets[1:])
        buffers = [valid, pa.py_buffer(offsets), pa.py_buffer(b"".join(encoded))]
    elif kind == pa.bool_():
        bits = np.fromiter((bool(v) for v in values), bool, count)
        buffers = [valid, pa.py_buffer(np.packbits(bits, bitorder="little"))]
    else:
        dtype = np.int64 if kind == pa.int64() else np.float64
        data = np.array([0 if v is None else v for v in values], dtype=dtype)
        buffers = [valid, pa.py_buffer(data)]
    return pa.Array.from_buffers(kind, count, buffers, null_count=nulls)


#: NumPy's type of each Arrow type of a sweep's number and boolean columns (and codes).
_NUMPY_TYPES: dict[str, Any] = {
    "int8": np.int8,
    "int16": np.int16,
    "int32": np.int32,
    "int64": np.int64,
    "double": np.float64,
    "bool": np.bool_,
}


def to_numpy(column: Any) -> np.ndarray:
    """An ``Array`` or ``ChunkedArray`` of numbers or booleans as NumPy's, from its buffers.

    What ``to_numpy(zero_copy_only=False)`` gives (a null is NaN, an int column with
    nulls is float, a bool one object with ``None``), without its import of pandas (see
    :func:`record_batch`).
    """
    name = str(column.type)
    chunks = column.chunks if hasattr(column, "chunks") else [column]
    parts = [_chunk_to_numpy(chunk, name) for chunk in chunks]
    if not parts:
        return np.empty(0, _NUMPY_TYPES[name])
    return parts[0] if len(parts) == 1 else np.concatenate(parts)


def _chunk_to_numpy(chunk: Any, name: str) -> np.ndarray:
    count = len(chunk)
    if chunk.null_count:
        return np.array(chunk.to_pylist(), dtype=object if name == "bool" else np.float64)
    dtype = np.dtype(_NUMPY_TYPES[name])
    if count == 0:
        return np.empty(0, dtype)
    data = chunk.buffers()[1]
    if name == "bool":
        bits = np.unpackbits(np.frombuffer(data, np.uint8), bitorder="little")
        return bits[chunk.offset : chunk.offset + count].astype(bool)
    return np.frombuffer(data, dtype, count=count, offset=chunk.offset * dtype.itemsize)


#: The Parquet key-value metadata of a part (and of ``summary.parquet``) naming its sweep:
#: the spec copy's SHA-256, the seed, the SHA-256 of the options that shape a row, and the
#: compiled loop's key. A part carries them all, and its row groups' sample ranges
#: (:data:`RANGES_KEY`): ``--resume`` merges only parts of its own sweep.
IDENTITY_KEYS = ("tvopt.sweep.spec", "tvopt.sweep.seed", "tvopt.sweep.options", "tvopt.sweep.loop")
#: A part's row groups' sample ranges, ``[[start, stop], ...]`` as JSON.
RANGES_KEY = "tvopt.sweep.ranges"


def sweep_identity(
    spec: bytes, options: SweepOptions, loop: str, extension: str = ""
) -> dict[str, str]:
    """What makes two sweeps' rows interchangeable, as the parts' metadata.

    ``samples`` is left out: sample ``i``'s row depends on the seed and ``i`` alone, and
    the ranges are checked against the sweep's count. Every other option (horizon,
    spreads, limits, noise, sample time, tolerances, output times, step budget) changes
    rows, and so does the extension the derivation was asked for.
    """
    import hashlib  # noqa: PLC0415
    import json  # noqa: PLC0415

    shaping = {k: v for k, v in options.as_dict().items() if k not in ("samples", "seed")}
    shaping["extension"] = extension
    text = json.dumps(shaping, sort_keys=True, separators=(",", ":"))
    return {
        "tvopt.sweep.spec": hashlib.sha256(spec).hexdigest(),
        "tvopt.sweep.seed": str(options.seed),
        "tvopt.sweep.options": hashlib.sha256(text.encode()).hexdigest(),
        "tvopt.sweep.loop": loop,
    }


def with_identity(schema: Any, identity: Mapping[str, str]) -> Any:
    """``schema`` carrying a sweep's identity (:func:`sweep_identity`) as metadata."""
    return schema.with_metadata({**(schema.metadata or {}), **identity})


def _batch_range(batch: Any) -> list[int]:
    """``[start, stop]`` of a chunk's batch (its samples are consecutive, in order)."""
    samples = batch.column(batch.schema.get_field_index("sample"))
    if not len(samples):
        return [0, 0]
    return [int(samples[0].as_py()), int(samples[len(samples) - 1].as_py()) + 1]


def write_part(handle: Any, batches: Sequence[Any], schema: Any) -> None:
    """A part: each chunk's batch as its own row group (so one chunk reads alone).

    The file's metadata holds ``schema``'s (the sweep's identity) and each row group's
    sample range, which ``--resume`` holds against the rows themselves.
    """
    import json  # noqa: PLC0415

    _, pq = pyarrow()
    ranges = json.dumps([_batch_range(batch) for batch in batches], separators=(",", ":"))
    schema = schema.with_metadata({**(schema.metadata or {}), RANGES_KEY: ranges})
    with pq.ParquetWriter(handle, schema) as writer:
        for batch in batches:
            writer.write_batch(batch, row_group_size=max(1, batch.num_rows))


@dataclass(frozen=True)
class Piece:
    """One chunk in a part: samples ``start`` to ``stop - 1``, row group ``group``."""

    start: int
    stop: int
    path: Path
    group: int


class _RefusedError(Exception):
    """Why a part cannot join this sweep's table (the caller names the file)."""


def _identity_problem(found: Mapping[str, str], expected: Mapping[str, str]) -> str | None:
    """Why a part's identity is not the sweep's, or None when it is."""
    if not all(key in found for key in IDENTITY_KEYS):
        return (
            "it carries no sweep identity (not written by this sweep: another tool, or an "
            "older tvopt-codegen)"
        )
    if found["tvopt.sweep.spec"] != expected["tvopt.sweep.spec"]:
        return "it is a part of another sweep: another spec"
    if found["tvopt.sweep.seed"] != expected["tvopt.sweep.seed"]:
        return (
            f"it is a part of another sweep: seed {clip(found['tvopt.sweep.seed'], 24)}, "
            f"this sweep's is {expected['tvopt.sweep.seed']}"
        )
    if found["tvopt.sweep.options"] != expected["tvopt.sweep.options"]:
        return (
            "it is a part of another sweep: other options (horizon, spreads, limits, noise, "
            "sample time, tolerances or output times)"
        )
    if found["tvopt.sweep.loop"] != expected["tvopt.sweep.loop"]:
        return "it is a part of another sweep: another compiled loop (another tvopt-codegen?)"
    return None


def _metadata(meta: Any) -> dict[str, str]:
    raw = meta.metadata or {}
    return {k.decode(errors="replace"): v.decode(errors="replace") for k, v in raw.items()}


def _ranges(found: Mapping[str, str], groups: int) -> list[tuple[int, int]]:
    """The part's recorded sample range of each row group."""
    import json  # noqa: PLC0415

    try:
        ranges = [(int(a), int(b)) for a, b in json.loads(found[RANGES_KEY])]
    except (KeyError, ValueError, TypeError):
        raise _RefusedError("it records no sample range for its row groups") from None
    if len(ranges) != groups:
        raise _RefusedError(
            f"it records {len(ranges)} sample ranges for {groups} row groups (rewritten?)"
        )
    return ranges


def _check_group(
    rows: Any, group: int, span: tuple[int, int], samples: int | None, seed: int | None
) -> None:
    """A row group holds exactly the samples of its range, each once, with their seeds."""
    from tvopt_codegen.sweep.program import sample_seed  # noqa: PLC0415

    start, stop = span
    if not 0 <= start < stop or (samples is not None and stop > samples):
        whole = "" if samples is None else f" of 0..{samples - 1}"
        raise _RefusedError(f"row group {group}'s range {start}..{stop - 1} is not a range{whole}")
    if rows.num_rows != stop - start:
        raise _RefusedError(
            f"row group {group} holds {rows.num_rows} rows for samples {start}..{stop - 1} "
            f"({stop - start} samples)"
        )
    held = to_numpy(rows.column("sample"))
    if not np.array_equal(held, np.arange(start, stop)):
        values, counts = np.unique(held, return_counts=True)
        absent = np.setdiff1d(np.arange(start, stop), values)
        if np.any(counts > 1):
            twice = int(values[np.argmax(counts > 1)])
            lost = f"; sample {int(absent[0])} is missing" if len(absent) else ""
            raise _RefusedError(
                f"its sample column holds sample {twice} twice (row group {group}{lost})"
            )
        raise _RefusedError(
            f"its sample column in row group {group} is not samples {start}..{stop - 1} in order"
        )
    if seed is not None:
        seeds = to_numpy(rows.column("seed"))
        for where in {0, len(held) - 1}:
            if int(seeds[where]) != sample_seed(seed, int(held[where])):
                raise _RefusedError(
                    f"sample {int(held[where])}'s seed is not this sweep's (its rows come from "
                    "a sweep with another seed)"
                )


def index_parts(paths: Sequence[Path], schema: Any, samples: int | None = None) -> list[Piece]:
    """The chunks the parts hold, by first sample, each checked against this sweep.

    When ``schema`` carries the sweep's identity (:func:`with_identity`), a part must
    carry the same (spec, seed, options, loop); its row groups must hold exactly their
    recorded sample ranges (as many rows, each sample once, in order, the seeds of this
    sweep's seed at both ends), within ``0 .. samples - 1``; and no two parts may hold
    the same sample.

    Raises
    ------
    OutputError
        One line naming the first part refused and why.
    """
    _, pq = pyarrow()
    expected = {k: v for k, v in _metadata(schema).items() if k in IDENTITY_KEYS}
    seed = int(expected["tvopt.sweep.seed"]) if "tvopt.sweep.seed" in expected else None
    pieces: list[Piece] = []
    for path in paths:
        try:
            handle = pq.ParquetFile(path)
            meta = handle.metadata
            if not meta.schema.to_arrow_schema().equals(schema):
                raise _RefusedError("its columns are not this sweep's")
            found = _metadata(handle.schema_arrow)
            if expected:
                problem = _identity_problem(found, expected)
                if problem is not None:
                    raise _RefusedError(problem)
            ranges = _ranges(found, meta.num_row_groups)
            # Two columns of the whole file in one read (a row group at a time costs a
            # read per chunk: seconds for 10^6 samples), sliced at the row groups.
            columns = handle.read(columns=["sample", "seed"])
            offset = 0
            for group, span in enumerate(ranges):
                count = meta.row_group(group).num_rows
                _check_group(columns.slice(offset, count), group, span, samples, seed)
                offset += count
                pieces.append(Piece(span[0], span[1], path, group))
        except _RefusedError as exc:
            raise OutputError(f"{path}: {exc}; nothing was changed") from None
        except (OSError, ValueError, KeyError, AttributeError, TypeError) as exc:
            problem = " ".join(str(exc).split())
            raise OutputError(
                f"{path}: not a part of this sweep (unreadable: {clip(problem, 120)}); "
                "nothing was changed"
            ) from None
    pieces.sort(key=lambda p: (p.start, p.stop))
    _disjoint(pieces)
    return pieces


def _disjoint(pieces: Sequence[Piece]) -> list[Piece]:
    """The pieces, refused if two hold a sample (whichever holds the right rows is unknown)."""
    end, holder = 0, None
    for piece in pieces:
        if holder is not None and piece.start < end:
            where = holder.path.name if holder.path != piece.path else "its own row groups"
            raise OutputError(
                f"{piece.path}: holds samples {piece.start}..{piece.stop - 1}, which "
                f"{where} holds too (overlapping parts); nothing was changed"
            )
        if piece.stop > end:
            end, holder = piece.stop, piece
    return list(pieces)


def missing(pieces: Sequence[Piece], samples: int) -> list[range]:
    """The runs of samples in ``0 .. samples - 1`` that no piece holds."""
    gaps: list[range] = []
    end = 0
    for piece in _disjoint(pieces):
        if piece.start > end:
            gaps.append(range(end, min(piece.start, samples)))
        end = max(end, piece.stop)
    if end < samples:
        gaps.append(range(end, samples))
    return [gap for gap in gaps if len(gap)]


def _ordered(pieces: Sequence[Piece]) -> Iterator[Any]:
    """Each piece's rows as a table, in sample order (one part file open at a time)."""
    _, pq = pyarrow()
    opened: tuple[Path, Any] | None = None
    for piece in _disjoint(pieces):
        if opened is None or opened[0] != piece.path:
            opened = (piece.path, pq.ParquetFile(piece.path))
        yield opened[1].read_row_group(piece.group)


def write_table(handle: Any, pieces: Sequence[Piece], schema: Any) -> int:
    """``summary.parquet`` from the pieces, in row groups of :data:`TABLE_ROW_GROUP`.

    Returns
    -------
    int
        The rows written.
    """
    pa, pq = pyarrow()
    waiting: list[Any] = []
    count = total = 0
    with pq.ParquetWriter(handle, schema) as writer:
        for table in _ordered(pieces):
            waiting.append(table)
            count += table.num_rows
            while count >= TABLE_ROW_GROUP:
                joined = pa.concat_tables(waiting)
                writer.write_table(joined.slice(0, TABLE_ROW_GROUP), row_group_size=TABLE_ROW_GROUP)
                rest = joined.slice(TABLE_ROW_GROUP)
                waiting, count = [rest], rest.num_rows
                total += TABLE_ROW_GROUP
        if count:
            writer.write_table(pa.concat_tables(waiting), row_group_size=TABLE_ROW_GROUP)
            total += count
    return total


#: The columns the summary's statistics read (those a sweep has).
SUMMARY_COLUMNS = (
    "sample",
    "status",
    "final_error",
    "settling_1pct",
    "time_saturated",
    "nominal",
    "certificate_holds",
    "violations",
    "final_constraint",
    "final_equality",
    "error",
)


def read_summary(path: str | Path) -> list[dict[str, Any]]:
    """The rows of a (small) ``summary.parquet`` as dicts."""
    _, pq = pyarrow()
    rows: list[dict[str, Any]] = pq.ParquetFile(path).read().to_pylist()
    return rows


def read_row(path: str | Path, index: int) -> dict[str, Any] | None:
    """The row of sample ``index`` in a ``summary.parquet`` (one row group read), or None."""
    _, pq = pyarrow()
    try:
        table = pq.ParquetFile(path)
        where = table.schema_arrow.names.index("sample")
    except (OSError, ValueError):
        return None
    for group in range(table.metadata.num_row_groups):
        stats = table.metadata.row_group(group).column(where).statistics
        if stats is None or not int(stats.min) <= index <= int(stats.max):
            continue
        rows = table.read_row_group(group)
        hits = np.nonzero(to_numpy(rows.column("sample")) == index)[0]
        if len(hits):
            found: dict[str, Any] = rows.slice(int(hits[0]), 1).to_pylist()[0]
            return found
    return None
