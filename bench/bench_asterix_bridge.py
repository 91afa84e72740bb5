"""The ASTERIX bridge end to end: CAT048 records/s through decode, batching and publishing.

A feed of 12 radars (the national scenario's sites with SAC/SIC) and 1 500 aircraft, encoded
to CAT048 (with CAT034 sector crossings) in UDP-sized datagrams, is run through the bridge's
own loop (``service.asterix.command.Run``) four ways, side by side in one run:
  1. decode only (``decode_datagram``),
  2. decode + the bridge's batching into PlotBatch bodies (no encoding),
  3. 2 + JSON encoding (what is put on the wire),
  4. 3 + Zenoh puts to a peer session with a subscriber counting the samples (the command's
     publishing path, loopback).
Goal: the bridge is never the bottleneck; at least 50 000 CAT048 records/s on one core for 4
(a C++ decoder alone does 50 000-150 000).
Run: .venv/bin/python bench/bench_asterix_bridge.py [--records N] [--repeat K]
"""

from __future__ import annotations

import argparse
import contextlib
import threading
import time
from collections import Counter
from collections.abc import Callable, Iterable, Iterator

import numpy as np

from service.asterix.bridge import AsterixBridge, DayClock, Message
from service.asterix.capture import Datagram
from service.asterix.command import Publisher, Run
from service.asterix.decode import Cat034Message, Cat048Report, Decoded, decode_datagram
from service.transport.session import ZenohOptions, open_session
from service.wire.models import RadarSite
from topofusion_lab.asterix_encode import encode_cat034_blocks, encode_cat048_blocks
from topofusion_lab.scenarios.catalog import get_scenario

MIDNIGHT = 1_763_769_600.0


def feed(records: int, seed: int = 0) -> tuple[list[RadarSite], list[bytes]]:
    """Datagrams of about ``records`` CAT048 reports: per radar, 32 sectors per scan, each
    sector's reports then its CAT034 sector crossing."""
    rng = np.random.default_rng(seed)
    radars = get_scenario("national").radars
    sites = [replace_site(r.wire_site(), sac=30, sic=i + 1) for i, r in enumerate(radars)]
    per_sector = 12  # ~1 500 aircraft seen by ~half of 12 radars over 32 sectors
    datagrams: list[bytes] = []
    t = 3_600.0
    n = 0
    while n < records:
        for s in sites:
            assert s.sac is not None and s.sic is not None
            reports = [
                Cat048Report(
                    s.sac,
                    s.sic,
                    t + 0.01 * k,
                    float(rng.uniform(5e3, 3e5)),
                    float(rng.uniform(0, 360)),
                    f"{int(rng.integers(0, 4096)):04o}",
                    float(rng.integers(0, 1600)) / 4,
                    None if rng.random() < 0.1 else f"{int(rng.integers(0, 1 << 24)):06x}",
                    None,
                    False,
                )
                for k in range(per_sector)
            ]
            datagrams += encode_cat048_blocks(reports)
            datagrams += encode_cat034_blocks([Cat034Message(s.sac, s.sic, 2, t + 0.125, None)])
            n += per_sector
        t += 0.125
    return sites, datagrams


class Unencoded(Publisher):
    """Takes the bridge's messages and drops them (isolates the batching from the encoding)."""

    def publish(self, messages: Iterable[Message]) -> None:
        for _ in messages:
            pass


def replace_site(site: RadarSite, **kw: object) -> RadarSite:
    return site.model_copy(update=kw)


def timed(fn: Callable[[], None], repeat: int) -> float:
    best = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--records", type=int, default=100_000)
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    sites, datagrams = feed(args.records)
    n = 0
    for d in datagrams:
        out = Decoded()
        decode_datagram(d, out)
        n += len(out.cat048)
    print(f"feed: {n} CAT048 reports in {len(datagrams)} datagrams ({sum(map(len, datagrams)) / 1e6:.1f} MB)")

    def decode_only() -> None:
        for d in datagrams:
            decode_datagram(d, Decoded())

    def bridge_run(put: Callable[[str, bytes], None], encode: bool) -> Callable[[], None]:
        def go() -> None:
            bridge = AsterixBridge(sites, clock=DayClock(MIDNIGHT))
            publisher = Publisher(put, "fusion") if encode else Unencoded(put, "fusion")
            run = Run(bridge, publisher, threading.Event(), speed=0.0, fixed_date=True)
            for d in datagrams:
                run.datagram(Datagram(d, None, "", ""), None)
            run.finish()

        return go

    rows = [
        ("decode", timed(decode_only, args.repeat)),
        ("decode + batching", timed(bridge_run(lambda k, p: None, encode=False), args.repeat)),
        ("decode + batching + JSON", timed(bridge_run(lambda k, p: None, encode=True), args.repeat)),
    ]
    with socket_pair() as (put, received):
        rows.append(
            ("decode + batching + JSON + Zenoh put", timed(bridge_run(put, encode=True), args.repeat))
        )
        got = received()
    for name, secs in rows:
        print(f"{name:<40} {n / secs:>10,.0f} records/s  ({secs * 1e3:.0f} ms)")
    base = rows[0][1]
    print("ratios to decode alone: " + ", ".join(f"{name} {secs / base:.2f}x" for name, secs in rows[1:]))
    print(
        f"subscriber received {got} samples; goal 50 000 records/s for the last row: "
        f"{'met' if n / rows[-1][1] >= 50_000 else 'NOT met'}"
    )


@contextlib.contextmanager
def socket_pair() -> Iterator[tuple[Callable[[str, bytes], None], Callable[[], int]]]:
    """A listening peer session and a client putting to it; the listener counts samples."""
    import socket

    import zenoh

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        endpoint = f"tcp/127.0.0.1:{s.getsockname()[1]}"
    server = open_session(ZenohOptions(mode="peer", listen=(endpoint,)))
    count: Counter[str] = Counter()
    sub = server.declare_subscriber("fusion/**", lambda sample: count.update(("n",)))
    client = open_session(ZenohOptions(mode="client", connect=(endpoint,)))
    enc, block = zenoh.Encoding.APPLICATION_JSON, zenoh.CongestionControl.BLOCK
    time.sleep(0.5)  # the subscription reaches the client

    def put(key: str, payload: bytes) -> None:
        client.put(key, payload, encoding=enc, congestion_control=block)

    try:
        yield put, lambda: count["n"]
    finally:
        sub.undeclare()
        client.close()
        server.close()


if __name__ == "__main__":
    main()
