"""Tracks without any neighbour in one radar's picture (sparse traffic, the first scans of a
stream, a neighbour only one radar sees) are a normal case for every method: an update gives
"no decision" values, never an exception."""

from __future__ import annotations

import numpy as np
import pytest

from service.correlation import METHODS, PairCorrelator
from service.geo import Site
from service.tracking.base import TrackTable
from topofusion_lab.evaluation.correlation_scenario import make_sites, sample_references


def _table(site: Site, truth: np.ndarray, prefix: str) -> TrackTable:
    n = len(truth)
    r, az, el = site.ecef_to_polar(truth)
    pos = site.polar_to_ecef(r + 100.0, az + 0.1, el)  # a small bias, no noise
    cov = np.broadcast_to(np.diag([200.0**2] * 3 + [10.0**2] * 3), (n, 6, 6)).copy()
    return TrackTable(
        np.array([f"{prefix}{i}" for i in range(n)]),
        np.ones(n, dtype=bool),
        np.zeros(n),
        pos,
        np.zeros((n, 3)),
        cov,
        np.full(n, 10, dtype=np.int64),
        np.full(n, None, dtype=object),
    )


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("count", [1, 2])
def test_isolated_common_tracks_do_not_raise(method: str, count: int) -> None:
    a, b = make_sites()
    rng = np.random.default_rng(4)
    truth = sample_references(rng, a, b, 50)[:: 50 // count][:count]  # far apart: no neighbours
    # radar A also sees a neighbour 3 km east of each target that B misses: A's sequences have
    # one element, B's none
    east = a.rotation[:, 0]
    seen_by_a = np.concatenate([truth, truth + 3_000.0 * east])
    corr = PairCorrelator(method, a, b)
    for k in range(3):
        corr.update(_table(a, seen_by_a, "a"), _table(b, truth, "b"), 1.0 + k)
    for p in corr.pairs():  # whatever was decided is one-to-one and well formed
        assert p.track_a.startswith("a") and p.track_b.startswith("b")
