"""ASTERIX in five minutes: the sample capture under examples/ and the README's walkthrough.

* The capture is decodable by the bridge (every datagram, nothing left out) and, where
  libasterix is installed (the test extra), by that independent decoder too; it is small.
* It is what the command in examples/README.md makes (to the resolution ASTERIX carries).
* The README's walkthrough, run as written (free ports instead of 7447 and 8000): the service,
  then the bridge with the capture, gives radar-radar and radar-ADS-B pairs and CAT062 out.
* ``simulate --asterix-udp`` sends a scenario as datagrams (what the bridge's ``--udp`` reads).
"""

from __future__ import annotations

import collections
import json
import re
import socket
import subprocess
from pathlib import Path
from typing import Any

import httpx
import pytest

from service.asterix.capture import read_datagrams
from service.asterix.decode import Decoded, decode_datagram
from service.wire.models import RadarSite
from tests.doc_commands import (
    PROCESS_S,
    ROOT,
    TOPOFUSION,
    code_block,
    commands,
    environment,
    free_ports,
    started,
    with_ports,
)
from tests.support import wait_for
from topofusion_lab.asterix_scenario import AZIMUTH_STEP_DEG, HEIGHT_STEP_M, LATLON_STEP_DEG, RANGE_STEP_M

EXAMPLES = ROOT / "examples"
CAPTURE = EXAMPLES / "three-radar.pcap"
SITES = EXAMPLES / "three-radar-sites.json"
#: The sample stays small: a repository carries it (bytes).
MAX_CAPTURE_BYTES = 300_000
#: Time of day resolution of the items (s): 1/128.
TOD_STEP_S = 1.0 / 128.0
#: What the sample holds (examples/README.md): 360 radar batches (3 radars x 60 s, 2 a second),
#: each closed by one CAT034 message; over 3 000 plots and 1 000 ADS-B reports.
SECTOR_MESSAGES = 360
MIN_PLOTS, MIN_ADSB_REPORTS = 3000, 1000
#: Through the README's walkthrough the service pairs nearly every aircraft (80, a quarter of
#: them with ADS-B) across the 6 source pairs; at least this many pairs ...
MIN_PAIRS = 200
#: ... and the bridge writes at least this many CAT062 system track reports.
MIN_CAT062_TRACKS = 100


def decoded(path: Path) -> tuple[int, Decoded, collections.Counter[str], list[float]]:
    skipped: collections.Counter[str] = collections.Counter()
    out = Decoded()
    stamps = []
    n = 0
    for d in read_datagrams(path, skipped):
        decode_datagram(d.payload, out)
        assert d.time_s is not None
        stamps.append(d.time_s)
        n += 1
    return n, out, skipped, stamps


def test_the_sample_is_small_and_the_bridge_decodes_all_of_it() -> None:
    assert CAPTURE.stat().st_size <= MAX_CAPTURE_BYTES
    _, out, skipped, stamps = decoded(CAPTURE)
    assert not skipped and not out.errors, (skipped, out.errors)
    assert stamps == sorted(stamps) and stamps[-1] - stamps[0] == pytest.approx(59.5, abs=1.0)
    sites = [RadarSite.model_validate(s) for s in json.loads(SITES.read_text())]
    sources = {(s.sac, s.sic) for s in sites}
    assert len(sources) == len(sites) == 3
    assert {(r.sac, r.sic) for r in out.cat048} == sources
    assert {(m.sac, m.sic) for m in out.cat034} == sources
    assert (
        len(out.cat048) > MIN_PLOTS
        and len(out.cat034) == SECTOR_MESSAGES
        and len(out.cat021) > MIN_ADSB_REPORTS
    )
    positioned = [r for r in out.cat048 if r.rho_m is not None and r.theta_deg is not None]
    assert len(positioned) == len(out.cat048)
    assert sum(r.mode_s is not None for r in out.cat048) > len(out.cat048) // 2  # Mode S radars


