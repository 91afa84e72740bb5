"""Publishing a simulated scenario over Zenoh, paced by data time."""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Callable

import zenoh

from service.wire.keys import Keys
from topofusion_lab.scenarios.simulator import Scenario, generate

#: Sites are published again every this many plot batches, so that a service started after
#: the simulator still learns them.
SITE_REPEAT_BATCHES = 200


def publish_scenario(
    session: zenoh.Session,
    scenario: Scenario,
    prefix: str = "fusion",
    speed: float = 1.0,
    seed: int = 0,
    stop: threading.Event | None = None,
    on_batch: Callable[[int, int], None] | None = None,
) -> tuple[int, int]:
    """Publish sites and plot batches; ``speed`` scales data time to wall time (0: no pacing).

    Returns ``(batches, plots)`` published.  Publishers block under congestion rather than
    drop, so a slow service slows the simulator instead of losing data.
    """
    if speed < 0:
        raise ValueError("speed must be >= 0")
    keys = Keys(prefix)
    stop = stop or threading.Event()
    enc = zenoh.Encoding.APPLICATION_JSON
    block = zenoh.CongestionControl.BLOCK
    wall0: float | None = None
    data0: float | None = None
    batches = plots = 0
    sites: dict[str, bytes] = {}
    for msg in generate(scenario, seed):
        if stop.is_set():
            break
        payload = json.dumps(msg.body).encode()
        if msg.kind == "site":
            sites[msg.radar_id] = payload
            session.put(keys.site(msg.radar_id), payload, encoding=enc, congestion_control=block)
            continue
        if wall0 is None or data0 is None:
            wall0, data0 = time.monotonic(), msg.time_s
        if speed > 0:
            delay = wall0 + (msg.time_s - data0) / speed - time.monotonic()
            if delay > 0 and stop.wait(delay):
                break
        session.put(keys.input(msg.kind, msg.radar_id), payload, encoding=enc, congestion_control=block)
        if msg.kind != "plots":
            continue
        batches += 1
        plots += len(msg.body["plots"]["time_s"])
        if batches % SITE_REPEAT_BATCHES == 0:
            for rid, site_payload in sites.items():
                session.put(keys.site(rid), site_payload, encoding=enc, congestion_control=block)
        if on_batch is not None:
            on_batch(batches, plots)
    return batches, plots
