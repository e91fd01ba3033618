"""hil.parquet: the Parquet files of the signal blocks, checked against pyarrow (an independent
implementation of the format) both ways, and its reader's refusals."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from hil.parquet import ParquetError, encode_table, read_table

NAMES = [f"column_{i}" for i in range(17)] + ["kappa_1 [é]"]


def _columns(rows: int) -> np.ndarray:
    rng = np.random.default_rng(7)
    data = rng.normal(0.0, 10.0 ** rng.integers(-300, 300, (len(NAMES), 1)), (len(NAMES), rows))
    if rows:
        data[3, 0] = math.nan
        data[4, -1] = -0.0
        data[5, rows // 2] = math.inf
        data[6, 0] = 5e-324
    return data


@pytest.mark.parametrize(
    "rows,width", [(0, 18), (1, 18), (1000, 18), (3, 1), (3, 13), (3, 14), (3, 15), (3, 16)]
)
def test_pyarrow_reads_what_we_write_bit_for_bit(tmp_path: Path, rows: int, width: int) -> None:
    """Every shape, the lists of the footer on either side of Thrift's short form (14 items
    and fewer: the size in the list's header byte; 15 and more: a varint after it)."""
    pq = pytest.importorskip("pyarrow.parquet")
    names = NAMES[-width:]
    data = _columns(rows)[-width:]
    metadata = {"softhil.units": '{"kappa_1 [é]": "1/m"}', "empty": ""}
    path = tmp_path / "block.parquet"
    path.write_bytes(encode_table(names, data, metadata))
    table = pq.read_table(path)
    assert table.column_names == names and table.num_rows == rows
    assert all(str(field.type) == "double" and not field.nullable for field in table.schema)
    got = np.array([table.column(n).to_numpy() for n in names]).reshape(width, rows)
    assert np.array_equal(got.view(np.int64), data.view(np.int64))
    assert pq.read_metadata(path).metadata == {k.encode(): v.encode() for k, v in metadata.items()}
    read_names, ours, read_metadata = read_table(path)
    assert read_names == names and read_metadata == metadata
    assert np.array_equal(ours.view(np.int64), data.view(np.int64))


def test_we_read_what_pyarrow_writes_plain_and_refuse_the_rest(tmp_path: Path) -> None:
    """A file pyarrow writes as ours are (plain, uncompressed, required doubles, several row
    groups) reads the same; a compressed one or another type is refused, naming the file."""
    pa = pytest.importorskip("pyarrow")
    pq = pytest.importorskip("pyarrow.parquet")
    data = _columns(100)
    schema = pa.schema([pa.field(n, pa.float64(), nullable=False) for n in NAMES])
    table = pa.table([pa.array(c) for c in data], schema=schema)
    path = tmp_path / "plain.parquet"
    pq.write_table(
        table,
        path,
        compression="NONE",
        use_dictionary=False,
        row_group_size=30,
        data_page_version="1.0",
        write_statistics=False,
    )
    names, ours, _ = read_table(path)
    assert names == NAMES and np.array_equal(ours.view(np.int64), data.view(np.int64))
    pq.write_table(table, tmp_path / "snappy.parquet", compression="SNAPPY")
    with pytest.raises(ParquetError, match="snappy.parquet: not a softhil signal block"):
        read_table(tmp_path / "snappy.parquet")
    pq.write_table(pa.table({"n": pa.array([1, 2], pa.int64())}), tmp_path / "int.parquet")
    with pytest.raises(ParquetError, match="int.parquet: .* not a required double"):
        read_table(tmp_path / "int.parquet")


def test_a_file_cut_short_or_damaged_is_refused(tmp_path: Path) -> None:
    whole = encode_table(NAMES, _columns(20), {"k": "v"})
    path = tmp_path / "b.parquet"
    path.write_bytes(whole)
    assert read_table(path)[1].shape == (len(NAMES), 20)
    for cut in (0, 4, len(whole) // 2, len(whole) - 1):
        path.write_bytes(whole[:cut])
        with pytest.raises(ParquetError, match=r"b.parquet: not a softhil signal block"):
            read_table(path)
    path.write_bytes(whole[:4] + bytes(len(whole) - 8) + whole[-4:])  # zeros between the magics
    with pytest.raises(ParquetError, match=r"b.parquet: not a softhil signal block"):
        read_table(path)
    one = bytearray(encode_table(["x"], np.zeros((1, 2)), {}))
    assert one[4:10] == b"\x15\x00\x15\x20\x15\x20"  # page: type 0, sizes 16 and 16
    one[9] = 0x10  # a page of 8 bytes for 2 doubles
    path.write_bytes(bytes(one))
    with pytest.raises(ParquetError, match="a page beyond the file's end"):
        read_table(path)
    with pytest.raises(ParquetError, match="missing.parquet: cannot read"):
        read_table(tmp_path / "missing.parquet")


def test_the_names_and_shapes_must_agree() -> None:
    with pytest.raises(ValueError, match="columns for 2 names"):
        encode_table(["a", "b"], np.zeros((3, 4)), {})
