"""Reading a recording back: any MCAP file of the contract's shape, whoever wrote it.

Two paths:

* a complete, indexed file (summary with chunk indexes) streams in log-time order through the
  ``mcap`` library's seeking reader, holding one chunk at a time;
* a file without a usable summary (the recorder was killed, the disk filled, or the writer
  wrote no index) is scanned record by record from the start; everything up to the first
  damaged byte is kept, sorted by log time (stable: file order breaks ties), and the place
  where reading stopped is reported in :attr:`RecordingReader.damage`.  This path holds the
  file's messages in memory.

Which channels are replayed is decided here too (:func:`select_channels`).
"""

from __future__ import annotations

import io
import os
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import BinaryIO

from mcap.reader import SeekingReader
from mcap.records import Channel, Chunk, Footer, Message, Schema
from mcap.stream_reader import MAGIC_SIZE, StreamReader, breakup_chunk
from mcap.summary import Summary

from service.recording.keys import KeyFilter, is_concrete_key
from service.wire.keys import INPUT_KINDS, KeyKind, classify_key

MCAP_MAGIC = bytes([137, 77, 67, 65, 80, 48, 13, 10])
#: Message encodings read as JSON (the contract writes ``json``).
JSON_ENCODINGS = frozenset({"json", "application/json"})


class RecordingError(Exception):
    """A recording that cannot be replayed at all; the message says why, for an operator."""


class NotMcapError(RecordingError):
    pass


class NoUsableChannelError(RecordingError):
    pass


@dataclass(frozen=True)
class ChannelInfo:
    id: int
    topic: str
    message_encoding: str
    schema_name: str
    kind: KeyKind
    problem: str | None  # why this channel cannot be replayed; None when it can

    @property
    def usable(self) -> bool:
        return self.problem is None


@dataclass(frozen=True)
class RecordedMessage:
    key: str
    kind: KeyKind
    payload: bytes
    log_time_ns: int
    publish_time_ns: int
    sequence: int


@dataclass
class Damage:
    """Where and why reading stopped early (or what had to be skipped)."""

    offset: int  # first byte not read
    file_bytes: int
    detail: str
    skipped: list[str] = field(default_factory=list)  # damaged chunks / orphan messages passed over

    def describe(self) -> str:
        where = f"at byte {self.offset} of {self.file_bytes}"
        text = f"recording damaged {where}: {self.detail}"
        if self.skipped:
            text += f"; skipped: {'; '.join(self.skipped[:5])}"
            if len(self.skipped) > 5:
                text += f" (+{len(self.skipped) - 5} more)"
        return text


@dataclass(frozen=True)
class Survey:
    """What a recording holds, before any message is read."""

    channels: dict[int, ChannelInfo]
    message_counts: dict[int, int] | None  # per channel id, when the file says
    start_ns: int | None  # first log time in the file
    end_ns: int | None
    indexed: bool


def _channel_info(channel: Channel, schemas: dict[int, Schema], prefix: str) -> ChannelInfo:
    schema = schemas.get(channel.schema_id)
    problem = None
    if channel.message_encoding.lower() not in JSON_ENCODINGS:
        problem = f"message_encoding {channel.message_encoding!r} is not json"
    elif not is_concrete_key(channel.topic):
        problem = f"topic {channel.topic!r} is not a concrete Zenoh key"
    return ChannelInfo(
        id=channel.id,
        topic=channel.topic,
        message_encoding=channel.message_encoding,
        schema_name=schema.name if schema is not None else "",
        kind=classify_key(channel.topic, prefix) if problem is None else "other",
        problem=problem,
    )


