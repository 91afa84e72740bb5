"""Partitioned workers (``--partition K/N``): ownership, the track-state exchange, and N engines
giving the pair updates of one, whatever the interleaving of their messages."""

from __future__ import annotations

import functools
import hashlib
import itertools
import json
import os
import subprocess
import sys
from collections import deque
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from pydantic import ValidationError

from service.engine import Engine, EngineConfig
from service.pipeline.errors import RejectionError
from service.pipeline.merger import TableMerger
from service.pipeline.partition import FIRST_WORKER_EXTRA, Partition, balanced_salt, shares
from service.pipeline.peers import MAX_PENDING_STATES
from service.pipeline.read_model import SystemTrackView
from service.pipeline.sequencer import RADAR
from service.pipeline.track_exchange import (
    ExchangeParams,
    StatesForm,
    StatesMessage,
    StatesReceiver,
    StatesSender,
    changed_rows,
    decode_states,
    states_frame,
)
from service.tracking.base import TrackTable
from service.wire.frames import decode_frame, is_frame
from service.wire.keys import Keys
from service.wire.models import TrackStates
from service.wire.outgoing import Outgoing
from service.wire.outputs import encode
from service.wire.packed import pack_floats
from tests.scenario_helpers import is_peer, run_one, run_partitioned, scenario_messages
from tests.support import random_track_table
from topofusion_lab.evaluation.promptness import OutputMonitor

ROOT = Path(__file__).resolve().parents[1]


# -- ownership ------------------------------------------------------------------------------
def _owner_by_hand(name: str, n: int) -> int:
    """The documented rule, written out: the highest BLAKE2b-64 weight of "{k}:{name}"."""
    weights = [
        int(hashlib.blake2b(f"{k}:{name}".encode(), digest_size=8).hexdigest(), 16) for k in range(1, n + 1)
    ]
    return 1 + weights.index(max(weights))


def test_every_name_has_exactly_one_owner_as_documented() -> None:
    names = [f"R{i}" for i in range(300)]
    for n in (1, 2, 3, 5):
        workers = [Partition(k, n) for k in range(1, n + 1)]
        for name in names:
            owners = [w.index for w in workers if w.owns(name)]
            assert owners == [_owner_by_hand(name, n) if n > 1 else 1]
        for a, b in itertools.combinations(names[:40], 2):
            assert sum(w.owns_pair(a, b) for w in workers) == 1
            assert [w.owns_pair(a, b) for w in workers] == [w.owns_pair(b, a) for w in workers]


def test_shares_are_even_and_a_new_worker_only_takes_names() -> None:
    names = [f"radar-{i}" for i in range(3000)]
    three = [Partition(1, 3).owner(x) for x in names]
    counts = np.bincount(three, minlength=4)[1:]
    assert np.all(np.abs(counts - 1000) < 4 * np.sqrt(3000 * (1 / 3) * (2 / 3)))
    four = [Partition(1, 4).owner(x) for x in names]
    moved = [(a, b) for a, b in zip(three, four, strict=True) if a != b]
    assert all(b == 4 for _, b in moved)  # names move only to the new worker
    assert abs(len(moved) - 750) < 4 * np.sqrt(3000 * 0.25 * 0.75)


def test_a_salt_is_mixed_into_every_weight_as_documented() -> None:
    """With salt S the weights are those of "{S}:{k}:{name}"; salt 0 is the plain rule."""
    names = [f"R{i}" for i in range(200)]

    def by_hand(name: str, n: int, salt: int) -> int:
        text = [f"{salt}:{k}:{name}" for k in range(1, n + 1)]
        weights = [int(hashlib.blake2b(t.encode(), digest_size=8).hexdigest(), 16) for t in text]
        return 1 + weights.index(max(weights))

    for n in (2, 3):
        assert [Partition(1, n, 7).owner(x) for x in names] == [by_hand(x, n, 7) for x in names]
        assert [Partition(1, n, 0).owner(x) for x in names] == [_owner_by_hand(x, n) for x in names]
        assert [Partition(1, n, 7).owner(x) for x in names] != [Partition(1, n).owner(x) for x in names]
    # still rendezvous: a fourth worker takes names, nothing else moves
    three = [Partition(1, 3, 7).owner(x) for x in names]
    four = [Partition(1, 4, 7).owner(x) for x in names]
    assert all(b == 4 for a, b in zip(three, four, strict=True) if a != b)
    with pytest.raises(ValueError, match="salt"):
        Partition(1, 2, -1)


def test_the_balanced_salt_is_the_best_of_those_tried() -> None:
    """:func:`balanced_salt` against a plain reference: every salt's shares counted through
    ``Partition.owns``, the lowest salt of the smallest busiest share."""
    radars = [f"N{i:02d}" for i in range(1, 13)]
    pairs = list(itertools.combinations(radars, 2))
    for n in (2, 4):

        def busiest(salt: int, n: int = n) -> float:
            parts = [Partition(k, n, salt) for k in range(1, n + 1)]
            r = [sum(p.owns(x) for x in radars) / len(radars) for p in parts]
            q = [sum(p.owns_pair(a, b) for a, b in pairs) / len(pairs) for p in parts]
            loads = [(x + y) / 2 for x, y in zip(r, q, strict=True)]
            loads[0] += FIRST_WORKER_EXTRA  # worker 1 also draws the picture, solves the biases
            return max(loads)

        tries = 60
        want = min(range(tries), key=lambda s: (round(busiest(s), 12), s))
        got = balanced_salt(n, radars, pairs, tries)
        assert got == want
        assert max(shares(n, got, radars, pairs)) == pytest.approx(busiest(got))
        assert busiest(got) <= busiest(0)
    # with its thousand tries, 2 workers get an even split of these 12 radars and 66 pairs,
    # worker 1's extra counted: within one pair and one radar of the ideal
    ideal = (1 + FIRST_WORKER_EXTRA) / 2
    assert max(shares(2, balanced_salt(2, radars, pairs), radars, pairs)) <= ideal + (1 / 12 + 1 / 66) / 2


