"""``topofusion run --state-dir DIR`` killed and started again: what it learnt is back at once.

The service as an operator runs it (a subprocess, a client of a Zenoh router on a free loopback
port, multicast scouting off), fed a two-radar stream whose radars are both biased until
``/biases`` answers, then killed with SIGKILL (no graceful stop: only the periodic writes
count) and started again with the same directory.
"""

from __future__ import annotations

import json
import signal
import subprocess
from pathlib import Path
from typing import Any

import httpx
import pytest
import zenoh

from service.state.fileformat import decode
from tests.scenario_helpers import scenario_messages
from tests.support import free_port, put_json, wait_for, wait_subscribed
from tests.test_cli_process import _http_ready, process


def _ready(proc: subprocess.Popen[str], url: str) -> None:
    wait_for(lambda: _http_ready(url) or proc.poll() is not None, timeout=60)
    assert proc.poll() is None, proc.stdout.read() if proc.stdout else ""


def _batches(url: str) -> int:
    return sum(r["batches"] for r in httpx.get(url + "/status", timeout=5).json()["radars"])


def _biases(url: str) -> dict[str, dict[str, Any]]:
    return {b["radar_id"]: b for b in httpx.get(url + "/biases", timeout=5).json()}


@pytest.mark.slow
def test_a_killed_service_comes_back_with_sites_biases_and_fresh_track_ids(
    router: str, client: zenoh.Session, tmp_path: Path
) -> None:
    stream = scenario_messages("two-radar", duration_s=120.0)
    cut = len(stream) * 3 // 4
    first, rest = stream[:cut], [(k, p) for k, p in stream[cut:] if k.endswith("/plots")]
    assert not any(k.endswith("/site") for k, _ in stream[cut:])  # sites come only before the kill
    ids: dict[str, set[str]] = {"before": set(), "after": set()}
    newest = {"A": 0.0, "B": 0.0}  # data time of the newest TrackBatch heard of each radar
    phase = "before"

    def tracks(sample: zenoh.Sample) -> None:
        body = json.loads(sample.payload.to_bytes())
        ids[phase].update(t["track_id"] for t in body["tracks"])
        newest[body["radar_id"]] = max(newest[body["radar_id"]], body["time_s"])

    sub = client.declare_subscriber("fusion/radar/*/tracks", tracks)
    hport = free_port()
    url = f"http://127.0.0.1:{hport}"
    args = ["run", "--mode", "client", "--connect", router, "--http-port", str(hport)]
    args += ["--prefix", "fusion", "--state-dir", str(tmp_path / "state")]
    # a write every 10 s of data time: the last one comes after the last bias solve of the run
    settings = {"TOPOFUSION_STATE_INTERVAL_S": "10"}
    try:
        with process(args, settings) as proc:
            _ready(proc, url)
            wait_subscribed(client, "fusion/radar/A/plots")
            wait_subscribed(client, "fusion/radar/A/site")
            for key, payload in first:
                put_json(client, key, payload)
            n_first = sum(k.endswith("/plots") for k, _ in first)
            wait_for(lambda: _batches(url) == n_first, timeout=60)
            before = wait_for(lambda: len(_biases(url)) == 2 and _biases(url), timeout=30)
            # every track the killed run published has come (a late one must not count as
            # after): its batches are released up to the radars' common clock
            times = {
                r: [json.loads(p)["time_s"] for k, p in first if k == f"fusion/radar/{r}/plots"]
                for r in newest
            }
            common = min(max(t) for t in times.values())
            want = {r: max(t for t in times[r] if t <= common) for r in newest}
            wait_for(lambda: all(newest[r] >= want[r] for r in newest), timeout=30)
            assert ids["before"]
            proc.kill()  # SIGKILL: no final write
            out, _ = proc.communicate(timeout=10)
            assert proc.returncode == -signal.SIGKILL
            assert "none yet, starting clean; track-id epoch 0" in out, out
        # the file holds the last periodic write, less than one interval before the newest data;
        # the batches the killed run took after it come as a gap after the restart
        state = decode((tmp_path / "state" / "state.bin").read_bytes(), "fusion", "1/1")[1]
        assert max(max(t) for t in times.values()) - state["data_clock_s"] < 10.0
        kept = {s["source_id"]: s["seq"] for s in state["sources"]}
        sent = {
            r: max(json.loads(p)["seq"] for k, p in first if k == f"fusion/radar/{r}/plots") for r in newest
        }

        phase = "after"
        with process(args, settings) as proc:
            _ready(proc, url)
            # at once, before any new data: the biases of before, both radars known
            after = _biases(url)
            assert sorted(after) == ["A", "B"]
            for rid, then in before.items():
                for field in ("range_bias_m", "azimuth_bias_deg", "elevation_bias_deg"):
                    assert abs(after[rid][field] - then[field]) <= 0.1 * abs(then[field]), (rid, field)
            assert [r["radar_id"] for r in httpx.get(url + "/radars", timeout=5).json()] == ["A", "B"]
            # the state's health, for an operator: this start's epoch, the write made at the start
            state = httpx.get(url + "/status", timeout=5).json()["state"]
            assert state["epoch"] == 1 and state["writes"] >= 1 and state["failures"] == 0
            assert state["data_time_s"] is not None and state["bytes"] > 0
            metrics = httpx.get(url + "/metrics", timeout=5).text
            assert f"topofusion_state_writes_total {float(state['writes'])}" in metrics
            assert "topofusion_state_write_failures_total 0.0" in metrics
            # the radars' plots, without their sites sent again, are taken
            wait_subscribed(client, "fusion/radar/A/plots")
            for key, payload in rest:
                put_json(client, key, payload)
            wait_for(lambda: _batches(url) == len(rest), timeout=60)
            status = httpx.get(url + "/status", timeout=5).json()
            assert "unknown_radar" not in status["rejected"], status["rejected"]
            # a batch the killed run took after its last write comes as a gap after the restart
            assert {r["radar_id"]: (r["rejected"], r["lost_batches"]) for r in status["radars"]} == {
                rid: (0, sent[rid] - kept[rid]) for rid in newest
            }
            # the new tracks' ids are of the next epoch: none of the killed run's comes again
            wait_for(lambda: ids["after"], timeout=30)
            assert not ids["after"] & ids["before"]
            assert all(int(t.rsplit("-", 1)[1]) > 10**9 for t in ids["after"])
            proc.send_signal(signal.SIGTERM)
            out, _ = proc.communicate(timeout=30)
            assert proc.returncode == 0, out
            assert "restored 2 radar sites" in out and "track-id epoch 1" in out, out
    finally:
        sub.undeclare()
