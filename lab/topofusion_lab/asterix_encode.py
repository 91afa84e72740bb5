"""A fast hand-written ASTERIX encoder for tests, benchmarks and simulations.

It writes the report tuples of ``service.asterix.decode`` as data blocks of the EUROCONTROL
ASTERIX categories 048 "Monoradar Target Reports" (edition 1.32), 034 "Transmission of
Monoradar Service Messages" (edition 1.29) and 021 "ADS-B Target Reports" (edition 2.7), with a
minimal valid item set per record.  libasterix
encodes at about 2 400 records/s; this is plain ``struct``/integer packing (tests check it
byte for byte against libasterix, tests/asterix/test_asterix_encode.py).

Items written:
  - CAT048: 010, 140 (if ``tod_s``), 020 (TYP 5 "Mode S roll-call" with ``mode_s``, else 3
    "SSR + PSR"; a first extent carrying TST only when ``test_target``), 040 (if ``rho_m`` and
    ``theta_deg``), 070 (if ``mode_3a``), 090 (if ``flight_level``), 220 (if ``mode_s``),
    110 (if ``height_m``).
  - CAT034: 010, 000, 030 (if ``tod_s``), 020 (if ``sector_deg``).
  - CAT021: 010, 040 (ATP 0 "24-bit ICAO address", ARC 0 "25 ft", no extent), 131 (if both
    coordinates), 080 (if ``icao24``), 073 (if ``tod_s``), 140 (if ``geometric_height_m``), 145
    (if ``flight_level``).
  Validity and group bits (V, G, L) are 0.

**Rounding.** A value becomes ``round(value_in_item_unit / lsb)``: Python's round-half-to-even,
the nearest step, with the same operations as libasterix (so both give the same octets).  The
decoder gives the value back within half a step.  Azimuth and sector wrap at 360° (a value that
rounds up to 360° is sent as 0°).  Any other value the item cannot hold raises ValueError.
"""

from __future__ import annotations

import struct
from collections.abc import Iterable, Sequence

from service.asterix.blocks import block, pack_blocks
from service.asterix.decode import FT_M, NM_M, Cat021Report, Cat034Message, Cat048Report

_HH = struct.Struct(">HH").pack
_H = struct.Struct(">H").pack
_ii = struct.Struct(">ii").pack

_OCTAL = frozenset("01234567")


def _raw(value: float, lsb: float, lo: int, hi: int, what: str) -> int:
    raw = round(value / lsb)
    if not lo <= raw <= hi:
        raise ValueError(f"{what} {value!r} out of range")
    return raw


def _tod(tod_s: float) -> bytes:
    return _raw(tod_s, 0.0078125, 0, 0xFFFFFF, "time of day").to_bytes(3, "big")


def _address(hex6: str, what: str) -> bytes:
    b = bytes.fromhex(hex6)
    if len(b) != 3:
        raise ValueError(f"{what} {hex6!r} is not 6 hex digits")
    return b


def encode_cat048_record(r: Cat048Report) -> bytes:
    """One CAT048 record (FSPEC and items; module docstring)."""
    o1 = 0xA0  # 010, 020
    o2 = o3 = 0
    parts = [bytes((r.sac, r.sic))]
    if r.tod_s is not None:
        o1 |= 0x40
        parts.append(_tod(r.tod_s))
    typ = 5 if r.mode_s is not None else 3
    parts.append(bytes((typ << 5 | 1, 0x80)) if r.test_target else bytes((typ << 5,)))
    if r.rho_m is not None and r.theta_deg is not None:
        o1 |= 0x10
        rho = _raw(r.rho_m / NM_M, 0.00390625, 0, 0xFFFF, "rho_m")
        parts.append(_HH(rho, round(r.theta_deg / 0.0054931640625) & 0xFFFF))
    if r.mode_3a is not None:
        o1 |= 0x08
        if len(r.mode_3a) != 4 or not _OCTAL.issuperset(r.mode_3a):
            raise ValueError(f"mode_3a {r.mode_3a!r} is not 4 octal digits")
        parts.append(_H(int(r.mode_3a, 8)))
    if r.flight_level is not None:
        o1 |= 0x04
        parts.append(_H(_raw(r.flight_level, 0.25, -0x2000, 0x1FFF, "flight_level") & 0x3FFF))
    if r.mode_s is not None:
        o2 = 0x80  # FRN 8
        parts.append(_address(r.mode_s, "mode_s"))
    if r.height_m is not None:
        o3 = 0x08  # FRN 19
        parts.append(_H(_raw(r.height_m / FT_M, 25.0, -0x2000, 0x1FFF, "height_m") & 0x3FFF))
    if o3:
        fspec = bytes((o1 | 1, o2 | 1, o3))
    elif o2:
        fspec = bytes((o1 | 1, o2))
    else:
        fspec = bytes((o1,))
    return fspec + b"".join(parts)