def test_workers_of_other_salts_are_refused() -> None:
    """A progress message of a worker hashing with another salt would split the names
    differently: refused, counted, and nothing changes."""
    engine = Engine(EngineConfig(partition=Partition(1, 2, 5)))
    keys = Keys("fusion")
    body = {"partition": "2/2", "released_s": 10.0, "correlated_s": 10.0}
    before = engine.peers.progress()
    out = engine.ingest(keys.worker_progress(2), json.dumps(body).encode())
    assert engine.rejected == {"schema": 1}
    assert "TOPOFUSION_PARTITION_SALT" in json.loads(out[0].payload)["detail"]
    assert engine.peers.progress() == before
    engine.ingest(keys.worker_progress(2), json.dumps({**body, "salt": 5}).encode())
    assert engine.rejected == {"schema": 1}  # the same salt: taken


@pytest.mark.parametrize(
    ("key_worker", "partition", "said"),
    [
        (1, "1/2", "another worker runs partition 1/2 too"),  # the same K twice
        (2, "2/3", "worker 2/3 counts 3 workers, this worker 1/2"),  # another N
    ],
)
def test_workers_of_the_same_k_or_another_n_are_refused_and_said_so(
    key_worker: int, partition: str, said: str
) -> None:
    engine = Engine(EngineConfig(partition=Partition(1, 2)))
    keys = Keys("fusion")
    body = {"partition": partition, "released_s": 10.0, "correlated_s": 10.0}
    before = engine.peers.progress()
    for key in (keys.worker_progress(key_worker), keys.worker_clock(key_worker)):
        out = engine.ingest(key, json.dumps(body).encode())
        assert said in json.loads(out[0].payload)["detail"]
    assert engine.rejected == {"schema": 2}
    assert engine.peers.progress() == before


@pytest.mark.parametrize("kind", ["links", "registration"])
def test_a_workers_own_pair_messages_heard_back_are_not_parsed_the_others_are(kind: str) -> None:
    """Worker 1 hears its own pairs' links and registration rows back, as it hears its own track
    states: it skips them unread (it made them); another worker's are read and checked, and a
    broken one is rejected and counted."""
    partition = Partition(1, 2)
    engine = Engine(EngineConfig(partition=partition))
    keys = Keys("fusion")
    names = [f"R{i}" for i in range(8)]
    pairs = [(a, b) for i, a in enumerate(names) for b in names[i + 1 :]]
    own = next(p for p in pairs if partition.owns_pair(*p))
    other = next(p for p in pairs if not partition.owns_pair(*p))
    key_of = keys.links if kind == "links" else keys.registration
    assert engine.ingest(key_of(*own), b"{not json") == [] and engine.rejected == {}
    out = engine.ingest(key_of(*other), b"{not json")
    assert engine.rejected == {"malformed_json": 1}
    assert [o.key for o in out] == ["fusion/errors"]


@pytest.mark.parametrize("spec", ["0/2", "3/2", "1", "a/b", "1/0", "1/257", "3/1000000000"])
def test_bad_partitions_are_refused(spec: str) -> None:
    """... at once, with a message (N beyond the bound would weigh every name against every
    worker: a billion made ``topofusion config`` hang)."""
    with pytest.raises(ValueError, match="partition"):
        Partition.parse(spec)
    Partition.parse("256/256")  # (the bound itself is taken)


@pytest.mark.parametrize(
    ("command", "said"),
    [
        (["partition", "--count", "100000000", "N01", "N02"], "--count must be in 1..256"),
        (["run", "--partition", "1/1000000000"], "at most 256 workers"),
        (["demo", "--workers", "100000"], "need 1 to 16"),
    ],
)
def test_worker_counts_beyond_the_bounds_are_refused_before_anything_starts(
    command: list[str], said: str
) -> None:
    env = {k: v for k, v in os.environ.items() if not k.startswith("TOPOFUSION_")}
    proc = subprocess.run(
        [str(Path(sys.executable).parent / "topofusion"), *command],
        capture_output=True,
        text=True,
        timeout=60,
        env=env,
    )
    assert proc.returncode == 2 and said in proc.stderr, proc.stderr


# -- the track-state exchange ---------------------------------------------------------------
def _changed_by_hand(old: TrackTable, new: TrackTable) -> tuple[list[str], list[str]]:
    """Plain reference form of :func:`changed_rows`: compare row by row through dicts (floats
    by their bytes: exactly)."""

    def rows(t: TrackTable) -> dict[str, tuple[object, ...]]:
        return {
            str(t.track_id[i]): (
                bool(t.confirmed[i]),
                int(t.plots[i]),
                t.time_s[i].tobytes(),
                t.position_ecef_m[i].tobytes(),
                t.velocity_ecef_mps[i].tobytes(),
                t.covariance[i].tobytes(),
                t.quality[i].tobytes(),
                t.truth_id[i],
            )
            for i in range(len(t))
        }

    o, n = rows(old), rows(new)
    return [k for k in n if o.get(k) != n[k]], [k for k in o if k not in n]


def _evolve(rng: np.random.Generator, t: TrackTable, next_id: int) -> tuple[TrackTable, int]:
    keep = rng.random(len(t)) > 0.1
    t = t.take(keep)
    pos = t.position_ecef_m.copy()
    moved = rng.random(len(t)) < 0.2
    pos[moved] += 1.0
    quality = t.quality.copy()
    requal = rng.random(len(t)) < 0.1  # only its quality changes: a changed row too
    quality[requal] = np.where(rng.random(int(requal.sum())) < 0.3, np.nan, rng.random(int(requal.sum())))
    cov = t.covariance.copy()
    signed = rng.random(len(t)) < 0.05  # a zero that changes its sign only: a changed row too
    cov[signed, 2, 4] = np.where(np.signbit(cov[signed, 2, 4]), 0.0, -0.0)
    t = TrackTable(
        t.track_id,
        t.confirmed,
        t.time_s,
        pos,
        t.velocity_ecef_mps,
        cov,
        t.plots,
        t.truth_id,
        quality=quality,
    )
    new = random_track_table(rng, [f"A-{next_id + i}" for i in range(int(rng.integers(0, 5)))])
    return TrackTable.concat([t, new]).by_id(), next_id + len(new)


