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
from collections.abc import Mapping
from typing import Any

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
