"""Partitioned workers as an operator runs them (``topofusion run --partition K/2``), and faults.

Worker 2 is killed (SIGKILL) half-way: worker 1 goes on with what it owns, and ``/status``
says partition 2 is missing.  Worker 2 is started again: it rebuilds what it owns from the
input that follows, and the network is whole again.
"""

from __future__ import annotations

import itertools
import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import httpx
import pytest
import zenoh

from service.pipeline.partition import Partition
from tests.scenario_helpers import scenario_messages
from tests.support import free_port, put_json, wait_for, wait_subscribed

TOPOFUSION = str(Path(sys.executable).parent / "topofusion")


@contextmanager
def worker(
    k: int, router: str, port: int, ready: str = "/readyz", log: Path | None = None, **settings: str
) -> Iterator[subprocess.Popen[bytes]]:
    """Worker ``k`` of 2, given once ``ready`` (a route) answers 200 (``log``: its output there)."""
    env = {key: v for key, v in os.environ.items() if not key.startswith("TOPOFUSION_")}
    env.update(settings)
    env.update(
        TOPOFUSION_PARTITION=f"{k}/2",
        TOPOFUSION_ZENOH_MODE="client",
        TOPOFUSION_ZENOH_CONNECT=router,
        TOPOFUSION_HTTP_PORT=str(port),
        TOPOFUSION_CORRELATION_PROCESS="false",
        TOPOFUSION_PEER_GRACE_S="2",
        TOPOFUSION_LOG_LEVEL="WARNING",
    )
    out = log.open("ab") if log is not None else subprocess.DEVNULL
    proc = subprocess.Popen([TOPOFUSION, "run"], env=env, stdout=out, stderr=subprocess.STDOUT)
    if log is not None:
        out.close()  # type: ignore[union-attr]  # (the worker holds its own copy)
    try:
        wait_for(lambda: _get(port, ready) is not None or proc.poll() is not None, timeout=60)
        assert proc.poll() is None, f"worker {k} exited with {proc.returncode}"
        yield proc
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
            try:
                proc.wait(timeout=20)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(timeout=10)


def _get(port: int, path: str, **params: Any) -> Any:
    try:
        r = httpx.get(f"http://127.0.0.1:{port}{path}", params=params, timeout=5)
    except httpx.HTTPError:
        return None
    return r.json() if r.status_code == 200 else None


def _whole(port: int) -> bool:
    """The worker on ``port`` misses no partition."""
    return bool((_get(port, "/status") or {}).get("partition", {}).get("missing") == [])


def _batches(port: int, radars: list[str]) -> int:
    st = _get(port, "/status")
    return sum(r["batches"] for r in st["radars"] if r["radar_id"] in radars) if st else -1


def _latest_pair_time(port: int, a: str, b: str) -> float:
    sets = _get(port, "/pairs", radar_a=a, radar_b=b, status="all") or []
    return max((s["time_s"] for s in sets), default=0.0)


Messages = list[tuple[str, bytes]]


def _settled(p1: int, p2: int, pair: tuple[str, str]) -> bool:
    """Both workers' queues empty and ``pair``'s pairs at worker 1 unchanged over a second."""
    before = _get(p1, "/pairs", radar_a=pair[0], radar_b=pair[1], status="all")
    time.sleep(1.0)
    queues = [(_get(p, "/status") or {}).get("queue", {}).get("depth") for p in (p1, p2)]
    after = _get(p1, "/pairs", radar_a=pair[0], radar_b=pair[1], status="all")
    return queues == [0, 0] and before is not None and before == after


