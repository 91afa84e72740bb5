"""Recording and replaying over a real Zenoh router on a free loopback port."""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import threading
from collections.abc import Iterator
from pathlib import Path

import pytest
import zenoh
from mcap.reader import make_reader
from recording_helpers import PREFIX, plots, site, wait_for, wait_subscribed

from service.recording import (
    RecordingReader,
    ReplayOptions,
    add_record_arguments,
    add_replay_arguments,
    record,
    record_main,
    replay,
    replay_main,
)
from service.recording.publisher import ZenohReplayPublisher
from service.recording.recorder import ReceivedSample, Recorder, RecordReport
from service.recording.replay import paced
from service.transport.ingest_queue import BoundedQueue
from service.transport.session import ZenohOptions, open_session

TRACKS = f"{PREFIX}/radar/A/tracks"


@pytest.fixture
def session_factory(router: str) -> Iterator[object]:
    opened: list[zenoh.Session] = []

    def make() -> zenoh.Session:
        s = open_session(ZenohOptions(mode="client", connect=(router,)))
        opened.append(s)
        return s

    try:
        yield make
    finally:
        for s in opened:
            s.close()


def _publish_run(session: zenoh.Session, radar: str, seqs: range) -> list[tuple[str, bytes]]:
    sent = [(f"{PREFIX}/radar/{radar}/site", site(radar))]
    sent += [(f"{PREFIX}/radar/{radar}/plots", plots(radar, i, 1e9 + i)) for i in seqs]
    for key, payload in sent:
        session.put(
            key,
            payload,
            encoding=zenoh.Encoding.APPLICATION_JSON,
            congestion_control=zenoh.CongestionControl.BLOCK,
        )
    return sent


def test_record_survives_a_publisher_that_disappears_and_replays_exactly(
    tmp_path: Path, session_factory: object
) -> None:
    make = session_factory  # type: ignore[assignment]
    out = tmp_path / "live.mcap"
    rec_session = make()  # type: ignore[operator]
    recorder = Recorder(rec_session, out, f"{PREFIX}/**", PREFIX).start()
    try:
        first = make()  # type: ignore[operator]
        wait_subscribed(first, f"{PREFIX}/radar/A/plots")
        sent = _publish_run(first, "A", range(0, 60))
        first.put(TRACKS, b'{"radar_id":"A","time_s":1.0,"tracks":[]}')
        wait_for(
            lambda: sum(recorder._writer.totals.by_key.get(k, _Zero).messages for k, _ in sent[:2]) >= 61
        )
        first.close()  # the publisher disappears ...
        second = make()  # type: ignore[operator]
        sent += _publish_run(second, "B", range(0, 40))  # ... and another one comes
        wait_for(lambda: recorder._writer.totals.messages >= len(sent) + 1)
    finally:
        report = recorder.stop()
    assert report.dropped == 0 and report.error is None
    assert report.messages_by_key[f"{PREFIX}/radar/A/plots"] == 60
    assert report.messages_by_key[f"{PREFIX}/radar/B/plots"] == 40
    assert report.messages_by_key[TRACKS] == 1
    assert report.file_bytes == out.stat().st_size > 0
    with open(out, "rb") as f:
        recorded = [(c.topic, m) for _, c, m in make_reader(f).iter_messages(log_time_order=True)]
    assert [(k, m.data) for k, m in recorded if k != TRACKS] == sent  # bytes unchanged, order kept
    # The router stamps samples: publish_time is the Zenoh timestamp, within a second of receipt.
    assert all(abs(m.log_time - m.publish_time) < 10**9 for _, m in recorded)

    # Replay at speed 0 into a subscriber: inputs only, same bytes, same order, JSON encoding.
    got: list[tuple[str, bytes, str]] = []
    sub_session = make()  # type: ignore[operator]
    sub = sub_session.declare_subscriber(
        f"{PREFIX}/**", lambda s: got.append((str(s.key_expr), s.payload.to_bytes(), str(s.encoding)))
    )
    try:
        pub_session = make()  # type: ignore[operator]
        with ZenohReplayPublisher(pub_session) as publish:
            report2 = replay(out, publish, PREFIX, ReplayOptions(speed=0), progress=False)
        wait_for(lambda: len(got) >= len(sent))
    finally:
        sub.undeclare()
    assert report2.messages == len(sent)
    assert [(k, p) for k, p, _ in got] == sent
    assert {e for _, _, e in got} == {"application/json"}


class _ZeroCount:
    messages = 0


_Zero = _ZeroCount()


def test_record_stops_after_duration_and_reports(tmp_path: Path, session_factory: object) -> None:
    make = session_factory  # type: ignore[assignment]
    out = tmp_path / "short.mcap"
    report = record(make(), out, f"{PREFIX}/**", PREFIX, duration_s=0.3)  # type: ignore[operator]
    assert report.messages == 0 and report.error is None
    with RecordingReader(out) as reader:
        assert reader.damage is None  # a finished, valid (empty) MCAP file
        assert reader.survey().channels == {}


