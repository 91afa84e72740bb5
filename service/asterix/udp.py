"""Datagrams from UDP sockets: unicast ports and multicast groups, IPv4 and IPv6.

The live input side of ``topofusion asterix``: :func:`parse_endpoint` reads the command line's
``HOST:PORT``, ``GROUP:PORT@INTERFACE`` and ``[IPV6]:PORT`` forms into :class:`UdpEndpoint`, and
:class:`UdpReceiver` binds them all and hands out what arrives as
:class:`~service.asterix.capture.Datagram` objects (``time_s`` None; the caller stamps them).
No ASTERIX decoding here.

Multicast (RFC 1112 / RFC 3493 socket options): an IPv4 group is joined with ``IP_ADD_MEMBERSHIP``
on the interface whose address follows ``@`` (any interface, ``INADDR_ANY``, without one); an IPv6
group with ``IPV6_JOIN_GROUP`` on the interface named or numbered after ``@`` (0, the default,
without one).  Multicast sockets set ``SO_REUSEADDR`` and, where the platform has it,
``SO_REUSEPORT`` so that several bridges can listen to one group and port; unicast sockets set
neither, so that a second listener on a unicast port fails loudly instead of silently taking a
share of the datagrams.  Every socket asks for an 8 MiB receive buffer and accepts what the
system grants (:attr:`UdpReceiver.receive_buffers` tells); radar feeds arrive in bursts at the end
of each sector.

What the kernel dropped because a socket's buffer was full is read from ``/proc/net/udp`` and
``/proc/net/udp6`` (Linux: the ``drops`` column of the line whose inode is the socket's;
:meth:`UdpReceiver.kernel_drops`).  That costs one small file read when asked, nothing per
datagram, and keeps the plain ``recvfrom_into`` loop; ``SO_RXQ_OVFL`` would carry the same count
as ancillary data of every datagram, which needs ``recvmsg`` and its per-datagram cost.

:class:`FairQueue` holds what was read until it is decoded: per sender, served in turn, bounded in
datagrams and bytes, so that one sender flooding a port costs the others one turn each, not the
time it takes to decode its backlog.
"""

from __future__ import annotations

import contextlib
import ipaddress
import os
import re
import selectors
import socket
import struct
import sys
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass
from types import TracebackType

from service.asterix.capture import Datagram

#: Receive buffer asked of the system for each socket (Linux grants at most net.core.rmem_max).
RECEIVE_BUFFER_BYTES = 8 * 1024 * 1024
#: Largest UDP payload; every datagram fits.
MAX_DATAGRAM_BYTES = 65535
#: Datagrams read from one socket per :meth:`UdpReceiver.receive` call (the rest wait for the next).
MAX_BATCH_PER_SOCKET = 4096
#: ... and bytes: a flood of 64 KiB datagrams must not make one call read hundreds of megabytes
#: (4096 of them) before anything is decoded.  1 MiB is an eighth of the socket's buffer, so a
#: few calls drain a full one.
MAX_BYTES_PER_SOCKET = 1024 * 1024
#: Datagrams waiting to be decoded (:class:`FairQueue`), at most: as many bytes as one socket's
#: receive buffer, about 2-3 s of decoding at full speed (docs/asterix.md, "Speed") ...
QUEUE_BYTES = RECEIVE_BUFFER_BYTES
#: ... and datagrams (small ones: a count bound as well, each costs its own object).
QUEUE_DATAGRAMS = 16_384
#: The kernel's count tables, IPv4 and IPv6 (Linux).
PROC_NET_UDP = ("/proc/net/udp", "/proc/net/udp6")

_HOSTNAME = re.compile(r"(?!-)[A-Za-z0-9-]{1,63}(?<!-)(\.(?!-)[A-Za-z0-9-]{1,63}(?<!-))*\.?")
_INTERFACE_NAME = re.compile(r"[A-Za-z0-9_.:-]{1,64}")


