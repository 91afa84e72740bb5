"""The state file: a fixed head, a JSON header, a numpy ``.npz`` body and a SHA-256 trailer.

Layout (all integers big-endian)::

    16 bytes  MAGIC  b"TOPOFUSION-STATE"
     4 bytes  format version (VERSION)
     4 bytes  header length H
     H bytes  header, JSON: prefix, partition, epoch, data_clock_s, written_unix_s (then spaces:
              room for :func:`rewrite_epoch` to write a longer epoch in place)
     ...      body: an .npz archive (numpy's zip of arrays): ``tree``, the state as JSON text
              whose arrays are references ``{"__array__": "a7"}``, and the arrays themselves
    32 bytes  SHA-256 of everything before it

The version is read before anything else, so a later format can change all that follows it.
The digest covers the whole file: a flipped byte anywhere or a file cut short is refused
before any of it is believed.  Nothing is unpickled, and numpy's loader is not used: the body
is read here (:func:`_members`, :func:`_array`), which keeps every size it believes bounded.

A file is read at every start, before any input, so whatever lies in its place must not cost
more than a bounded amount of time and memory (each bound a named constant below):

* **Only a regular file** is opened (:func:`read_file`): the type is checked before the open
  (a FIFO would block the start, a device has no end) and again on the open descriptor; a
  symbolic link to a regular file is followed, one to anything else is refused.
* **At most** :data:`MAX_FILE_BYTES`, checked on the size before a byte is read, and the read
  never takes more than that size (a file growing meanwhile is refused).
* **Inflation bounded by what the archive declares.**  The archive's central directory declares
  each member's size; their sum must be at most :data:`MAX_INFLATED_BYTES` before anything is
  inflated, a member is inflated into exactly its declared size (``zlib`` with ``max_length``:
  never more than one byte past it) and must fill it, and its array header must account for
  those bytes exactly.  Peak memory of a load is the file's bytes plus the declared sizes, and
  :data:`MAX_ARRAYS` and :data:`MAX_TREE_BYTES` bound the per-array and JSON overheads.

Bump :data:`VERSION` whenever :class:`~service.engine.EngineState` or anything it holds
changes shape: an older or newer file is then refused (and the service starts clean) rather
than misread.
"""

from __future__ import annotations

import errno
import hashlib
import io
import json
import os
import stat
import struct
import zlib
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

MAGIC = b"TOPOFUSION-STATE"
VERSION = 1
_HEAD = struct.Struct(">16sII")  # magic, version, header length
_DIGEST_BYTES = 32
_ARRAY = "__array__"
#: The header is a few hundred bytes; a length beyond this is a file that is not one.
_MAX_HEADER_BYTES = 1 << 20
#: Spaces after the header's JSON: :func:`rewrite_epoch` writes the next epoch in place, and an
#: epoch with more digits (and nothing else) must still fit.
_HEADER_ROOM = 16
#: Track-id epochs a state directory can number (0 to ``MAX_EPOCH - 1``): start ``E`` numbers
#: its tracks from ``E * 10**9 + 1``, so ids stay below 10^15, exact even as a float64.  A
#: million starts is a restart every minute for two years; a start that would need epoch
#: ``MAX_EPOCH`` is refused (:mod:`.keeper`) rather than reuse an id.
MAX_EPOCH = 1_000_000
#: Largest state file read (bytes).  The registration memories dominate it: a national network
#: (12 radars, 66 pairs) writes 46.5 MB after ten minutes, and even with every pair's memory
#: at its own bound (``max_rows`` 40 000 rows of about 226 bytes) 0.6 GB.  A file beyond this
#: was not written by this service for a network it can run; the writer refuses to write one.
MAX_FILE_BYTES = 1 << 30
#: Largest sum of the body's declared (inflated) member sizes (bytes): the file's own writer
#: stores its arrays uncompressed, so this is the file's size again.
MAX_INFLATED_BYTES = 1 << 30
#: Most arrays (archive members) in a body: each costs a few hundred bytes of bookkeeping
#: beyond its data.  A national network's file has about 500 (seven a registration memory).
MAX_ARRAYS = 20_000
#: Largest ``tree`` (the JSON text of everything but the arrays: sites, source clocks, one
#: small dict a registration memory), bytes.  Parsed JSON can take 26 times its text in memory,
#: so this bounds that overhead (to about 26 MB); a national network's tree is about 50 kB.
MAX_TREE_BYTES = 1 << 20
#: Input read (and inflated) per step when a member is inflated or a file is hashed (bytes).
_CHUNK = 1 << 20

