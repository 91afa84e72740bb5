"""Publication holds every pair set and the system tracks to the latest tables
(service/pipeline/publication.py): a table that lost tracks takes them out of every view that
named them, by the lost ids only; checked against holding each view to the whole new table."""

from __future__ import annotations

import numpy as np

from service.pipeline.publication import Publication
from service.pipeline.read_model import PairSetView, SystemTrackView
from service.tracking.base import TrackTable
from service.wire.keys import Keys
from tests.support import random_track_table

RADARS = ("A", "B", "C")


def _pair_view(key: tuple[str, str], ids: dict[str, np.ndarray], rng: np.random.Generator) -> PairSetView:
    n = 40
    ta, tb = rng.choice(ids[key[0]], n), rng.choice(ids[key[1]], n)
    order = np.lexsort((tb, ta))
    confirmed = rng.random(n) < 0.7
    held = ~confirmed & (rng.random(n) < 0.3)
    cols = {"track_a": ta[order], "track_b": tb[order], "confirmed": confirmed, "score": rng.random(n)}
    cols["held"] = held
    n_conf = int(confirmed.sum())
    return PairSetView(key[0], key[1], 10.0, "svd-topology", cols, n_conf, n - n_conf, int(held.sum()))


def _system_view(ids: dict[str, np.ndarray], rng: np.random.Generator) -> SystemTrackView:
    k = 30  # system tracks of one to three members, one of each radar at most
    source, track, counts = [], [], []
    for _ in range(k):
        radars = sorted(rng.choice(RADARS, rng.integers(1, 4), replace=False))
        source += radars
        track += [str(rng.choice(ids[r])) for r in radars]
        counts.append(len(radars))
    bounds = np.concatenate([[0], np.cumsum(counts)])
    return SystemTrackView(
        10.0,
        np.arange(k),
        rng.random(k) < 0.8,
        rng.normal(size=(k, 3)) * 1e6,
        rng.normal(size=(k, 3)),
        rng.random(k) * 100,
        np.asarray(source, dtype=str),
        np.asarray(track, dtype=str),
        bounds,
    )


def _ids_of(view: PairSetView, side: int) -> set[str]:
    return set(view.columns["track_a" if side == 0 else "track_b"].tolist())


def test_a_table_that_lost_tracks_takes_them_out_of_every_view_as_holding_to_it_would() -> None:
    rng = np.random.default_rng(7)
    pub = Publication(Keys("fusion"))
    tables = {r: random_track_table(rng, [f"{r}-{i}" for i in range(60)]) for r in RADARS}
    for r in RADARS:
        assert pub.tracks(r, 10.0, tables[r], own=True)[-1].key == f"fusion/radar/{r}/tracks"
    ids = {r: tables[r].track_id for r in RADARS}
    keys = [("A", "B"), ("A", "C"), ("B", "C")]
    for key in keys:
        pub.pairs(key, _pair_view(key, ids, rng))
    pub.system_tracks(_system_view(ids, rng))
    for step in range(1, 30):
        r = RADARS[step % 3]
        keep = rng.random(len(tables[r])) > 0.15  # some tracks go, some come
        born = [f"{r}-{60 + 3 * step + j}" for j in range(2)]
        table = TrackTable.concat([tables[r].take(keep), random_track_table(rng, born)]).by_id()
        before = dict(pub.views), pub.system
        out = pub.tracks(r, 10.0 + step, table, own=False)
        tables[r] = table
        held = set(table.track_id.tolist())
        for key in keys:
            if r in key:  # the plain form: each view held to the whole new table
                side = key.index(r)
                expected = before[0][key].held(side, table.track_id)
                assert pub.views[key].columns["track_a"].tolist() == expected.columns["track_a"].tolist()
                assert pub.views[key].columns["track_b"].tolist() == expected.columns["track_b"].tolist()
                assert _ids_of(pub.views[key], side) <= held
                view = pub.views[key]  # (its counts those of the pairs it kept)
                assert view.held_pairs == int(np.count_nonzero(view.columns["held"]))
                assert view.confirmed == int(np.count_nonzero(view.columns["confirmed"]))
        assert before[1] is not None and pub.system is not None
        expected_system = before[1].held(r, table.track_id)
        assert pub.system.member_track.tolist() == expected_system.member_track.tolist()
        assert np.array_equal(pub.system.number, expected_system.number)
        assert set(pub.system.member_track[pub.system.member_source == r].tolist()) <= held
        changed = {o.key for o in out}
        assert ("fusion/system/tracks" in changed) == (pub.system is not before[1])
