"""``topofusion asterix``: the bridge from an ASTERIX feed to the service (contract §4.3).

Files (``--file``, raw data blocks, pcap or pcapng) are read first, in the order given, paced
by ``--speed``; then the UDP endpoints (``--udp``, unicast or multicast) are read until the
bridge is stopped (SIGINT, SIGTERM) or ``--duration`` has passed.  Each datagram is decoded
(:mod:`.decode`), turned into payloads (:mod:`.bridge`) and published over Zenoh.  What is
still held at the end is sent, and a summary says what was read, sent and left out.

The bridge's clock (:mod:`.bridge`, "The bridge's own clock"): a file's capture time stamps;
for UDP the wall clock when the datagram was read; with ``--date`` the data's own clock.

UDP: the sockets are read into a :class:`~.udp.FairQueue` (per sender, bounded) and decoded
from it in turn, looking at the sockets again after at most :data:`DECODE_SLICE_S` of decoding,
so that a flood of large datagrams from one sender neither starves the others nor keeps the
kernel's buffers full; what the kernel and the queue drop is counted, and charged to the
sources that socket or sender fed (their next batch skips a ``seq`` number, so the service
counts it in ``lost_batches``).  While it runs the bridge prints its counters every
``--report-every`` seconds when they changed; on a stop it ends within :data:`STOP_GRACE_S`.
"""

from __future__ import annotations

import argparse
import datetime as dt
import gc
import math
import sys
import threading
import time
from collections import Counter
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import Any

import orjson

from service.asterix.bridge import DAY_S, AsterixBridge, BridgeParams, DayClock, Message
from service.asterix.capture import CaptureError, Datagram, read_datagrams
from service.asterix.cat062 import Cat062Track, encode_cat062_blocks
from service.asterix.decode import Decoded, decode_datagram
from service.asterix.udp import FairQueue, UdpEndpoint, UdpReceiver, parse_endpoint
from service.output_files import check_writable
from service.wire.keys import Keys
from service.wire.models import MAX_ALTITUDE_M, MAX_TIME_S, MIN_ALTITUDE_M, RadarSite
from service.wire.vocabulary import is_source_id

