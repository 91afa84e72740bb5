"""A pair's links and registration rows between partitioned workers as frames: read back as
the JSON form reads, held to the JSON form's rules and to the frame's layout, and a broken one
rejected whole."""

from __future__ import annotations

import json
import struct
from collections.abc import Callable
from dataclasses import replace
from typing import Any

import numpy as np
import pytest

from service.correlation.registration import RegistrationRowsData
from service.engine import Engine, EngineConfig
from service.fusion.members import Links
from service.pipeline.errors import RejectionError
from service.pipeline.pair_exchange import (
    decode_links,
    decode_rows,
    links_body,
    links_frame,
    rows_body,
    rows_frame,
)
from service.pipeline.partition import Partition
from service.pipeline.shared_links import PairRegistration, SharedLinks
from service.wire.frames import MAX_ID_CHARS, decode_frame, encode_frame
from service.wire.keys import Keys
from service.wire.outputs import encode

KEY = ("A", "B")


def _shared(n: int, seed: int = 1, a_ids: list[str] | None = None) -> SharedLinks:
    rng = np.random.default_rng(seed)
    track_a = np.array(a_ids if a_ids is not None else [f"A-{i}" for i in rng.permutation(n)], dtype=str)
    track_b = np.array([f"B-{i:06d}" for i in range(n)], dtype=str)
    links = Links("A", "B", track_a, track_b, rng.random(n))
    return SharedLinks(KEY, 1234.25, "B", links)


def _same(got: SharedLinks, want: SharedLinks) -> None:
    assert (got.key, got.time_s, got.release) == (want.key, want.time_s, want.release)
    assert (got.links.source_a, got.links.source_b) == (want.links.source_a, want.links.source_b)
    assert got.links.track_a.tolist() == want.links.track_a.tolist()
    assert got.links.track_b.tolist() == want.links.track_b.tolist()
    assert got.links.score.dtype == np.float64
    assert got.links.score.tobytes() == want.links.score.tobytes()


@pytest.mark.parametrize("n", [0, 1, 7, 490])
def test_a_frame_reads_back_what_the_json_form_reads(n: int) -> None:
    sent = _shared(n)
    from_json = decode_links(encode(links_body(sent)), KEY)
    from_frame = decode_links(links_frame(sent), KEY)
    _same(from_json, sent)
    _same(from_frame, sent)
    # ids of other scripts and lengths: code points, not bytes, and each side its own width
    odd = _shared(4, a_ids=["Ä-1", "航-22", "x", "😀-333"])
    _same(decode_links(links_frame(odd), KEY), odd)
    _same(decode_links(encode(links_body(odd)), KEY), odd)


def test_an_id_too_long_for_a_frame_goes_as_json() -> None:
    sent = _shared(2, a_ids=["a" * (MAX_ID_CHARS + 1), "b"])
    payload = links_frame(sent)
    assert payload.startswith(b"{")
    _same(decode_links(payload, KEY), sent)


Change = Callable[[dict[str, Any], dict[str, np.ndarray]], None]


def _parts(sent: SharedLinks) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    header, body = decode_frame(links_frame(sent))
    n, (wa, wb) = header["count"], header["widths"]
    cols = {
        "score": np.frombuffer(body, "<f8", n).copy(),
        "track_a": np.frombuffer(body, "<u4", n * wa, 8 * n).copy(),
        "track_b": np.frombuffer(body, "<u4", n * wb, 8 * n + 4 * n * wa).copy(),
    }
    return header, cols


