"""Simulated input streams for tests (the real simulator, short scenarios)."""

from __future__ import annotations

import random
from collections import defaultdict
from collections.abc import Callable
from dataclasses import replace
from typing import Any

from service.engine import Engine, EngineConfig
from service.pipeline.partition import Partition
from service.wire.keys import Keys
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


# -- N engines as partitioned workers, in one process --------------------------------------
def is_peer(key: str) -> bool:
    return Keys("fusion").classify_peer(key) is not None


def run_one(
    msgs: list[tuple[str, bytes]],
    watch: Callable[[Engine], object] = lambda e: None,
    config: EngineConfig | None = None,
) -> tuple[dict[str, list[bytes]], Engine]:
    """One engine (``config``, default the defaults): its pair updates by key, in order."""
    engine = Engine(config or EngineConfig())
    watch(engine)
    pairs: dict[str, list[bytes]] = defaultdict(list)
    for key, payload in msgs:
        for o in engine.ingest(key, payload):
            if "/pairs/" in o.key:
                pairs[o.key].append(o.payload)
    return pairs, engine


def run_partitioned(
    msgs: list[tuple[str, bytes]],
    n: int,
    seed: int,
    watch: Callable[[Engine], object] = lambda e: None,
    salt: int = 0,
    lagging: int | None = None,
    heard: Callable[[int, Outgoing], object] = lambda k, o: None,
    config: EngineConfig | None = None,
) -> tuple[dict[str, list[bytes]], dict[str, set[int]], list[Engine]]:
    """N engines, each message delivered to each in its own random batches, the peers'
    messages to the others in the order they were produced, at random later moments;
    ``lagging``: that worker (1..N) takes its messages seldom, so it falls far behind;
    ``heard``: every output of worker K (1..N), in the order it puts them; ``config``: the
    engines' (default the defaults), each with its partition."""
    rng = random.Random(seed)
    base = config or EngineConfig()
    engines = [Engine(replace(base, partition=Partition(k, n, salt))) for k in range(1, n + 1)]
    for engine in engines:
        watch(engine)
    queues: list[list[tuple[str, bytes]]] = [[] for _ in engines]
    pairs: dict[str, list[bytes]] = defaultdict(list)
    publishers: dict[str, set[int]] = defaultdict(set)

    def run(j: int, upto: int) -> None:
        batch, queues[j] = queues[j][:upto], queues[j][upto:]
        for key, payload in batch:
            out: list[Outgoing] = engines[j].ingest(key, payload)
            for o in out:
                heard(j + 1, o)
                if "/pairs/" in o.key:
                    pairs[o.key].append(o.payload)
                    publishers[o.key].add(j + 1)
                elif is_peer(o.key):
                    for other in range(n):
                        if other != j:
                            queues[other].append((o.key, o.payload))

    for key, payload in msgs:
        for j in range(n):
            queues[j].append((key, payload))
        for j in rng.sample(range(n), n):
            if j + 1 != lagging or rng.random() < 0.02:
                run(j, rng.randint(0, len(queues[j])))
    while any(queues):
        for j in range(n):
            run(j, len(queues[j]))
    return pairs, publishers, engines
