"""Replaying a recording: selection, original timing scaled by ``speed``, progress.

:func:`iter_replay` is the one place that decides *what* is replayed and *in which order*
(log-time order, stable); both the Zenoh replay and the offline replay consume it, so they
feed the service exactly the same sequence.
"""

from __future__ import annotations

import sys
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TextIO

from service.recording.keys import KeyFilter, key_lines
from service.recording.reader import RecordedMessage, RecordingReader, check_recording, select_channels

#: Progress is shown on replays expected to take longer than this (seconds of wall time) or
#: holding more messages than ``PROGRESS_MIN_MESSAGES``.
PROGRESS_MIN_WALL_S = 5.0
PROGRESS_MIN_MESSAGES = 5_000
#: Refresh period of the progress line: a terminal is redrawn in place, a log gets a line.
PROGRESS_TTY_PERIOD_S = 0.25
PROGRESS_LOG_PERIOD_S = 10.0


@dataclass(frozen=True)
class ReplayOptions:
    speed: float = 1.0  # 0: as fast as the receiver takes it
    key_expr: str | None = None
    start_s: float | None = None  # seconds after the recording's first message
    end_s: float | None = None
    include_outputs: bool = False  # replay the service's own outputs too (--all-keys)
    loop: bool = False

    def __post_init__(self) -> None:
        if not self.speed >= 0:
            raise ValueError(f"--speed must be >= 0, got {self.speed}")
        if self.start_s is not None and self.start_s < 0:
            raise ValueError(f"--start must be >= 0, got {self.start_s}")
        if self.start_s is not None and self.end_s is not None and self.end_s < self.start_s:
            raise ValueError(f"--end ({self.end_s}) is before --start ({self.start_s})")


@dataclass
class ReplayReport:
    path: str
    messages_by_key: dict[str, int] = field(default_factory=dict)
    bytes_by_key: dict[str, int] = field(default_factory=dict)
    passes: int = 0
    wall_s: float = 0.0
    span_s: float = 0.0  # log-time span replayed
    damage: str | None = None
    interrupted: bool = False

    @property
    def messages(self) -> int:
        return sum(self.messages_by_key.values())

    def count(self, message: RecordedMessage) -> None:
        self.messages_by_key[message.key] = self.messages_by_key.get(message.key, 0) + 1
        self.bytes_by_key[message.key] = self.bytes_by_key.get(message.key, 0) + len(message.payload)

    def lines(self) -> list[str]:
        rate = self.messages / self.wall_s if self.wall_s > 0 else 0.0
        out = [
            f"replayed {self.messages} messages on {len(self.messages_by_key)} keys from {self.path} "
            f"({self.span_s:.1f} s of recording in {self.wall_s:.1f} s, {rate:.0f} msg/s"
            f"{f', {self.passes} passes' if self.passes > 1 else ''})"
        ]
        out += key_lines(self.messages_by_key, self.bytes_by_key)
        if self.interrupted:
            out.append("interrupted before the end of the recording")
        if self.damage:
            out.append(f"WARNING: {self.damage}; replayed what it holds up to there")
        return out


class Progress:
    """A progress line on stderr: redrawn in place on a terminal, periodic lines otherwise."""

    def __init__(self, total: int | None, span_s: float, enabled: bool, stream: TextIO | None = None) -> None:
        self.stream = stream if stream is not None else sys.stderr
        self.total = total
        self.span_s = span_s
        self.enabled = enabled
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self.period = PROGRESS_TTY_PERIOD_S if self.tty else PROGRESS_LOG_PERIOD_S
        self._last = 0.0
        self._started = time.monotonic()
        self._drawn = False

    def update(self, done: int, position_s: float, force: bool = False) -> None:
        if not self.enabled:
            return
        now = time.monotonic()
        if not force and now - self._last < self.period:
            return
        self._last = now
        if self.total:
            frac = min(done / self.total, 1.0)
            bar = "#" * int(frac * 30)
            head = f"[{bar:<30}] {100 * frac:5.1f}% {done}/{self.total} msgs"
        else:
            head = f"{done} msgs"
        line = f"replay {head}  t+{position_s:.1f}/{self.span_s:.1f} s  ({now - self._started:.0f} s elapsed)"
        if self.tty:
            self.stream.write("\r" + line)
            self._drawn = True
        else:
            self.stream.write(line + "\n")
        self.stream.flush()

    def close(self) -> None:
        if self.enabled and self.tty and self._drawn:
            self.stream.write("\n")
            self.stream.flush()


