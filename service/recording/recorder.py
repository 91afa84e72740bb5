"""Recording Zenoh samples: subscriber callback -> bounded queue -> writer thread -> MCAP.

The Zenoh callback only stamps the receipt time and appends to a
:class:`~service.transport.ingest_queue.BoundedQueue` (no blocking, no Zenoh calls:
zenoh-python ``docs/concepts.rst``).  The queue is bounded in samples and bytes; when it is
full the sample is *dropped and counted per key*, never silently: the
:class:`RecordReport` carries the counts, and the command prints them and exits non-zero.
"""

from __future__ import annotations

import contextlib
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from service.recording.keys import key_lines
from service.recording.writer import RecordingWriter
from service.transport.ingest_queue import BoundedQueue

#: Queue bounds: enough for tens of seconds of a large site's traffic while the disk stalls.
DEFAULT_QUEUE_SAMPLES = 100_000
DEFAULT_QUEUE_BYTES = 512 * 1024 * 1024
#: The writer pushes its data to the OS at least this often (bounds the loss on a crash).
FLUSH_INTERVAL_S = 1.0


@dataclass(frozen=True)
class ReceivedSample:
    key: str
    payload: bytes
    log_time_ns: int
    publish_time_ns: int | None


@dataclass
class RecordReport:
    """What a recording wrote; ``dropped`` non-empty means the file is incomplete."""

    path: str
    key_expr: str
    messages_by_key: dict[str, int] = field(default_factory=dict)
    bytes_by_key: dict[str, int] = field(default_factory=dict)
    dropped_by_key: dict[str, int] = field(default_factory=dict)
    file_bytes: int = 0
    duration_s: float = 0.0
    queue_high_water: int = 0
    error: str | None = None

    @property
    def messages(self) -> int:
        return sum(self.messages_by_key.values())

    @property
    def payload_bytes(self) -> int:
        return sum(self.bytes_by_key.values())

    @property
    def dropped(self) -> int:
        return sum(self.dropped_by_key.values())

    def lines(self) -> list[str]:
        """A human-readable report, one line each."""
        out = [
            f"recorded {self.messages} messages ({self.payload_bytes} payload bytes) on "
            f"{len(self.messages_by_key)} keys in {self.duration_s:.1f} s to {self.path} "
            f"({self.file_bytes} bytes on disk), subscribed to {self.key_expr}"
        ]
        out += key_lines(self.messages_by_key, self.bytes_by_key)
        if self.dropped:
            out.append(
                f"WARNING: {self.dropped} samples DROPPED (queue full; the recording is incomplete): "
                + ", ".join(f"{k}={n}" for k, n in sorted(self.dropped_by_key.items()))
            )
        if self.error:
            out.append(f"ERROR: {self.error}")
        return out


def ntp64_to_unix_ns(timestamp: Any) -> int | None:
    """Nanoseconds since the Unix epoch of a Zenoh ``Timestamp`` (None when absent).

    Zenoh's NTP64 (uhlc) counts seconds since the *Unix* epoch in its upper 32 bits, not since
    1900 as RFC 5905 does; ``as_nanos`` converts the 32-bit fraction exactly.
    """
    if timestamp is None:
        return None
    try:
        return int(timestamp.get_time_as_ntp64().as_nanos())
    except Exception:  # a timestamp we cannot read is a missing timestamp, not a lost sample
        return None


