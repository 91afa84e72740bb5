"""The cycle step (service/correlation/cycles.py) against plain loops, and where it runs."""

from __future__ import annotations

import numpy as np
import pytest

from service.correlation import CorrelationParams
from service.correlation.cycles import CycleParams, Implied, contradicted, implied_pairs
from service.correlation.pairs import StrongPairs
from service.pipeline.correlation_stage import CorrelationStage
from service.pipeline.partition import Partition


def _strong(rng: np.random.Generator, first: str, second: str, n: int, long: bool) -> StrongPairs:
    """A one-to-one set of strong confirmed pairs between two radars' tracks.  Track ``k`` of
    radar ``r`` is named alike in every book; ``long``: track 0's name is longer than 8
    characters, so that the sides that hold it have no integer codes and the others do."""

    def name(radar: str, k: int) -> str:
        return f"{radar}{k:02d}" + ("-longname" if long and k == 0 else "")

    a = np.array([name(first, k) for k in rng.permutation(n)[: n - 2]])
    b = np.array([name(second, k) for k in rng.permutation(n)[: n - 2]])
    return StrongPairs.of(a, b, rng.uniform(0.5, 1.0, len(a)))


@pytest.mark.parametrize("long", [False, True])
def test_implied_pairs_match_the_plain_join(long: bool) -> None:
    rng = np.random.default_rng(2)
    for _ in range(50):
        xz = _strong(rng, "X", "Z", 12, long)
        zy = _strong(rng, "Z", "Y", 12, long)
        for x_first, z_first in ((True, True), (False, True), (True, False)):
            xs, zs = (xz.track_a, xz.track_b) if x_first else (xz.track_b, xz.track_a)
            zs2, ys = (zy.track_a, zy.track_b) if z_first else (zy.track_b, zy.track_a)
            got = implied_pairs(xz, x_first, zy, z_first)
            want = {
                (str(xs[i]), str(ys[j])): min(xz.score[i], zy.score[j])
                for i in range(len(xs))
                for j in range(len(zs2))
                if zs[i] == zs2[j]
            }
            pairs = zip(got.track_a.tolist(), got.track_b.tolist(), strict=True)
            assert dict(zip(pairs, got.strength, strict=True)) == want


def test_contradicted_matches_the_plain_rule() -> None:
    rng = np.random.default_rng(4)
    for _ in range(100):
        rows_a = np.arange(6)
        rows_b = rng.permutation(6)
        own = rng.uniform(0, 1, 6)
        imp_a, imp_b, imp_s = rng.integers(0, 8, 5), rng.integers(0, 8, 5), rng.uniform(0, 1, 5)
        got = contradicted(rows_a, rows_b, own, imp_a, imp_b, imp_s, 8, 8)
        for k in range(6):
            # The strongest chain through each of the pair's rows names another partner and is
            # stronger than the pair.
            want = False
            sides = ((rows_a[k], imp_a, rows_b[k], imp_b), (rows_b[k], imp_b, rows_a[k], imp_a))
            for mine, theirs, partner, other in sides:
                through = [r for r in range(5) if theirs[r] == mine]
                if through:
                    r = max(through, key=lambda r: (imp_s[r], r))
                    want |= bool(other[r] != partner and imp_s[r] > own[k])
            assert got[k] == want


def test_the_stage_runs_the_cycles_in_every_worker_unless_disabled() -> None:
    """One worker and a partitioned one alike (their chains come from the links' grid,
    service/pipeline/cycle_links.py); ``cycles.enabled = false`` turns the step off in both."""
    off = CorrelationParams(cycles=CycleParams(enabled=False))
    for partition in (Partition(), Partition(1, 2), Partition(2, 2)):
        on = CorrelationStage("svd-topology", correlation=CorrelationParams(), partition=partition)
        assert isinstance(on.system.implied(("A", "B"), 0.0), Implied)
        stage = CorrelationStage("svd-topology", correlation=off, partition=partition)
        assert stage.system.implied(("A", "B"), 0.0) is None
