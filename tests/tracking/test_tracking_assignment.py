"""Vectorised assignment (direct singletons + LSA on the rest) against one dense LSA."""

from __future__ import annotations

import numpy as np

from service.tracking.assignment import assign
from tests.tracking_reference_forms import assign_reference


def test_assignment_matches_dense_reference() -> None:
    rng = np.random.default_rng(2)
    for _ in range(50):
        nr, nc = rng.integers(1, 25), rng.integers(1, 25)
        mask = rng.random((nr, nc)) < 0.15
        rows, cols = np.nonzero(mask)
        cost = rng.uniform(0, 16, rows.shape[0])
        a = assign(rows, cols, cost, 16.27)
        b = assign_reference(nr, nc, rows, cols, cost, 16.27)
        total_a = cost[a].sum() + 16.27 * (nr - a.shape[0])
        total_b = cost[b].sum() + 16.27 * (nr - b.shape[0])
        assert abs(total_a - total_b) < 1e-9
        assert np.unique(rows[a]).shape[0] == a.shape[0] and np.unique(cols[a]).shape[0] == a.shape[0]
