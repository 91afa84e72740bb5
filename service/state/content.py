"""Whether a whole state file's values can be believed, before the engine takes any of them.

A file that passed its checksum was written whole, but not necessarily by this service: anyone
who may write the directory can write a file with a correct digest.  Its values still go
through what the engine checks of its shape (:meth:`~service.engine.Engine.restore_state`),
and first through this: a kept value judges the input of the whole run that follows (a source
clock ahead of its radar's batches rejects every one of them; a NaN bias spreads into every
compensated position), so a file with one implausible value is refused whole, as a damaged
one is, and nothing of it is written back.

* **Finite.**  Every number, in the tree and in every float array (biases, covariances, clocks,
  positions), is finite.  One exception: the joint solve's time is ``-inf`` while there is no
  joint solution (before the first solve), and is then not used.
* **Clocks not ahead of the file's own write time.**  The header records the data time the
  file was written at (the newest data clock, ``data_clock_s``, which the tree repeats): no
  kept source clock is after it.  That data time itself is not more than
  :data:`MAX_AHEAD_OF_WALL_S` ahead of the wall clock it was written at, nor that write time
  more than as much ahead of the wall clock now; every other kept time (registration rows, the
  joint solve, another worker's biases) is within the same bound, and every time is within the
  input's own range (``0 .. MAX_TIME_S``).
* **Plausible numbering.**  A kept ``seq`` is in ``0 .. MAX_KEPT_SEQ``; every integer fits in
  64 bits.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from service.state.fileformat import Header, RefusedError
from service.wire.models import MAX_TIME_S

#: Largest kept ``seq`` believed.  Publishers count their batches; the largest numbering the
#: sequencer lets a live source have is a millisecond timestamp (a batch every few seconds
#: jumps by a few thousand, within ``max_seq_jump``; a finer one jumps more and is refused),
#: which stays below 10^13 until the input's last time (``MAX_TIME_S``, the year 2286).  A
#: larger kept ``seq`` would refuse every batch of that source as a duplicate.
MAX_KEPT_SEQ = 10**13
#: How far a file's data clock may be ahead of the wall clock of its write, and its write time
#: ahead of the wall clock at the start (s).  A live stream is stamped within seconds of the
#: wall clock and a replay is behind it; a day covers any time-zone mistake of either clock.
#: A kept clock further ahead would hold back or refuse that much data time after the start.
MAX_AHEAD_OF_WALL_S = 86_400.0
_INT64 = 2**63 - 1


def check(header: Header, tree: dict[str, Any], now_unix_s: float) -> None:
    """:class:`RefusedError` naming the first field that cannot be believed (module
    docstring), with ``header``'s epoch; nothing if every value can."""
    try:
        _check(header, tree, now_unix_s)
    except _InvalidError as bad:
        raise RefusedError(f"implausible content: {bad}", header.epoch) from None


class _InvalidError(Exception):
    pass


def _check(header: Header, tree: dict[str, Any], now_unix_s: float) -> None:
    written = header.written_unix_s
    if not _number(written) or not math.isfinite(written):
        raise _InvalidError(f"header written_unix_s {written!r}")
    if written > now_unix_s + MAX_AHEAD_OF_WALL_S:
        raise _InvalidError(
            f"header written_unix_s {written:.0f} is ahead of the wall clock now ({now_unix_s:.0f})"
        )
    # every kept time: within the input's range and not far ahead of the wall clock of the write
    latest = min(MAX_TIME_S, written + MAX_AHEAD_OF_WALL_S)
    clock = header.data_clock_s
    if clock is not None:
        _time("header data_clock_s", clock, latest)
    if tree.get("data_clock_s") != clock:
        raise _InvalidError(f"data_clock_s {tree.get('data_clock_s')!r} is not the header's {clock!r}")
    correlation = tree.get("correlation")
    no_joint = isinstance(correlation, dict) and correlation.get("joint") is None
    _finite(tree, "", no_joint)
    for i, source in enumerate(_list(tree, "sources")):
        where = f"sources[{i}]"
        if not isinstance(source, dict):
            raise _InvalidError(f"{where} is not a source")
        seq = source.get("seq")
        if not (isinstance(seq, int) and not isinstance(seq, bool) and 0 <= seq <= MAX_KEPT_SEQ):
            raise _InvalidError(f"{where}.seq {seq!r} (at most {MAX_KEPT_SEQ})")
        if clock is None:
            raise _InvalidError(f"{where} has a clock but the file has no data time")
        _time(f"{where}.time_s", source.get("time_s"), clock, "the file's data time")
    if isinstance(correlation, dict):
        for i, memory in enumerate(_list(correlation, "memories")):
            rows = memory.get("rows") if isinstance(memory, dict) else None
            for column in ("time", "update_time"):
                values = rows.get(column) if isinstance(rows, dict) else None
                if isinstance(values, np.ndarray) and values.size:
                    if values.dtype.kind not in "iuf":
                        raise _InvalidError(f"correlation.memories[{i}].rows.{column} of {values.dtype}")
                    _time(f"correlation.memories[{i}].rows.{column}", float(values.min()), latest)
                    _time(f"correlation.memories[{i}].rows.{column}", float(values.max()), latest)
        if not no_joint:
            _time("correlation.joint_time_s", correlation.get("joint_time_s"), latest)
    published = tree.get("published_biases")
    if isinstance(published, dict):
        if published.get("time_s") is not None:
            _time("published_biases.time_s", published["time_s"], latest)
        for i, bias in enumerate(_list(published, "biases")):
            if isinstance(bias, dict) and "time_s" in bias:
                _time(f"published_biases.biases[{i}].time_s", bias["time_s"], latest)


def _list(parent: dict[str, Any], name: str) -> list[Any]:
    value = parent.get(name, [])
    if not isinstance(value, list):
        raise _InvalidError(f"{name} is not a list")
    return value


def _number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _time(where: str, value: Any, latest: float, what: str | None = None) -> None:
    """``value`` a time in ``0 .. latest``; ``what`` names ``latest`` in the message."""
    if not _number(value) or not math.isfinite(value) or value < 0:
        raise _InvalidError(f"{where} {value!r}")
    if value > latest:
        bound = what or ("the input's last time" if latest >= MAX_TIME_S else "the wall clock of the write")
        raise _InvalidError(f"{where} {value} is ahead of {bound} ({latest})")


def _finite(value: Any, where: str, no_joint: bool) -> None:
    """Every number in ``value`` finite and every integer within 64 bits (module docstring)."""
    if isinstance(value, dict):
        for key, item in value.items():
            path = f"{where}.{key}" if where else str(key)
            if no_joint and path == "correlation.joint_time_s":
                if not _number(item) or math.isnan(item):  # -inf there: no solve yet
                    raise _InvalidError(f"{path} {item!r}")
                continue
            _finite(item, path, no_joint)
    elif isinstance(value, list):
        for i, item in enumerate(value):
            _finite(item, f"{where}[{i}]", no_joint)
    elif isinstance(value, bool) or value is None or isinstance(value, str):
        return
    elif isinstance(value, int):
        if not -_INT64 - 1 <= value <= _INT64:
            raise _InvalidError(f"{where} {value} does not fit in 64 bits")
    elif isinstance(value, float):
        if not math.isfinite(value):
            raise _InvalidError(f"{where} is not finite ({value})")
    elif isinstance(value, np.ndarray):
        if value.dtype.kind in "fc" and value.size and not np.isfinite(value).all():
            bad = value[~np.isfinite(value)].flat[0]
            raise _InvalidError(f"{where} is not finite ({bad})")
    else:
        raise _InvalidError(f"{where} of type {type(value).__name__}")