def test_full_queue_drops_are_counted_per_key_and_reported_loudly() -> None:
    q = BoundedQueue(max_items=2, max_bytes=10**6)
    for i in range(5):
        key = f"k/{i % 2}"
        q.put(ReceivedSample(key=key, payload=b"x", log_time_ns=i, publish_time_ns=None), 1, key)
    assert len(q) == 2 and q.dropped == {"k/0": 2, "k/1": 1}
    big = BoundedQueue(max_items=100, max_bytes=10)
    assert big.put(ReceivedSample("a", b"x" * 50, 0, None), 50, "a")  # one oversized sample still passes
    assert not big.put(ReceivedSample("a", b"x", 0, None), 1, "a")
    report = RecordReport(path="f.mcap", key_expr="x/**", messages_by_key={"k/0": 1}, bytes_by_key={"k/0": 1})
    report.dropped_by_key = dict(q.dropped)
    assert any(line.startswith("WARNING: 3 samples DROPPED") for line in report.lines())


def _parser(add: object) -> argparse.ArgumentParser:
    p = argparse.ArgumentParser()
    p.add_argument("--prefix", default=PREFIX)
    add(p)  # type: ignore[operator]
    return p


def test_record_main_and_replay_main(tmp_path: Path, router: str, capsys: pytest.CaptureFixture[str]) -> None:
    options = ZenohOptions(mode="client", connect=(router,))
    out = tmp_path / "cli.mcap"
    args = _parser(add_record_arguments).parse_args(["--out", str(out), "--duration", "5"])
    stop = threading.Event()
    result: dict[str, int] = {}
    thread = threading.Thread(target=lambda: result.setdefault("rc", record_main(args, options, stop)))
    thread.start()
    pub = open_session(options)
    try:
        wait_subscribed(pub, f"{PREFIX}/radar/A/plots")
        sent = _publish_run(pub, "A", range(0, 20))
        threading.Event().wait(0.5)
        stop.set()
        thread.join(timeout=20)
    finally:
        pub.close()
    assert result["rc"] == 0
    text = capsys.readouterr().out
    assert f"{PREFIX}/radar/A/plots" in text and "recorded" in text
    with RecordingReader(out) as reader:
        msgs = list(reader.messages(list(reader.survey().channels.values())))
    assert [(m.key, m.payload) for m in msgs] == sent

    offline = tmp_path / "result.json"
    rargs = _parser(add_replay_arguments).parse_args([str(out), "--offline", "--out", str(offline)])
    try:
        import service.engine  # noqa: F401
    except ImportError:
        pytest.skip("engine not available")
    assert replay_main(rargs, options) == 0
    body = json.loads(offline.read_text())
    assert set(body) == {"tracks", "pairs", "biases", "replay"}
    assert body["replay"]["messages"] == len(msgs)


def test_replay_main_errors_are_clear(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(b"PK\x03\x04 zip, not mcap")
    options = ZenohOptions(mode="client", connect=("tcp/127.0.0.1:9",))
    args = _parser(add_replay_arguments).parse_args([str(bad), "--offline"])
    assert replay_main(args, options) == 2
    assert "is not an MCAP file" in capsys.readouterr().err
    args = _parser(add_replay_arguments).parse_args([str(tmp_path / "missing.mcap"), "--offline"])
    assert replay_main(args, options) == 2
    assert "missing.mcap" in capsys.readouterr().err


class _FakeTime:
    def __init__(self) -> None:
        self.now = 100.0
        self.waits: list[float] = []

    def clock(self) -> float:
        return self.now

    def is_set(self) -> bool:
        return False

    def wait(self, delay: float) -> bool:
        self.waits.append(delay)
        self.now += delay
        return False


def test_pacing_follows_log_time_scaled_by_speed() -> None:
    from service.recording.reader import RecordedMessage

    msgs = [RecordedMessage("k", "other", b"", 10**9 * t, 0, 0) for t in (0, 1, 1, 3, 7)]
    fake = _FakeTime()
    out = list(paced(iter(msgs), speed=10.0, stop=fake, clock=fake.clock))  # type: ignore[arg-type]
    assert out == msgs
    assert fake.waits == pytest.approx([0.1, 0.2, 0.4])
    fake0 = _FakeTime()
    assert list(paced(iter(msgs), speed=0.0, stop=fake0, clock=fake0.clock)) == msgs  # type: ignore[arg-type]
    assert fake0.waits == []


@pytest.mark.skipif(sys.platform == "win32", reason="POSIX signals")
def test_sigterm_finishes_the_file(tmp_path: Path, router: str) -> None:
    out = tmp_path / "signal.mcap"
    cmd = [
        sys.executable,
        "-m",
        "service",
        "record",
        "--out",
        str(out),
        "--connect",
        router,
        "--prefix",
        PREFIX,
    ]
    proc = subprocess.Popen(
        cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=dict(os.environ)
    )
    try:
        pub = open_session(ZenohOptions(mode="client", connect=(router,)))
        try:
            wait_subscribed(pub, f"{PREFIX}/radar/Z/site", timeout=30)
            for _ in range(10):
                pub.put(f"{PREFIX}/radar/Z/site", site("Z"))
            threading.Event().wait(0.3)
        finally:
            pub.close()
        proc.send_signal(signal.SIGTERM)
        stdout, stderr = proc.communicate(timeout=20)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0, stderr
    assert "recorded" in stdout and f"{PREFIX}/radar/Z/site" in stdout
    with RecordingReader(out) as reader:
        survey = reader.survey()
        assert survey.indexed and reader.damage is None  # summary and footer were written
        assert sum((survey.message_counts or {}).values()) > 0
