"""The lab's hand-written ASTERIX encoder: byte for byte libasterix's, and round trips.

libasterix (test extra) encodes the same values from the same units with its own conversion
(``round(value / lsb)``); our octets must be the same.  Decoding ours gives the values back
within half a resolution step.
"""

from __future__ import annotations

from typing import Any

import asterix.generated as gen
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from service.asterix.blocks import MAX_BLOCK, block, pack_blocks
from service.asterix.decode import Cat021Report, Cat034Message, Cat048Report, Decoded, decode_datagram
from topofusion_lab.asterix_encode import (
    encode_cat021_block,
    encode_cat021_blocks,
    encode_cat034_block,
    encode_cat034_blocks,
    encode_cat048_block,
    encode_cat048_blocks,
    encode_cat048_record,
)

C048, C034, C021 = gen.Cat_048_1_32, gen.Cat_034_1_29, gen.Cat_021_2_7
FT = 0.3048


# ---------------------------------------------------------------- libasterix's encoding


def _lib048(r: Cat048Report) -> Any:
    args: dict[str, Any] = {"010": (("SAC", r.sac), ("SIC", r.sic))}
    if r.tod_s is not None:
        args["140"] = (r.tod_s, "s")
    typ = 5 if r.mode_s is not None else 3
    first = (("TYP", typ), ("SIM", 0), ("RDP", 0), ("SPI", 0), ("RAB", 0), None)
    tst = (("TST", 1), ("ERR", 0), ("XPP", 0), ("ME", 0), ("MI", 0), ("FOEFRI", 0), None)
    args["020"] = (first, tst) if r.test_target else (first,)
    if r.rho_m is not None and r.theta_deg is not None:
        args["040"] = (("RHO", (r.rho_m / 1852.0, "NM")), ("THETA", (r.theta_deg, "°")))
    if r.mode_3a is not None:
        args["070"] = (("V", 0), ("G", 0), ("L", 0), 0, ("MODE3A", r.mode_3a))
    if r.flight_level is not None:
        args["090"] = (("V", 0), ("G", 0), ("FL", (r.flight_level, "FL")))
    if r.mode_s is not None:
        args["220"] = int(r.mode_s, 16)
    if r.height_m is not None:
        args["110"] = (0, ("3DH", (r.height_m / FT, "ft")))
    return C048.cv_record.create(args)


def _lib034(m: Cat034Message) -> Any:
    args: dict[str, Any] = {"010": (("SAC", m.sac), ("SIC", m.sic)), "000": m.message_type}
    if m.tod_s is not None:
        args["030"] = (m.tod_s, "s")
    if m.sector_deg is not None:
        args["020"] = (m.sector_deg, "°")
    return C034.cv_record.create(args)


def _lib021(r: Cat021Report) -> Any:
    args: dict[str, Any] = {
        "010": (("SAC", r.sac), ("SIC", r.sic)),
        "040": ((("ATP", 0), ("ARC", 0), ("RC", 0), ("RAB", 0), None),),
    }
    if r.latitude_deg is not None and r.longitude_deg is not None:
        args["131"] = (("LAT", (r.latitude_deg, "°")), ("LON", (r.longitude_deg, "°")))
    if r.icao24 is not None:
        args["080"] = int(r.icao24, 16)
    if r.tod_s is not None:
        args["073"] = (r.tod_s, "s")
    if r.geometric_height_m is not None:
        args["140"] = (r.geometric_height_m / FT, "ft")
    if r.flight_level is not None:
        args["145"] = (r.flight_level, "FL")
    return C021.cv_record.create(args)


# ---------------------------------------------------------------- value ranges


def _opt(s: st.SearchStrategy[Any]) -> st.SearchStrategy[Any]:
    return st.none() | s


_u8 = st.integers(0, 255)
_tod = st.floats(0.0, 86400.0, exclude_max=True)
_hex6 = st.integers(0, 2**24 - 1).map(lambda x: f"{x:06x}")
_fl = st.floats(-15.0, 1500.0)


@st.composite
def _report048(draw: st.DrawFn) -> Cat048Report:
    pos = draw(_opt(st.tuples(st.floats(0.0, 255.99 * 1852.0), st.floats(0.0, 360.0, exclude_max=True))))
    return Cat048Report(
        draw(_u8),
        draw(_u8),
        draw(_opt(_tod)),
        None if pos is None else pos[0],
        None if pos is None else pos[1],
        draw(_opt(st.integers(0, 0o7777).map(lambda x: f"{x:04o}"))),
        draw(_opt(_fl)),
        draw(_opt(_hex6)),
        draw(_opt(st.floats(-1000.0, 30000.0))),
        draw(st.booleans()),
    )


