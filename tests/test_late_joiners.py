"""Late joiners learn the sites (docs/contract.md, RadarSite): a service, a worker or a recorder
that starts after the source learns every site within one re-put interval, from the simulator
and from the ASTERIX bridge; a site put again, equal to the one held, changes nothing.

The sources run as the README starts them (``topofusion simulate``, ``topofusion asterix``),
against a router on a free loopback port; the late service is the real one in-process, the
late recorder the real ``topofusion record``.
"""

from __future__ import annotations

import json
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import pytest

from service.engine import EngineConfig
from service.pipeline.sequencer import SequencerParams
from service.wire.keys import Keys
from tests.doc_commands import PROCESS_S, TOPOFUSION, Proc, started
from tests.scenario_helpers import scenario_messages
from tests.support import RunningService, run_engine, running_service, wait_for

#: The sources' re-put interval in these tests (``--site-every``, s): short, to keep them fast.
SITE_EVERY_S = 1.0
#: A put reaches a subscriber and the service's worker within this long (s) on a loaded
#: 2-core machine.
DELIVERY_S = 2.0


def radars_known(svc: RunningService) -> set[str]:
    return {r["radar_id"] for r in svc.http.get("/status").json()["radars"]}


@contextmanager
def simulator(router: str, cwd: Path) -> Iterator[Proc]:
    argv = [TOPOFUSION, "simulate", "--scenario", "two-radar", "--speed", "1", "--wait", "0"]
    argv += ["--site-every", str(SITE_EVERY_S), "--connect", router]
    with started(argv, cwd) as sim:
        wait_for(lambda: "publishing 'two-radar'" in sim.output(), timeout=PROCESS_S)
        time.sleep(SITE_EVERY_S)  # the first puts are gone: nobody subscribed to them
        yield sim
        assert sim.popen.poll() is None, sim.output()  # still running: the test stops it


@contextmanager
def bridge(router: str, cwd: Path) -> Iterator[Proc]:
    sites = cwd / "sites.json"
    sites.write_text(
        json.dumps(
            [
                {"radar_id": "P", "latitude_deg": 49.0, "longitude_deg": 2.5, "sac": 25, "sic": 1},
                {"radar_id": "Q", "latitude_deg": 50.0, "longitude_deg": 3.5, "sac": 25, "sic": 2},
            ]
        )
    )
    argv = [TOPOFUSION, "asterix", "--udp", "127.0.0.1:0", "--sites", str(sites), "--connect", router]
    with started([*argv, "--site-every", str(SITE_EVERY_S)], cwd) as proc:
        wait_for(lambda: "asterix: listening on" in proc.output(), timeout=PROCESS_S)
        time.sleep(SITE_EVERY_S)
        yield proc
        assert proc.popen.poll() is None, proc.output()


@pytest.mark.parametrize("worker", [False, True], ids=["service", "worker owning A"])
def test_a_service_started_after_the_simulator_learns_every_site(
    router: str, tmp_path: Path, worker: bool
) -> None:
    with (
        simulator(router, tmp_path),
        running_service(router, radars=("A",) if worker else (), correlation_process=False) as svc,
    ):
        t0 = time.monotonic()
        wait_for(
            lambda: radars_known(svc) >= ({"A"} if worker else {"A", "B"}), timeout=SITE_EVERY_S + DELIVERY_S
        )
        took = time.monotonic() - t0
        # and it tracks the radar from then on: its plots are taken
        wait_for(lambda: svc.http.get("/status").json()["radars"][0]["batches"] > 0, timeout=PROCESS_S)
    assert took <= SITE_EVERY_S + DELIVERY_S


@pytest.mark.slow
def test_a_recorder_started_after_the_simulator_records_every_site(router: str, tmp_path: Path) -> None:
    out = tmp_path / "late.mcap"
    with simulator(router, tmp_path):
        argv = [TOPOFUSION, "record", "--out", str(out), "--connect", router]
        with started([*argv, "--duration", str(SITE_EVERY_S + DELIVERY_S)], tmp_path) as rec:
            assert rec.popen.wait(timeout=PROCESS_S) == 0, rec.output()
    report = rec.output()
    for radar in ("A", "B"):
        assert f"fusion/radar/{radar}/site " in report, report


def test_a_service_started_after_the_bridge_learns_its_sites(router: str, tmp_path: Path) -> None:
    with bridge(router, tmp_path), running_service(router, correlation_process=False) as svc:
        wait_for(lambda: radars_known(svc) == {"P", "Q"}, timeout=SITE_EVERY_S + DELIVERY_S)
        sites = {r["radar_id"]: r for r in svc.http.get("/radars").json()}
    assert (sites["P"]["sac"], sites["P"]["sic"], sites["Q"]["sic"]) == (25, 1, 2)


# -- a repeated site changes nothing -------------------------------------------------------------


def _with_repeated_sites(stream: list[tuple[str, bytes]], every: int) -> list[tuple[str, bytes]]:
    """``stream`` with every site put again after every ``every``-th message."""
    sites = [(k, p) for k, p in stream if k.endswith("/site")]
    out: list[tuple[str, bytes]] = []
    for i, message in enumerate(stream):
        out.append(message)
        if i % every == every - 1:
            out += sites
    return out


def _outputs(stream: list[tuple[str, bytes]], config: EngineConfig) -> tuple[list[Any], dict[str, Any]]:
    engine, out = run_engine(stream, config)
    status = engine.snapshot().status()
    # the correlation's wall-clock timings differ from run to run; what it did does not
    status["correlation"] = {k: status["correlation"][k] for k in ("updates", "pending")}
    return [(o.key, o.payload) for o in out], status


def test_an_identical_site_put_again_changes_nothing() -> None:
    """The same stream with and without the sites put again (every few messages, also while a
    radar is silent, expires and is forgotten, and after it comes back): the same outputs,
    message for message, and the same status."""
    params = SequencerParams(source_expiry_s=20.0, forget_after_s=30.0, max_lag_s=10.0)
    config = EngineConfig(sequencer=params)
    stream = scenario_messages("two-radar", duration_s=150.0)
    t0 = min(json.loads(p)["time_s"] for k, p in stream if k.endswith("/plots"))
    silent = Keys("fusion").plots("B")
    stream = [
        (k, p) for k, p in stream if not (k == silent and t0 + 40 < json.loads(p)["time_s"] < t0 + 110)
    ]  # B silent for 70 s: expired after 20, forgotten 30 later, then back
    plain, plain_status = _outputs(stream, config)
    repeated, repeated_status = _outputs(_with_repeated_sites(stream, every=7), config)
    assert plain == repeated
    assert plain_status == repeated_status
    assert plain_status["rejected"] == {} and plain_status["pairs_confirmed"] > 0
