"""Track states between partitioned workers: the owner sends what changed, peers rebuild.

A worker that correlates a pair whose radars it does not track needs those radars' track
tables exactly as their owner's correlation would see them: the same rows, bit for bit, in the
same (canonical, :meth:`TrackTable.by_id`) order, at the same data times.  The owner publishes
one ``TrackStates`` per released table on ``{prefix}/radar/{id}/track-states``:

* ``full``: the whole table, at a radar's first table and then at least once per
  ``full_interval_s`` of data time, so that a worker that starts late or lost a message is
  whole again by then;
* otherwise the rows that differ from the previous table (new tracks and updated ones: a
  radar's batch covers a sector of its scan, so about a tenth of its tracks) and the ids that
  left.  ``count`` is the size of the table after the change, a check.

Floats travel as JSON numbers in their shortest round-trip form, packed (the doubles
themselves in base64, :mod:`service.wire.packed`), or the whole message as a frame (a JSON
header with the ids and labels, the numbers as raw columns behind it, :mod:`service.wire.frames`),
each once every other worker has said it reads it (:attr:`ExchangeParams.packed`,
:attr:`ExchangeParams.frames`); every form rebuilds the owner's table bit for bit.  A receiver
applies a change only on top of the table of ``seq - 1``; after a gap (a lost message, a
restarted owner) it waits for the next full table and counts the gap.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
import orjson
from numpy.typing import NDArray

from service.columns import put_rows, row_bits
from service.correlation.pairkeys import isin_sorted
from service.pipeline.decode import list_of
from service.pipeline.errors import RejectionError
from service.tracking.base import TrackTable
from service.wire.frames import decode_frame, encode_frame, is_frame
from service.wire.models import MAX_ECEF_M, MAX_TIME_S, MAX_TRACKS
from service.wire.outputs import nullable
from service.wire.packed import pack_floats, unpack_floats
from service.wire.vocabulary import is_source_id

#: The label columns a table carries besides its state (sent only when one is set).
LABELS = ("truth_id", "mode_3a", "mode_s")


#: How a ``TrackStates`` goes: JSON numbers, packed float columns, or a frame.
StatesForm = Literal["numbers", "packed", "frame"]


@dataclass(frozen=True)
class ExchangeParams:
    """How track states are sent between partitioned workers."""

    #: A radar's whole table is sent at least once per this many data seconds (and with its
    #: first table).  A change costs about a tenth of a whole table; a whole table once a
    #: minute bounds how long a worker that lost a message lacks that radar.
    full_interval_s: float = 60.0
    #: A worker's progress and radar clocks are sent to the others once they moved this much
    #: data time (s), and whenever it is idle.  They only pace the others' merge: coarser
    #: means a little more latency, never another result.
    step_s: float = 1.0
    #: Whether this worker reads track states with packed float columns, says so in its
    #: progress, and packs its own once every other worker has said it reads them
    #: (:mod:`service.wire.packed`: the same tables, bit for bit, a fraction of the JSON
    #: numbers' parsing).  Off: JSON numbers only, both ways (a worker of a version before
    #: packing never says it reads them, so it is never sent any).
    packed: bool = True
    #: Whether this worker reads track states as frames (:mod:`service.wire.frames`: the
    #: numbers as raw columns, no base64 and no JSON to parse them from), says so in its
    #: progress, and sends its own so once every other worker has said it reads them; else
    #: packed or numbers as :attr:`packed` says.  The same tables, bit for bit, in three
    #: quarters of the packed form's bytes and a fraction of its decoding.  The same for a
    #: pair's links and registration rows (:mod:`.pair_exchange`: JSON otherwise).
    frames: bool = True

    def form(self, reads_frames: bool, reads_packed: bool) -> StatesForm:
        """The form to send in, given whether every other worker reads frames and packed
        columns."""
        if self.frames and reads_frames:
            return "frame"
        return "packed" if self.packed and reads_packed else "numbers"


def _positions(ids: NDArray[np.str_], query: NDArray[np.str_]) -> NDArray[np.intp]:
    """Where each ``query`` id would sit in ``ids`` (a table's ids, in canonical order: sorted,
    so one binary search; unsorted ids are sorted first), clipped to a valid row."""
    order = None if bool(np.all(ids[1:] >= ids[:-1])) else np.argsort(ids, kind="stable")
    pos = np.minimum(np.searchsorted(ids, query, sorter=order), len(ids) - 1)
    return pos if order is None else order[pos]


def changed_rows(old: TrackTable, new: TrackTable) -> tuple[np.ndarray, np.ndarray]:
    """Rows of ``new`` that are not in ``old`` exactly (a mask), and the ids of ``old`` that
    are not in ``new``.  Floats are compared by their bits: a NaN equals the same NaN and
    ``-0.0`` differs from ``0.0``, so that a table rebuilt from the change is the same, bit for
    bit."""
    n = len(new)
    if len(old) == 0:
        return np.ones(n, dtype=bool), np.empty(0, dtype=str)
    pos = _positions(old.track_id, new.track_id)
    known = old.track_id[pos] == new.track_id
    same = known & (old.confirmed[pos] == new.confirmed)
    same &= old.plots[pos] == new.plots
    before = row_bits([(getattr(old, name), width) for name, width in _FLOATS])[pos]
    same &= np.all(before == row_bits([(getattr(new, name), width) for name, width in _FLOATS]), axis=1)
    for name in LABELS:
        same &= getattr(old, name)[pos] == getattr(new, name)
    kept = np.zeros(len(old), dtype=bool)
    kept[pos[known]] = True
    return ~same, old.track_id[~kept]


#: A table's float columns and their values per row.
_FLOATS = (
    ("time_s", 1),
    ("position_ecef_m", 3),
    ("velocity_ecef_mps", 3),
    ("covariance", 36),
    ("quality", 1),
)


def states_body(
    radar_id: str,
    seq: int,
    time_s: float,
    table: TrackTable,
    full: bool,
    removed: np.ndarray,
    count: int,
    form: StatesForm = "numbers",
) -> dict[str, Any]:
    """The ``TrackStates`` payload of ``table``'s rows (numpy columns: encoded as they are;
    ``packed``: the float columns packed, :mod:`service.wire.packed`; ``frame``: numpy columns,
    ``quality`` with NaN for null, for :func:`states_frame`)."""
    n = len(table)
    packed = form == "packed"
    floats = {
        "time_s": np.ascontiguousarray(table.time_s, dtype=float),
        "position_ecef_m": np.ascontiguousarray(table.position_ecef_m, dtype=float),
        "velocity_ecef_mps": np.ascontiguousarray(table.velocity_ecef_mps, dtype=float),
        "covariance": np.ascontiguousarray(table.covariance, dtype=float).reshape(n, 36),
    }
    columns: dict[str, Any] = {
        "track_id": table.track_id.tolist(),
        "confirmed": np.ascontiguousarray(table.confirmed),
        **({k: pack_floats(v) for k, v in floats.items()} if packed else floats),
        "plots": np.ascontiguousarray(table.plots, dtype=np.int64),
    }
    for name in LABELS:
        labels = getattr(table, name).tolist()
        if any(x is not None for x in labels):
            columns[name] = labels
    if np.isfinite(table.quality).any():
        q = table.quality
        columns["quality"] = pack_floats(q) if packed else q if form == "frame" else nullable(q)
    return {
        "radar_id": radar_id,
        "seq": seq,
        "time_s": time_s,
        "full": full,
        "count": count,
        "removed": removed.tolist(),
        "tracks": columns,
    }


#: A frame's binary columns in the order of its body: name, numbers per track, type.
#: ``quality`` is there only when the header's ``tracks.binary`` lists it; ``confirmed`` (one
#: byte, 0 or 1) comes last so that every column of eight-byte numbers stays aligned.
_FRAME_COLUMNS = (
    ("plots", 1, "<i8"),
    ("time_s", 1, "<f8"),
    ("position_ecef_m", 3, "<f8"),
    ("velocity_ecef_mps", 3, "<f8"),
    ("covariance", 36, "<f8"),
    ("quality", 1, "<f8"),
    ("confirmed", 1, "|u1"),
)
#: The two layouts a frame's ``tracks.binary`` may name: every column, or all but ``quality``.
_FRAME_LAYOUTS = (
    [name for name, _, _ in _FRAME_COLUMNS],
    [name for name, _, _ in _FRAME_COLUMNS if name != "quality"],
)


def states_frame(body: dict[str, Any]) -> bytes:
    """A ``TrackStates`` frame of ``body`` (:func:`states_body` with ``form="frame"``): the
    header is ``body`` with ``tracks`` holding the ids and labels and, in ``binary``, the names
    of the columns in the body, which holds them (:data:`_FRAME_COLUMNS`)."""
    cols = body["tracks"]
    names = [name for name, _, _ in _FRAME_COLUMNS if name in cols]
    header = {
        **body,
        "tracks": {**{k: v for k, v in cols.items() if k not in names}, "binary": names},
    }
    types = {name: dtype for name, _, dtype in _FRAME_COLUMNS}
    return encode_frame(
        header, b"".join(np.ascontiguousarray(cols[name], dtype=types[name]).tobytes() for name in names)
    )


def apply_change(base: TrackTable, rows: TrackTable, removed: np.ndarray) -> TrackTable:
    """``base`` with ``rows`` put in (new or changed) and the ids ``removed`` taken out, in
    canonical order: the table :func:`changed_rows` was computed from.

    Both tables are in canonical (id) order, so the few ids of the change are found among the
    many by binary search, and the rows merged into place without sorting the whole table
    again (the many: a radar's table, about ten times a change's rows)."""
    ids, new_ids = base.track_id, rows.track_id
    if not (_ascending(ids) and _ascending(new_ids)):  # (not canonical: sort it)
        gone = isin_sorted(ids, np.concatenate([removed, new_ids]))
        return TrackTable.concat([base.take(~gone), rows]).by_id()
    kept = np.ones(len(ids), dtype=bool)
    if len(ids):
        out = np.concatenate([removed, new_ids])
        pos = np.minimum(np.searchsorted(ids, out), len(ids) - 1)
        found = ids[pos] == out
        if not len(removed) and bool(np.all(found)):  # (only tracks updated: a third of changes)
            return put_rows(base, pos, rows)
        kept[pos[found]] = False
    kept_at = np.flatnonzero(kept)
    # row j of the change goes after the kept ids below it, and after the j rows before it
    at = np.searchsorted(ids[kept_at], new_ids) + np.arange(len(new_ids))
    from_rows = np.zeros(len(kept_at) + len(new_ids), dtype=bool)
    from_rows[at] = True
    order = np.empty(len(from_rows), dtype=np.intp)
    order[from_rows] = len(ids) + np.arange(len(new_ids))
    order[~from_rows] = kept_at
    return TrackTable.concat([base, rows]).take(order)


def _ascending(ids: NDArray[np.str_]) -> bool:
    return bool(np.all(ids[1:] > ids[:-1]))


@dataclass(frozen=True)
class StatesMessage:
    """A decoded ``TrackStates``: its fields, and its rows as a table in canonical order."""

    radar_id: str
    seq: int
    time_s: float
    full: bool
    count: int | None
    removed: np.ndarray
    expiry: bool
    rows: TrackTable


def _fail(reason: str, detail: str, radar_id: str | None) -> RejectionError:
    return RejectionError(reason, f"track states: {detail}", radar_id)  # type: ignore[arg-type]


def _column(cols: dict[str, Any], name: str, shape: tuple[int, ...], dtype: type, rid: str) -> np.ndarray:
    try:
        values = cols[name]
        a: np.ndarray = (
            unpack_floats(values, int(np.prod(shape))).reshape(shape)
            if isinstance(values, str) and dtype is float
            else np.asarray(values, dtype=dtype)
        )
    except KeyError:
        raise _fail("schema", f"tracks.{name} missing", rid) from None
    except (TypeError, ValueError):
        raise _fail("schema", f"tracks.{name}: not an array of {dtype.__name__}", rid) from None
    if a.size == 0 and shape[0] == 0:
        a = a.reshape(shape)
    if a.shape != shape:
        raise _fail("schema", f"tracks.{name}: shape {a.shape} != {shape}", rid)
    return a


def decode_states(payload: bytes, radar_id: str) -> StatesMessage:
    """Parse and check a ``TrackStates`` with the rules of its model
    (:class:`service.wire.models.TrackStates`), columns as numpy arrays: a national network
    sends hundreds a second, and the model's per-number validation costs ten times this.
    ``tests/test_partition.py`` holds the two to the same verdicts.  A frame
    (:func:`states_frame`) is held to the same rules, its binary columns to their layout."""
    if is_frame(payload):
        body, cols = _frame_parts(payload, radar_id)
    else:
        try:
            body = orjson.loads(payload)
        except orjson.JSONDecodeError as exc:
            raise _fail("malformed_json", str(exc), radar_id) from None
        if not isinstance(body, dict):  # (JSON, but not the object a message needs: §2.8)
            raise _fail("malformed_json", "not a JSON object", radar_id)
        if not isinstance(body.get("tracks"), dict):
            raise _fail("schema", "not an object with a tracks object", radar_id)
        cols = body["tracks"]
    rid, seq, full = body.get("radar_id"), body.get("seq"), body.get("full")
    time_s: Any = body.get("time_s")
    count, removed, expiry = body.get("count"), body.get("removed", []), body.get("expiry", False)
    if not isinstance(rid, str) or not is_source_id(rid):
        raise _fail("schema", "radar_id", radar_id)
    if type(seq) is not int or not 0 <= seq <= 2**63 - 1:
        raise _fail("schema" if type(seq) is not int else "out_of_range", "seq", radar_id)
    number = type(time_s) in (int, float)  # (a JSON number: not true or false, not a string)
    if not number or not np.isfinite(time_s) or not 0 <= time_s <= MAX_TIME_S:
        raise _fail("out_of_range" if number else "schema", "time_s", radar_id)
    if type(full) is not bool or type(expiry) is not bool:
        raise _fail("schema", "full/expiry must be booleans", radar_id)
    if count is not None and (type(count) is not int or not 0 <= count <= MAX_TRACKS):
        raise _fail("schema", "count", radar_id)
    if not list_of(removed, str) or len(removed) > MAX_TRACKS:
        raise _fail("schema", "removed must be a list of ids", radar_id)
    ids: Any = cols.get("track_id")
    if not list_of(ids, str):
        raise _fail("schema", "tracks.track_id must be a list of strings", radar_id)
    n = len(ids)
    if n > MAX_TRACKS:
        raise _fail("too_large", f"{n} tracks > {MAX_TRACKS}", radar_id)
    if not isinstance(cols.get("confirmed"), np.ndarray):  # (a frame's are typed by its layout)
        _check_list_columns(cols, radar_id)
    c = _column(cols, "confirmed", (n,), bool, radar_id)
    t = _column(cols, "time_s", (n,), float, radar_id)
    pos = _column(cols, "position_ecef_m", (n, 3), float, radar_id)
    vel = _column(cols, "velocity_ecef_mps", (n, 3), float, radar_id)
    cov = _column(cols, "covariance", (n, 36), float, radar_id)
    npl = _column(cols, "plots", (n,), np.int64, radar_id)
    for name, a in (("time_s", t), ("position_ecef_m", pos), ("velocity_ecef_mps", vel), ("covariance", cov)):
        if not np.all(np.isfinite(a)):
            raise _fail("non_finite", f"tracks.{name}", radar_id)
    if np.any(t < 0) or np.any(t > MAX_TIME_S) or np.any(npl < 0):
        raise _fail("out_of_range", "tracks.time_s or tracks.plots", radar_id)
    if np.any(np.abs(pos) > MAX_ECEF_M) or np.any(np.abs(vel) > MAX_ECEF_M):
        raise _fail("out_of_range", "tracks position or velocity", radar_id)
    label = {name: _label_column(cols, name, n, radar_id) for name in LABELS}
    quality = _quality_column(cols, n, radar_id)
    rows = TrackTable(
        np.asarray(ids, dtype=str), c, t, pos, vel, cov.reshape(n, 6, 6), npl, **label, quality=quality
    ).by_id()
    return StatesMessage(rid, seq, float(time_s), full, count, np.asarray(removed, dtype=str), expiry, rows)


def _check_list_columns(cols: dict[str, Any], radar_id: str) -> None:
    """The JSON form's columns that numpy would take too leniently: booleans, integers and
    times (numbers only: not true or false, not strings)."""
    confirmed = cols.get("confirmed")
    if not list_of(confirmed, bool):
        raise _fail("schema", "tracks.confirmed must be a list of booleans", radar_id)
    plots = cols.get("plots")
    if not list_of(plots, int):
        raise _fail("schema", "tracks.plots must be a list of integers", radar_id)
    times = cols.get("time_s")
    if isinstance(times, list) and not list_of(times, int, float):
        raise _fail("schema", "tracks.time_s must be a list of numbers", radar_id)


def _frame_parts(payload: bytes, radar_id: str) -> tuple[dict[str, Any], dict[str, Any]]:
    """A frame's header and its columns: the header's ``tracks`` (ids, labels) with the body's
    binary columns as numpy arrays, checked against :data:`_FRAME_COLUMNS`."""
    try:
        body, data = decode_frame(payload)
    except ValueError as exc:
        raise _fail("schema", str(exc), radar_id) from None
    cols = body.get("tracks") if isinstance(body, dict) else None
    if not isinstance(cols, dict) or not isinstance(cols.get("track_id"), list):
        raise _fail("schema", "not a frame with a tracks object of track ids", radar_id)
    names = cols.get("binary")
    layout = _FRAME_LAYOUTS[0]
    if names not in _FRAME_LAYOUTS:
        raise _fail("schema", f"tracks.binary must be {layout}, quality optional", radar_id)
    if any(name in cols for name in layout):
        raise _fail("schema", "a frame's tracks must not repeat its binary columns", radar_id)
    n = len(cols["track_id"])
    spec = [(name, width, np.dtype(dtype)) for name, width, dtype in _FRAME_COLUMNS if name in names]
    size = sum(n * width * dtype.itemsize for _, width, dtype in spec)
    if len(data) != size:
        raise _fail("schema", f"a body of {len(data)} bytes, {size} for {n} tracks", radar_id)
    out = {k: v for k, v in cols.items() if k != "binary"}
    at = 0
    for name, width, dtype in spec:
        a = np.frombuffer(data, dtype=dtype, count=n * width, offset=at).astype(dtype.newbyteorder("="))
        at += a.nbytes
        out[name] = a.reshape((n, width) if width > 1 else (n,))
    if not np.all(out["confirmed"] <= 1):
        raise _fail("schema", "tracks.confirmed must be bytes 0 or 1", radar_id)
    out["confirmed"] = out["confirmed"].astype(bool)
    return body, out


def _label_column(cols: dict[str, Any], name: str, n: int, radar_id: str) -> np.ndarray:
    """An optional label column (strings or nulls), all None when left out."""
    out = np.full(n, None, dtype=object)
    labels = cols.get(name)
    if labels is not None:
        if not list_of(labels, str, type(None)) or len(labels) != n:
            raise _fail("schema", f"tracks.{name}", radar_id)
        out[:] = labels
    return out


def _quality_column(cols: dict[str, Any], n: int, radar_id: str) -> np.ndarray:
    """The optional ``quality`` column (numbers in [0, 1] or nulls), NaN where null or left out."""
    out = np.full(n, np.nan)
    values = cols.get("quality")
    if values is None:
        return out
    if isinstance(values, (str, np.ndarray)):  # packed or a frame's: NaN for null
        try:
            out = values if isinstance(values, np.ndarray) else unpack_floats(values, n)
        except ValueError:
            raise _fail(
                "schema", "tracks.quality: not a packed column of one number per track", radar_id
            ) from None
        if not np.all(np.isnan(out) | ((out >= 0.0) & (out <= 1.0))):
            raise _fail("schema", "tracks.quality must be numbers in [0, 1] or nulls", radar_id)
        return out
    if (
        not isinstance(values, list)
        or len(values) != n
        or not all(x is None or (type(x) in (int, float) and 0.0 <= x <= 1.0) for x in values)
    ):
        raise _fail("schema", "tracks.quality must be numbers in [0, 1] or nulls", radar_id)
    out[:] = [np.nan if x is None else float(x) for x in values]
    return out


class StatesSender:
    """The owner's side: one ``TrackStates`` body per released table of each radar."""

    def __init__(self, params: ExchangeParams | None = None) -> None:
        self.params = params or ExchangeParams()
        # radar -> (seq of the last message, its table, data time of the last full table,
        # its form)
        self._sent: dict[str, tuple[int, TrackTable, float, StatesForm]] = {}

    def states(
        self, radar_id: str, table: TrackTable, time_s: float, form: StatesForm = "numbers"
    ) -> dict[str, Any]:
        """The message for ``table`` (canonical order) at data time ``time_s`` in ``form``
        (:func:`states_body`).  A change of form sends the whole table: a worker that could not
        read the last form is whole again at once."""
        last = self._sent.get(radar_id)
        full = (
            last is None or not (last[2] <= time_s < last[2] + self.params.full_interval_s) or last[3] != form
        )
        seq = 1 if last is None else last[0] + 1
        if full or last is None:
            body = states_body(radar_id, seq, time_s, table, True, np.empty(0, dtype=str), len(table), form)
            full_s = time_s
        else:
            changed, removed = changed_rows(last[1], table)
            body = states_body(radar_id, seq, time_s, table.take(changed), False, removed, len(table), form)
            full_s = last[2]
        self._sent[radar_id] = (seq, table, full_s, form)
        return body

    def forget(self, radar_id: str) -> None:
        self._sent.pop(radar_id, None)