def test_changed_rows_matches_its_reference_form() -> None:
    rng = np.random.default_rng(4)
    t = random_track_table(rng, [f"A-{i}" for i in range(60)])
    next_id = 60
    for _ in range(30):
        new, next_id = _evolve(rng, t, next_id)
        changed, removed = changed_rows(t, new)
        want_changed, want_removed = _changed_by_hand(t, new)
        assert sorted(new.track_id[changed].tolist()) == sorted(want_changed)
        assert sorted(removed.tolist()) == sorted(want_removed)
        t = new


def _through_the_wire(body: dict[str, Any], form: StatesForm) -> StatesMessage:
    if form == "frame":
        payload = states_frame(body)
        header, _ = decode_frame(payload)
        # the header is the message without its numbers, which the body holds in this order
        assert {k: v for k, v in header.items() if k != "tracks"} == {
            k: v for k, v in body.items() if k != "tracks"
        }
        assert header["tracks"]["track_id"] == body["tracks"]["track_id"]
        binary = [
            "plots",
            "time_s",
            "position_ecef_m",
            "velocity_ecef_mps",
            "covariance",
            "quality",
            "confirmed",
        ]
        assert header["tracks"]["binary"] == [x for x in binary if x in body["tracks"]]
    else:
        payload = encode(body)
        TrackStates.model_validate_json(payload)  # what is sent is what the contract's model says
    return decode_states(payload, "A")


@pytest.mark.parametrize("form", ["numbers", "packed", "frame"])
def test_a_peer_rebuilds_the_owners_tables_bit_for_bit_and_recovers_from_a_gap(form: StatesForm) -> None:
    rng = np.random.default_rng(5)
    sender = StatesSender()
    receiver = StatesReceiver()
    t = random_track_table(rng, [f"A-{i}" for i in range(80)])
    next_id = 80
    fulls = 0
    for step in range(200):
        body = sender.states("A", t, 1000.0 + step, form)  # full once per 60 data seconds
        assert isinstance(body["tracks"]["covariance"], str) == (form == "packed")
        fulls += bool(body["full"])
        # step 100 is lost on the way: the receiver has no base until the next full table
        got = None if step == 100 else receiver.apply(_through_the_wire(body, form))
        if 100 <= step < 120 and not body["full"]:
            assert got is None
        else:
            assert got is not None
            for name in (
                "track_id",
                "confirmed",
                "time_s",
                "position_ecef_m",
                "velocity_ecef_mps",
                "covariance",
                "plots",
            ):
                assert np.array_equal(getattr(got, name), getattr(t, name)), name
            assert got.truth_id.tolist() == t.truth_id.tolist()
            assert np.array_equal(got.quality, t.quality, equal_nan=True)
        t, next_id = _evolve(rng, t, next_id)
    assert fulls == 4
    assert receiver.gaps["A"] >= 1


def _form_of(payload: bytes) -> str:
    if is_frame(payload):
        return "frame"
    body = json.loads(payload)
    if "tracks" not in body:
        return "json"  # (links, registration rows)
    return "packed" if isinstance(body["tracks"]["time_s"], str) else "numbers"


def _sent_forms(exchange: tuple[ExchangeParams, ...], kind: str = "/track-states") -> list[set[str]]:
    """Workers, each with the ``exchange`` settings given, on a three-radar stream: per worker,
    the forms of the track states (or of the messages whose key holds ``kind``) it sent
    after the first 200 messages (each worker has heard the others' progress by then)."""
    n = len(exchange)
    engines = [
        Engine(EngineConfig(partition=Partition(k + 1, n), exchange=x)) for k, x in enumerate(exchange)
    ]
    forms: list[set[str]] = [set() for _ in engines]
    pending: deque[tuple[int, str, bytes]] = deque()

    def take(j: int, out: list[Outgoing], late: bool) -> None:
        for o in out:
            if is_peer(o.key):
                pending.append((j, o.key, o.payload))
                if kind in o.key and late:
                    forms[j].add(_form_of(o.payload))

    for i, (key, payload) in enumerate(scenario_messages("three-radar", duration_s=60.0, seed=2)):
        for j, engine in enumerate(engines):
            take(j, engine.ingest(key, payload), i >= 200)
        while pending:  # every peer message to every other worker, in order
            j, peer_key, body = pending.popleft()
            for k, engine in enumerate(engines):
                if k != j:
                    take(k, engine.ingest(peer_key, body), i >= 200)
    for engine in engines:
        engine.close()
    return forms


def test_track_states_go_as_frames_or_packed_once_every_other_worker_reads_them() -> None:
    default, no_frames, neither = (
        ExchangeParams(),
        ExchangeParams(frames=False),
        ExchangeParams(packed=False, frames=False),
    )
    assert _sent_forms((default, default)) == [{"frame"}, {"frame"}]
    # a worker that does not read frames (frames off, or a version before them) gets packed
    # columns; one that reads neither (a version before packing) gets numbers
    assert _sent_forms((default, no_frames)) == [{"packed"}, {"packed"}]
    assert _sent_forms((default, neither)) == [{"numbers"}, {"numbers"}]


@pytest.mark.parametrize("kind", ["/links/", "/registration/"])
def test_links_and_rows_go_as_frames_once_every_other_worker_reads_them(kind: str) -> None:
    default, no_frames = ExchangeParams(), ExchangeParams(frames=False)
    # (worker 1 solves the biases itself: it sends no rows)
    senders = slice(0, 2) if kind == "/links/" else slice(1, 2)
    assert _sent_forms((default, default), kind)[senders] == [{"frame"}, {"frame"}][senders]
    assert _sent_forms((default, no_frames), kind)[senders] == [{"json"}, {"json"}][senders]


# -- N engines give the pair updates of one --------------------------------------------------
def _chains(engine: Engine) -> list[int]:
    """The number of implied pairs each of ``engine``'s radar-pair updates takes from now on."""
    counts: list[int] = []
    cycles = engine.correlation.stage.system.cycles  # type: ignore[attr-defined]
    implied = cycles.implied

    def counted(key: tuple[str, str], time_s: float) -> Any:
        out = implied(key, time_s)
        counts.append(len(out))
        return out

    cycles.implied = counted
    return counts