_ZIP_END = struct.Struct("<4s4H2LH")  # end of central directory (22 bytes)
_ZIP_CENTRAL = struct.Struct("<4s4B4HL2L5H2L")  # central directory entry (46 bytes + names)
_ZIP_LOCAL = struct.Struct("<4s2B4HL2L2H")  # local file header (30 bytes + names)
_STORED, _DEFLATED = 0, 8
#: Array element kinds a state holds: booleans, integers, floats and unicode text.
_KINDS = "biufU"


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
    #: The newest data clock of the state (None: no data yet): the data time the file was
    #: written at, which no kept source clock may be ahead of (:mod:`.content`).
    data_clock_s: float | None
    #: Wall-clock time of the write (UNIX s): an operator's, and the plausibility of the data
    #: clock (:data:`~service.state.content.MAX_AHEAD_OF_WALL_S`).
    written_unix_s: float


def encode(header: Header, tree: dict[str, Any]) -> bytes:
    """The whole file of ``tree`` (plain values, lists, dicts with string keys, numpy arrays)."""
    arrays: dict[str, Any] = {}
    text = json.dumps(_flatten(tree, arrays), separators=(",", ":")).encode()
    body = io.BytesIO()
    # allow_pickle=False: an array of Python objects raises here instead of being pickled
    np.savez(body, allow_pickle=False, tree=np.frombuffer(text, dtype=np.uint8), **arrays)
    head = json.dumps(asdict(header)).encode() + b" " * _HEADER_ROOM
    out = io.BytesIO()
    out.write(_HEAD.pack(MAGIC, VERSION, len(head)))
    out.write(head)
    out.write(body.getbuffer())
    out.write(hashlib.sha256(out.getbuffer()).digest())
    return out.getvalue()


def read_file(path: Path) -> bytearray:
    """The bytes of the state file at ``path``, or :class:`RefusedError` if what is there is not
    a regular file of at most :data:`MAX_FILE_BYTES` (module docstring); ``FileNotFoundError``
    if there is nothing (or a symbolic link to nothing), other ``OSError`` if it cannot be read.
    """
    link = os.lstat(path)
    try:
        st = os.stat(path)  # a symbolic link is judged by what it points at
    except FileNotFoundError:
        raise FileNotFoundError(errno.ENOENT, "a symbolic link to nothing", str(path)) from None
    if not stat.S_ISREG(st.st_mode):  # checked before the open: a FIFO's open would block
        what = _kind(st.st_mode)
        if stat.S_ISLNK(link.st_mode):
            what = f"a symbolic link to {what}"
        raise RefusedError(f"not a regular file but {what}")
    _check_size(st.st_size)
    # O_NONBLOCK: should it have become a FIFO since the check, the open still returns
    fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0))
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise RefusedError(f"not a regular file but {_kind(st.st_mode)}")
        _check_size(st.st_size)
        data = bytearray(st.st_size)
        view = memoryview(data)
        got = 0
        while got < len(data):
            n = os.readv(fd, [view[got:]])
            if n == 0:
                raise RefusedError(f"changed while read: {got} bytes of {len(data)}")
            got += n
        if os.read(fd, 1):
            raise RefusedError(f"changed while read: more than its {len(data)} bytes")
    finally:
        os.close(fd)
    return data


