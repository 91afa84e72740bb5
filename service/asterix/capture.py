"""Datagrams from files: pcap and pcapng captures of UDP traffic, and raw ASTERIX recordings.

The input side of ``topofusion asterix`` for files.  :func:`read_datagrams` streams a file and
yields :class:`Datagram` objects (the UDP payloads, i.e. ASTERIX data blocks, with capture time and
addresses); it does no ASTERIX decoding.  :func:`detect_format` tells the three kinds apart by their
first octets.

Formats:

* **pcap**, the libpcap file format (https://www.tcpdump.org/manpages/pcap-savefile.5.html and
  draft-ietf-opsawg-pcap): both byte orders, microsecond (``0xA1B2C3D4``) and nanosecond
  (``0xA1B23C4D``) time stamps.
* **pcapng**, the PCAP Next Generation capture file format (draft-ietf-opsawg-pcapng): sections in
  either byte order (several per file), Interface Description Blocks with ``if_tsresol`` (default
  microseconds) and ``if_tsoffset``, Enhanced, Simple (no time stamp: ``time_s`` is None) and
  obsolete Packet Blocks; other block types are skipped by their length.
* **raw**: the file is ASTERIX data blocks one after the other (CAT, LEN, records), yielded in
  chunks of whole data blocks of at most 64 KiB (:data:`RAW_CHUNK_BYTES`) with ``time_s`` None.

Link types (http://www.tcpdump.org/linktypes.html): Ethernet (1, with 802.1Q / 802.1ad / QinQ VLAN
tags), raw IP (101, and 12 as some old writers put it; 228 IPv4, 229 IPv6), Linux cooked capture
SLL (113) and SLL2 (276), BSD loopback / null (0, family in the writer's byte order) and OpenBSD
loopback (108).  Network layer IPv4 (options, fragments reassembled) and IPv6 (hop-by-hop,
routing, destination options and authentication headers skipped; fragments reassembled); UDP only.

Nothing in a file's body raises: every frame that yields no datagram is counted by cause in the
caller's :class:`collections.Counter` (names in :data:`COUNTER_NAMES`), and reading stops (counted)
where the file cannot be framed any further.  Only a file that cannot be read as any of the formats
at all (unopenable, a garbage or truncated file header) raises :class:`CaptureError`, and it does so
when :func:`read_datagrams` is called, before the first datagram.

Corrupted files, precisely:

* a record or block header with an impossible length (pcap ``caplen`` above 16 MiB; pcapng total
  length below 12, not a multiple of 4, above 16 MiB for a packet block, a trailing length that
  differs, or a later section header with an unknown byte-order magic): ``bad_block``, and reading
  of that file stops, since nothing after it can be framed;
* a pcapng block that is framed correctly but inconsistent inside (unknown interface, captured
  length past the block, a packet block before any interface): ``bad_block``, and reading goes on;
* the file ends inside a record or block: ``truncated_file``;
* a raw file whose data block has LEN < 3 or runs past the end: the rest of the file is yielded as
  one final chunk for the decoder to count; when that rest exceeds 64 KiB only its first 64 KiB are
  yielded and ``bad_block`` counts the abandoned remainder.

Frames: ``not_ip`` (not IPv4/IPv6, or a malformed IP header), ``not_udp`` (another protocol, or a
malformed UDP header), ``truncated_frame`` (captured length shorter than the IP or UDP length
says), ``unsupported_link_type``, ``fragment_lost`` (a fragmented datagram never completed: evicted
from the bounded reassembly buffer, at most :data:`MAX_PENDING_FRAGMENTED` datagrams and
:data:`FRAGMENT_TIMEOUT_S` of capture time, or still incomplete at the end of the file).

Reading is streamed (one record or block in memory at a time) and linear in the file's size.
"""

from __future__ import annotations

import collections
import socket
import struct
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import BinaryIO, Literal

CaptureFormat = Literal["pcap", "pcapng", "raw"]

#: Every counter name this module uses.
COUNTER_NAMES = (
    "not_ip",
    "not_udp",
    "truncated_frame",
    "fragment_lost",
    "bad_block",
    "truncated_file",
    "unsupported_link_type",
)