@dataclass
class ReplayPlan:
    """What one pass replays: the opened reader and the chosen window."""

    reader: RecordingReader
    channels: list[Any]
    start_ns: int | None
    end_ns: int | None
    origin_ns: int  # the recording's first log time
    total: int | None  # messages this pass will replay, when known
    span_s: float


def plan_replay(reader: RecordingReader, prefix: str, options: ReplayOptions) -> ReplayPlan:
    survey = reader.survey()
    channels = select_channels(survey, prefix, KeyFilter(options.key_expr), options.include_outputs)
    origin = survey.start_ns or 0
    start_ns = origin + round(options.start_s * 1e9) if options.start_s is not None else None
    end_ns = origin + round(options.end_s * 1e9) if options.end_s is not None else None
    total = None
    if survey.message_counts is not None and start_ns is None and end_ns is None:
        total = sum(survey.message_counts.get(c.id, 0) for c in channels)
    first = start_ns if start_ns is not None else origin
    last = end_ns if end_ns is not None else (survey.end_ns or origin)
    span_s = max(0.0, (min(last, survey.end_ns or last) - first) / 1e9)
    return ReplayPlan(reader, channels, start_ns, end_ns, origin, total, span_s)


def preflight(path: str | Path, prefix: str, options: ReplayOptions) -> None:
    """What can be known of ``path`` before anything is connected: it is a readable MCAP file
    and, when it is indexed (its survey is cheap), it holds something to replay; raises
    :class:`~service.recording.reader.RecordingError` saying why not.  An unindexed file
    (an unfinished recording) is scanned once, by the replay itself."""
    check_recording(path)
    with RecordingReader(path, prefix) as reader:
        if reader.indexed:
            plan_replay(reader, prefix, options)


def iter_replay(plan: ReplayPlan) -> Iterator[RecordedMessage]:
    """The messages one pass replays, in log-time order."""
    return plan.reader.messages(plan.channels, plan.start_ns, plan.end_ns)


def paced(
    messages: Iterator[RecordedMessage],
    speed: float,
    stop: threading.Event,
    clock: Callable[[], float] = time.monotonic,
) -> Iterator[RecordedMessage]:
    """``messages`` released at their recorded log-time offsets divided by ``speed``.

    The schedule is anchored on the first message, so a slow receiver delays the messages
    behind it without the later ones drifting (they catch up when it recovers); ``speed == 0``
    releases them as fast as the consumer takes them.
    """
    anchor_wall: float | None = None
    anchor_log = 0
    for message in messages:
        if stop.is_set():
            return
        if speed > 0:
            if anchor_wall is None:
                anchor_wall, anchor_log = clock(), message.log_time_ns
            due = anchor_wall + (message.log_time_ns - anchor_log) / 1e9 / speed
            delay = due - clock()
            if delay > 0 and stop.wait(delay):
                return
        yield message


def replay(
    path: str | Path,
    publish: Callable[[RecordedMessage], None],
    prefix: str,
    options: ReplayOptions,
    stop: threading.Event | None = None,
    progress: bool | None = None,
    progress_stream: TextIO | None = None,
) -> ReplayReport:
    """Replay ``path`` through ``publish`` (one call per message, blocking = backpressure).

    Raises :class:`~service.recording.reader.RecordingError` when the file cannot be replayed
    at all; a damaged file replays what it holds and the report says where it stopped.
    """
    stop = stop or threading.Event()
    report = ReplayReport(path=str(path))
    started = time.monotonic()
    while not stop.is_set():
        with RecordingReader(path, prefix) as reader:
            plan = plan_replay(reader, prefix, options)
            report.span_s += plan.span_s
            show = progress
            if show is None:
                wall = plan.span_s / options.speed if options.speed > 0 else 0.0
                show = wall >= PROGRESS_MIN_WALL_S or (plan.total or 0) >= PROGRESS_MIN_MESSAGES
            bar = Progress(plan.total, plan.span_s, bool(show), progress_stream)
            done = 0
            first_ns: int | None = None
            for message in paced(iter_replay(plan), options.speed, stop):
                publish(message)
                report.count(message)
                done += 1
                if first_ns is None:
                    first_ns = message.log_time_ns
                bar.update(done, (message.log_time_ns - first_ns) / 1e9)
            bar.update(done, plan.span_s, force=True)
            bar.close()
            report.passes += 1
            if reader.damage is not None:
                report.damage = reader.damage.describe()
        if not options.loop or report.messages == 0:
            break
    report.interrupted = stop.is_set()
    report.wall_s = time.monotonic() - started
    return report
