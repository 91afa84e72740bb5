"""CAT062 output (service/asterix/cat062.py) byte for byte against libasterix, an independent
encoder of EUROCONTROL CAT062 edition 1.21, over realistic values."""

from __future__ import annotations

import contextlib
import signal
import socket
import time
from pathlib import Path
from typing import Any

import orjson
import pytest
import zenoh
from asterix import generated as gen
from hypothesis import given, settings
from hypothesis import strategies as st

from service.asterix.cat062 import Cat062Track, encode_cat062_blocks, encode_cat062_record
from service.asterix.command import Cat062Writer
from tests.asterix.test_asterix_service import bridge, output
from tests.scenario_helpers import scenario_messages
from tests.support import free_port, put_json, running_service, wait_for, wait_subscribed

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


def _decode_062(data: bytes) -> list[Any]:
    """Every CAT062 record of ``data`` as libasterix reads it (the independent decoder)."""
    from asterix.base import Bits, RawDatablock

    blocks = RawDatablock.parse(Bits.from_bytes(data))
    assert not isinstance(blocks, ValueError)
    records = []
    for b in blocks:
        assert b.get_category() == 62
        got = C062.cv_uap.parse(b.get_raw_records())
        assert not isinstance(got, ValueError)
        records += got
    return records


def test_the_bridge_writes_the_service_s_system_tracks_as_cat062(
    router: str, client: zenoh.Session, tmp_path: Path
) -> None:
    port = free_port()
    out_file = tmp_path / "tracks.ast"
    stream = scenario_messages("three-radar", duration_s=60.0)
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as rx:
        rx.bind(("127.0.0.1", port))
        rx.settimeout(0.2)
        with running_service(router, correlation_process=False) as svc:
            args = ["--connect", router, "--out-udp", f"127.0.0.1:{port}", "--out-file", str(out_file)]
            with bridge([*args, "--system-sac", "9", "--system-sic", "7"]) as (proc, lines):
                wait_for(
                    lambda: "writing system tracks" in output(lines) or proc.poll() is not None, timeout=30
                )
                assert proc.poll() is None
                wait_subscribed(client, "fusion/radar/A/plots")
                wait_subscribed(client, "fusion/system/tracks")
                for key, payload in stream:
                    put_json(client, key, payload)
                final = wait_for(
                    lambda: (b := svc.http.get("/system-tracks").json())["system_tracks"] and b, timeout=60
                )
                datagrams = []

                def received() -> bool:
                    with contextlib.suppress(TimeoutError):
                        datagrams.append(rx.recv(65535))
                    return len(datagrams) >= 3

                wait_for(received, timeout=30)
                time.sleep(1.5)  # the rebuilds of the last data seconds reach the bridge
                final = svc.http.get("/system-tracks").json()
                proc.send_signal(signal.SIGINT)
                assert proc.wait(timeout=30) == 0
    records = _decode_062(out_file.read_bytes())
    assert all(len(d) <= 1400 and d[0] == 62 for d in datagrams)
    assert records
    sac_sic = {
        (
            r.get_item("010").variation.get_item("SAC").variation.content.as_uint(),
            r.get_item("010").variation.get_item("SIC").variation.content.as_uint(),
        )
        for r in records
    }
    assert sac_sic == {(9, 7)}
    tod = final["time_s"] % 86_400
    last = [r for r in records if abs(r.get_item("070").variation.content.as_quantity("s") - tod) < 0.01]
    by_number = {r.get_item("040").variation.content.as_uint(): r for r in last}
    want = {int(t["system_track_id"][2:]): t for t in final["system_tracks"]}
    assert set(by_number) == set(want)
    for n, t in want.items():
        pos = by_number[n].get_item("105").variation
        assert pos.get_item("LAT").variation.content.as_quantity("°") == pytest.approx(
            t["latitude_deg"], abs=1e-5
        )
        assert pos.get_item("LON").variation.content.as_quantity("°") == pytest.approx(
            t["longitude_deg"], abs=1e-5
        )


def test_the_writer_refuses_what_is_no_system_track_and_says_so(tmp_path: Path) -> None:
    """Anyone may put on the system-track key: a position off the globe, a speed or height no
    aircraft has, or no batch at all is refused whole and counted, never written nor raised."""

    def batch(**track: Any) -> bytes:
        t = {
            "system_track_id": "S-1",
            "status": "confirmed",
            "latitude_deg": 48.0,
            "longitude_deg": 2.0,
            "altitude_m": 9_000.0,
            "velocity_ecef_mps": [100.0, -50.0, 0.0],
            "members": [{"radar_id": "A", "track_id": "A-1"}],
        }
        return orjson.dumps({"time_s": 1_763_769_600.0, "system_tracks": [{**t, **track}]})

    out = tmp_path / "tracks.ast"
    writer = Cat062Writer(0, 1, [], [], out)
    try:
        writer.write(batch())
        good = out.read_bytes()
        for hostile in (
            batch(latitude_deg=1e300),
            batch(velocity_ecef_mps=[1e308, 0.0, 0.0]),
            batch(altitude_m=-1e9),
            b"not json",
            b'{"time_s": "T-x"}',
        ):
            writer.write(hostile)
    finally:
        writer.close()
    assert out.read_bytes() == good and len(_decode_062(good)) == 1
    assert writer.bad == 5
    assert (
        writer.summary()
        == "1 tracks in 1 data blocks; 5 system-track batches refused (not writable as CAT062)"
    )


def test_a_track_missing_from_one_picture_keeps_its_age(tmp_path: Path) -> None:
    def track(tid: str) -> dict[str, Any]:
        return {
            "system_track_id": tid,
            "status": "confirmed",
            "latitude_deg": 48.0,
            "longitude_deg": 2.0,
            "altitude_m": None,
            "velocity_ecef_mps": [100.0, 0.0, 0.0],
            "members": [{"radar_id": "A", "track_id": "A-1"}],
        }

    writer = Cat062Writer(0, 1, [], [], None)
    t0 = 1_763_769_600.0
    writer.tracks_of({"time_s": t0, "system_tracks": [track("S-1"), track("S-2")]})
    writer.tracks_of({"time_s": t0 + 2, "system_tracks": [track("S-1")]})  # S-2 missing once
    ages = {
        t.number: t.age_s
        for t in writer.tracks_of({"time_s": t0 + 4, "system_tracks": [track("S-1"), track("S-2")]})
    }
    assert ages == {1: 4.0, 2: 4.0}
    writer.tracks_of({"time_s": t0 + 100, "system_tracks": [track("S-1")]})
    later = writer.tracks_of({"time_s": t0 + 102, "system_tracks": [track("S-1"), track("S-3")]})
    assert {t.number: t.age_s for t in later} == {1: 63.75, 3: 0.0}  # (the age item's most)
    assert set(writer._seen) == {"S-1", "S-3"}  # S-2, gone a minute, forgotten
    writer.close()
