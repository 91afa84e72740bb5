"""service.asterix.udp: endpoint parsing and the UDP receiver (unicast and multicast).

Everything stays on the loopback interface with ports chosen by the system; the multicast
senders set TTL 0 as well, and the multicast tests skip (saying why) where the loopback
interface cannot carry multicast.
"""

from __future__ import annotations

import contextlib
import re
import socket
import time
from collections.abc import Iterator

import pytest

from service.asterix.capture import Datagram
from service.asterix.udp import (
    MAX_BYTES_PER_SOCKET,
    FairQueue,
    UdpEndpoint,
    UdpReceiver,
    parse_endpoint,
)

GROUP = "239.255.73.41"  # administratively scoped (RFC 2365)
GROUP6 = "ff01::7341"  # interface-local scope


def receive_until(receiver: UdpReceiver, count: int, timeout_s: float = 5.0) -> list[Datagram]:
    received: list[Datagram] = []
    deadline = time.monotonic() + timeout_s
    while len(received) < count and time.monotonic() < deadline:
        received += receiver.receive(0.2)
    return received


@contextlib.contextmanager
def sender(family: int = socket.AF_INET) -> Iterator[socket.socket]:
    with socket.socket(family, socket.SOCK_DGRAM) as sock:
        yield sock


# ---------------------------------------------------------------------------------------------
# parse_endpoint


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("127.0.0.1:8600", UdpEndpoint("127.0.0.1", 8600, None)),
        ("0.0.0.0:0", UdpEndpoint("0.0.0.0", 0, None)),
        (":8600", UdpEndpoint("0.0.0.0", 8600, None)),
        (" 232.2.1.31:22131 ", UdpEndpoint("232.2.1.31", 22131, None)),
        ("232.2.1.31:22131@10.17.58.1", UdpEndpoint("232.2.1.31", 22131, "10.17.58.1")),
        ("localhost:65535", UdpEndpoint("localhost", 65535, None)),
        ("radar-feed.example.org:30001", UdpEndpoint("radar-feed.example.org", 30001, None)),
        ("[::1]:8600", UdpEndpoint("::1", 8600, None)),
        ("[::]:8600", UdpEndpoint("::", 8600, None)),
        ("[ff15::1:2]:8600@eth0", UdpEndpoint("ff15::1:2", 8600, "eth0")),
        ("[ff02::5]:8600@3", UdpEndpoint("ff02::5", 8600, "3")),
    ],
)
def test_parse_endpoint(text: str, expected: UdpEndpoint) -> None:
    assert parse_endpoint(text) == expected


def test_endpoint_text_round_trip() -> None:
    for text in ("127.0.0.1:8600", "232.2.1.31:22131@10.17.58.1", "[ff15::1:2]:8600@eth0", "[::1]:0"):
        assert str(parse_endpoint(text)) == text
    assert parse_endpoint("232.2.1.31:1").is_multicast
    assert not parse_endpoint("[::1]:1").is_multicast
    assert parse_endpoint("[::1]:1").is_ipv6


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("127.0.0.1", "expected HOST:PORT"),
        ("", "expected HOST:PORT"),
        ("127.0.0.1:", "port '' is not a number"),
        ("127.0.0.1:http", "port 'http' is not a number"),
        ("127.0.0.1:-1", "port '-1' is not a number"),
        ("127.0.0.1:65536", "out of range"),
        ("127.0.0.1:99999999", "out of range"),
        ("300.1.2.3:8600", "'300.1.2.3' is not an IPv4 address"),
        ("bad_host!:8600", "not an address or a host name"),
        ("::1:8600", "in brackets"),
        ("[::1:8600", "[ADDRESS]:PORT"),
        ("[::1]8600", "[ADDRESS]:PORT"),
        ("[not-v6]:8600", "not an IPv6 address"),
        ("127.0.0.1:8600@127.0.0.1", "only for multicast groups"),
        ("232.2.1.31:8600@eth0", "given by its IPv4 address"),
        ("232.2.1.31:8600@", "given by its IPv4 address"),
        ("[ff15::1]:8600@bad name", "not an interface name or index"),
        ("127.0.0.1:٨٦٠٠", "not a number"),  # Arabic-Indic digits
    ],
)
def test_parse_endpoint_rejects(text: str, message: str) -> None:
    with pytest.raises(ValueError, match="UDP endpoint") as raised:
        parse_endpoint(text)
    assert message in str(raised.value)