def _kind(mode: int) -> str:
    for test, what in (
        (stat.S_ISFIFO, "a FIFO"),
        (stat.S_ISCHR, "a character device"),
        (stat.S_ISBLK, "a block device"),
        (stat.S_ISDIR, "a directory"),
        (stat.S_ISSOCK, "a socket"),
    ):
        if test(mode):
            return what
    return f"a file of mode {mode:o}"


def _check_size(size: int) -> None:
    if size > MAX_FILE_BYTES:
        raise RefusedError(f"{size} bytes, more than the {MAX_FILE_BYTES} a state file may have")


def decode(data: bytes | bytearray, prefix: str, partition: str) -> tuple[Header, dict[str, Any]]:
    """The header and tree of a file :func:`encode` wrote for ``prefix`` and ``partition``;
    :class:`RefusedError` saying why otherwise."""
    if len(data) < _HEAD.size + _DIGEST_BYTES:
        raise RefusedError(f"truncated: {len(data)} bytes")
    _check_size(len(data))
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
        arrays = {name: _array(data) for name, data in _members(content[_HEAD.size + head_len :])}
        tree_text = arrays.pop("tree")
        if tree_text.dtype != np.uint8 or tree_text.ndim != 1:
            raise ValueError(f"tree of {tree_text.dtype} {tree_text.shape}")
        if tree_text.size > MAX_TREE_BYTES:  # before it is parsed (module docstring)
            raise ValueError(f"tree of {tree_text.size} bytes, more than the {MAX_TREE_BYTES} it may have")
        tree = _unflatten(json.loads(tree_text.tobytes()), arrays)
    except RefusedError as exc:
        raise RefusedError(str(exc), header.epoch) from None
    except Exception as exc:  # whatever a damaged archive raises: the file is refused, not the start
        raise RefusedError(f"unreadable body ({type(exc).__name__}: {exc})", header.epoch) from None
    if not isinstance(tree, dict):
        raise RefusedError("unreadable body (not a state)", header.epoch)
    return header, tree


def _members(body: memoryview) -> list[tuple[str, memoryview | bytearray]]:
    """The archive's members as ``(name without .npy, bytes)``: stored ones as views of
    ``body``, deflated ones inflated into exactly their declared size (module docstring).

    Only what numpy's ``savez`` writes is read: one archive, no comment, no zip64, members
    stored or deflated, not encrypted, one after the other."""
    if len(body) < _ZIP_END.size:
        raise RefusedError(f"unreadable body (an archive of {len(body)} bytes)")
    sig, disk, cd_disk, n_here, n, cd_size, cd_at, comment = _ZIP_END.unpack_from(
        body, len(body) - _ZIP_END.size
    )
    if sig != b"PK\x05\x06" or disk or cd_disk or n_here != n or comment:
        raise RefusedError("unreadable body (no end of archive where it should be)")
    if n > MAX_ARRAYS:
        raise RefusedError(f"unreadable body ({n} arrays, more than the {MAX_ARRAYS} a state may have)")
    if cd_at + cd_size != len(body) - _ZIP_END.size:
        raise RefusedError("unreadable body (its directory is not where it says)")
    entries = []
    at = cd_at
    for _ in range(n):
        if at + _ZIP_CENTRAL.size > cd_at + cd_size:
            raise RefusedError("unreadable body (its directory is cut short)")
        (
            sig,
            _,
            _,
            _,
            _,
            flags,
            method,
            _,
            _,
            crc,
            csize,
            size,
            name_len,
            extra_len,
            comment_len,
            _,
            _,
            _,
            offset,
        ) = _ZIP_CENTRAL.unpack_from(body, at)
        name = bytes(body[at + _ZIP_CENTRAL.size : at + _ZIP_CENTRAL.size + name_len]).decode(
            "utf-8", "replace"
        )
        at += _ZIP_CENTRAL.size + name_len + extra_len + comment_len
        if sig != b"PK\x01\x02" or at > cd_at + cd_size:
            raise RefusedError("unreadable body (a damaged directory entry)")
        if flags & 0x1 or method not in (_STORED, _DEFLATED) or (method == _STORED and csize != size):
            raise RefusedError(f"unreadable body (array {name!r}: flags {flags:#x}, method {method})")
        if not name.endswith(".npy"):
            raise RefusedError(f"unreadable body (a member {name!r})")
        entries.append((offset, name[: -len(".npy")], method, crc, csize, size))
    declared = sum(e[5] for e in entries)
    if declared > MAX_INFLATED_BYTES:  # before anything is inflated
        raise RefusedError(
            f"unreadable body (arrays of {declared} bytes declared, more than the "
            f"{MAX_INFLATED_BYTES} a state may have)"
        )
    out: dict[str, memoryview | bytearray] = {}
    end = 0  # members one after the other: none shares another's bytes
    for offset, name, method, crc, csize, size in sorted(entries):
        if name in out:
            raise RefusedError(f"unreadable body (two arrays named {name!r})")
        if offset < end or offset + _ZIP_LOCAL.size > cd_at:
            raise RefusedError(f"unreadable body (array {name!r} overlaps another)")
        sig, _, _, _, local_method, _, _, _, _, _, name_len, extra_len = _ZIP_LOCAL.unpack_from(body, offset)
        start = offset + _ZIP_LOCAL.size + name_len + extra_len
        end = start + csize
        if sig != b"PK\x03\x04" or local_method != method or end > cd_at:
            raise RefusedError(f"unreadable body (array {name!r}: a damaged header)")
        data = body[start:end] if method == _STORED else _inflate(body[start:end], size, name)
        if zlib.crc32(data) != crc:
            raise RefusedError(f"unreadable body (array {name!r}: CRC mismatch)")
        out[name] = data
    return list(out.items())