@dataclass(frozen=True)
class UdpEndpoint:
    """Where to listen: an address (a multicast group, a local address, a wildcard) and a port."""

    host: str  # an IPv4 or IPv6 address (without brackets) or a host name
    port: int  # 0: the system picks one (see UdpReceiver.addresses)
    interface: str | None = None  # multicast only: IPv4 interface address, or IPv6 interface name/index

    @property
    def is_ipv6(self) -> bool:
        return ":" in self.host

    @property
    def is_multicast(self) -> bool:
        try:
            return ipaddress.ip_address(self.host).is_multicast
        except ValueError:
            return False

    def __str__(self) -> str:
        host = f"[{self.host}]" if self.is_ipv6 else self.host
        return f"{host}:{self.port}" + (f"@{self.interface}" if self.interface is not None else "")


def parse_endpoint(text: str) -> UdpEndpoint:
    """``HOST:PORT``, ``GROUP:PORT@IFACE`` or ``[IPV6]:PORT[@IFACE]``; ``:PORT`` means ``0.0.0.0:PORT``.

    HOST is an IPv4 address, a bracketed IPv6 address or a host name; PORT 0–65535. ``@IFACE`` is
    only for multicast groups: the local interface's IPv4 address for an IPv4 group, the interface
    name or index for an IPv6 group.  Raises ValueError saying what is wrong.
    """
    original = text
    text = text.strip()
    body, at, interface = text.partition("@")
    if body.startswith("["):
        close = body.find("]")
        if close < 0 or body[close + 1 : close + 2] != ":":
            raise ValueError(f"UDP endpoint {original!r}: an IPv6 address is written [ADDRESS]:PORT")
        host, port_text = body[1:close], body[close + 2 :]
        try:
            ipaddress.IPv6Address(host)
        except ValueError:
            raise ValueError(f"UDP endpoint {original!r}: {host!r} is not an IPv6 address") from None
    else:
        host, colon, port_text = body.rpartition(":")
        if not colon:
            raise ValueError(f"UDP endpoint {original!r}: expected HOST:PORT (or GROUP:PORT@INTERFACE)")
        if ":" in host:
            raise ValueError(
                f"UDP endpoint {original!r}: an IPv6 address is written in brackets, [ADDRESS]:PORT"
            )
        host = host or "0.0.0.0"
        if re.fullmatch(r"[0-9.]+", host):
            try:
                ipaddress.IPv4Address(host)
            except ValueError:
                raise ValueError(f"UDP endpoint {original!r}: {host!r} is not an IPv4 address") from None
        elif not _HOSTNAME.fullmatch(host):
            raise ValueError(f"UDP endpoint {original!r}: {host!r} is not an address or a host name")
    if not port_text.isascii() or not port_text.isdigit():
        raise ValueError(f"UDP endpoint {original!r}: the port {port_text!r} is not a number")
    port = int(port_text)
    if port > 65535:
        raise ValueError(f"UDP endpoint {original!r}: the port {port} is out of range (0-65535)")
    endpoint = UdpEndpoint(host, port, interface if at else None)
    if at:
        if not endpoint.is_multicast:
            raise ValueError(
                f"UDP endpoint {original!r}: @INTERFACE is only for multicast groups "
                f"(224.0.0.0/4, ff00::/8), and {host!r} is not one"
            )
        if endpoint.is_ipv6:
            if not _INTERFACE_NAME.fullmatch(interface):
                raise ValueError(
                    f"UDP endpoint {original!r}: {interface!r} is not an interface name or index"
                )
        else:
            try:
                ipaddress.IPv4Address(interface)
            except ValueError:
                raise ValueError(
                    f"UDP endpoint {original!r}: the interface of an IPv4 group is given by its IPv4 "
                    f"address, and {interface!r} is not one"
                ) from None
    return endpoint


def _format_address(address: tuple[object, ...]) -> str:
    host = str(address[0])
    return f"[{host}]:{address[1]}" if ":" in host else f"{host}:{address[1]}"


