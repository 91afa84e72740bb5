"""Input payloads into what the stages take: validated wire models, then numpy columns.

Every check of a message's content happens here or in the models (:mod:`service.wire.models`)
before anything changes: a message that fails is a :class:`~.errors.RejectionError` with the
contract's reason, and no stage has seen it.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from pydantic import ValidationError

from service.pipeline.errors import RejectionError
from service.tracking.base import PlotColumns
from service.wire.models import AdsbBatch, AisBatch, AisReportsModel, PlotBatch, RadarSite, rejection_reason

#: The model of each input kind's payload.
INPUT_MODELS: dict[str, type[Any]] = {
    "site": RadarSite,
    "plots": PlotBatch,
    "ais": AisBatch,
    "adsb": AdsbBatch,
}


def list_of(values: object, *types: type) -> bool:
    """``values`` is a list whose items are each exactly of one of ``types``: JSON's own types,
    which a parser makes without subclasses.  One pass in C, not a Python test per item (a
    peer's whole table carries hundreds of ids and labels)."""
    return isinstance(values, list) and set(map(type, values)) <= set(types)


def parse(model: type[Any], payload: bytes, source_id: str | None) -> Any:
    """``payload`` validated as ``model``; a failure is the rejection the contract names."""
    try:
        return model.model_validate_json(payload)
    except ValidationError as exc:
        reason, detail = rejection_reason(exc)
        raise RejectionError(reason, detail, source_id) from None


def decode_input(what: str, source_id: str, payload: bytes) -> RadarSite | PlotBatch | AisBatch | AdsbBatch:
    """An input message of kind ``what`` (``site``, ``plots``, ``ais``, ``adsb``) for the source of
    its key: validated, and its body's id the key's."""
    msg = parse(INPUT_MODELS[what], payload, source_id)
    body_id = msg.source_id if what in ("ais", "adsb") else msg.radar_id
    check_body_id("source_id" if what in ("ais", "adsb") else "radar_id", body_id, source_id)
    return msg


def check_body_id(field_name: str, body_id: str, key_id: str) -> None:
    """The id in a payload's body must be the one in its key (``schema`` otherwise)."""
    if body_id != key_id:
        raise RejectionError("schema", f"{field_name} {body_id!r} in body != {key_id!r} in key", key_id)


@dataclass(frozen=True)
class ReleasedPlots(PlotColumns):
    """A batch's plots as released: the tracker's columns, and the barometric flight level
    (NaN: none) that the performance assessment checks Mode C with (trackers ignore it)."""

    flight_level: np.ndarray = None  # type: ignore[assignment]  # filled by __post_init__

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.flight_level is None:
            object.__setattr__(self, "flight_level", np.full(len(self), np.nan))


def plot_columns(batch: PlotBatch) -> ReleasedPlots:
    """A plot batch's columns as the tracker takes them (NaN / None where a column is null)."""
    p = batch.plots
    n = len(p.time_s)
    return ReleasedPlots(
        time_s=np.asarray(p.time_s, dtype=float),
        range_m=np.asarray(p.range_m, dtype=float),
        azimuth_deg=np.asarray(p.azimuth_deg, dtype=float),
        elevation_deg=floats(p.elevation_deg, n),
        altitude_m=floats(p.altitude_m, n),
        truth_id=labels(p.truth_id, n),
        mode_3a=labels(p.mode_3a, n),
        mode_s=labels(p.mode_s, n),
        flight_level=floats(p.flight_level, n),
    )


def reference_kind(batch: AisBatch | AdsbBatch) -> str:
    """``ais`` or ``adsb``: the input kind of a reference batch."""
    return "ais" if isinstance(batch, AisBatch) else "adsb"


def reference_columns(batch: AisBatch | AdsbBatch) -> tuple[np.ndarray, ...]:
    """A reference batch's columns ``(report times, ids, latitude, longitude, altitude)`` as
    the correlation stage takes them: one path for AIS and ADS-B, which differ only in the id
    column and in the altitude ADS-B may give (AIS: vessels at sea level; NaN: not reported)."""
    r = batch.reports
    if isinstance(r, AisReportsModel):
        ids, altitude = np.asarray(r.mmsi, dtype=str), np.zeros(len(r.time_s))
    else:
        ids = np.asarray(r.icao24, dtype=str)
        altitude = floats(r.altitude_m, len(r.time_s))
    return (
        np.asarray(r.time_s, dtype=float),
        ids,
        np.asarray(r.latitude_deg, dtype=float),
        np.asarray(r.longitude_deg, dtype=float),
        altitude,
    )


def reference_identity(batch: AisBatch | AdsbBatch) -> tuple[np.ndarray, np.ndarray]:
    """A reference batch's Mode 3/A codes (None: none) and barometric flight levels (NaN:
    none): ADS-B's optional columns, AIS has neither."""
    r = batch.reports
    n = len(r.time_s)
    if isinstance(r, AisReportsModel):
        return np.full(n, None, dtype=object), np.full(n, np.nan)
    return labels(r.mode_3a, n), floats(r.flight_level, n)


def floats(column: Sequence[float | None] | None, n: int) -> np.ndarray:
    """A wire column of numbers or nulls as floats, NaN for null (all NaN when left out)."""
    if column is None:
        return np.full(n, np.nan)
    if None in column:
        return np.array([np.nan if x is None else x for x in column], dtype=float)
    return np.asarray(column, dtype=float)


def labels(column: list[str | None] | None, n: int) -> np.ndarray:
    """A wire label column as an object array (all None when left out)."""
    out = np.full(n, None, dtype=object)
    if column is not None:
        out[:] = column
    return out
