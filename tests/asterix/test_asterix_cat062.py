"""CAT062 output (service/asterix/cat062.py) byte for byte against libasterix, an independent
encoder of EUROCONTROL CAT062 edition 1.21, over realistic values."""

from __future__ import annotations

from typing import Any

from asterix import generated as gen
from hypothesis import given, settings
from hypothesis import strategies as st

from service.asterix.cat062 import Cat062Track, encode_cat062_blocks, encode_cat062_record

C062 = gen.Cat_062_1_21
FT = 0.3048


def _lib062(t: Cat062Track, sac: int, sic: int, service: int) -> Any:
    args: dict[str, Any] = {
        "010": (("SAC", sac), ("SIC", sic)),
        "015": service,
        "070": (t.tod_s, "s"),
        "105": (("LAT", (t.latitude_deg, "°")), ("LON", (t.longitude_deg, "°"))),
        "185": (("VX", (t.east_mps, "m/s")), ("VY", (t.north_mps, "m/s"))),
        "040": t.number % 65536,
        "080": (
            (("MON", int(t.mono)), ("SPI", 0), ("MRH", 0), ("SRC", 0), ("CNF", int(not t.confirmed)), None),
        ),
        "290": {"TRK": (t.age_s, "s")},
    }
    if t.altitude_m is not None:
        args["130"] = (t.altitude_m / FT, "ft")
    if t.sensor is not None:
        args["340"] = {"SID": (("SAC", t.sensor[0]), ("SIC", t.sensor[1]))}
    return C062.cv_record.create(args)


tracks = st.builds(
    Cat062Track,
    number=st.integers(1, 200_000),
    tod_s=st.floats(0, 86_399.99),
    latitude_deg=st.floats(-89.9, 89.9),
    longitude_deg=st.floats(-179.9, 179.9),
    east_mps=st.floats(-800, 800),
    north_mps=st.floats(-800, 800),
    confirmed=st.booleans(),
    mono=st.booleans(),
    age_s=st.floats(0, 63.7),
    altitude_m=st.none() | st.floats(-400, 40_000),
    sensor=st.none() | st.tuples(st.integers(0, 255), st.integers(0, 255)),
)


@settings(max_examples=200, deadline=None)
@given(t=tracks, sac=st.integers(0, 255), sic=st.integers(0, 255))
def test_records_equal_libasterix(t: Cat062Track, sac: int, sic: int) -> None:
    ours = encode_cat062_record(t, sac, sic, 3)
    theirs = C062.create([_lib062(t, sac, sic, 3)]).unparse().to_bytes()[3:]
    assert ours == theirs


@settings(max_examples=20, deadline=None)
@given(ts=st.lists(tracks, min_size=1, max_size=120))
def test_blocks_hold_every_track_in_order(ts: list[Cat062Track]) -> None:
    blocks = encode_cat062_blocks(ts, 1, 2, max_bytes=1400)
    assert all(len(b) <= 1400 and b[0] == 62 for b in blocks)
    assert b"".join(b[3:] for b in blocks) == b"".join(encode_cat062_record(t, 1, 2) for t in ts)