class UdpReceiver:
    """Binds every endpoint; joins multicast groups; gathers what arrives on any of them.

    IPv4 groups are joined with ``IP_ADD_MEMBERSHIP`` on the given interface address (or
    ``INADDR_ANY``), IPv6 groups with ``IPV6_JOIN_GROUP`` (interface index 0 when none is given).
    Multicast sockets set ``SO_REUSEADDR`` and ``SO_REUSEPORT`` (where available) so that several
    bridges can listen to one group; each socket asks for an 8 MiB receive buffer.  An endpoint that
    cannot be bound or joined raises OSError naming it, and nothing stays open.
    """

    def __init__(self, endpoints: Sequence[UdpEndpoint]) -> None:
        if not endpoints:
            raise ValueError("UdpReceiver needs at least one endpoint")
        self._selector = selectors.DefaultSelector()
        self._sockets: list[socket.socket] = []
        self._buffer = bytearray(MAX_DATAGRAM_BYTES)
        self._closed = False
        try:
            for endpoint in endpoints:
                self._open(endpoint)
        except BaseException:
            self.close()
            raise

    def _open(self, endpoint: UdpEndpoint) -> None:
        try:
            infos = socket.getaddrinfo(endpoint.host, endpoint.port, type=socket.SOCK_DGRAM)
        except socket.gaierror as error:
            raise OSError(
                error.errno, f"UDP endpoint {endpoint}: cannot resolve: {error.strerror}"
            ) from error
        # A host name may resolve to both families: IPv4 first, as the address literals of the feeds are.
        infos.sort(key=lambda info: info[0] != socket.AF_INET)
        family, _, _, _, address = infos[0]
        sock = socket.socket(family, socket.SOCK_DGRAM)
        self._sockets.append(sock)
        host = str(address[0])
        multicast = ipaddress.ip_address(host.partition("%")[0]).is_multicast
        try:
            if multicast:
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
                if hasattr(socket, "SO_REUSEPORT"):
                    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEPORT, 1)
            with contextlib.suppress(OSError):  # else keep the system's default
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, RECEIVE_BUFFER_BYTES)
            if multicast and family == socket.AF_INET6:
                index = self._interface_index(endpoint.interface)
                # Windows cannot bind a group address; elsewhere binding it filters out other groups.
                sock.bind(("::" if sys.platform == "win32" else host, endpoint.port, 0, index))
                request = socket.inet_pton(socket.AF_INET6, host) + struct.pack("@I", index)
                sock.setsockopt(socket.IPPROTO_IPV6, socket.IPV6_JOIN_GROUP, request)
            elif multicast:
                sock.bind(("" if sys.platform == "win32" else host, endpoint.port))
                request = socket.inet_aton(host) + socket.inet_aton(endpoint.interface or "0.0.0.0")
                sock.setsockopt(socket.IPPROTO_IP, socket.IP_ADD_MEMBERSHIP, request)
            else:
                sock.bind(address)
            sock.setblocking(False)
        except OSError as error:
            raise OSError(error.errno, f"UDP endpoint {endpoint}: {error.strerror or error}") from error
        bound = sock.getsockname()
        destination = _format_address((host, bound[1]))
        self._selector.register(sock, selectors.EVENT_READ, destination)

    @staticmethod
    def _interface_index(interface: str | None) -> int:
        if interface is None:
            return 0
        if interface.isdigit():
            return int(interface)
        return socket.if_nametoindex(interface)

    @property
    def addresses(self) -> list[tuple[str, int]]:
        """(host, port) each socket is bound to, in endpoint order (a port 0 shows the port chosen)."""
        return [(str(name[0]), int(name[1])) for name in (sock.getsockname() for sock in self._sockets)]

    @property
    def receive_buffers(self) -> list[int]:
        """The receive buffer size the system granted each socket (Linux reports twice the request)."""
        return [sock.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF) for sock in self._sockets]

    def receive(self, timeout_s: float) -> list[Datagram]:
        """Every datagram ready within ``timeout_s`` (waiting at most that long for the first).

        At most :data:`MAX_BATCH_PER_SOCKET` datagrams and about :data:`MAX_BYTES_PER_SOCKET`
        bytes per socket per call; the source is the sender's "ip:port", the destination the
        group or bound address and port it came in on.
        """
        if self._closed:
            raise ValueError("UdpReceiver is closed")
        received: list[Datagram] = []
        buffer = self._buffer
        for key, _ in self._selector.select(max(0.0, timeout_s)):
            sock = key.fileobj
            assert isinstance(sock, socket.socket)
            budget = MAX_BYTES_PER_SOCKET
            for _ in range(MAX_BATCH_PER_SOCKET):
                try:
                    size, sender = sock.recvfrom_into(buffer)
                except BlockingIOError:
                    break
                except ConnectionError:
                    continue  # Windows reports an earlier ICMP port unreachable here
                received.append(Datagram(bytes(buffer[:size]), None, _format_address(sender), key.data))
                budget -= size
                if budget <= 0:
                    break
        return received

    def kernel_drops(self) -> dict[str, int]:
        """Datagrams the kernel dropped on each socket so far (a full receive buffer), by the
        destination the socket stands for; empty where the system does not tell (not Linux)."""
        if self._closed:
            return {}
        inodes: dict[int, str] = {}
        for sock in self._sockets:
            with contextlib.suppress(KeyError, ValueError, OSError):
                inodes[os.fstat(sock.fileno()).st_ino] = self._selector.get_key(sock).data
        drops: dict[str, int] = {}
        for path in PROC_NET_UDP:
            try:
                with open(path, encoding="ascii", errors="replace") as table:
                    lines = table.read().splitlines()[1:]
            except OSError:
                continue
            for line in lines:
                # sl local rem st tx:rx tr:when retrnsmt uid timeout inode ref pointer drops
                fields = line.split()
                if len(fields) < 13 or not fields[9].isdigit() or not fields[-1].isdigit():
                    continue
                destination = inodes.get(int(fields[9]))
                if destination is not None:
                    drops[destination] = drops.get(destination, 0) + int(fields[-1])
        return drops

    def close(self) -> None:
        """Closes every socket (leaving the groups); idempotent."""
        if self._closed:
            return
        self._closed = True
        for sock in self._sockets:
            with contextlib.suppress(KeyError, ValueError):  # not registered: failed to bind
                self._selector.unregister(sock)
            sock.close()
        self._sockets.clear()
        self._selector.close()

    def __enter__(self) -> UdpReceiver:
        return self

    def __exit__(
        self,
        kind: type[BaseException] | None,
        value: BaseException | None,
        traceback: TracebackType | None,
    ) -> None:
        self.close()


