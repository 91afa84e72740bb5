"""Simulated input streams for tests (the real simulator, short scenarios)."""

from __future__ import annotations

import json
from dataclasses import replace

from service.keys import Keys
from service.scenarios.catalog import get_scenario
from service.scenarios.simulator import generate


def scenario_messages(
    name: str = "two-radar",
    duration_s: float = 60.0,
    seed: int = 1,
    prefix: str = "fusion",
    **changes: object,
) -> list[tuple[str, bytes]]:
    """``(key, payload)`` of a scenario's sites and batches, in data-time order."""
    sc = replace(get_scenario(name), duration_s=duration_s, **changes)  # type: ignore[arg-type]
    keys = Keys(prefix)
    out = []
    for m in generate(sc, seed):
        out.append((keys.input(m.kind, m.radar_id), json.dumps(m.body).encode()))
    return out
