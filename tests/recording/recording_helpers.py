"""Helpers shared by the recording tests (imported by name; tests/recording has no package)."""

from __future__ import annotations

import json
from pathlib import Path

from mcap.writer import CompressionType, Writer

from tests.support import free_port, wait_for, wait_subscribed

__all__ = ["PREFIX", "foreign_mcap", "free_port", "plots", "site", "wait_for", "wait_subscribed"]

PREFIX = "fusion"


def site(radar_id: str, lat: float = 31.0, lon: float = 121.0) -> bytes:
    return json.dumps({"radar_id": radar_id, "latitude_deg": lat, "longitude_deg": lon}).encode()


def plots(radar_id: str, seq: int, t: float, n: int = 3) -> bytes:
    body = {
        "radar_id": radar_id,
        "seq": seq,
        "time_s": t,
        "plots": {
            "time_s": [t - 0.1 * i for i in range(n)],
            "range_m": [10_000.0 + 100 * i for i in range(n)],
            "azimuth_deg": [10.0 + i for i in range(n)],
            "elevation_deg": [1.0] * n,
        },
    }
    return json.dumps(body).encode()


def foreign_mcap(
    path: Path,
    messages: list[tuple[str, bytes, int]],
    *,
    chunked: bool = True,
    compression: CompressionType = CompressionType.LZ4,
    chunk_size: int = 1024 * 1024,
    with_schema: bool = False,
    extra_channels: dict[str, str] | None = None,
) -> None:
    """An MCAP file written with the ``mcap`` library directly, following the contract only."""
    with open(path, "wb") as f:
        w = Writer(f, chunk_size=chunk_size, compression=compression, use_chunking=chunked)
        w.start(profile="", library="some-other-writer")
        schema_id = 0
        if with_schema:
            schema_id = w.register_schema("AnyJson", "jsonschema", b"{}")
        channels: dict[str, int] = {}
        for topic, encoding in (extra_channels or {}).items():
            channels[topic] = w.register_channel(topic, encoding, 0)
        for key, payload, log_time in messages:
            if key not in channels:
                channels[key] = w.register_channel(key, "json", schema_id)
            w.add_message(channels[key], log_time=log_time, data=payload, publish_time=log_time)
        w.finish()