#: Largest chunk of a raw file handed out at once (whole data blocks; one block is at most 65535).
RAW_CHUNK_BYTES = 65536
#: Bounds of the IPv4/IPv6 fragment reassembly buffer.
MAX_PENDING_FRAGMENTED = 64
FRAGMENT_TIMEOUT_S = 30.0
#: Largest pcap record / pcapng packet block read into memory; a bigger length is corruption.
MAX_RECORD_BYTES = 1 << 24

_READ_BUFFER = 1 << 20

# pcap magic numbers as they appear in the file -> (struct byte order, time stamp units per second)
_PCAP_MAGICS: dict[bytes, tuple[str, int]] = {
    b"\xd4\xc3\xb2\xa1": ("<", 1_000_000),
    b"\xa1\xb2\xc3\xd4": (">", 1_000_000),
    b"\x4d\x3c\xb2\xa1": ("<", 1_000_000_000),
    b"\xa1\xb2\x3c\x4d": (">", 1_000_000_000),
}
# Alexey Kuznetzov's modified pcap (longer record headers): recognised only to refuse it clearly.
_PCAP_MODIFIED_MAGICS = (b"\x34\xcd\xb2\xa1", b"\xa1\xb2\xcd\x34")
_PCAPNG_SHB = b"\x0a\x0d\x0d\x0a"
_PCAPNG_BOM_BIG = b"\x1a\x2b\x3c\x4d"
_PCAPNG_BOM_LITTLE = b"\x4d\x3c\x2b\x1a"
_COMPRESSED_MAGICS = {
    b"\x1f\x8b": "gzip",
    b"BZh": "bzip2",
    b"\xfd7zXZ\x00": "xz",
    b"\x28\xb5\x2f\xfd": "zstd",
    b"PK\x03\x04": "zip",
}

# Link types.
_LINKTYPE_NULL = 0
_LINKTYPE_ETHERNET = 1
_LINKTYPE_RAW_OLD = 12
_LINKTYPE_RAW = 101
_LINKTYPE_LOOP = 108
_LINKTYPE_LINUX_SLL = 113
_LINKTYPE_IPV4 = 228
_LINKTYPE_IPV6 = 229
_LINKTYPE_LINUX_SLL2 = 276

_ETHERTYPE_IPV4 = 0x0800
_ETHERTYPE_IPV6 = 0x86DD
_ETHERTYPE_VLAN = (0x8100, 0x88A8, 0x9100)
# BSD address families for IPv6 on the loopback / null link (Linux 10, BSDs 24, FreeBSD 28, Darwin 30).
_AF_INET6_VALUES = (10, 24, 28, 30)

_IPPROTO_UDP = 17
_IPV6_SKIPPED_HEADERS = (0, 43, 60)  # hop-by-hop, routing, destination options: (len + 1) * 8 octets
_IPV6_FRAGMENT = 44
_IPV6_AUTH = 51  # (len + 2) * 4 octets

_U16 = struct.Struct(">H")
_UDP_HEADER = struct.Struct(">HHH")


@dataclass(frozen=True)
class Datagram:
    """One UDP payload (for raw files: one chunk of whole data blocks) and where it came from."""

    payload: bytes
    #: Capture time stamp, Unix seconds (UTC), for pcap / pcapng packets that carry one; None for raw
    #: files, pcapng Simple Packet Blocks and datagrams received live.
    time_s: float | None
    #: "ip:port" of the sender ("[ip]:port" for IPv6) if known, else "".
    source: str
    #: "ip:port" of the destination ("[ip]:port" for IPv6) if known, else "".
    destination: str


class CaptureError(Exception):
    """A file that cannot be read at all as the format it claims or looks like; says which and why."""


def detect_format(head: bytes) -> CaptureFormat:
    """The file format from its first octets (at least 4): pcap or pcapng by magic number, else raw."""
    if head[:4] in _PCAP_MAGICS:
        return "pcap"
    if head[:4] == _PCAPNG_SHB:
        return "pcapng"
    return "raw"


