"""Simulated input streams for tests (the real simulator, short scenarios)."""

from __future__ import annotations

import random
from dataclasses import replace
from typing import Any

from service.engine import Engine, EngineConfig
from service.wire.outgoing import Outgoing
from topofusion_lab.scenarios.catalog import get_scenario
from topofusion_lab.scenarios.simulator import wire_messages


def scenario_messages(
    name: str = "two-radar",
    duration_s: float = 60.0,
    seed: int = 1,
    prefix: str = "fusion",
    **changes: object,
) -> list[tuple[str, bytes]]:
    """``(key, payload)`` of a scenario's sites and batches, in data-time order."""
    sc = replace(get_scenario(name), duration_s=duration_s, **changes)  # type: ignore[arg-type]
    return list(wire_messages(sc, seed, prefix))


def interleaved(stream: list[tuple[str, bytes]], seed: int) -> list[tuple[str, bytes]]:
    """Another arrival order: sites first, each radar's batches in order, radars interleaved at random."""
    rng = random.Random(seed)
    queues: dict[str, list[tuple[str, bytes]]] = {}
    out = [m for m in stream if m[0].endswith("/site")]
    for key, payload in stream:
        if key.endswith("/plots"):
            queues.setdefault(key.split("/")[2], []).append((key, payload))
    while queues:
        rid = rng.choice(sorted(queues))
        out.append(queues[rid].pop(0))
        if not queues[rid]:
            del queues[rid]
    return out


def run_engine(
    messages: list[tuple[str, bytes]], process: bool = False, config: EngineConfig | None = None
) -> tuple[dict[str, Any], list[Outgoing]]:
    """Every message through an :class:`Engine` (``process``: its correlation in a child
    process), then its flush: the final snapshot's tracks, pairs, biases, system tracks,
    correlation updates and radars' status, and every output in order."""
    engine = Engine(config or EngineConfig(), correlation_process=process)
    try:
        out = []
        for key, payload in messages:
            out.extend(engine.ingest(key, payload, receive_time_s=0.0))
        out.extend(engine.flush())
        snap = engine.snapshot()
        return {
            "tracks": snap.track_batches("all"),
            "pairs": snap.pair_sets(status="all"),
            "biases": snap.biases(),
            "system": snap.system_tracks("all"),
            "updates": snap.correlation["updates"],
            "radars": snap.status()["radars"],
        }, out
    finally:
        engine.close()
