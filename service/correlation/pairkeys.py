"""String keys of track pairs and the set operations the books do on them (numpy, no loops)."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

#: Separates the two track ids of a key (a control character: no track id contains it).
SEP = "\x1f"


def pair_keys(a: NDArray[np.str_], b: NDArray[np.str_]) -> NDArray[np.str_]:
    """One string key per pair ``(a[k], b[k])``."""
    return np.char.add(np.char.add(np.asarray(a).astype(str), SEP), np.asarray(b).astype(str))


def find(keys: NDArray[np.str_], query: NDArray[np.str_]) -> NDArray[np.intp]:
    """Index of each ``query`` key in ``keys`` (unique), -1 where absent (one search, after one
    sort unless ``keys`` is sorted already, as a track table's ids are)."""
    if len(keys) == 0 or len(query) == 0:
        return np.full(len(query), -1, dtype=np.intp)
    if is_ascending(keys):
        idx = np.minimum(np.searchsorted(keys, query), len(keys) - 1)
    else:
        order = np.argsort(keys)
        idx = order[np.minimum(np.searchsorted(keys, query, sorter=order), len(keys) - 1)]
    return np.where(keys[idx] == query, idx, -1).astype(np.intp)


def is_ascending(y: NDArray[np.str_]) -> bool:
    """Whether ``y`` is sorted (one comparison pass)."""
    return y.shape[0] < 2 or bool(np.all(y[1:] >= y[:-1]))


def ascending(y: NDArray[np.str_]) -> NDArray[np.str_]:
    """``y`` sorted: as it is when it already is (a track table's ids are: one comparison pass
    instead of a sort)."""
    y = np.asarray(y)
    return y if is_ascending(y) else np.sort(y)


def isin_sorted(x: NDArray[np.str_], y: NDArray[np.str_]) -> NDArray[np.bool_]:
    """``np.isin(x, y)`` for string arrays by one sort of ``y`` (none when it is sorted already)
    and a binary search (``np.isin`` sorts both sides and their union; this is the books' most
    frequent operation)."""
    x, y = np.asarray(x), np.asarray(y)
    if x.shape[0] == 0 or y.shape[0] == 0:
        return np.zeros(x.shape[0], dtype=bool)
    ys = ascending(y)
    pos = np.minimum(np.searchsorted(ys, x), ys.shape[0] - 1)
    return np.asarray(ys[pos] == x)


def isin_few(x: NDArray[np.str_], y: NDArray[np.str_]) -> NDArray[np.bool_]:
    """``np.isin(x, y)`` for a few ``x`` among many ``y`` (a book's new pairs against the whole
    book): the few are sorted and every ``y`` searched among them, then each ``x`` among the
    ``y`` found, so the many are never sorted (:func:`isin_sorted` sorts ``y`` unless it is)."""
    x, y = np.asarray(x), np.asarray(y)
    if x.shape[0] == 0 or y.shape[0] == 0:
        return np.zeros(x.shape[0], dtype=bool)
    return isin_sorted(x, y[isin_sorted(y, x)])