_message034 = st.builds(
    Cat034Message,
    _u8,
    _u8,
    st.integers(1, 4),
    _opt(_tod),
    _opt(st.floats(0.0, 360.0, exclude_max=True)),
)


@st.composite
def _report021(draw: st.DrawFn) -> Cat021Report:
    pos = draw(_opt(st.tuples(st.floats(-90.0, 90.0), st.floats(-180.0, 180.0))))
    return Cat021Report(
        draw(_u8),
        draw(_u8),
        draw(_opt(_tod)),
        draw(_opt(_hex6)),
        None if pos is None else pos[0],
        None if pos is None else pos[1],
        draw(_opt(st.floats(-1000.0, 30000.0))),
        draw(_opt(_fl)),
    )


SETTINGS = settings(max_examples=80, deadline=None)


def _close(a: float | None, b: float | None, step: float, period: float | None = None) -> bool:
    if a is None or b is None:
        return a is None and b is None
    d = abs(a - b)
    if period is not None:
        d = min(d, period - d)
    return d <= step / 2 * (1 + 1e-9) + 1e-9


# ---------------------------------------------------------------- byte for byte, round trips


@SETTINGS
@given(st.lists(_report048(), min_size=1, max_size=4))
def test_cat048_is_libasterix_byte_for_byte_and_round_trips(reports: list[Cat048Report]) -> None:
    ours = encode_cat048_block(reports)
    assert ours == C048.create([_lib048(r) for r in reports]).unparse().to_bytes()
    d = Decoded()
    decode_datagram(ours, d)
    assert not d.errors and len(d.cat048) == len(reports)
    for got, r in zip(d.cat048, reports, strict=True):
        assert (got.sac, got.sic, got.mode_3a, got.mode_s, got.test_target) == (
            r.sac,
            r.sic,
            r.mode_3a,
            r.mode_s,
            r.test_target,
        )
        assert _close(got.tod_s, r.tod_s, 1 / 128)
        assert _close(got.rho_m, r.rho_m, 1852 / 256)
        assert _close(got.theta_deg, r.theta_deg, 360 / 2**16, 360.0)
        assert got.theta_deg is None or 0 <= got.theta_deg < 360
        assert _close(got.flight_level, r.flight_level, 0.25)
        assert _close(got.height_m, r.height_m, 25 * FT)


@SETTINGS
@given(st.lists(_message034, min_size=1, max_size=4))
def test_cat034_is_libasterix_byte_for_byte_and_round_trips(messages: list[Cat034Message]) -> None:
    ours = encode_cat034_block(messages)
    assert ours == C034.create([_lib034(m) for m in messages]).unparse().to_bytes()
    d = Decoded()
    decode_datagram(ours, d)
    assert not d.errors and len(d.cat034) == len(messages)
    for got, m in zip(d.cat034, messages, strict=True):
        assert (got.sac, got.sic, got.message_type) == (m.sac, m.sic, m.message_type)
        assert _close(got.tod_s, m.tod_s, 1 / 128)
        assert _close(got.sector_deg, m.sector_deg, 360 / 256, 360.0)


@SETTINGS
@given(st.lists(_report021(), min_size=1, max_size=4))
def test_cat021_is_libasterix_byte_for_byte_and_round_trips(reports: list[Cat021Report]) -> None:
    ours = encode_cat021_block(reports)
    assert ours == C021.create([_lib021(r) for r in reports]).unparse().to_bytes()
    d = Decoded()
    decode_datagram(ours, d)
    assert not d.errors and len(d.cat021) == len(reports)
    for got, r in zip(d.cat021, reports, strict=True):
        assert (got.sac, got.sic, got.icao24) == (r.sac, r.sic, r.icao24)
        assert _close(got.tod_s, r.tod_s, 1 / 128)
        assert _close(got.latitude_deg, r.latitude_deg, 180 / 2**30)
        assert _close(got.longitude_deg, r.longitude_deg, 180 / 2**30)
        assert _close(got.geometric_height_m, r.geometric_height_m, 6.25 * FT)
        assert _close(got.flight_level, r.flight_level, 0.25)


@pytest.mark.parametrize("half", [0.5, 1.5, 2.5, -0.5, -1.5])
def test_ties_round_half_to_even_like_libasterix(half: float) -> None:
    r = Cat048Report(
        1,
        2,
        abs(half) / 128,
        abs(half) * 1852 / 256,
        abs(half) * 360 / 2**16,
        None,
        half / 4,
        None,
        half * 25 * FT,
        False,
    )
    assert encode_cat048_block([r]) == C048.create([_lib048(r)]).unparse().to_bytes()
    d = Decoded()
    decode_datagram(encode_cat048_block([r]), d)
    assert d.cat048[0].flight_level == round(half) / 4  # to the even step


