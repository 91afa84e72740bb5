"""The truth tally's counts of how plots join tracks (evaluation only), against a plain loop."""

from __future__ import annotations

from collections import defaultdict

import numpy as np

from service.evaluation.truth import LED_PLOTS, TruthTally

Call = tuple[list[tuple[list[int], list[str | None]]], list[str | None]]


def _plain(calls: list[Call]) -> tuple[int, int, int, list[dict[int, str]]]:
    """The same counts by dicts: each call's plots judged against the leaders before it (most
    plots, ties to the name seen first: a call's new names in the order of their first chunk,
    then by name), only tracks whose leader has ``LED_PLOTS`` plots or more; *seen*: the
    leader is among the batch's labels."""
    code: dict[str, int] = {}
    counts: dict[int, dict[str, int]] = defaultdict(dict)
    led = other = seen = 0
    leaders_after: list[dict[int, str]] = []

    def leader(uid: int) -> tuple[str, int] | None:
        c = counts.get(uid)
        if not c:
            return None
        name = min(c, key=lambda n: (-c[n], code[n]))
        return name, c[name]

    for chunks, batch in calls:
        for uids, names in chunks:
            for u, n in zip(uids, names, strict=True):
                lead = leader(u) if n is not None else None
                # (judged before the call: a plot of this call does not count for another)
                if lead is not None and lead[1] >= LED_PLOTS:
                    led += 1
                    other += lead[0] != n
                    seen += lead[0] != n and lead[0] in batch
        first: dict[str, int] = {}
        for k, (_, names) in enumerate(chunks):
            for n in names:
                if n is not None and n not in code:
                    first.setdefault(n, k)
        for n in sorted(first, key=lambda n: (first[n], n)):
            code[n] = len(code)
        for uids, names in chunks:
            for u, n in zip(uids, names, strict=True):
                if n is not None:
                    counts[u][n] = counts[u].get(n, 0) + 1
        leaders_after.append({u: lead[0] for u in counts if (lead := leader(u)) is not None})
    return led, other, seen, leaders_after


def test_joined_counts_match_a_plain_loop() -> None:
    rng = np.random.default_rng(7)
    names = [f"AC{i}" for i in range(6)]
    calls: list[Call] = []
    for _ in range(60):
        chunks = []
        for _ in range(int(rng.integers(1, 3))):
            k = int(rng.integers(1, 6))
            uids = [int(u) for u in rng.choice(8, size=k, replace=False) + 1]
            # mostly a track's own aircraft (uid % 6), sometimes a neighbour's or none
            own = [names[u % 6] for u in uids]
            picked: list[str | None] = [
                n if r < 0.75 else (None if r > 0.95 else names[int(rng.integers(6))])
                for n, r in zip(own, rng.random(k), strict=True)
            ]
            chunks.append((uids, picked))
        # the batch: the joined plots' labels and some that joined no track (or none)
        batch = [n for _, ns in chunks for n in ns] + [
            names[int(i)] if i < 6 else None for i in rng.integers(0, 8, size=int(rng.integers(0, 3)))
        ]
        calls.append((chunks, batch))
    tally = TruthTally()
    led, other, seen, leaders_after = _plain(calls)
    for (chunks, batch), after in zip(calls, leaders_after, strict=True):
        tally.add_chunks(
            [(np.array(u, dtype=np.int64), np.array(n, dtype=object)) for u, n in chunks],
            np.array(batch, dtype=object),
        )
        uids = np.array(sorted(after), dtype=np.int64)
        assert list(tally.of(uids)) == [after[int(u)] for u in uids]
    assert (tally.joined_led, tally.joined_other, tally.joined_other_seen) == (led, other, seen)
    assert 0 < seen < other < led  # the run exercises every kind