@functools.cache
def _reference() -> tuple[list[tuple[str, bytes]], dict[str, list[bytes]], Engine, list[SystemTrackView]]:
    """The three-radar stream the partitioned runs here take, and one worker's run of it (its
    pair updates, engine and drawn pictures; the cycle step on, as by default, and its chains
    naming pairs): run once per test process, read only."""
    msgs = scenario_messages("three-radar", duration_s=150.0, seed=2)
    drawn: list[list[SystemTrackView]] = []
    chains: list[list[int]] = []
    pairs, engine = run_one(msgs, lambda e: (drawn.append(_drawn(e)), chains.append(_chains(e))))
    assert sum(n > 0 for n in chains[0]) > 0.5 * len(chains[0]) > 10
    return msgs, pairs, engine, drawn[0]


@pytest.mark.parametrize(
    ("n", "seed", "salt", "lagging"), [(2, 0, 0, None), (3, 1, 0, 3), (2, 2, 46, 1), (3, 5, 16, 1)]
)
def test_n_engines_give_the_pair_updates_of_one(n: int, seed: int, salt: int, lagging: int | None) -> None:
    """Every pair update of one worker, the cycle step on, whichever worker owns which pair of
    the triangle, also when one worker falls far behind the others (its chains are then read
    from links it sent long before)."""
    msgs, one, single, _ = _reference()
    many, publishers, engines = run_partitioned(msgs, n, seed, salt=salt, lagging=lagging)
    assert sorted(many) == sorted(one)
    for key in one:
        assert len(publishers[key]) == 1, f"{key} correlated by workers {publishers[key]}"
        # A worker hears another's tables once that one released them: at the end of the
        # input the newest update of a pair may still be held back, never a different one.
        assert len(one[key]) - 1 <= len(many[key]) <= len(one[key])
        assert many[key] == one[key][: len(many[key])], key
    a, b, c = (Partition(1, n, salt).owner(x) for x in "ABC")
    crossing = [k for k in one if len({Partition(1, n, salt).owner(r) for r in k.split("/")[-2:]}) > 1]
    assert crossing, (a, b, c)  # the stream has pairs whose radars two workers track
    # The joint bias estimate: solved by worker 1 over every worker's rows, at the same data
    # times over the same rows as one worker's, so the very same numbers; every worker serves it.
    want = single.snapshot().biases()
    assert want
    for engine in engines:
        assert engine.snapshot().biases() == want
    for engine in engines:
        assert engine.rejected == {}
        assert not engine.peers.receiver.gaps
        assert engine.peers.progress()["reordered"] == 0  # every table in one worker's order


def _drawn(engine: Engine) -> list[SystemTrackView]:
    """Every system-track picture ``engine`` draws from now on (its system tracker watched:
    a partitioned worker 1 may publish only the newest of several drawn at once)."""
    drawn: list[SystemTrackView] = []
    tracker = engine.correlation.drawer.tracker  # type: ignore[attr-defined]
    update = tracker.update

    def recorded(members: Any, la: Any, lb: Any, score: Any, time_s: float) -> Any:
        tracks = update(members, la, lb, score, time_s)
        drawn.append(SystemTrackView.of(time_s, tracks, members))
        return tracks

    tracker.update = recorded
    return drawn


@pytest.mark.parametrize(("n", "seed"), [(2, 3), (3, 4)])
def test_worker_1_draws_the_system_tracks_one_worker_draws(n: int, seed: int) -> None:
    """The fused picture of N workers: drawn by worker 1 from its own pairs (2 workers: B/C)
    and the links the others send (A/B, A/C; 3 workers: every pair), at the same data times
    from the same inputs as one worker's, so the same groups, numbers, states and members."""
    msgs, _, _, one = _reference()
    pictures: dict[int, list[SystemTrackView]] = {}
    _, _, engines = run_partitioned(
        msgs, n, seed, lambda e: pictures.setdefault(e.partition.index, _drawn(e))
    )
    many = pictures[1]
    assert all(not pictures[k] for k in range(2, n + 1))  # only worker 1 draws
    assert len(one) > 50 and max(int(np.count_nonzero(np.diff(v.bounds) > 1)) for v in one) > 10
    # the others send their links after they correlated: the newest pictures may wait
    assert len(one) - 5 <= len(many) <= len(one)
    owners = {Partition(1, n).owner(f"{a}/{b}") for a, b in itertools.combinations("ABC", 2)}
    assert owners - {1}  # pairs of other workers feed worker 1's picture
    for want, got in zip(one, many, strict=False):
        assert got.time_s == want.time_s
        np.testing.assert_array_equal(got.number, want.number)
        np.testing.assert_array_equal(got.confirmed, want.confirmed)
        np.testing.assert_array_equal(got.member_source, want.member_source)
        np.testing.assert_array_equal(got.member_track, want.member_track)
        np.testing.assert_array_equal(got.bounds, want.bounds)
        np.testing.assert_allclose(got.position, want.position, rtol=0, atol=1e-6)
        np.testing.assert_allclose(got.velocity, want.velocity, rtol=0, atol=1e-9)
    assert engines[0].correlation.stage.system.forced == 0  # type: ignore[attr-defined]


@pytest.mark.parametrize(("n", "seed"), [(2, 0), (3, 1)])
def test_worker_1s_pictures_name_only_tracks_its_radars_latest_batches_hold(n: int, seed: int) -> None:
    """Worker 1 draws a picture once the others have correlated past its data time, so after it
    published the tables of that time released after the picture's radar: a track one of
    them dropped must not be named by the picture (as its outputs reach one subscriber)."""
    msgs = _reference()[0]
    scans = {
        json.loads(p)["radar_id"]: json.loads(p)["scan_period_s"] for k, p in msgs if k.endswith("/site")
    }
    own = {rid: scan for rid, scan in scans.items() if Partition(1, n).owns(rid)}
    keys = Keys("fusion")
    watched = {keys.system_tracks, *(keys.tracks(rid) for rid in own)}
    monitor = OutputMonitor(own)
    pictures = dropped = 0
    last: dict[str, set[str]] = {}

    def heard(k: int, o: Outgoing) -> None:
        nonlocal pictures, dropped
        if k != 1 or o.key not in watched:
            return
        body = o.body()
        monitor.feed(o.key, body)
        if o.key == keys.system_tracks:
            pictures += 1
        else:
            ids = {t["track_id"] for t in body["tracks"]}
            dropped += len(last.get(body["radar_id"], set()) - ids)
            last[body["radar_id"]] = ids

    run_partitioned(msgs, n, seed, heard=heard)
    assert own and pictures > 50 and dropped >= 5  # worker 1's radars do drop tracks
    dangling = monitor.report().dangling
    assert dangling.references == 0, dangling.examples