def read_datagrams(path: Path, counters: collections.Counter[str]) -> Iterator[Datagram]:
    """The datagrams in a capture or raw file, streamed in file order.

    The file's header is checked now (:class:`CaptureError` if the file cannot be opened or is not
    any of the formats); the body is read as the iterator is consumed, and what cannot be used is
    counted in ``counters`` (see the module docstring), never raised.
    """
    path = Path(path)
    kind = _check_header(path)
    return _iterate(path, kind, counters)


# ---------------------------------------------------------------------------------------------
# Header checks (eager: errors reach the caller before any datagram)


def _check_header(path: Path) -> CaptureFormat:
    try:
        with path.open("rb") as f:
            head = f.read(64)
            size = f.seek(0, 2)
    except OSError as error:
        raise CaptureError(f"{path}: cannot read the file: {error.strerror or error}") from error
    kind = detect_format(head)
    if kind == "pcap":
        if len(head) < 24:
            raise CaptureError(f"{path}: pcap file header truncated ({len(head)} of 24 octets)")
        order, _ = _PCAP_MAGICS[head[:4]]
        major, minor = struct.unpack(order + "HH", head[4:8])
        if major != 2:
            raise CaptureError(f"{path}: pcap version {major}.{minor} is not supported (2.x is)")
        return kind
    if kind == "pcapng":
        problem = _shb_problem(head)
        if problem:
            raise CaptureError(f"{path}: not a readable pcapng file: {problem}")
        return kind
    if not head:
        return kind  # an empty file holds no data blocks
    if head[:4] in _PCAP_MODIFIED_MAGICS:
        raise CaptureError(f"{path}: modified (Kuznetzov) pcap is not supported; convert it with editcap")
    for magic, name in _COMPRESSED_MAGICS.items():
        if head.startswith(magic):
            raise CaptureError(f"{path}: the file is {name}-compressed; decompress it first")
    if len(head) < 3:
        raise CaptureError(
            f"{path}: not pcap, pcapng or ASTERIX data blocks: {len(head)} octet(s), "
            "less than one data block header"
        )
    category, length = head[0], (head[1] << 8) | head[2]
    if category == 0 or length < 3 or length > size:
        raise CaptureError(
            f"{path}: not pcap, pcapng or ASTERIX data blocks: the first octets "
            f"{head[:8].hex(' ')} read as category {category}, length {length} "
            f"(file of {size} octets)"
        )
    return kind


def _shb_problem(head: bytes) -> str | None:
    if len(head) < 28:
        return f"section header block truncated ({len(head)} of at least 28 octets)"
    bom = head[8:12]
    if bom == _PCAPNG_BOM_BIG:
        order = ">"
    elif bom == _PCAPNG_BOM_LITTLE:
        order = "<"
    else:
        return f"unknown byte-order magic {bom.hex()} in the section header block"
    (total,) = struct.unpack(order + "I", head[4:8])
    if total < 28 or total % 4:
        return f"section header block length {total} (must be a multiple of 4, at least 28)"
    (major,) = struct.unpack(order + "H", head[12:14])
    if major != 1:
        return f"pcapng version {major} is not supported (1.x is)"
    return None


def _iterate(path: Path, kind: CaptureFormat, counters: collections.Counter[str]) -> Iterator[Datagram]:
    with path.open("rb", buffering=_READ_BUFFER) as f:
        if kind == "pcap":
            yield from _read_pcap(f, counters)
        elif kind == "pcapng":
            yield from _read_pcapng(f, counters)
        else:
            yield from _read_raw(f, counters)


# ---------------------------------------------------------------------------------------------
# raw ASTERIX


def _read_raw(f: BinaryIO, counters: collections.Counter[str]) -> Iterator[Datagram]:
    chunk = bytearray()
    rest = b""
    while True:
        head = f.read(3)
        if len(head) < 3:
            rest = head
            break
        length = (head[1] << 8) | head[2]
        if length < 3:
            rest = head + f.read(RAW_CHUNK_BYTES - 3)
            if f.read(1):
                counters["bad_block"] += 1
            break
        body = f.read(length - 3)
        if len(body) < length - 3:
            rest = head + body
            break
        if len(chunk) + length > RAW_CHUNK_BYTES:
            yield Datagram(bytes(chunk), None, "", "")
            chunk.clear()
        chunk += head
        chunk += body
    if chunk:
        yield Datagram(bytes(chunk), None, "", "")
    if rest:
        yield Datagram(bytes(rest), None, "", "")


