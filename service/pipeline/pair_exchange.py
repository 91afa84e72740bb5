"""What a pair's owner sends the other partitioned workers: its links
(``{prefix}/links/{a}/{b}``, ``PairLinks``) and the registration rows its updates add
(``{prefix}/registration/{a}/{b}``, ``RegistrationRows``), each as JSON or as a frame of
columns whose ids and numbers need no parsing.

**Links.** Every worker takes every other worker's links for the cycle step, and worker 1 for the picture
too: about one message a pair per picture interval, each with a few hundred confirmed pairs.
Read by the model, a JSON message of 490 links costs about 120 µs, most of it the ids made into
lists and then into numpy arrays; as a frame (:func:`service.wire.frames.columns_frame`: the
scores as doubles, each side's ids as numpy keeps them) it is the header's few fields and three
views, about 20 µs.  A frame is read with the JSON form's rules (the ``PairLinks`` model's, for
the header's fields, and scores in [0, 1]) and the frame's layout.  ``docs/contract.md``,
"Scale-out".

**Rows.** Worker 1 takes every other worker's rows for the joint bias estimate: by the model,
about 2.3 µs a row (three vectors and a 3x3 covariance of JSON numbers each); as a frame, the
numbers are doubles read in place.  The JSON form's rules hold (the model's for the header's
fields; positions and velocities within the model's ECEF bound, covariances finite).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from pydantic import ValidationError

from service.correlation.registration import RegistrationRowsData
from service.fusion.members import Links
from service.pipeline.decode import parse
from service.pipeline.errors import RejectionError
from service.pipeline.shared_links import PairRegistration, SharedLinks
from service.wire.frames import columns_frame, is_frame, read_columns
from service.wire.models import (
    MAX_ECEF_M,
    MAX_TRACKS,
    REGISTRATION_TERMS,
    LinksRegistration,
    PairLinks,
    RegistrationRows,
    rejection_reason,
)
from service.wire.outputs import encode

#: A frame's id columns (links and rows alike).
IDS = ("track_a", "track_b")
#: A links frame's number columns (name, values a row).
LINK_NUMBERS = (("score", 1),)
#: A rows frame's number columns; ``v`` may be left out (rows that say nothing of time biases).
ROW_NUMBERS = (("p_a", 3), ("p_b", 3), ("s", 9), ("v", 3))


def links_body(shared: SharedLinks) -> dict[str, Any]:
    """The ``PairLinks`` JSON body of a pair's links."""
    links = shared.links
    return {
        **_links_fields(shared),
        "track_a": links.track_a.tolist(),
        "track_b": links.track_b.tolist(),
        "score": links.score.tolist(),
    }


def links_frame(shared: SharedLinks) -> bytes:
    """The same message as a frame (the JSON bytes when an id is too long for one)."""
    links = shared.links
    ids = [("track_a", links.track_a), ("track_b", links.track_b)]
    framed = columns_frame(_links_fields(shared), [("score", links.score)], ids)
    return framed if framed is not None else encode(links_body(shared))


def _links_fields(shared: SharedLinks) -> dict[str, Any]:
    links, reg = shared.links, shared.registration
    registration = (
        {}
        if reg is None
        else {
            "registration": {
                "radar_ids": list(reg.radar_ids),
                "terms": reg.terms.tolist(),
                "covariance": reg.covariance.tolist(),
            }
        }
    )
    return {
        "source_a": links.source_a,
        "source_b": links.source_b,
        "time_s": shared.time_s,
        "release": shared.release,
        **registration,
    }


def rows_body(source_a: str, source_b: str, reference: bool, rows: RegistrationRowsData) -> dict[str, Any]:
    """The ``RegistrationRows`` JSON body of rows an owned pair added."""
    return {
        **_rows_fields(source_a, source_b, reference, rows),
        "track_a": rows.track_a.tolist(),
        "track_b": rows.track_b.tolist(),
        "p_a": rows.p_a.tolist(),
        "p_b": rows.p_b.tolist(),
        "s": rows.s.reshape(len(rows), 9).tolist(),
        **({} if rows.v is None else {"v": rows.v.tolist()}),
    }


def rows_frame(source_a: str, source_b: str, reference: bool, rows: RegistrationRowsData) -> bytes:
    """The same message as a frame (the JSON bytes when an id is too long for one)."""
    numbers = [("p_a", rows.p_a), ("p_b", rows.p_b), ("s", rows.s)]
    numbers += [] if rows.v is None else [("v", rows.v)]
    fields = _rows_fields(source_a, source_b, reference, rows)
    framed = columns_frame(fields, numbers, [("track_a", rows.track_a), ("track_b", rows.track_b)])
    return framed if framed is not None else encode(rows_body(source_a, source_b, reference, rows))


def _rows_fields(source_a: str, source_b: str, reference: bool, rows: RegistrationRowsData) -> dict[str, Any]:
    return {"source_a": source_a, "source_b": source_b, "reference": reference, "time_s": rows.time_s}


