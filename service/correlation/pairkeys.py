"""Keys of tracks and of track pairs, and the set operations the books do on them (numpy, no
loops).

A book identifies a track by an identifier of either kind, the same kind throughout: its track
id (a string), or the integer key :class:`TrackKeys` gives it.  The correlation uses the keys:
sorting, searching and comparing int64 is four to six times faster than the same on track ids
(numpy compares strings character by character), and these operations run on every update.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

#: Separates the two track ids of a string key (a control character: no track id contains it).
SEP = "\x1f"

#: Track keys count from 0 to below this, then start again at 0 (:class:`TrackKeys`): a pair's
#: key puts its A key above 32 bits, so each must stay below 2**31.
KEY_LIMIT = 1 << 31


def pair_keys(a: NDArray[Any], b: NDArray[Any]) -> NDArray[Any]:
    """One key per pair ``(a[k], b[k])``: ``a * 2**32 + b`` for track keys (int64), the two
    ids joined by :data:`SEP` for track ids (strings)."""
    a, b = np.asarray(a), np.asarray(b)
    if a.dtype.kind in "iu" and b.dtype.kind in "iu":
        return np.asarray(a.astype(np.int64) << 32 | b.astype(np.int64))
    return np.char.add(np.char.add(a.astype(str), SEP), b.astype(str))


def joined(old: NDArray[Any], new: NDArray[Any]) -> NDArray[Any]:
    """``old`` then ``new``: a book's column grown by new rows (an empty column takes the new
    rows as they are, so a book takes whichever kind of identifier it is given first)."""
    return np.asarray(new) if old.shape[0] == 0 else np.concatenate([old, new])


class TrackKeys:
    """Integer keys for the tracks of one source's tables, in the order the correlation reads them.

    A track keeps its key from table to table while it is in them; a track id not in the last
    table given gets a new key, counted up from 0 (modulo :data:`KEY_LIMIT`).  Only the last
    table's ids are remembered: memory as one table, one search of its ids a table.  A track
    that left the table leaves the pair book and the evidence at their next check against a
    table (its key is absent from every later one); an id that came back after a table without
    it would be a new track to them (trackers never reuse an id; a reference source's table
    leaves out a track not heard from lately, which may come back: each of its pairs keys it
    alone, so that only a pair that saw it absent pairs it afresh).  Keys come round again
    after 2**31 new tracks of one source, far beyond the life of any book entry.
    """

    def __init__(self) -> None:
        self._ids: NDArray[np.str_] = np.empty(0, dtype=str)  # the last table's ids, ascending
        self._keys: NDArray[np.int64] = np.empty(0, dtype=np.int64)  # their keys
        self._next = 0
        self._last: tuple[NDArray[np.str_], NDArray[np.int64]] | None = None

    def of(self, ids: NDArray[np.str_]) -> NDArray[np.int64]:
        """The key of each of ``ids`` (a table's track ids, unique), row for row."""
        if self._last is not None and self._last[0] is ids:
            return self._last[1]  # (the same table again: a decision, then the pair's update)
        ids = np.asarray(ids)
        at = find(self._ids, ids)
        known = at >= 0
        keys = np.empty(ids.shape[0], dtype=np.int64)
        keys[known] = self._keys[at[known]]
        fresh = np.flatnonzero(~known)
        keys[fresh] = (self._next + np.arange(fresh.shape[0])) % KEY_LIMIT
        self._next = (self._next + int(fresh.shape[0])) % KEY_LIMIT
        if is_ascending(ids):
            self._ids, self._keys = ids, keys
        else:
            order = np.argsort(ids)
            self._ids, self._keys = ids[order], keys[order]
        self._last = (ids, keys)
        return keys


#: Track ids of at most this many characters, each at most U+00FF, have an integer code
#: (:func:`comparable`): one byte a character in a uint64.
CODE_CHARS = 8


def id_codes(ids: NDArray[Any]) -> NDArray[np.uint64] | None:
    """Each track id as an integer that sorts, searches and compares as the id does, or None
    when an id is longer than :data:`CODE_CHARS` or holds a character beyond U+00FF.

    The code is the id's characters as bytes, big-endian and zero-padded to 8: integers compare
    as their bytes do, and numpy compares strings as their characters zero-padded to the
    longest (a string holds no trailing NUL), so every comparison, and with it every sort and
    search, comes out the same on the codes as on the ids."""
    ids = np.asarray(ids)
    if ids.dtype.kind != "U":
        return None
    n, width = ids.shape[0], ids.dtype.itemsize // 4
    if width > CODE_CHARS:
        return None
    chars = np.ascontiguousarray(ids).view(np.uint32).reshape(n, width)
    if width and bool((chars > 0xFF).any()):
        return None
    packed = np.zeros((n, CODE_CHARS), dtype=np.uint8)
    packed[:, :width] = chars
    return packed.view(">u8").reshape(n).astype(np.uint64)


def comparable(*columns: NDArray[Any]) -> tuple[NDArray[Any], ...]:
    """The columns of track ids as their integer codes (:func:`id_codes`: numpy sorts,
    searches and compares them several times faster than strings), all of them or none (as
    they are): a search of one column in another must see both alike."""
    codes = [id_codes(c) for c in columns]
    if any(c is None for c in codes):
        return columns
    return tuple(c for c in codes if c is not None)


def find(keys: NDArray[Any], query: NDArray[Any]) -> NDArray[np.intp]:
    """Index of each ``query`` key in ``keys`` (unique), -1 where absent (one search, after one
    sort unless ``keys`` is sorted already, as a track table's ids are; ids searched as their
    integer codes where they have them, :func:`comparable`)."""
    if len(keys) == 0 or len(query) == 0:
        return np.full(len(query), -1, dtype=np.intp)
    if np.asarray(keys).dtype.kind == "U":
        keys, query = comparable(np.asarray(keys), np.asarray(query))
    if is_ascending(keys):
        idx = np.minimum(np.searchsorted(keys, query), len(keys) - 1)
    else:
        order = np.argsort(keys)
        idx = order[np.minimum(np.searchsorted(keys, query, sorter=order), len(keys) - 1)]
    return np.where(keys[idx] == query, idx, -1).astype(np.intp)


def is_ascending(y: NDArray[Any]) -> bool:
    """Whether ``y`` is sorted (one comparison pass)."""
    return y.shape[0] < 2 or bool(np.all(y[1:] >= y[:-1]))


def ascending(y: NDArray[Any]) -> NDArray[Any]:
    """``y`` sorted: as it is when it already is (a track table's ids are: one comparison pass
    instead of a sort)."""
    y = np.asarray(y)
    return y if is_ascending(y) else np.sort(y)


def isin_sorted(x: NDArray[Any], y: NDArray[Any]) -> NDArray[np.bool_]:
    """``np.isin(x, y)`` for keys or ids by one sort of ``y`` (none when it is sorted already)
    and a binary search (``np.isin`` sorts both sides and their union; this is the books' most
    frequent operation; ids as their integer codes where they have them, :func:`comparable`)."""
    x, y = np.asarray(x), np.asarray(y)
    if x.shape[0] == 0 or y.shape[0] == 0:
        return np.zeros(x.shape[0], dtype=bool)
    if y.dtype.kind == "U":
        x, y = comparable(x, y)
    ys = ascending(y)
    pos = np.minimum(np.searchsorted(ys, x), ys.shape[0] - 1)
    return np.asarray(ys[pos] == x)


def isin_few(x: NDArray[Any], y: NDArray[Any]) -> NDArray[np.bool_]:
    """``np.isin(x, y)`` for a few ``x`` among many ``y`` (a book's new pairs against the whole
    book): the few are sorted and every ``y`` searched among them, then each ``x`` among the
    ``y`` found, so the many are never sorted (:func:`isin_sorted` sorts ``y`` unless it is)."""
    x, y = np.asarray(x), np.asarray(y)
    if x.shape[0] == 0 or y.shape[0] == 0:
        return np.zeros(x.shape[0], dtype=bool)
    return isin_sorted(x, y[isin_sorted(y, x)])
