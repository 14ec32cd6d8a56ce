"""The pages of a Parquet file: where each page's header and data lie, and whether it carries a CRC.

pyarrow verifies page checksums on reading but does not say whether a file has any: a file written
without them (as every dataset before schema 1.1) reads back silently whatever happened to its
bytes. The page headers say it: each is a Thrift compact-protocol ``PageHeader`` whose optional
field 4 is the page's CRC-32. This module walks every column chunk's pages from the offsets in the
file's footer and reads those headers, nothing else (the data is neither read nor decompressed).
"""

from __future__ import annotations

import dataclasses
import mmap
from pathlib import Path

import pyarrow.parquet as pq

# Thrift compact protocol type ids (thrift/doc/specs/thrift-compact-protocol.md).
_TRUE, _FALSE, _BYTE, _I16, _I32, _I64, _DOUBLE, _BINARY, _LIST, _SET, _MAP, _STRUCT = range(1, 13)
# PageHeader fields (parquet.thrift): 1 type, 2 uncompressed_page_size, 3 compressed_page_size, 4 crc.
_PAGE_SIZE, _CRC = 3, 4


@dataclasses.dataclass(frozen=True)
class Page:
    """One page of a Parquet file.

    Attributes:
        column: the column's path in the schema.
        header: byte offset of the page header.
        data: byte offset of the page data (just after the header).
        end: byte offset just after the page data.
        crc: whether the header carries a checksum of the data.
    """

    column: str
    header: int
    data: int
    end: int
    crc: bool


def _varint(buf, i: int) -> tuple[int, int]:
    out = shift = 0
    while True:
        b = buf[i]
        i += 1
        out |= (b & 0x7F) << shift
        if b < 0x80:
            return out, i
        shift += 7


def _zigzag(buf, i: int) -> tuple[int, int]:
    z, i = _varint(buf, i)
    return (z >> 1) ^ -(z & 1), i


def _skip(buf, i: int, kind: int) -> int:
    """Offset just after a value of compact type ``kind`` starting at ``i``."""
    if kind in (_TRUE, _FALSE):  # a boolean field's value is its type
        return i
    if kind == _BYTE:
        return i + 1
    if kind in (_I16, _I32, _I64):
        return _varint(buf, i)[1]
    if kind == _DOUBLE:
        return i + 8
    if kind == _BINARY:
        n, i = _varint(buf, i)
        return i + n
    if kind in (_LIST, _SET):
        n, elem = buf[i] >> 4, buf[i] & 0x0F
        i += 1
        if n == 15:
            n, i = _varint(buf, i)
        for _ in range(n):
            i = i + 1 if elem in (_TRUE, _FALSE) else _skip(buf, i, elem)  # list booleans take a byte
        return i
    if kind == _MAP:
        n, i = _varint(buf, i)
        if n:
            key, value = buf[i] >> 4, buf[i] & 0x0F
            i += 1
            for _ in range(n):
                i = _skip(buf, _skip(buf, i, key), value)
        return i
    if kind == _STRUCT:
        return _struct(buf, i)[1]
    raise ValueError(f"not a Thrift compact value (type {kind}) at byte {i}")


def _struct(buf, i: int) -> tuple[dict[int, int], int]:
    """The i32 fields of the struct at ``i`` ({field id: value}) and the offset just after it."""
    field, ints = 0, {}
    while True:
        head = buf[i]
        i += 1
        if head == 0:  # STOP
            return ints, i
        delta, kind = head >> 4, head & 0x0F
        if delta:
            field += delta
        else:
            field, i = _zigzag(buf, i)
        if kind == _I32:
            ints[field], i = _zigzag(buf, i)
        else:
            i = _skip(buf, i, kind)


def pages(file) -> list[Page]:
    """Every page of every column chunk of the Parquet file ``file``, in file order.

    Arguments:
        file: path of the Parquet file.

    Returns:
        The :class:`Page` s. Raises ``ValueError``, ``IndexError`` or ``RecursionError`` for
        headers that are not Thrift, ``OSError`` for an unreadable file (pyarrow's ``ArrowInvalid``,
        a ``ValueError``, for a damaged footer).
    """
    file = Path(file)
    meta = pq.ParquetFile(file).metadata
    out = []
    with open(file, "rb") as f, mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as buf:
        for g in range(meta.num_row_groups):
            for c in range(meta.num_columns):
                col = meta.row_group(g).column(c)
                # A dictionary page comes first; an empty chunk may hold only that and a data page
                # offset of 0.
                dictionary = col.dictionary_page_offset if col.has_dictionary_page else None
                start = dictionary if dictionary else col.data_page_offset
                end = start + col.total_compressed_size
                i = start
                while i < end:
                    ints, data = _struct(buf, i)
                    size = ints.get(_PAGE_SIZE)
                    if size is None or size < 0 or data + size > end:
                        raise ValueError(f"page header at byte {i} of column {col.path_in_schema} is damaged")
                    out.append(Page(col.path_in_schema, i, data, data + size, _CRC in ints))
                    i = data + size
    return out


def has_checksums(file) -> bool:
    """Whether every page of the Parquet file ``file`` carries a CRC (so pyarrow can verify it)."""
    return all(p.crc for p in pages(file))