# ---------------------------------------------------------------------------------------------
# pcap


def _read_pcap(f: BinaryIO, counters: collections.Counter[str]) -> Iterator[Datagram]:
    header = f.read(24)
    order, units = _PCAP_MAGICS[header[:4]]
    (network,) = struct.unpack(order + "I", header[20:24])
    linktype = network & 0x03FFFFFF  # the upper bits may carry the FCS length
    record = struct.Struct(order + "IIII")
    frames = _FrameDecoder(counters)
    while True:
        head = f.read(16)
        if not head:
            break
        if len(head) < 16:
            counters["truncated_file"] += 1
            break
        seconds, fraction, caplen, _ = record.unpack(head)
        if caplen > MAX_RECORD_BYTES:
            counters["bad_block"] += 1
            break
        data = f.read(caplen)
        if len(data) < caplen:
            counters["truncated_file"] += 1
            break
        datagram = frames.decode(linktype, data, seconds + fraction / units)
        if datagram is not None:
            yield datagram
    frames.finish()


# ---------------------------------------------------------------------------------------------
# pcapng


@dataclass
class _Interface:
    linktype: int
    snaplen: int
    units: int = 1_000_000  # time stamp units per second (if_tsresol)
    offset_s: int = 0  # if_tsoffset

    def time(self, high: int, low: int) -> float:
        seconds, fraction = divmod((high << 32) | low, self.units)
        return self.offset_s + seconds + fraction / self.units


def _read_pcapng(f: BinaryIO, counters: collections.Counter[str]) -> Iterator[Datagram]:
    frames = _FrameDecoder(counters)
    order = "<"
    interfaces: list[_Interface] = []
    while True:
        head = f.read(8)
        if not head:
            break
        if len(head) < 8:
            counters["truncated_file"] += 1
            break
        if head[:4] == _PCAPNG_SHB:
            bom = f.read(4)
            if len(bom) < 4:
                counters["truncated_file"] += 1
                break
            if bom == _PCAPNG_BOM_BIG:
                order = ">"
            elif bom == _PCAPNG_BOM_LITTLE:
                order = "<"
            else:
                counters["bad_block"] += 1
                break
            (total,) = struct.unpack(order + "I", head[4:8])
            if total < 28 or total % 4 or total > MAX_RECORD_BYTES:
                counters["bad_block"] += 1
                break
            rest = _block_rest(f, total, 12, order)
            if isinstance(rest, str):
                counters[rest] += 1
                break
            interfaces = []  # interface ids are numbered per section
            continue
        block_type, total = struct.unpack(order + "II", head)
        if total < 12 or total % 4:
            counters["bad_block"] += 1
            break
        if block_type not in (1, 2, 3, 6):
            status = _skip_block(f, total, order)
            if status:
                counters[status] += 1
                break
            continue
        if total > MAX_RECORD_BYTES:
            counters["bad_block"] += 1
            break
        rest = _block_rest(f, total, 8, order)
        if isinstance(rest, str):
            counters[rest] += 1
            break
        body = rest[:-4]
        if block_type == 1:
            interface = _interface(body, order)
            if interface is None:
                counters["bad_block"] += 1
            else:
                interfaces.append(interface)
            continue
        packet = _packet(block_type, body, order, interfaces)
        if packet is None:
            counters["bad_block"] += 1
            continue
        interface, data, time_s = packet
        datagram = frames.decode(interface.linktype, data, time_s)
        if datagram is not None:
            yield datagram
    frames.finish()


def _block_rest(f: BinaryIO, total: int, read: int, order: str) -> bytes | str:
    """The rest of a block of ``total`` bytes whose first ``read`` are read, ending in the block's
    length (checked); else the counter to raise as reading must stop."""
    rest = f.read(total - read)
    if len(rest) < total - read:
        return "truncated_file"
    if struct.unpack(order + "I", rest[-4:])[0] != total:
        return "bad_block"
    return rest


