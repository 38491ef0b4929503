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

from tvopt_codegen.errors import MissingExtraError, OutputError
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
    """One chunk's rows as a ``pyarrow.RecordBatch`` of the table's schema."""
    pa, _ = pyarrow()
    return pa.RecordBatch.from_pylist(list(rows), schema=schema)


def write_part(handle: Any, batches: Sequence[Any], schema: Any) -> None:
    """A part: each chunk's batch as its own row group (so one chunk reads alone)."""
    _, pq = pyarrow()
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


def index_parts(paths: Sequence[Path], schema: Any) -> list[Piece]:
    """The chunks the parts hold, by first sample; read from the files' footers only.

    Raises
    ------
    OutputError
        A part that is not a table of this sweep (another schema, unreadable).
    """
    _, pq = pyarrow()
    pieces: list[Piece] = []
    for path in paths:
        try:
            meta = pq.ParquetFile(path).metadata
            if not meta.schema.to_arrow_schema().equals(schema):
                raise ValueError("its columns are not this sweep's")
            where = meta.schema.names.index("sample")
            for group in range(meta.num_row_groups):
                stats = meta.row_group(group).column(where).statistics
                rows = meta.row_group(group).num_rows
                start, stop = int(stats.min), int(stats.max) + 1
                if stop - start != rows:
                    raise ValueError(f"row group {group} is not a run of consecutive samples")
                pieces.append(Piece(start, stop, path, group))
        except (OSError, ValueError, AttributeError, TypeError) as exc:
            raise OutputError(f"{path}: not a part of this sweep ({exc})") from None
    pieces.sort(key=lambda p: (p.start, -p.stop))
    return pieces


def _disjoint(pieces: Sequence[Piece]) -> list[Piece]:
    """The pieces without repeats: a chunk kept twice (a resume raced a flush) counts once."""
    kept: list[Piece] = []
    end = 0
    for piece in pieces:
        if piece.start >= end:
            kept.append(piece)
            end = piece.stop
        elif piece.stop > end:
            raise OutputError(
                f"{piece.path}: holds samples {piece.start}..{piece.stop - 1}, which overlap "
                "another part's without matching it"
            )
    return kept


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
    rows: list[dict[str, Any]] = pq.read_table(path).to_pylist()
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
        hits = np.nonzero(rows.column("sample").to_numpy() == index)[0]
        if len(hits):
            found: dict[str, Any] = rows.slice(int(hits[0]), 1).to_pylist()[0]
            return found
    return None
