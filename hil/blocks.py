"""A run's signals in column blocks: Parquet files written as the run goes, the CSV made from them.

The recorder (`hil.recording.SignalRecorder`) keeps a run's rows and writes them every
FLUSH_INTERVAL of wall time as one block: a complete Parquet file `part-NNNNNN.parquet` in the
folder `signals.parquet` beside `signals.csv` (`hil.parquet` writes it; a temporary file renamed
into place, so a block is on disk whole or not at all). Every column is float64 (an empty cell
is NaN, as `pandas.read_csv` reads the CSV); the metadata of each block keeps what float64 does
not: the unit of every column (`softhil.units`) and which cells were integers or booleans
(`softhil.integers`, `softhil.booleans`: column -> the block's rows, or null for every cell that
is not empty). `pandas.read_parquet("signals.parquet")` or `pyarrow.dataset` read the folder as
one table.

Why Parquet, one file per block (the criteria of issue 33):
1. a run killed hard (SIGKILL, a full disk, a dead controller) keeps every block written before:
   each is a complete file, and a block cut short never has its final name. A single Parquet
   file would be unreadable without its footer, which comes last; an HDF5 file needs its
   metadata flushed in order (SWMR) and a crash leaves it marked open, to be cleared first.
2. ordinary tools read it: pyarrow, pandas, polars, duckdb, Spark; units in the metadata.
3. no dependency: the files are written and read here with numpy (pyarrow's wheel is 55 MB,
   h5py's 5 MB, asammdf brings pandas); pyarrow checks them in the tests.
4. a block is one numpy conversion and a few bytes of Thrift: the row's cost on the SYNC is an
   append, where formatting the CSV row took a C formatter of floats (Ryu) to keep up.

`signals.csv` is written from the blocks on disk when the recorder closes (also when a run
fails or is stopped: SIGINT, SIGTERM); its bytes are those of `csv.writer` on the row of the
values as recorded: a float as `repr` writes it (the shortest text that reads back as it), an
integer as an integer, a boolean as True or False, NaN as an empty cell. A run killed hard
leaves the blocks without the CSV: `hil csv RUN` writes it (`write_csv`).

Invariant: equal runs give byte-identical blocks and CSV.
"""

from __future__ import annotations

import csv
import io
import json
import numbers
import operator
import re
from collections.abc import Iterable, Sequence
from itertools import compress, repeat
from pathlib import Path
from typing import cast

import numpy as np

from hil.errors import HilError
from hil.parquet import ParquetError, encode_table, read_table
from hil.results import write_file

UNITS_SUFFIX = ".units.csv"
BLOCKS_SUFFIX = ".parquet"  # the blocks folder: signals.csv -> signals.parquet
PART = re.compile(r"part-(\d{6,})\.parquet")
UNITS, INTEGERS, BOOLEANS, FIRST_ROW = (
    "softhil.units",
    "softhil.integers",
    "softhil.booleans",
    "softhil.first_row",
)
EXACT_INTEGER = 2**53  # a float64 holds every integer up to this magnitude exactly


def blocks_folder(csv_path: Path) -> Path:
    """The folder of the blocks of the signals CSV `csv_path` (signals.parquet)."""
    return csv_path.with_suffix(BLOCKS_SUFFIX)


def part_name(index: int) -> str:
    return f"part-{index:06d}.parquet"


def units_metadata(units: dict[str, str]) -> str:
    """The `softhil.units` metadata of a block: every column's unit, as JSON."""
    return json.dumps(units, ensure_ascii=False, separators=(",", ":"))


def encode_block(
    columns: Sequence[str], cells: Sequence[float], first_row: int, units: str
) -> bytes:
    """The Parquet file of the rows whose `cells` follow each other (a value per column, row
    after row): float64 columns, with the cells that were integers or booleans named in its
    metadata. HilError naming the column for a cell that is not a number, or an integer a
    float64 does not hold exactly."""
    width = len(columns)
    rows = len(cells) // width
    types = list(map(type, cells))
    integers: dict[str, list[int] | None] = {}
    booleans: dict[str, list[int] | None] = {}
    if types.count(float) != len(types):  # the rare block: look at the other columns' cells
        for c in range(width):
            kinds = types[c::width]
            if kinds.count(float) != len(kinds) and not _plain_integers(
                columns[c], kinds, cells[c::width], integers
            ):
                _odd_cells(columns[c], list(cells[c::width]), first_row, integers, booleans)
    data = np.array(cells, dtype=np.float64).reshape(rows, width).T
    for found in (integers, booleans):
        for name, rows_of in found.items():  # null: every cell that is not empty
            if rows_of is not None and len(rows_of) == np.count_nonzero(
                ~np.isnan(data[columns.index(name)])
            ):
                found[name] = None
    metadata = {
        UNITS: units,
        INTEGERS: json.dumps(integers, separators=(",", ":")),
        BOOLEANS: json.dumps(booleans, separators=(",", ":")),
        FIRST_ROW: str(first_row),
    }
    return encode_table(columns, data, metadata)