class FairQueue:
    """Datagrams read and not yet decoded, per sender ("ip:port"), served in turn.

    :meth:`get` gives the oldest datagram of the sender whose turn it is (round robin over the
    senders with datagrams waiting), so a sender that floods the port waits for its own backlog
    while the others are served at once.  Past :data:`QUEUE_BYTES` or :data:`QUEUE_DATAGRAMS` the
    sender with the most bytes waiting loses its oldest datagram (:meth:`put` returns what was
    dropped, for the caller to count).  Each datagram waits with the time it was received.
    """

    def __init__(self, max_bytes: int = QUEUE_BYTES, max_datagrams: int = QUEUE_DATAGRAMS) -> None:
        self.max_bytes = max_bytes
        self.max_datagrams = max_datagrams
        #: Per sender, in turn order (a dict keeps insertion order; a served sender goes last).
        self._queues: dict[str, deque[tuple[float, Datagram]]] = {}
        self._bytes: dict[str, int] = {}
        self.bytes = 0
        self.count = 0

    def __len__(self) -> int:
        return self.count

    def put(self, datagram: Datagram, received_s: float) -> list[Datagram]:
        """Queue ``datagram``; the datagrams dropped to stay within the bounds (oldest first)."""
        sender = datagram.source
        queue = self._queues.get(sender)
        if queue is None:
            queue = self._queues[sender] = deque()
            self._bytes[sender] = 0
        queue.append((received_s, datagram))
        size = len(datagram.payload)
        self._bytes[sender] += size
        self.bytes += size
        self.count += 1
        dropped: list[Datagram] = []
        while self.bytes > self.max_bytes or self.count > self.max_datagrams:
            longest = max(self._bytes, key=self._bytes.__getitem__)
            dropped.append(self._pop(longest)[1])
        return dropped

    def get(self) -> tuple[float, Datagram] | None:
        """The next datagram (round robin over the senders) and when it was received, or None."""
        sender = next(iter(self._queues), None)
        if sender is None:
            return None
        item = self._pop(sender)
        if sender in self._queues:  # more of it waits: its next turn comes after the others'
            self._queues[sender] = self._queues.pop(sender)
        return item

    def _pop(self, sender: str) -> tuple[float, Datagram]:
        queue = self._queues[sender]
        item = queue.popleft()
        size = len(item[1].payload)
        self._bytes[sender] -= size
        self.bytes -= size
        self.count -= 1
        if not queue:
            del self._queues[sender], self._bytes[sender]
        return item
