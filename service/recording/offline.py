"""Offline replay: a recording fed straight into an engine in this process (no Zenoh).

The same selection and order as a Zenoh replay (:func:`~service.recording.replay.iter_replay`),
the same engine code path as the running service, ``flush`` at the end, then the final tracks,
pairs and biases as JSON.  Only the service's inputs are fed: the engine recomputes its outputs.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

from service.recording.reader import RecordingReader
from service.recording.replay import ReplayOptions, plan_replay


class EngineLike(Protocol):
    def ingest(self, key: str, payload: bytes, receive_time_s: float | None = None) -> list[Any]: ...

    def flush(self) -> list[Any]: ...

    def snapshot(self) -> Any: ...


@dataclass
class OfflineResult:
    """Final state of the engine after the whole recording, plus what was fed."""

    tracks: list[dict[str, Any]]
    pairs: list[dict[str, Any]]
    biases: list[dict[str, Any]]
    messages: int = 0
    plots: int = 0
    messages_by_key: dict[str, int] = field(default_factory=dict)
    rejected: dict[str, int] = field(default_factory=dict)
    wall_s: float = 0.0
    damage: str | None = None

    def to_json(self) -> dict[str, Any]:
        return {
            "tracks": self.tracks,
            "pairs": self.pairs,
            "biases": self.biases,
            "replay": {
                "messages": self.messages,
                "plots": self.plots,
                "messages_by_key": self.messages_by_key,
                "rejected": self.rejected,
                "damage": self.damage,
            },
        }


def _count_plots(payload: bytes) -> int:
    """Plots in a PlotBatch payload without a full parse (for throughput figures only)."""
    head = payload.find(b'"range_m"')
    if head < 0:
        return 0
    end = payload.find(b"]", head)
    body = payload[payload.find(b"[", head) + 1 : end].strip()
    return body.count(b",") + 1 if body else 0


def replay_offline(
    path: str | Path, engine: EngineLike, prefix: str = "fusion", options: ReplayOptions | None = None
) -> OfflineResult:
    """Feed ``path``'s input messages (log-time order) into ``engine``; returns its final state.

    ``receive_time_s`` passed to the engine is the recorded receipt time (log_time), so even
    rejections carry the times they had live.
    """
    options = options or ReplayOptions(speed=0)
    if options.include_outputs:
        raise ValueError("offline replay feeds the service's inputs only (no --all-keys)")
    started = time.monotonic()
    messages = plots = 0
    by_key: dict[str, int] = {}
    with RecordingReader(path, prefix) as reader:
        plan = plan_replay(reader, prefix, options)
        for message in reader.messages(plan.channels, plan.start_ns, plan.end_ns):
            engine.ingest(message.key, message.payload, message.log_time_ns / 1e9)
            messages += 1
            by_key[message.key] = by_key.get(message.key, 0) + 1
            if message.kind == "plots":
                plots += _count_plots(message.payload)
        damage = reader.damage.describe() if reader.damage is not None else None
    engine.flush()
    snap = engine.snapshot()
    status = snap.status() if hasattr(snap, "status") else {}
    return OfflineResult(
        tracks=snap.track_batches(status="all"),
        pairs=snap.pair_sets(status="all"),
        biases=snap.biases(),
        messages=messages,
        plots=plots,
        messages_by_key=by_key,
        rejected=dict(status.get("rejected", {})),
        wall_s=time.monotonic() - started,
        damage=damage,
    )


def write_result(result: OfflineResult, out: str | Path) -> None:
    Path(out).write_text(json.dumps(result.to_json(), indent=1, sort_keys=True) + "\n", encoding="utf-8")