def encode_cat034_record(m: Cat034Message) -> bytes:
    """One CAT034 record: 010, 000, 030 and 020 when given."""
    o1 = 0xC0
    parts = [bytes((m.sac, m.sic, m.message_type))]
    if m.tod_s is not None:
        o1 |= 0x20
        parts.append(_tod(m.tod_s))
    if m.sector_deg is not None:
        o1 |= 0x10
        parts.append(bytes((round(m.sector_deg / 1.40625) & 0xFF,)))
    return bytes((o1,)) + b"".join(parts)


def encode_cat021_record(r: Cat021Report) -> bytes:
    """One CAT021 record (module docstring)."""
    o1 = 0xC0  # 010, 040
    o2 = o3 = 0
    parts = [bytes((r.sac, r.sic, 0))]
    if r.latitude_deg is not None and r.longitude_deg is not None:
        o1 |= 0x02  # FRN 7
        lsb = 180 / 2**30
        lat = _raw(r.latitude_deg, lsb, -(2**31), 2**31 - 1, "latitude_deg")
        parts.append(_ii(lat, _raw(r.longitude_deg, lsb, -(2**31), 2**31 - 1, "longitude_deg")))
    if r.icao24 is not None:
        o2 |= 0x10  # FRN 11
        parts.append(_address(r.icao24, "icao24"))
    if r.tod_s is not None:
        o2 |= 0x08  # FRN 12
        parts.append(_tod(r.tod_s))
    if r.geometric_height_m is not None:
        o3 |= 0x40  # FRN 16
        parts.append(
            _H(_raw(r.geometric_height_m / FT_M, 6.25, -0x8000, 0x7FFF, "geometric_height_m") & 0xFFFF)
        )
    if r.flight_level is not None:
        o3 |= 0x02  # FRN 21
        parts.append(_H(_raw(r.flight_level, 0.25, -0x8000, 0x7FFF, "flight_level") & 0xFFFF))
    if o3:
        fspec = bytes((o1 | 1, o2 | 1, o3))
    elif o2:
        fspec = bytes((o1 | 1, o2))
    else:
        fspec = bytes((o1,))
    return fspec + b"".join(parts)


def encode_cat048_block(reports: Sequence[Cat048Report]) -> bytes:
    """One CAT048 data block holding ``reports``."""
    return block(48, map(encode_cat048_record, reports))


def encode_cat034_block(messages: Sequence[Cat034Message]) -> bytes:
    """One CAT034 data block holding ``messages``."""
    return block(34, map(encode_cat034_record, messages))


def encode_cat021_block(reports: Sequence[Cat021Report]) -> bytes:
    """One CAT021 data block holding ``reports``."""
    return block(21, map(encode_cat021_record, reports))


def encode_cat048_blocks(reports: Iterable[Cat048Report], max_bytes: int = 1400) -> list[bytes]:
    """CAT048 data blocks of at most ``max_bytes`` octets (pack_blocks)."""
    return pack_blocks(48, map(encode_cat048_record, reports), max_bytes)


def encode_cat034_blocks(messages: Iterable[Cat034Message], max_bytes: int = 1400) -> list[bytes]:
    """CAT034 data blocks of at most ``max_bytes`` octets (pack_blocks)."""
    return pack_blocks(34, map(encode_cat034_record, messages), max_bytes)


def encode_cat021_blocks(reports: Iterable[Cat021Report], max_bytes: int = 1400) -> list[bytes]:
    """CAT021 data blocks of at most ``max_bytes`` octets (pack_blocks)."""
    return pack_blocks(21, map(encode_cat021_record, reports), max_bytes)