def _skip_block(f: BinaryIO, total: int, order: str) -> str | None:
    """Skips an unknown block's body; the counter to raise if reading must stop, else None."""
    remaining = total - 12
    while remaining:
        piece = f.read(min(remaining, _READ_BUFFER))
        if not piece:
            return "truncated_file"
        remaining -= len(piece)
    trailer = f.read(4)
    if len(trailer) < 4:
        return "truncated_file"
    if struct.unpack(order + "I", trailer)[0] != total:
        return "bad_block"
    return None


def _interface(body: bytes, order: str) -> _Interface | None:
    if len(body) < 8:
        return None
    linktype, _, snaplen = struct.unpack(order + "HHI", body[:8])
    interface = _Interface(linktype, snaplen)
    option = struct.Struct(order + "HH")
    p = 8
    while p + 4 <= len(body):
        code, length = option.unpack_from(body, p)
        p += 4
        if code == 0:
            break
        value = body[p : p + length]
        p += (length + 3) & ~3
        if code == 9 and len(value) >= 1:  # if_tsresol
            resolution = value[0]
            interface.units = 2 ** (resolution & 0x7F) if resolution & 0x80 else 10**resolution
        elif code == 14 and len(value) == 8:  # if_tsoffset
            (interface.offset_s,) = struct.unpack(order + "q", value)
    return interface


def _packet(
    block_type: int, body: bytes, order: str, interfaces: list[_Interface]
) -> tuple[_Interface, bytes, float | None] | None:
    """(interface, captured frame, time) of an EPB / SPB / OPB body, or None when inconsistent."""
    if block_type == 3:  # Simple Packet Block: interface 0, no time stamp
        if not interfaces or len(body) < 4:
            return None
        (original,) = struct.unpack(order + "I", body[:4])
        caplen = min(original, len(body) - 4)
        if interfaces[0].snaplen:
            caplen = min(caplen, interfaces[0].snaplen)
        return interfaces[0], body[4 : 4 + caplen], None
    if len(body) < 20:
        return None
    if block_type == 6:  # Enhanced Packet Block
        index, high, low, caplen, _ = struct.unpack(order + "IIIII", body[:20])
    else:  # Packet Block (obsolete): 16-bit interface id and drops count
        index, _, high, low, caplen, _ = struct.unpack(order + "HHIIII", body[:20])
    if index >= len(interfaces) or 20 + caplen > len(body):
        return None
    interface = interfaces[index]
    return interface, body[20 : 20 + caplen], interface.time(high, low)


# ---------------------------------------------------------------------------------------------
# Link, network and transport layers


@dataclass
class _Pending:
    first_time: float | None
    pieces: list[tuple[int, bytes]] = field(default_factory=list)
    size: int = 0
    total: int | None = None
    protocol: int | None = None


class _Reassembler:
    """IP fragment reassembly with a bounded buffer (datagrams in arrival order, oldest first)."""

    def __init__(self, counters: collections.Counter[str]) -> None:
        self._counters = counters
        self._pending: dict[tuple[object, ...], _Pending] = {}

    def add(
        self,
        key: tuple[object, ...],
        offset: int,
        more: bool,
        data: bytes,
        protocol: int,
        time_s: float | None,
    ) -> tuple[bytes, int] | None:
        """Adds a fragment; the whole payload and its protocol when this fragment completes it."""
        self._expire(time_s)
        entry = self._pending.get(key)
        if entry is None:
            if len(self._pending) >= MAX_PENDING_FRAGMENTED:
                del self._pending[next(iter(self._pending))]
                self._counters["fragment_lost"] += 1
            entry = self._pending[key] = _Pending(time_s)
        end = offset + len(data)
        if not more and entry.total == end:
            return None  # the last fragment again (captured twice)
        if end > 0xFFFF or entry.size + len(data) > 2 * 0xFFFF or (not more and entry.total is not None):
            del self._pending[key]  # oversized, endlessly repeated, or two different ends
            self._counters["fragment_lost"] += 1
            return None
        entry.pieces.append((offset, data))
        entry.size += len(data)
        if not more:
            entry.total = end
        if offset == 0:
            entry.protocol = protocol
        if entry.total is None or entry.protocol is None or entry.size < entry.total:
            return None
        whole = bytearray(entry.total)
        covered = 0
        for start, piece in sorted(entry.pieces, key=lambda item: item[0]):
            if start > covered:
                return None  # a hole: wait for the missing fragment
            piece = piece[: max(0, entry.total - start)]
            whole[start : start + len(piece)] = piece
            covered = max(covered, start + len(piece))
        if covered < entry.total:
            return None
        del self._pending[key]
        return bytes(whole), entry.protocol

    def _expire(self, now: float | None) -> None:
        if now is None:
            return
        while self._pending:
            key = next(iter(self._pending))
            first = self._pending[key].first_time
            if first is None or now - first <= FRAGMENT_TIMEOUT_S:
                break
            del self._pending[key]
            self._counters["fragment_lost"] += 1

    def finish(self) -> None:
        if self._pending:
            self._counters["fragment_lost"] += len(self._pending)
            self._pending.clear()


