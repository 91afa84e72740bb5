"""``replay --offline --compare``: the replay against the service's last outputs in the file."""

from __future__ import annotations

import json
from pathlib import Path

from recording_helpers import PREFIX

from service.recording import RecordingWriter
from service.recording.offline import OfflineResult, compare_with_recording, recorded_final_outputs

T0 = 1_763_769_600 * 10**9


def _track(tid: str, status: str, x: float) -> dict[str, object]:
    return {
        "track_id": tid, "status": status, "time_s": 1.0, "latitude_deg": 31.0, "longitude_deg": 121.0,
        "altitude_m": 0.0, "position_ecef_m": [x, 0.0, 0.0], "velocity_ecef_mps": [0.0, 0.0, 0.0],
        "plots": 3, "truth_id": None,
    }  # fmt: skip


def _pair(a: str, b: str, status: str) -> dict[str, object]:
    return {
        "track_a": a, "track_b": b, "status": status, "score": 1.0, "statistic": 0.5, "rotation_weight": 1.0,
        "scale": 1.0, "neighbors": 3, "hits": 4, "first_time_s": 1.0, "last_time_s": 2.0,
    }  # fmt: skip


def test_compare_uses_the_last_outputs_and_confirmed_items_only(tmp_path: Path) -> None:
    path = tmp_path / "rec.mcap"
    old = {"radar_id": "A", "time_s": 1.0, "tracks": [_track("A-1", "tentative", 1.0)]}
    final_a = {
        "radar_id": "A",
        "time_s": 2.0,
        "tracks": [_track("A-1", "confirmed", 2.0), _track("A-2", "tentative", 0)],
    }
    final_b = {"radar_id": "B", "time_s": 2.0, "tracks": [_track("B-1", "confirmed", 3.0)]}
    pairs = {"radar_a": "A", "radar_b": "B", "time_s": 2.0, "method": "svd-topology",
             "pairs": [_pair("A-1", "B-1", "confirmed"), _pair("A-2", "B-1", "tentative")]}  # fmt: skip
    with RecordingWriter(path, PREFIX) as w:
        w.write(f"{PREFIX}/radar/A/tracks", json.dumps(old).encode(), T0)
        w.write(f"{PREFIX}/radar/A/tracks", json.dumps(final_a).encode(), T0 + 1)
        w.write(f"{PREFIX}/radar/B/tracks", json.dumps(final_b).encode(), T0 + 2)
        w.write(f"{PREFIX}/pairs/A/B", json.dumps(pairs).encode(), T0 + 3)
    recorded = recorded_final_outputs(path, PREFIX)
    assert recorded["tracks"] == [final_a, final_b] and recorded["pairs"] == [pairs]

    same = OfflineResult(tracks=[final_a, final_b], pairs=[pairs], biases=[])
    cmp = compare_with_recording(same, path, PREFIX)
    assert cmp.identical and (cmp.recorded_tracks, cmp.recorded_pairs) == (2, 1)

    # A tentative item differing does not count; a confirmed one moved by one ulp does.
    moved = json.loads(json.dumps(final_b))
    moved["tracks"][0]["position_ecef_m"][0] = 3.0000000000000004
    other = OfflineResult(tracks=[{**final_a, "tracks": final_a["tracks"][:1]}, moved], pairs=[], biases=[])
    cmp = compare_with_recording(other, path, PREFIX)
    assert not cmp.identical
    assert "confirmed track B-1 differs" in cmp.differences
    assert "confirmed pair ('A', 'B', 'A-1', 'B-1') recorded but not replayed" in cmp.differences
