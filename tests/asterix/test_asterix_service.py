"""A real capture through `topofusion asterix` (a subprocess) into the real service over Zenoh:
through ``--file`` and through ``--udp``, every positioned target report becomes a plot of
the right radar and the service rejects nothing."""

from __future__ import annotations

import datetime as dt
import json
import os
import queue
import signal
import socket
import subprocess
import sys
import threading
import time
from collections import Counter
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest

from service.asterix.capture import read_datagrams
from service.asterix.decode import Decoded, decode_datagram
from service.engine import EngineConfig
from service.wire.models import RadarSite
from tests.asterix.real_capture import real_capture_path
from tests.support import RunningService, free_port, running_service, wait_for

TOPOFUSION = str(Path(sys.executable).parent / "topofusion")
#: The capture's radars: SAC 25, these SICs (its data sources); positions are not in the data.
SICS = (11, 12, 13, 14, 201, 204, 205)
#: Between two datagrams sent to the bridge over UDP (s).
UDP_PACE_S = 0.002


@pytest.fixture(scope="module")
def capture() -> Path:
    path = real_capture_path()
    if path is None:
        pytest.skip(
            "the public ASTERIX capture could not be fetched (offline?): see tests/asterix/real_capture.py"
        )
    return path


def sites() -> list[RadarSite]:
    return [
        RadarSite(radar_id=f"S{sic}", latitude_deg=45.0 + i * 0.1, longitude_deg=15.0, sac=25, sic=sic)
        for i, sic in enumerate(SICS)
    ]


def positioned_reports(path: Path) -> Counter[str]:
    out = Decoded()
    for d in read_datagrams(path, Counter()):
        decode_datagram(d.payload, out)
    assert not out.errors
    return Counter(f"S{r.sic}" for r in out.cat048 if r.rho_m is not None and r.theta_deg is not None)


@contextmanager
def bridge(args: list[str]) -> Iterator[tuple[subprocess.Popen[str], queue.Queue[str]]]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("TOPOFUSION_")}
    proc = subprocess.Popen(
        [TOPOFUSION, "asterix", *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        env={**env, "PYTHONUNBUFFERED": "1"},
    )
    lines: queue.Queue[str] = queue.Queue()
    assert proc.stdout is not None
    reader = threading.Thread(target=lambda: [lines.put(x) for x in proc.stdout], daemon=True)  # type: ignore[union-attr]
    reader.start()
    try:
        yield proc, lines
    finally:
        if proc.poll() is None:
            proc.kill()  # only reached when a test failed before the bridge ended
        proc.wait(timeout=10)
        reader.join(timeout=5)
        proc.stdout.close()


def wait_listening(proc: subprocess.Popen[str], lines: queue.Queue[str]) -> list[str]:
    """Wait until the bridge says it listens on its UDP endpoints; the lines it wrote so far."""
    seen: list[str] = []

    def listening() -> bool:
        while not lines.empty():
            seen.append(lines.get())
        return any("listening on" in x for x in seen) or proc.poll() is not None

    wait_for(listening, timeout=30)
    assert proc.poll() is None, "".join(seen)
    return seen


def output(lines: queue.Queue[str]) -> str:
    out = []
    while not lines.empty():
        out.append(lines.get())
    return "".join(out)


def plots_by_radar(svc: RunningService) -> dict[str, int]:
    return {r["radar_id"]: r["plots"] for r in svc.http.get("/status").json()["radars"] if r["plots"]}


def check_service(svc: RunningService, expected: Counter[str]) -> None:
    try:
        wait_for(lambda: plots_by_radar(svc) == dict(expected), timeout=30)
    except AssertionError:
        raise AssertionError(f"{plots_by_radar(svc)} != {dict(expected)}") from None
    status = svc.http.get("/status").json()
    assert status["rejected"] == {}
    assert all(r["rejected"] == 0 for r in status["radars"])


def test_a_real_capture_through_file(capture: Path, router: str, tmp_path: Path) -> None:
    expected = positioned_reports(capture)
    assert sum(expected.values()) == 126  # 128 target reports, 2 without a position
    sites_file = tmp_path / "sites.json"
    sites_file.write_text(json.dumps([s.model_dump(exclude_none=True) for s in sites()]))
    with running_service(router, EngineConfig(sites=tuple(sites()))) as svc:
        args = ["--file", str(capture), "--sites", str(sites_file), "--connect", router, "--speed", "0"]
        with bridge(args) as (proc, lines):
            assert proc.wait(timeout=60) == 0, output(lines)
        text = output(lines)
        check_service(svc, expected)
    assert "126 plots and 0 ADS-B reports used" in text, text
    assert "left out: cat048_no_position 2" in text, text
    assert "Traceback" not in text


def test_a_real_capture_through_udp(capture: Path, router: str, tmp_path: Path) -> None:
    expected = positioned_reports(capture)
    sites_file = tmp_path / "sites.json"
    sites_file.write_text(json.dumps([s.model_dump(exclude_none=True) for s in sites()]))
    port = free_port()
    datagrams = list(read_datagrams(capture, Counter()))
    payloads = [d.payload for d in datagrams]
    # a recording replayed over UDP: --date, or the bridge judges its times by the wall clock
    assert datagrams[0].time_s is not None
    date = dt.datetime.fromtimestamp(datagrams[0].time_s, dt.timezone.utc).date().isoformat()
    with running_service(router, EngineConfig(sites=tuple(sites()))) as svc:
        args = ["--udp", f"127.0.0.1:{port}", "--sites", str(sites_file), "--connect", router, "--date", date]
        with bridge(args) as (proc, lines):
            seen = wait_listening(proc, lines)
            junk = [b"\x30\x00", b"\x30\x00\x09\xff\xff\xff\xff\xff\xff", b"\x3e\x00\x04\x00", b"garbage!"]
            with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as tx:
                for i, p in enumerate(payloads):
                    # paced as a radar's sectors come (far faster still): a burst of the whole
                    # capture can overflow the socket's buffer while a loaded machine starves
                    # the bridge, and the count below is exact
                    time.sleep(UDP_PACE_S)
                    tx.sendto(p, ("127.0.0.1", port))
                    if i % 25 == 0:  # malformed datagrams in between: counted, never fatal
                        tx.sendto(junk[(i // 25) % len(junk)], ("127.0.0.1", port))
            wait_for(lambda: sum(plots_by_radar(svc).values()) > 0, timeout=30)
            proc.send_signal(signal.SIGINT)  # what is still held is sent on stop
            assert proc.wait(timeout=30) == 0
            text = "".join(seen) + output(lines)
        check_service(svc, expected)
    assert f"{len(payloads) + 4} datagrams" in text, text
    assert "blocks_truncated 2" in text and "blocks_undecodable 1" in text, text
    assert "blocks_unsupported_category 1" in text, text
    assert "Traceback" not in text