class _FrameDecoder:
    """Link-layer frames to UDP datagrams, counting what is skipped."""

    def __init__(self, counters: collections.Counter[str]) -> None:
        self._counters = counters
        self._fragments = _Reassembler(counters)
        self._addresses: dict[bytes, str] = {}

    def finish(self) -> None:
        self._fragments.finish()

    def _skip(self, cause: str) -> None:
        self._counters[cause] += 1

    def decode(self, linktype: int, data: bytes, time_s: float | None) -> Datagram | None:
        offset, version = self._link(linktype, data)
        if offset < 0:
            return None
        if len(data) <= offset:
            self._skip("truncated_frame")
            return None
        actual = data[offset] >> 4
        if version is None:
            version = actual
        if version != actual or version not in (4, 6):
            self._skip("not_ip")
            return None
        if version == 4:
            return self._ipv4(data, offset, time_s)
        return self._ipv6(data, offset, time_s)

    def _link(self, linktype: int, data: bytes) -> tuple[int, int | None]:
        """(offset of the IP header, expected IP version or None to read it), or (-1, _) if skipped."""
        if linktype == _LINKTYPE_ETHERNET:
            if len(data) < 14:
                return self._fail("truncated_frame")
            offset = 12
            (ethertype,) = _U16.unpack_from(data, offset)
            while ethertype in _ETHERTYPE_VLAN:
                offset += 4
                if len(data) < offset + 2:
                    return self._fail("truncated_frame")
                (ethertype,) = _U16.unpack_from(data, offset)
            return self._ethertype(ethertype, offset + 2)
        if linktype in (_LINKTYPE_RAW, _LINKTYPE_RAW_OLD):
            return 0, None
        if linktype == _LINKTYPE_IPV4:
            return 0, 4
        if linktype == _LINKTYPE_IPV6:
            return 0, 6
        if linktype == _LINKTYPE_LINUX_SLL:
            if len(data) < 16:
                return self._fail("truncated_frame")
            return self._ethertype(_U16.unpack_from(data, 14)[0], 16)
        if linktype == _LINKTYPE_LINUX_SLL2:
            if len(data) < 20:
                return self._fail("truncated_frame")
            return self._ethertype(_U16.unpack_from(data, 0)[0], 20)
        if linktype in (_LINKTYPE_NULL, _LINKTYPE_LOOP):
            if len(data) < 4:
                return self._fail("truncated_frame")
            # LOOP is in network order; NULL in the writer's, which puts the zero octets first or last.
            big = linktype == _LINKTYPE_LOOP or data[:2] == b"\0\0"
            family = int.from_bytes(data[:4], "big" if big else "little")
            if family == 2:
                return 4, 4
            if family in _AF_INET6_VALUES:
                return 4, 6
            return self._fail("not_ip")
        return self._fail("unsupported_link_type")

    def _ethertype(self, ethertype: int, offset: int) -> tuple[int, int | None]:
        if ethertype == _ETHERTYPE_IPV4:
            return offset, 4
        if ethertype == _ETHERTYPE_IPV6:
            return offset, 6
        return self._fail("not_ip")

    def _fail(self, cause: str) -> tuple[int, int | None]:
        self._counters[cause] += 1
        return -1, None

    def _ipv4(self, data: bytes, offset: int, time_s: float | None) -> Datagram | None:
        if len(data) < offset + 20:
            self._skip("truncated_frame")
            return None
        header = (data[offset] & 0x0F) * 4
        (total,) = _U16.unpack_from(data, offset + 2)
        if header < 20 or total < header:
            self._skip("not_ip")
            return None
        if len(data) < offset + total:
            self._skip("truncated_frame")
            return None
        protocol = data[offset + 9]
        if protocol != _IPPROTO_UDP:
            self._skip("not_udp")
            return None
        source = data[offset + 12 : offset + 16]
        destination = data[offset + 16 : offset + 20]
        segment = data[offset + header : offset + total]
        (flags,) = _U16.unpack_from(data, offset + 6)
        more, fragment_offset = bool(flags & 0x2000), (flags & 0x1FFF) * 8
        if more or fragment_offset:
            key = (4, source, destination, data[offset + 4 : offset + 6], protocol)
            whole = self._fragments.add(key, fragment_offset, more, segment, protocol, time_s)
            if whole is None:
                return None
            segment = whole[0]
        return self._udp(segment, source, destination, time_s)

    def _ipv6(self, data: bytes, offset: int, time_s: float | None) -> Datagram | None:
        if len(data) < offset + 40:
            self._skip("truncated_frame")
            return None
        (length,) = _U16.unpack_from(data, offset + 4)
        following = data[offset + 6]
        source = data[offset + 8 : offset + 24]
        destination = data[offset + 24 : offset + 40]
        end = offset + 40 + length
        if len(data) < end:
            self._skip("truncated_frame")
            return None
        buffer, p = data, offset + 40
        while following != _IPPROTO_UDP:
            if following in _IPV6_SKIPPED_HEADERS or following == _IPV6_AUTH:
                if p + 2 > end:
                    self._skip("not_ip")
                    return None
                size = (buffer[p + 1] + 2) * 4 if following == _IPV6_AUTH else (buffer[p + 1] + 1) * 8
                following, p = buffer[p], p + size
                if p > end:
                    self._skip("not_ip")
                    return None
            elif following == _IPV6_FRAGMENT:
                if p + 8 > end:
                    self._skip("not_ip")
                    return None
                (field_,) = _U16.unpack_from(buffer, p + 2)
                fragment_offset, more = field_ & 0xFFF8, bool(field_ & 1)
                inner = buffer[p]
                if fragment_offset == 0 and not more:  # an atomic fragment
                    following, p = inner, p + 8
                    continue
                key = (6, source, destination, buffer[p + 4 : p + 8])
                whole = self._fragments.add(key, fragment_offset, more, buffer[p + 8 : end], inner, time_s)
                if whole is None:
                    return None
                buffer, following = whole
                p, end = 0, len(buffer)
            else:
                self._skip("not_udp")
                return None
        return self._udp(buffer[p:end], source, destination, time_s)

    def _udp(
        self, segment: bytes, source: bytes, destination: bytes, time_s: float | None
    ) -> Datagram | None:
        if len(segment) < 8:
            self._skip("not_udp")
            return None
        source_port, destination_port, length = _UDP_HEADER.unpack_from(segment, 0)
        if length == 0 and len(segment) > 0xFFFF:
            length = len(segment)  # IPv6 jumbogram
        if length < 8:
            self._skip("not_udp")
            return None
        if length > len(segment):
            self._skip("truncated_frame")
            return None
        return Datagram(
            segment[8:length],
            time_s,
            f"{self._address(source)}:{source_port}",
            f"{self._address(destination)}:{destination_port}",
        )

    def _address(self, packed: bytes) -> str:
        text = self._addresses.get(packed)
        if text is None:
            if len(self._addresses) > 4096:
                self._addresses.clear()
            if len(packed) == 4:
                text = socket.inet_ntop(socket.AF_INET, packed)
            else:
                text = "[" + socket.inet_ntop(socket.AF_INET6, packed) + "]"
            self._addresses[packed] = text
        return text
