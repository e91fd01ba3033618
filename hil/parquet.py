"""Parquet files of float64 columns, written and read without a Parquet library.

The signals of a run are kept in column blocks, each written as one complete Parquet file
(`hil.recording`): what any Parquet reader reads (pyarrow, pandas, polars, duckdb, Spark), with
no dependency beyond numpy. A file holds one row group of REQUIRED DOUBLE columns, each one
PLAIN-encoded, uncompressed data page, and its key-value metadata (text keys and values); the
footer is Thrift's compact protocol, as the format specifies
(https://parquet.apache.org/docs/file-format/, parquet.thrift). `read_table` reads exactly
what `write_table` writes and refuses anything else (another type, codec, encoding, nesting)
with a ParquetError naming the file: it is the reader of softhil's own files, not a general
one. The tests check both against pyarrow, an independent implementation.
"""

from __future__ import annotations

import struct
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from hil.errors import HilError

MAGIC = b"PAR1"
CREATED_BY = "softhil (hil.parquet)"
# parquet.thrift's enums, the values used here
DOUBLE, REQUIRED, PLAIN, RLE, UNCOMPRESSED, DATA_PAGE = 5, 0, 0, 3, 0, 0
# Thrift compact protocol's field types
_I32, _I64, _BINARY, _LIST, _STRUCT = 5, 6, 8, 9, 12
_TRUE, _FALSE, _BYTE, _I16, _DOUBLE_T, _SET, _MAP = 1, 2, 3, 4, 7, 10, 11


class ParquetError(HilError):
    """A file that is not a Parquet table as `write_table` writes them (names the file)."""


# ------------------------------------------------------------------ Thrift compact: writing


def _varint(value: int) -> bytes:
    out = bytearray()
    while True:
        byte = value & 0x7F
        value >>= 7
        if value:
            out.append(byte | 0x80)
        else:
            out.append(byte)
            return bytes(out)


def _zigzag(value: int) -> bytes:
    return _varint((value << 1) ^ (value >> 63))


class _Struct:
    """A Thrift struct in the compact protocol, its fields added in increasing id order."""

    def __init__(self) -> None:
        self.data = bytearray()
        self.last = 0

    def _field(self, field: int, kind: int) -> None:
        assert field > self.last
        delta = field - self.last
        if delta <= 15:
            self.data.append(delta << 4 | kind)
        else:  # pragma: no cover - the structures here number their fields densely
            self.data.append(kind)
            self.data += _zigzag(field)
        self.last = field

    def i32(self, field: int, value: int) -> _Struct:
        self._field(field, _I32)
        self.data += _zigzag(value)
        return self

    def i64(self, field: int, value: int) -> _Struct:
        self._field(field, _I64)
        self.data += _zigzag(value)
        return self

    def text(self, field: int, value: str) -> _Struct:
        self._field(field, _BINARY)
        raw = value.encode("utf-8")
        self.data += _varint(len(raw)) + raw
        return self

    def struct(self, field: int, value: _Struct) -> _Struct:
        self._field(field, _STRUCT)
        self.data += value.end()
        return self

    def items(self, field: int, kind: int, values: Sequence[bytes]) -> _Struct:
        """A list of elements of `kind`, each already encoded."""
        self._field(field, _LIST)
        if len(values) < 15:
            self.data.append(len(values) << 4 | kind)
        else:
            self.data.append(0xF0 | kind)
            self.data += _varint(len(values))
        for value in values:
            self.data += value
        return self

    def end(self) -> bytes:
        return bytes(self.data) + b"\x00"


def _text(value: str) -> bytes:
    raw = value.encode("utf-8")
    return _varint(len(raw)) + raw


# ------------------------------------------------------------------ Thrift compact: reading


class _Reader:
    """Thrift compact structs decoded as {field id: value} (lists as lists, binary as bytes;
    values typed Any: what a field holds is checked where it is used)."""

    def __init__(self, data: bytes, position: int = 0) -> None:
        self.data = data
        self.position = position

    def _byte(self) -> int:
        byte = self.data[self.position]
        self.position += 1
        return byte

    def varint(self) -> int:
        shift = result = 0
        while True:
            byte = self._byte()
            result |= (byte & 0x7F) << shift
            if not byte & 0x80:
                return result
            shift += 7

    def zigzag(self) -> int:
        value = self.varint()
        return (value >> 1) ^ -(value & 1)

    def value(self, kind: int) -> Any:
        if kind in (_TRUE, _FALSE):
            return kind == _TRUE
        if kind == _BYTE:
            return self._byte()
        if kind in (_I16, _I32, _I64):
            return self.zigzag()
        if kind == _DOUBLE_T:
            self.position += 8
            return struct.unpack_from("<d", self.data, self.position - 8)[0]
        if kind == _BINARY:
            size = self.varint()
            self.position += size
            return self.data[self.position - size : self.position]
        if kind in (_LIST, _SET):
            header = self._byte()
            size = header >> 4 if header >> 4 != 15 else self.varint()
            element = header & 0x0F
            return [self.value(element) for _ in range(size)]
        if kind == _STRUCT:
            return self.struct()
        raise ValueError(f"Thrift type {kind} (a map) where Parquet has none")

    def struct(self) -> dict[int, Any]:
        fields: dict[int, Any] = {}
        last = 0
        while True:
            header = self._byte()
            if header == 0:
                return fields
            delta, kind = header >> 4, header & 0x0F
            last = last + delta if delta else self.zigzag()
            fields[last] = self.value(kind)


# ------------------------------------------------------------------ tables


