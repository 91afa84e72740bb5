"""Key kinds and payload schemas of recorded channels."""

from __future__ import annotations

import json

import pytest

from service.recording.keys import KeyFilter, is_concrete_key, schema_for_kind
from service.wire.keys import classify_key


@pytest.mark.parametrize(
    ("key", "kind"),
    [
        ("fusion/radar/A/site", "site"),
        ("fusion/radar/r-2_x/plots", "plots"),
        ("fusion/radar/A/tracks", "tracks"),
        ("fusion/ais/coast-1/reports", "ais"),
        ("fusion/pairs/A/B", "pairs"),
        ("fusion/errors", "errors"),
        ("fusion/status", "status"),
        ("fusion/radar/A/other", "other"),
        ("other/radar/A/plots", "other"),
        ("fusion/radar/A/B/plots", "other"),
    ],
)
def test_classify_key_follows_the_contract_table(key: str, kind: str) -> None:
    assert classify_key(key, "fusion") == kind


def test_classify_key_with_a_multi_level_prefix() -> None:
    assert classify_key("site1/fusion/radar/A/plots", "site1/fusion") == "plots"
    assert classify_key("fusion/radar/A/plots", "site1/fusion") == "other"


def test_schemas_come_from_the_wire_models() -> None:
    from service.wire.models import PlotBatch

    name, data = schema_for_kind("plots") or ("", b"")
    assert name == "PlotBatch"
    assert json.loads(data) == PlotBatch.model_json_schema()
    assert schema_for_kind("other") is None
    names = {schema_for_kind(k)[0] for k in ("site", "ais", "tracks", "pairs", "errors", "status")}  # type: ignore[index]
    assert names == {"RadarSite", "AisBatch", "TrackBatch", "PairSet", "Rejection", "Status"}


def test_concrete_keys_and_filters() -> None:
    assert is_concrete_key("fusion/radar/A/plots")
    assert not is_concrete_key("fusion/radar/*/plots")
    assert not is_concrete_key("/fusion/plots")  # ROS-style topics are not Zenoh keys
    assert not is_concrete_key("")
    f = KeyFilter("fusion/radar/A/**")
    assert f.matches("fusion/radar/A/plots") and not f.matches("fusion/radar/B/plots")
    assert KeyFilter(None).matches("anything/at/all")
    with pytest.raises(ValueError, match="invalid key expression"):
        KeyFilter("a//b")
