"""System tracks as ASTERIX CAT062 (EUROCONTROL CAT062 edition 1.21, SDPS track messages).

Items written per track (the record's FSPEC follows the UAP: FRN in brackets):
  - I062/010 [1] data source: the system's SAC/SIC (settings of the bridge);
  - I062/015 [3] service identification;
  - I062/070 [4] time of track information, the system tracks' data time (1/128 s);
  - I062/105 [5] calculated position in WGS-84 (180/2^25 deg);
  - I062/185 [7] calculated velocity, east and north (0.25 m/s) in the local horizontal plane of
    the track: the system has no stereographic plane of its own, and over a track's own
    position the two agree;
  - I062/040 [12] track number: the system track's number modulo 65 536;
  - I062/080 [13] track status: MON (one member), CNF (tentative), SRC 0 (no height source
    claimed);
  - I062/290 [14] system track update ages: TRK, the time since the track was first seen
    (0.25 s, at most 63.75);
  - I062/130 [18] calculated geometric altitude (6.25 ft), when within the item's range;
  - I062/340 [28] measured information: SID, the SAC/SIC of a member radar, when known.
I062/100 (cartesian position) is left out: it needs a system reference point we do not have.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Iterable
from dataclasses import dataclass

from service.asterix.blocks import pack_blocks

_FT_M = 0.3048
#: The items' steps (values are divided by them and rounded to the nearest, ties to even).
_TOD = 1.0 / 128.0
_LATLON = 180.0 / 2**25
_HH = struct.Struct(">hh").pack
_II = struct.Struct(">ii").pack
_H = struct.Struct(">H").pack
_h = struct.Struct(">h").pack


@dataclass(frozen=True)
class Cat062Track:
    number: int
    tod_s: float
    latitude_deg: float
    longitude_deg: float
    east_mps: float
    north_mps: float
    confirmed: bool
    mono: bool
    age_s: float
    altitude_m: float | None
    sensor: tuple[int, int] | None


def _fspec(frns: list[int]) -> bytes:
    octets = bytearray((max(frns) + 6) // 7)
    for frn in frns:
        k, bit = divmod(frn - 1, 7)
        octets[k] |= 0x80 >> bit
    for k in range(len(octets) - 1):
        octets[k] |= 1  # FX: another octet follows
    return bytes(octets)


def _clip(raw: float, lo: int, hi: int) -> int:
    return max(lo, min(hi, round(raw)))


def encode_cat062_record(t: Cat062Track, sac: int, sic: int, service: int = 1) -> bytes:
    """One CAT062 record (module docstring for the items)."""
    items: dict[int, bytes] = {
        1: bytes((sac, sic)),
        3: bytes((service,)),
        4: (round(t.tod_s / _TOD) % (1 << 24)).to_bytes(3, "big"),
        5: _II(
            _clip(t.latitude_deg / _LATLON, -(2**31), 2**31 - 1),
            _clip(t.longitude_deg / _LATLON, -(2**31), 2**31 - 1),
        ),
        7: _HH(_clip(t.east_mps / 0.25, -32768, 32767), _clip(t.north_mps / 0.25, -32768, 32767)),
        12: _H(t.number % 65536),
        13: bytes(((0x80 if t.mono else 0) | (0 if t.confirmed else 0x02),)),
        14: bytes((0x80, _clip(t.age_s / 0.25, 0, 255))),
    }
    if t.altitude_m is not None and math.isfinite(t.altitude_m):
        feet = t.altitude_m / _FT_M
        if -1500 <= feet <= 150_000:
            items[18] = _h(_clip(feet / 6.25, -32768, 32767))
    if t.sensor is not None:
        items[28] = bytes((0x80, *t.sensor))
    frns = sorted(items)
    return _fspec(frns) + b"".join(items[f] for f in frns)


def encode_cat062_blocks(
    tracks: Iterable[Cat062Track], sac: int, sic: int, service: int = 1, max_bytes: int = 1400
) -> list[bytes]:
    """Data blocks of at most ``max_bytes`` octets (one UDP datagram each)."""
    return pack_blocks(62, (encode_cat062_record(t, sac, sic, service) for t in tracks), max_bytes)
