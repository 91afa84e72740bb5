"""The status's identity figure (contract §4.1) is counted once per pair view and pair of
tables, and always agrees with a plain count over the snapshot it is asked of."""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np

from service.pipeline.read_model import PairSetView, Snapshot
from service.tracking.base import TrackTable
from tests.support import random_track_table


def _codes(rng: np.random.Generator, n: int) -> np.ndarray:
    """Mode S addresses drawn from a few, a third unknown (None)."""
    codes = np.array([f"{c:06X}" for c in rng.integers(0, 4, n)], dtype=object)
    codes[rng.random(n) < 1 / 3] = None
    return codes


def _snapshot(
    tables: dict[str, TrackTable], view: PairSetView, adsb: frozenset[str] = frozenset()
) -> Snapshot:
    return Snapshot(
        tracks={rid: (0.0, t) for rid, t in tables.items()},
        radar_rows=[],
        pair_views=[view],
        biases_all=[],
        correlation={},
        rejected={},
        method="svd-topology",
        prefix="fusion",
        adsb_sources=adsb,
    )


def _plain(snap: Snapshot) -> dict[str, Any]:
    """The figure counted pair by pair, from the snapshot's tables."""
    n = k = 0
    for v in snap.pair_views:
        codes = []
        for rid in (v.radar_a, v.radar_b):
            if rid in snap.adsb_sources:
                codes.append(None)
                continue
            held = snap.tracks.get(rid)
            codes.append(
                {}
                if held is None
                else dict(zip(held[1].track_id.tolist(), held[1].mode_s.tolist(), strict=True))
            )
        for a, b, c in zip(v.columns["track_a"], v.columns["track_b"], v.columns["confirmed"], strict=True):
            if not c:
                continue
            ma = a if codes[0] is None else codes[0].get(a)
            mb = b if codes[1] is None else codes[1].get(b)
            if ma is not None and mb is not None:
                n += 1
                k += ma == mb
    return {"pairs_with_mode_s": n, "mode_s_equal": k}


def test_identity_follows_the_tables_of_each_snapshot() -> None:
    rng = np.random.default_rng(7)
    ids_a, ids_b = [f"A-{i:03d}" for i in range(60)], [f"B-{i:03d}" for i in range(50)]
    table_a = replace(random_track_table(rng, ids_a), mode_s=_codes(rng, 60))
    table_b = replace(random_track_table(rng, ids_b), mode_s=_codes(rng, 50))
    pairs = rng.choice(50, 40, replace=False)
    view = PairSetView(
        "A",
        "B",
        0.0,
        "svd-topology",
        {
            "track_a": np.array(ids_a[:40]),
            # one pair names a track the table no longer holds: no address, not counted
            "track_b": np.array([ids_b[j] for j in pairs[:39]] + ["B-gone"]),
            "confirmed": rng.random(40) < 0.8,
        },
        32,
        8,
    )
    first = _snapshot({"A": table_a, "B": table_b}, view)
    want = _plain(first)
    assert want["pairs_with_mode_s"] > 5 and 0 < want["mode_s_equal"] < want["pairs_with_mode_s"]
    assert {k: first.identity()[k] for k in want} == want
    assert {k: first.identity()[k] for k in want} == want  # asked again: the same
    # B's next table (same tracks, other addresses): the same view counts it afresh
    table_b2 = replace(table_b, mode_s=_codes(rng, 50))
    second = _snapshot({"A": table_a, "B": table_b2}, view)
    want2 = _plain(second)
    assert want2 != want
    assert {k: second.identity()[k] for k in want2} == want2
    # the older snapshot still answers for its own tables
    assert {k: first.identity()[k] for k in want} == want
    # B as an ADS-B source: its track ids are the addresses
    adsb = _snapshot({"A": table_a}, view, frozenset({"B"}))
    want3 = _plain(adsb)
    assert {k: adsb.identity()[k] for k in want3} == want3
    # B's next table carries no address at all (the common radar): nothing counted, and the
    # table after it, with addresses again, is counted afresh
    bare = _snapshot({"A": table_a, "B": replace(table_b, mode_s=np.full(50, None, dtype=object))}, view)
    assert _plain(bare)["pairs_with_mode_s"] == 0
    assert {k: bare.identity()[k] for k in want} == _plain(bare)
    again = _snapshot({"A": table_a, "B": table_b2}, view)
    assert {k: again.identity()[k] for k in want2} == want2