def test_azimuth_and_sector_wrap_at_360() -> None:
    r = Cat048Report(1, 2, None, 1000.0, 360 - 1e-9, None, None, None, None, False)
    m = Cat034Message(1, 2, 2, None, 359.9)
    d = Decoded()
    decode_datagram(encode_cat048_block([r]) + encode_cat034_block([m]), d)
    assert d.cat048[0].theta_deg == 0.0 and d.cat034[0].sector_deg == 0.0
    assert encode_cat048_block([r]) == C048.create([_lib048(r)]).unparse().to_bytes()


@pytest.mark.parametrize(
    "bad",
    [
        Cat048Report(1, 2, None, 256 * 1852.0, 0.0, None, None, None, None, False),  # beyond 16 bits
        Cat048Report(1, 2, -1.0, None, None, None, None, None, None, False),
        Cat048Report(1, 2, None, None, None, None, 2048.0, None, None, False),
        Cat048Report(1, 2, None, None, None, "8000", None, None, None, False),
        Cat048Report(1, 2, None, None, None, "777", None, None, None, False),
        Cat048Report(1, 2, None, None, None, "+777", None, None, None, False),
        Cat048Report(1, 2, None, None, None, None, None, "abcdefab", None, False),
        Cat048Report(1, 2, None, None, None, None, None, "xyzxyz", None, False),
        Cat048Report(256, 2, None, None, None, None, None, None, None, False),
        Cat048Report(1, 2, None, None, None, None, None, None, 70_000.0, False),
    ],
)
def test_values_the_items_cannot_hold_raise(bad: Cat048Report) -> None:
    with pytest.raises(ValueError):
        encode_cat048_record(bad)


def test_cat021_minimal_descriptor_and_out_of_range() -> None:
    r = Cat021Report(1, 2, None, None, None, None, None, None)
    assert encode_cat021_block([r]) == bytes((21, 0, 7, 0xC0, 1, 2, 0))
    with pytest.raises(ValueError):
        encode_cat021_block([r._replace(flight_level=8192.0)])


# ---------------------------------------------------------------- splitting into datagrams


@pytest.mark.parametrize("max_bytes", [60, 200, 1400])
def test_blocks_split_at_max_bytes_and_keep_every_record(max_bytes: int) -> None:
    reports = [
        Cat048Report(
            1,
            2,
            i * 0.5,
            1000.0 + i,
            i % 360,
            f"{i:04o}",
            300.0,
            f"{i:06x}" if i % 3 else None,
            None,
            i % 7 == 0,
        )
        for i in range(500)
    ]
    blocks = encode_cat048_blocks(reports, max_bytes)
    assert all(len(b) <= max_bytes for b in blocks)
    d = Decoded()
    for b in blocks:
        decode_datagram(b, d)
    assert not d.errors and len(d.cat048) == 500
    assert [r.mode_s for r in d.cat048] == [r.mode_s for r in reports]
    # as full as they go: each block's next record would not have fitted
    records = [encode_cat048_record(r) for r in reports]
    assert b"".join(b[3:] for b in blocks) == b"".join(records)
    first_at: dict[int, int] = {}  # offset in the records' octets -> record starting there
    offset = 0
    for i, rec in enumerate(records):
        first_at[offset] = i
        offset += len(rec)
    offset = 0
    for b in blocks[:-1]:
        offset += len(b) - 3
        assert len(b) + len(records[first_at[offset]]) > max_bytes
    messages = [Cat034Message(1, 2, 2, i / 8, i * 1.40625 % 360) for i in range(300)]
    reports21 = [Cat021Report(1, 2, i / 2, f"{i:06x}", 45.0, 7.0, 1000.0, 300.0) for i in range(300)]
    for blocks_, attr, n in (
        (encode_cat034_blocks(messages, max_bytes), "cat034", 300),
        (encode_cat021_blocks(reports21, max_bytes), "cat021", 300),
    ):
        d = Decoded()
        decode_datagram(b"".join(blocks_), d)
        assert all(len(b) <= max_bytes for b in blocks_) and len(getattr(d, attr)) == n and not d.errors


def test_pack_blocks_limits() -> None:
    assert pack_blocks(48, []) == []
    assert pack_blocks(48, [b"\x00" * 7], max_bytes=10) == [block(48, [b"\x00" * 7])]
    with pytest.raises(ValueError):
        pack_blocks(48, [b"\x00" * 8], max_bytes=10)
    with pytest.raises(ValueError):
        pack_blocks(48, [b"\x00"], max_bytes=MAX_BLOCK + 1)
    with pytest.raises(ValueError):
        block(48, [b"\x00" * (MAX_BLOCK - 2)])
    assert len(block(48, [b"\x00" * (MAX_BLOCK - 3)])) == MAX_BLOCK
    assert len(pack_blocks(48, [b"\x00" * 10] * 100, max_bytes=103)) == 10