#: The counters line is printed at most this often (wall s) while the bridge runs, and only when
#: something changed (``--report-every``): often enough to watch a feed, rare enough for a log.
REPORT_EVERY_S = 10.0
#: The kernel's UDP drop counts are read this often (wall s): a loss is charged to the batch
#: interval it happened in (a radar sends a batch per sector, a few per second, so a second
#: charges it to the next batch or two), for one small file read a second.
KERNEL_DROPS_EVERY_S = 1.0
#: The bridge decodes queued datagrams for at most about this long (s) before it reads the
#: sockets again: 8 MiB of receive buffer fill in a few ms under a flood of 64 KiB datagrams on
#: a fast link, and every datagram the kernel drops while the bridge decodes may be a good one.
DECODE_SLICE_S = 0.002
#: Records decoded from one live UDP datagram, at most (more: the rest of it is dropped, counted
#: ``blocks_too_many_records``).  A datagram holds at most 65 507 octets and a real target report
#: takes 16 and more (time, position, a code), so no real datagram holds more; 64 KiB of the
#: smallest records (3 octets) would be 21 800 and cost about 50 ms, 4096 about 10 ms.
MAX_UDP_RECORDS = 4096
#: With nothing queued, a wait on the sockets lasts at most this long (s): a stop is seen within it.
POLL_S = 0.2
#: After SIGINT/SIGTERM the bridge ends within this long (s): half of Docker's default stop
#: timeout (10 s) before it sends SIGKILL.  The loops look at the stop between datagrams (a
#: live one costs at most about 10 ms, ``MAX_UDP_RECORDS``), ...
STOP_GRACE_S = 5.0
#: ... what is still held is sent for at most this long (s; held data is bounded,
#: ``BridgeParams.max_held_records``, and normally takes well under a second) and the rest is
#: counted as unsent, which leaves room for closing the Zenoh session.
STOP_FLUSH_S = 3.0
#: Senders and sockets whose sources the bridge remembers, to charge a loss to: at most this many
#: (the oldest is forgotten first).
MAX_ORIGINS = 4096
#: The sites are put again every this many wall seconds (``--site-every``), so that a service,
#: worker or recorder that starts after the bridge learns them within this long (and rejects a
#: radar's plots as ``unknown_radar`` only until then); a site equal to the one a service holds
#: changes nothing there.  A site is a few hundred bytes: a dozen radars cost under 1 kB/s.
SITE_EVERY_S = 5.0
#: The oldest track age I062/290 says (s): older tracks are said to be this old.
MAX_TRACK_AGE_S = 63.75
#: A system track faster than this (m/s, any ECEF component) is no aircraft: its batch is refused
#: rather than written (I062/185 holds +-8 192 m/s).
MAX_SPEED_MPS = 10_000.0
#: ``--wait`` (s): with a CAT062 output, how long the bridge waits after its inputs' end for the
#: service to report its outputs complete through them (contract §5.1); a busy service is still
#: working through its queue when the last message is sent.  As ``replay``'s.
OUTPUTS_WAIT_S = 120.0
#: Then the last system tracks the service put are taken once none came for this long (s), ...
OUTPUTS_QUIET_S = 0.5
#: ... at most this long (s): a picture arrives within a moment of the status saying it is out.
OUTPUTS_SETTLE_S = 5.0


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--udp",
        action="append",
        type=_endpoint,
        default=[],
        metavar="HOST:PORT",
        help="UDP endpoint to read (repeatable); a multicast group joins it, GROUP:PORT@IFACE_ADDR picks the "
        "interface",
    )
    p.add_argument(
        "--file",
        action="append",
        type=Path,
        default=[],
        metavar="PATH",
        help="raw ASTERIX data blocks, pcap or pcapng capture (repeatable; read before --udp)",
    )
    p.add_argument(
        "--sites", metavar="FILE", help="JSON list of RadarSite with sac/sic (setting TOPOFUSION_SITES)"
    )
    p.add_argument(
        "--date",
        type=dt.date.fromisoformat,
        metavar="YYYY-MM-DD",
        help="UTC date of the data's first time of day (default: the capture's time stamps, else today)",
    )
    p.add_argument(
        "--speed", type=float, default=1.0, help="files: x the capture's own pace; 0 = as fast as possible"
    )
    p.add_argument("--duration", type=float, metavar="S", help="UDP: stop after S wall seconds")
    p.add_argument("--adsb-id", default="adsb", help="source id of the ADS-B reports (default adsb)")
    p.add_argument(
        "--adsb-batch", type=float, default=1.0, metavar="S", help="data seconds per ADS-B batch (default 1)"
    )
    p.add_argument(
        "--max-batch", type=float, default=2.0, metavar="S", help="batch length of a radar without CAT034"
    )
    p.add_argument(
        "--max-time-ahead",
        type=float,
        default=BridgeParams.max_time_ahead_s,
        metavar="S",
        help="drop a record stamped more than S ahead of the bridge's clock (capture stamps, else the "
        f"wall clock; with --date the data's own; default {BridgeParams.max_time_ahead_s:g})",
    )
    p.add_argument(
        "--max-time-behind",
        type=float,
        default=BridgeParams.max_time_behind_s,
        metavar="S",
        help=f"drop a record stamped more than S behind it (default {BridgeParams.max_time_behind_s:g})",
    )
    p.add_argument(
        "--report-every",
        type=float,
        default=REPORT_EVERY_S,
        metavar="S",
        help=f"print the counters every S wall seconds when they changed (0: only at the end; "
        f"default {REPORT_EVERY_S:g})",
    )
    p.add_argument(
        "--out-udp",
        action="append",
        type=_endpoint,
        default=[],
        metavar="HOST:PORT",
        help="write the service's system tracks as CAT062 to this UDP destination (repeatable)",
    )
    p.add_argument(
        "--out-file", type=Path, metavar="PATH", help="append the system tracks as CAT062 data blocks"
    )
    p.add_argument(
        "--system-sac", type=int, default=0, metavar="N", help="SAC of the CAT062 output (default 0)"
    )
    p.add_argument(
        "--system-sic", type=int, default=1, metavar="N", help="SIC of the CAT062 output (default 1)"
    )
    p.add_argument(
        "--site-every",
        type=float,
        default=SITE_EVERY_S,
        metavar="S",
        help=f"put the sites again every S wall seconds, for late joiners (0: only at the start; "
        f"default {SITE_EVERY_S:g})",
    )
    p.add_argument(
        "--wait-service",
        type=float,
        default=0.0,
        metavar="S",
        help="before the first message, wait up to S s for a service to answer {prefix}/status (default 0)",
    )
    p.add_argument(
        "--wait",
        type=float,
        default=OUTPUTS_WAIT_S,
        metavar="S",
        help="with --out-udp/--out-file: after the inputs' last message, wait up to S s until the service "
        "reports its outputs complete through it, so the CAT062 output holds the whole picture; 0: do not "
        f"wait (default {OUTPUTS_WAIT_S:g}, as replay's)",
    )
    p.add_argument(
        "--no-fl-altitude",
        action="store_true",
        help="leave altitude_m out where only a flight level is known (default: FL x 30.48 m)",
    )