def _frame_cases() -> list[tuple[str, bytes]]:
    good_header, good_cols = _parts(_shared(5))
    cases = [("valid", encode_frame(good_header, b"".join(c.tobytes() for c in good_cols.values())))]

    def variant(name: str, change: Change) -> None:
        header, cols = json.loads(json.dumps(good_header)), {k: v.copy() for k, v in good_cols.items()}
        change(header, cols)
        cases.append((name, encode_frame(header, b"".join(c.tobytes() for c in cols.values()))))

    def put(field: str, value: object) -> Change:
        return lambda header, cols: header.__setitem__(field, value)

    def col(name: str, at: int, value: float) -> Change:
        return lambda header, cols: cols[name].__setitem__(at, value)

    variant("score NaN", col("score", 1, np.nan))
    variant("score above one", col("score", 2, 1.5))
    variant("score negative", col("score", 0, -0.1))
    variant("id a surrogate", col("track_a", 0, 0xD800))
    variant("id beyond Unicode", col("track_b", 3, 0x110000))
    variant("count one more", put("count", 6))
    variant("count not an integer", put("count", 5.0))
    variant("count negative", put("count", -1))
    variant("width zero", put("widths", [0, good_header["widths"][1]]))
    variant("width too large", put("widths", [MAX_ID_CHARS + 1, 1]))
    variant("one width", put("widths", [3]))
    variant("columns out of order", put("binary", ["track_a", "score", "track_b"]))
    variant("a column repeated in the header", put("score", [0.5] * 5))
    variant("source id bad", put("source_a", "a b"))
    variant("release missing", lambda header, cols: header.pop("release"))
    variant("time negative", put("time_s", -1.0))
    variant("time a string", put("time_s", "now"))
    variant("sources not the key's", put("source_b", "C"))
    good = cases[0][1]
    cases.append(("body one byte short", good[:-1]))
    cases.append(("body one byte long", good + b"\0"))
    cases.append(("header longer than the frame", good[:4] + struct.pack("<I", len(good)) + good[8:]))
    cases.append(("header not an object", encode_frame([1, 2], b"")))  # type: ignore[arg-type]
    return cases


@pytest.mark.parametrize(("name", "payload"), _frame_cases(), ids=[c[0] for c in _frame_cases()])
def test_a_links_frame_is_read_whole_or_rejected(name: str, payload: bytes) -> None:
    got = _read_whole_or_rejected(name, payload)
    if got is not None:
        _same(got, _shared(5))


def _read_whole_or_rejected(name: str, payload: bytes) -> SharedLinks | None:
    """``payload`` read when the case is the valid one, else rejected (then None)."""
    try:
        got = decode_links(payload, KEY)
    except RejectionError:
        assert name != "valid", name
        return None
    assert name == "valid", name
    return got


@pytest.mark.parametrize(
    ("field", "value"),
    [("time_s", -1.0), ("time_s", "now"), ("source_a", "a b"), ("release", None), ("time_s", 1e300)],
)
def test_the_header_keeps_the_json_forms_verdicts(field: str, value: object) -> None:
    """A field the frame's header shares with the JSON form gets the same reason either way."""
    header, cols = _parts(_shared(3))
    body = links_body(_shared(3))
    header[field] = body[field] = value
    reasons = []
    for payload in (encode_frame(header, b"".join(c.tobytes() for c in cols.values())), encode(body)):
        with pytest.raises(RejectionError) as got:
            decode_links(payload, KEY)
        reasons.append(got.value.reason)
    assert reasons[0] == reasons[1]


def test_a_broken_links_frame_is_rejected_counted_and_reported() -> None:
    partition = Partition(1, 2)  # worker 1 reads every other worker's links (picture, biases)
    engine = Engine(EngineConfig(partition=partition))
    a, b = next(
        (f"R{i}", f"R{j}")
        for i in range(50)
        for j in range(i + 1, 50)
        if not partition.owns_pair(f"R{i}", f"R{j}")
    )
    sent = _shared(4)
    shared = SharedLinks(
        (a, b),
        sent.time_s,
        a,
        Links(a, b, sent.links.track_a, sent.links.track_b, sent.links.score),
    )
    out = engine.ingest(Keys("fusion").links(a, b), links_frame(shared)[:-2])
    assert engine.rejected == {"schema": 1}
    assert [o.key for o in out] == ["fusion/errors"]
    assert b"links frame" in out[0].payload
    engine.close()


# -- the pair's registration with its links (the aid of association) ----------------------------
def _registered(n: int, seed: int = 3) -> SharedLinks:
    rng = np.random.default_rng(seed)
    m = rng.normal(size=(10, 10))
    reg = PairRegistration(("A", "B"), rng.normal(size=(2, 5)) * [30.0, 1e-3, 1e-3, 20.0, 1.0], m @ m.T)
    return replace(_shared(n), registration=reg)


