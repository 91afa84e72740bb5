"""Frames: a JSON header and a binary body in one payload, for numbers that need no parsing.

A frame is ``MAGIC`` (4 bytes), the header's length (unsigned 32-bit little-endian), the
header (a UTF-8 JSON object, padded with spaces so that the body starts at a multiple of 8
bytes from the frame's start) and the body: raw little-endian columns, in a layout the header
names and the message's reader knows (docs/contract.md, "Scale-out").  A JSON payload starts
with ``{``, never with ``MAGIC``, so one key can carry both forms and a reader tells them by
the first bytes.  The numbers are the sender's own bytes: read with :func:`numpy.frombuffer`,
no base64 and no JSON number in between, and bit for bit what was sent.
"""

from __future__ import annotations

import struct
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import orjson

#: A frame's first bytes ("TopoFusion frame", version 1).
MAGIC = b"TFF1"
_LENGTH = struct.Struct("<I")
_START = len(MAGIC) + _LENGTH.size
#: The body starts at a multiple of this many bytes (of its doubles' size).
ALIGN = 8


def is_frame(payload: bytes) -> bool:
    return payload[: len(MAGIC)] == MAGIC


def encode_frame(header: Mapping[str, Any], body: bytes) -> bytes:
    """``header`` (JSON, encoded with orjson and numpy's scalars) and ``body`` as one frame."""
    head = orjson.dumps(header, option=orjson.OPT_SERIALIZE_NUMPY)
    head += b" " * (-(_START + len(head)) % ALIGN)
    return b"".join((MAGIC, _LENGTH.pack(len(head)), head, body))


def decode_frame(payload: bytes) -> tuple[Any, memoryview]:
    """The header (parsed JSON, any type: the reader checks it) and a view of the body;
    ``ValueError`` when ``payload`` is not a frame (no magic, a header longer than the payload,
    a body that does not start aligned, or a header that is not JSON)."""
    if not is_frame(payload) or len(payload) < _START:
        raise ValueError("not a frame: it must start with the frame's magic and the header's length")
    (n,) = _LENGTH.unpack_from(payload, len(MAGIC))
    if n > len(payload) - _START:
        raise ValueError(f"a header of {n} bytes in a frame of {len(payload)}")
    if (_START + n) % ALIGN:
        raise ValueError(f"the body must start at a multiple of {ALIGN} bytes")
    view = memoryview(payload)
    try:
        header = orjson.loads(view[_START : _START + n])
    except orjson.JSONDecodeError as exc:
        raise ValueError(f"the frame's header is not JSON: {exc}") from None
    return header, view[_START + n :]


#: The longest id (characters) a frame of columns carries (:func:`columns_frame`).
MAX_ID_CHARS = 256
#: The header fields a frame of columns keeps for its layout.
_LAYOUT_FIELDS = ("count", "widths", "binary")
#: Unicode's code points end here; 0xD800-0xDFFF are surrogates, no characters of their own.
_CODE_POINTS_END = 0x110000
_SURROGATES = (0xD800, 0xE000)


def columns_frame(
    fields: Mapping[str, Any],
    numbers: Sequence[tuple[str, np.ndarray]],
    ids: Sequence[tuple[str, np.ndarray]],
) -> bytes | None:
    """A message of ``fields`` and columns of one row each as a frame: ``count`` rows,
    ``binary`` the columns' names in body order (``numbers`` then ``ids``), ``widths`` the
    characters of each id column.  A number column is little-endian doubles, a row's values
    then the next row's; an id column each id as ``width`` UTF-32LE code units padded with NUL
    (numpy's own string form: the arrays' bytes as they are).  None when an id is longer than
    :data:`MAX_ID_CHARS` (send the JSON form then)."""
    id_cols = [np.asarray(col, dtype=str) for _, col in ids]
    widths = [max(col.dtype.itemsize // 4, 1) for col in id_cols]
    if widths and max(widths) > MAX_ID_CHARS:
        return None
    count = len(id_cols[0]) if id_cols else len(numbers[0][1])
    header = {**fields, "count": count, "widths": widths, "binary": [n for n, _ in (*numbers, *ids)]}
    body = [np.ascontiguousarray(col, dtype="<f8").tobytes() for _, col in numbers]
    body += [col.astype(f"<U{w}").tobytes() for col, w in zip(id_cols, widths, strict=True)]
    return encode_frame(header, b"".join(body))


def read_columns(
    payload: bytes,
    numbers: Sequence[tuple[str, int]],
    ids: Sequence[str],
    optional: frozenset[str] = frozenset(),
    *,
    max_rows: int,
) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """A frame of :func:`columns_frame`: its header's other fields, and its columns (a number
    column ``(count,)`` or ``(count, width)`` doubles, ``width`` from ``numbers``; an id column
    numpy strings), read-only views of ``payload``.  ``ValueError`` saying what is wrong when
    it does not hold the layout: ``binary`` must name ``numbers`` (those in ``optional`` may be
    left out) then ``ids``, in order; ``count`` and ``widths`` (1..:data:`MAX_ID_CHARS`) must
    be integers; no column may be in the header too; the body must be exactly the columns'
    bytes, and every id code unit a Unicode scalar value."""
    header, data = decode_frame(payload)
    if not isinstance(header, dict):
        raise ValueError("the header is not an object")
    names = header.get("binary")
    present = [(name, width) for name, width in numbers if not isinstance(names, list) or name in names]
    layout = [name for name, _ in present] + list(ids)
    if names != layout or any(name not in names for name, _ in numbers if name not in optional):
        want = [n for n, _ in numbers] + list(ids)
        raise ValueError(f"binary must be {want} (optional: {sorted(optional)})")
    if any(name in header for name in layout):
        raise ValueError("a binary column is repeated in the header")
    n, widths = header.get("count"), header.get("widths")
    if type(n) is not int or not 0 <= n <= max_rows:
        raise ValueError(f"count must be an integer 0..{max_rows}")
    if (
        not isinstance(widths, list)
        or len(widths) != len(ids)
        or not all(type(w) is int and 1 <= w <= MAX_ID_CHARS for w in widths)
    ):
        raise ValueError(f"widths must be {len(ids)} integers 1..{MAX_ID_CHARS}")
    size = n * (8 * sum(width for _, width in present) + 4 * sum(widths))
    if len(data) != size:
        raise ValueError(f"a body of {len(data)} bytes, {size} for {n} rows")
    cols: dict[str, np.ndarray] = {}
    at = 0
    for name, width in present:
        a = np.frombuffer(data, dtype="<f8", count=n * width, offset=at)
        cols[name] = a.reshape(n, width) if width > 1 else a
        at += a.nbytes
    units = np.frombuffer(data, dtype="<u4", offset=at)
    if np.any(units >= _CODE_POINTS_END) or np.any((units >= _SURROGATES[0]) & (units < _SURROGATES[1])):
        raise ValueError("ids must be UTF-32LE characters")
    for name, width in zip(ids, widths, strict=True):
        cols[name] = np.frombuffer(data, dtype=f"<U{width}", count=n, offset=at)
        at += 4 * width * n
    return {k: v for k, v in header.items() if k not in _LAYOUT_FIELDS}, cols