_CHUNK_HEAD = bytes([2 << 4 | _I64])  # a ColumnChunk's field 2 (its file offset) first
_META_HEAD = bytes([1 << 4 | _STRUCT])  # then field 3 (its metadata)
_NAMED: dict[str, bytes] = {}  # a column's metadata up to its name (fields 1-3), by name


def _named(name: str) -> bytes:
    """A ColumnMetaData's fields 1-3 (type, encodings, path) of column `name`."""
    found = _NAMED.get(name)
    if found is None:
        meta = _Struct().i32(1, DOUBLE).items(2, _I32, [_zigzag(PLAIN)])
        found = _NAMED[name] = bytes(meta.items(3, _BINARY, [_text(name)]).data)
    return found


_LEAVES: dict[str, bytes] = {}  # a column's schema element, by name


def _leaf(name: str) -> bytes:
    """The schema element of column `name`: a required double."""
    found = _LEAVES.get(name)
    if found is None:
        found = _LEAVES[name] = _Struct().i32(1, DOUBLE).i32(3, REQUIRED).text(4, name).end()
    return found


def encode_table(names: Sequence[str], columns: np.ndarray, metadata: Mapping[str, str]) -> bytes:
    """The Parquet file of `columns` (shape (len(names), rows), float64), one row group."""
    columns = np.ascontiguousarray(columns, dtype="<f8")
    if columns.ndim != 2 or columns.shape[0] != len(names):
        raise ValueError(f"{columns.shape} columns for {len(names)} names")
    rows = columns.shape[1]
    size = 8 * rows  # a column's plain data page
    # every column's page header is the same; its chunk's metadata differs only by its name
    # (fields 1-3, made once per name) and its offset (field 9): the rest is made once
    header = (
        _Struct()
        .i32(1, DATA_PAGE)
        .i32(2, size)
        .i32(3, size)
        .struct(5, _Struct().i32(1, rows).i32(2, PLAIN).i32(3, RLE).i32(4, RLE))
        .end()
    )
    size += len(header)
    middle = _Struct()
    middle.last = 3  # after the name
    middle = middle.i32(4, UNCOMPRESSED).i64(5, rows).i64(6, size).i64(7, size)
    middle.data.append((9 - 7) << 4 | _I64)  # field 9 (the offset) follows
    between = bytes(middle.data)
    body = [MAGIC]
    offset = len(MAGIC)
    chunks = []
    for name, column in zip(names, columns, strict=True):
        at = _zigzag(offset)
        # ColumnChunk: file_offset (2), meta_data (3) ending with data_page_offset (9)
        chunks.append(_CHUNK_HEAD + at + _META_HEAD + _named(name) + between + at + b"\x00\x00")
        body += [header, column.tobytes()]
        offset += size
    schema = [_Struct().text(4, "schema").i32(5, len(names)).end()]
    schema += map(_leaf, names)
    group = _Struct().items(1, _STRUCT, chunks).i64(2, offset - len(MAGIC)).i64(3, rows)
    pairs = [_Struct().text(1, k).text(2, v).end() for k, v in metadata.items()]
    footer = (
        _Struct()
        .i32(1, 1)
        .items(2, _STRUCT, schema)
        .i64(3, rows)
        .items(4, _STRUCT, [group.end()])
        .items(5, _STRUCT, pairs)
        .text(6, CREATED_BY)
        .end()
    )
    body += [footer, struct.pack("<I", len(footer)), MAGIC]
    return b"".join(body)


def read_table(path: Path) -> tuple[list[str], np.ndarray, dict[str, str]]:
    """(names, columns of shape (len(names), rows), metadata) of a file `encode_table` wrote."""
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise ParquetError(f"{path}: cannot read: {exc.strerror or exc}") from None
    try:
        return _decode(data)
    except (ValueError, KeyError, IndexError, TypeError, struct.error) as exc:
        raise ParquetError(f"{path}: not a softhil signal block ({exc})") from None


def _decode(data: bytes) -> tuple[list[str], np.ndarray, dict[str, str]]:
    if len(data) < 12 or data[:4] != MAGIC or data[-4:] != MAGIC:
        raise ValueError("no Parquet magic at both ends (a file cut short?)")
    (size,) = struct.unpack_from("<I", data, len(data) - 8)
    footer = _Reader(data, len(data) - 8 - size).struct()
    schema = footer[2]
    rows = footer[3]
    assert isinstance(schema, list) and isinstance(rows, int)
    leaves = schema[1:]
    if any(leaf.get(1) != DOUBLE or leaf.get(3) != REQUIRED for leaf in leaves):
        raise ValueError("a column that is not a required double")
    names = [bytes(leaf[4]).decode("utf-8") for leaf in leaves]
    columns = np.empty((len(names), rows))
    start = 0
    for group in footer[4]:
        count = group[3]
        for i, chunk in enumerate(group[1]):
            meta = chunk[3]
            if meta[4] != UNCOMPRESSED or not set(meta[2]) <= {PLAIN, RLE}:  # RLE: levels
                raise ValueError("a compressed or encoded column")
            page = _Reader(data, meta[9])
            header = page.struct()
            if header[1] != DATA_PAGE or header[5][1] != count or header[5][2] != PLAIN:
                raise ValueError("a page that is not one plain data page of the group")
            end = page.position + header[3]
            if end > len(data) or header[3] != 8 * count:
                raise ValueError("a page beyond the file's end")
            columns[i, start : start + count] = np.frombuffer(data, "<f8", count, page.position)
        start += count
    if start != rows:
        raise ValueError(f"row groups of {start} rows in a table of {rows}")
    metadata = {
        bytes(pair[1]).decode("utf-8"): bytes(pair.get(2, b"")).decode("utf-8")
        for pair in footer.get(5, [])
    }
    return names, columns, metadata
