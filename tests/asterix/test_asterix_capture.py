"""service.asterix.capture: pcap, pcapng and raw ASTERIX files to datagrams.

Every capture here is built in the test by the small writers below (libpcap file format,
pcapng per draft-ietf-opsawg-pcapng), so the expected payloads, addresses and times are known
exactly; the one real capture is read in test_asterix_real_capture.py.
"""

from __future__ import annotations

import collections
import gzip
import re
import socket
import struct
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from service.asterix import capture
from service.asterix.capture import CaptureError, Datagram, detect_format, read_datagrams

T0 = 1_462_433_756  # 2016-05-05 07:35:56 UTC

# ---------------------------------------------------------------------------------------------
# Writers: UDP / IP / link layers


def udp(payload: bytes, sport: int = 21124, dport: int = 22131, length: int | None = None) -> bytes:
    return struct.pack(">HHHH", sport, dport, len(payload) + 8 if length is None else length, 0) + payload


def ipv4(
    segment: bytes,
    src: str = "10.17.58.184",
    dst: str = "232.2.1.31",
    protocol: int = 17,
    ident: int = 7,
    more: bool = False,
    offset: int = 0,
    options: bytes = b"",
    total: int | None = None,
) -> bytes:
    assert len(options) % 4 == 0 and offset % 8 == 0
    header_length = 20 + len(options)
    flags = (0x2000 if more else 0) | (offset // 8)
    length = header_length + len(segment) if total is None else total
    header = struct.pack(
        ">BBHHHBBH4s4s",
        0x40 | header_length // 4,
        0,
        length,
        ident,
        flags,
        61,
        protocol,
        0,
        socket.inet_aton(src),
        socket.inet_aton(dst),
    )
    return header + options + segment


def ipv6(
    payload: bytes,
    src: str = "2001:db8::1",
    dst: str = "ff15::1:2",
    next_header: int = 17,
    extensions: tuple[tuple[int, bytes], ...] = (),
) -> bytes:
    """IPv6 with extension headers given as (type, body); each body is padded to its 8-octet size."""
    chain = b""
    types = [next_header_of for next_header_of, _ in extensions] + [next_header]
    for index, (_, body) in enumerate(extensions):
        following = types[index + 1]
        if types[index] == 44:  # fragment header: fixed 8 octets, body is its last 6
            chain += bytes([following, 0]) + body
            continue
        padded = body + b"\0" * (-(len(body) + 2) % 8)
        chain += bytes([following, (len(padded) + 2) // 8 - 1]) + padded
    first = types[0]
    header = struct.pack(
        ">IHBB16s16s",
        6 << 28,
        len(chain) + len(payload),
        first,
        64,
        socket.inet_pton(socket.AF_INET6, src),
        socket.inet_pton(socket.AF_INET6, dst),
    )
    return header + chain + payload


def ethernet(packet: bytes, ethertype: int = 0x0800, vlans: tuple[int, ...] = ()) -> bytes:
    frame = bytes.fromhex("01005e02011f bc1665fe5fc2")
    for tpid in vlans:
        frame += struct.pack(">HH", tpid, 42)
    return frame + struct.pack(">H", ethertype) + packet


def sll(packet: bytes, protocol: int = 0x0800) -> bytes:
    return struct.pack(">HHH8sH", 0, 1, 6, b"\x02\x42\xac\x11\x00\x02\0\0", protocol) + packet


def sll2(packet: bytes, protocol: int = 0x0800) -> bytes:
    return struct.pack(">HHIHBB8s", protocol, 0, 3, 1, 0, 6, b"\x02\x42\xac\x11\x00\x02\0\0") + packet


def null(packet: bytes, family: int, order: str = "<") -> bytes:
    return struct.pack(order + "I", family) + packet


def frame4(payload: bytes, src: str = "10.17.58.184") -> bytes:
    return ethernet(ipv4(udp(payload), src=src))


# ---------------------------------------------------------------------------------------------
# Writers: files

Record = tuple[int, int, bytes] | tuple[int, int, bytes, int]  # seconds, fraction, frame[, original length]


def pcap(records: list[Record], linktype: int = 1, order: str = "<", nano: bool = False) -> bytes:
    magic = 0xA1B23C4D if nano else 0xA1B2C3D4
    out = struct.pack(order + "IHHiIII", magic, 2, 4, 0, 0, 262144, linktype)
    for record in records:
        seconds, fraction, frame = record[:3]
        original = record[3] if len(record) == 4 else len(frame)
        out += struct.pack(order + "IIII", seconds, fraction, len(frame), original) + frame
    return out


def block(block_type: int, body: bytes, order: str = "<") -> bytes:
    body += b"\0" * (-len(body) % 4)
    total = len(body) + 12
    return struct.pack(order + "II", block_type, total) + body + struct.pack(order + "I", total)


def options(items: list[tuple[int, bytes]], order: str = "<") -> bytes:
    out = b""
    for code, value in items:
        out += struct.pack(order + "HH", code, len(value)) + value + b"\0" * (-len(value) % 4)
    return out + struct.pack(order + "HH", 0, 0) if items else out


def shb(order: str = "<") -> bytes:
    return block(0x0A0D0D0A, struct.pack(order + "IHHq", 0x1A2B3C4D, 1, 0, -1), order)


def idb(
    linktype: int = 1, tsresol: int | None = None, tsoffset: int | None = None, order: str = "<"
) -> bytes:
    items = []
    if tsresol is not None:
        items.append((9, bytes([tsresol])))
    if tsoffset is not None:
        items.append((14, struct.pack(order + "q", tsoffset)))
    return block(1, struct.pack(order + "HHI", linktype, 0, 0) + options(items, order), order)


def epb(interface: int, ticks: int, frame: bytes, order: str = "<", original: int | None = None) -> bytes:
    head = struct.pack(
        order + "IIIII", interface, ticks >> 32, ticks & 0xFFFFFFFF, len(frame), original or len(frame)
    )
    return block(6, head + frame, order)


def spb(frame: bytes, order: str = "<") -> bytes:
    return block(3, struct.pack(order + "I", len(frame)) + frame, order)


def opb(interface: int, ticks: int, frame: bytes, order: str = "<") -> bytes:
    head = struct.pack(
        order + "HHIIII", interface, 0, ticks >> 32, ticks & 0xFFFFFFFF, len(frame), len(frame)
    )
    return block(2, head + frame, order)


def read(
    tmp_path: Path, data: bytes, name: str = "capture"
) -> tuple[list[Datagram], collections.Counter[str]]:
    path = tmp_path / name
    path.write_bytes(data)
    counters: collections.Counter[str] = collections.Counter()
    return list(read_datagrams(path, counters)), counters


def asterix_block(category: int, records: bytes) -> bytes:
    return bytes([category]) + struct.pack(">H", len(records) + 3) + records


CAT48 = asterix_block(48, bytes(range(1, 40)))
CAT34 = asterix_block(34, bytes.fromhex("f602190200a1b2c30a"))


# ---------------------------------------------------------------------------------------------
# pcap


def test_pcap_ethernet_ipv4_udp_payloads_addresses_and_times(tmp_path: Path) -> None:
    data = pcap([(T0, 508910, frame4(CAT48)), (T0 + 1, 999999, frame4(CAT34, src="10.0.0.2"))])
    datagrams, counters = read(tmp_path, data)
    assert datagrams == [
        Datagram(CAT48, T0 + 508910 / 1_000_000, "10.17.58.184:21124", "232.2.1.31:22131"),
        Datagram(CAT34, T0 + 1 + 999999 / 1_000_000, "10.0.0.2:21124", "232.2.1.31:22131"),
    ]
    assert not counters


def test_pcap_nanosecond_and_big_endian(tmp_path: Path) -> None:
    records: list[Record] = [(T0, 123456789, frame4(CAT48)), (T0 + 2, 5, frame4(CAT34))]
    nano, _ = read(tmp_path, pcap(records, nano=True), "nano")
    assert [d.time_s for d in nano] == [T0 + 123456789 / 1e9, T0 + 2 + 5 / 1e9]
    big_nano, _ = read(tmp_path, pcap(records, order=">", nano=True), "big-nano")
    assert big_nano == nano
    micro: list[Record] = [(T0, 250000, frame4(CAT48))]
    big, counters = read(tmp_path, pcap(micro, order=">"), "big")
    assert big == [Datagram(CAT48, T0 + 0.25, "10.17.58.184:21124", "232.2.1.31:22131")]
    assert not counters


def test_vlan_tags_ipv4_options_and_ethernet_padding(tmp_path: Path) -> None:
    tagged = ethernet(ipv4(udp(CAT48)), vlans=(0x8100,))
    qinq = ethernet(ipv4(udp(CAT34)), vlans=(0x88A8, 0x8100))
    with_options = ethernet(ipv4(udp(b"\x30\x00\x04\x01"), options=b"\x94\x04\x00\x00")) + b"\0" * 20
    datagrams, counters = read(tmp_path, pcap([(T0, 0, tagged), (T0, 1, qinq), (T0, 2, with_options)]))
    assert [d.payload for d in datagrams] == [CAT48, CAT34, b"\x30\x00\x04\x01"]
    assert not counters


def test_ipv6_with_extension_headers(tmp_path: Path) -> None:
    plain = ethernet(ipv6(udp(CAT48)), ethertype=0x86DD)
    chained = ethernet(
        ipv6(udp(CAT34), extensions=((0, b"\x01\x04\0\0\0\0"), (43, b"\0" * 6), (60, b"\x01\x00"))),
        ethertype=0x86DD,
    )
    datagrams, counters = read(tmp_path, pcap([(T0, 0, plain), (T0, 1, chained)]))
    assert datagrams == [
        Datagram(CAT48, T0, "[2001:db8::1]:21124", "[ff15::1:2]:22131"),
        Datagram(CAT34, T0 + 1e-6, "[2001:db8::1]:21124", "[ff15::1:2]:22131"),
    ]
    assert not counters


@pytest.mark.parametrize(
    ("linktype", "frame"),
    [
        (113, sll(ipv4(udp(CAT48)))),
        (113, sll(ipv6(udp(CAT48)), 0x86DD)),
        (276, sll2(ipv4(udp(CAT48)))),
        (276, sll2(ipv6(udp(CAT48)), 0x86DD)),
        (0, null(ipv4(udp(CAT48)), 2, "<")),
        (0, null(ipv4(udp(CAT48)), 2, ">")),
        (0, null(ipv6(udp(CAT48)), 30, "<")),
        (0, null(ipv6(udp(CAT48)), 24, ">")),
        (108, null(ipv4(udp(CAT48)), 2, ">")),
        (101, ipv4(udp(CAT48))),
        (101, ipv6(udp(CAT48))),
        (12, ipv4(udp(CAT48))),
        (228, ipv4(udp(CAT48))),
        (229, ipv6(udp(CAT48))),
    ],
    ids=lambda value: str(value) if isinstance(value, int) else "",
)
def test_link_types(tmp_path: Path, linktype: int, frame: bytes) -> None:
    datagrams, counters = read(tmp_path, pcap([(T0, 7, frame)], linktype=linktype))
    assert [(d.payload, d.time_s) for d in datagrams] == [(CAT48, T0 + 7e-6)]
    assert datagrams[0].source in ("10.17.58.184:21124", "[2001:db8::1]:21124")
    assert not counters


def test_skipped_frames_are_counted_by_cause(tmp_path: Path) -> None:
    tcp = ethernet(ipv4(b"\0" * 20, protocol=6))
    icmpv6 = ethernet(ipv6(b"\x80\0\0\0", next_header=58), ethertype=0x86DD)
    arp = ethernet(b"\0" * 28, ethertype=0x0806)
    bad_version = ethernet(b"\x65" + ipv4(udp(CAT48))[1:])  # ethertype IPv4, version nibble 6
    cut = frame4(CAT48)
    truncated = (T0, 4, cut[:-10], len(cut))  # the capture kept less than the IP length says
    udp_too_long = ethernet(ipv4(udp(CAT48, length=len(CAT48) + 20)))
    runt = ethernet(b"")[:10]
    good = (T0, 9, frame4(CAT34))
    datagrams, counters = read(
        tmp_path,
        pcap(
            [
                (T0, 0, tcp),
                (T0, 1, icmpv6),
                (T0, 2, arp),
                (T0, 3, bad_version),
                truncated,
                (T0, 5, udp_too_long),
                (T0, 6, runt),
                good,
            ]
        ),
    )
    assert [d.payload for d in datagrams] == [CAT34]
    assert counters == {"not_udp": 2, "not_ip": 2, "truncated_frame": 3}


def test_unsupported_link_type_counted_per_frame(tmp_path: Path) -> None:
    datagrams, counters = read(tmp_path, pcap([(T0, 0, b"\0" * 40)] * 3, linktype=105))  # 802.11
    assert datagrams == []
    assert counters == {"unsupported_link_type": 3}


def test_truncated_file_keeps_what_came_before(tmp_path: Path) -> None:
    data = pcap([(T0, 0, frame4(CAT48)), (T0, 1, frame4(CAT34))])
    inside_frame, counters = read(tmp_path, data[:-5], "a")
    assert [d.payload for d in inside_frame] == [CAT48]
    assert counters == {"truncated_file": 1}
    last_record = len(pcap([(T0, 0, frame4(CAT48))]))
    inside_header, counters = read(tmp_path, data[: last_record + 7], "b")
    assert [d.payload for d in inside_header] == [CAT48]
    assert counters == {"truncated_file": 1}


def test_impossible_record_length_stops_reading(tmp_path: Path) -> None:
    data = bytearray(pcap([(T0, 0, frame4(CAT48)), (T0, 1, frame4(CAT34)), (T0, 2, frame4(CAT34))]))
    second = len(pcap([(T0, 0, frame4(CAT48))]))
    struct.pack_into("<I", data, second + 8, 0xFFFFFFF0)  # caplen of the second record
    datagrams, counters = read(tmp_path, bytes(data))
    assert [d.payload for d in datagrams] == [CAT48]
    assert counters == {"bad_block": 1}


# ---------------------------------------------------------------------------------------------
# Fragments


def fragments4(payload: bytes, size: int, ident: int = 99) -> list[bytes]:
    segment = udp(payload)
    pieces = []
    for start in range(0, len(segment), size):
        more = start + size < len(segment)
        pieces.append(ethernet(ipv4(segment[start : start + size], ident=ident, more=more, offset=start)))
    return pieces


def test_ipv4_fragments_reassembled_in_any_order(tmp_path: Path) -> None:
    payload = bytes(range(256)) * 8
    pieces = fragments4(payload, 600)
    assert len(pieces) == 4
    order = [2, 0, 3, 1]
    records: list[Record] = [(T0, i, pieces[j]) for i, j in enumerate(order)]
    records.insert(2, (T0, 10, frame4(CAT48)))  # an unfragmented datagram in between
    datagrams, counters = read(tmp_path, pcap(records))
    assert [d.payload for d in datagrams] == [CAT48, payload]
    assert datagrams[1].time_s == T0 + 3e-6  # the frame that completed it
    assert datagrams[1].source == "10.17.58.184:21124"
    assert not counters


def test_duplicated_fragment_is_harmless(tmp_path: Path) -> None:
    payload = bytes(range(200)) * 5
    pieces = fragments4(payload, 400)
    records: list[Record] = [(T0, i, piece) for i, piece in enumerate([*pieces[:2], pieces[1], pieces[-1]])]
    datagrams, counters = read(tmp_path, pcap(records))
    assert [d.payload for d in datagrams] == [payload]
    assert not counters


def test_ipv6_fragments_reassembled(tmp_path: Path) -> None:
    payload = bytes(range(250)) * 6
    segment = udp(payload)
    frames = []
    for start in range(0, len(segment), 512):
        more = start + 512 < len(segment)
        fragment = struct.pack(">HI", start | more, 0xABCD)
        packet = ipv6(segment[start : start + 512], extensions=((44, fragment),))
        frames.append(ethernet(packet, ethertype=0x86DD))
    datagrams, counters = read(tmp_path, pcap([(T0, i, f) for i, f in enumerate(reversed(frames))]))
    assert [(d.payload, d.destination) for d in datagrams] == [(payload, "[ff15::1:2]:22131")]
    assert not counters


def test_incomplete_fragments_counted_lost(tmp_path: Path) -> None:
    pieces = fragments4(bytes(3000), 1000)
    datagrams, counters = read(tmp_path, pcap([(T0, 0, pieces[0]), (T0, 1, pieces[2])]))
    assert datagrams == []
    assert counters == {"fragment_lost": 1}


def test_fragment_buffer_is_bounded_in_count_and_time(tmp_path: Path) -> None:
    limit = capture.MAX_PENDING_FRAGMENTED
    firsts = [(T0, i, fragments4(bytes(2000), 1000, ident=i)[0]) for i in range(limit + 5)]
    last_of_0 = (T0, 999, fragments4(bytes(2000), 1000, ident=0)[-1])
    datagrams, counters = read(tmp_path, pcap([*firsts, last_of_0]), "count")
    assert datagrams == []  # ident 0 was evicted before its end came
    assert counters == {
        "fragment_lost": limit + 5 + 1
    }  # 5 + 1 evicted (ident 0's last came as a new one), 64 left at the end

    pieces = fragments4(CAT48 * 40, 1000, ident=1)
    late = int(capture.FRAGMENT_TIMEOUT_S) + 1
    records: list[Record] = [(T0, 0, pieces[0]), (T0 + late, 0, pieces[1])]
    datagrams, counters = read(tmp_path, pcap(records), "time")
    assert datagrams == []
    assert counters == {"fragment_lost": 2}  # the first expired; the second alone at the end
    in_time: list[Record] = [(T0, 0, pieces[0]), (T0 + late - 2, 0, pieces[1])]
    datagrams, counters = read(tmp_path, pcap(in_time), "in-time")
    assert [d.payload for d in datagrams] == [CAT48 * 40]


def test_tcp_fragments_are_not_udp(tmp_path: Path) -> None:
    first = ethernet(ipv4(b"\0" * 16, protocol=6, more=True))
    datagrams, counters = read(tmp_path, pcap([(T0, 0, first)]))
    assert datagrams == [] and counters == {"not_udp": 1}


# ---------------------------------------------------------------------------------------------
# pcapng


def test_pcapng_interfaces_resolutions_simple_and_unknown_blocks(tmp_path: Path) -> None:
    data = (
        shb()
        + idb(1)  # microseconds by default
        + block(0x0BAD, b"custom block to skip")
        + idb(101, tsresol=9)  # nanoseconds, raw IP
        + idb(1, tsresol=0x80 | 10, tsoffset=T0)  # 2^-10 s since T0
        + epb(0, T0 * 1_000_000 + 508910, frame4(CAT48))
        + block(5, b"\x00" * 16)  # interface statistics
        + epb(1, T0 * 1_000_000_000 + 123456789, ipv4(udp(CAT34)))
        + spb(frame4(CAT34))  # interface 0, no time stamp
        + epb(2, 3 * 1024 + 512, frame4(CAT48))
        + opb(1, T0 * 1_000_000_000 + 1, ipv4(udp(CAT48)))
        + block(0x40000BAD, b"local use")
    )
    datagrams, counters = read(tmp_path, data)
    assert [(d.payload, d.time_s) for d in datagrams] == [
        (CAT48, T0 + 508910 / 1e6),
        (CAT34, T0 + 123456789 / 1e9),
        (CAT34, None),
        (CAT48, T0 + 3.5),
        (CAT48, T0 + 1e-9),
    ]
    assert datagrams[2].source == "10.17.58.184:21124"
    assert not counters


def test_pcapng_big_endian_and_several_sections(tmp_path: Path) -> None:
    first = shb(">") + idb(1, order=">") + epb(0, T0 * 1_000_000, frame4(CAT48), ">")
    # interface ids restart in each section: 0 is now the nanosecond raw-IP one
    second = shb("<") + idb(101, tsresol=9) + epb(0, T0 * 1_000_000_000 + 5, ipv4(udp(CAT34)))
    datagrams, counters = read(tmp_path, first + second)
    assert [(d.payload, d.time_s) for d in datagrams] == [(CAT48, float(T0)), (CAT34, T0 + 5e-9)]
    assert not counters


def test_pcapng_inconsistent_blocks_counted_and_skipped(tmp_path: Path) -> None:
    bad_interface = epb(7, 0, frame4(CAT48))
    epb_body = bytearray(epb(0, 0, frame4(CAT48)))
    struct.pack_into("<I", epb_body, 20, 5000)  # captured length past the block
    before_interface = shb() + spb(frame4(CAT48))  # no interface in this section yet
    data = shb() + idb(1) + bad_interface + bytes(epb_body) + epb(0, 0, frame4(CAT34)) + before_interface
    datagrams, counters = read(tmp_path, data)
    assert [d.payload for d in datagrams] == [CAT34]
    assert counters == {"bad_block": 3}


@pytest.mark.parametrize(
    "damage",
    ["length not a multiple of 4", "length too small", "trailer differs", "section byte-order magic"],
)
def test_pcapng_bad_block_length_stops_reading(tmp_path: Path, damage: str) -> None:
    good = shb() + idb(1) + epb(0, 0, frame4(CAT48))
    broken = bytearray(epb(0, 1, frame4(CAT34)) + epb(0, 2, frame4(CAT34)))
    if damage == "length not a multiple of 4":
        struct.pack_into("<I", broken, 4, len(epb(0, 1, frame4(CAT34))) + 2)
    elif damage == "length too small":
        struct.pack_into("<I", broken, 4, 8)
    elif damage == "trailer differs":
        struct.pack_into("<I", broken, len(epb(0, 1, frame4(CAT34))) - 4, 12)
    else:
        broken = bytearray(shb())
        broken[8:12] = b"\x01\x02\x03\x04"
    datagrams, counters = read(tmp_path, good + bytes(broken))
    assert [d.payload for d in datagrams] == [CAT48]
    assert counters == {"bad_block": 1}


def test_pcapng_truncated_file(tmp_path: Path) -> None:
    data = shb() + idb(1) + epb(0, 0, frame4(CAT48)) + epb(0, 1, frame4(CAT34))
    for cut in (3, 30):
        datagrams, counters = read(tmp_path, data[:-cut], f"cut{cut}")
        assert [d.payload for d in datagrams] == [CAT48]
        assert counters == {"truncated_file": 1}
    unknown = shb() + idb(1) + block(0x0BAD, b"\0" * 100)
    datagrams, counters = read(tmp_path, unknown[:-50], "unknown")
    assert datagrams == [] and counters == {"truncated_file": 1}


# ---------------------------------------------------------------------------------------------
# Format detection and unreadable files


def test_detect_format_by_magic() -> None:
    assert detect_format(pcap([])) == "pcap"
    assert detect_format(pcap([], order=">", nano=True)) == "pcap"
    assert detect_format(shb(">")) == "pcapng"
    assert detect_format(shb("<")) == "pcapng"
    assert detect_format(CAT48) == "raw"
    assert detect_format(b"") == "raw"


@pytest.mark.parametrize(
    ("content", "message"),
    [
        (b"hello, this is not a capture\n" * 3, "not pcap, pcapng or ASTERIX data blocks"),
        (b"\x30\x00\x01rest", "length 1"),
        (b"\x00\x00\x10" + b"\0" * 13, "category 0"),
        (b"\x30", "less than one data block header"),
        (pcap([])[:20], "pcap file header truncated"),
        (b"\xd4\xc3\xb2\xa1\x01\x00\x00\x00" + b"\0" * 16, "pcap version 1.0"),
        (shb()[:8] + b"\x01\x02\x03\x04" + shb()[12:], "unknown byte-order magic"),
        (shb()[:4] + b"\x1e\0\0\0" + shb()[8:], "section header block length 30"),
        (shb()[:16], "section header block truncated"),
        (gzip.compress(pcap([(T0, 0, frame4(CAT48))])), "gzip-compressed"),
        (b"\x34\xcd\xb2\xa1" + b"\0" * 20, "modified (Kuznetzov) pcap"),
    ],
    ids=lambda value: value if isinstance(value, str) else "",
)
def test_unreadable_headers_raise_capture_error(tmp_path: Path, content: bytes, message: str) -> None:
    path = tmp_path / "bad.bin"
    path.write_bytes(content)
    with pytest.raises(CaptureError, match=re.escape(message)) as raised:
        read_datagrams(path, collections.Counter())  # raised before iterating
    assert str(path) in str(raised.value)


def test_missing_file_and_directory_raise_capture_error(tmp_path: Path) -> None:
    with pytest.raises(CaptureError, match="cannot read the file"):
        read_datagrams(tmp_path / "absent.pcap", collections.Counter())
    with pytest.raises(CaptureError, match="cannot read the file"):
        read_datagrams(tmp_path, collections.Counter())


def test_empty_file_has_no_datagrams(tmp_path: Path) -> None:
    assert read(tmp_path, b"") == ([], collections.Counter())


# ---------------------------------------------------------------------------------------------
# raw


def test_raw_chunks_end_on_block_boundaries(tmp_path: Path) -> None:
    blocks = [asterix_block(48 if i % 3 else 34, bytes([i % 256]) * (i * 37 % 900 + 1)) for i in range(400)]
    blocks.append(asterix_block(48, b"\x55" * 65532))  # the largest data block, alone in its chunk
    blocks.append(CAT34)
    data = b"".join(blocks)
    datagrams, counters = read(tmp_path, data)
    assert not counters
    assert b"".join(d.payload for d in datagrams) == data
    assert all(d.time_s is None and d.source == d.destination == "" for d in datagrams)
    assert all(len(d.payload) <= capture.RAW_CHUNK_BYTES for d in datagrams)
    assert len(datagrams) > 3
    boundaries = {0}
    for b in blocks:
        boundaries.add(max(boundaries) + len(b))
    position = 0
    for d in datagrams:
        assert position in boundaries
        position += len(d.payload)
        assert position in boundaries
    assert datagrams[-2].payload == blocks[-2]


def test_raw_trailing_partial_block_is_the_last_chunk(tmp_path: Path) -> None:
    partial = CAT48[:10]
    datagrams, counters = read(tmp_path, CAT34 + CAT48 + partial)
    assert [d.payload for d in datagrams] == [CAT34 + CAT48, partial]
    assert not counters
    datagrams, _ = read(tmp_path, CAT34 + b"\x30\x00", "header")
    assert [d.payload for d in datagrams] == [CAT34, b"\x30\x00"]


def test_raw_bad_length_yields_the_rest_once(tmp_path: Path) -> None:
    rest = b"\x30\x00\x02" + b"\xee" * 100
    datagrams, counters = read(tmp_path, CAT34 + rest)
    assert [d.payload for d in datagrams] == [CAT34, rest]
    assert not counters
    long_rest = b"\x30\x00\x00" + b"\xee" * (2 * capture.RAW_CHUNK_BYTES)
    datagrams, counters = read(tmp_path, CAT34 + long_rest, "long")
    assert [d.payload for d in datagrams] == [CAT34, long_rest[: capture.RAW_CHUNK_BYTES]]
    assert counters == {"bad_block": 1}


# ---------------------------------------------------------------------------------------------
# Robustness: damaged bodies never raise and always end


VALID_PCAP = pcap([(T0, i, f) for i, f in enumerate([frame4(CAT48), *fragments4(CAT34 * 100, 400)])])
VALID_PCAPNG = (
    shb()
    + idb(1)
    + idb(101, tsresol=9)
    + epb(0, 5, frame4(CAT48))
    + spb(frame4(CAT34))
    + epb(1, 9, ipv4(udp(CAT48)))
)


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    which=st.sampled_from(["pcap", "pcapng", "raw"]),
    edits=st.lists(st.tuples(st.integers(0, 10_000), st.integers(0, 255)), max_size=8),
    cut=st.integers(0, 10_000),
)
def test_damaged_bodies_never_raise(
    tmp_path: Path, which: str, edits: list[tuple[int, int]], cut: int
) -> None:
    original = {"pcap": VALID_PCAP, "pcapng": VALID_PCAPNG, "raw": CAT34 * 20 + CAT48 * 20}[which]
    # the file header stays valid (raw: its first data block, which the header check reads whole)
    keep = {"pcap": 24, "pcapng": 28, "raw": len(CAT34)}[which]
    data = bytearray(original[: max(keep, len(original) - cut % len(original))])
    for position, value in edits:
        if len(data) > keep:
            data[keep + position % (len(data) - keep)] = value
    datagrams, counters = read(tmp_path, bytes(data), "damaged")
    assert all(isinstance(d.payload, bytes) for d in datagrams)
    assert set(counters) <= set(capture.COUNTER_NAMES)
