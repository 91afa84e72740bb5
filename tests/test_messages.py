"""Wire models, rejection reasons and the committed JSON Schemas (docs/contract.md §1)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import jsonschema
import pytest
from pydantic import ValidationError

from service.schema_files import EXAMPLES, render, schema_documents
from service.wire.models import WIRE_MODELS, AisBatch, PlotBatch, RadarSite, rejection_reason

SCHEMAS = Path(__file__).resolve().parents[1] / "schemas"


def test_committed_schemas_match_the_models() -> None:
    """`topofusion schemas` output is committed; a model change without regenerating fails here."""
    for rel, doc in schema_documents().items():
        path = SCHEMAS / rel
        assert path.is_file(), f"{path} missing: run `topofusion schemas`"
        assert path.read_text(encoding="utf-8") == render(doc), f"{rel} drifted: run `topofusion schemas`"


@pytest.mark.parametrize("name", sorted(WIRE_MODELS))
def test_every_example_validates_against_model_and_schema(name: str) -> None:
    example = json.loads((SCHEMAS / "examples" / f"{name}.json").read_text())
    WIRE_MODELS[name].model_validate(example)
    schema = json.loads((SCHEMAS / f"{name}.schema.json").read_text())
    jsonschema.validate(example, schema)


def _plot_batch(**plots: object) -> dict[str, object]:
    body = json.loads(json.dumps(EXAMPLES["PlotBatch"]))
    body["plots"].update(plots)
    return body


@pytest.mark.parametrize(
    ("payload", "reason"),
    [
        (b"{not json", "malformed_json"),
        (b"\xff\xfe\x00", "malformed_json"),
        # JSON, but not the object the message needs (contract §2.8); a nested one is schema
        (b"[1, 2, 3]", "malformed_json"),
        (b"null", "malformed_json"),
        (b'"plots"', "malformed_json"),
        (json.dumps({**_plot_batch(), "plots": [1, 2]}).encode(), "schema"),
        (json.dumps({"radar_id": "A"}).encode(), "schema"),
        (json.dumps(_plot_batch(range_m=[1.0])).encode(), "schema"),  # unequal columns
        (json.dumps({**_plot_batch(), "radar_id": "bad id!"}).encode(), "schema"),
        (json.dumps(_plot_batch(range_m=[1.0, -5.0])).encode(), "out_of_range"),
        (json.dumps(_plot_batch(azimuth_deg=[360.0, 1.0])).encode(), "out_of_range"),
        (json.dumps(_plot_batch(elevation_deg=[91.0, 1.0])).encode(), "out_of_range"),
        (json.dumps(_plot_batch(range_m=[1.0, 2.7e156])).encode(), "out_of_range"),  # finite, absurd
        (
            json.dumps(_plot_batch(time_s=[1763769603.1, 1763769699.0])).encode(),
            "out_of_range",
        ),  # after batch
        (json.dumps({**_plot_batch(), "time_s": 1e300}).encode(), "out_of_range"),
        (json.dumps(_plot_batch(elevation_deg=None, altitude_m=[0.0, 1e200])).encode(), "out_of_range"),
        (json.dumps(_plot_batch()).replace("152031.5", "NaN").encode(), "non_finite"),
        (json.dumps(_plot_batch()).replace("152031.5", "Infinity").encode(), "non_finite"),
        (json.dumps(_plot_batch()).replace("152031.5", "1e999").encode(), "non_finite"),
        # a NaN where an integer belongs is as non-finite as one in a float column
        (json.dumps(_plot_batch()).replace('"seq": 42', '"seq": NaN').encode(), "non_finite"),
        (
            json.dumps(
                _plot_batch(
                    time_s=[1.0] * 100_001,
                    range_m=[1.0] * 100_001,
                    azimuth_deg=[1.0] * 100_001,
                    elevation_deg=None,
                )
            ).encode(),
            "too_large",
        ),
    ],
)
def test_rejection_reasons(payload: bytes, reason: str) -> None:
    with pytest.raises(ValidationError) as info:
        PlotBatch.model_validate_json(payload)
    assert rejection_reason(info.value)[0] == reason


def test_optional_columns_and_2d_radar() -> None:
    body = _plot_batch(elevation_deg=None, altitude_m=[9000.0, 0.0], truth_id=["T1", None])
    batch = PlotBatch.model_validate_json(json.dumps(body))
    assert batch.plots.elevation_deg is None
    assert batch.plots.altitude_m == [9000.0, 0.0]


def test_ais_and_site_rules() -> None:
    ais = json.loads(json.dumps(EXAMPLES["AisBatch"]))
    AisBatch.model_validate(ais)
    ais["reports"]["latitude_deg"] = [91.0, 0.0]
    with pytest.raises(ValidationError) as info:
        AisBatch.model_validate_json(json.dumps(ais))
    assert rejection_reason(info.value)[0] == "out_of_range"
    with pytest.raises(ValidationError):
        RadarSite.model_validate({"radar_id": "A", "latitude_deg": 0, "longitude_deg": 200})


def test_everything_the_engine_publishes_is_valid_against_models_and_schemas() -> None:
    """The output builders (service/wire/outputs.py) are fast, hand-written JSON: every payload
    a real run publishes, and what the read model serves, must still be its model's."""
    from service.engine import Engine
    from service.wire.keys import MODEL_BY_KIND, parse_key
    from tests.scenario_helpers import scenario_messages

    stream = scenario_messages("coastal", duration_s=120.0)  # a radar and an AIS reference
    stream += scenario_messages("three-radar", duration_s=60.0, targets=30)
    stream.append(("fusion/radar/A/plots", b"{broken"))
    engine = Engine()
    out = []
    for key, payload in stream:
        out.extend(engine.ingest(key, payload, receive_time_s=0.0))
    out.extend(engine.flush())
    seen: set[str] = set()
    validators: dict[str, Any] = {}
    for msg in out:
        kind, _ = parse_key(msg.key, "fusion")
        model = MODEL_BY_KIND[kind]
        body = json.loads(msg.payload)
        model.model_validate(body)
        name = model.__name__
        if name not in validators:  # the schema checked once (jsonschema.validate does per call)
            schema = json.loads((SCHEMAS / f"{name}.schema.json").read_text())
            cls = jsonschema.validators.validator_for(schema)
            cls.check_schema(schema)
            validators[name] = cls(schema)
        validators[name].validate(body)
        seen.add(kind)
    assert seen == {"tracks", "pairs", "system_tracks", "errors"}
    snap = engine.snapshot()
    for status in ("confirmed", "tentative", "all"):
        WIRE_MODELS["SystemTrackBatch"].model_validate(snap.system_tracks(status))
    for ps in snap.pair_sets(status="all"):
        WIRE_MODELS["PairSet"].model_validate(ps)
    for tb in snap.track_batches("all"):
        WIRE_MODELS["TrackBatch"].model_validate(tb)
    for b in snap.biases():
        WIRE_MODELS["BiasEstimate"].model_validate(b)
    WIRE_MODELS["Status"].model_validate(snap.status())
    for r in snap.radars():
        WIRE_MODELS["RadarInfo"].model_validate(r)


def test_the_wire_names_the_methods_the_numerics_have() -> None:
    """The contract's method names (service/wire/vocabulary.py) are the correlators' registry."""
    from service.correlation import METHODS as REGISTERED
    from service.wire.vocabulary import METHODS

    assert METHODS == REGISTERED


def test_the_wire_names_the_pair_bases_the_numerics_have() -> None:
    """``Pair.basis`` words (service/wire/vocabulary.py) are the correlator's ``Basis`` names."""
    from service.correlation.base import BASIS_NAMES
    from service.wire.vocabulary import PAIR_BASES

    assert PAIR_BASES == BASIS_NAMES
