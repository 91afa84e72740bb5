"""A simulated scenario sent as ASTERIX (``topofusion simulate --asterix-file/--asterix-udp``).

What a surveillance network would send in front of the ASTERIX bridge: each radar's plot
batches as CAT048 target reports closed by a CAT034 sector crossing, the scenario's ADS-B
reports as CAT021 (:mod:`.asterix_scenario`), to a capture file and/or over UDP, paced by
data time like the Zenoh publisher.

CAT048 carries a height (I048/110), not an elevation, and a radar is found by its data source
(SAC/SIC), so :func:`asterix_scenario` makes every radar of a scenario send heights, gives
each a SAC/SIC where it has none, and makes each a Mode S radar (its plots carry the
aircraft's Mode 3/A code, Mode S address and flight level, as a secondary radar's do).
The random stream is not touched by any of this: the same seed gives the same plots.

Files: a name ending in ``.pcap`` is written as a pcap capture (libpcap format, Ethernet,
IPv4, UDP; time stamps = data time), so that the bridge takes the date and the pace from it;
any other name gets the raw data blocks one after the other (the bridge then needs
``--date`` for data of another day).
"""

from __future__ import annotations

import json
import socket
import struct
import threading
from collections.abc import Iterable
from dataclasses import dataclass, replace
from pathlib import Path
from types import TracebackType
from typing import BinaryIO, Protocol

from topofusion_lab.asterix_scenario import message_datagrams
from topofusion_lab.pacing import Pacer
from topofusion_lab.scenarios.simulator import Scenario, SimMessage

#: Data source of the radars that have none: SAC 0 ("local"), SIC 10, 11, ... in the
#: scenario's order (the simulated ADS-B ground station is SAC 0 / SIC 1).
DEFAULT_SAC = 0
FIRST_SIC = 10
#: Addresses in a pcap capture: each radar sends from its own host of the documentation
#: network 192.0.2.0/24 (RFC 5737), the ADS-B station from .100, all to one source-specific
#: multicast group, as ASTERIX feeds are usually distributed.
PCAP_SOURCE_NET = "192.0.2."
PCAP_ADSB_HOST = 100
PCAP_GROUP = "232.1.1.1"
PCAP_PORT = 8600
#: UDP payload size of a datagram (ASTERIX data blocks packed up to it): below a 1500-octet
#: Ethernet MTU with IP and UDP headers, so nothing is fragmented.
DATAGRAM_BYTES = 1400


def asterix_scenario(sc: Scenario) -> Scenario:
    """The scenario as an ASTERIX network sends it (module docstring): heights, SAC/SIC, codes."""
    radars = tuple(
        replace(
            r,
            two_d=True,
            identity=True,
            sac=r.sac if r.sac is not None else DEFAULT_SAC,
            sic=r.sic if r.sic is not None else FIRST_SIC + i,
        )
        for i, r in enumerate(sc.radars)
    )
    pairs = [(r.sac, r.sic) for r in radars]
    if len(set(pairs)) != len(pairs):
        raise ValueError(f"scenario {sc.name!r}: two radars have the same SAC/SIC")
    return replace(sc, radars=radars)


def sites_document(sc: Scenario) -> str:
    """The scenario's sites as a sites file (``run --sites``, ``asterix --sites``)."""
    return json.dumps([r.site_message() for r in sc.radars], indent=1) + "\n"


class Sink(Protocol):
    def send(self, time_s: float, source: str, payload: bytes) -> None: ...

    def close(self) -> None: ...


def _checksum(header: bytes) -> int:
    total = sum(struct.unpack(f">{len(header) // 2}H", header))
    while total > 0xFFFF:
        total = (total & 0xFFFF) + (total >> 16)
    return ~total & 0xFFFF