def test_libasterix_decodes_every_record_of_the_sample() -> None:
    asterix = pytest.importorskip("asterix.generated", reason="libasterix (the test extra) is not installed")
    from asterix.base import Bits, RawDatablock

    uaps = {48: asterix.Cat_048_1_32, 34: asterix.Cat_034_1_29, 21: asterix.Cat_021_2_7}
    counts: collections.Counter[int] = collections.Counter()
    for d in read_datagrams(CAPTURE, collections.Counter()):
        blocks = RawDatablock.parse(Bits.from_bytes(d.payload))
        assert not isinstance(blocks, ValueError), blocks
        for b in blocks:
            records = uaps[b.get_category()].cv_uap.parse(b.get_raw_records())
            assert not isinstance(records, ValueError), records
            counts[b.get_category()] += len(records)
    _, ours, _, _ = decoded(CAPTURE)
    assert counts == {48: len(ours.cat048), 34: len(ours.cat034), 21: len(ours.cat021)}


def _made_by_the_documented_command(tmp_path: Path) -> tuple[Path, Path]:
    text = (EXAMPLES / "README.md").read_text()
    block = re.search(r"^```bash\n(topofusion simulate .*?)^```", text, flags=re.MULTILINE | re.DOTALL)
    assert block is not None
    [command] = commands(block.group(1))
    argv = command.replace("examples/", f"{tmp_path}/").split()
    assert argv[0] == "topofusion"
    run = subprocess.run(
        [TOPOFUSION, *argv[1:]],
        env=environment(),
        capture_output=True,
        text=True,
        timeout=PROCESS_S,
        check=False,
    )
    assert run.returncode == 0, run.stderr
    return tmp_path / CAPTURE.name, tmp_path / SITES.name


def _close(a: Any, b: Any, step: float) -> bool:
    if a is None or b is None:
        return a is b
    return abs(a - b) <= step * 1.01  # one step apart at most: a value on a rounding boundary


def test_the_sample_is_what_its_documented_command_makes(tmp_path: Path) -> None:
    capture, sites = _made_by_the_documented_command(tmp_path)
    assert json.loads(sites.read_text()) == json.loads(SITES.read_text())
    n_new, new, _, stamps_new = decoded(capture)
    n_old, old, _, stamps_old = decoded(CAPTURE)
    assert (n_new, len(new.cat048), len(new.cat034), len(new.cat021)) == (
        n_old,
        len(old.cat048),
        len(old.cat034),
        len(old.cat021),
    )
    assert stamps_new == stamps_old
    assert new.cat034 == old.cat034
    # the same records to the last step of each item (the arithmetic of another machine may
    # put a value on the other side of a rounding boundary)
    for a, b in zip(new.cat048, old.cat048, strict=True):
        assert (a.sac, a.sic, a.mode_3a, a.mode_s) == (b.sac, b.sic, b.mode_3a, b.mode_s)
        assert _close(a.tod_s, b.tod_s, TOD_STEP_S) and _close(a.rho_m, b.rho_m, RANGE_STEP_M)
        assert _close(a.theta_deg, b.theta_deg, AZIMUTH_STEP_DEG) or abs(a.theta_deg - b.theta_deg) > 359
        assert _close(a.height_m, b.height_m, HEIGHT_STEP_M) and _close(a.flight_level, b.flight_level, 0.25)
    for c, d in zip(new.cat021, old.cat021, strict=True):
        assert (c.sac, c.sic, c.icao24) == (d.sac, d.sic, d.icao24)
        assert _close(c.tod_s, d.tod_s, TOD_STEP_S)
        assert _close(c.latitude_deg, d.latitude_deg, LATLON_STEP_DEG)
        assert _close(c.longitude_deg, d.longitude_deg, LATLON_STEP_DEG)


