"""The one real public capture (cat_034_048.pcap; docs/asterix.md, "Public captures inside
sdists") read end to end.

The file is GPL-3.0-or-later and is never committed: tests/asterix/real_capture.py fetches the
pinned asterix-decoder 0.7.11 sdist at test time, checks it and caches the capture outside the
repository; these tests skip, saying what failed, when that is not possible (offline).
Set TOPOFUSION_ASTERIX_CAPTURE to a local copy to run them without the network.
"""

from __future__ import annotations

import collections
import ipaddress
from datetime import datetime, timezone
from pathlib import Path

import pytest

from service.asterix.capture import Datagram, detect_format, read_datagrams
from service.asterix.decode import Decoded, decode_datagram
from tests.asterix import real_capture as real_capture_module
from tests.asterix.real_capture import real_capture


@pytest.fixture(scope="module")
def capture_path() -> Path:
    path, problem = real_capture()
    if path is None:
        pytest.skip(f"real ASTERIX capture not available: {problem}")
    return path


@pytest.fixture(scope="module")
def datagrams(capture_path: Path) -> list[Datagram]:
    counters: collections.Counter[str] = collections.Counter()
    read = list(read_datagrams(capture_path, counters))
    assert not counters, counters  # every frame is a UDP datagram: nothing skipped
    return read


def data_blocks(payload: bytes) -> list[bytes]:
    """The payload cut into ASTERIX data blocks by their CAT/LEN headers (asserting they tile it)."""
    blocks = []
    position = 0
    while position < len(payload):
        assert position + 3 <= len(payload)
        length = int.from_bytes(payload[position + 1 : position + 3], "big")
        assert length >= 3 and position + length <= len(payload)
        blocks.append(payload[position : position + length])
        position += length
    assert position == len(payload)  # the data blocks' LENs sum to the UDP payload's length
    return blocks


def test_capture_is_pcap_of_100_udp_frames(capture_path: Path, datagrams: list[Datagram]) -> None:
    assert detect_format(capture_path.read_bytes()[:4]) == "pcap"
    assert len(datagrams) == 100


def test_payloads_are_whole_cat034_and_cat048_data_blocks(datagrams: list[Datagram]) -> None:
    categories: collections.Counter[int] = collections.Counter()
    for datagram in datagrams:
        assert datagram.payload[0] in (34, 48)
        blocks = data_blocks(datagram.payload)
        categories.update(block[0] for block in blocks)
    assert categories == {48: 86, 34: 34}  # as docs/asterix.md, "Public captures inside sdists", counts them


def test_addresses_are_the_radar_feeds(datagrams: list[Datagram]) -> None:
    for datagram in datagrams:
        source, _, source_port = datagram.source.rpartition(":")
        group, _, group_port = datagram.destination.rpartition(":")
        assert source in ("10.17.58.183", "10.17.58.184") and int(source_port) > 0
        assert ipaddress.ip_address(group).is_multicast and int(group_port) > 0
    assert len({datagram.destination for datagram in datagrams}) == 14


def test_times_lie_on_2016_05_05_and_span_0_44_s(datagrams: list[Datagram]) -> None:
    times = [datagram.time_s for datagram in datagrams]
    assert all(t is not None for t in times)
    stamps = [t for t in times if t is not None]
    assert stamps == sorted(stamps)
    days = {datetime.fromtimestamp(t, timezone.utc).date().isoformat() for t in stamps}
    assert days == {"2016-05-05"}
    assert stamps[-1] - stamps[0] == pytest.approx(0.4446, abs=0.001)


def test_cache_hit_needs_no_network(capture_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    def offline(*args: object, **kwargs: object) -> None:
        raise OSError("the network was used")

    monkeypatch.setattr(real_capture_module.urllib.request, "urlopen", offline)
    monkeypatch.setattr(real_capture_module.subprocess, "run", offline)
    real_capture.cache_clear()
    try:
        assert real_capture() == (capture_path, "")
    finally:
        real_capture.cache_clear()


def test_local_copy_must_be_the_capture(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    other = tmp_path / "other.pcap"
    other.write_bytes(b"not the capture")
    monkeypatch.setenv(real_capture_module.ENV_VAR, str(other))
    real_capture.cache_clear()
    try:
        path, problem = real_capture()
        assert path is None and "sha256" in problem and str(other) in problem
        monkeypatch.setenv(real_capture_module.ENV_VAR, str(tmp_path / "absent.pcap"))
        real_capture.cache_clear()
        path, problem = real_capture()
        assert path is None and "cannot read it" in problem
    finally:
        real_capture.cache_clear()


# ---------------------------------------------------------------------------------------------
# Decoding (service/asterix/decode.py)


def test_the_capture_decodes_whole(datagrams: list[Datagram]) -> None:
    """128 CAT048 target reports from SAC 25 and 7 SICs, 34 CAT034 records (32 sector
    crossings, 2 north markers), per docs/asterix.md, "Public captures inside sdists"; nothing dropped."""
    out = Decoded()
    for d in datagrams:
        decode_datagram(d.payload, out)
    assert not out.errors and not out.cat021
    assert len(out.cat048) == 128
    assert {(r.sac, r.sic) for r in out.cat048} == {(25, s) for s in (11, 12, 13, 14, 201, 204, 205)}
    assert collections.Counter(m.message_type for m in out.cat034) == {2: 32, 1: 2}
    positioned = [r for r in out.cat048 if r.rho_m is not None and r.theta_deg is not None]
    assert len(positioned) == 126
    assert all(0 < r.rho_m < 500_000 and 0 <= r.theta_deg < 360 for r in positioned)  # type: ignore[operator]
    # the time of day agrees with the capture's time stamps (2016-05-05, UTC): a report is
    # sent within 2.5 s of its detection, but for the two reports without a position (SIC 13, 20 s old)
    lags = []
    for d in datagrams:
        one = Decoded()
        decode_datagram(d.payload, one)
        assert d.time_s is not None
        lags += [d.time_s % 86_400 - r.tod_s for r in one.cat048]  # type: ignore[operator]
    assert all(0 <= x < 30 for x in lags)
    assert sum(x < 2.5 for x in lags) == len(lags) - 2
    assert all(r.mode_s is None or len(r.mode_s) == 6 for r in out.cat048)
