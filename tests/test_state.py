"""``--state-dir``: what takes minutes to learn survives a restart (service/state, contract §4.6).

Engines fed the simulator's two-radar stream (both radars biased), a state written by the real
keeper into a real directory, and fresh engines restored from it: in process and with the
correlation in its own process, a damaged or foreign file refused, a crash mid-write.
"""

from __future__ import annotations

import json
import logging
import multiprocessing as mp
import os
import shutil
import time
from pathlib import Path
from typing import Any

import pytest

from service.engine import Engine, EngineConfig
from service.pipeline.partition import Partition
from service.state import StateKeeper
from service.state.fileformat import decode, encode
from service.wire.keys import Keys
from service.wire.outgoing import Outgoing
from tests.scenario_helpers import scenario_messages

STATE = "state.bin"


@pytest.fixture(scope="module")
def stream() -> list[tuple[str, bytes]]:
    return scenario_messages("two-radar", duration_s=120.0)


def _split(stream: list[tuple[str, bytes]]) -> tuple[list[tuple[str, bytes]], list[tuple[str, bytes]]]:
    """The first 90 s (sites, then batches: biases are solved by then) and the batches after."""
    cut = len(stream) * 3 // 4
    return stream[:cut], stream[cut:]


def _feed(
    engine: Engine, messages: list[tuple[str, bytes]], keeper: StateKeeper | None = None
) -> list[Outgoing]:
    out = []
    for key, payload in messages:
        out.extend(engine.ingest(key, payload, receive_time_s=0.0))
        if keeper is not None:
            keeper.maybe_save(engine)
    return out


def _track_ids(out: list[Outgoing], radar: str) -> set[str]:
    return {
        t["track_id"]
        for o in out
        if o.key == f"fusion/radar/{radar}/tracks"
        for t in json.loads(o.payload)["tracks"]
    }


def _errors(out: list[Outgoing]) -> list[dict[str, Any]]:
    return [json.loads(o.payload) for o in out if o.key == "fusion/errors"]


def _radar(engine: Engine, rid: str) -> dict[str, Any]:
    return next(r for r in engine.snapshot().status_core()["radars"] if r["radar_id"] == rid)