def _states_cases() -> list[tuple[str, object]]:
    """A valid ``TrackStates`` and hostile variants of it (contract-shaped and not)."""
    good = json.loads((ROOT / "schemas" / "examples" / "TrackStates.json").read_text())
    cases: list[tuple[str, object]] = [("valid", good)]

    def variant(name: str, path: list[str], value: object) -> None:
        body = json.loads(json.dumps(good))
        node = body
        for p in path[:-1]:
            node = node[p]
        if value is _DROP:
            del node[path[-1]]
        else:
            node[path[-1]] = value
        cases.append((name, body))

    variant("no tracks", ["tracks"], _DROP)
    variant("seq negative", ["seq"], -1)
    variant("seq float", ["seq"], 1.5)
    variant("time far", ["time_s"], 1e12)
    variant("time string", ["time_s"], "now")
    variant("time a bool", ["time_s"], True)
    variant("time a numeric string", ["time_s"], "12.5")
    variant("track time a bool", ["tracks", "time_s"], [True])
    variant("track time a numeric string", ["tracks", "time_s"], ["12.5"])
    variant("valid integer track time", ["tracks", "time_s"], [12])
    variant("bad radar id", ["radar_id"], "a b")
    variant("full not bool", ["full"], 1)
    variant("short covariance", ["tracks", "covariance"], [[1.0] * 35])
    variant("ragged columns", ["tracks", "plots"], [1, 2])
    variant("negative plots", ["tracks", "plots"], [-1])
    variant("plots float", ["tracks", "plots"], [1.5])
    variant("huge position", ["tracks", "position_ecef_m"], [[1e9, 0.0, 0.0]])
    variant("nested junk", ["tracks", "velocity_ecef_mps"], [["x", 0, 0]])
    variant("confirmed int", ["tracks", "confirmed"], [1])
    variant("ids not strings", ["tracks", "track_id"], [17])
    variant("removed not strings", ["removed"], [3])
    variant("truth wrong length", ["tracks", "truth_id"], ["a", "b"])
    variant("valid quality", ["tracks", "quality"], [0.25])
    variant("valid null quality", ["tracks", "quality"], [None])
    variant("quality above one", ["tracks", "quality"], [1.5])
    variant("quality negative", ["tracks", "quality"], [-0.1])
    variant("quality string", ["tracks", "quality"], ["high"])
    variant("quality bool", ["tracks", "quality"], [True])
    variant("quality wrong length", ["tracks", "quality"], [0.5, 0.5])
    variant("valid integer quality", ["tracks", "quality"], [1])
    variant("quality huge", ["tracks", "quality"], [1e300])
    variant("long covariance row", ["tracks", "covariance"], [[1.0] * 37])
    variant("covariance row an object", ["tracks", "covariance"], [{"a": 1.0}])
    variant("covariance numbers not in rows", ["tracks", "covariance"], [1.0] * 36)
    variant("position of lists", ["tracks", "position_ecef_m"], [[[1.0], [2.0], [3.0]]])
    variant("truth not a string", ["tracks", "truth_id"], [5])
    variant("removed an object", ["removed"], [{"id": "A-1"}])
    n = len(good["tracks"]["track_id"])
    cov = np.asarray(good["tracks"]["covariance"], dtype=float)
    variant("valid packed covariance", ["tracks", "covariance"], pack_floats(cov))
    variant("valid packed time", ["tracks", "time_s"], pack_floats(np.asarray(good["tracks"]["time_s"])))
    variant("valid packed quality with a null", ["tracks", "quality"], pack_floats(np.full(n, np.nan)))
    variant("packed covariance short", ["tracks", "covariance"], pack_floats(cov.ravel()[:-1]))
    variant("packed covariance not base64", ["tracks", "covariance"], "%%%%" * 96)
    variant("packed covariance bad padding", ["tracks", "covariance"], pack_floats(cov)[:-1])
    variant("packed covariance infinite", ["tracks", "covariance"], pack_floats(np.full(36 * n, np.inf)))
    variant("packed covariance NaN", ["tracks", "covariance"], pack_floats(np.full(36 * n, np.nan)))
    variant("packed position far", ["tracks", "position_ecef_m"], pack_floats(np.full(3 * n, 1e9)))
    variant("packed time negative", ["tracks", "time_s"], pack_floats(np.full(n, -1.0)))
    variant("packed quality above one", ["tracks", "quality"], pack_floats(np.full(n, 1.5)))
    variant("packed plots", ["tracks", "plots"], pack_floats(np.ones(n)))
    return cases


_DROP = object()


@pytest.mark.parametrize(("name", "body"), _states_cases(), ids=[c[0] for c in _states_cases()])
def test_fast_states_decoder_agrees_with_the_model(name: str, body: object) -> None:
    payload = json.dumps(body).encode()
    try:
        TrackStates.model_validate_json(payload)
        model_ok = True
    except ValidationError:
        model_ok = False
    try:
        decode_states(payload, "A")
        fast_ok = True
    except RejectionError:
        fast_ok = False
    assert fast_ok == model_ok, name
    assert model_ok == name.startswith("valid")