def _stream_in_thirds() -> tuple[Messages, list[str], list[str], list[str], tuple[str, str], list[Messages]]:
    """A 12-radar stream: its site messages, the radars, those worker 1 of 2 owns and the
    others, a radar pair worker 1 owns across the two partitions, and the plot batches in
    thirds."""
    stream = scenario_messages("national", duration_s=150.0, seed=3, targets=150)
    sites = [(k, p) for k, p in stream if k.endswith("/site")]
    batches = [(k, p) for k, p in stream if k.endswith("/plots")]
    radars = sorted(json.loads(p)["radar_id"] for _, p in sites)
    one, two = Partition(1, 2), Partition(2, 2)
    mine = [r for r in radars if one.owns(r)]
    theirs = [r for r in radars if two.owns(r)]
    across = next((a, b) for a, b in itertools.product(mine, theirs) if one.owns_pair(a, b))
    n = len(batches)
    thirds = [batches[: n // 3], batches[n // 3 : 2 * n // 3], batches[2 * n // 3 :]]
    return sites, radars, mine, theirs, across, thirds


@pytest.mark.slow
def test_a_killed_worker_leaves_the_rest_going_and_a_restarted_one_rebuilds(
    router: str, client: zenoh.Session
) -> None:
    sites, radars, mine, theirs, across, thirds = _stream_in_thirds()
    one = Partition(1, 2)
    # a pair worker 1 owns whose radars it tracks itself (``across``: one across partitions)
    inside = next((a, b) for a, b in itertools.combinations(mine, 2) if one.owns_pair(a, b))
    p1, p2 = free_port(), free_port()
    # a radar silent this long in data time expires (the stream's thirds are 50 s long)
    expiry = {"TOPOFUSION_ENGINE__SEQUENCER__SOURCE_EXPIRY_S": "20"}

    def put_all(messages: list[tuple[str, bytes]]) -> None:
        for key, payload in messages:
            put_json(client, key, payload)

    def end_time(messages: list[tuple[str, bytes]]) -> float:
        return float(json.loads(messages[-1][1])["time_s"])

    with worker(1, router, p1, **expiry):
        with worker(2, router, p2, **expiry) as w2:
            wait_subscribed(client, "fusion/radar/N01/site")
            wait_for(lambda: _whole(p1), timeout=30)
            put_all(sites)
            wait_for(lambda: len(_get(p1, "/radars") or []) == len(radars) == len(_get(p2, "/radars") or []))
            put_all(thirds[0])
            n_first = sum(json.loads(p)["radar_id"] in mine for _, p in thirds[0])
            wait_for(lambda: _batches(p1, mine) == n_first, timeout=60)
            wait_for(lambda: _latest_pair_time(p1, *across) > 0, timeout=60)
            w2.kill()  # SIGKILL: no goodbye
            w2.wait(timeout=10)

        # Worker 1 says which partition is missing, and goes on with what it owns.
        wait_for(lambda: _get(p1, "/status")["partition"]["missing"] == [2], timeout=30)
        status = _get(p1, "/status")
        assert [w["alive"] for w in status["partition"]["workers"]] == [True, False]
        before = _latest_pair_time(p1, *inside)
        put_all(thirds[1])
        n_two = n_first + sum(json.loads(p)["radar_id"] in mine for _, p in thirds[1])
        wait_for(lambda: _batches(p1, mine) == n_two, timeout=60)
        # its own pairs go on to the end of what came (within the merge's lag bound)
        wait_for(
            lambda: _latest_pair_time(p1, *inside) >= max(before + 1, end_time(thirds[1]) - 30), timeout=60
        )
        # The dead worker's radars are missing from the network's status, and their last
        # tracks coast out as a silent radar's do, in data time: no output of worker 1 names
        # them any more (it served them, confirmed, for as long as worker 2 stayed away).
        assert sorted(r["radar_id"] for r in _get(p1, "/status")["radars"]) == mine
        wait_for(lambda: all(not _get(p1, f"/radars/{rid}/tracks", status="all")["tracks"] for rid in theirs))
        system = _get(p1, "/system-tracks", status="all")["system_tracks"]
        assert system and not {m["radar_id"] for s in system for m in s["members"]} & set(theirs)
        sets = _get(p1, "/pairs", radar_a=across[0], radar_b=across[1], status="all")
        assert sets is not None and not any(s["pairs"] for s in sets)
        stalled = _latest_pair_time(p1, *across)

        # Worker 2 comes back: it rebuilds what it owns from the input that follows.
        with worker(2, router, p2, **expiry):
            wait_for(lambda: _get(p1, "/status")["partition"]["missing"] == [], timeout=30)
            put_all(sites)  # (a restarted worker learns sites again; see docs/scale-out.md)
            wait_for(lambda: len(_get(p2, "/radars") or []) == len(radars))
            put_all(thirds[2])
            n_theirs = sum(json.loads(p)["radar_id"] in theirs for _, p in thirds[2])
            wait_for(lambda: _batches(p2, theirs) == n_theirs, timeout=60)
            wait_for(lambda: _latest_pair_time(p1, *across) > stalled, timeout=60)
            wait_for(lambda: sorted(r["radar_id"] for r in _get(p1, "/status")["radars"]) == radars)
            # (it tracks what came, with the aid of association a lag behind worker 1 at most:
            # at a replay's full speed both catch up over some seconds, not at once)
            wait_for(lambda: _get(p2, f"/radars/{theirs[0]}/tracks")["tracks"], timeout=30)
            # and worker 1 holds them too, once their track states have reached it
            wait_for(lambda: _get(p1, f"/radars/{theirs[0]}/tracks")["tracks"], timeout=30)


@pytest.mark.slow
def test_a_worker_stopped_for_30_s_comes_back_without_disordering_the_picture(
    router: str, client: zenoh.Session
) -> None:
    """Worker 2 is frozen (SIGSTOP) for 30 s, longer than its Zenoh lease and the peer grace,
    while the stream goes on, then resumed (SIGCONT).  Worker 1 goes on alone meanwhile, and
    takes worker 2 back when it answers again.  The order: every radar pair's PairSets reach a
    subscriber in data-time order, before, during and after, and ``/status`` counts every table
    released out of order (documented: only lateness may grow).  The picture: worker 1's pairs
    across the two partitions move on again after the resume, and no pair names a track its
    radar's table does not hold."""
    sites, radars, mine, _, across, thirds = _stream_in_thirds()
    p1, p2 = free_port(), free_port()
    received: dict[str, list[float]] = {}

    def on_pairs(sample: zenoh.Sample) -> None:
        received.setdefault(str(sample.key_expr), []).append(json.loads(sample.payload.to_bytes())["time_s"])

    def put_all(messages: list[tuple[str, bytes]]) -> None:
        for key, payload in messages:
            put_json(client, key, payload)

    sub = client.declare_subscriber("fusion/pairs/**", on_pairs)
    try:
        with worker(1, router, p1), worker(2, router, p2) as w2:
            wait_for(lambda: _whole(p1), timeout=30)
            put_all(sites)
            wait_for(lambda: len(_get(p1, "/radars") or []) == len(radars) == len(_get(p2, "/radars") or []))
            put_all(thirds[0])
            wait_for(lambda: _latest_pair_time(p1, *across) > 0, timeout=60)
            stopped = time.monotonic()
            w2.send_signal(signal.SIGSTOP)
            try:
                put_all(thirds[1])
                n_two = sum(json.loads(p)["radar_id"] in mine for part in thirds[:2] for _, p in part)
                wait_for(lambda: _batches(p1, mine) >= n_two, timeout=60)
                wait_for(lambda: _get(p1, "/status")["partition"]["missing"] == [2], timeout=40)
                time.sleep(max(0.0, 30.0 - (time.monotonic() - stopped)))
            finally:
                w2.send_signal(signal.SIGCONT)
            wait_for(lambda: _get(p1, "/status")["partition"]["missing"] == [], timeout=60)
            put_all(sites)  # as after any restart of a worker (docs/scale-out.md)
            stalled = _latest_pair_time(p1, *across)
            put_all(thirds[2])
            wait_for(lambda: _latest_pair_time(p1, *across) > stalled, timeout=90)
            status = _get(p1, "/status")
            assert isinstance(status["partition"]["progress"]["reordered"], int)
            # The picture is whole: every confirmed pair names tracks its radars' tables hold.
            # Three HTTP reads are three snapshots while input still flows (a track confirmed
            # and paired between the first and the last is no fault), so they are read once
            # every worker's input is done and the pairs have stopped changing.
            wait_for(lambda: _settled(p1, p2, across), timeout=60, interval=0.5)
            for a, b in (across,):
                held_a = {t["track_id"] for t in _get(p1, f"/radars/{a}/tracks")["tracks"]}
                held_b = {t["track_id"] for t in _get(p1, f"/radars/{b}/tracks")["tracks"]}
                for pair_set in _get(p1, "/pairs", radar_a=a, radar_b=b) or []:
                    for pair in pair_set["pairs"]:
                        assert pair["track_a"] in held_a and pair["track_b"] in held_b
    finally:
        sub.undeclare()
    # every radar pair's updates arrived in data-time order
    assert received
    for key, times in received.items():
        assert times == sorted(times), key


def test_a_worker_of_another_salt_makes_readyz_say_why_the_merge_stalls(router: str) -> None:
    """Worker 2 started with another salt hashes the names differently: worker 1 refuses its
    messages (they would split the radars another way), so its merge cannot go on while worker
    2 holds K = 2; ``/readyz`` says so and why, instead of ready."""
    p1, p2 = free_port(), free_port()
    with worker(1, router, p1):
        assert _get(p1, "/readyz") == {"status": "ready"}
        with worker(2, router, p2, ready="/healthz", TOPOFUSION_PARTITION_SALT="5"):
            wait_for(lambda: _get(p1, "/readyz") is None, timeout=30)
            r = httpx.get(f"http://127.0.0.1:{p1}/readyz", timeout=5)
            assert r.status_code == 503
            reason = r.json()["reason"]
            assert reason.startswith("partition mismatch: ") and "TOPOFUSION_PARTITION_SALT" in reason


def test_without_worker_1_another_worker_says_the_picture_is_unavailable(router: str) -> None:
    """Worker 1 draws the picture; while it does not answer, worker 2's ``/system-tracks`` is
    503 saying why, not an empty sky served as if it were the picture (it was 200 with no
    system tracks)."""
    p1, p2 = free_port(), free_port()
    with worker(2, router, p2):
        with worker(1, router, p1) as w1:
            wait_for(lambda: _whole(p2), timeout=30)
            assert httpx.get(f"http://127.0.0.1:{p2}/system-tracks", timeout=10).status_code == 200
            w1.kill()  # SIGKILL: no goodbye
            w1.wait(timeout=10)
        r = httpx.get(f"http://127.0.0.1:{p2}/system-tracks", timeout=10)
        assert r.status_code == 503, r.text
        assert r.json() == {"detail": "the picture is drawn by worker 1, which does not answer"}
        assert r.headers["retry-after"] == "2"


def test_a_worker_that_leaves_and_comes_back_is_said_both_ways(router: str, tmp_path: Path) -> None:
    """The log says "worker 2/2 left" and then "worker 2/2 is back" (it said only the first,
    and an operator could not tell from it that the network was whole again)."""
    p1, p2 = free_port(), free_port()
    log = tmp_path / "worker-1.log"
    with worker(1, router, p1, log=log, TOPOFUSION_LOG_LEVEL="WARNING"):
        with worker(2, router, p2):
            wait_for(lambda: _whole(p1), timeout=30)
        wait_for(lambda: "worker 2/2 left" in log.read_text(), timeout=30)
        with worker(2, router, p2):
            wait_for(lambda: "worker 2/2 is back" in log.read_text(), timeout=30)
    text = log.read_text()
    assert text.index("worker 2/2 left") < text.index("worker 2/2 is back"), text