class StatesReceiver:
    """A peer's side: every remote radar's table, rebuilt from the owner's messages."""

    def __init__(self) -> None:
        self._tables: dict[str, tuple[int, TrackTable, float]] = {}
        #: Messages that could not be applied (a gap before them), per radar.
        self.gaps: Counter[str] = Counter()

    def apply(self, msg: StatesMessage) -> TrackTable | None:
        """The radar's table after ``msg``; None when it cannot be applied (counted)."""
        rows = msg.rows
        held = self._tables.get(msg.radar_id)
        if msg.full:
            table = rows
        elif held is None or held[0] != msg.seq - 1:
            self.gaps[msg.radar_id] += 1
            self._tables.pop(msg.radar_id, None)
            return None
        else:
            table = apply_change(held[1], rows, msg.removed)
        if msg.count is not None and len(table) != msg.count:
            self.gaps[msg.radar_id] += 1
            self._tables.pop(msg.radar_id, None)
            return None
        self._tables[msg.radar_id] = (msg.seq, table, msg.time_s)
        return table

    def latest(self, radar_id: str) -> tuple[float, TrackTable]:
        """The data time and table of the last message applied (an empty table if none)."""
        held = self._tables.get(radar_id)
        return (held[2], held[1]) if held else (0.0, TrackTable.empty())

    def radars(self) -> list[str]:
        return sorted(self._tables)

    def forget(self, radar_id: str) -> None:
        self._tables.pop(radar_id, None)
