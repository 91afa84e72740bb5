"""JSON Schemas of every contract payload, and one example of each (``topofusion schemas``)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from service.wire.models import WIRE_MODELS

#: The contract's own examples (docs/contract.md §1-2), one per payload.
EXAMPLES: dict[str, Any] = {
    "RadarSite": {
        "radar_id": "A",
        "latitude_deg": 31.20,
        "longitude_deg": 118.50,
        "altitude_m": 40.0,
        "range_sigma_m": 200.0,
        "azimuth_sigma_deg": 0.2,
        "elevation_sigma_deg": 0.2,
        "scan_period_s": 4.0,
    },
    "PlotBatch": {
        "radar_id": "A",
        "seq": 42,
        "time_s": 1763769604.0,
        "plots": {
            "time_s": [1763769603.1, 1763769603.4],
            "range_m": [152031.5, 98012.0],
            "azimuth_deg": [41.25, 310.0],
            "elevation_deg": [2.10, 1.35],
        },
    },
    "AisBatch": {
        "source_id": "coast-1",
        "seq": 7,
        "time_s": 1763769604.0,
        "reports": {
            "time_s": [1763769601.0, 1763769603.5],
            "mmsi": ["412345678", "413000111"],
            "latitude_deg": [30.61, 30.70],
            "longitude_deg": [122.31, 122.45],
        },
    },
    "AdsbBatch": {
        "source_id": "ads-b",
        "seq": 3,
        "time_s": 1763769604.0,
        "reports": {
            "time_s": [1763769603.1],
            "icao24": ["3c6444"],
            "latitude_deg": [48.71],
            "longitude_deg": [2.36],
            "altitude_m": [10363.0],
            "mode_3a": ["4521"],
            "flight_level": [340.0],
        },
    },
    "TrackBatch": {
        "radar_id": "A",
        "time_s": 1763769604.0,
        "tracks": [
            {
                "track_id": "A-17",
                "status": "confirmed",
                "time_s": 1763769603.4,
                "latitude_deg": 31.9,
                "longitude_deg": 119.1,
                "altitude_m": 9100.0,
                "position_ecef_m": [-2.7e6, 4.7e6, 3.3e6],
                "velocity_ecef_mps": [120.0, -80.0, 0.5],
                "plots": 12,
                "truth_id": None,
                "mode_3a": "7000",
                "mode_s": "3c6444",
                "quality": 0.94,
            }
        ],
    },
    "PairSet": {
        "radar_a": "A",
        "radar_b": "B",
        "time_s": 1763769604.0,
        "method": "svd-topology",
        "pairs": [
            {
                "track_a": "A-17",
                "track_b": "B-4",
                "status": "confirmed",
                "score": 0.97,
                "statistic": 1.21,
                "rotation_weight": 0.999,
                "scale": 1.0004,
                "neighbors": 6,
                "hits": 5,
                "first_time_s": 1763769580.0,
                "last_time_s": 1763769604.0,
                "held": False,
            }
        ],
    },
    "SystemTrackBatch": {
        "time_s": 1763769604.0,
        "system_tracks": [
            {
                "system_track_id": "T-12",
                "status": "confirmed",
                "time_s": 1763769603.8,
                "latitude_deg": 48.71,
                "longitude_deg": 2.36,
                "altitude_m": 10360.0,
                "position_ecef_m": [4.2e6, 1.7e5, 4.7e6],
                "velocity_ecef_mps": [120.0, -80.0, 0.5],
                "position_sigma_m": 85.0,
                "members": [{"radar_id": "A", "track_id": "A-17"}, {"radar_id": "B", "track_id": "B-4"}],
            }
        ],
    },
    "Rejection": {
        "key": "fusion/radar/A/plots",
        "radar_id": "A",
        "reason": "duplicate_seq",
        "detail": "seq 41 <= last accepted 42",
        "time_s": 1763769604.2,
    },
    "Status": {
        "uptime_s": 12.5,
        "method": "svd-topology",
        "prefix": "fusion",
        "zenoh": {"mode": "peer", "listen": ["tcp/127.0.0.1:7447"], "connect": []},
        "radars": [
            {
                "radar_id": "A",
                "batches": 30,
                "plots": 15000,
                "rejected": 0,
                "lost_batches": 0,
                "window_plots": 2000,
                "tracks_confirmed": 48,
                "tracks_tentative": 3,
                "last_time_s": 1763769604.0,
            }
        ],
        "pairs_confirmed": 40,
        "pairs_tentative": 5,
        "pairs_held": 0,
        "correlation": {"updates": 60, "last_ms": 3.2, "p50_ms": 2.9, "p99_ms": 7.5},
        "rejected": {"duplicate_seq": 1},
    },
    "BiasEstimate": {
        "radar_id": "A",
        "range_bias_m": 98.0,
        "azimuth_bias_deg": 0.11,
        "elevation_bias_deg": 0.04,
        "pairs_used": 35,
        "time_s": 1763769604.0,
    },
    "TrackStates": {
        "radar_id": "A",
        "seq": 12,
        "time_s": 1763769604.0,
        "full": False,
        "count": 48,
        "removed": ["A-9"],
        "tracks": {
            "track_id": ["A-17"],
            "confirmed": [True],
            "time_s": [1763769603.4],
            "position_ecef_m": [[-2.7e6, 4.7e6, 3.3e6]],
            "velocity_ecef_mps": [[120.0, -80.0, 0.5]],
            "covariance": [
                [float(40000 if i % 7 == 0 and i < 21 else 25 if i % 7 == 0 else 0) for i in range(36)]
            ],
            "plots": [12],
            "quality": [0.94],
        },
    },
    "RegistrationRows": {
        "source_a": "A",
        "source_b": "B",
        "reference": False,
        "time_s": 1763769604.0,
        "track_a": ["A-17"],
        "track_b": ["B-4"],
        "p_a": [[-2.7e6, 4.7e6, 3.3e6]],
        "p_b": [[-2.7003e6, 4.7001e6, 3.3002e6]],
        "s": [[80000.0, 0.0, 0.0, 0.0, 80000.0, 0.0, 0.0, 0.0, 80000.0]],
    },
    "PairLinks": {
        "source_a": "A",
        "source_b": "B",
        "time_s": 1763769604.0,
        "release": "B",
        "track_a": ["A-17", "A-21"],
        "track_b": ["B-4", "B-9"],
        "score": [0.998, 0.97],
    },
    "BiasSet": {
        "time_s": 1763769604.0,
        "partition": "1/2",
        "biases": [
            {
                "radar_id": "A",
                "range_bias_m": 148.2,
                "azimuth_bias_deg": 0.148,
                "elevation_bias_deg": 0.0,
                "pairs_used": 40,
                "time_s": 1763769604.0,
            }
        ],
    },
    "WorkerClock": {
        "partition": "2/3",
        "released_s": 1763769603.5,
        "correlated_s": 1763769601.0,
        "clocks": {"A": 1763769604.0, "C": 1763769603.5},
    },
    "RadarPerformance": {
        "radar_id": "PAR",
        "time_s": 1763769604.0,
        "window_s": 600.0,
        "references": ["ads-b"],
        "aircraft": 41,
        "detection": {"pd": 0.921, "pd_sigma": 0.006, "expected": 2210, "detected": 2036},
        "position": {
            "rms_m": 168.0,
            "median_m": 121.0,
            "rms_uncorrected_m": 402.0,
            "range_rms_m": 101.0,
            "azimuth_rms_deg": 0.121,
            "plots": 2036,
        },
        "mode_3a": {"checked": 1800, "correct": 1791, "rate": 0.995},
        "mode_c": {"checked": 1790, "correct": 1760, "rate": 0.983},
        "requirements": {"pd_min": 0.97, "mode_3a_min": 0.98, "mode_c_min": 0.96},
        "verdict": {"pd": False, "mode_3a": True, "mode_c": True},
    },
    "RadarInfo": {
        "radar_id": "A",
        "latitude_deg": 31.20,
        "longitude_deg": 118.50,
        "altitude_m": 40.0,
        "range_sigma_m": 200.0,
        "azimuth_sigma_deg": 0.2,
        "elevation_sigma_deg": 0.2,
        "scan_period_s": 4.0,
        "batches": 30,
        "plots": 15000,
        "rejected": 0,
        "lost_batches": 0,
        "last_time_s": 1763769604.0,
    },
}


def schema_documents() -> dict[str, dict[str, Any]]:
    """File name -> JSON document, for every schema and example."""
    docs: dict[str, dict[str, Any]] = {}
    for name, model in WIRE_MODELS.items():
        schema = model.model_json_schema(mode="validation")
        schema["$schema"] = "https://json-schema.org/draft/2020-12/schema"
        schema["$id"] = f"{name}.schema.json"
        docs[f"{name}.schema.json"] = schema
        docs[f"examples/{name}.json"] = EXAMPLES[name]
    return docs


def render(doc: dict[str, Any]) -> str:
    return json.dumps(doc, indent=2, sort_keys=True) + "\n"


def write_schemas(out: Path) -> list[Path]:
    written = []
    for rel, doc in schema_documents().items():
        path = out / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(render(doc), encoding="utf-8")
        written.append(path)
    return written