def _endpoint(text: str) -> UdpEndpoint:
    try:
        return parse_endpoint(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


class Publisher:
    """Puts the bridge's messages on their keys (JSON, blocking under congestion).

    A put that fails is counted (:attr:`failed`) and its batch is gone; its ``seq`` number stays
    unused, so the service counts it as lost.  Past :attr:`deadline` (the stop's) the rest is
    counted as :attr:`unsent`.
    """

    def __init__(self, put: Callable[[str, bytes], None], prefix: str) -> None:
        self.put = put
        self.keys = Keys(prefix)
        self.sent: Counter[str] = Counter()
        self.failed: Counter[str] = Counter()
        self.unsent: Counter[str] = Counter()
        self.last_error = ""
        self.plots = 0
        #: Each key's latest batch time sent (where the service's outputs can be complete through).
        self.last_time_s: dict[str, float] = {}
        #: Monotonic time after which nothing more is put (None: no limit).
        self.deadline: float | None = None

    def publish(self, messages: Iterable[Message]) -> None:
        deadline = self.deadline
        for m in messages:
            if deadline is not None and time.monotonic() > deadline:
                self.unsent[m.kind] += 1
                continue
            key = self.keys.plots(m.source_id) if m.kind == "plots" else self.keys.adsb(m.source_id)
            try:
                self.put(key, orjson.dumps(m.body))
            except Exception as exc:  # Zenoh's own errors: one batch is lost, not the run
                self.failed[m.kind] += 1
                self.last_error = str(exc)
                continue
            self.sent[m.kind] += 1
            time_s = float(m.body["time_s"])
            self.last_time_s[key] = max(time_s, self.last_time_s.get(key, time_s))
            if m.kind == "plots":
                self.plots += len(m.body["plots"]["time_s"])

    def sites(self, sites: Iterable[RadarSite]) -> None:
        for s in sites:
            self.put(self.keys.site(s.radar_id), s.model_dump_json(exclude_none=True).encode())


class SiteRepeater:
    """Puts the mapped sites again every ``every_s`` wall seconds (``--site-every``; 0: never)."""

    def __init__(
        self,
        publisher: Publisher,
        sites: list[RadarSite],
        every_s: float,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.publisher = publisher
        self.sites = sites
        self.every_s = every_s if every_s > 0 and sites else None
        self.clock = clock
        self._next = clock() + every_s if self.every_s is not None else math.inf

    def start(self) -> None:
        """The first put of the sites (and the clock of the next)."""
        self.publisher.sites(self.sites)
        if self.every_s is not None:
            self._next = self.clock() + self.every_s

    def tick(self) -> None:
        if self.every_s is None:
            return
        now = self.clock()
        if now >= self._next:
            self._next = now + self.every_s
            try:
                self.publisher.sites(self.sites)
            except Exception as exc:  # Zenoh's own errors: the next period tries again
                self.publisher.last_error = str(exc)

    def left_s(self) -> float:
        """Wall seconds until the next put (inf: none)."""
        return max(self._next - self.clock(), 0.0)


class Cat062Writer:
    """The service's system tracks (``{prefix}/system/tracks``) as CAT062, to UDP and/or a file.

    Each ``SystemTrackBatch`` becomes CAT062 data blocks of at most one datagram each
    (:mod:`.cat062`).  Track ages count from when this writer first saw a track (a track absent
    from a batch or two keeps its age); member radars with a SAC/SIC in the sites give I062/340's
    sensor.
    """

    def __init__(
        self,
        sac: int,
        sic: int,
        sites: Iterable[RadarSite],
        udp: list[UdpEndpoint],
        path: Path | None,
    ) -> None:
        import socket

        self.sac, self.sic = sac, sic
        self.sensor = {s.radar_id: (s.sac, s.sic) for s in sites if s.sac is not None and s.sic is not None}
        #: Each system track's first and latest time in a batch (its I062/290 age).
        self._seen: dict[str, tuple[float, float]] = {}
        self._udp = [(e.host, e.port) for e in udp]
        self._sock = (
            socket.socket(
                socket.AF_INET6 if any(":" in h for h, _ in self._udp) else socket.AF_INET, socket.SOCK_DGRAM
            )
            if udp
            else None
        )
        self._file = path.open("ab") if path is not None else None
        self._lock = threading.Lock()
        self.blocks = 0
        self.tracks = 0
        #: Monotonic time of the last batch received (written or not).
        self.last_received = time.monotonic()
        self.bad = 0
        self.send_errors = 0

    def write(self, payload: bytes) -> None:
        self.last_received = time.monotonic()
        try:
            body = orjson.loads(payload)
            tracks = self.tracks_of(body)
            blocks = encode_cat062_blocks(tracks, self.sac, self.sic)
        except (ValueError, KeyError, TypeError, AttributeError, OverflowError):
            self.bad += 1  # not a SystemTrackBatch the items can hold: nothing written
            return
        with self._lock:
            for b in blocks:
                for addr in self._udp:
                    assert self._sock is not None
                    try:
                        self._sock.sendto(b, addr)
                    except OSError:  # an unreachable destination must not stop the others
                        self.send_errors += 1
                if self._file is not None:
                    self._file.write(b)
            if self._file is not None:
                self._file.flush()
            self.blocks += len(blocks)
            self.tracks += len(tracks)

    def summary(self) -> str:
        refused = f"; {self.bad} system-track batches refused (not writable as CAT062)" if self.bad else ""
        unsent = f"; {self.send_errors} datagrams not sent" if self.send_errors else ""
        return f"{self.tracks} tracks in {self.blocks} data blocks{refused}{unsent}"

    def tracks_of(self, body: dict[str, Any]) -> list[Cat062Track]:
        """The batch's tracks for CAT062; ValueError for one that is no system track (a
        position off the globe, a speed or height no aircraft has: anyone may put on the key)."""
        time_s = float(body["time_s"])
        if not 0.0 <= time_s <= MAX_TIME_S:
            raise ValueError(f"time_s {time_s}")
        out = []
        seen = dict(self._seen)
        for t in body["system_tracks"]:
            tid = t["system_track_id"]
            seen[tid] = (seen.get(tid, (time_s, time_s))[0], time_s)
            if not (-90.0 <= t["latitude_deg"] <= 90.0 and -180.0 <= t["longitude_deg"] <= 180.0):
                raise ValueError(f"{tid}: position off the globe")
            if not all(abs(v) <= MAX_SPEED_MPS for v in t["velocity_ecef_mps"]):
                raise ValueError(f"{tid}: velocity")
            if t["altitude_m"] is not None and not MIN_ALTITUDE_M <= t["altitude_m"] <= MAX_ALTITUDE_M:
                raise ValueError(f"{tid}: altitude")
            lat, lon = math.radians(t["latitude_deg"]), math.radians(t["longitude_deg"])
            vx, vy, vz = t["velocity_ecef_mps"]
            east = -math.sin(lon) * vx + math.cos(lon) * vy
            north = (
                -math.sin(lat) * math.cos(lon) * vx - math.sin(lat) * math.sin(lon) * vy + math.cos(lat) * vz
            )
            sensor = next(
                (self.sensor[m["radar_id"]] for m in t["members"] if m["radar_id"] in self.sensor), None
            )
            out.append(
                Cat062Track(
                    number=int(tid.rsplit("-", 1)[-1]),
                    tod_s=time_s % DAY_S,
                    latitude_deg=t["latitude_deg"],
                    longitude_deg=t["longitude_deg"],
                    east_mps=east,
                    north_mps=north,
                    confirmed=t["status"] == "confirmed",
                    mono=len(t["members"]) == 1,
                    age_s=min(time_s - seen[tid][0], MAX_TRACK_AGE_S),
                    altitude_m=t["altitude_m"],
                    sensor=sensor,
                )
            )
        # a track missing from a batch or two keeps its age; one gone longer than the age
        # I062/290 can say is forgotten: memory bounded by the tracks of the last minute
        self._seen = {k: v for k, v in seen.items() if v[1] >= time_s - MAX_TRACK_AGE_S}
        return out

    def close(self) -> None:
        if self._sock is not None:
            self._sock.close()
        if self._file is not None:
            self._file.close()


def today_midnight_s() -> float:
    now = time.time()
    return now - now % DAY_S


class Run:
    """One bridge run over its inputs (the Zenoh-free part of the command: tests drive it)."""

    def __init__(
        self,
        bridge: AsterixBridge,
        publisher: Publisher,
        stop: threading.Event,
        speed: float = 1.0,
        fixed_date: bool = False,
        progress: Callable[[str], None] | None = None,
        report_every_s: float = REPORT_EVERY_S,
        sites: SiteRepeater | None = None,
    ) -> None:
        self.bridge = bridge
        self.publisher = publisher
        self.stop = stop
        self.sites = sites
        self.speed = speed
        self.fixed_date = fixed_date
        self.progress = progress
        self.report_every_s = report_every_s
        self.capture: Counter[str] = Counter()
        self.datagrams = 0
        self.decoded = Counter[str]()
        #: UDP datagrams lost before decoding: by the kernel (full socket buffer), by the queue.
        self.lost: Counter[str] = Counter()
        #: The sources each sender ("from ip:port") and socket ("to ip:port") fed lately.
        self._sources_of: dict[str, set[str]] = {}
        self._kernel_drops: dict[str, int] = {}
        self._rx: UdpReceiver | None = None
        self._udp = False  # UDP was read: its losses are reported
        now = time.monotonic()
        self._next_report = now + report_every_s
        self._next_drops = now + KERNEL_DROPS_EVERY_S
        self._reported = ""

    def datagram(self, d: Datagram, reference_s: float | None, max_records: int | None = None) -> None:
        out = Decoded()
        decode_datagram(d.payload, out, max_records)
        self.datagrams += 1
        self.decoded.update(cat048=len(out.cat048), cat034=len(out.cat034), cat021=len(out.cat021))
        self.publisher.publish(self.bridge.feed(out, None if self.fixed_date else reference_s))
        fed = self.bridge.fed
        if fed:
            self._remember(f"from {d.source}", fed)
            self._remember(f"to {d.destination}", fed)
        self.tick()

    def _remember(self, origin: str, fed: set[str]) -> None:
        known = self._sources_of.get(origin)
        if known is None:
            if len(self._sources_of) >= MAX_ORIGINS:
                del self._sources_of[next(iter(self._sources_of))]
            self._sources_of[origin] = set(fed)
        elif not fed <= known:
            known |= fed

    def tick(self) -> None:
        """Read the kernel's drop counts, print the counters and put the sites again when their
        times have come."""
        if self.sites is not None:
            self.sites.tick()
        now = time.monotonic()
        if self._rx is not None and now >= self._next_drops:
            self._next_drops = now + KERNEL_DROPS_EVERY_S
            self.read_kernel_drops()
        if self.progress is not None and self.report_every_s > 0 and now >= self._next_report:
            self._next_report = now + self.report_every_s
            line = self.report()
            if line != self._reported:
                self._reported = line
                self.progress(line)

    def read_kernel_drops(self) -> None:
        """New kernel drops on each socket are counted and charged to the sources it fed."""
        if self._rx is None:
            return
        for destination, n in self._rx.kernel_drops().items():
            new = n - self._kernel_drops.get(destination, n)  # the first reading is the baseline
            self._kernel_drops[destination] = n
            if new > 0:
                self.lost["kernel"] += new
                self.bridge.mark_lost(self._sources_of.get(f"to {destination}", set()))

    def files(self, paths: list[Path]) -> None:
        for path in paths:
            self._paced(read_datagrams(path, self.capture))
            if self.stop.is_set():
                return

    def _paced(self, datagrams: Iterator[Datagram]) -> None:
        wall0 = data0 = None
        for d in datagrams:
            if self.stop.is_set():
                return
            # the capture's own time stamps, else the data time the records reached
            t = d.time_s if d.time_s is not None else self.bridge.clock.latest_s
            if self.speed > 0 and t is not None:
                if wall0 is None or data0 is None:
                    wall0, data0 = time.monotonic(), t
                delay = wall0 + (t - data0) / self.speed - time.monotonic()
                if delay > 0 and self.idle(delay):
                    return
            self.datagram(d, d.time_s)

    def idle(self, duration_s: float | None) -> bool:
        """Wait ``duration_s`` (None: until stopped), keeping the periodic chores (sites,
        counters) going; True when stopped meanwhile."""
        end = None if duration_s is None else time.monotonic() + duration_s
        while True:
            left = math.inf if end is None else end - time.monotonic()
            if left <= 0:
                return self.stop.is_set()
            chore = self.sites.left_s() if self.sites is not None else math.inf
            if self.stop.wait(min(left, chore, self.report_every_s or math.inf, POLL_S * 5)):
                return True
            self.tick()

    def udp(self, endpoints: list[UdpEndpoint], duration_s: float | None) -> None:
        end = None if duration_s is None else time.monotonic() + duration_s
        queue = FairQueue()
        with UdpReceiver(endpoints) as rx:
            self._rx, self._udp = rx, True
            self.read_kernel_drops()  # the baseline: what happened before the bridge is not its loss
            if self.progress is not None:
                bound = ", ".join(f"{h}:{p}" for h, p in rx.addresses)
                self.progress(f"asterix: listening on {bound}")
            try:
                while not self.stop.is_set() and (end is None or time.monotonic() < end):
                    received_s = time.time()  # live: the wall clock is the bridge's clock
                    for d in rx.receive(0.0 if queue else POLL_S):
                        for gone in queue.put(d, received_s):
                            self.lost["queue"] += 1
                            self.bridge.mark_lost(self._sources_of.get(f"from {gone.source}", set()))
                    slice_end = time.monotonic() + DECODE_SLICE_S
                    while not self.stop.is_set():
                        item = queue.get()
                        if item is None:
                            break
                        self.datagram(item[1], item[0], MAX_UDP_RECORDS)
                        if time.monotonic() >= slice_end:
                            break
                    self.tick()
            finally:
                self.read_kernel_drops()
                self._rx = None
                if len(queue):  # read and never decoded: stopped first
                    self.lost["unread_at_stop"] += len(queue)

    def finish(self, deadline: float | None = None) -> None:
        """Send what is still held (until ``deadline``, monotonic s, if given)."""
        self.publisher.deadline = deadline
        self.publisher.publish(self.bridge.flush())

    def line(self) -> str:
        used, sent = self.bridge.used, self.publisher.sent
        return (
            f"asterix: {self.datagrams} datagrams, {used['cat048']} plots and {used['cat021']} ADS-B reports "
            f"used; sent {sent['plots']} plot batches, {sent['adsb']} ADS-B batches"
        )

    def report(self) -> str:
        """The counters on one line (the periodic report)."""
        left = _counts(self.bridge.unusable) if self.bridge.unusable else "nothing"
        udp = f"; UDP datagrams lost: {_lost(self.lost)}" if self._udp else ""
        return f"{self.line()}; held {self.bridge.held} records; left out: {left}{udp}"

    def summary(self) -> str:
        lines = [self.line()]
        lines.append(f"asterix: records decoded: {_counts(self.decoded)}")
        left = self.bridge.unusable
        lines.append(f"asterix: left out: {_counts(left) if left else 'nothing'}")
        if self.bridge.rebased:
            lines.append(f"asterix: the data's clock moved to a jump in time {self.bridge.rebased} times")
        if self._udp:
            lines.append(f"asterix: UDP datagrams lost: {_lost(self.lost)}")
        if self.capture:
            lines.append(f"asterix: capture frames skipped: {_counts(self.capture)}")
        pub = self.publisher
        if pub.failed:
            lines.append(f"asterix: batches lost to failed puts: {_counts(pub.failed)} ({pub.last_error})")
        if pub.unsent:
            lines.append(f"asterix: batches not sent within the stop's grace: {_counts(pub.unsent)}")
        off = sum(n for k, n in left.items() if k.endswith(("_time_ahead", "_time_behind")))
        if off and not (self.bridge.used["cat048"] or self.bridge.used["cat021"]):
            lines.append(
                "asterix: every timed record was far from the bridge's clock (the capture's stamps, else "
                "the wall clock): is that clock right, or is this a recording? --date replays by the "
                "data's own time"
            )
        return "\n".join(lines)


def _outputs_complete(
    session: Any, prefix: str, publisher: Publisher, writer: Cat062Writer, wait_s: float
) -> None:
    """``--wait``: the service's outputs complete through what was sent, then the system tracks
    it published last: once none came for ``OUTPUTS_QUIET_S`` since (at most ``OUTPUTS_SETTLE_S``)."""
    from service.recording.completion import RecordingEnd, wait_for_outputs

    def say(line: str) -> None:
        print(f"asterix: {line}", file=sys.stderr, flush=True)

    if not wait_for_outputs(
        session, prefix, RecordingEnd(dict(publisher.last_time_s)), wait_s, "the input", say
    ):
        return
    done = time.monotonic()
    end = done + OUTPUTS_SETTLE_S
    while time.monotonic() < end and time.monotonic() - max(writer.last_received, done) < OUTPUTS_QUIET_S:
        time.sleep(OUTPUTS_QUIET_S / 5)


def _check_writable(path: Path) -> None:
    """A file the bridge will write: refused now, before any connection, if it cannot be."""
    check_writable(path, "asterix: --out-file")


def _lost(c: Counter[str]) -> str:
    return f"{c['kernel']} by the kernel, {c['queue']} by the bridge's queue" + (
        f", {c['unread_at_stop']} unread at stop" if c["unread_at_stop"] else ""
    )


def _counts(c: Counter[str]) -> str:
    return ", ".join(f"{k} {v}" for k, v in sorted(c.items())) or "none"


def asterix_main(
    args: argparse.Namespace, options: Any, prefix: str, sites_path: Path | None, stop: threading.Event
) -> int:
    """The command: check the inputs, open the session, run, say what happened."""
    from service.config import load_sites
    from service.transport.session import open_tool_session

    outputs = bool(args.out_udp or args.out_file)
    if not args.file and not args.udp and not outputs:
        raise ValueError(
            "asterix: give at least one --file or --udp input, or an --out-udp/--out-file output"
        )
    for name in ("system_sac", "system_sic"):
        if not 0 <= getattr(args, name) <= 255:
            raise ValueError(f"asterix: --{name.replace('_', '-')} must be in 0..255")
    if not (math.isfinite(args.speed) and args.speed >= 0):
        raise ValueError("asterix: --speed must be a finite number >= 0")
    if args.duration is not None and not (math.isfinite(args.duration) and args.duration > 0):
        raise ValueError("asterix: --duration must be a finite number > 0")
    if not is_source_id(args.adsb_id):
        raise ValueError(f"asterix: --adsb-id {args.adsb_id!r} must match [A-Za-z0-9_-]{{1,64}}")
    if any(e.port == 0 for e in args.out_udp):
        raise ValueError("asterix: --out-udp needs a destination port (1-65535), not 0")
    if sites_path is None and (args.file or args.udp):
        raise ValueError("asterix: --sites FILE (or TOPOFUSION_SITES) is needed to map SAC/SIC to radars")
    sites = load_sites(sites_path) if sites_path is not None else ()
    mapped = [s for s in sites if s.sac is not None and s.sic is not None]
    if not mapped and sites:
        print(
            f"asterix: no site in {sites_path} has sac and sic: no radar report can be mapped",
            file=sys.stderr,
        )
    for path in args.file:
        try:
            read_datagrams(path, Counter())  # header check now: a clear error before any publishing
        except CaptureError as exc:
            raise ValueError(f"asterix: {exc}") from None
    if args.out_file is not None:
        _check_writable(args.out_file)
    if not (args.site_every >= 0 and args.wait_service >= 0 and args.wait >= 0):
        raise ValueError("asterix: --site-every, --wait-service and --wait must be >= 0")
    start = (
        dt.datetime.combine(args.date, dt.time(), tzinfo=dt.timezone.utc).timestamp() if args.date else None
    )
    clock = DayClock(start if start is not None else today_midnight_s())
    if not all(math.isfinite(x) and x > 0 for x in (args.adsb_batch, args.max_batch)):
        raise ValueError("asterix: --adsb-batch and --max-batch must be finite numbers > 0")
    if not (args.max_time_ahead > 0 and args.max_time_behind > 0):
        raise ValueError("asterix: --max-time-ahead and --max-time-behind must be > 0")
    if not args.report_every >= 0:
        raise ValueError("asterix: --report-every must be >= 0")
    params = BridgeParams(
        adsb_source_id=args.adsb_id,
        adsb_batch_s=args.adsb_batch,
        max_batch_s=args.max_batch,
        altitude_from_fl=not args.no_fl_altitude,
        max_time_ahead_s=args.max_time_ahead,
        max_time_behind_s=args.max_time_behind,
    )
    bridge = AsterixBridge(list(sites), params, clock)
    session = open_tool_session(options, "asterix")
    try:
        import zenoh

        enc, block = zenoh.Encoding.APPLICATION_JSON, zenoh.CongestionControl.BLOCK

        def put(key: str, payload: bytes) -> None:
            session.put(key, payload, encoding=enc, congestion_control=block)

        if args.wait_service > 0:
            from service.recording.completion import service_statuses

            print(
                f"asterix: asking the service for {prefix}/status (up to {args.wait_service:g} s)",
                file=sys.stderr,
            )
            answered = service_statuses(session, prefix, args.wait_service, stop)
            print(
                "asterix: the service answers"
                if answered
                else f"asterix: no service answered {prefix}/status within {args.wait_service:g} s: going on",
                file=sys.stderr,
            )
        publisher = Publisher(put, prefix)
        sites_out = SiteRepeater(publisher, mapped, args.site_every)
        sites_out.start()
        writer = None
        if outputs:
            writer = Cat062Writer(args.system_sac, args.system_sic, sites, args.out_udp, args.out_file)
            out_sub = session.declare_subscriber(
                Keys(prefix).system_tracks, lambda sample: writer.write(sample.payload.to_bytes())
            )
        # Everything allocated so far lives for the whole run: out of the collector's scans,
        # which otherwise slow the decoder by up to 40 % (bench/bench_asterix_decode.py).
        gc.freeze()
        run = Run(
            bridge,
            publisher,
            stop,
            args.speed,
            args.date is not None,
            lambda m: print(m, file=sys.stderr),
            args.report_every,
            sites_out,
        )
        try:
            run.files(args.file)
            if args.udp and not stop.is_set():
                run.udp(args.udp, args.duration)
            elif not args.file and not args.udp:  # CAT062 output only: until stopped
                print("asterix: writing system tracks as CAT062 until stopped", file=sys.stderr)
                run.idle(args.duration)
        finally:
            # stopped: what is held goes out within the stop's grace; at the input's end all of it
            run.finish(time.monotonic() + STOP_FLUSH_S if stop.is_set() else None)
            print(run.summary(), file=sys.stderr)
            if writer is not None:
                if args.wait > 0 and publisher.last_time_s and not stop.is_set():
                    _outputs_complete(session, prefix, publisher, writer, args.wait)
                out_sub.undeclare()
                writer.close()
                print(f"asterix: CAT062 out: {writer.summary()}", file=sys.stderr)
    finally:
        session.close()
    return 0