#: Formats a file given to ``replay`` by mistake is often in, by its first bytes: named in the
#: refusal, so that the operator sees at once what they gave.
_KNOWN_HEADS: tuple[tuple[bytes, str], ...] = (
    (b"\xd4\xc3\xb2\xa1", "a pcap capture (topofusion asterix --file reads those)"),
    (b"\xa1\xb2\xc3\xd4", "a pcap capture (topofusion asterix --file reads those)"),
    (b"\x4d\x3c\xb2\xa1", "a pcap capture (topofusion asterix --file reads those)"),
    (b"\xa1\xb2\x3c\x4d", "a pcap capture (topofusion asterix --file reads those)"),
    (b"\x0a\x0d\x0d\x0a", "a pcapng capture (topofusion asterix --file reads those)"),
    (b"\x1f\x8b", "a gzip file (decompress it first)"),
    (b"\x28\xb5\x2f\xfd", "a zstd file (decompress it first)"),
    (b"PK\x03\x04", "a zip archive"),
    (b"SQLite format 3", "an SQLite database (a ROS 2 bag? convert it to MCAP first)"),
)


#: First octets (the CAT of a data block) of a raw ASTERIX recording of the categories the
#: bridge reads and writes (and their usual companions).
_ASTERIX_CATEGORIES = frozenset({1, 2, 21, 34, 48, 62, 63, 65})


def not_mcap(path: str, head: bytes) -> str:
    """Why ``path``, which starts with ``head``, is refused: what it starts with, and what it
    looks like when that is recognisable."""
    if not head:
        return f"{path} is not an MCAP file (it is empty)"
    known = next((what for magic, what in _KNOWN_HEADS if head.startswith(magic)), None)
    if known is None and head[:1] in (b"{", b"["):
        known = "JSON text"
    if (
        known is None
        and len(head) >= 3
        and head[0] in _ASTERIX_CATEGORIES
        and int.from_bytes(head[1:3], "big") >= 3
    ):
        known = "raw ASTERIX data blocks (topofusion asterix --file reads those)"
    shown = head[:MAGIC_SIZE]
    return (
        f"{path} is not an MCAP file (it starts with {shown!r}, not the MCAP magic {MCAP_MAGIC!r}"
        + (f"; it looks like {known}" if known else "")
        + ")"
    )


def open_recording(path: str | Path) -> BinaryIO:
    """``path`` opened for reading, or :class:`RecordingError` saying in plain words why not."""
    where = Path(path)
    if where.is_dir():
        raise NotMcapError(f"{path} is a directory, not an MCAP file")
    try:
        return open(where, "rb")
    except FileNotFoundError:
        raise RecordingError(f"{path}: no such file") from None
    except PermissionError:
        raise RecordingError(f"{path}: not readable (permission denied)") from None
    except OSError as exc:
        raise RecordingError(f"{path}: cannot be read ({exc.strerror or exc})") from None


def check_recording(path: str | Path) -> None:
    """Raise :class:`RecordingError` (saying why) unless ``path`` is a readable file that starts
    like an MCAP file: the quick check a command makes before it connects to anything."""
    with open_recording(path) as f:
        head = f.read(MAGIC_SIZE)
    if head != MCAP_MAGIC:
        raise NotMcapError(not_mcap(str(path), head))


