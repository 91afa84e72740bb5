"""Benchmark of the ASTERIX decoder, service/asterix/decode.py (prints figures; never run by the tests).

Goal (docs/asterix.md, "The decoder: survey and choice"): at least 50 000 CAT048 records/s on
one core; the design aims at >= 300 000 for typical records.  Data, built with the lab's encoder
(topofusion_lab/asterix_encode.py) and split into data blocks of at most 1 400 octets (one UDP
datagram each), decoded datagram by datagram as the service receives them:

1. CAT048 "typical": ``--aircraft`` aircraft seen by one radar every 4 s scan, 10 % without a Mode
   S address; every record has I048/010, 140, 020, 040, 070, 090, 220 (if Mode S), 240, 161 and
   170 (the survey's item set), 10 % with a second extent in 020 and 170.  240, 161 and 170 are
   spliced into the encoder's records here (the encoder writes a minimal set).
2. CAT048 as the encoder writes it (010, 140, 020, 040, 070, 090, 220, and 110 for a third).
3. CAT021 ADS-B reports of the same aircraft (010, 040, 131, 080, 073, 140, 145).
4. CAT034: a north marker and 32 sector crossings per scan.

Printed: records per datagram and per second (best of ``--passes`` passes, each into a fresh
``Decoded``, so the records are kept as the service keeps a batch), and libasterix (test extra)
on the first ``--lib-records`` records of the same datagrams (parse plus extraction of the same
fields, best of 2) with the ratio to ours on that same subset, side by side in the same run.
Ours is timed before libasterix is imported (its generated module's objects slow every full
garbage collection of the process).

Usage: ``.venv/bin/python bench/bench_asterix_decode.py [--records N] [--aircraft A] [--passes P]``
"""

from __future__ import annotations

import argparse
import math
import os
import random
import time
from collections.abc import Callable
from typing import Any

from service.asterix.decode import Cat021Report, Cat034Message, Cat048Report, Decoded, decode_datagram
from topofusion_lab.asterix_encode import (
    encode_cat021_blocks,
    encode_cat034_blocks,
    encode_cat048_record,
    pack_blocks,
)

SCAN_S = 4.0
RADAR_LAT, RADAR_LON = 50.0, 8.0


class Aircraft:
    """A straight, level flight in the radar's plane (x east, y north, metres)."""

    def __init__(self, rng: random.Random, i: int) -> None:
        r = rng.uniform(5e3, 3.1e5)
        a = rng.uniform(0, 2 * math.pi)
        self.x, self.y = r * math.sin(a), r * math.cos(a)
        heading = rng.uniform(0, 2 * math.pi)
        speed = rng.uniform(60, 260)
        self.vx, self.vy = speed * math.sin(heading), speed * math.cos(heading)
        self.fl = rng.choice([rng.uniform(20, 100), rng.uniform(100, 410)])
        self.mode_3a = f"{rng.randrange(4096):04o}"
        self.mode_s = None if rng.random() < 0.1 else f"{rng.randrange(1 << 24):06x}"
        self.track_number = i
        self.extents = rng.random() < 0.1  # a second extent in 020 (TST) and 170

    def at(self, t: float) -> tuple[float, float]:
        """Position at ``t`` s; wrapped into a square of +-170 NM (within CAT048's 256 NM)."""
        lim = 170 * 1852.0
        x, y = self.x + self.vx * t, self.y + self.vy * t
        return (x + lim) % (2 * lim) - lim, (y + lim) % (2 * lim) - lim


