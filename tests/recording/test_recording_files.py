"""MCAP files: our writer's shape, reading any contract-shaped file, damaged files."""

from __future__ import annotations

from pathlib import Path

import pytest
from mcap.reader import make_reader
from mcap.writer import CompressionType
from recording_helpers import PREFIX, foreign_mcap, plots, site

from service.recording import (
    NotMcapError,
    NoUsableChannelError,
    RecordingReader,
    RecordingWriter,
    ReplayOptions,
    replay,
)
from service.recording.keys import KeyFilter
from service.recording.reader import select_channels

T0 = 1_763_769_600 * 10**9


def _write_demo(path: Path, n: int = 50, **kwargs: object) -> list[tuple[str, bytes, int]]:
    sent = [(f"{PREFIX}/radar/A/site", site("A"), T0), (f"{PREFIX}/radar/B/site", site("B"), T0 + 1)]
    for i in range(n):
        sent.append(
            (f"{PREFIX}/radar/{'AB'[i % 2]}/plots", plots("AB"[i % 2], i // 2, 1e9 + i), T0 + 10**8 * (i + 1))
        )
    sent.append(
        (f"{PREFIX}/radar/A/tracks", b'{"radar_id":"A","time_s":1.0,"tracks":[]}', T0 + 10**8 * (n + 1))
    )
    sent.append((f"{PREFIX}/status", b"{}", T0 + 10**8 * (n + 2)))
    with RecordingWriter(path, PREFIX, **kwargs) as w:  # type: ignore[arg-type]
        for key, payload, t in sent:
            w.write(key, payload, t, publish_time_ns=t - 5)
    return sent


def _replayed(path: Path, **options: object) -> list[tuple[str, bytes, int]]:
    out: list[tuple[str, bytes, int]] = []
    opts = ReplayOptions(speed=0, **options)  # type: ignore[arg-type]
    replay(path, lambda m: out.append((m.key, m.payload, m.log_time_ns)), PREFIX, opts, progress=False)
    return out


def test_writer_follows_the_contract_shape(tmp_path: Path) -> None:
    path = tmp_path / "rec.mcap"
    sent = _write_demo(path)
    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None
        topics = {c.topic: c for c in summary.channels.values()}
        assert set(topics) == {k for k, _, _ in sent}  # one channel per key, topic = key
        assert all(c.message_encoding == "json" for c in topics.values())
        schema_names = {t: summary.schemas[c.schema_id].name for t, c in topics.items()}
        assert schema_names[f"{PREFIX}/radar/A/plots"] == "PlotBatch"
        assert schema_names[f"{PREFIX}/radar/A/site"] == "RadarSite"
        assert schema_names[f"{PREFIX}/radar/A/tracks"] == "TrackBatch"
        assert schema_names[f"{PREFIX}/status"] == "Status"
        assert all(s.encoding == "jsonschema" for s in summary.schemas.values())
        got = [
            (c.topic, m.data, m.log_time, m.publish_time)
            for _, c, m in reader.iter_messages(log_time_order=True)
        ]
    assert [(k, p, t) for k, p, t, _ in got] == sent  # payload bytes unchanged, log time = receipt
    assert all(pt == t - 5 for _, _, t, pt in got)
    with RecordingReader(path, PREFIX) as ours:
        survey = ours.survey()
        assert survey.indexed and ours.damage is None  # read through the index, not the fallback scan
        assert survey.start_ns == T0 and sum((survey.message_counts or {}).values()) == len(sent)


def test_log_time_is_made_non_decreasing(tmp_path: Path) -> None:
    path = tmp_path / "rec.mcap"
    with RecordingWriter(path, PREFIX) as w:
        w.write(f"{PREFIX}/radar/A/site", site("A"), T0 + 100)
        w.write(f"{PREFIX}/radar/A/plots", plots("A", 0, 1.0), T0)  # wall clock stepped back
    got = _replayed(path)
    assert [k for k, _, _ in got] == [f"{PREFIX}/radar/A/site", f"{PREFIX}/radar/A/plots"]
    assert got[1][2] == T0 + 100


def test_replay_selects_inputs_by_default_and_all_keys_on_request(tmp_path: Path) -> None:
    path = tmp_path / "rec.mcap"
    sent = _write_demo(path)
    inputs = [s for s in sent if s[0].endswith(("/site", "/plots"))]
    assert _replayed(path) == inputs
    assert _replayed(path, include_outputs=True) == sent
    assert _replayed(path, key_expr=f"{PREFIX}/radar/A/*") == [s for s in inputs if "/A/" in s[0]]


def test_start_and_end_cut_the_recording_by_log_time(tmp_path: Path) -> None:
    path = tmp_path / "rec.mcap"
    sent = _write_demo(path)
    got = _replayed(path, start_s=1.0, end_s=2.0)
    expected = [s for s in sent if s[0].endswith(("/site", "/plots")) and T0 + 10**9 <= s[2] < T0 + 2 * 10**9]
    assert got == expected and len(got) == 10


@pytest.mark.parametrize("chunked", [True, False])
def test_a_foreign_writer_s_file_replays_in_log_time_order(tmp_path: Path, chunked: bool) -> None:
    # Another writer: lz4 or no chunks, small chunks, messages written out of log-time order.
    msgs = [(f"{PREFIX}/radar/A/site", site("A"), T0)]
    msgs += [(f"{PREFIX}/radar/A/plots", plots("A", i, 1e9 + i), T0 + (20 - i) * 10**6) for i in range(20)]
    path = tmp_path / "foreign.mcap"
    foreign_mcap(path, msgs, chunked=chunked, chunk_size=500, with_schema=True)
    got = _replayed(path)
    assert got == sorted(msgs, key=lambda m: m[2])


def test_not_an_mcap_file_is_a_clear_error(tmp_path: Path) -> None:
    bad = tmp_path / "notes.mcap"
    bad.write_text("this is not a recording\n")
    with pytest.raises(NotMcapError, match="not an MCAP file"):
        RecordingReader(bad)
    empty = tmp_path / "empty.mcap"
    empty.write_bytes(b"")
    with pytest.raises(NotMcapError, match="empty"):
        RecordingReader(empty)


def test_no_usable_channel_is_a_clear_error(tmp_path: Path) -> None:
    path = tmp_path / "ros.mcap"
    foreign_mcap(
        path,
        [("/camera/image", b"\x00\x01", T0), (f"{PREFIX}/radar/A/tracks", b"{}", T0 + 1)],
        extra_channels={"/camera/image": "cdr"},
    )
    with RecordingReader(path, PREFIX) as reader, pytest.raises(NoUsableChannelError) as err:
        select_channels(reader.survey(), PREFIX, KeyFilter(None), include_outputs=False)
    text = str(err.value)
    assert "'cdr' is not json" in text and "--all-keys" in text
    with RecordingReader(path, PREFIX) as reader, pytest.raises(NoUsableChannelError, match="prefix 'other'"):
        select_channels(reader.survey(), "other", KeyFilter(None), include_outputs=False)


def _mid_record(data: bytes, near: int) -> int:
    """A byte in the middle of the body of the record (opcode, 8-byte length, body) that holds
    byte ``near``: a cut there ends the file mid-record, wherever the records fall."""
    at = 8  # (the leading magic)
    while True:
        end = at + 9 + int.from_bytes(data[at + 1 : at + 9], "little")
        if end > near:
            return at + 9 + (end - at - 9) // 2
        at = end


def test_a_truncated_recording_replays_what_it_holds_and_says_where(tmp_path: Path) -> None:
    path = tmp_path / "rec.mcap"
    sent = _write_demo(path, n=400, chunk_bytes=4096)  # many small chunks
    data = path.read_bytes()
    cut = tmp_path / "cut.mcap"
    # mid-way through the messages (the footer, 29 bytes before the closing 8-byte magic, says
    # where the summary starts; the schemas it repeats can be half the file), mid-chunk, no
    # summary, no footer
    summary_start = int.from_bytes(data[-37 + 9 : -37 + 17], "little")
    at = _mid_record(data, summary_start // 2)
    cut.write_bytes(data[:at])
    got: list[str] = []
    with RecordingReader(cut, PREFIX) as reader:
        assert not reader.survey().indexed
    report = replay(cut, lambda m: got.append(m.key), PREFIX, ReplayOptions(speed=0), progress=False)
    inputs = [s for s in sent if s[0].endswith(("/site", "/plots"))]
    assert 0 < len(got) < len(inputs)
    assert got == [k for k, _, _ in inputs[: len(got)]]  # a prefix of the recording, in order
    assert report.damage is not None
    assert f"of {at}" in report.damage and "truncated record starting at byte" in report.damage
    assert any("WARNING" in line and "replayed what it holds" in line for line in report.lines())


def test_an_unfinished_recording_cut_at_a_record_boundary(tmp_path: Path) -> None:
    path = tmp_path / "rec.mcap"
    w = RecordingWriter(path, PREFIX)
    w.write(f"{PREFIX}/radar/A/site", site("A"), T0)
    w.write(f"{PREFIX}/radar/A/plots", plots("A", 0, 1.0), T0 + 1)
    w.flush()  # what a killed recorder leaves after its last periodic flush
    size = path.stat().st_size
    got = _replayed(path)
    assert [k for k, _, _ in got] == [f"{PREFIX}/radar/A/site", f"{PREFIX}/radar/A/plots"]
    with RecordingReader(path, PREFIX) as reader:
        list(reader.messages(list(reader.survey().channels.values())))
        assert reader.damage is not None and "without the MCAP footer" in reader.damage.describe()
        assert reader.damage.offset == size
    w.close()


def test_a_corrupt_chunk_in_the_middle_is_skipped_and_reported(tmp_path: Path) -> None:
    path = tmp_path / "rec.mcap"
    sent = _write_demo(path, n=400, chunk_bytes=4096, compression=CompressionType.NONE)
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None and len(summary.chunk_indexes) > 5
    bad_chunk = summary.chunk_indexes[2]
    data = bytearray(path.read_bytes())
    middle = bad_chunk.chunk_start_offset + bad_chunk.chunk_length // 2
    data[middle : middle + 16] = b"\xff" * 16  # caught by the chunk's CRC
    damaged = tmp_path / "damaged.mcap"
    damaged.write_bytes(bytes(data[: summary.chunk_indexes[-1].chunk_start_offset]))  # and no footer
    got: list[bytes] = []
    report = replay(damaged, lambda m: got.append(m.payload), PREFIX, ReplayOptions(speed=0), progress=False)
    inputs = [p for k, p, _ in sent if k.endswith(("/site", "/plots"))]
    assert got and set(got) < set(inputs)
    assert got[-1] == [p for p in inputs if p in set(got)][-1]
    # Messages after the damaged chunk are still there: more than a plain prefix of the input.
    assert got != inputs[: len(got)]
    assert report.damage is not None and f"chunk at byte {bad_chunk.chunk_start_offset}" in report.damage


def test_a_corrupt_chunk_in_a_complete_file_stops_there_and_says_so(tmp_path: Path) -> None:
    path = tmp_path / "rec.mcap"
    sent = _write_demo(path, n=400, chunk_bytes=4096, compression=CompressionType.NONE)
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    bad_chunk = summary.chunk_indexes[3]
    data = bytearray(path.read_bytes())
    middle = bad_chunk.chunk_start_offset + bad_chunk.chunk_length // 2
    data[middle : middle + 16] = b"\xff" * 16
    damaged = tmp_path / "damaged.mcap"
    damaged.write_bytes(bytes(data))  # footer and index intact: the indexed path
    got: list[bytes] = []
    report = replay(damaged, lambda m: got.append(m.payload), PREFIX, ReplayOptions(speed=0), progress=False)
    inputs = [p for k, p, _ in sent if k.endswith(("/site", "/plots"))]
    assert 0 < len(got) < len(inputs) and got == inputs[: len(got)]
    assert report.damage is not None and "unreadable chunk after log time" in report.damage
    # where reading stopped: the damaged chunk's start (not the reader's last seek, the end)
    assert f"damaged at byte {bad_chunk.chunk_start_offset} of {len(data)}" in report.damage
