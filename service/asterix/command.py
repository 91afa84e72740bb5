"""``topofusion asterix``: the bridge from an ASTERIX feed to the service (contract §4.3).

Files (``--file``, raw data blocks, pcap or pcapng) are read first, in the order given, paced
by ``--speed``; then the UDP endpoints (``--udp``, unicast or multicast) are read until the
bridge is stopped (SIGINT, SIGTERM) or ``--duration`` has passed.  Each datagram is decoded
(:mod:`.decode`), turned into payloads (:mod:`.bridge`) and published over Zenoh.  What is
still held at the end is sent, and a summary says what was read, sent and left out.
"""

from __future__ import annotations

import argparse
import datetime as dt
import gc
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
from service.asterix.decode import Decoded, decode_datagram
from service.asterix.udp import UdpEndpoint, UdpReceiver, parse_endpoint
from service.wire.keys import Keys
from service.wire.models import RadarSite

#: Progress is printed at most this often (wall seconds) on long runs.
PROGRESS_EVERY_S = 10.0


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
    """Puts the bridge's messages on their keys (JSON, blocking under congestion)."""

    def __init__(self, put: Callable[[str, bytes], None], prefix: str) -> None:
        self.put = put
        self.keys = Keys(prefix)
        self.sent: Counter[str] = Counter()
        self.plots = 0

    def publish(self, messages: Iterable[Message]) -> None:
        for m in messages:
            key = self.keys.plots(m.source_id) if m.kind == "plots" else self.keys.adsb(m.source_id)
            self.put(key, orjson.dumps(m.body))
            self.sent[m.kind] += 1
            if m.kind == "plots":
                self.plots += len(m.body["plots"]["time_s"])

    def sites(self, sites: Iterable[RadarSite]) -> None:
        for s in sites:
            self.put(self.keys.site(s.radar_id), s.model_dump_json(exclude_none=True).encode())


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
    ) -> None:
        self.bridge = bridge
        self.publisher = publisher
        self.stop = stop
        self.speed = speed
        self.fixed_date = fixed_date
        self.progress = progress
        self.capture: Counter[str] = Counter()
        self.datagrams = 0
        self.decoded = Counter[str]()
        self._next_progress = time.monotonic() + PROGRESS_EVERY_S

    def datagram(self, d: Datagram, reference_s: float | None) -> None:
        out = Decoded()
        decode_datagram(d.payload, out)
        self.datagrams += 1
        self.decoded.update(cat048=len(out.cat048), cat034=len(out.cat034), cat021=len(out.cat021))
        self.publisher.publish(self.bridge.feed(out, None if self.fixed_date else reference_s))
        if self.progress is not None and time.monotonic() >= self._next_progress:
            self._next_progress = time.monotonic() + PROGRESS_EVERY_S
            self.progress(self.line())

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
                if delay > 0 and self.stop.wait(delay):
                    return
            self.datagram(d, d.time_s)

    def udp(self, endpoints: list[UdpEndpoint], duration_s: float | None) -> None:
        end = None if duration_s is None else time.monotonic() + duration_s
        with UdpReceiver(endpoints) as rx:
            if self.progress is not None:
                bound = ", ".join(f"{h}:{p}" for h, p in rx.addresses)
                self.progress(f"asterix: listening on {bound}")
            while not self.stop.is_set() and (end is None or time.monotonic() < end):
                for d in rx.receive(0.2):
                    self.datagram(d, time.time())  # live: the clock's date

    def finish(self) -> None:
        self.publisher.publish(self.bridge.flush())

    def line(self) -> str:
        used, sent = self.bridge.used, self.publisher.sent
        return (
            f"asterix: {self.datagrams} datagrams, {used['cat048']} plots and {used['cat021']} ADS-B reports "
            f"used; sent {sent['plots']} plot batches, {sent['adsb']} ADS-B batches"
        )

    def summary(self) -> str:
        lines = [self.line()]
        lines.append(f"asterix: records decoded: {_counts(self.decoded)}")
        left = self.bridge.unusable
        lines.append(f"asterix: left out: {_counts(left) if left else 'nothing'}")
        if self.capture:
            lines.append(f"asterix: capture frames skipped: {_counts(self.capture)}")
        return "\n".join(lines)


def _counts(c: Counter[str]) -> str:
    return ", ".join(f"{k} {v}" for k, v in sorted(c.items())) or "none"


def asterix_main(
    args: argparse.Namespace, options: Any, prefix: str, sites_path: Path | None, stop: threading.Event
) -> int:
    """The command: check the inputs, open the session, run, say what happened."""
    from service.engine import load_sites
    from service.transport.session import open_tool_session

    if not args.file and not args.udp:
        raise ValueError("asterix: give at least one --file or --udp input")
    if args.speed < 0:
        raise ValueError("asterix: --speed must be >= 0")
    if sites_path is None:
        raise ValueError("asterix: --sites FILE (or TOPOFUSION_SITES) is needed to map SAC/SIC to radars")
    sites = load_sites(sites_path)
    mapped = [s for s in sites if s.sac is not None and s.sic is not None]
    if not mapped:
        print(
            f"asterix: no site in {sites_path} has sac and sic: no radar report can be mapped",
            file=sys.stderr,
        )
    for path in args.file:
        try:
            read_datagrams(path, Counter())  # header check now: a clear error before any publishing
        except CaptureError as exc:
            raise ValueError(f"asterix: {exc}") from None
    start = (
        dt.datetime.combine(args.date, dt.time(), tzinfo=dt.timezone.utc).timestamp() if args.date else None
    )
    clock = DayClock(start if start is not None else today_midnight_s())
    if args.adsb_batch <= 0 or args.max_batch <= 0:
        raise ValueError("asterix: --adsb-batch and --max-batch must be > 0")
    params = BridgeParams(
        adsb_source_id=args.adsb_id,
        adsb_batch_s=args.adsb_batch,
        max_batch_s=args.max_batch,
        altitude_from_fl=not args.no_fl_altitude,
    )
    bridge = AsterixBridge(list(sites), params, clock)
    session = open_tool_session(options, "asterix")
    try:
        import zenoh

        enc, block = zenoh.Encoding.APPLICATION_JSON, zenoh.CongestionControl.BLOCK

        def put(key: str, payload: bytes) -> None:
            session.put(key, payload, encoding=enc, congestion_control=block)

        publisher = Publisher(put, prefix)
        publisher.sites(mapped)
        # Everything allocated so far lives for the whole run: out of the collector's scans,
        # which otherwise slow the decoder by up to 40 % (bench/bench_asterix_decode.py).
        gc.freeze()
        run = Run(
            bridge, publisher, stop, args.speed, args.date is not None, lambda m: print(m, file=sys.stderr)
        )
        try:
            run.files(args.file)
            if args.udp and not stop.is_set():
                run.udp(args.udp, args.duration)
        finally:
            run.finish()
            print(run.summary(), file=sys.stderr)
    finally:
        session.close()
    return 0