def _inflate(deflated: memoryview, size: int, name: str) -> bytearray:
    """``deflated`` inflated into exactly ``size`` bytes: refused as soon as it would give more
    (never more than one byte past ``size`` is inflated) or when it gives fewer."""
    out = bytearray(size)
    inflater = zlib.decompressobj(-zlib.MAX_WBITS)
    got, taken = 0, 0
    while not inflater.eof:
        if inflater.unconsumed_tail:
            chunk: bytes | memoryview = inflater.unconsumed_tail
        elif taken < len(deflated):
            chunk, taken = deflated[taken : taken + _CHUNK], taken + _CHUNK
        else:
            break
        piece = inflater.decompress(chunk, size - got + 1)
        if got + len(piece) > size:
            raise RefusedError(f"unreadable body (array {name!r} inflates beyond its declared {size} bytes)")
        out[got : got + len(piece)] = piece
        got += len(piece)
    if not inflater.eof or got != size or inflater.unused_data or taken < len(deflated):
        raise RefusedError(f"unreadable body (array {name!r}: {got} bytes inflated, {size} declared)")
    return out


def _array(data: memoryview | bytearray) -> np.ndarray:
    """The array of one ``.npy`` member; its header must account for its bytes exactly.  A
    stored member (a view of the file) is copied, an inflated one is used as it is."""
    fp = io.BytesIO(data[: min(len(data), 65_536)])
    major, _ = np.lib.format.read_magic(fp)
    if major == 1:
        shape, fortran, dtype = np.lib.format.read_array_header_1_0(fp)
    elif major == 2:
        shape, fortran, dtype = np.lib.format.read_array_header_2_0(fp)
    else:  # (3.0 only for field names beyond latin-1: structured arrays are not kept)
        raise ValueError(f"array format {major}")
    if dtype.hasobject or dtype.fields is not None or dtype.kind not in _KINDS:
        raise ValueError(f"arrays of {dtype} are not kept")
    count = 1
    for dim in shape:
        count *= int(dim)
    if any(int(dim) < 0 for dim in shape) or count * dtype.itemsize != len(data) - fp.tell():
        raise ValueError(f"an array of shape {shape} in {len(data) - fp.tell()} bytes")
    array = np.frombuffer(data, dtype=dtype, count=count, offset=fp.tell())
    array = array.reshape(shape, order="F" if fortran else "C")
    return array.copy() if isinstance(data, memoryview) else array