class RecordingReader:
    """Reads one recording file; use as a context manager."""

    def __init__(self, path: str | Path, prefix: str = "fusion") -> None:
        self.path = str(path)
        self.prefix = prefix
        self.damage: Damage | None = None
        self._file: BinaryIO = open_recording(self.path)
        try:
            self.file_bytes = os.fstat(self._file.fileno()).st_size
            head = self._file.read(MAGIC_SIZE)
            if head != MCAP_MAGIC:
                raise NotMcapError(not_mcap(self.path, head))
            self._summary = self._read_summary()
            self._linear: tuple[dict[int, ChannelInfo], list[RecordedMessage]] | None = None
            self._survey: Survey | None = None
        except BaseException:
            self._file.close()
            raise

    @property
    def indexed(self) -> bool:
        """The file is complete and indexed: its survey reads the summary only."""
        return self._summary is not None

    # -- lifecycle ------------------------------------------------------------------------

    def close(self) -> None:
        self._file.close()

    def __enter__(self) -> RecordingReader:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.close()

    # -- survey ---------------------------------------------------------------------------

    def _read_summary(self) -> Summary | None:
        """The file's summary when it is complete and indexed by chunk, else None."""
        try:
            self._file.seek(0, io.SEEK_SET)
            summary = SeekingReader(self._file, record_size_limit=max(self.file_bytes, 1)).get_summary()
        except Exception:  # no footer: truncated / unfinished file -> linear scan
            return None
        if summary is None or not summary.chunk_indexes:
            return None
        return summary

    def survey(self) -> Survey:
        if self._survey is not None:
            return self._survey
        if self._summary is not None:
            summary = self._summary
            channels = {
                cid: _channel_info(ch, summary.schemas, self.prefix) for cid, ch in summary.channels.items()
            }
            stats = summary.statistics
            counts = dict(stats.channel_message_counts) if stats is not None else None
            start = min(ci.message_start_time for ci in summary.chunk_indexes)
            end = max(ci.message_end_time for ci in summary.chunk_indexes)
            self._survey = Survey(channels, counts, start, end, indexed=True)
        else:
            channels, messages = self._scan()
            scanned: dict[int, int] = {}
            by_topic = {c.topic: c.id for c in channels.values()}
            for m in messages:
                cid = by_topic[m.key]
                scanned[cid] = scanned.get(cid, 0) + 1
            first = messages[0].log_time_ns if messages else None
            last = messages[-1].log_time_ns if messages else None
            self._survey = Survey(channels, scanned, first, last, indexed=False)
        return self._survey

    # -- linear scan ----------------------------------------------------------------------

    def _scan(self) -> tuple[dict[int, ChannelInfo], list[RecordedMessage]]:
        """Every readable message, in log-time order; sets :attr:`damage` when it stops early."""
        if self._linear is not None:
            return self._linear
        self._file.seek(0, io.SEEK_SET)
        stream = StreamReader(self._file, emit_chunks=True, record_size_limit=max(self.file_bytes, 1))
        records = stream.records
        schemas: dict[int, Schema] = {}
        raw_channels: dict[int, Channel] = {}
        infos: dict[int, ChannelInfo] = {}
        messages: list[RecordedMessage] = []
        skipped: list[str] = []
        orphans = 0
        good_end = MAGIC_SIZE
        finished = False
        stop_detail = ""
        while True:
            record_start = good_end
            try:
                record = next(records)
            except StopIteration:
                finished = True
                break
            except Exception as exc:
                if record_start >= self.file_bytes:
                    stop_detail = "the file ends without the MCAP footer (the recording was not finished)"
                else:
                    stop_detail = (
                        f"unreadable or truncated record starting at byte {record_start} "
                        f"({type(exc).__name__}{': ' + str(exc) if str(exc) else ''})"
                    )
                break
            good_end = self._file.tell()
            inner: list[object]
            if isinstance(record, Chunk):
                try:
                    inner = list(breakup_chunk(record, validate_crc=True))
                except Exception as exc:
                    skipped.append(f"chunk at byte {record_start} ({type(exc).__name__}: {exc})")
                    continue
            else:
                inner = [record]
            for item in inner:
                if isinstance(item, Schema):
                    schemas[item.id] = item
                elif isinstance(item, Channel):
                    raw_channels[item.id] = item
                    infos[item.id] = _channel_info(item, schemas, self.prefix)
                elif isinstance(item, Message):
                    info = infos.get(item.channel_id)
                    if info is None:
                        orphans += 1
                        continue
                    messages.append(
                        RecordedMessage(
                            key=info.topic,
                            kind=info.kind,
                            payload=item.data,
                            log_time_ns=item.log_time,
                            publish_time_ns=item.publish_time,
                            sequence=item.sequence,
                        )
                    )
                elif isinstance(item, Footer):
                    finished = True
            if finished:
                break
        if orphans:
            skipped.append(f"{orphans} messages of channels whose definition was lost")
        if not finished or skipped:
            self.damage = Damage(
                offset=good_end if not finished else self.file_bytes,
                file_bytes=self.file_bytes,
                detail=stop_detail if not finished else "damaged records inside the file",
                skipped=skipped,
            )
        messages.sort(key=lambda m: m.log_time_ns)  # stable: file order breaks ties
        # Duplicate topics across channel ids (a writer may re-register): keep the first id per topic.
        unique: dict[int, ChannelInfo] = {}
        seen: set[str] = set()
        for cid, info in infos.items():
            if info.topic not in seen:
                seen.add(info.topic)
                unique[cid] = info
        self._linear = (unique, messages)
        return self._linear

    # -- messages -------------------------------------------------------------------------

    def _damaged_chunk(self, last_time: int | None) -> int:
        """Where an indexed read failed after ``last_time``: the start of the chunk it was
        reading (the reader's own position is wherever its seeks left it, often the end)."""
        found = _first_chunk_after(self._summary, last_time) if self._summary is not None else None
        return found if found is not None else self._file.tell()

    def messages(
        self, channels: list[ChannelInfo], start_ns: int | None = None, end_ns: int | None = None
    ) -> Iterator[RecordedMessage]:
        """Messages of ``channels`` with ``start_ns <= log_time < end_ns``, in log-time order."""
        topics = {c.topic for c in channels}
        if self._summary is None:
            _, messages = self._scan()
            for m in messages:
                if m.key not in topics:
                    continue
                if start_ns is not None and m.log_time_ns < start_ns:
                    continue
                if end_ns is not None and m.log_time_ns >= end_ns:
                    break
                yield m
            return
        kinds = {c.topic: c.kind for c in channels}
        self._file.seek(0, io.SEEK_SET)
        reader = SeekingReader(self._file, validate_crcs=True, record_size_limit=max(self.file_bytes, 1))
        iterator = reader.iter_messages(
            topics=sorted(topics), log_time_order=True, starting_at=start_ns, ending_before=end_ns
        )
        last_time: int | None = None
        while True:
            try:
                _schema, channel, message = next(iterator)
            except StopIteration:
                return
            except Exception as exc:  # a damaged chunk: stop here and say where
                after = f" after log time {last_time} ns" if last_time is not None else ""
                self.damage = Damage(
                    offset=self._damaged_chunk(last_time),
                    file_bytes=self.file_bytes,
                    detail=f"unreadable chunk{after} ({type(exc).__name__}: {exc})",
                )
                return
            last_time = message.log_time
            yield RecordedMessage(
                key=channel.topic,
                kind=kinds.get(channel.topic, "other"),
                payload=message.data,
                log_time_ns=message.log_time,
                publish_time_ns=message.publish_time,
                sequence=message.sequence,
            )


