"""``simulate`` waits for the service's outputs through its last batches' own times: a radar
with a time-stamp bias stamps its batches off the true time the simulator paces them by, and
the service can only be complete through the times the batches carry."""

from __future__ import annotations

from pathlib import Path

from service.engine import EngineConfig
from tests.doc_commands import PROCESS_S, TOPOFUSION, started
from tests.support import running_service
from topofusion_lab.scenarios.catalog import get_scenario

T0 = 1_763_769_600.0


def test_simulate_of_time_biased_radars_completes(router: str, tmp_path: Path) -> None:
    biases = [r.time_bias_s for r in get_scenario("assessment").radars]
    assert min(biases) < 0 < max(biases)  # (what the test is about: stamps before and after)
    argv = [TOPOFUSION, "simulate", "--scenario", "assessment", "--duration", "12", "--speed", "0"]
    argv += ["--start-time", str(T0), "--connect", router, "--wait-service", "30", "--wait", "20"]
    with running_service(router, EngineConfig(), correlation_process=False), started(argv, tmp_path) as sim:
        assert sim.popen.wait(timeout=PROCESS_S) == 0, sim.output()
    assert "the service's outputs are complete through data time" in sim.output()
