"""Simulated input streams for tests (the real simulator, short scenarios)."""

from __future__ import annotations

from dataclasses import replace

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
