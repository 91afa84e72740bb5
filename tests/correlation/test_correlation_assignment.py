"""One-to-one assignment with ambiguity margin: vectorised form vs plain reference."""

from __future__ import annotations

import numpy as np

from service.correlation.assignment import assign_unambiguous
from tests.reference_forms import assign_reference


def test_matches_reference_on_random_graphs() -> None:
    rng = np.random.default_rng(0)
    for _ in range(200):
        na, nb = rng.integers(1, 8, 2)
        k = int(rng.integers(1, na * nb + 1))
        flat = rng.choice(na * nb, size=k, replace=False)
        ia, ib = np.divmod(flat, nb)
        cost = rng.uniform(-3, 20, k)  # continuous: no ties
        acc = rng.uniform(size=k) < 0.8
        margin = float(rng.choice([0.0, 2.0, 6.0]))
        got, _ = assign_unambiguous(ia, ib, cost, acc, margin)
        np.testing.assert_array_equal(got, assign_reference(ia, ib, cost, acc, margin))


def test_ambiguous_pair_is_no_decision() -> None:
    ia = np.array([0, 0, 1])
    ib = np.array([0, 1, 2])
    chosen, amb = assign_unambiguous(ia, ib, np.array([1.0, 2.0, 0.0]), np.ones(3, bool), 6.0)
    np.testing.assert_array_equal(chosen, [False, False, True])
    np.testing.assert_array_equal(amb, [True, False, False])
    chosen, _ = assign_unambiguous(ia, ib, np.array([1.0, 9.0, 0.0]), np.ones(3, bool), 6.0)
    np.testing.assert_array_equal(chosen, [True, False, True])