@pytest.mark.parametrize("form", ["json", "frame"])
def test_the_registration_reads_back_bit_for_bit(form: str) -> None:
    sent = _registered(6)
    payload = links_frame(sent) if form == "frame" else encode(links_body(sent))
    assert payload.startswith(b"{") == (form == "json")
    got = decode_links(payload, KEY)
    _same(got, sent)
    assert got.registration is not None and sent.registration is not None
    assert got.registration.radar_ids == ("A", "B")
    assert got.registration.terms.tobytes() == sent.registration.terms.tobytes()
    assert got.registration.covariance.tobytes() == sent.registration.covariance.tobytes()
    assert decode_links(links_frame(_shared(2)), KEY).registration is None  # (the aid off: none)


def _registration_cases() -> list[tuple[str, Any]]:
    good = links_body(_registered(3))["registration"]
    cases: list[tuple[str, Any]] = [("valid", good)]

    def variant(name: str, change: Callable[[dict[str, Any]], None]) -> None:
        reg = json.loads(json.dumps(good))
        change(reg)
        cases.append((name, reg))

    variant("a radar not of the pair", lambda r: r["radar_ids"].__setitem__(1, "C"))
    variant("a radar twice", lambda r: r["radar_ids"].__setitem__(1, "A"))
    variant("three radars", lambda r: r["radar_ids"].append("C"))
    variant("no radar", lambda r: r.update(radar_ids=[], terms=[], covariance=[]))
    variant("four terms", lambda r: r["terms"][0].pop())
    variant("a row of terms missing", lambda r: r["terms"].pop())
    variant("a term not a number", lambda r: r["terms"][1].__setitem__(2, "x"))
    variant("a term infinite", lambda r: r["terms"][1].__setitem__(2, float("inf")))
    variant("a covariance row short", lambda r: r["covariance"][4].pop())
    variant("a covariance row missing", lambda r: r["covariance"].pop())
    variant("a covariance NaN", lambda r: r["covariance"][0].__setitem__(0, float("nan")))
    variant("not an object", lambda r: r.clear())
    return cases


@pytest.mark.parametrize(("name", "reg"), _registration_cases(), ids=[c[0] for c in _registration_cases()])
@pytest.mark.parametrize("form", ["json", "frame"])
def test_a_links_message_s_registration_is_read_whole_or_rejected(name: str, reg: Any, form: str) -> None:
    if form == "json":
        body = {**links_body(_shared(3)), "registration": reg}
        payload = json.dumps(body, allow_nan=True).encode()
    else:
        header, cols = _parts(_shared(3))
        header["registration"] = reg
        payload = encode_frame(header, b"".join(c.tobytes() for c in cols.values()))
    got = _read_whole_or_rejected(name, payload)
    if got is not None:
        assert got.registration is not None and got.registration.terms.shape == (2, 5)


# -- registration rows -------------------------------------------------------------------------
def _rows(k: int, velocity: bool = True, seed: int = 2) -> RegistrationRowsData:
    rng = np.random.default_rng(seed)
    s = rng.normal(size=(k, 3, 3)) * 100.0
    return RegistrationRowsData(
        1234.5,
        np.array([f"A-{i}" for i in range(k)], dtype=str),
        np.array([f"Bé-{i:04d}" for i in range(k)], dtype=str),
        rng.normal(size=(k, 3)) * 4e6,
        rng.normal(size=(k, 3)) * 4e6,
        s @ s.transpose(0, 2, 1),
        rng.normal(size=(k, 3)) * 200.0 if velocity else None,
    )


def _same_rows(got: RegistrationRowsData, want: RegistrationRowsData) -> None:
    assert got.time_s == want.time_s
    assert got.track_a.tolist() == want.track_a.tolist()
    assert got.track_b.tolist() == want.track_b.tolist()
    for name in ("p_a", "p_b", "s", "v"):
        a, b = getattr(got, name), getattr(want, name)
        assert (a is None) == (b is None), name
        if a is not None:
            assert a.dtype == np.float64 and a.shape == b.shape and a.tobytes() == b.tobytes(), name


@pytest.mark.parametrize(("k", "velocity"), [(0, True), (1, False), (40, True), (300, False)])
def test_rows_read_back_the_same_from_a_frame_as_from_json(k: int, velocity: bool) -> None:
    rows = _rows(k, velocity)
    for payload in (rows_frame("A", "B", False, rows), encode(rows_body("A", "B", False, rows))):
        got, data = decode_rows(payload, KEY)
        assert (got.source_a, got.source_b, got.reference) == ("A", "B", False)
        _same_rows(data, rows)