# ---------------------------------------------------------------------------------------------
# Unicast


def test_unicast_loopback() -> None:
    with UdpReceiver([UdpEndpoint("127.0.0.1", 0), parse_endpoint("127.0.0.1:0")]) as receiver:
        (host, port_a), (_, port_b) = receiver.addresses
        assert host == "127.0.0.1" and port_a > 0 and port_b > 0 and port_a != port_b
        assert receiver.receive(0.05) == []
        with sender() as sock:
            sock.bind(("127.0.0.1", 0))
            origin = f"127.0.0.1:{sock.getsockname()[1]}"
            sock.sendto(b"\x30\x00\x05\x01\x02", ("127.0.0.1", port_a))
            sock.sendto(b"\x22\x00\x03", ("127.0.0.1", port_b))
            sock.sendto(b"", ("127.0.0.1", port_a))
            big = bytes(range(256)) * 255  # 65280 octets, near the UDP maximum
            sock.sendto(big, ("127.0.0.1", port_b))
            received = receive_until(receiver, 4)
        assert sorted(received, key=lambda d: (d.destination, len(d.payload))) == sorted(
            [
                Datagram(b"\x30\x00\x05\x01\x02", None, origin, f"127.0.0.1:{port_a}"),
                Datagram(b"", None, origin, f"127.0.0.1:{port_a}"),
                Datagram(b"\x22\x00\x03", None, origin, f"127.0.0.1:{port_b}"),
                Datagram(big, None, origin, f"127.0.0.1:{port_b}"),
            ],
            key=lambda d: (d.destination, len(d.payload)),
        )
        # in order per socket
        assert [d.payload for d in received if d.destination.endswith(f":{port_a}")] == [
            b"\x30\x00\x05\x01\x02",
            b"",
        ]
        assert all(size > 0 for size in receiver.receive_buffers)


def test_unicast_ipv6_loopback() -> None:
    if not socket.has_ipv6:
        pytest.skip("this Python has no IPv6")
    try:
        receiver = UdpReceiver([parse_endpoint("[::1]:0")])
    except OSError as error:
        pytest.skip(f"no IPv6 loopback here ({error})")
    with receiver, sender(socket.AF_INET6) as sock:
        sock.bind(("::1", 0))
        port = receiver.addresses[0][1]
        sock.sendto(b"\x30\x00\x03", ("::1", port))
        received = receive_until(receiver, 1)
        assert received == [
            Datagram(b"\x30\x00\x03", None, f"[::1]:{sock.getsockname()[1]}", f"[::1]:{port}")
        ]


def test_unicast_port_taken_fails_loudly_and_closes_everything() -> None:
    with UdpReceiver([parse_endpoint("127.0.0.1:0")]) as first:
        port = first.addresses[0][1]
        with pytest.raises(OSError, match=re.escape(f"UDP endpoint 127.0.0.1:{port}")):
            UdpReceiver([parse_endpoint("127.0.0.1:0"), parse_endpoint(f"127.0.0.1:{port}")])


def test_receive_waits_at_most_the_timeout_and_close_is_idempotent() -> None:
    receiver = UdpReceiver([parse_endpoint("127.0.0.1:0")])
    started = time.monotonic()
    assert receiver.receive(0.2) == []
    assert 0.15 <= time.monotonic() - started < 2.0
    receiver.close()
    receiver.close()
    with pytest.raises(ValueError, match="closed"):
        receiver.receive(0.0)
    with pytest.raises(ValueError, match="at least one endpoint"):
        UdpReceiver([])


