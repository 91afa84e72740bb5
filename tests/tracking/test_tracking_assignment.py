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


def test_a_candidate_beyond_the_miss_cost_is_never_chosen() -> None:
    """Costs other than the gate's own d^2 (the aid of association's) may exceed the miss cost:
    such a candidate is never chosen, lone or contested, as in the dense reference."""
    rng = np.random.default_rng(5)
    for _ in range(50):
        nr, nc = rng.integers(1, 25), rng.integers(1, 25)
        rows, cols = np.nonzero(rng.random((nr, nc)) < 0.15)
        cost = rng.uniform(0, 30, rows.shape[0])
        a = assign(rows, cols, cost, 16.27)
        b = assign_reference(nr, nc, rows, cols, cost, 16.27)
        assert np.all(cost[a] <= 16.27)
        total_a = cost[a].sum() + 16.27 * (nr - a.shape[0])
        total_b = cost[b].sum() + 16.27 * (nr - b.shape[0])
        assert abs(total_a - total_b) < 1e-9
        assert np.all(np.diff(a) > 0)