class Recorder:
    """Subscribes ``key_expr`` on ``session`` and writes what arrives until :meth:`stop`."""

    def __init__(
        self,
        session: Any,
        output: str | Path,
        key_expr: str,
        prefix: str = "fusion",
        *,
        max_queue_samples: int = DEFAULT_QUEUE_SAMPLES,
        max_queue_bytes: int = DEFAULT_QUEUE_BYTES,
        clock_ns: Callable[[], int] = time.time_ns,
    ) -> None:
        self.path = str(output)
        self.key_expr = key_expr
        self._session = session
        self._clock_ns = clock_ns
        self.queue = BoundedQueue(max_queue_samples, max_queue_bytes)
        self._writer = RecordingWriter(output, prefix, metadata={"key_expr": key_expr})
        self._thread = threading.Thread(target=self._write_loop, name="mcap-writer", daemon=True)
        self._subscriber: Any = None
        self._started = 0.0
        self.error: str | None = None
        self.failed = threading.Event()

    def _on_sample(self, sample: Any) -> None:
        # Runs on a Zenoh thread: stamp, copy the bytes out, enqueue. Nothing else.
        received = self._clock_ns()
        key = str(sample.key_expr)
        payload = sample.payload.to_bytes()
        item = ReceivedSample(key, payload, received, ntp64_to_unix_ns(sample.timestamp))
        self.queue.put(item, len(payload), key)

    def start(self) -> Recorder:
        self._started = time.monotonic()
        self._thread.start()
        self._subscriber = self._session.declare_subscriber(self.key_expr, self._on_sample)
        return self

    def _write_loop(self) -> None:
        last_flush = time.monotonic()
        dirty = False
        try:
            while not self.queue.closed_and_empty:
                for item in self.queue.take_all(timeout_s=0.2):
                    self._writer.write(item.key, item.payload, item.log_time_ns, item.publish_time_ns)
                    dirty = True
                now = time.monotonic()
                if dirty and now - last_flush >= FLUSH_INTERVAL_S:
                    self._writer.flush()
                    last_flush, dirty = now, False
        except Exception as exc:  # disk full, permissions...: stop recording, say why
            self.error = f"writing {self.path} failed: {type(exc).__name__}: {exc}"
            self.failed.set()
            self.queue.close()

    def stop(self) -> RecordReport:
        """Unsubscribe, write what is queued, finish the file; returns the report."""
        if self._subscriber is not None:
            with contextlib.suppress(Exception):  # the session may already be closed
                self._subscriber.undeclare()
            self._subscriber = None
        self.queue.close()
        if self._thread.is_alive():
            self._thread.join()
        try:
            self._writer.close()
        except Exception as exc:
            self.error = self.error or f"finishing {self.path} failed: {type(exc).__name__}: {exc}"
        totals = self._writer.totals.by_key
        try:
            file_bytes = Path(self.path).stat().st_size
        except OSError:
            file_bytes = 0
        return RecordReport(
            path=self.path,
            key_expr=self.key_expr,
            messages_by_key={k: c.messages for k, c in totals.items()},
            bytes_by_key={k: c.bytes for k, c in totals.items()},
            dropped_by_key=self.queue.dropped_counts(),
            file_bytes=file_bytes,
            duration_s=time.monotonic() - self._started if self._started else 0.0,
            queue_high_water=self.queue.high_water,
            error=self.error,
        )


def record(
    session: Any,
    output: str | Path,
    key_expr: str,
    prefix: str = "fusion",
    *,
    duration_s: float | None = None,
    stop: threading.Event | None = None,
    max_queue_samples: int = DEFAULT_QUEUE_SAMPLES,
    max_queue_bytes: int = DEFAULT_QUEUE_BYTES,
) -> RecordReport:
    """Record until ``stop`` is set or ``duration_s`` has passed (whichever first)."""
    stop = stop or threading.Event()
    recorder = Recorder(
        session,
        output,
        key_expr,
        prefix,
        max_queue_samples=max_queue_samples,
        max_queue_bytes=max_queue_bytes,
    )
    deadline = None if duration_s is None else time.monotonic() + duration_s
    try:
        recorder.start()
        while not stop.is_set() and not recorder.failed.is_set():
            remaining = None if deadline is None else deadline - time.monotonic()
            if remaining is not None and remaining <= 0:
                break
            stop.wait(0.2 if remaining is None else min(0.2, remaining))
    finally:
        report = recorder.stop()
    return report