def _first_chunk_after(summary: Summary, last_time: int | None) -> int | None:
    """The start of the first chunk (by its messages' times) holding a message after
    ``last_time`` (None: the first chunk): where an indexed read that stopped there failed."""
    chunks = sorted(summary.chunk_indexes, key=lambda c: (c.message_start_time, c.chunk_start_offset))
    later = [c for c in chunks if last_time is None or c.message_end_time > last_time]
    return later[0].chunk_start_offset if later else None


def select_channels(
    survey: Survey, prefix: str, key_filter: KeyFilter, include_outputs: bool
) -> list[ChannelInfo]:
    """The channels to replay; raises :class:`NoUsableChannelError` (saying why) when none is.

    By default only the service's inputs (sites, plots, AIS reports under ``prefix``) are
    replayed: its own outputs would be recomputed by the service under test.
    """
    chosen: list[ChannelInfo] = []
    seen: set[str] = set()
    for info in survey.channels.values():
        if not info.usable or info.topic in seen or not key_filter.matches(info.topic):
            continue
        if not include_outputs and info.kind not in INPUT_KINDS:
            continue
        seen.add(info.topic)
        chosen.append(info)
    if chosen:
        return chosen
    if not survey.channels:
        raise NoUsableChannelError("the recording holds no channels")
    lines = []
    for info in list(survey.channels.values())[:20]:
        why = info.problem or (
            "excluded by --key"
            if not key_filter.matches(info.topic)
            else f"not a service input under prefix {prefix!r} (kind {info.kind}; --all-keys replays it)"
        )
        lines.append(f"  {info.topic!r}: {why}")
    raise NoUsableChannelError(
        f"no usable channel to replay (prefix {prefix!r}, key filter {key_filter.expr or 'none'}):\n"
        + "\n".join(lines)
    )