def test_unresolvable_host_names_the_endpoint(monkeypatch: pytest.MonkeyPatch) -> None:
    def no_resolver(*args: object, **kwargs: object) -> None:
        raise socket.gaierror(socket.EAI_NONAME, "Name or service not known")

    monkeypatch.setattr(socket, "getaddrinfo", no_resolver)  # no DNS query leaves the host
    with pytest.raises(OSError, match=re.escape("UDP endpoint radar.example:0: cannot resolve")):
        UdpReceiver([parse_endpoint("radar.example:0")])


def test_one_receive_reads_about_a_byte_budget_per_socket() -> None:
    with UdpReceiver([parse_endpoint("127.0.0.1:0")]) as receiver, sender() as sock:
        port = receiver.addresses[0][1]
        big = bytes(60_000)
        n = MAX_BYTES_PER_SOCKET // len(big) + 5
        for _ in range(n):
            sock.sendto(big, ("127.0.0.1", port))
        time.sleep(0.05)
        first = receiver.receive(1.0)
        assert len(first) == MAX_BYTES_PER_SOCKET // len(big) + 1  # the one that crossed the budget
        assert len(first) + len(receive_until(receiver, n - len(first))) == n  # the rest waited


def test_kernel_drops_are_read_per_socket() -> None:
    """Datagrams the kernel dropped on a full receive buffer, by the socket's destination."""
    with UdpReceiver([parse_endpoint("127.0.0.1:0"), parse_endpoint("127.0.0.1:0")]) as receiver:
        (_, port), (_, other) = receiver.addresses
        before = receiver.kernel_drops()
        if not before:
            pytest.skip("the system does not tell UDP drops (/proc/net/udp)")
        assert before == {f"127.0.0.1:{port}": 0, f"127.0.0.1:{other}": 0}
        with sender() as sock:
            sent = 2 * max(receiver.receive_buffers) // 60_000 + 10  # twice what the buffer holds
            for _ in range(sent):
                sock.sendto(bytes(60_000), ("127.0.0.1", port))
        drops = receiver.kernel_drops()
        got = len(receive_until(receiver, sent, timeout_s=1.0))
        assert drops[f"127.0.0.1:{other}"] == 0
        assert drops[f"127.0.0.1:{port}"] > 0 and got + drops[f"127.0.0.1:{port}"] == sent
    assert receiver.kernel_drops() == {}  # closed


def test_fair_queue_serves_senders_in_turn_and_drops_the_longest_oldest() -> None:
    def d(sender: str, size: int, tag: int) -> Datagram:
        return Datagram(bytes([tag]) * size, None, sender, "127.0.0.1:1")

    queue = FairQueue(max_bytes=1000, max_datagrams=8)
    assert queue.get() is None
    for i in range(4):
        assert queue.put(d("flood:1", 200, i), float(i)) == []
    assert queue.put(d("radar:2", 10, 100), 4.0) == []
    gone = queue.put(d("flood:1", 200, 4), 5.0)  # 1010 bytes: the flood's oldest goes
    assert [g.payload[0] for g in gone] == [0]
    assert (len(queue), queue.bytes) == (5, 810)
    assert queue.put(d("radar:2", 10, 101), 6.0) == []
    order = []
    while (item := queue.get()) is not None:
        order.append((item[1].source, item[1].payload[0], item[0]))
    # in turn: flood, radar, flood, radar, flood, ...; each sender's own in order
    assert order == [
        ("flood:1", 1, 1.0),
        ("radar:2", 100, 4.0),
        ("flood:1", 2, 2.0),
        ("radar:2", 101, 6.0),
        ("flood:1", 3, 3.0),
        ("flood:1", 4, 5.0),
    ]
    assert (len(queue), queue.bytes) == (0, 0)
    small = FairQueue(max_bytes=10**6, max_datagrams=3)  # empty datagrams: the count bounds them
    gone = [g for i in range(5) for g in small.put(d("x:1", 0, 0), float(i))]
    assert len(gone) == 2 and len(small) == 3


# ---------------------------------------------------------------------------------------------
# Multicast on the loopback interface