def test_partition_command_prints_the_assignment_the_workers_use() -> None:
    ids = [f"R{i}" for i in range(7)]
    exe = str(Path(sys.executable).parent / "topofusion")
    out = subprocess.run([exe, "partition", "--count", "3", *ids], capture_output=True, text=True, check=True)
    blocks = out.stdout.split("worker ")[1:]
    assert len(blocks) == 3
    for k, block in enumerate(blocks, start=1):
        radars = block.split("radars:")[1].split("\n")[0].split()
        pairs = block.split("pairs:")[1].split()
        p = Partition(k, 3)
        assert radars == [i for i in ids if p.owns(i)] or (radars == ["-"] and not any(map(p.owns, ids)))
        want = [f"{a}/{b}" for a, b in itertools.combinations(ids, 2) if p.owns_pair(a, b)]
        assert pairs == want or (pairs == ["-"] and not want)


def test_partition_balance_prints_the_salt_and_its_assignment(tmp_path: Path) -> None:
    """``--balance`` names the salt balanced_salt finds for the sites' pairs (those at most
    --pair-km apart), and prints the assignment the workers given that salt use."""
    ids = [f"N{i:02d}" for i in range(1, 13)]
    sites = [{"radar_id": r, "latitude_deg": 46.0, "longitude_deg": 1.0 + 2.0 * i} for i, r in enumerate(ids)]
    path = tmp_path / "sites.json"
    path.write_text(json.dumps(sites))
    exe = str(Path(sys.executable).parent / "topofusion")
    argv = [exe, "partition", "--count", "2", "--sites", str(path), "--balance", "--pair-km", "400"]
    out = subprocess.run(argv, capture_output=True, text=True, check=True).stdout
    salt = int(out.split("TOPOFUSION_PARTITION_SALT=")[1].split()[0])
    # neighbours 2 degrees of longitude apart (about 155 km): pairs up to two apart are near
    near = [(a, b) for a, b in itertools.combinations(ids, 2) if abs(ids.index(a) - ids.index(b)) <= 2]
    assert salt == balanced_salt(2, ids, near)
    blocks = out.split("\nworker ")[1:]
    assert len(blocks) == 2
    for k, block in enumerate(blocks, start=1):
        p = Partition(k, 2, salt)
        assert block.split("radars:")[1].split("\n")[0].split() == [i for i in ids if p.owns(i)]
        assert block.split("pairs:")[1].split() == [f"{a}/{b}" for a, b in near if p.owns_pair(a, b)]
        assert f"share {shares(2, salt, ids, near)[k - 1]:.3f}" in block


def test_track_states_before_the_radars_site_wait_for_it() -> None:
    """A worker can hear a radar's track states from its owner before the radar's own site
    (the workers' messages are taken ahead of inputs): they wait for the site, bounded, and
    are not rejected as `unknown_radar`."""
    msgs = scenario_messages("two-radar", duration_s=40.0)
    owner_k = next(k for k in (1, 2) if Partition(k, 2).owns("A"))
    owner = Engine(EngineConfig(partition=Partition(owner_k, 2)))
    other = Engine(EngineConfig(partition=Partition(3 - owner_k, 2)))
    states = [
        o for key, payload in msgs for o in owner.ingest(key, payload) if o.key.endswith("A/track-states")
    ]
    assert len(states) > 5
    errors = [o for o in states if other.ingest(o.key, o.payload)]  # before any site: no output
    assert errors == [] and other.rejected.get("unknown_radar", 0) == 0
    site = next(p for k, p in msgs if k == "fusion/radar/A/site")
    assert other.ingest("fusion/radar/A/site", site) == []
    time_s, held = other.peers.receiver.latest("A")
    assert time_s > 0 and sorted(held.track_id) == sorted(owner.tracking.tracked["A"].table.track_id)
    # beyond the bound, such messages are rejected (a flood must not grow without end)
    z = next(r for r in ("Z", "Y", "X", "W") if not other.partition.owns(r))
    flood = states[0].payload.replace(b'"A"', f'"{z}"'.encode())
    for _ in range(MAX_PENDING_STATES):
        other.ingest(f"fusion/radar/{z}/track-states", flood)
    assert other.rejected.get("unknown_radar", 0) == 0
    out = other.ingest(f"fusion/radar/{z}/track-states", flood)  # the oldest held is given up
    assert other.rejected["unknown_radar"] == 1 and [o.key for o in out] == ["fusion/errors"]
    assert out[0].body()["radar_id"] == z


def test_a_table_after_the_merge_passed_its_time_is_released_and_counted_as_reordered() -> None:
    """A worker no longer waited for (its link down beyond the grace) publishes on: its tables
    arrive after the merge went past their data time.  They are not lost nor held, but released
    out of the one-worker order, and each is counted."""
    merger = TableMerger()
    merger.push(RADAR, "A", 1, 10.0, "A@10")
    merger.progress(1, 20.0)  # worker 1 published up to 20 s; worker 2 is not waited for
    assert [r.item for r in merger.release({1})] == ["A@10"] and merger.reordered == 0
    merger.push(RADAR, "A", 2, 25.0, "A@25")  # in order: after the merge's 20 s
    merger.push(RADAR, "B", 1, 5.0, "B@5")  # worker 2's, from before the merge's 20 s
    merger.push(RADAR, "B", 2, 10.0, "B@10")  # at A@10's time, but after it in the order
    merger.push(RADAR, "0", 1, 10.0, "0@10")  # at A@10's time, and before it in the order
    assert merger.reordered == 2
    merger.progress(1, 30.0)
    assert [r.item for r in merger.release({1})] == ["B@5", "0@10", "B@10", "A@25"]
    assert merger.reordered == 2  # (counted when they came, once each)


