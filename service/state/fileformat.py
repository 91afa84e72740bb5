"""The state file: a fixed head, a JSON header, a numpy ``.npz`` body and a SHA-256 trailer.

Layout (all integers big-endian)::

    16 bytes  MAGIC  b"TOPOFUSION-STATE"
     4 bytes  format version (VERSION)
     4 bytes  header length H
     H bytes  header, JSON: prefix, partition, epoch, data_clock_s, written_unix_s
     ...      body: an .npz archive (numpy's zip of arrays): ``tree``, the state as JSON text
              whose arrays are references ``{"__array__": "a7"}``, and the arrays themselves
    32 bytes  SHA-256 of everything before it

The version is read before anything else, so a later format can change all that follows it.
The digest covers the whole file: a flipped byte anywhere or a file cut short is refused
before any of it is believed.  Nothing is unpickled: the body is read with
``np.load(allow_pickle=False)``, and arrays of Python objects are never written.

Bump :data:`VERSION` whenever :class:`~service.engine.EngineState` or anything it holds
changes shape: an older or newer file is then refused (and the service starts clean) rather
than misread.
"""

from __future__ import annotations

import hashlib
import io
import json
import struct
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

MAGIC = b"TOPOFUSION-STATE"
VERSION = 1
_HEAD = struct.Struct(">16sII")  # magic, version, header length
_DIGEST_BYTES = 32
_ARRAY = "__array__"
#: The header is a few hundred bytes; a length beyond this is a file that is not one.
_MAX_HEADER_BYTES = 1 << 20
#: Epochs beyond this are not believed (a damaged header): ids must stay within 64 bits, and a
#: million starts is a restart every minute for two years.
MAX_EPOCH = 1_000_000


class RefusedError(Exception):
    """A state file that is not taken; ``str()`` says why in a few words.  ``epoch``: the
    file's track-id epoch when its header could be read (else None)."""

    def __init__(self, why: str, epoch: int | None = None) -> None:
        super().__init__(why)
        self.epoch = epoch


@dataclass(frozen=True)
class Header:
    """What a state file says of itself."""

    prefix: str
    partition: str
    #: The track-id epoch of the start that wrote it.
    epoch: int
    #: The newest data clock of the state (None: no data yet).
    data_clock_s: float | None
    #: Wall-clock time of the write (UNIX s), for an operator's eyes only.
    written_unix_s: float


def encode(header: Header, tree: dict[str, Any]) -> bytes:
    """The whole file of ``tree`` (plain values, lists, dicts with string keys, numpy arrays)."""
    arrays: dict[str, Any] = {}
    text = json.dumps(_flatten(tree, arrays), separators=(",", ":")).encode()
    body = io.BytesIO()
    # allow_pickle=False: an array of Python objects raises here instead of being pickled
    np.savez(body, allow_pickle=False, tree=np.frombuffer(text, dtype=np.uint8), **arrays)
    head = json.dumps(asdict(header)).encode()
    out = io.BytesIO()
    out.write(_HEAD.pack(MAGIC, VERSION, len(head)))
    out.write(head)
    out.write(body.getbuffer())
    out.write(hashlib.sha256(out.getbuffer()).digest())
    return out.getvalue()


def decode(data: bytes, prefix: str, partition: str) -> tuple[Header, dict[str, Any]]:
    """The header and tree of a file :func:`encode` wrote for ``prefix`` and ``partition``;
    :class:`RefusedError` saying why otherwise."""
    if len(data) < _HEAD.size + _DIGEST_BYTES:
        raise RefusedError(f"truncated: {len(data)} bytes")
    magic, version, head_len = _HEAD.unpack_from(data)
    if magic != MAGIC:
        raise RefusedError("not a TopoFusion state file (no magic string)")
    if version != VERSION:
        raise RefusedError(
            f"format version {version}, this service reads version {VERSION}", peek_epoch(data)
        )
    content, digest = memoryview(data)[:-_DIGEST_BYTES], data[-_DIGEST_BYTES:]
    if hashlib.sha256(content).digest() != digest:
        raise RefusedError("checksum mismatch: the file is corrupt or truncated", peek_epoch(data))
    header = _header(data, head_len)
    if header is None:
        raise RefusedError("unreadable header")
    if (header.prefix, header.partition) != (prefix, partition):
        raise RefusedError(
            f"written for prefix {header.prefix!r} partition {header.partition}, this service runs "
            f"prefix {prefix!r} partition {partition}",
            header.epoch,
        )
    try:
        with np.load(io.BytesIO(content[_HEAD.size + head_len :]), allow_pickle=False) as npz:
            arrays = {name: npz[name] for name in npz.files}
        tree = _unflatten(json.loads(arrays.pop("tree").tobytes()), arrays)
    except Exception as exc:  # whatever a damaged archive raises: the file is refused, not the start
        raise RefusedError(f"unreadable body ({type(exc).__name__}: {exc})", header.epoch) from None
    if not isinstance(tree, dict):
        raise RefusedError("unreadable body (not a state)", header.epoch)
    return header, tree


def peek_epoch(data: bytes) -> int | None:
    """The epoch in a file's header if it can be read at all, whatever else is wrong with the
    file (a refused file's epoch still counts: ids are not reused)."""
    if len(data) < _HEAD.size:
        return None
    header = _header(data, _HEAD.unpack_from(data)[2])
    return None if header is None else header.epoch


def _header(data: bytes, length: int) -> Header | None:
    if length > _MAX_HEADER_BYTES or _HEAD.size + length > len(data):
        return None
    try:
        fields = json.loads(data[_HEAD.size : _HEAD.size + length])
        header = Header(**fields)
    except (ValueError, TypeError):
        return None
    if not (isinstance(header.epoch, int) and 0 <= header.epoch < MAX_EPOCH):
        return None
    return header


def _flatten(value: Any, arrays: dict[str, Any]) -> Any:
    """``value`` as JSON-ready values, its arrays moved to ``arrays`` (referenced by name)."""
    if isinstance(value, np.ndarray):
        name = f"a{len(arrays)}"
        arrays[name] = value
        return {_ARRAY: name}
    if isinstance(value, dict):
        return {str(k): _flatten(v, arrays) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_flatten(v, arrays) for v in value]
    if isinstance(value, np.generic):
        return value.item()
    if value is None or isinstance(value, (str, int, float, bool)):
        return value
    raise TypeError(f"a {type(value).__name__} cannot be kept")


def _unflatten(value: Any, arrays: dict[str, np.ndarray]) -> Any:
    if isinstance(value, dict):
        if len(value) == 1 and _ARRAY in value:
            return arrays[value[_ARRAY]]
        return {k: _unflatten(v, arrays) for k, v in value.items()}
    if isinstance(value, list):
        return [_unflatten(v, arrays) for v in value]
    return value