def _scans(n_records: int, n_aircraft: int, seed: int) -> list[list[tuple[float, Aircraft, float, float]]]:
    """Per scan: (time of day, aircraft, range m, azimuth °) in azimuth order."""
    rng = random.Random(seed)
    fleet = [Aircraft(rng, i) for i in range(n_aircraft)]
    scans = []
    t0 = 36_000.0
    n_scans = -(-n_records // n_aircraft)
    for s in range(n_scans):
        scan = []
        for a in fleet:
            x, y = a.at(s * SCAN_S)
            rho = math.hypot(x, y)
            theta = math.degrees(math.atan2(x, y)) % 360.0
            scan.append((t0 + s * SCAN_S + theta / 360.0 * SCAN_S, a, rho, theta))
        scan.sort(key=lambda e: e[3])
        scans.append(scan)
    return scans


def _typical(rec: bytes, a: Aircraft) -> bytes:
    """An encoder record without I048/110 plus 240 (FRN 9), 161 (FRN 11) and 170 (FRN 14)."""
    if rec[0] & 1:
        o1, o2, body = rec[0], rec[1], rec[2:]
    else:
        o1, o2, body = rec[0] | 1, 0, rec[1:]
    callsign = bytes((0x04, 0x20, 0xC7, 0x1C, 0x72, 0x08))  # six 6-bit characters, not read
    i170 = b"\x41\x00" if a.extents else b"\x40"
    return bytes((o1, o2 | 0x52)) + body + callsign + a.track_number.to_bytes(2, "big") + i170


def build(n_records: int, n_aircraft: int, max_bytes: int, seed: int) -> dict[str, tuple[int, list[bytes]]]:
    """The four data sets: name -> (records, datagrams)."""
    scans = _scans(n_records, n_aircraft, seed)
    typical, minimal, ads_b = [], [], []
    for scan in scans:
        for tod, a, rho, theta in scan:
            r = Cat048Report(1, 2, tod, rho, theta, a.mode_3a, a.fl, a.mode_s, None, a.extents)
            typical.append(_typical(encode_cat048_record(r), a))
            h = a.fl * 30.48 if a.track_number % 3 == 0 else None
            minimal.append(encode_cat048_record(r._replace(height_m=h, test_target=False)))
            x, y = a.at(tod - 36_000.0)
            lat = RADAR_LAT + y / 111_195.0
            lon = RADAR_LON + x / (111_195.0 * math.cos(math.radians(RADAR_LAT)))
            icao = a.mode_s or f"{a.track_number:06x}"
            ads_b.append(Cat021Report(3, 4, tod, icao, lat, lon, a.fl * 30.48 + 150.0, a.fl))
    typical, minimal, ads_b = typical[:n_records], minimal[:n_records], ads_b[:n_records]
    messages = []
    for s in range(-(-n_records // 33)):
        t = 36_000.0 + s * SCAN_S
        messages.append(Cat034Message(1, 2, 1, t, None))
        messages += [Cat034Message(1, 2, 2, t + k / 32 * SCAN_S, k * 11.25) for k in range(32)]
    messages = messages[:n_records]
    return {
        "CAT048 typical": (len(typical), pack_blocks(48, typical, max_bytes)),
        "CAT048 encoder items": (len(minimal), pack_blocks(48, minimal, max_bytes)),
        "CAT021": (len(ads_b), encode_cat021_blocks(ads_b, max_bytes)),
        "CAT034": (len(messages), encode_cat034_blocks(messages, max_bytes)),
    }


def _best(run: Callable[[], int], passes: int) -> tuple[float, int]:
    best, n = math.inf, 0
    for _ in range(passes):
        t0 = time.perf_counter()
        n = run()
        best = min(best, time.perf_counter() - t0)
    return best, n


def ours(datagrams: list[bytes]) -> int:
    d = Decoded()
    for datagram in datagrams:
        decode_datagram(datagram, d)
    assert not d.errors, d.errors
    return len(d.cat048) + len(d.cat034) + len(d.cat021)


def _libasterix() -> Callable[[list[bytes]], int] | None:
    try:
        import asterix.generated as gen
        from asterix.base import Bits, RawDatablock
    except ImportError:
        return None
    specs: dict[int, Any] = {48: gen.Cat_048_1_32, 34: gen.Cat_034_1_29, 21: gen.Cat_021_2_7}

    def q(rec: Any, item: str, sub: str | None, unit: str) -> float | None:
        i = rec.get_item(item)
        if i is None:
            return None
        v = i.variation if sub is None else i.variation.get_item(sub).variation
        return float(v.content.as_quantity(unit))

    def extract(cat: int, rec: Any) -> tuple[Any, ...]:
        sac = rec.get_item("010").variation.get_item("SAC").variation.as_uint()
        sic = rec.get_item("010").variation.get_item("SIC").variation.as_uint()
        if cat == 48:
            m3a, adr = rec.get_item("070"), rec.get_item("220")
            return (
                sac,
                sic,
                q(rec, "140", None, "s"),
                q(rec, "040", "RHO", "NM"),
                q(rec, "040", "THETA", "°"),
                None if m3a is None else m3a.variation.get_item("MODE3A").variation.content.as_string(),
                q(rec, "090", "FL", "FL"),
                None if adr is None else f"{adr.variation.as_uint():06x}",
            )
        if cat == 34:
            return (sac, sic, rec.get_item("000").variation.as_uint(), q(rec, "030", None, "s"))
        adr = rec.get_item("080")
        return (
            sac,
            sic,
            q(rec, "073", None, "s"),
            None if adr is None else f"{adr.variation.as_uint():06x}",
            q(rec, "131", "LAT", "°"),
            q(rec, "131", "LON", "°"),
            q(rec, "140", None, "ft"),
            q(rec, "145", None, "FL"),
        )

    def decode(datagrams: list[bytes]) -> int:
        out = []
        for datagram in datagrams:
            blocks = RawDatablock.parse(Bits.from_bytes(datagram))
            assert not isinstance(blocks, ValueError)
            for db in blocks:
                cat = db.get_category()
                records = specs[cat].cv_uap.parse(db.get_raw_records())
                assert not isinstance(records, ValueError)
                out += [extract(cat, r) for r in records]
        return len(out)

    return decode


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--records", type=int, default=100_000, help="records per data set")
    parser.add_argument("--aircraft", type=int, default=300, help="aircraft in the scene")
    parser.add_argument("--max-bytes", type=int, default=1400, help="largest datagram (one data block each)")
    parser.add_argument("--passes", type=int, default=5, help="decode passes per data set (best taken)")
    parser.add_argument("--lib-records", type=int, default=2000, help="records decoded by libasterix")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()

    t0 = time.perf_counter()
    sets = build(args.records, args.aircraft, args.max_bytes, args.seed)
    built = time.perf_counter() - t0
    print(f"built in {built:.1f} s: {args.aircraft} aircraft, datagrams <= {args.max_bytes} octets")
    # Ours first, libasterix after: importing its 6 MB generated module adds tens of thousands
    # of objects that every full garbage collection then walks, which the service never has.
    rows = []
    for name, (n, datagrams) in sets.items():
        dt, got = _best(lambda d=datagrams: ours(d), args.passes)
        assert got == n, (name, got, n)
        subset, k = [], 0
        for d in datagrams:
            if k >= args.lib_records:
                break
            subset.append(d)
            k += ours([d])
        sub_dt, _ = _best(lambda s=subset: ours(s), args.passes)
        octets = sum(map(len, datagrams)) - 3 * len(datagrams)
        rows.append((name, n, len(datagrams), octets, dt, subset, k, sub_dt))
    lib = _libasterix()
    if lib is None:
        print("libasterix not installed (pip install -e '.[test]'): no side-by-side figures")
    header = f"{'data set':22s} {'records':>8s} {'rec/dgram':>9s} {'oct/rec':>7s} {'ours rec/s':>11s}"
    print(header + (f" {'libasterix rec/s':>16s} {'ratio':>6s}" if lib else ""))
    for name, n, n_datagrams, octets, dt, subset, k, sub_dt in rows:
        line = f"{name:22s} {n:8d} {n / n_datagrams:9.1f} {octets / n:7.1f} {n / dt:11.0f}"
        if lib is not None:
            lib_dt, lib_n = _best(lambda s=subset: lib(s), 2)
            assert lib_n == k
            line += f" {lib_n / lib_dt:16.0f} {lib_dt / sub_dt:5.0f}x"
        print(line)
    print(f"goal: >= 50 000 CAT048 records/s on one core; load average {os.getloadavg()[0]:.1f}")
    print(f"total {time.perf_counter() - t0:.1f} s")


if __name__ == "__main__":
    main()
