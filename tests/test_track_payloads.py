"""``TrackBatch`` payloads encoded row by row are the plain encoding's bytes
(service/pipeline/track_payloads.py)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from service.pipeline.read_model import track_batch
from service.pipeline.track_payloads import TrackBatchEncoder
from service.tracking.base import TrackTable
from service.wire.outputs import encode
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
    encoder = TrackBatchEncoder()
    t = random_track_table(rng, [f"R-{i:05d}" for i in range(300)])
    next_id = 300
    for k in range(40):
        time_s = 1000.0 + k
        if k % 7 != 3:  # (now and then a table nobody read: the next compares with an older one)
            assert encoder.encode("R", time_s, t) == encode(track_batch("R", time_s, t))
        t, next_id = _next(rng, t, next_id)
    empty = t.take(np.zeros(len(t), dtype=bool))
    assert encoder.encode("R", 2000.0, empty) == encode(track_batch("R", 2000.0, empty))
    assert encoder.encode("R", 2001.0, t) == encode(track_batch("R", 2001.0, t))
    encoder.forget("R")
    assert encoder.encode("R", 2002.0, t) == encode(track_batch("R", 2002.0, t))


def test_a_row_is_reused_only_while_every_published_value_is_the_same() -> None:
    rng = np.random.default_rng(22)
    encoder = TrackBatchEncoder()
    t = random_track_table(rng, [f"R-{i:05d}" for i in range(20)])
    encoder.encode("R", 1.0, t)
    # one track's quality from a number to NaN (null), another's label, another's plot count
    quality, truth, plots = t.quality.copy(), t.truth_id.copy(), t.plots.copy()
    quality[3], truth[5], plots[7] = np.nan, "changed", plots[7] + 1
    later = replace(t, quality=quality, truth_id=truth, plots=plots)
    assert encoder.encode("R", 2.0, later) == encode(track_batch("R", 2.0, later))
    other = encoder.encode("S", 2.0, later)  # (each radar its own base)
    assert other == encode(track_batch("S", 2.0, later))