@pytest.fixture(scope="module")
def written(stream: list[tuple[str, bytes]], tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A state file as a first run (in process) left it at a graceful stop, after 90 s."""
    directory = tmp_path_factory.mktemp("written")
    engine = Engine(EngineConfig())
    keeper = StateKeeper(directory, "fusion", "1/1")
    keeper.restore(engine)
    _feed(engine, _split(stream)[0], keeper)
    keeper.save(engine)
    return directory / STATE


@pytest.mark.parametrize("process", [False, True], ids=["in-process", "correlation-process"])
def test_a_restart_keeps_sites_biases_seq_and_moves_the_id_epoch(
    stream: list[tuple[str, bytes]], tmp_path: Path, caplog: pytest.LogCaptureFixture, process: bool
) -> None:
    caplog.set_level(logging.INFO, logger="service.state")
    first, rest = _split(stream)
    engine = Engine(EngineConfig(), correlation_process=process)
    try:
        keeper = StateKeeper(tmp_path, "fusion", "1/1", interval_s=30.0)
        keeper.restore(engine)
        assert keeper.epoch == 0 and "none yet" in caplog.text
        out = _feed(engine, first, keeper)
        keeper.wait()
        # a periodic write has come (with the correlation process: its answer with a later
        # message), with the registration rows of the pair
        header, tree = decode((tmp_path / STATE).read_bytes(), "fusion", "1/1")
        assert header.data_clock_s is not None and tree["correlation"]["memories"]
        out += engine.flush()
        keeper.save(engine)
        biases = engine.snapshot().biases()
        before_ids = _track_ids(out, "A") | _track_ids(out, "B")
        systems_before = {
            t["system_track_id"] for t in engine.snapshot().system_tracks("all")["system_tracks"]
        }
        last_a = max(json.loads(p)["seq"] for k, p in first if k == "fusion/radar/A/plots")
    finally:
        engine.close()
    assert len(biases) == 2 and before_ids and systems_before

    caplog.clear()
    engine = Engine(EngineConfig(), correlation_process=process)
    try:
        keeper = StateKeeper(tmp_path, "fusion", "1/1", interval_s=30.0)
        keeper.restore(engine)
        assert keeper.epoch == 1
        assert "restored 2 radar sites" in caplog.text and "track-id epoch 1" in caplog.text
        # GET /biases answers at once, with the values of before
        restored = engine.snapshot().biases()
        assert restored == biases
        for now, then in zip(restored, biases, strict=True):
            assert abs(now["range_bias_m"] - then["range_bias_m"]) <= 0.1 * abs(then["range_bias_m"])
        # the radars' sites are known: their batches are taken without a new site message;
        # A's next four batches are lost on the way, and its last batch before comes again
        rest_a = [i for i, (k, _) in enumerate(rest) if k == "fusion/radar/A/plots"]
        replay = next(p for k, p in first if k == "fusion/radar/A/plots" and json.loads(p)["seq"] == last_a)
        after = [m for i, m in enumerate(rest) if i not in rest_a[:4]]
        out = _feed(engine, [("fusion/radar/A/plots", replay), *after], keeper)
        out += engine.flush()
        errors = _errors(out)
        assert [e["reason"] for e in errors] == ["duplicate_seq"], errors
        assert _radar(engine, "A")["lost_batches"] == 4 and _radar(engine, "B")["lost_batches"] == 0
        assert _radar(engine, "A")["batches"] == len(rest_a) - 4
        # new track ids (radars and system) are of epoch 1: none of the first run's comes again
        after_ids = _track_ids(out, "A") | _track_ids(out, "B")
        assert after_ids and not after_ids & before_ids
        assert all(int(t.rsplit("-", 1)[1]) > 10**9 for t in after_ids)
        systems = {t["system_track_id"] for t in engine.snapshot().system_tracks("all")["system_tracks"]}
        assert systems and not systems & systems_before
        assert all(int(t.rsplit("-", 1)[1]) > 10**9 for t in systems)
        # the pair registers from the kept memory: its pairs confirm again and the biases go on
        assert engine.snapshot().status_core()["pairs_confirmed"] > 0
        assert engine.snapshot().biases()[0]["time_s"] > biases[0]["time_s"]
    finally:
        engine.close()


def test_a_publisher_restarted_behind_the_restored_clock_is_told_why(
    written: Path, stream: list[tuple[str, bytes]], tmp_path: Path
) -> None:
    """A simulator run again from its start after a restart: its batches are behind the kept
    clock, and the rejection says by how much and what to do."""
    shutil.copy(written, tmp_path / STATE)
    engine = Engine(EngineConfig())
    StateKeeper(tmp_path, "fusion", "1/1").restore(engine)
    first_a = next(p for k, p in stream if k == "fusion/radar/A/plots")
    (err,) = _errors(engine.ingest("fusion/radar/A/plots", first_a))
    assert err["reason"] == "duplicate_seq"
    assert "behind this source's data clock (restored from the state file" in err["detail"]
    assert "--start-time resume" in err["detail"]


def _later(payload: bytes, shift_s: float) -> bytes:
    """A plot batch as it would come ``shift_s`` later (batch and plot times)."""
    body = json.loads(payload)
    body["time_s"] += shift_s
    body["plots"]["time_s"] = [t + shift_s for t in body["plots"]["time_s"]]
    return json.dumps(body).encode()


def test_a_restart_after_an_hour_down_takes_the_radars_at_once(
    written: Path, stream: list[tuple[str, bytes]], tmp_path: Path
) -> None:
    """The kept clocks are an hour old when the data comes back: they judge each radar's own
    numbering, not whether the new batches' clocks are plausible (they would all look an hour
    ahead of the kept ones)."""
    shutil.copy(written, tmp_path / STATE)
    engine = Engine(EngineConfig())
    StateKeeper(tmp_path, "fusion", "1/1").restore(engine)
    assert [r["expired"] for r in engine.snapshot().status_core()["radars"]] == [True, True]
    rest = _split(stream)[1]
    out = _feed(engine, [(k, _later(p, 3600.0)) for k, p in rest])
    assert _errors(out) == []
    for rid in ("A", "B"):
        radar = _radar(engine, rid)
        assert radar["batches"] == sum(k == f"fusion/radar/{rid}/plots" for k, _ in rest)
        assert radar["lost_batches"] == 0 and not radar["expired"] and radar["tracks_confirmed"] > 0


def _damaged(written: Path, directory: Path, how: str) -> StateKeeper:
    """A copy of ``written`` in ``directory``, damaged ``how``; the keeper that will read it."""
    path = directory / STATE
    data = bytearray(written.read_bytes())
    prefix, partition = "fusion", "1/1"
    if how == "corrupt":
        data[len(data) // 2] ^= 0x01
    elif how == "truncated":
        data = data[: len(data) - 1000]
    elif how == "version":
        data[16:20] = (2).to_bytes(4, "big")
    elif how == "prefix":
        prefix = "other"
    elif how == "partition":
        partition = "1/2"
    path.write_bytes(bytes(data))
    return StateKeeper(directory, prefix, partition)


@pytest.mark.parametrize(
    ("how", "why"),
    [
        ("corrupt", "checksum mismatch"),
        ("truncated", "checksum mismatch"),
        ("version", "format version 2, this service reads version 1"),
        ("prefix", "written for prefix 'fusion' partition 1/1, this service runs prefix 'other'"),
        (
            "partition",
            "written for prefix 'fusion' partition 1/1, this service runs prefix 'fusion' partition 1/2",
        ),
    ],
)
def test_a_damaged_or_foreign_file_is_refused_renamed_and_the_engine_starts_clean(
    written: Path,
    stream: list[tuple[str, bytes]],
    tmp_path: Path,
    caplog: pytest.LogCaptureFixture,
    how: str,
    why: str,
) -> None:
    caplog.set_level(logging.INFO, logger="service.state")
    keeper = _damaged(written, tmp_path, how)
    damaged = (tmp_path / STATE).read_bytes()
    engine = Engine(EngineConfig())
    keeper.restore(engine)
    [record] = [r for r in caplog.records if r.name.startswith("service.state")]
    line = record.getMessage()
    assert record.levelno == logging.WARNING
    assert f"state {tmp_path / STATE} refused ({why}" in line, line
    assert "renamed to state.bin.refused, starting clean" in line
    assert (tmp_path / "state.bin.refused").read_bytes() == damaged
    # ... clean: no site, no bias; but the refused file's epoch still counts (its header says 0)
    assert engine.snapshot().biases() == [] and engine.snapshot().sites == {}
    assert keeper.epoch == 1
    plots = next(p for k, p in _split(stream)[1] if k == "fusion/radar/A/plots")
    assert [e["reason"] for e in _errors(engine.ingest("fusion/radar/A/plots", plots))] == ["unknown_radar"]
    # and a new file of the clean state is written at once, which the next start takes
    assert decode((tmp_path / STATE).read_bytes(), keeper.prefix, keeper.partition)[0].epoch == 1


def test_content_the_engine_cannot_take_is_refused_and_changes_nothing(
    written: Path, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """A whole file of this format whose content is not a state (here a registration memory
    with a row missing from one column): refused before the engine changed at all."""
    header, tree = decode(written.read_bytes(), "fusion", "1/1")
    rows = tree["correlation"]["memories"][0]["rows"]
    rows["p_a"] = rows["p_a"][:-1]
    (tmp_path / STATE).write_bytes(encode(header, tree))
    engine = Engine(EngineConfig())
    keeper = StateKeeper(tmp_path, "fusion", "1/1")
    keeper.restore(engine)
    assert "refused (unreadable content (ValueError: registration memory column p_a" in caplog.text
    assert engine.snapshot().sites == {} and engine.snapshot().biases() == [] and not engine.sequencer.sources
    assert keeper.epoch == 1


def test_a_file_from_nowhere_is_refused(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    (tmp_path / STATE).write_bytes(b"hello, this is not a state file at all, but long enough to look")
    keeper = StateKeeper(tmp_path, "fusion", "1/1")
    keeper.restore(Engine(EngineConfig()))
    assert "refused (not a TopoFusion state file (no magic string))" in caplog.text
    assert keeper.epoch == 0


def test_writes_are_periodic_on_data_time(stream: list[tuple[str, bytes]], tmp_path: Path) -> None:
    engine = Engine(EngineConfig())
    keeper = StateKeeper(tmp_path, "fusion", "1/1", interval_s=30.0)
    keeper.restore(engine)
    first = _split(stream)[0]
    clocks = []
    written = os.stat(tmp_path / STATE).st_mtime_ns
    for key, payload in first:
        engine.ingest(key, payload, receive_time_s=0.0)
        keeper.maybe_save(engine)
        keeper.wait()
        if os.stat(tmp_path / STATE).st_mtime_ns != written:
            written = os.stat(tmp_path / STATE).st_mtime_ns
            clocks.append(decode((tmp_path / STATE).read_bytes(), "fusion", "1/1")[0].data_clock_s)
    t0 = json.loads(first[2][1])["time_s"]  # the first batch's: the baseline
    t_end = json.loads(first[-1][1])["time_s"]
    # one write per 30 s of data time (at the first batch at or past it), however fast the
    # messages came (here: as fast as the engine took them)
    assert len(clocks) == int((t_end - t0) // 30.0)
    for a, b in zip([t0, *clocks], clocks, strict=False):
        assert 30.0 <= b - a < 31.0


def test_a_failed_write_is_counted_and_logged_and_the_next_one_goes_on(
    stream: list[tuple[str, bytes]], tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    engine = Engine(EngineConfig())
    directory = tmp_path / "state"
    keeper = StateKeeper(directory, "fusion", "1/1", interval_s=30.0)
    keeper.restore(engine)
    assert keeper.status()["writes"] == 1 and keeper.status()["failures"] == 0
    first = _split(stream)[0]
    half = len(first) // 2
    shutil.rmtree(directory)  # the directory goes away under the service (an unmounted disk)
    with caplog.at_level(logging.ERROR):
        for key, payload in first[:half]:
            engine.ingest(key, payload, receive_time_s=0.0)
            keeper.maybe_save(engine)
            keeper.wait()
    assert keeper.status()["failures"] >= 1 and "not written" in caplog.text
    directory.mkdir()
    for key, payload in first[half:]:
        engine.ingest(key, payload, receive_time_s=0.0)
        keeper.maybe_save(engine)
        keeper.wait()
    status = keeper.status()
    assert status["writes"] >= 2  # the next due write went on, into the directory back again
    assert f"state {directory / STATE} written again after {status['failures']} failed writes" in caplog.text
    on_disk = decode((directory / STATE).read_bytes(), "fusion", "1/1")[0]
    assert status["data_time_s"] == on_disk.data_clock_s is not None


def test_a_crash_mid_write_leaves_the_previous_whole_file(written: Path, tmp_path: Path) -> None:
    """A process writing the state over and over is killed (SIGKILL) at some moment: the file
    is always a whole one, and the temporary file a cut write left is deleted at the start."""
    shutil.copy(written, tmp_path / STATE)
    child = mp.get_context("fork").Process(target=_write_forever, args=(tmp_path,), daemon=True)
    child.start()
    try:
        deadline = time.monotonic() + 30
        while (tmp_path / "started").exists() is False and time.monotonic() < deadline:
            time.sleep(0.01)
        time.sleep(0.3)
    finally:
        child.kill()
        child.join(10)
    decode((tmp_path / STATE).read_bytes(), "fusion", "1/1")  # whole: no exception
    (tmp_path / "state.bin.x1y2z3.tmp").write_bytes(b"half a state")  # as a cut write leaves it
    engine = Engine(EngineConfig())
    keeper = StateKeeper(tmp_path, "fusion", "1/1")
    keeper.restore(engine)
    assert engine.snapshot().biases() and set(engine.snapshot().sites) == {"A", "B"}
    assert not list(tmp_path.glob("*.tmp")) and not (tmp_path / "state.bin.refused").exists()


def _write_forever(directory: Path) -> None:
    engine = Engine(EngineConfig())
    keeper = StateKeeper(directory, "fusion", "1/1")
    keeper.restore(engine)
    (directory / "started").touch()
    while True:
        keeper.save(engine)


def test_partitioned_workers_each_keep_their_own(tmp_path: Path) -> None:
    """Two workers on one stream: worker 1 (the bias worker) keeps the rows every worker's pairs
    added and its solution, worker 2 its own pairs' rows and the biases worker 1 published;
    after a restart both answer GET /biases at once with the estimate of before."""
    msgs = scenario_messages("three-radar", duration_s=60.0, seed=2)
    keys = Keys("fusion")
    engines = [Engine(EngineConfig(partition=Partition(k, 2))) for k in (1, 2)]
    keepers = [StateKeeper(tmp_path / f"worker-{k}", "fusion", f"{k}/2") for k in (1, 2)]
    for engine, keeper in zip(engines, keepers, strict=True):
        keeper.restore(engine)
    queues: list[list[tuple[str, bytes]]] = [[], []]
    for message in msgs:
        queues[0].append(message)
        queues[1].append(message)
        while any(queues):
            for j in (0, 1):
                batch, queues[j] = queues[j], []
                for key, payload in batch:
                    for o in engines[j].ingest(key, payload):
                        if keys.classify_peer(o.key) is not None:
                            queues[1 - j].append((o.key, o.payload))
                    keepers[j].maybe_save(engines[j])
    want = engines[0].snapshot().biases()
    assert want and engines[1].snapshot().biases() == want
    for engine, keeper in zip(engines, keepers, strict=True):
        keeper.save(engine)
    pairs = [("A", "B"), ("A", "C"), ("B", "C")]
    # worker 1 holds every pair's rows (its own and mirrored), worker 2 only its own pairs'
    assert len(engines[0].export_state().correlation["memories"]) == len(pairs)
    own = sum(Partition(2, 2).owns_pair(a, b) for a, b in pairs)
    assert len(engines[1].export_state().correlation["memories"]) == own
    for k in (1, 2):
        fresh = Engine(EngineConfig(partition=Partition(k, 2)))
        keeper = StateKeeper(tmp_path / f"worker-{k}", "fusion", f"{k}/2")
        keeper.restore(fresh)
        assert keeper.epoch == 1 and fresh.snapshot().biases() == want
    # one worker's directory is not another's
    keeper = StateKeeper(tmp_path / "worker-1", "fusion", "2/2")
    keeper.restore(Engine(EngineConfig(partition=Partition(2, 2))))
    assert (tmp_path / "worker-1" / "state.bin.refused").exists()


def test_the_state_file_is_bounded_by_the_memories(written: Path) -> None:
    """The size the keeper's docstring gives: about 130 bytes a remembered row and 4 bytes per
    character of its two track ids; the rest is small."""
    _, tree = decode(written.read_bytes(), "fusion", "1/1")
    rows = [m["rows"] for m in tree["correlation"]["memories"]]
    n = sum(len(r["time"]) for r in rows)
    per_row = 128 + max(r["pair"].dtype.itemsize for r in rows)
    assert n > 0 and os.path.getsize(written) < n * per_row + 20_000


def test_the_restore_line_counts_the_bias_set_a_later_worker_keeps() -> None:
    """A partitioned worker other than 1 keeps the bias set worker 1 published, not a joint
    solution of its own: its restore line counts those (it said "biases of 0 radars" while
    ``/biases`` answered with them at once)."""
    from service.pipeline.restart import EngineState

    published = {"time_s": 1.0, "partition": "1/2", "biases": [{"radar_id": "A"}, {"radar_id": "B"}]}
    state = EngineState([], [], {}, published, {"memories": [], "joint": None}, None)
    assert state.summary().endswith("biases of 2 radars (as published)")
    alone = EngineState([], [], {}, None, {"memories": [], "joint": None}, None)
    assert alone.summary().endswith("biases of 0 radars")
