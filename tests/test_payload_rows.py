"""``TrackBatch`` and ``PairSet`` payloads encoded row by row are the plain encoding's bytes
(service/pipeline/payload_rows.py)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from service.pipeline.payload_rows import PairPayloads, TrackPayloads
from service.pipeline.read_model import PairSetView, track_batch
from service.tracking.base import TrackTable
from service.wire.models import PairSet
from service.wire.outputs import PAIR_BASES, encode
from tests.support import random_track_table


def _next(rng: np.random.Generator, t: TrackTable, next_id: int) -> tuple[TrackTable, int]:
    """A radar's next table: tracks gone, a sector's worth moved, labels and qualities changed,
    a zero's sign flipped, a few tracks born."""
    t = t.take(rng.random(len(t)) > 0.05)
    n = len(t)
    pos, vel, quality = t.position_ecef_m.copy(), t.velocity_ecef_mps.copy(), t.quality.copy()
    moved = rng.random(n) < 0.1
    pos[moved] += rng.normal(0.0, 50.0, (int(moved.sum()), 3))
    quality[rng.random(n) < 0.05] = np.nan
    signed = rng.random(n) < 0.03  # only the sign of a zero: a different row on the wire
    vel[signed, 2] = np.where(np.signbit(vel[signed, 2]), 0.0, -0.0)
    mode_3a = t.mode_3a.copy()
    mode_3a[rng.random(n) < 0.05] = "7000"
    confirmed = t.confirmed | (rng.random(n) < 0.05)
    t = replace(
        t, position_ecef_m=pos, velocity_ecef_mps=vel, quality=quality, mode_3a=mode_3a, confirmed=confirmed
    )
    born = random_track_table(rng, [f"R-{next_id + i:05d}" for i in range(int(rng.integers(0, 4)))])
    return TrackTable.concat([t, born]).by_id(), next_id + len(born)


def test_payloads_are_the_plain_encodings_bytes_table_after_table() -> None:
    rng = np.random.default_rng(21)
    encoder = TrackPayloads()
    t = random_track_table(rng, [f"R-{i:05d}" for i in range(300)])
    next_id = 300
    for k in range(40):
        time_s = 1000.0 + k
        if k % 7 != 3:  # (now and then a table nobody read: the next compares with an older one)
            assert encoder.batch("R", time_s, t) == encode(track_batch("R", time_s, t))
        t, next_id = _next(rng, t, next_id)
    empty = t.take(np.zeros(len(t), dtype=bool))
    assert encoder.batch("R", 2000.0, empty) == encode(track_batch("R", 2000.0, empty))
    assert encoder.batch("R", 2001.0, t) == encode(track_batch("R", 2001.0, t))
    encoder.forget("R")
    assert encoder.batch("R", 2002.0, t) == encode(track_batch("R", 2002.0, t))


def test_a_row_is_reused_only_while_every_published_value_is_the_same() -> None:
    rng = np.random.default_rng(22)
    encoder = TrackPayloads()
    t = random_track_table(rng, [f"R-{i:05d}" for i in range(20)])
    encoder.batch("R", 1.0, t)
    # one track's quality from a number to NaN (null), another's label, another's plot count
    quality, truth, plots = t.quality.copy(), t.truth_id.copy(), t.plots.copy()
    quality[3], truth[5], plots[7] = np.nan, "changed", plots[7] + 1
    later = replace(t, quality=quality, truth_id=truth, plots=plots)
    assert encoder.batch("R", 2.0, later) == encode(track_batch("R", 2.0, later))
    other = encoder.batch("S", 2.0, later)  # (each radar its own base)
    assert other == encode(track_batch("S", 2.0, later))


def _view(rng: np.random.Generator, pairs: list[tuple[str, str]], time_s: float) -> PairSetView:
    """A radar pair's set of ``pairs`` (in the order a view keeps them) with random columns."""
    n = len(pairs)
    nullable = np.where(rng.random(n) < 0.2, np.nan, rng.random(n))
    cols = {
        "track_a": np.array([a for a, _ in pairs], dtype=str),
        "track_b": np.array([b for _, b in pairs], dtype=str),
        "confirmed": rng.random(n) < 0.8,
        "score": rng.random(n),
        "neighbors": rng.integers(0, 5, n),
        "hits": rng.integers(1, 9, n),
        "basis": rng.integers(-1, 4, n).astype(np.int8),
        "held": rng.random(n) < 0.1,
        "statistic": nullable,
        "rotation_weight": rng.random(n),
        "scale": np.where(rng.random(n) < 0.5, np.nan, 1.0),
        "first_time_s": np.full(n, 10.0),
        "last_time_s": np.full(n, time_s),
        "probability": rng.random(n),  # (a book column a PairSet does not publish)
    }
    order = np.lexsort((cols["track_b"], cols["track_a"]))
    cols = {k: v[order] for k, v in cols.items()}
    conf = int(np.count_nonzero(cols["confirmed"]))
    return PairSetView("A", "B", time_s, "svd-topology", cols, conf, n - conf)


def test_pair_set_payloads_are_the_plain_encodings_bytes() -> None:
    rng = np.random.default_rng(23)
    encoder = PairPayloads()
    pairs = [(f"A-{i}", f"B-{i}") for i in range(200)]
    view = _view(rng, pairs, 100.0)
    for k in range(25):
        assert encoder.pair_set(view) == encode(view.body())
        # the next update: a few pairs gone, a few new, some rescored (the rest as they were)
        keep = rng.random(len(pairs)) > 0.03
        pairs = [p for p, kept in zip(pairs, keep, strict=True) if kept]
        pairs += [
            (f"A-{1000 + 10 * k + j}", f"B-{1000 + 10 * k + j}") for j in range(int(rng.integers(0, 4)))
        ]
        fresh = _view(rng, pairs, 100.0 + k)
        same = rng.random(len(pairs)) < 0.7
        before = zip(view.columns["track_a"], view.columns["track_b"], strict=True)
        old = {(a, b): i for i, (a, b) in enumerate(before)}
        cols = {key: col.copy() for key, col in fresh.columns.items()}
        for i, (a, b) in enumerate(zip(cols["track_a"], cols["track_b"], strict=True)):
            if same[i] and (a, b) in old:
                for name in cols:
                    cols[name][i] = view.columns[name][old[(a, b)]]
        # and a kept pair or two with one published field changed alone
        i, j, k2, m, c = (int(x) for x in rng.integers(0, len(pairs), 5))
        cols["hits"][i] += 1
        cols["neighbors"][j] += 1
        cols["basis"][k2] = (cols["basis"][k2] + 1) % len(PAIR_BASES)
        cols["statistic"][m] = np.nan if np.isfinite(cols["statistic"][m]) else 1.5
        cols["confirmed"][c] = not cols["confirmed"][c]
        cols["held"][m] = not cols["held"][m]
        view = replace(fresh, columns=cols)
    assert encoder.pair_set(view) == encode(view.body())


def test_a_held_pair_says_so_in_its_pair_set() -> None:
    """``Pair.held`` is the book's held column, row for row, and the contract's model reads it."""
    view = _view(np.random.default_rng(5), [(f"A-{i}", f"B-{i}") for i in range(50)], 10.0)
    body = PairSet.model_validate_json(PairPayloads().pair_set(view))
    assert [p.held for p in body.pairs] == view.columns["held"].tolist()
    assert any(p.held for p in body.pairs) and not all(p.held for p in body.pairs)