class PcapFile:
    """A pcap capture (microsecond time stamps, link type Ethernet) of UDP datagrams."""

    #: Multicast MAC of :data:`PCAP_GROUP` (01:00:5e + the group's low 23 bits) and a locally
    #: administered sender MAC.
    _DST_MAC = bytes.fromhex("01005e010101")
    _SRC_MAC = bytes.fromhex("020000000001")

    def __init__(self, path: Path) -> None:
        self._file: BinaryIO = path.open("wb")
        self._file.write(struct.pack("<IHHiIII", 0xA1B2C3D4, 2, 4, 0, 0, 65535, 1))
        self._ident = 0
        self.datagrams = 0

    def send(self, time_s: float, source: str, payload: bytes) -> None:
        udp = struct.pack(">HHHH", PCAP_PORT, PCAP_PORT, 8 + len(payload), 0) + payload  # no UDP checksum
        self._ident = (self._ident + 1) & 0xFFFF
        head = struct.pack(
            ">BBHHHBBH4s4s",
            0x45,
            0,
            20 + len(udp),
            self._ident,
            0x4000,  # don't fragment
            1,  # multicast TTL: the local network
            17,
            0,
            socket.inet_aton(source),
            socket.inet_aton(PCAP_GROUP),
        )
        ip = head[:10] + struct.pack(">H", _checksum(head)) + head[12:] + udp
        frame = self._DST_MAC + self._SRC_MAC + b"\x08\x00" + ip
        micros = round(time_s * 1e6)
        self._file.write(
            struct.pack("<IIII", micros // 1_000_000, micros % 1_000_000, len(frame), len(frame))
        )
        self._file.write(frame)
        self.datagrams += 1

    def close(self) -> None:
        self._file.close()


class RawFile:
    """The data blocks one after the other (no time stamps, no addresses)."""

    def __init__(self, path: Path) -> None:
        self._file: BinaryIO = path.open("wb")
        self.datagrams = 0

    def send(self, time_s: float, source: str, payload: bytes) -> None:
        self._file.write(payload)
        self.datagrams += 1

    def close(self) -> None:
        self._file.close()


class UdpOut:
    """Datagrams to one UDP destination (unicast or a multicast group)."""

    def __init__(self, host: str, port: int) -> None:
        family, kind, proto, _, address = socket.getaddrinfo(host, port, type=socket.SOCK_DGRAM)[0]
        self._sock = socket.socket(family, kind, proto)
        self._address = address
        self.datagrams = 0

    def send(self, time_s: float, source: str, payload: bytes) -> None:
        self._sock.sendto(payload, self._address)
        self.datagrams += 1

    def close(self) -> None:
        self._sock.close()


def open_file(path: Path) -> PcapFile | RawFile:
    return PcapFile(path) if path.suffix.lower() == ".pcap" else RawFile(path)


@dataclass
class Sent:
    """What an ASTERIX run sent: plot and ADS-B batches, datagrams, messages left out."""

    batches: int = 0
    plots: int = 0
    adsb_batches: int = 0
    datagrams: int = 0
    left_out: dict[str, int] | None = None


class Sinks:
    """Several sinks as one; closes them all."""

    def __init__(self, sinks: list[Sink]) -> None:
        self.sinks = sinks

    def __enter__(self) -> Sinks:
        return self

    def __exit__(
        self, kind: type[BaseException] | None, error: BaseException | None, trace: TracebackType | None
    ) -> None:
        for s in self.sinks:
            s.close()

    def send(self, time_s: float, source: str, payload: bytes) -> None:
        for s in self.sinks:
            s.send(time_s, source, payload)


def send_asterix(
    sc: Scenario,
    messages: Iterable[SimMessage],
    sinks: Sinks,
    speed: float = 1.0,
    stop: threading.Event | None = None,
) -> Sent:
    """Send ``messages`` of the ASTERIX-ready scenario ``sc`` (:func:`asterix_scenario`) to
    ``sinks``, each message's datagrams at its data time (paced by ``speed``, 0: at once)."""
    stop = stop or threading.Event()
    sac_sic: dict[str, tuple[int, int]] = {}
    hosts: dict[str, str] = {}
    for i, r in enumerate(sc.radars):
        assert r.sac is not None and r.sic is not None and r.two_d, "asterix_scenario() first"
        sac_sic[r.radar_id] = (r.sac, r.sic)
        hosts[r.radar_id] = f"{PCAP_SOURCE_NET}{10 + i}"
    adsb_host = f"{PCAP_SOURCE_NET}{PCAP_ADSB_HOST}"
    pacer = Pacer(speed, stop)
    sent = Sent(left_out={})
    for m in messages:
        if m.kind == "site":
            continue
        if m.kind not in ("plots", "adsb"):
            assert sent.left_out is not None
            sent.left_out[m.kind] = sent.left_out.get(m.kind, 0) + 1
            continue
        if not pacer.due(m.time_s):
            break
        source = hosts[m.radar_id] if m.kind == "plots" else adsb_host
        for datagram in message_datagrams(m, sac_sic, DATAGRAM_BYTES):
            sinks.send(m.time_s, source, datagram)
            sent.datagrams += 1
        if m.kind == "plots":
            sent.batches += 1
            sent.plots += len(m.body["plots"]["time_s"])
        else:
            sent.adsb_batches += 1
    return sent


def describe(sent: Sent, wall_s: float) -> str:
    """One line for the command's summary."""
    left = ", ".join(f"{n} {k} batches" for k, n in sorted((sent.left_out or {}).items()))
    return (
        f"{sent.batches} plot batches ({sent.plots} plots, CAT048 + CAT034), {sent.adsb_batches} ADS-B "
        f"batches (CAT021) in {sent.datagrams} datagrams in {wall_s:.1f} s"
        + (f"; left out (not ASTERIX): {left}" if left else "")
    )