def test_a_radar_whose_owner_is_gone_expires_in_data_time_unless_it_is_heard_again() -> None:
    """A radar whose owner is no longer waited for is silent: its armed expiry (an empty table)
    comes out in data-time order, after that time's tables; called off, or armed again, the
    earlier one never comes out; and a shutdown does not expire what the input did not reach."""
    merger = TableMerger()
    merger.push(RADAR, "B", 1, 10.0, "B@10")
    merger.expire("B", 40.0, "B expired")  # worker 2 gone: B silent from 10 s
    merger.push(RADAR, "A", 1, 40.0, "A@40")
    merger.progress(1, 30.0)
    assert len(merger) == 2  # (the tables held; an armed expiry is none)
    assert [r.item for r in merger.release({1})] == ["B@10"]
    merger.progress(1, 45.0)
    assert [(r.item, r.time_s) for r in merger.release({1})] == [("A@40", 40.0), ("B expired", 40.0)]
    assert not merger.expiring("B") and merger.reordered == 0
    # armed again, then called off (its owner is back): never released, and it holds nothing back
    merger.expire("B", 60.0, "B expired again")
    merger.call_off("B")
    merger.push(RADAR, "A", 2, 70.0, "A@70")
    merger.progress(1, 65.0)
    assert [r.item for r in merger.release({1})] == []
    assert merger.through({1}) == 65.0
    # armed twice: only the latest counts
    merger.expire("B", 80.0, "B@80 expiry")
    merger.expire("B", 90.0, "B@90 expiry")
    merger.progress(1, 100.0)
    assert [r.item for r in merger.release({1})] == ["A@70", "B@90 expiry"]
    # shutdown: the tables held go out, an expiry beyond the last of them does not
    merger.push(RADAR, "A", 3, 110.0, "A@110")
    merger.expire("B", 400.0, "B beyond the input")
    assert [r.item for r in merger.flush()] == ["A@110"]


def test_a_gone_worker_s_radars_expire_also_after_a_gap_in_their_track_states() -> None:
    """A gap in a radar's track states drops its table in the receiver until the next whole
    one, not its tracks from the merge: if the owner goes then, the radar expires all the
    same (it was left out, and its last tracks stayed for good); the owner back calls it off."""
    msgs, *_ = _reference()
    _, _, engines = run_partitioned(msgs, 2, 0)
    one = engines[0]
    theirs = [r for r in "ABC" if Partition(1, 2).owner(r) == 2]
    assert theirs and all(r in one.peers.receiver.radars() for r in theirs)
    gap = theirs[0]
    assert len(one.publication.tables[gap][1])  # its last tracks
    one.peers.receiver.forget(gap)  # (what a gap does to it)
    one.wait_for({1})
    # its last table's time unknown, it expires at once: its tracks gone from every output
    assert len(one.publication.tables[gap][1]) == 0 and not one.merger.expiring(gap)
    assert all(one.merger.expiring(r) for r in theirs[1:])  # the others after source_expiry_s
    one.wait_for({1, 2})
    assert not any(one.merger.expiring(r) for r in theirs)


def test_a_late_table_never_takes_a_pair_back_in_data_time() -> None:
    """A table released out of order (a worker back after the grace) is older than the pairs
    it would update: they keep their book and publish nothing older than they have published
    (a subscriber sees every pair's updates in data-time order)."""
    msgs = scenario_messages("three-radar", duration_s=60.0, seed=2)
    _, engine = run_one(msgs)
    stage = engine.correlation.stage  # type: ignore[attr-defined]
    assert stage.views
    key = next(iter(sorted(stage.views)))
    view, corr = stage.views[key], stage.pair_correlators[key]
    rid = key[0]
    geometry = engine.tracking.tracked[rid].geometry
    table = engine.tracking.tracked[rid].table.by_id()
    stage.next_due[key] = -np.inf  # due for a whole update, and still not taken back
    updated = stage.radar(rid, geometry, table, view.time_s - 10.0)
    assert key not in updated
    assert stage.views[key] is view and corr.time_s <= view.time_s
    # at the pair's own time or later it is correlated as ever
    later = stage.radar(rid, geometry, table, view.time_s + 60.0)
    assert key in later and stage.views[key].time_s == view.time_s + 60.0


def test_the_merge_says_how_far_it_has_released_when_a_cap_holds_tables_back() -> None:
    """A worker whose merge a cap holds back (the cycle step: at most ``lag_s`` ahead of the
    others) says it released everything up to just short of its oldest table held, not only
    up to the cap: the workers waiting for it must hear that, or two capped workers wait for
    each other forever."""
    merger = TableMerger()
    merger.progress(1, 30.0)
    merger.push(RADAR, "A", 1, 12.0, "A@12")
    merger.push(RADAR, "A", 2, 17.0, "A@17")
    assert [r.item for r in merger.release({1}, cap=10.0)] == []
    assert merger.last_limit == 10.0
    assert merger.through({1}) == np.nextafter(12.0, -np.inf)  # nothing below 12 s is held
    assert [r.item for r in merger.release({1}, cap=15.0)] == ["A@12"]
    assert merger.through({1}) == np.nextafter(17.0, -np.inf)
    assert [r.item for r in merger.release({1})] == ["A@17"]
    assert merger.through({1}) == 30.0  # nothing held: as far as every owner published
    merger.progress(1, 40.0)
    merger.push(RADAR, "A", 3, 35.0, "A@35")
    assert merger.through({1}) == np.nextafter(35.0, -np.inf)  # not released yet: held


@pytest.mark.slow
@pytest.mark.parametrize(("n", "seed"), [(2, 7), (3, 8)])
def test_a_radar_s_pairs_with_a_reference_go_with_the_radar_and_so_does_its_assessment(
    n: int, seed: int
) -> None:
    """A pair of a radar and a reference source (ADS-B) is correlated by the radar's owner, the
    one worker with the radar's plots; so that worker measures the radar against the
    reference exactly as one worker does (contract §5.3), and the pair updates of N workers,
    radar pairs and reference pairs, are one worker's."""
    lab = pytest.importorskip("topofusion_lab.scenarios.simulator")
    msgs = scenario_messages(
        "three-radar", duration_s=120.0, seed=3, adsb=(lab.AdsbSpec("ads-b", identity=True),)
    )
    one, single = run_one(msgs)
    single.flush()
    many, publishers, engines = run_partitioned(msgs, n, seed)
    for engine in engines:
        engine.flush()
    with_reference = [k for k in one if k.endswith("/ads-b")]
    assert len(with_reference) == 3, sorted(one)
    assert sorted(many) == sorted(one)
    for key in one:
        assert many[key] == one[key][: len(many[key])] and len(many[key]) >= len(one[key]) - 1, key
    owner = {rid: Partition(1, n).owner(rid) for rid in "ABC"}
    assert len(set(owner.values())) > 1  # the radars' owners differ: the rule is put to work
    for key in with_reference:
        radar = key.split("/")[-2]
        assert publishers[key] == {owner[radar]}, (key, publishers[key], owner)
    want = single.snapshot()
    for rid in "ABC":
        got = engines[owner[rid] - 1].snapshot().radar_performance(rid)
        assert got is not None and got["detection"]["pd"] is not None, rid
        assert got == want.radar_performance(rid), rid


