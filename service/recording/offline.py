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


@dataclass
class Comparison:
    """Confirmed tracks and pairs of a replay against the service's last outputs in a recording."""

    recorded_tracks: int
    replayed_tracks: int
    recorded_pairs: int
    replayed_pairs: int
    differences: list[str]

    @property
    def identical(self) -> bool:
        return not self.differences


def recorded_final_outputs(path: str | Path, prefix: str = "fusion") -> dict[str, list[dict[str, Any]]]:
    """The last ``TrackBatch`` per radar and ``PairSet`` per radar pair the service published."""
    last: dict[str, dict[str, Any]] = {}
    options = ReplayOptions(speed=0, include_outputs=True)
    with RecordingReader(path, prefix) as reader:
        plan = plan_replay(reader, prefix, options)
        for message in reader.messages(plan.channels, plan.start_ns, plan.end_ns):
            if message.kind in ("tracks", "pairs"):
                last[message.key] = json.loads(message.payload)
    tracks = [v for k, v in sorted(last.items()) if k.endswith("/tracks")]
    pairs = [v for k, v in sorted(last.items()) if "/pairs/" in k]
    return {"tracks": tracks, "pairs": pairs}


def _confirmed_tracks(batches: list[dict[str, Any]]) -> dict[str, str]:
    return {
        t["track_id"]: json.dumps(t, sort_keys=True)
        for b in batches
        for t in b["tracks"]
        if t["status"] == "confirmed"
    }


def _confirmed_pairs(sets: list[dict[str, Any]]) -> dict[tuple[str, str, str, str], str]:
    return {
        (s["radar_a"], s["radar_b"], p["track_a"], p["track_b"]): json.dumps(p, sort_keys=True)
        for s in sets
        for p in s["pairs"]
        if p["status"] == "confirmed"
    }


def compare_with_recording(result: OfflineResult, path: str | Path, prefix: str = "fusion") -> Comparison:
    """Exact comparison (every field, floats bit for bit) of confirmed tracks and pairs.

    Meaningful when the recording holds the service's final outputs: stop the service (it
    flushes and publishes its last tracks and pairs) before stopping the recorder.
    """
    recorded = recorded_final_outputs(path, prefix)
    rec_t, rep_t = _confirmed_tracks(recorded["tracks"]), _confirmed_tracks(result.tracks)
    rec_p, rep_p = _confirmed_pairs(recorded["pairs"]), _confirmed_pairs(result.pairs)
    diffs: list[str] = []
    for name, rec, rep in (("track", rec_t, rep_t), ("pair", rec_p, rep_p)):
        for k in sorted(set(rec) - set(rep), key=str):
            diffs.append(f"confirmed {name} {k} recorded but not replayed")
        for k in sorted(set(rep) - set(rec), key=str):
            diffs.append(f"confirmed {name} {k} replayed but not recorded")
        for k in sorted(set(rec) & set(rep), key=str):
            if rec[k] != rep[k]:  # type: ignore[index]
                diffs.append(f"confirmed {name} {k} differs")
    return Comparison(len(rec_t), len(rep_t), len(rec_p), len(rep_p), diffs)
