"""Publishing a simulated scenario over Zenoh, paced by data time."""

from __future__ import annotations

import json
import threading
from collections.abc import Callable

import zenoh

from service.wire.keys import Keys
from topofusion_lab.pacing import Pacer
from topofusion_lab.scenarios.simulator import Scenario, generate, generate_looped

#: Without ``site_every_s``, sites are published again every this many plot batches, so that a
#: service started after the simulator still learns them.  A count, not a time: the number of
#: messages then follows from the scenario alone, which in-process runs and tests count on.
SITE_REPEAT_BATCHES = 200
#: ``topofusion simulate`` puts the sites again every this many wall seconds (``--site-every``):
#: a service, worker or recorder that starts later learns every site within this long, and
#: rejects that radar's plots (``unknown_radar``) only until then.  A site is a few hundred
#: bytes, so even a national network's twelve cost under 1 kB/s at this period.
SITE_EVERY_S = 5.0


def publish_scenario(
    session: zenoh.Session,
    scenario: Scenario,
    prefix: str = "fusion",
    speed: float = 1.0,
    seed: int = 0,
    stop: threading.Event | None = None,
    on_batch: Callable[[int, int], None] | None = None,
    *,
    site_every_s: float | None = None,
    loop: bool = False,
    last_times: dict[str, float] | None = None,
) -> tuple[int, int]:
    """Publish sites and plot batches; ``speed`` scales data time to wall time (0: no pacing).

    Sites go first, then again every ``site_every_s`` wall seconds (0: never again; None:
    every :data:`SITE_REPEAT_BATCHES` plot batches).  A repeated site equals the one the
    service holds, which changes nothing there (docs/contract.md, RadarSite).  ``loop``:
    the scenario over and over without end (:func:`generate_looped`).  ``last_times``, when
    given, gets each input key's last data time as its batch says it (what a service can be
    complete through).

    Returns ``(batches, plots)`` published.  Publishers block under congestion rather than
    drop, so a slow service slows the simulator instead of losing data.
    """
    if speed < 0:
        raise ValueError("speed must be >= 0")
    keys = Keys(prefix)
    stop = stop or threading.Event()
    enc = zenoh.Encoding.APPLICATION_JSON
    block = zenoh.CongestionControl.BLOCK
    batches = plots = 0
    sites: dict[str, bytes] = {}

    def put_sites() -> None:
        for rid, site_payload in sites.items():
            session.put(keys.site(rid), site_payload, encoding=enc, congestion_control=block)

    pacer = Pacer(speed, stop, site_every_s, put_sites)
    messages = generate_looped(scenario, seed) if loop else generate(scenario, seed)
    for msg in messages:
        if stop.is_set():
            break
        payload = json.dumps(msg.body).encode()
        if msg.kind == "site":
            sites[msg.radar_id] = payload
            session.put(keys.site(msg.radar_id), payload, encoding=enc, congestion_control=block)
            continue
        if not pacer.due(msg.time_s):
            break
        key = keys.input(msg.kind, msg.radar_id)
        session.put(key, payload, encoding=enc, congestion_control=block)
        if last_times is not None:
            # the batch's own time_s (what the service reads; a radar's time-stamp bias moves it
            # off the true time the message is paced by)
            stamped = msg.body.get("time_s")
            last_times[key] = float(stamped) if isinstance(stamped, (int, float)) else msg.time_s
        if msg.kind != "plots":
            continue
        batches += 1
        plots += len(msg.body["plots"]["time_s"])
        if site_every_s is None and batches % SITE_REPEAT_BATCHES == 0:
            put_sites()
        if on_batch is not None:
            on_batch(batches, plots)
    return batches, plots