def peek_epoch(data: bytes | bytearray) -> int | None:
    """The epoch in a file's header if it can be read at all, whatever else is wrong with the
    file (a refused file's epoch still counts: ids are not reused)."""
    if len(data) < _HEAD.size:
        return None
    header = _header(data, _HEAD.unpack_from(data)[2])
    return None if header is None else header.epoch


def _header(data: bytes | bytearray | memoryview, length: int) -> Header | None:
    if length > _MAX_HEADER_BYTES or _HEAD.size + length > len(data):
        return None
    try:
        fields = json.loads(bytes(data[_HEAD.size : _HEAD.size + length]))
        header = Header(**fields)
    except (ValueError, TypeError):
        return None
    # any epoch a whole header states counts, however large: the keeper refuses to go beyond
    # MAX_EPOCH rather than start again from 0
    if not (isinstance(header.epoch, int) and not isinstance(header.epoch, bool) and header.epoch >= 0):
        return None
    return header


def rewrite_epoch(path: Path, epoch: int, whole: bool) -> None:
    """Write ``epoch`` into the header of the state file at ``path`` in place: no new file, no
    new block, so it works where a new file cannot be written (a full disk, a directory the
    service may not write).  ``whole``: the file passed its checksum, which is then updated
    too (the file stays whole); otherwise only the header changes (the file stays refused, its
    epoch counts).  ``OSError`` when it cannot be done; nothing is changed then, but for a
    failure between the header and the checksum, after which the file is refused and its new
    epoch still counts (the header is written first for that reason)."""
    fd = os.open(path, os.O_RDWR | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0))
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode) or st.st_size > MAX_FILE_BYTES:
            raise OSError(errno.EINVAL, "not a state file")
        head = os.pread(fd, _HEAD.size, 0)
        if len(head) < _HEAD.size or _HEAD.unpack(head)[0] != MAGIC:
            raise OSError(errno.EINVAL, "not a state file")
        length = _HEAD.unpack(head)[2]
        if length > _MAX_HEADER_BYTES:
            raise OSError(errno.EINVAL, "unreadable header")
        old = os.pread(fd, length, _HEAD.size)
        header = _header(head + old, length)
        if header is None:
            raise OSError(errno.EINVAL, "unreadable header")
        new = json.dumps(asdict(replace(header, epoch=epoch))).encode()
        if len(new) > length:
            raise OSError(errno.ENOSPC, "no room in the header for the epoch")
        new = new.ljust(length, b" ")
        digest_at = st.st_size - _DIGEST_BYTES
        old_digest = os.pread(fd, _DIGEST_BYTES, digest_at)
        if whole:
            before, after = hashlib.sha256(head + old), hashlib.sha256(head + new)
            at = _HEAD.size + length
            while at < digest_at:
                chunk = os.pread(fd, min(_CHUNK, digest_at - at), at)
                if not chunk:
                    raise OSError(errno.EINVAL, "changed while read")
                before.update(chunk)
                after.update(chunk)
                at += len(chunk)
            if before.digest() != old_digest:
                whole = False  # not whole after all: its checksum is left as it is
        # the same bytes written again first: a write that must fail (a file-size limit, a
        # copy-on-write file system without room) fails here, before anything has changed
        _pwrite(fd, old, _HEAD.size)
        if whole:
            _pwrite(fd, old_digest, digest_at)
        os.fsync(fd)
        _pwrite(fd, new, _HEAD.size)
        os.fsync(fd)
        if whole:
            _pwrite(fd, after.digest(), digest_at)
            os.fsync(fd)
    finally:
        os.close(fd)


def _pwrite(fd: int, data: bytes, at: int) -> None:
    if os.pwrite(fd, data, at) != len(data):
        raise OSError(errno.EIO, f"short write at {at}")


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
