"""The cycle step's chains on the links' grid (service/pipeline/cycle_links.py) against a plain
form written from its documented rule: an update at data time ``t`` joins the books as they
were at the latest crossing at or before ``t - lag_s``, whichever worker owns which pair."""

from __future__ import annotations

import itertools

import numpy as np

from service.correlation.cycles import CycleParams
from service.fusion.members import Links
from service.pipeline.cycle_links import CycleLinks
from service.pipeline.shared_links import SharedLinks

RADARS = ("A", "B", "C", "D")
PAIRS = list(itertools.combinations(RADARS, 2))


def _random_links(rng: np.random.Generator, key: tuple[str, str]) -> Links:
    """A one-to-one set of confirmed pairs between tracks 0..7 of each side, random scores."""
    n = int(rng.integers(0, 8))
    a = rng.permutation(8)[:n]
    b = rng.permutation(8)[:n]
    first, second = key if rng.random() < 0.5 else key[::-1]  # either radar may be the A side
    return Links(
        first,
        second,
        np.array([f"{first}{i}" for i in a], dtype=str),
        np.array([f"{second}{i}" for i in b], dtype=str),
        rng.choice([0.5, 0.85, 0.9, 0.95, 0.99], size=n),
    )


def _chains_by_hand(
    key: tuple[str, str], books: dict[tuple[str, str], Links], radars: set[str], least: float
) -> list[tuple[str, str, float]]:
    """Every chain x-z-y of strong confirmed pairs through a third radar, written out."""
    x, y = key
    out = []
    for z in sorted(radars - {x, y}):
        xz, zy = books.get(tuple(sorted((x, z)))), books.get(tuple(sorted((z, y))))  # type: ignore[call-overload]
        if xz is None or zy is None:
            continue
        x_of_z = {}
        for a, b, s in zip(xz.track_a, xz.track_b, xz.score, strict=True):
            if s >= least:
                xt, zt = (a, b) if xz.source_a == x else (b, a)
                x_of_z[str(zt)] = (str(xt), float(s))
        for a, b, s in zip(zy.track_a, zy.track_b, zy.score, strict=True):
            zt, yt = (a, b) if zy.source_a == z else (b, a)
            if s >= least and str(zt) in x_of_z:
                xt, s0 = x_of_z[str(zt)]
                out.append((xt, str(yt), min(s0, float(s))))
    return sorted(out)


def test_chains_are_those_of_the_books_at_the_latest_crossing_lag_s_before() -> None:
    rng = np.random.default_rng(11)
    params = CycleParams()
    one = CycleLinks(params)  # every pair its own
    two = CycleLinks(params)  # owns A-B and C-D; the other pairs' links come from their owner
    owned_by_two = {("A", "B"), ("C", "D")}
    updates: list[tuple[tuple[float, str], tuple[str, str], Links]] = []
    since: dict[tuple[str, str], SharedLinks] = {}
    crossings: list[tuple[float, str]] = []
    checked = nonempty = 0
    next_grid = 0.0
    for step in range(240):
        time_s, release = 0.5 * step, RADARS[step % 4]
        for key in PAIRS:
            if release in key and rng.random() < 0.6:
                links = _random_links(rng, key)
                updates.append(((time_s, release), key, links))
                since[key] = SharedLinks(key, time_s, release, links)
        # the chains of this release's updates (before the crossing: the stage asks during updates)
        for key in PAIRS:
            if release in key:
                got = [one.implied(key, time_s), two.implied(key, time_s)]
                taken = [c for c in crossings if c[0] + params.lag_s <= time_s]
                books = {}
                if taken:
                    for position, k, links in updates:
                        if position <= taken[-1]:
                            books[k] = links
                want = _chains_by_hand(key, books, set(RADARS), params.min_strength)
                for implied in got:
                    rows = sorted(
                        zip(
                            map(str, implied.track_a),
                            map(str, implied.track_b),
                            map(float, implied.strength),
                            strict=True,
                        )
                    )
                    assert rows == want, (key, time_s)
                checked += 1
                nonempty += bool(want)
        if time_s >= next_grid:  # a crossing of the 2 s grid, after the release's updates
            next_grid = np.floor(time_s / 2.0) * 2.0 + 2.0
            own = [since[k] for k in sorted(since)]
            since = {}
            one.crossed((time_s, release), own, RADARS)
            two.crossed((time_s, release), [s for s in own if s.key in owned_by_two], RADARS)
            for s in own:  # the other worker's links arrive after they were sent
                if s.key not in owned_by_two:
                    two.mirror(s)
            crossings.append((time_s, release))
    assert checked > 200 and nonempty > 100


def test_a_forgotten_radar_leaves_the_chains_and_the_history() -> None:
    params = CycleParams(lag_s=0.0)
    cycles = CycleLinks(params)
    links = {
        ("A", "C"): Links("A", "C", np.array(["A1"]), np.array(["C1"]), np.array([0.99])),
        ("B", "C"): Links("B", "C", np.array(["B1"]), np.array(["C1"]), np.array([0.95])),
    }
    own = [SharedLinks(k, 1.0, "C", v) for k, v in sorted(links.items())]
    cycles.crossed((1.0, "C"), own, {"A", "B", "C"})
    implied = cycles.implied(("A", "B"), 1.0)
    assert (list(implied.track_a), list(implied.track_b), list(implied.strength)) == (["A1"], ["B1"], [0.95])
    cycles.forget("C")
    assert len(cycles.implied(("A", "B"), 2.0)) == 0
    cycles.crossed((2.0, "A"), [], {"A", "B"})
    assert len(cycles.implied(("A", "B"), 2.0)) == 0