def open_group_receiver(endpoints: list[UdpEndpoint]) -> UdpReceiver:
    try:
        return UdpReceiver(endpoints)
    except OSError as error:
        pytest.skip(f"cannot join {endpoints[0]} on the loopback interface here: {error}")


def send_multicast(payload: bytes, group: str, port: int) -> None:
    with sender() as sock:
        sock.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_IF, socket.inet_aton("127.0.0.1"))
        sock.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_LOOP, 1)
        sock.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, 0)  # never leaves the host
        try:
            sock.sendto(payload, (group, port))
        except OSError as error:
            pytest.skip(f"no multicast route on the loopback interface here (sending failed: {error})")


def test_multicast_group_on_loopback_two_listeners() -> None:
    first = open_group_receiver([parse_endpoint(f"{GROUP}:0@127.0.0.1")])
    with first:
        port = first.addresses[0][1]
        # a second bridge on the same group and port (SO_REUSEADDR / SO_REUSEPORT)
        with UdpReceiver([parse_endpoint(f"{GROUP}:{port}@127.0.0.1")]) as second:
            send_multicast(b"\x30\x00\x04\x99", GROUP, port)
            got_first = receive_until(first, 1, timeout_s=3.0)
            got_second = receive_until(second, 1, timeout_s=1.0)
        if not got_first:
            pytest.skip(
                f"no multicast delivery on the loopback interface here ({GROUP} sent, nothing came back)"
            )
        assert [(d.payload, d.destination) for d in got_first] == [(b"\x30\x00\x04\x99", f"{GROUP}:{port}")]
        assert got_first[0].source.startswith("127.0.0.1:")
        assert [d.payload for d in got_second] == [b"\x30\x00\x04\x99"]


def test_multicast_socket_hears_only_its_group() -> None:
    other = "239.255.73.42"
    receiver = open_group_receiver([parse_endpoint(f"{GROUP}:0@127.0.0.1")])
    with receiver:
        port = receiver.addresses[0][1]
        with UdpReceiver([parse_endpoint(f"{other}:{port}@127.0.0.1")]) as neighbour:
            send_multicast(b"\x22\x00\x03", other, port)
            send_multicast(b"\x30\x00\x03", GROUP, port)
            mine = receive_until(receiver, 1, timeout_s=3.0)
            theirs = receive_until(neighbour, 1, timeout_s=1.0)
        if not mine:
            pytest.skip(
                f"no multicast delivery on the loopback interface here ({GROUP} sent, nothing came back)"
            )
        assert [d.payload for d in mine + receiver.receive(0.2)] == [b"\x30\x00\x03"]
        assert [d.payload for d in theirs] == [b"\x22\x00\x03"]


def test_ipv6_multicast_on_loopback() -> None:
    if not socket.has_ipv6:
        pytest.skip("this Python has no IPv6")
    try:
        index = socket.if_nametoindex("lo")
    except OSError:
        pytest.skip("no interface named lo here")
    receiver = open_group_receiver([parse_endpoint(f"[{GROUP6}]:0@lo")])
    with receiver, sender(socket.AF_INET6) as sock:
        port = receiver.addresses[0][1]
        sock.setsockopt(socket.IPPROTO_IPV6, socket.IPV6_MULTICAST_IF, index)
        sock.setsockopt(socket.IPPROTO_IPV6, socket.IPV6_MULTICAST_LOOP, 1)
        sock.setsockopt(socket.IPPROTO_IPV6, socket.IPV6_MULTICAST_HOPS, 0)
        try:
            sock.sendto(b"\x30\x00\x03", (GROUP6, port, 0, index))
        except OSError as error:
            pytest.skip(f"no IPv6 multicast route on the loopback interface here (sending failed: {error})")
        received = receive_until(receiver, 1, timeout_s=3.0)
        if not received:
            pytest.skip("no IPv6 multicast delivery on the loopback interface here")
        assert [(d.payload, d.destination) for d in received] == [(b"\x30\x00\x03", f"[{GROUP6}]:{port}")]
