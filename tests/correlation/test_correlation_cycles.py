"""The cycle step (service/correlation/cycles.py) against plain loops, and where it runs."""

from __future__ import annotations

import numpy as np

from service.correlation import CorrelationParams
from service.correlation.cycles import Implied, contradicted, implied_pairs
from service.pipeline.correlation_stage import CorrelationStage
from service.pipeline.partition import Partition


def _random_confirmed(rng: np.random.Generator, first: str, second: str, n: int) -> tuple:
    """A one-to-one set of confirmed pairs between two radars' tracks, with scores."""
    a = np.array([f"{first}-{k}" for k in rng.permutation(n)[: n - 2]])
    b = np.array([f"{second}-{k}" for k in rng.permutation(n)[: n - 2]])
    return a, b, rng.uniform(0.5, 1.0, len(a))


def test_implied_pairs_match_the_plain_join() -> None:
    rng = np.random.default_rng(2)
    for _ in range(50):
        x, zx, sxz = _random_confirmed(rng, "X", "Z", 12)
        zy, y, szy = _random_confirmed(rng, "Z", "Y", 12)
        got = implied_pairs(x, zx, sxz, zy, y, szy, 0.7)
        want = {
            (str(x[i]), str(y[j])): min(sxz[i], szy[j])
            for i in range(len(x))
            for j in range(len(zy))
            if zx[i] == zy[j] and min(sxz[i], szy[j]) >= 0.7
        }
        assert (
            dict(zip(zip(got.track_a.tolist(), got.track_b.tolist(), strict=True), got.strength, strict=True))
            == want
        )


def test_contradicted_matches_the_plain_rule() -> None:
    rng = np.random.default_rng(4)
    for _ in range(50):
        ta = np.array([f"X-{k}" for k in range(6)])
        tb = np.array([f"Y-{k}" for k in rng.permutation(6)])
        own = rng.uniform(0, 1, 6)
        imp = Implied(
            np.array([f"X-{k}" for k in rng.integers(0, 8, 5)]),
            np.array([f"Y-{k}" for k in rng.integers(0, 8, 5)]),
            rng.uniform(0, 1, 5),
        )
        got = contradicted(ta, tb, own, imp)
        for k in range(6):
            # The strongest chain through each of the pair's tracks names another partner and
            # is stronger than the pair.
            want = False
            for mine, theirs, partner, other in (
                (ta[k], imp.track_a, tb[k], imp.track_b),
                (tb[k], imp.track_b, ta[k], imp.track_a),
            ):
                rows = [r for r in range(len(imp)) if theirs[r] == mine]
                if rows:
                    r = max(rows, key=lambda r: (imp.strength[r], -r))
                    want |= bool(other[r] != partner and imp.strength[r] > own[k])
            assert got[k] == want


def test_the_stage_runs_the_cycles_only_with_every_pair() -> None:
    whole = CorrelationStage("svd-topology", correlation=CorrelationParams())
    part = CorrelationStage("svd-topology", correlation=CorrelationParams(), partition=Partition(1, 2))
    assert isinstance(whole._implied(("A", "B")), Implied)
    assert part._implied(("A", "B")) is None