def decode_rows(payload: bytes, ids: tuple[str, str]) -> tuple[RegistrationRows, RegistrationRowsData]:
    """A ``RegistrationRows`` (JSON or a frame) on the key of the pair ``ids``, checked: its
    fields (the model, its lists empty for a frame) and its rows; a :class:`RejectionError`
    when it breaks a rule."""
    if is_frame(payload):
        got, cols = _checked_frame(
            payload, RegistrationRows, ROW_NUMBERS, IDS, ids[0], "registration", frozenset({"v"})
        )
        k = len(cols["track_a"])
        for name in ("p_a", "p_b", "v"):
            if name in cols and not np.all(np.abs(cols[name]) <= MAX_ECEF_M):  # (NaN fails)
                raise RejectionError("schema", f"registration frame: {name} beyond the ECEF bound", ids[0])
        if not np.all(np.isfinite(cols["s"])):
            raise RejectionError("schema", "registration frame: s must be finite", ids[0])
        data = RegistrationRowsData(
            got.time_s,
            cols["track_a"],
            cols["track_b"],
            cols["p_a"].astype(float),
            cols["p_b"].astype(float),
            cols["s"].reshape(k, 3, 3).astype(float),
            cols["v"].astype(float) if "v" in cols else None,
        )
    else:
        got = parse(RegistrationRows, payload, ids[0])
        k = len(got.p_a)
        data = RegistrationRowsData(
            got.time_s,
            np.asarray(got.track_a, dtype=str),
            np.asarray(got.track_b, dtype=str),
            np.asarray(got.p_a, dtype=float).reshape(k, 3),
            np.asarray(got.p_b, dtype=float).reshape(k, 3),
            np.asarray(got.s, dtype=float).reshape(k, 3, 3),
            None if got.v is None else np.asarray(got.v, dtype=float).reshape(k, 3),
        )
    _check_sources(got.source_a, got.source_b, ids)
    return got, data


def decode_links(payload: bytes, ids: tuple[str, str]) -> SharedLinks:
    """A ``PairLinks`` (JSON or a frame) on the key of the pair ``ids``, checked; a
    :class:`RejectionError` when it breaks a rule."""
    if is_frame(payload):
        got, cols = _checked_frame(payload, PairLinks, LINK_NUMBERS, IDS, ids[0], "links")
        track_a, track_b, score = cols["track_a"], cols["track_b"], cols["score"].astype(float)
        if not np.all((score >= 0.0) & (score <= 1.0)):  # (NaN fails both)
            raise RejectionError("schema", "links frame: scores must be numbers in [0, 1]", ids[0])
    else:
        got = parse(PairLinks, payload, ids[0])
        track_a, track_b = np.asarray(got.track_a, dtype=str), np.asarray(got.track_b, dtype=str)
        score = np.asarray(got.score, dtype=float)
    _check_sources(got.source_a, got.source_b, ids)
    links = Links(got.source_a, got.source_b, track_a, track_b, score)
    return SharedLinks((ids[0], ids[1]), got.time_s, got.release, links, _registration(got.registration, ids))


def _registration(got: LinksRegistration | None, ids: tuple[str, str]) -> PairRegistration | None:
    """A links message's registration (its shapes checked by the model), its radars the pair's."""
    if got is None:
        return None
    if not set(got.radar_ids) <= set(ids):
        raise RejectionError("schema", f"registration radars {got.radar_ids} not of the pair {ids}", ids[0])
    terms = np.asarray(got.terms, dtype=float).reshape(len(got.radar_ids), REGISTRATION_TERMS)
    return PairRegistration(tuple(got.radar_ids), terms, np.asarray(got.covariance, dtype=float))


def _check_sources(source_a: str, source_b: str, ids: tuple[str, str]) -> None:
    """The body's two sources must be the key's pair (either order; ``schema`` otherwise)."""
    if sorted((source_a, source_b)) != sorted(ids):
        raise RejectionError("schema", f"sources {source_a}, {source_b} != key {ids}", ids[0])


def _checked_frame(
    payload: bytes,
    model: type[Any],
    numbers: tuple[tuple[str, int], ...],
    ids: tuple[str, ...],
    source_id: str,
    what: str,
    optional: frozenset[str] = frozenset(),
) -> tuple[Any, dict[str, np.ndarray]]:
    """A frame of columns of a message of ``model``: its header's fields validated by the model
    (its list columns empty there), and its columns; a ``schema`` rejection naming ``what``
    when the layout is broken, the model's reason when a field is."""
    try:
        fields, cols = read_columns(payload, numbers, ids, optional, max_rows=MAX_TRACKS)
    except ValueError as exc:
        raise RejectionError("schema", f"{what} frame: {exc}", source_id) from None
    empty: dict[str, list[Any]] = {name: [] for name in (*(n for n, _ in numbers if n in cols), *ids)}
    try:
        return model.model_validate({**fields, **empty}), cols
    except ValidationError as exc:
        reason, detail = rejection_reason(exc)
        raise RejectionError(reason, detail, source_id) from None
