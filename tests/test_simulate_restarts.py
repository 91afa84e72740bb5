"""Restarts that explain themselves: ``simulate --loop`` runs on without end, data time and
``seq`` going on; ``simulate --start-time resume`` starts after the data clock the service
reports, where a plain restart would be rejected as duplicates; each says what it does."""

from __future__ import annotations

import itertools
import json
import signal
from pathlib import Path
from typing import Any

import pytest

from service.engine import EngineConfig
from tests.doc_commands import PROCESS_S, TOPOFUSION, started
from tests.support import RunningService, running_service, wait_for
from topofusion_lab.scenarios.catalog import get_scenario
from topofusion_lab.scenarios.simulator import generate, generate_looped

#: A fixed first data time (2025-11-22T00:00:00Z), so that runs are comparable.
T0 = 1_763_769_600.0
#: Each pass of the looped scenario (data s): two 4 s scans of each radar, 8 sectors each.
PASS_S = 8.0
BATCHES_PER_RADAR = 16


def radars(svc: RunningService) -> dict[str, dict[str, Any]]:
    return {r["radar_id"]: r for r in svc.http.get("/status").json()["radars"]}


def test_generate_looped_repeats_the_traffic_with_time_and_seq_running_on() -> None:
    from dataclasses import replace

    sc = replace(get_scenario("two-radar"), duration_s=PASS_S, start_time_s=T0)
    one = [m for m in generate(sc, 3) if m.kind == "plots"]
    looped = list(itertools.islice(generate_looped(sc, 3), 2 + 3 * len(one)))
    assert [m.kind for m in looped[:2]] == ["site", "site"]  # the sites once, at the start
    plots = looped[2:]
    assert all(m.kind == "plots" for m in plots)
    for k in range(3):
        for a, b in zip(one, plots[k * len(one) : (k + 1) * len(one)], strict=True):
            assert b.time_s == a.time_s + k * PASS_S
            assert b.body["seq"] == a.body["seq"] + k * BATCHES_PER_RADAR
            assert b.body["plots"]["range_m"] == a.body["plots"]["range_m"]  # the same traffic
    times = [m.time_s for m in plots]
    assert times == sorted(times)


def test_simulate_loop_runs_on_without_end(router: str, tmp_path: Path) -> None:
    argv = [TOPOFUSION, "simulate", "--scenario", "two-radar", "--duration", str(PASS_S), "--loop"]
    argv += ["--start-time", str(T0), "--speed", "8", "--connect", router, "--wait-service", "30"]
    with running_service(router, EngineConfig(), correlation_process=False) as svc:
        with started(argv, tmp_path) as sim:
            # three passes and more: one pass a second at 8x
            wait_for(
                lambda: min((r["batches"] for r in radars(svc).values()), default=0) > 3 * BATCHES_PER_RADAR,
                timeout=PROCESS_S,
            )
            sim.popen.send_signal(signal.SIGINT)
            assert sim.popen.wait(timeout=PROCESS_S) == 0, sim.output()
        status = svc.http.get("/status").json()
    assert "over and over (--loop)" in sim.output()
    assert status["rejected"] == {}
    for r in status["radars"]:
        assert r["lost_batches"] == 0 and r["restarts"] == 0, r  # seq went on from pass to pass
        assert r["last_time_s"] >= T0 + 3 * PASS_S  # and so did data time


def _simulate(router: str, cwd: Path, start: str, status: int = 0) -> str:
    argv = [TOPOFUSION, "simulate", "--scenario", "two-radar", "--duration", str(PASS_S), "--speed", "0"]
    with started([*argv, "--start-time", start, "--connect", router, "--wait-service", "30"], cwd) as sim:
        assert sim.popen.wait(timeout=PROCESS_S) == status, sim.output()
    return sim.output()


@pytest.mark.slow
def test_simulate_resume_starts_after_the_service_s_data_clock(router: str, tmp_path: Path) -> None:
    with running_service(router, EngineConfig(), correlation_process=False) as svc:
        first = _simulate(router, tmp_path, str(T0))
        assert "the service's outputs are complete through data time" in first  # it waited for them
        clock = max(r["last_time_s"] for r in radars(svc).values())
        assert clock == T0 + PASS_S
        resumed = _simulate(router, tmp_path, "resume")
        assert f"resuming after the service's data clock {clock:.3f} (2025-11-22T00:00:08Z, " in resumed, (
            resumed
        )
        assert f"the first scan starts at {clock + 1:.0f}" in resumed
        wait_for(lambda: all(r["batches"] == 2 * BATCHES_PER_RADAR for r in radars(svc).values()))
        after = svc.http.get("/status").json()
        assert after["rejected"] == {}
        for r in after["radars"]:
            assert r["restarts"] == 1 and r["lost_batches"] == 0, r  # seq back at 1, later: a restart
            assert r["last_time_s"] == clock + 1 + PASS_S
        # the same run restarted without resume: behind the service's clock, every batch is a
        # duplicate, and the service says how to go on
        errors: list[dict[str, Any]] = []
        sub = svc.node.session.declare_subscriber(
            "fusion/errors", lambda s: errors.append(json.loads(s.payload.to_bytes()))
        )
        try:
            again = _simulate(router, tmp_path, str(T0), status=1)
            wait_for(lambda: len(errors) >= 2 * BATCHES_PER_RADAR, timeout=PROCESS_S)
        finally:
            sub.undeclare()
    assert f"the service rejected messages of this run: {2 * BATCHES_PER_RADAR} duplicate_seq" in again
    assert "start after it with --start-time resume" in again
    assert {e["reason"] for e in errors} == {"duplicate_seq"}
    assert any("--start-time resume" in e["detail"] for e in errors)


def test_simulate_resume_without_a_service_says_so(router: str, tmp_path: Path) -> None:
    argv = [TOPOFUSION, "simulate", "--scenario", "two-radar", "--start-time", "resume"]
    with started([*argv, "--wait-service", "1", "--connect", router], tmp_path) as sim:
        assert sim.popen.wait(timeout=PROCESS_S) == 2
    assert "no service answered fusion/status within 1 s: cannot resume" in sim.output()
