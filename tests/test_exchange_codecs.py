"""The partitioned workers' track states as frames, and a change applied to a table, each
against its plain form (the JSON form's rules, a whole sort); how a frame is put on Zenoh."""

from __future__ import annotations

import json
import queue
import struct
from collections.abc import Callable
from typing import Any

import numpy as np
import pytest
import zenoh

from service.engine import Engine, EngineConfig
from service.pipeline.errors import RejectionError
from service.pipeline.partition import Partition
from service.pipeline.track_exchange import StatesSender, apply_change, decode_states, states_frame
from service.tracking.base import TrackTable
from service.transport.publisher import Publisher
from service.wire.frames import MAGIC, decode_frame, encode_frame
from service.wire.keys import Keys
from service.wire.outgoing import Outgoing
from service.wire.outputs import encode
from tests.support import random_track_table

_BINARY = ("plots", "time_s", "position_ecef_m", "velocity_ecef_mps", "covariance", "quality", "confirmed")
_TYPES = {"plots": "<i8", "confirmed": "|u1"}


def _table(n: int = 6, quality: bool = True) -> TrackTable:
    t = random_track_table(np.random.default_rng(3), [f"A-{i}" for i in range(n)])
    if quality:
        t.quality[:] = np.linspace(0.1, 0.9, n)
        t.quality[0] = np.nan  # a null among them
    else:
        t.quality[:] = np.nan
    return t


def _parts(table: TrackTable) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """A frame's header and binary columns, as the sender makes them, to be altered."""
    header, body = decode_frame(states_frame(StatesSender().states("A", table, 1000.0, "frame")))
    cols, at = {}, 0
    for name in header["tracks"]["binary"]:
        dtype = np.dtype(_TYPES.get(name, "<f8"))
        width = {"position_ecef_m": 3, "velocity_ecef_mps": 3, "covariance": 36}.get(name, 1)
        cols[name] = np.frombuffer(body, dtype=dtype, count=len(table) * width, offset=at).copy()
        at += cols[name].nbytes
    return header, cols


def _frame(header: dict[str, Any], cols: dict[str, np.ndarray]) -> bytes:
    """The frame of ``header`` with the columns ``cols`` in the body, in layout order."""
    return encode_frame(header, b"".join(cols[name].tobytes() for name in _BINARY if name in cols))


def _frame_cases() -> list[tuple[str, bytes]]:
    """Valid frames and hostile ones (wrong layout, bad numbers, broken framing)."""
    good_header, good_cols = _parts(_table())
    cases = [("valid", _frame(good_header, good_cols))]
    bare_header, bare_cols = _parts(_table(quality=False))
    cases.append(("valid without quality", _frame(bare_header, bare_cols)))

    def variant(name: str, change: Callable[[dict[str, Any], dict[str, np.ndarray]], None]) -> None:
        header, cols = json.loads(json.dumps(good_header)), {k: v.copy() for k, v in good_cols.items()}
        change(header, cols)
        cases.append((name, _frame(header, cols)))

    def put(path: str, value: object) -> Callable[[dict[str, Any], dict[str, np.ndarray]], None]:
        def change(header: dict[str, Any], cols: dict[str, np.ndarray]) -> None:
            *parents, last = path.split(".")
            node = header
            for p in parents:
                node = node[p]
            node[last] = value

        return change

    Change = Callable[[dict[str, Any], dict[str, np.ndarray]], None]

    def number(name: str, value: float, at: int = 0) -> Change:
        def change(header: dict[str, Any], cols: dict[str, np.ndarray]) -> None:
            cols[name][at] = value

        return change

    variant("covariance NaN", number("covariance", np.nan, 7))
    variant("covariance infinite", number("covariance", np.inf))
    variant("position far", number("position_ecef_m", 1e9, 2))
    variant("velocity far", number("velocity_ecef_mps", -1e9))
    variant("time negative", number("time_s", -1.0))
    variant("time far", number("time_s", 1e12))
    variant("time NaN", number("time_s", np.nan))
    variant("plots negative", number("plots", -1))
    variant("quality above one", number("quality", 1.5, 1))
    variant("confirmed not 0 or 1", number("confirmed", 2))
    variant("columns out of order", put("tracks.binary", list(reversed(good_header["tracks"]["binary"]))))
    variant("a column missing", put("tracks.binary", [x for x in _BINARY if x != "plots"]))
    variant("a binary column repeated as JSON", put("tracks.time_s", [1.0] * 6))
    variant("ids not strings", put("tracks.track_id", list(range(6))))
    variant("more ids than rows", put("tracks.track_id", [f"A-{i}" for i in range(7)]))
    variant("tracks not an object", put("tracks", [1, 2]))
    variant("seq negative", put("seq", -1))
    variant("time string", put("time_s", "now"))
    variant("bad radar id", put("radar_id", "a b"))
    variant("label wrong length", put("tracks.mode_s", ["abc"]))
    good = cases[0][1]
    cases.append(("body one byte short", good[:-1]))
    cases.append(("body one byte long", good + b"\0"))
    cases.append(("header longer than the frame", good[:4] + struct.pack("<I", len(good)) + good[8:]))
    cases.append(("header not aligned", MAGIC + struct.pack("<I", 3) + b"{} " + b"\0" * 8))
    cases.append(("header not JSON", MAGIC + struct.pack("<I", 8) + b"{{{{{{{{"))
    cases.append(("header not an object", encode_frame([1, 2, 3], b"")))  # type: ignore[arg-type]
    cases.append(("magic alone", MAGIC))
    return cases


