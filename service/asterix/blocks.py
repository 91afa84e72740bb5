"""ASTERIX data blocks: encoded records packed into blocks (CAT, LEN, records), e.g. one per
UDP datagram.  Used by the CAT062 output (:mod:`.cat062`) and the test encoder."""

from __future__ import annotations

import struct
from collections.abc import Iterable

#: The largest data block (LEN is 16 bit and counts the 3-octet header).
MAX_BLOCK = 0xFFFF
_H = struct.Struct(">H").pack


def block(cat: int, records: Iterable[bytes]) -> bytes:
    """One data block of encoded records; ValueError beyond the 16-bit LEN."""
    body = b"".join(records)
    if len(body) + 3 > MAX_BLOCK:
        raise ValueError(f"{len(body) + 3} octets do not fit one data block")
    return bytes((cat,)) + _H(len(body) + 3) + body


def pack_blocks(cat: int, records: Iterable[bytes], max_bytes: int = 1400) -> list[bytes]:
    """Encoded records as data blocks of at most ``max_bytes`` octets each (e.g. one UDP datagram
    each), in order, as full as they go; ValueError if one record does not fit."""
    if not 4 <= max_bytes <= MAX_BLOCK:
        raise ValueError(f"max_bytes {max_bytes} not in [4, {MAX_BLOCK}]")
    blocks: list[bytes] = []
    current: list[bytes] = []
    size = 3
    for rec in records:
        if size + len(rec) > max_bytes:
            if not current:
                raise ValueError(f"a record of {len(rec)} octets does not fit {max_bytes}-octet blocks")
            blocks.append(block(cat, current))
            current, size = [], 3
            if size + len(rec) > max_bytes:
                raise ValueError(f"a record of {len(rec)} octets does not fit {max_bytes}-octet blocks")
        current.append(rec)
        size += len(rec)
    if current:
        blocks.append(block(cat, current))
    return blocks