@pytest.mark.slow
def test_the_readme_walkthrough_gives_pairs_and_cat062(tmp_path: Path) -> None:
    block = code_block(ROOT / "README.md", "### ASTERIX in five minutes", language="bash")
    ports = free_ports()
    lines = [with_ports(c, ports) for c in commands(block)]
    run_line, bridge_line, curl_line, kill_line = lines
    assert run_line.startswith(".venv/bin/topofusion run &") and kill_line.startswith("kill ")
    assert bridge_line.startswith(".venv/bin/topofusion asterix ") and curl_line.startswith("curl ")
    # `run` names no port: its defaults (7447, 8000) become the free ports through its settings
    env = environment(
        TOPOFUSION_ZENOH_LISTEN=f"tcp/127.0.0.1:{ports['7447']}", TOPOFUSION_HTTP_PORT=ports["8000"]
    )
    bridge_argv = [TOPOFUSION, *bridge_line.split()[1:]]
    bridge_argv = [a.replace("examples/", f"{EXAMPLES}/") for a in bridge_argv]
    with started([TOPOFUSION, "run"], tmp_path, env) as service:
        # started at once: the bridge waits for the router, then for the service to answer
        bridge = subprocess.run(
            bridge_argv,
            cwd=tmp_path,
            env=environment(),
            capture_output=True,
            text=True,
            timeout=3 * PROCESS_S,
        )  # (it waits for the service's outputs, which a loaded machine makes slow)
        assert bridge.returncode == 0, bridge.stderr + service.output()
        assert "asterix: the service answers" in bridge.stderr
        assert "left out: nothing" in bridge.stderr, bridge.stderr
        # the CAT062 file holds the whole picture: the bridge waited for the service to be done
        assert "asterix: the service's outputs are complete through data time" in bridge.stderr
        url = re.search(r"curl -s (\S+)", curl_line)
        assert url is not None
        with httpx.Client(timeout=10) as http:
            # complete through the input's end (the bridge waited): the status says so too
            def idle() -> Any:
                status = http.get(f"http://localhost:{ports['8000']}/status").json()
                return status if status["queue"]["depth"] == status["correlation"]["pending"] == 0 else None

            status = wait_for(idle, timeout=PROCESS_S, interval=0.2)
            pair_sets = http.get(f"http://{url.group(1)}").json()
    pairs = {(ps["radar_a"], ps["radar_b"]): len(ps["pairs"]) for ps in pair_sets}
    assert {("A", "B"), ("A", "C"), ("B", "C"), ("A", "adsb"), ("B", "adsb"), ("C", "adsb")} <= set(pairs)
    assert sum(pairs.values()) >= MIN_PAIRS, pairs
    assert status["rejected"] == {}
    assert_cat062_written(tmp_path / "system-tracks.ast", bridge.stderr)


def assert_cat062_written(path: Path, bridge_stderr: str) -> None:
    """The bridge's ``--out-file``: whole CAT062 data blocks, one after the other, and at least
    :data:`MIN_CAT062_TRACKS` track reports by its own count."""
    cat062 = path.read_bytes()
    blocks = position = 0
    while position < len(cat062):
        assert cat062[position] == 62
        position += int.from_bytes(cat062[position + 1 : position + 3], "big")
        blocks += 1
    assert position == len(cat062) and blocks > 0
    written = re.search(r"CAT062 out: (\d+) tracks", bridge_stderr)
    assert written is not None and int(written.group(1)) >= MIN_CAT062_TRACKS


def test_simulate_sends_a_scenario_as_asterix_datagrams(tmp_path: Path) -> None:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as rx:
        rx.bind(("127.0.0.1", 0))
        rx.settimeout(0.2)
        port = rx.getsockname()[1]
        argv = [TOPOFUSION, "simulate", "--scenario", "two-radar", "--duration", "8", "--speed", "0"]
        argv += ["--asterix-udp", f"127.0.0.1:{port}", "--write-sites", str(tmp_path / "sites.json")]
        with started(argv, tmp_path) as sim:
            got: list[bytes] = []

            def drain() -> bool:
                try:
                    while True:
                        got.append(rx.recv(65536))
                except TimeoutError:
                    pass
                return sim.popen.poll() is not None

            wait_for(drain, timeout=PROCESS_S, interval=0.0)
            drain()
            assert sim.popen.returncode == 0, sim.output()
    out = Decoded()
    for d in got:
        decode_datagram(d, out)
    assert not out.errors
    sites = json.loads((tmp_path / "sites.json").read_text())
    assert {(s["sac"], s["sic"]) for s in sites} == {(r.sac, r.sic) for r in out.cat048} == {(0, 10), (0, 11)}
    assert len(out.cat034) == 2 * 16  # 8 s of 8 sectors per 4 s scan, each radar
    assert "--date" in sim.output()  # at --speed 0 the bridge must judge it by the data's own clock