@pytest.mark.parametrize(("name", "payload"), _frame_cases(), ids=[c[0] for c in _frame_cases()])
def test_a_frame_is_read_whole_or_rejected(name: str, payload: bytes) -> None:
    try:
        got = decode_states(payload, "A")
    except RejectionError:
        assert not name.startswith("valid"), name
        return
    assert name.startswith("valid"), name
    want = _table(quality=name == "valid")
    for field in ("track_id", "confirmed", "time_s", "position_ecef_m", "velocity_ecef_mps", "plots"):
        a, b = getattr(got.rows, field), getattr(want, field)
        assert a.dtype.kind == b.dtype.kind and np.array_equal(a, b), field
    assert got.rows.covariance.tobytes() == want.covariance.tobytes()
    assert np.array_equal(got.rows.quality, want.quality, equal_nan=True)
    assert got.rows.mode_s.tolist() == want.mode_s.tolist()


def test_every_form_of_a_table_reads_back_the_same_message() -> None:
    table = _table(40)
    msgs = []
    for form in ("numbers", "packed", "frame"):
        body = StatesSender().states("A", table, 1234.5, form)
        payload = states_frame(body) if form == "frame" else encode(body)
        msgs.append(decode_states(payload, "A"))
    for m in msgs[1:]:
        assert (m.radar_id, m.seq, m.time_s, m.full, m.count, m.expiry) == (
            msgs[0].radar_id,
            msgs[0].seq,
            msgs[0].time_s,
            msgs[0].full,
            msgs[0].count,
            msgs[0].expiry,
        )
        assert m.rows.covariance.tobytes() == msgs[0].rows.covariance.tobytes()
        assert m.rows.track_id.tolist() == msgs[0].rows.track_id.tolist()
    # the frame is the smallest: raw doubles, where packed columns are base64 (4 bytes for 3)
    sizes = [len(states_frame(StatesSender().states("A", table, 1.0, "frame")))]
    sizes.append(len(encode(StatesSender().states("A", table, 1.0, "packed"))))
    assert sizes[0] < 0.85 * sizes[1]


def test_a_change_of_updated_rows_only_is_applied_as_a_whole_sort_would() -> None:
    rng = np.random.default_rng(8)
    base = random_track_table(rng, [f"A-{i:03d}" for i in range(50)]).by_id()
    for pick in ([3], [0, 49], list(range(0, 50, 7)), []):
        rows = random_track_table(rng, [f"A-{i:03d}" for i in pick]).by_id()
        got = apply_change(base, rows, np.empty(0, dtype=str))
        keep = ~np.isin(base.track_id, rows.track_id)
        want = TrackTable.concat([base.take(keep), rows]).by_id()  # the plain form
        for field in ("track_id", "confirmed", "time_s", "position_ecef_m", "covariance", "plots", "mode_s"):
            assert np.array_equal(getattr(got, field), getattr(want, field)), field
        assert np.array_equal(got.quality, want.quality, equal_nan=True)
        assert got.covariance is not base.covariance  # (a new table: the base is not changed)


def test_a_broken_frame_from_another_worker_is_rejected_counted_and_reported() -> None:
    partition = Partition(1, 2)
    engine = Engine(EngineConfig(partition=partition))
    radar = next(f"R{i}" for i in range(50) if not partition.owns(f"R{i}"))
    payload = states_frame(StatesSender().states(radar, _table(), 1000.0, "frame"))
    out = engine.ingest(Keys("fusion").track_states(radar), payload[:-3])
    assert engine.rejected == {"schema": 1}
    assert [o.key for o in out] == ["fusion/errors"]
    assert b"track states" in out[0].payload
    engine.close()


def test_a_frame_is_put_as_octets_and_json_as_json(client: zenoh.Session) -> None:
    """Through a router: the publisher puts a track-states frame with the encoding of raw
    bytes, a JSON payload with its publisher's JSON, each byte for byte."""
    keys = Keys("fusion")
    got: queue.Queue[tuple[str, bytes]] = queue.Queue()
    sub = client.declare_subscriber(
        "fusion/radar/*/track-states", lambda s: got.put((str(s.encoding), s.payload.to_bytes()))
    )
    publisher = Publisher(keys, outbox_size=8)
    publisher.start(client)
    try:
        frame = states_frame(StatesSender().states("A", _table(), 1000.0, "frame"))
        json_body = StatesSender().states("B", _table(), 1000.0, "packed")
        publisher.hand(
            [
                Outgoing(keys.track_states("A"), lambda: {}, lambda: frame),
                Outgoing(keys.track_states("B"), lambda: json_body),
            ]
        )
        first, second = got.get(timeout=10), got.get(timeout=10)
    finally:
        publisher.stop(5.0)
        sub.undeclare()
    assert first == (str(zenoh.Encoding.APPLICATION_OCTET_STREAM), frame)
    assert second == (str(zenoh.Encoding.APPLICATION_JSON), encode(json_body))