def test_the_partition_command_lists_a_radar_s_reference_pairs_with_its_owner(
    capsys: pytest.CaptureFixture[str],
) -> None:
    """``topofusion partition --reference ID``: each worker's pairs with the reference sources
    are those of the radars it owns, as :meth:`Partition.owns_pair` decides them."""
    import argparse

    from service.cli.admin import partition_main

    refs = ["ads-b", "ais-1"]
    args = argparse.Namespace(
        count=3, sites=None, ids=list("ABCDE"), reference=refs, salt=0, balance=False, pair_km=600.0
    )
    assert partition_main(args) == 0
    listed = {}
    for block in capsys.readouterr().out.split("worker ")[1:]:
        k = int(block.split("/")[0])
        line = next((ln for ln in block.splitlines() if "with references:" in ln), "")
        listed[k] = set(line.split(":", 1)[1].split()) if line else set()
    want = {
        k: {
            f"{min(r, x)}/{max(r, x)}" for r in "ABCDE" for x in refs if Partition(k, 3).owns_pair(r, x, refs)
        }
        for k in (1, 2, 3)
    }
    assert listed == want
    assert sum(len(v) for v in want.values()) == 10
    assert all(Partition(k, 3).owns(p.split("/")[0]) for k, v in want.items() for p in v)


@pytest.mark.parametrize("payload", [b"[1, 2]", b"null", b"3", b'"tracks"'])
def test_a_peer_message_that_is_json_but_not_an_object_is_malformed_json(payload: bytes) -> None:
    """Contract §2.8: ``malformed_json`` is a payload that is not JSON or not the JSON object a
    message needs, the other workers' messages as the inputs (``schema`` is a wrong field)."""
    from service.pipeline.pair_exchange import decode_links, decode_rows

    for decode in (
        lambda p: decode_states(p, "A"),
        lambda p: decode_links(p, ("A", "B")),
        lambda p: decode_rows(p, ("A", "B")),
    ):
        with pytest.raises(RejectionError) as err:
            decode(payload)
        assert err.value.reason == "malformed_json", (decode, err.value.detail)


def test_workers_owning_one_radar_each_confirm_each_others_first_clocks() -> None:
    """Two workers, one radar each, on a fresh start: each radar's first clock is lone (no other
    source of its worker can check it), and a worker's radar alone proves nothing while other
    sites are known.  The workers tell each other their lone clocks, which agree: both are
    confirmed within a scan or two, and every TrackBatch one worker publishes is published
    (the two had waited for ``max_lag_s`` of data each, nothing released in a shorter run)."""
    msgs = scenario_messages("two-radar", duration_s=25.0)
    salt = next(s for s in range(100) if Partition(1, 2, s).owner("A") != Partition(1, 2, s).owner("B"))
    single = Engine(EngineConfig())
    want = [o.key for m in msgs for o in single.ingest(*m) if o.key.endswith("/tracks")]
    got: list[str] = []

    def heard(worker: int, o: Outgoing) -> None:
        if o.key.endswith("/tracks"):
            got.append(o.key)

    _, _, engines = run_partitioned(msgs, 2, seed=7, salt=salt, heard=heard)
    assert all(not e.sequencer._lone for e in engines)
    for rid in "AB":
        mine = [k for k in want if f"/{rid}/" in k]
        theirs = [k for k in got if f"/{rid}/" in k]
        assert len(mine) - 2 <= len(theirs) <= len(mine) and len(mine) > 5, rid


def test_a_worker_tells_the_others_its_radars_lone_clock_again_when_it_starts_again() -> None:
    """The worker owning radar B, B's first stamp an hour ahead: its clock message names B's
    lone clock there; B's next batch withdraws it and B is lone again at the true time.  The
    worker says so at once (it had waited for B's newest time to move ``exchange.step_s`` on,
    which going back never does, and the others kept the withdrawn span: a corrupted stamp of
    theirs near it was confirmed by it)."""
    msgs = scenario_messages("two-radar", duration_s=20.0)
    salt = next(s for s in range(100) if Partition(1, 2, s).owner("A") != Partition(1, 2, s).owner("B"))
    engine = Engine(EngineConfig(partition=Partition(Partition(1, 2, salt).owner("B"), 2, salt)))
    spans = []
    first = True
    for key, payload in msgs:
        if key.endswith("/B/plots") and first:
            body = json.loads(payload)
            body["time_s"] += 3600.0
            payload, first = json.dumps(body).encode(), False
        for o in engine.ingest(key, payload):
            if o.key.endswith("/clock"):
                spans.append(json.loads(o.payload))
    told = [s["lone_clocks"]["B"][0] for s in spans if "B" in s.get("lone_clocks", {})]
    t0 = min(json.loads(p)["time_s"] for k, p in msgs if k.endswith("/B/plots"))
    assert told[0] > t0 + 3000.0 and told[-1] < t0 + 10.0, told


def test_a_lone_clock_span_back_to_front_is_refused_and_changes_nothing() -> None:
    """Another worker's clock message whose lone clock ends before it begins is no clock:
    rejected whole (schema), counted, and no source of it is held."""
    engine = Engine(EngineConfig(partition=Partition(1, 2)))
    body = {"partition": "2/2", "clocks": {}, "lone_clocks": {"B": [500.0, 100.0]}}
    out = engine.ingest(Keys("fusion").worker_clock(2), json.dumps(body).encode())
    assert "first data time 500.0 is after the newest 100.0" in json.loads(out[0].payload)["detail"]
    assert engine.rejected == {"schema": 1} and "B" not in engine.sequencer.sources