def _plain_integers(
    column: str,
    kinds: list[type],
    values: Sequence[object],
    integers: dict[str, list[int] | None],
) -> bool:
    """Note the integer cells of one column of a block whose cells are all ints and floats
    (a counter's, a fault code's), read by `map` without a step per cell; False for any other
    column, or an integer beyond 2^53, which `_odd_cells` then reads (and refuses) cell by cell."""
    if kinds.count(int) + kinds.count(float) != len(kinds):
        return False
    whole = list(map(operator.is_, kinds, repeat(int)))
    found = cast(Iterable[int], compress(values, whole))
    if max(map(abs, found), default=0) > EXACT_INTEGER:
        return False
    integers[column] = list(compress(range(len(kinds)), whole))
    return True


def _odd_cells(
    column: str,
    values: list[object],
    first_row: int,
    integers: dict[str, list[int] | None],
    booleans: dict[str, list[int] | None],
) -> None:
    """Note the integer and boolean cells of one column of a block; refuse what is not a
    number (the row counted from the run's first)."""
    for row, value in enumerate(values):
        if isinstance(value, float):
            continue
        if isinstance(value, bool | np.bool_):
            booleans.setdefault(column, []).append(row)  # type: ignore[union-attr]
        elif isinstance(value, numbers.Integral):
            if abs(int(value)) > EXACT_INTEGER:
                raise HilError(
                    f"signal {column!r}, row {first_row + row + 1}: integer {value} is beyond "
                    f"2^53, which a float64 column does not hold exactly"
                )
            integers.setdefault(column, []).append(row)  # type: ignore[union-attr]
        elif not isinstance(value, numbers.Real):
            raise HilError(
                f"signal {column!r}, row {first_row + row + 1}: {value!r} is not a number"
            )


def csv_lines(columns: Sequence[str], data: np.ndarray, metadata: dict[str, str]) -> str:
    """The CSV lines of one block (`data`: one float64 array per column)."""
    integers = json.loads(metadata.get(INTEGERS, "{}"))
    booleans = json.loads(metadata.get(BOOLEANS, "{}"))
    texts = []
    for name, column in zip(columns, data, strict=True):
        cells = list(map(repr, column.tolist()))
        empty = np.isnan(column)
        for row in np.flatnonzero(empty).tolist():
            cells[row] = ""
        for found, write in ((integers, _integer), (booleans, _boolean)):
            if name in found:
                rows = found[name]
                for row in np.flatnonzero(~empty).tolist() if rows is None else rows:
                    cells[row] = write(column[row])
        texts.append(cells)
    if not texts or not texts[0]:
        return ""
    return "\n".join(map(",".join, zip(*texts, strict=True))) + "\n"


def _integer(value: float) -> str:
    return repr(int(value))


def _boolean(value: float) -> str:
    return repr(bool(value))


Block = tuple[list[str], np.ndarray, dict[str, str]]  # columns, data (columns x rows), metadata


def read_blocks(folder: Path) -> list[Block]:
    """Every block in `folder`, in order (none if there is no such folder); HilError naming the
    block that does not follow the one before (another run's columns, a gap in the rows) or
    cannot be read."""
    parts = sorted(
        (int(match.group(1)), entry)
        for entry in (folder.iterdir() if folder.is_dir() else ())
        if (match := PART.fullmatch(entry.name))
    )
    blocks: list[Block] = []
    rows = 0
    for index, (number, path) in enumerate(parts):
        names, data, meta = read_table(path)
        if (
            number != index
            or meta.get(FIRST_ROW) != str(rows)
            or (blocks and names != blocks[0][0])
        ):
            raise ParquetError(
                f"{path}: does not follow block {index - 1} of {folder} (rows from "
                f"{meta.get(FIRST_ROW)}, expected {rows}; a block missing, or another run's)"
            )
        blocks.append((names, data, meta))
        rows += data.shape[1]
    return blocks


def read_columns(folder: Path) -> tuple[list[str], np.ndarray]:
    """(columns, data of shape (columns, rows)) of every block in `folder`, in one table."""
    blocks = read_blocks(folder)
    if not blocks:
        return [], np.empty((0, 0))
    return blocks[0][0], np.concatenate([data for _, data, _ in blocks], axis=1)


def header_line(columns: Sequence[str]) -> str:
    text = io.StringIO()
    csv.writer(text, lineterminator="\n").writerow(columns)
    return text.getvalue()


def units_columns(csv_path: Path) -> list[str]:
    """The columns the units sidecar of `csv_path` lists (the header of a run with no row)."""
    path = csv_path.with_name(csv_path.stem + UNITS_SUFFIX)
    try:
        with path.open(newline="", encoding="utf-8") as file:
            return [row[0] for row in list(csv.reader(file))[1:] if row]
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise HilError(f"{path}: cannot read the signals' columns ({exc})") from None


def write_csv(csv_path: Path, columns: Sequence[str] | None = None) -> int:
    """Write `csv_path` (whole, atomically) from the blocks in its blocks folder; the rows
    written. `columns`: the header when there is no block (by default, those of the units
    sidecar)."""
    blocks = read_blocks(blocks_folder(csv_path))
    if blocks:
        columns = blocks[0][0]
    elif columns is None:
        columns = units_columns(csv_path)
    text = header_line(columns) + "".join(csv_lines(*block) for block in blocks)
    write_file(csv_path, text)
    return sum(data.shape[1] for _, data, _ in blocks)