def _rows_cases() -> list[tuple[str, bytes]]:
    rows = _rows(4)
    good = rows_frame("A", "B", True, rows)
    header, body = decode_frame(good)
    cols = {
        name: np.frombuffer(body, "<f8", 4 * width, at).copy()
        for name, width, at in (("p_a", 3, 0), ("p_b", 3, 96), ("s", 9, 192), ("v", 3, 480))
    }
    ids = body[576:]
    cases = [("valid", good)]

    def variant(name: str, change: Change) -> None:
        h, c = json.loads(json.dumps(header)), {k: v.copy() for k, v in cols.items()}
        change(h, c)
        cases.append((name, encode_frame(h, b"".join(v.tobytes() for v in c.values()) + ids)))

    def col(name: str, at: int, value: float) -> Change:
        return lambda h, c: c[name].__setitem__(at, value)

    variant("position beyond the bound", col("p_a", 2, 2e8))
    variant("position NaN", col("p_b", 0, np.nan))
    variant("covariance infinite", col("s", 5, np.inf))
    variant("velocity NaN", col("v", 1, np.nan))
    variant("reference not a boolean", lambda h, c: h.__setitem__("reference", [1]))
    variant("time far", lambda h, c: h.__setitem__("time_s", 1e12))
    variant("a column left out", lambda h, c: (h["binary"].remove("p_b"), c.pop("p_b")))
    cases.append(("body one byte short", good[:-1]))
    return cases


@pytest.mark.parametrize(("name", "payload"), _rows_cases(), ids=[c[0] for c in _rows_cases()])
def test_a_rows_frame_is_read_whole_or_rejected(name: str, payload: bytes) -> None:
    try:
        got, data = decode_rows(payload, KEY)
    except RejectionError:
        assert name != "valid", name
        return
    assert name == "valid", name
    assert got.reference is True
    _same_rows(data, _rows(4))


def test_worker_1_takes_a_reference_pair_s_rows_before_it_has_heard_the_reference() -> None:
    """A pair of a radar and a reference source is its radar owner's, whatever its name hashes
    to.  Worker 1, which solves the biases, takes the rows that owner sends even before it has
    taken a batch of the reference itself (started later, say): it must not read the pair as
    its own by the name's hash and drop them unread."""
    from service.schema_files import EXAMPLES

    partition = Partition(1, 2)
    engine = Engine(EngineConfig(partition=partition))
    radar, ref = next(
        (f"R{i}", f"ref{j}")
        for i in range(50)
        for j in range(50)
        if not partition.owns(f"R{i}") and partition.owns_pair(f"R{i}", f"ref{j}")
    )
    site = {**EXAMPLES["RadarSite"], "radar_id": radar}
    assert engine.ingest(Keys("fusion").site(radar), json.dumps(site).encode()) == []
    rows = rows_frame(radar, ref, True, _rows(5))
    assert engine.ingest(Keys("fusion").registration(radar, ref), rows) == []
    assert engine.rejected == {}
    stage = engine.correlation.stage  # type: ignore[attr-defined]
    assert (radar, ref) in stage.mirrors and len(stage.mirrors[(radar, ref)].memory) > 0
    engine.close()


def test_a_registration_with_a_number_not_finite_is_not_taken_so_its_links_go_without_it() -> None:
    """The wire takes finite numbers only: a pair whose registration holds another sends its
    links alone (a peer would reject the whole message, and the picture and cycles lose the
    pair)."""

    class Solved:
        radar_ids = ("A", "B")
        terms = np.zeros((2, 5))
        relative_covariance = np.eye(10)

    class Pair:
        registered = True
        solution = Solved()

    assert PairRegistration.of(Pair()) is not None
    Solved.relative_covariance = np.where(np.eye(10) > 0, np.inf, 0.0)
    assert PairRegistration.of(Pair()) is None
    Solved.relative_covariance, Solved.terms = np.eye(10), np.full((2, 5), np.nan)
    assert PairRegistration.of(Pair()) is None
